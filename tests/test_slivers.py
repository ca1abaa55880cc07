"""Slivers (#17): the audit counts faces whose smallest angle is below 1 degree, both repair backends remove them
by edge collapse (the paper removes degenerate triangles by edge collapse or swap), and the guard holds."""

import numpy as np
import pytest

from scanreg.types import RunContext as Context
from scanreg.geometry import Mesh, make_T
from scanreg.io import write_ply
from scanreg.stages.registry import REPAIR, load_all, make_params
from scanreg.mesh.slivers import collapse_slivers
from scanreg.mesh.topology import mesh_stats, min_angles_deg


def sliver_sphere() -> tuple[Mesh, Mesh]:
    """An octagonal bipyramid (16 faces, a coarse sphere) and the same with every face split 1-to-3 at a point
    1e-6 from an edge's midpoint (a cap and two needles) or from a corner (needles)."""
    n = 8
    ang = np.arange(n) * 2 * np.pi / n
    v = np.vstack([np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], 1), [[0, 0, 1.2], [0, 0, -0.9]]])
    faces = [f for i in range(n) for f in ((i, (i + 1) % n, n), ((i + 1) % n, i, n + 1))]
    V, F = list(v), []
    for k, (a, b, c) in enumerate(faces):
        mid = (v[a] + v[b]) / 2
        p = mid + 1e-6 * (v[c] - mid) if k % 2 == 0 else v[a] + 1e-6 * ((v[b] + v[c]) / 2 - v[a])
        V.append(p)
        F += [(a, b, len(V) - 1), (b, c, len(V) - 1), (c, a, len(V) - 1)]
    return Mesh(v, np.array(faces)), Mesh(np.array(V), np.array(F), "sliver_sphere")


def test_min_angles_known_answers():
    m = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, np.sqrt(3) / 2, 0], [2, 0, 0]], float),
             np.array([[0, 1, 2], [0, 1, 3], [0, 4, 1]]))
    a = min_angles_deg(m)
    assert np.allclose(a[:2], [45.0, 60.0]) and a[2] == 0.0  # right isosceles, equilateral, collinear


def test_sliver_sphere_counts_and_collapse():
    clean, sl = sliver_sphere()
    assert mesh_stats(clean)["sliver_faces"] == 0
    before = mesh_stats(sl)["sliver_faces"]
    assert before >= 16 and len(sl.faces) == 48
    out = collapse_slivers(sl)
    st = mesh_stats(out)
    assert st["sliver_faces"] == 0 and st["watertight"] == 1 and st["components"] == 1
    assert abs(st["volume"] - mesh_stats(clean)["volume"]) < 1e-4  # the surface did not move


@pytest.mark.parametrize("backend", ["meshfix", "meshlab"])
def test_both_backends_remove_slivers_within_the_guard(backend, tmp_path):
    load_all()
    _, sl = sliver_sphere()
    cls = REPAIR.get(backend)
    stage = cls(make_params(cls.Params, {}, backend))
    m = stage.repair(sl, Context(seed=0, run_dir=tmp_path)).metrics  # unprefixed names
    assert m["before_sliver_faces"] >= 16 and m["after_sliver_faces"] == 0, m
    assert m["guard_ok"] == 1
    stage_off = cls(make_params(cls.Params, {"remove_slivers": False}, backend))
    m_off = stage_off.repair(sl, Context(seed=0, run_dir=tmp_path)).metrics
    assert m_off["after_sliver_faces"] > 0  # the backends alone leave them: the step is what removes them


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["meshfix", "meshlab"])
def test_sliver_sphere_still_registers(backend, tmp_path):
    """The repaired sliver sphere registers to a sampling of the clean one moved by a known pose (5 degrees:
    within the bipyramid's 45-degree symmetry, so the answer is unique)."""
    import scanreg
    from scipy.spatial.transform import Rotation

    from scanreg.geometry import barycentric_sample, transform_errors

    clean, sl = sliver_sphere()
    write_ply(tmp_path / "slivers.ply", sl)
    tgt = barycentric_sample(clean, 20000, np.random.default_rng(0))[0]
    T = make_T(Rotation.from_euler("xyz", [3, -2, 4], degrees=True).as_matrix(), np.array([0.01, -0.02, 0.01]))
    res = scanreg.register(tmp_path / "slivers.ply", tgt @ T[:3, :3].T + T[:3, 3], gt=T,
                           overrides=[f"repair={backend}", "coarse=none"], run_dir=tmp_path / "run")
    assert res.metrics["repair_after_sliver_faces"] == 0
    assert transform_errors(res.T_target_source, T)[0] < 0.5, res.metrics


