"""The repair cache (repair.cache) and the audit's shared measurements: a sweep repairs each scan once, a cached
repair gives the same transform bit for bit, entries are written atomically; the NumPy non-manifold vertex
count agrees with MeshLab's."""

import json

import numpy as np
import pytest

from conftest import build, run_cli, shared
from scanreg.types import RunContext as Context
from scanreg.geometry import Mesh, submesh
from scanreg.io import read_mesh
from scanreg.stages.registry import REPAIR, load_all

COW = "pkg:pymeshlab/tests/sample_meshes/cow.obj"  # closed, 5804 faces


def holed_cow() -> Mesh:
    m = read_mesh(COW)
    keep = np.ones(len(m.faces), bool)
    keep[[10, 11, 12, 2000, 4000]] = False  # three holes to fill
    return submesh(m, keep)


def write_off(path, mesh: Mesh) -> None:
    lines = ["OFF", f"{len(mesh.vertices)} {len(mesh.faces)} 0"]
    lines += [" ".join(repr(float(x)) for x in v) for v in mesh.vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def _pair(res):
    """A :class:`~scanreg.types.Repaired` as (mesh, metrics); the metrics are unprefixed."""
    return res.mesh, res.metrics


def test_cache_round_trip_key_and_atomic_write(tmp_path, capsys):
    from scanreg.stages.repair.cache import RepairCache, cache_key, cached_repair

    load_all()
    st = build(REPAIR, "meshfix")
    mesh, ctx, cache = holed_cow(), Context(seed=0, run_dir=None), RepairCache(tmp_path / "c")
    out1, m1 = _pair(cached_repair(st, mesh, ctx, cache))
    out2, m2 = _pair(cached_repair(st, holed_cow(), ctx, cache))  # a new object with the same content
    assert (m1["cache_hit"], m2["cache_hit"]) == (0.0, 1.0)
    assert np.array_equal(out1.vertices, out2.vertices) and np.array_equal(out1.faces, out2.faces)
    assert out2.vertices.dtype == np.float64 and out2.faces.dtype == np.int64
    assert {k: v for k, v in m1.items() if k != "cache_hit"} == \
           {k: v for k, v in m2.items() if k != "cache_hit"}
    assert m1["before_boundary_loops"] == 3 and m1["after_boundary_loops"] == 0
    assert len(list(cache.dir.glob("*.npz"))) == 1 and not list(cache.dir.glob(".*"))  # no temporary left
    # the key follows the content, the parameters and the seed, not the cache's own settings
    k = cache_key(st, mesh, 0)
    assert cache_key(build(REPAIR, "meshfix", cache="on", cache_dir="x"), mesh, 0) == k
    assert cache_key(build(REPAIR, "meshfix", refine=False), mesh, 0) != k
    assert cache_key(st, mesh, 1) != k
    moved = Mesh(mesh.vertices + 1e-9, mesh.faces)
    assert cache_key(st, moved, 0) != k
    # an unreadable entry is a miss, and is replaced
    cache.path(k).write_bytes(b"not an npz")
    m3 = cached_repair(st, mesh, ctx, cache).metrics
    assert m3["cache_hit"] == 0.0 and cache.load(k, "") is not None


def test_a_job_waits_for_the_entry_another_job_is_making(tmp_path):
    import threading

    from scanreg.stages.repair.cache import RepairCache, cache_key, cached_repair

    load_all()
    st = build(REPAIR, "meshfix")
    mesh, ctx = holed_cow(), Context(seed=0, run_dir=None)
    made = RepairCache(tmp_path / "made")
    out = cached_repair(st, mesh, ctx, made).mesh
    key = cache_key(st, mesh, 0)
    cache = RepairCache(tmp_path / "c")
    lock = cache.lock(key)  # "another job" holds the lock and stores its entry a little later
    assert lock is not None and cache.lock(key) is None

    def other_job():
        cache.store(key, *made.load(key, ""))
        lock.unlink()

    timer = threading.Timer(0.5, other_job)
    timer.start()
    got, m = _pair(cached_repair(st, mesh, ctx, cache))
    timer.join()
    assert m["cache_hit"] == 1.0 and np.array_equal(got.faces, out.faces)
    assert not list(cache.dir.glob(".*"))  # no lock or temporary left


def test_cache_modes(tmp_path):
    """``auto`` caches in sweeps only (RunContext.in_sweep), ``on`` always, ``off`` never; the stage's own
    repair decides by its context's ``in_sweep``: a hit logs ``cache_hit`` 1, no cache no ``cache_hit``."""
    from scanreg.errors import ConfigError
    from scanreg.stages.repair.cache import cache_enabled

    assert cache_enabled("auto", True) and not cache_enabled("auto", False)
    assert cache_enabled("on", False) and not cache_enabled("off", True)
    with pytest.raises(ConfigError, match="cache must be auto, on or off"):
        build(REPAIR, "meshfix", cache="sometimes")
    load_all()
    mesh, where = holed_cow(), tmp_path / "c"
    auto = build(REPAIR, "meshfix", cache="auto", cache_dir=str(where))
    single = auto.repair(mesh, Context(seed=0, run_dir=None))
    assert "cache_hit" not in single.metrics and not where.exists()  # not a sweep: no cache
    first = auto.repair(mesh, Context(seed=0, run_dir=None, in_sweep=True))
    second = auto.repair(holed_cow(), Context(seed=0, run_dir=None, in_sweep=True))
    assert (first.metrics["cache_hit"], second.metrics["cache_hit"]) == (0.0, 1.0)
    assert len(list(where.glob("*.npz"))) == 1
    assert np.array_equal(second.mesh.faces, single.mesh.faces)
    assert np.array_equal(second.mesh.vertices, single.mesh.vertices)
    off = build(REPAIR, "meshfix", cache="off", cache_dir=str(where))
    assert "cache_hit" not in off.repair(mesh, Context(seed=0, run_dir=None, in_sweep=True)).metrics
    on = build(REPAIR, "meshfix", cache="on", cache_dir=str(where))
    assert on.repair(mesh, Context(seed=0, run_dir=None)).metrics["cache_hit"] == 1.0


def test_non_manifold_vertices_agree_with_meshlab():
    from scanreg.mesh.topology import _meshset, non_manifold_vertices

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0.0], [0, 0, 1.0]])
    bowtie = Mesh(v, np.array([[0, 1, 2], [0, 3, 4]]))
    fan = Mesh(v, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]]))  # one fan: manifold
    fin = Mesh(v, np.array([[0, 1, 2], [0, 1, 4], [0, 1, 5]]))  # a non-manifold edge: its vertices not counted
    assert [non_manifold_vertices(m) for m in (bowtie, fan, fin)] == [1, 0, 0]
    m = holed_cow()
    two = Mesh(np.vstack([m.vertices, m.vertices + 5.0]), np.vstack([m.faces, m.faces + len(m.vertices)]))
    weld = Mesh(two.vertices, np.where(two.faces == len(m.vertices) + 7, 7, two.faces))  # two cows touch at one vertex
    for mesh in (m, two, weld):
        assert non_manifold_vertices(mesh) == _meshset(mesh).get_topological_measures()["non_two_manifold_vertices"]
    assert non_manifold_vertices(weld) > non_manifold_vertices(two)


