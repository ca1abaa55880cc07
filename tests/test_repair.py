"""Repair backends and the repair audit on real defect meshes (../shared/data and meshes packages ship)."""

from pathlib import Path

import numpy as np
import pytest

from conftest import children, oriented_triangles, settled, shared
from scanreg.types import RunContext as Context
from scanreg.errors import StageError
from scanreg.io import read_mesh
from scanreg.stages.registry import REPAIR, make_params
from scanreg.stages.repair import repair_with_audit
from scanreg.mesh.topology import audit_mesh, mesh_stats

CTX = Context(seed=0, run_dir=None)


def stage(name, **kw):
    cls = REPAIR.get(name)
    return cls(make_params(cls.Params, kw, f"repair={name}"))


def load(spec):
    m = read_mesh(spec if spec.startswith("pkg:") else shared(spec))
    m.source = spec
    return m


def assert_clean(after, watertight=True):
    assert after["after_components"] == 1
    assert after["after_non_manifold_edges"] == 0 and after["after_non_manifold_vertices"] == 0
    assert after["after_inconsistent_orientation_edges"] == 0, "not coherently oriented"
    assert after["after_self_intersecting_faces"] == 0
    assert after["after_degenerate_faces"] == 0
    if watertight:
        assert after["after_boundary_edges"] == 0 and after["after_watertight"] == 1
        assert after["after_volume"] > 0, "outward orientation gives a positive volume"


def audited(st, mesh):
    """The audited repair (:func:`repair_with_audit`): the mesh to go on with and the audit's metrics (unprefixed
    names)."""
    res = repair_with_audit(st, mesh, CTX)
    return res.mesh, res.metrics


@pytest.mark.parametrize("backend,mesh", [
    ("meshfix", "pkg:pymeshfix/examples/StanfordBunny.ply"),
    pytest.param("meshlab", "pkg:pymeshfix/examples/StanfordBunny.ply", marks=pytest.mark.slow),  # ~40 s
    ("meshfix", "meshlab_defects/screwdriver.ply"),
    ("meshlab", "meshlab_defects/screwdriver.ply"),
])
def test_closed_models_become_single_watertight_manifolds(backend, mesh):
    m = load(mesh)
    out, a = audited(stage(backend), m)
    assert_clean(a)
    assert a["guard_ok"] == 1 and a["removed_area_share"] < 0.1 and a["hausdorff_max_rel"] < 0.01
    if "StanfordBunny" in mesh:  # the defects were there, and are reported as gone
        assert a["before_boundary_loops"] == 70 and a["before_non_manifold_edges"] == 132
        assert a["before_self_intersecting_faces"] > 0


@pytest.mark.parametrize("backend", ["meshfix", "meshlab"])
@pytest.mark.parametrize("mesh", ["meshlab_defects/many_small_holes.ply", "meshlab_defects/non_manif_hole.ply"])
def test_guard_stops_repairs_that_destroy_open_scans(backend, mesh):
    """Filling every hole (open_border=cap; the default, auto, keeps these borders open) caps these open scans'
    borders; the caps cut through the scans and removing the intersections eats a third or more of the surface.
    The guard must fail such a run, with the audit, and say which parameter to change."""
    m = load(mesh)
    with pytest.raises(StageError, match=r"removed \d+\.\d% of the surface") as e:
        repair_with_audit(stage(backend, open_border="cap"), m, CTX)
    assert "\n" not in str(e.value) and "repair.open_border=open" in str(e.value)
    assert str(e.value).startswith(f"repair={backend}: {mesh}: ")
    other = {"meshfix": "meshlab", "meshlab": "meshfix"}[backend]
    assert f"try the other backend (repair={other})" in str(e.value)
    assert e.value.metrics["removed_area_share"] > 0.3 and e.value.metrics["guard_ok"] == 0
    assert e.value.metrics["open_border_open"] == 0
    # check_only audits the same repair but hands the unchanged mesh on
    out, metrics = audited(stage(backend, open_border="cap", check_only=True), m)
    assert out is m and metrics["guard_ok"] == 0