def test_collapse_tracks_the_faces_it_changed():
    """collapse_slivers records which faces it changed (the faces with a moved or joined corner), for collapse_folds:
    the same faces as comparing the two meshes' coordinates finds on the sliver sphere, and collapse_folds gives
    the same counts either way."""
    from scanreg.mesh.slivers import _changed_faces, collapse_folds
    from scanreg.mesh.topology import known

    _, sl = sliver_sphere()
    out = collapse_slivers(sl)
    tracked = known(out, "collapsed_from")
    assert tracked is not None and tracked[0][0] is sl.vertices
    gone, new = _changed_faces(sl, out)
    assert gone.sum() >= 16 and (tracked[1] == gone).all() and (tracked[2] == new).all()
    untracked = Mesh(out.vertices, out.faces)  # the same arrays, nothing remembered
    for a, b in zip(collapse_folds(sl, out), collapse_folds(sl, untracked)):
        assert (a == b).all()


def test_audit_shortcuts_give_the_plain_computations_answers():
    """The audit's faster computations (#16) give what the plain ones give, bit for bit: the smallest angle from
    the largest cosine, the edge table from min/max keys, the surface samples from the remembered face areas
    (the points ``barycentric_sample`` draws), and the smallest angles ``collapse_slivers`` copies for the faces
    it kept."""
    from scanreg.geometry import barycentric_sample
    from scanreg.mesh.distances import _area_sample
    from scanreg.mesh.topology import _edge_table, _min_angles_deg, non_manifold_vertices

    _, sl = sliver_sphere()
    # a non-manifold edge (three faces on 0-1), a pinched vertex (two fans at 5) and a zero-area face
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [3, 0, 0], [4, 0, 0], [3, 1, 0],
                  [2, 0, 0], [3, -1, 0], [5, 0, 0]], float)
    odd = Mesh(v, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [5, 6, 7], [5, 8, 9], [5, 6, 10]]))
    for m in (sl, odd):
        P = m.vertices[m.faces]
        plain = np.full(len(P), 180.0)
        for i in range(3):  # the angle at each corner, the smallest kept
            a, b = P[:, (i + 1) % 3] - P[:, i], P[:, i - 1] - P[:, i]
            den = np.sqrt(np.einsum("ij,ij->i", a, a)) * np.sqrt(np.einsum("ij,ij->i", b, b))
            c = np.divide(np.einsum("ij,ij->i", a, b), den, out=np.ones(len(P)), where=den > 0)
            plain = np.minimum(plain, np.degrees(np.arccos(np.clip(c, -1, 1))))
        assert np.array_equal(_min_angles_deg(m), plain)
        d = np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]])
        _, inv, cnt = np.unique(np.sort(d, axis=1), axis=0, return_inverse=True, return_counts=True)
        directed, edge, counts = _edge_table(m.faces)
        assert np.array_equal(directed, d) and np.array_equal(edge, inv.ravel()) and np.array_equal(counts, cnt)
        for seed in (0, 3):
            assert np.array_equal(_area_sample(m, 500, np.random.default_rng(seed)),
                                  barycentric_sample(m, 500, np.random.default_rng(seed))[0])
    assert non_manifold_vertices(odd) == 1  # vertex 5 (0 and 1 are on the non-manifold edge, not counted)
    from scanreg.geometry import cross3, triangle_areas_normals
    from scanreg.mesh.topology import _face_areas
    from scipy.spatial import ConvexHull
    rng = np.random.default_rng(7)  # a closed hull of 3000 points on an ellipsoid of mixed scales: 5996 faces
    pts = rng.normal(size=(3000, 3))
    pts = pts / np.linalg.norm(pts, axis=1)[:, None] * [1.0, 1e-3, 1e3]
    hull = Mesh(pts, ConvexHull(pts).simplices.astype(np.int64))
    volumes = 0
    for m in (sl, odd, sliver_sphere()[0], hull):  # areas and volume column by column: the same bits as on rows
        v, f = m.vertices, m.faces
        assert np.array_equal(_face_areas(Mesh(v, f)), triangle_areas_normals(m)[0])
        rows = float(np.einsum("ij,ij->i", v[f[:, 0]], cross3(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)
        if mesh_stats(m)["watertight"]:
            assert mesh_stats(Mesh(v, f))["volume"] == rows
            volumes += 1
    assert volumes == 3  # the two spheres and the hull
    out = collapse_slivers(sl, 1.0)
    from scanreg.mesh.topology import known
    assert known(out, "collapsed_from") is not None  # the kept faces' angles were copied, not recomputed
    assert np.array_equal(min_angles_deg(out), _min_angles_deg(Mesh(out.vertices, out.faces)))


def _meshlab_collapse(mesh: Mesh, angle_deg: float = 1.0, rounds: int = 3) -> Mesh:
    """The reference: MeshLab's own filters, as collapse_slivers ran them before it computed them itself."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(mesh.vertices, mesh.faces.astype(np.int32)))
    for _ in range(rounds):
        ms.meshing_remove_t_vertices(method="Edge Collapse", threshold=1.0 / np.tan(np.radians(angle_deg)),
                                     repeat=True)
        ms.meshing_remove_null_faces()
        ms.meshing_remove_unreferenced_vertices()
        cm = ms.current_mesh()
        out = Mesh(cm.vertex_matrix(), cm.face_matrix().astype(np.int64))
        if not (min_angles_deg(out) < angle_deg).any():
            break
    return out


def _faces_by_coordinates(m: Mesh) -> list:
    """The faces as corner coordinates, each rotated to start at its smallest corner (orientation kept), sorted."""
    P = m.vertices[m.faces]
    first = np.lexsort((P[:, :, 2], P[:, :, 1], P[:, :, 0]), axis=1)[:, 0]
    return sorted(tuple(np.roll(p, -k, axis=0).ravel()) for p, k in zip(P, first))


def _pulled_grid(seed: int, n: int = 30, pulled: bool = True) -> Mesh:
    """A jittered height-field grid, faces shuffled, a third of its vertices pulled to within 1e-7..1e-3 of a
    neighbour (needles) or of the middle of an opposite edge (caps): about 200 slivers, many side by side
    (``pulled=False``: none pulled)."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    v = np.stack([x.ravel(), y.ravel(), 0.02 * rng.standard_normal(n * n)], 1)
    q = np.arange(n * n).reshape(n, n)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, 1:].ravel(), q[1:, :-1].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])[rng.permutation(2 * (n - 1) ** 2)]
    for i in rng.choice(n * n, n * n // 3, replace=False) if pulled else ():
        others = [t for t in f[rng.choice(np.flatnonzero((f == i).any(axis=1)))] if t != i]
        to = v[others[0]] if rng.random() < 0.5 else 0.5 * (v[others[0]] + v[others[1]])
        v[i] = to + rng.uniform(1e-7, 1e-3) * rng.standard_normal(3)
    return Mesh(v, f)


@pytest.mark.parametrize("seed", range(6))
def test_collapse_is_meshlabs_t_vertex_collapse(seed):
    """collapse_slivers computes MeshLab's "Remove T-vertices by edge collapse" (repeat), null-face and
    unreferenced-vertex removal itself (on the faces that take part, #16): the same faces, corner coordinates
    bit for bit, as MeshLab's filters give, on grids with about 200 slivers side by side (collapses that
    chain, apexes marked by an earlier collapse in the same round), and on the sliver sphere."""
    meshes = [_pulled_grid(seed)] + ([sliver_sphere()[1]] if seed == 0 else [])
    for m in meshes:
        assert (min_angles_deg(m) < 1).sum() >= (16 if m.source else 150)
        ours = collapse_slivers(Mesh(m.vertices.copy(), m.faces.copy()))
        assert len(ours.faces) < len(m.faces)
        assert _faces_by_coordinates(ours) == _faces_by_coordinates(_meshlab_collapse(m))


def test_collapse_leaves_coincident_vertices_apart():
    """Vertices a mesh already has twice (a pinch that a non-manifold repair split) are not joined by the
    collapse (MeshLab's filter joins every coincident pair in the mesh): a sliver elsewhere is collapsed, the
    pinch stays two vertices."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [-1, 0, 0], [0, -1, 0],
                  [3, 0, 0], [4, 0, 0], [3.5, 1e-5, 0], [3.5, 1, 0]], float)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 8, 9], [8, 7, 9], [6, 7, 8]])
    out = collapse_slivers(Mesh(v, f))
    assert len(out.faces) == 3 and (min_angles_deg(out) >= 1).all()  # the cap (6, 7, 8) and a neighbour gone
    assert len(out.vertices) == 9  # 8 joined to 7 or 6; 0 and 3 still two
    assert len(_meshlab_collapse(Mesh(v, f)).vertices) == 8  # MeshLab joins 0 and 3 as well


@pytest.mark.parametrize("seed", range(3))
def test_fold_check_neighbourhood_holds_every_face_a_changed_face_can_touch(seed):
    """collapse_folds compares the meshes on the faces near a changed face only (``_near_changes``): every face
    that can touch a changed face (its centroid within its circumradius of that face, by libigl's exact
    distance) is in it, on grids whose collapse changes long needles too, and where one long triangle alone
    changes (long faces are reached through grids of points, not their centroids); and those grids
    (``_face_grids``) are the points ``t0 + (a/n)(t1 - t0) + (b/n)(t2 - t0)``, a + b <= n, triangle by triangle."""
    from scanreg.mesh.distances import distances_to
    from scanreg.mesh.slivers import _centres, _changed_faces, _face_grids, _near_changes

    pulled, clean = _pulled_grid(seed), _pulled_grid(seed, pulled=False)
    m = Mesh(np.vstack([pulled.vertices, clean.vertices + [1.2, 0, 0]]),
             np.vstack([pulled.faces, clean.faces + len(pulled.vertices)]))  # slivers on one side only
    # and a long triangle over the clean grid, removed: it alone changes, its grid of points alone reaches
    v = np.vstack([clean.vertices, [[0.1, 0.5, 0.05], [0.9, 0.5, 0.05], [0.5, 0.52, 0.05]]])
    lid = Mesh(v, np.vstack([clean.faces, [[len(v) - 3, len(v) - 2, len(v) - 1]]]))
    for before, after in ((m, collapse_slivers(Mesh(m.vertices.copy(), m.faces.copy()))),
                          (lid, Mesh(v, clean.faces))):
        near_b, near_a = _near_changes(before, after)
        gone, new = _changed_faces(before, after)
        (xb, rb), (xa, ra) = _centres(before), _centres(after)
        rc = np.concatenate([rb[gone], ra[new]])
        assert (rc > max(np.quantile(rb, 0.99), np.quantile(ra, 0.99))).any()  # long changed faces: gridded
        changed = np.concatenate([before.vertices[before.faces[gone]], after.vertices[after.faces[new]]])
        to_changed = distances_to(Mesh(changed.reshape(-1, 3), np.arange(changed.size // 3).reshape(-1, 3)))
        for x, r, near in ((xb, rb, near_b), (xa, ra, near_a)):
            touching = to_changed(x) <= r  # a face lies within its circumradius of its centroid
            assert near[touching].sum() == touching.sum() > 0 and not near.all()
    rng = np.random.default_rng(seed)
    tris = rng.normal(size=(7, 3, 3)) * rng.uniform(0.01, 1, (7, 1, 1))
    expected = []
    for t in tris:
        n = int(np.ceil(max(np.linalg.norm(t[(k + 1) % 3] - t[k]) for k in range(3)) / 0.1))
        for b in range(n + 1):
            for a in range(n + 1 - b):
                expected.append(t[0] + a / n * (t[1] - t[0]) + b / n * (t[2] - t[0]))
    assert np.allclose(_face_grids(tris, 0.1), expected, rtol=0, atol=1e-12)


def test_one_face_t_vertex_test_is_the_array_test():
    """The collapse re-tests moved faces one at a time in Python floats (_tvertex_test_one): it must decide as
    the array test does, bit for bit, on slivers, caps, needles, zero and tiny sides, rounded and huge
    coordinates (a wrong side or corner changes which vertex moves)."""
    from scanreg.mesh.slivers import _tvertex_test, _tvertex_test_one

    rng = np.random.default_rng(3)
    thr = np.float32(1 / np.tan(np.radians(1.0)))
    seen = set()
    for trial in range(6000):
        P = rng.normal(size=(3, 3)) * 10.0 ** rng.integers(-8, 8)
        kind = trial % 6
        if kind == 1:  # a cap: the apex near its long side
            P[2] = P[0] + (P[1] - P[0]) * rng.random() + rng.normal(size=3) * 1e-9 * np.abs(P).max()
        elif kind == 2:  # a zero side
            P[1] = P[0]
        elif kind == 3:  # the apex's foot beyond a corner
            P[2] = P[0] + (P[1] - P[0]) * rng.choice([1.2, -0.3, 0.5]) + rng.normal(size=3) * 1e-4
        elif kind == 4:  # ties in length
            P = np.round(P, 0)
        elif kind == 5:  # sides beyond float32, and squares that underflow
            P *= rng.choice([1e36, 1e-160])
        with np.errstate(over="ignore"):  # (the array test casts sides beyond float32 to inf)
            a = tuple(x[0] for x in _tvertex_test(P[None], thr))
        b = _tvertex_test_one(P.tolist(), float(thr))
        assert (bool(a[0]), int(a[1]), int(a[2])) == b, (P, a, b)
        seen.add(b[0])
    assert seen == {True, False}