def _fan_groups_by_graph(mesh: Mesh) -> int:
    """non_manifold_vertices' count with the fans found as the corner graph's connected components (its way
    for inconsistently oriented faces), for any mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    import scanreg.mesh.topology as topo

    def by_graph(nf, vert, c1s, c1e, c2s, c2e):
        a, b = np.concatenate([c1s, c1e]), np.concatenate([c2e, c2s])
        g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(3 * nf, 3 * nf)).tocsr()
        return connected_components(g, directed=True, connection="weak")[1]
    fast, topo._fans_turning = topo._fans_turning, by_graph
    try:
        return topo.non_manifold_vertices(Mesh(mesh.vertices, mesh.faces))
    finally:
        topo._fans_turning = fast


def test_fans_by_pointer_doubling_are_the_graph_components():
    """non_manifold_vertices finds the fans of consistently oriented faces by pointer doubling: the same count
    as the corner graph's components on a holed cow with vertices welded into pinches, a cone whose apex has
    200 corners (8 doubling rounds), open fans at a border, and a pinch of two cones; a flipped face takes the
    graph's way, and MeshLab agrees."""
    from scanreg.mesh.topology import _meshset, non_manifold_vertices

    rng = np.random.default_rng(5)
    m = holed_cow()
    n = 200
    ring = np.stack([np.cos(np.linspace(0, 2 * np.pi, n, endpoint=False)),
                     np.sin(np.linspace(0, 2 * np.pi, n, endpoint=False)), np.zeros(n)], axis=1)
    k = np.arange(n)
    cone = Mesh(np.vstack([[0, 0, 1.0], ring]), np.stack([np.zeros(n, int), 1 + k, 1 + (k + 1) % n], axis=1))
    open_cone = Mesh(cone.vertices, cone.faces[: n // 2])
    twin = Mesh(np.vstack([cone.vertices, cone.vertices * [1, 1, -1] + [0, 0, 2]]),
                np.vstack([cone.faces, cone.faces[:, ::-1] + n + 1]))
    pinch = Mesh(twin.vertices, np.where(twin.faces == n + 1, 0, twin.faces))  # the apexes welded: two fans
    meshes = [m, cone, open_cone, pinch]
    for _ in range(3):
        f = m.faces.copy()
        for a, b in rng.integers(0, len(m.vertices), (4, 2)):
            f[f == b] = a
        meshes.append(Mesh(m.vertices, f))
    flipped = m.faces.copy()
    flipped[10] = flipped[10, ::-1]
    meshes.append(Mesh(m.vertices, flipped))
    counts = [non_manifold_vertices(x) for x in meshes]
    assert counts == [_fan_groups_by_graph(x) for x in meshes]
    assert counts[1:4] == [0, 0, 1] and max(counts[4:7]) > 0
    for x in meshes[3:]:
        assert non_manifold_vertices(x) == _meshset(x).get_topological_measures()["non_two_manifold_vertices"]


def test_edge_table_equals_unique_in_both_sorts():
    """The one edge table (rows sorted by edge as packed integers, or by an argsort when vertex indices are too
    large to pack) gives np.unique's edge ids and counts, and its order sorts the keys."""
    from scanreg.mesh.topology import _edge_table_sorted

    rng = np.random.default_rng(3)
    m = holed_cow()
    # the last: indices near 2^28, whose keys (under 2^57) leave too few bits for the rows: the argsort
    for f in (m.faces, np.vstack([m.faces, m.faces[rng.permutation(len(m.faces))[:50]]]), m.faces[:500] * 89_000):
        directed, edge, counts, order = _edge_table_sorted(f)
        keys = np.minimum(directed[:, 0], directed[:, 1]).astype(np.int64) * (int(f.max()) + 1) \
            + np.maximum(directed[:, 0], directed[:, 1])
        _, inv, cnt = np.unique(keys, return_inverse=True, return_counts=True)
        assert np.array_equal(edge, inv.ravel()) and np.array_equal(counts, cnt)
        assert np.array_equal(keys[order], np.sort(keys))


def test_non_manifold_vertices_on_raw_scans():
    from scanreg.mesh.topology import _meshset, non_manifold_vertices

    for rel in ("meshlab_defects/many_small_holes.ply", "stanford_bunny/bun045.ply"):
        mesh = read_mesh(str(shared(rel)))
        assert non_manifold_vertices(mesh) == _meshset(mesh).get_topological_measures()["non_two_manifold_vertices"] > 0


@pytest.mark.slow
def test_sweep_repairs_each_scan_once_and_cached_runs_match_uncached(tmp_path):
    target = holed_cow()
    a = np.radians(8.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    write_off(tmp_path / "target.off", target)
    write_off(tmp_path / "source.off", Mesh(target.vertices @ R.T + [0.02, -0.01, 0.0], target.faces))
    common = ["data=files", "data.source=source.off", "data.target=target.off", "tracking=none",
              "sampler.n_points=3000", "evaluate.view_html=false", "evaluate.pose_uncertainty=false",
              f"repair.cache_dir={tmp_path / 'cache'}"]
    iters = list(range(10, 18))
    r = run_cli(["-m", *common, "launch=serial", f"icp.max_iterations={','.join(map(str, iters))}",
                 f"hydra.sweep.dir={tmp_path / 'sweep'}"], tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    res = [json.loads((tmp_path / "sweep" / str(j) / "result.json").read_text()) for j in range(len(iters))]
    for role in ("repair_", "target_repair_"):  # each scan repaired once in 8 jobs, then taken from the cache
        assert [x[f"{role}cache_hit"] for x in res] == [0.0] + [1.0] * (len(iters) - 1)
        assert len({x[f"{role}after_faces"] for x in res}) == 1
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2 and not list((tmp_path / "cache").glob(".*"))
    # a single run without the cache (cache=auto is off outside sweeps) gives the cached job's transform bit for bit
    j = 5
    r = run_cli([*common, f"icp.max_iterations={iters[j]}", f"hydra.run.dir={tmp_path / 'single'}"], tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    single = json.loads((tmp_path / "single" / "result.json").read_text())
    assert "repair_cache_hit" not in single and res[j]["repair_cache_hit"] == 1.0
    assert single["T_target_source"] == res[j]["T_target_source"]