@pytest.mark.parametrize("backend,mesh,max_edges", [
    ("meshfix", "meshlab_defects/many_small_holes.ply", 100),
    ("meshlab", "meshlab_defects/many_small_holes.ply", 100),
    ("meshfix", "meshlab_defects/non_manif_hole.ply", 50),
    ("meshlab", "meshlab_defects/non_manif_hole.ply", 50),
    ("meshfix", "stanford_bunny/bun000.ply", 300),
])
def test_open_scans_with_the_border_kept_open(backend, mesh, max_edges):
    """Every hole but the scan's outer border closed; one manifold, oriented component, no self-intersection,
    little of the surface removed."""
    m = load(mesh)
    before = mesh_stats(m)
    _, a = audited(stage(backend, max_hole_edges=max_edges, max_hausdorff=1.0), m)
    assert_clean(a, watertight=False)
    assert before["boundary_loops"] > 1 and a["after_boundary_loops"] == 1
    assert a["removed_area_share"] < 0.1
    if "bun000" in mesh:
        assert a["hausdorff_max_rel"] < 0.01 and a["removed_area_share"] < 0.01


@pytest.mark.slow
def test_meshlab_on_a_stanford_scan_with_border_open():
    m = load("stanford_bunny/bun000.ply")
    _, a = audited(stage("meshlab", max_hole_edges=300, max_hausdorff=1.0), m)
    assert_clean(a, watertight=False)
    assert a["after_boundary_loops"] == 1 and a["removed_area_share"] < 0.01


def test_audit_counts_self_intersections_and_nonmanifold_vertices():
    from scanreg.geometry import Mesh

    # two triangles crossing each other
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, -1], [0.5, 0.5, 1], [1.5, 1.5, 0]], float)
    a = audit_mesh(Mesh(v, np.array([[0, 1, 2], [3, 4, 5]])))
    assert a["self_intersecting_faces"] == 2
    # two triangles sharing only a vertex: a non-manifold vertex
    v2 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    assert audit_mesh(Mesh(v2, np.array([[0, 1, 2], [0, 3, 4]])))["non_manifold_vertices"] == 1


# ---------------------------------------------------------------------------------------------- open scans as shells


def test_distances_to_are_exact_point_to_triangle_distances():
    """distances_to (libigl's AABB tree, the audit's distances between the input and the output): the
    known distances to a unit square of two triangles (above its face, beside an edge, beyond a corner), and
    Open3D's float32 distances on the bunny to within float32 rounding."""
    import open3d as o3d

    from scanreg.geometry import Mesh, bbox_diagonal
    from scanreg.mesh.distances import area_samples, distances_to

    square = Mesh(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    q = np.array([[0.3, 0.4, 0.5], [2, 0.5, 0], [2, 2, 0], [-1, -1, 1], [0.5, 0.5, 0]])
    assert np.allclose(distances_to(square)(q), [0.5, 1.0, np.sqrt(2), np.sqrt(3), 0.0], rtol=0, atol=1e-15)
    bunny = load("pkg:pymeshfix/examples/StanfordBunny.ply")
    pts = area_samples(bunny, 3000, 1) + np.random.default_rng(0).normal(0, 1e-3, (3000, 3))
    d = distances_to(bunny)(pts)
    scene = o3d.t.geometry.RaycastingScene()  # an independent implementation, in float32
    scene.add_triangles(o3d.core.Tensor(bunny.vertices.astype(np.float32)),
                        o3d.core.Tensor(bunny.faces.astype(np.uint32)))
    o3d_d = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert np.abs(d - o3d_d).max() < 1e-6 * bbox_diagonal(bunny.vertices)


def test_shared_faces_are_the_same_triangles_in_space():
    """shared_faces: a mesh and an edited copy (vertices renumbered, corners rotated, faces reordered, some faces
    moved, one face flipped, one face new): the faces left as they were are shared both ways (a flipped face is
    the same triangle), the moved and new ones are not."""
    from scanreg.geometry import Mesh
    from scanreg.mesh.distances import shared_faces

    rng = np.random.default_rng(0)
    a = load("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    v, f = a.vertices.copy(), a.faces.copy()
    moved_v = rng.choice(len(v), 20, replace=False)
    v[moved_v] += 1e-9  # their faces are not the same any more
    f[5] = f[5, ::-1]  # flipped: the same triangle
    f = np.vstack([f, [[0, 1, 2]]])  # new
    f = np.roll(f, 1, axis=1)  # corners rotated
    renum = rng.permutation(len(v))
    v, f = v[renum], np.argsort(renum)[f]
    perm = rng.permutation(len(f))
    b = Mesh(v, f[perm])
    in_a, in_b = shared_faces(a, b)
    moved = np.isin(a.faces, moved_v).any(axis=1)
    assert np.array_equal(in_a, ~moved)
    expect_b = np.append(~moved, False)[perm]  # (the new face [0, 1, 2] is no face of a)
    assert np.array_equal(in_b, expect_b) and in_b.sum() == in_a.sum()
    # hash collisions (every key one of 4 values) cost faces their sharing, never give a false one
    import scanreg.mesh.intersect as intersect

    keys = intersect.face_keys
    intersect.face_keys = lambda v, f: keys(v, f) % np.uint64(4)
    try:
        in_a, in_b = shared_faces(a, b)
    finally:
        intersect.face_keys = keys
    assert not (in_a & moved).any() and not (in_b & ~expect_b).any()


def test_distances_near_equal_the_whole_meshs():
    """distances_near measures on the faces near the points only, yet gives the whole mesh's distances bit for
    bit: points on and near the surface, and points far from it (farther than the reach: measured again)."""
    from scanreg.geometry import bbox_diagonal
    from scanreg.mesh.distances import area_samples, distances_near, exact_distances

    bunny = load("pkg:pymeshfix/examples/StanfordBunny.ply")
    rng = np.random.default_rng(2)
    diag = bbox_diagonal(bunny.vertices)
    pts = area_samples(bunny, 300, 3)
    pts = np.vstack([pts[:200] + rng.normal(0, 1e-3 * diag, (200, 3)),
                     pts[200:] + rng.normal(0, 0.1 * diag, (100, 3))])  # 100 far from the surface
    reach = 2e-3 * diag
    whole = exact_distances(bunny, pts)
    assert (whole > reach).sum() > 50
    assert np.array_equal(distances_near(bunny, pts, reach, exact_distances), whole)


def test_close_as_shell_on_an_open_surface():
    """A bumpy open sheet closed as a thin shell: watertight, outward oriented, no self-intersection, the
    scanned side unchanged and recovered by Mesh.scanned()."""
    from scanreg.geometry import Mesh
    from scanreg.mesh.shell import close_as_shell

    n = 20
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = 0.1 * np.sin(6 * x) * np.cos(5 * y)
    v = np.c_[x.ravel(), y.ravel(), z.ravel()]
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    sheet = Mesh(v, np.concatenate([np.c_[a, b, d], np.c_[a, d, c]]))
    shell = close_as_shell(sheet, 0.01)
    s = audit_mesh(shell)
    assert s["watertight"] == 1 and s["inconsistent_orientation_edges"] == 0 and s["self_intersecting_faces"] == 0
    assert s["non_manifold_vertices"] == 0 and s["components"] == 1
    assert s["volume"] == pytest.approx(mesh_stats(sheet)["area"] * 0.01, rel=0.05)  # area x thickness, outward
    back = shell.scanned()
    assert np.array_equal(back.faces, sheet.faces) and np.array_equal(back.vertices, sheet.vertices)
    assert shell.closure_faces == len(sheet.faces) + 2 * 4 * (n - 1)  # the back, two triangles per border edge


@pytest.mark.parametrize("backend,mesh", [
    ("meshfix", "meshlab_defects/many_small_holes.ply"),
    ("meshlab", "meshlab_defects/many_small_holes.ply"),
    ("meshfix", "meshlab_defects/non_manif_hole.ply"),
    ("meshlab", "meshlab_defects/non_manif_hole.ply"),
    ("meshfix", "stanford_bunny/bun000.ply"),  # (the shell is the backends' common code: one on a real scan)
])
def test_open_scans_become_watertight_shells(backend, mesh):
    """repair.open_border=shell: every hole but the outer border filled, then the scan closed as a thin shell.
    One watertight, edge- and vertex-manifold, oriented component with no self-intersecting face, with almost
    nothing removed; samplers see only the scanned side."""
    from scanreg.mesh.distances import surface_distances

    m = load(mesh)
    small = "meshlab_defects" in mesh
    out, a = audited(stage(backend, open_border="shell"), m)  # the default guard
    assert_clean(a)
    assert a["guard_ok"] == 1 and a["removed_area_share"] < (0.1 if small else 0.01)
    # the small meshes' median edge is 1.3 % (many_small_holes) and 3.8 % (non_manif_hole) of the diagonal: the
    # few border slivers the repair drops move the surface by about an edge, which the guard allows there
    assert a["hausdorff_max_rel"] < a["hausdorff_limit_rel"] and a["hausdorff_max_rel"] < (0.08 if small else 0.01)
    assert a["displacement_q_edges"] <= 2.0 and a["open_border_open"] == 1
    assert a["hausdorff_added_max_rel"] < 0.05  # the back lies just behind the surface
    assert out.closure_faces > 0
    scanned = out.scanned()
    assert len(scanned.faces) == len(out.faces) - out.closure_faces
    assert mesh_stats(scanned)["boundary_loops"] >= 1  # the scanned side alone is open again
    from scanreg.geometry import bbox_diagonal

    # the scanned side is (up to the float32 distance query) the repaired surface, which the input lies on
    assert surface_distances(scanned, out, 2000, 0).max() < 1e-5 * bbox_diagonal(m.vertices)


def test_open_border_open_keeps_only_the_outer_border():
    m = load("meshlab_defects/many_small_holes.ply")
    _, a = audited(stage("meshfix", open_border="open", max_hausdorff=0.05), m)
    assert_clean(a, watertight=False)
    assert a["before_boundary_loops"] == 32 and a["after_boundary_loops"] == 1


def _wavy_grid_with_hole(n: int = 40, hole: tuple[int, int] = (17, 23)):
    """A wavy n x n grid (an open surface, border of 4n edges) without the cells hole[0]..hole[1] in both
    directions (one interior hole of 4 (hole[1] - hole[0]) edges)."""
    from scanreg.geometry import Mesh

    x, y = np.meshgrid(np.arange(n + 1, dtype=float), np.arange(n + 1, dtype=float))
    v = np.stack([x.ravel(), y.ravel(), 0.3 * np.sin(x.ravel() / 3) * np.cos(y.ravel() / 4)], 1)
    f = []
    for i in range(n):
        for j in range(n):
            if not (hole[0] <= i < hole[1] and hole[0] <= j < hole[1]):
                a, b, c, d = i * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j + 1, (i + 1) * (n + 1) + j
                f += [(a, b, c), (a, c, d)]
    return Mesh(v, np.array(f))


def test_meshlab_closes_holes_on_their_neighbourhood_as_on_the_whole_mesh():
    """repair=meshlab closes holes on the submesh around them (MeshLab's refinement visits every face it is
    given): the patched mesh has the very faces MeshLab makes on the whole mesh, and the submesh's cut stays
    open (only the outer border of 160 edges is left)."""
    import pymeshlab

    from scanreg.geometry import Mesh
    from scanreg.mesh.topology import boundary_loop_sizes
    from scanreg.stages.registry import load_all
    from scanreg.stages.repair.meshlab import _FilterChain

    load_all()
    m = _wavy_grid_with_hole()
    assert sorted(boundary_loop_sizes(m)) == [24, 160]
    cls = REPAIR.get("meshlab")
    stage = cls(make_params(cls.Params, {"max_hole_edges": 100}, "meshlab"))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(m.vertices, m.faces.astype(np.int32)))
    _FilterChain(stage.p)._close(ms, prevent=True)  # the chain's hole closing with these parameters
    ref = pymeshlab.MeshSet()
    ref.add_mesh(pymeshlab.Mesh(m.vertices, m.faces.astype(np.int32)))
    ref.meshing_close_holes(maxholesize=100, selfintersection=True, refinehole=True)  # edge length 3 % of diag

    def faces(cm):  # each face as its sorted corners: the same faces whatever the order
        t = cm.vertex_matrix()[cm.face_matrix()]
        return sorted(tuple(sorted(map(tuple, np.round(x, 12)))) for x in t)

    local, whole = ms.current_mesh(), ref.current_mesh()
    assert local.face_number() > len(m.faces)  # patched
    assert faces(local) == faces(whole)
    assert list(boundary_loop_sizes(Mesh(local.vertex_matrix(), local.face_matrix()))) == [160]


@pytest.mark.parametrize("backend,mesh", [
    ("meshfix", "meshlab_defects/screwdriver.ply"),
    ("meshlab", "meshlab_defects/non_manif_hole.ply"),  # the output needs its own self-intersection test
])
def test_audit_is_the_same_with_and_without_forking(backend, mesh, monkeypatch):
    """The audited repair (the audit in this process, in sequence; MeshFix's sessions in forked children)
    gives the same mesh and the same metrics, bit for bit, whether the sessions run in children or here
    (SCANREG_NO_FORK); the audit's count of the output's self-intersecting faces (made incrementally from the
    input's test, or taken from the backend) is the full exact test's; and no child process is left behind,
    also when the backend fails."""
    from scanreg.mesh.intersect import self_intersecting_faces

    def run():
        out, metrics = audited(stage(backend), load(mesh))
        return out, {k: v for k, v in metrics.items() if not k.endswith("_time_s")}

    before = children()
    forked = run()
    monkeypatch.setenv("SCANREG_NO_FORK", "1")
    here = run()
    assert np.array_equal(forked[0].vertices, here[0].vertices)
    assert np.array_equal(forked[0].faces, here[0].faces)
    assert forked[1] == here[1]
    out, m = forked
    assert m["after_self_intersecting_faces"] == int(self_intersecting_faces(out.vertices, out.faces).sum())
    monkeypatch.delenv("SCANREG_NO_FORK")
    if not Path("/proc/self/stat").exists():
        pytest.skip("no /proc here: the child processes left behind are not counted")
    assert settled(before)  # no child process left behind, not even a zombie

    def breaks(mesh, p, ctx):
        raise RuntimeError("the backend broke")
    broken = stage(backend, scope="whole")  # the backend runs whatever the mesh (a clean one would pass untouched)
    broken.run = breaks
    with pytest.raises(StageError, match="the backend failed"):
        repair_with_audit(broken, load(mesh), CTX)
    assert settled(before)


def test_meshfix_renumbers_the_scattered_bunny_and_gets_the_same_triangles(monkeypatch):
    """pymeshfix's StanfordBunny.ply has its vertices scattered through the file: MeshFix gets it renumbered in
    Morton order (geometry.locality_ordered, 25 % faster) and returns the same oriented triangles as from the
    file's own order."""
    import scanreg.stages.repair.meshfix as mf
    from scanreg.geometry import locality_ordered

    mesh = load("pkg:pymeshfix/examples/StanfordBunny.ply")
    p = mf.MeshFix.Params()
    renumbered = []

    def spy(v, f):
        renumbered.append(locality_ordered(v, f))
        return renumbered[-1]

    monkeypatch.setattr(mf, "locality_ordered", spy)
    v1, f1, clean1 = mf._meshfix_session(mesh.vertices, mesh.faces, p, True)
    assert renumbered[0][1] is not mesh.faces  # renumbered
    monkeypatch.setattr(mf, "locality_ordered", lambda v, f: (v, f))
    v0, f0, clean0 = mf._meshfix_session(mesh.vertices, mesh.faces, p, True)
    assert clean0 == clean1 and len(f0) == len(f1) > len(mesh.faces)  # holes filled
    assert np.array_equal(oriented_triangles(v1, f1), oriented_triangles(v0, f0))
    # MeshFix's "clean" (its own intersection test), which the audit takes as the count, agrees with the exact test
    from scanreg.mesh.intersect import self_intersecting_faces

    assert clean1 and not self_intersecting_faces(v1, f1).any()


def test_meshfix_counts_intersections_between_parts_it_repaired_one_by_one(monkeypatch):
    """Two interpenetrating copies of the cow (two parts, repaired one by one, each certified by MeshFix): the
    audit's count of self-intersecting faces after the repair comes from the pairs across the parts only
    (intersect.intersecting_across; the output is given no self-intersection test of its own) and equals the
    full exact test of the repaired mesh. (MeshFix on the whole mesh, ``scope=whole``: with the default the input's
    test is decided on the census's pairs.)"""
    import scanreg.mesh.topology as topology
    import scanreg.stages.repair.meshfix as mf
    from scanreg.geometry import Mesh
    from scanreg.mesh.intersect import self_intersecting_faces

    cow = load("pkg:pymeshlab/tests/sample_meshes/cow.obj")
    shift = 0.3 * (cow.vertices.max(axis=0) - cow.vertices.min(axis=0))
    two = Mesh(np.vstack([cow.vertices, cow.vertices + shift]),
               np.vstack([cow.faces, cow.faces + len(cow.vertices)]), "two cows")
    calls, tested = [], []
    across, tests = mf.intersecting_across, topology.self_intersections

    def spy_across(*args):
        calls.append(across(*args))
        return calls[-1]

    def spy_tests(v, f, previous=None):  # every whole-mesh test the audit and the backend make
        tested.append(len(f))
        return tests(v, f, previous)

    monkeypatch.setattr(mf, "intersecting_across", spy_across)
    monkeypatch.setattr(topology, "self_intersections", spy_tests)
    monkeypatch.setenv("SCANREG_NO_FORK", "1")  # the input's test (beside the backend) made where the spy sees it
    res = stage("meshfix", check_only=False, scope="whole").repair(two, CTX)
    out, m = res.mesh, res.metrics
    assert len(calls) == 1 and int(calls[0].sum()) == m["after_self_intersecting_faces"]
    assert len(out.faces) not in tested  # the count came from the pairs across the parts
    assert tested[:1] == [len(two.faces)]  # the input's own test (the audit's before)
    full = int(self_intersecting_faces(out.vertices, out.faces).sum())
    assert m["after_self_intersecting_faces"] == full > 0
    assert m["after_components"] == 2
