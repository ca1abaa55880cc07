"""The defect census (scanreg.mesh.census): known answers on meshes built by hand, one per defect class, and the
same counts as the repair's audit on real meshes (pymeshfix's bunny, pymeshlab's samples, ../shared/data)."""

from __future__ import annotations

import numpy as np
import pytest

from scanreg.geometry import Mesh
from scanreg.io import read_mesh
from scanreg.mesh.broad_phase import fold_vertices, intersection_candidates
from scanreg.mesh.census import census
from scanreg.mesh.topology import audit_mesh, intersections
from tests.conftest import shared

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
"""A unit cube, outward oriented; faces 2k and 2k + 1 make one side (0-1: the bottom, z = 0)."""

AUDITED = ("vertices", "faces", "unreferenced_vertices", "components", "boundary_edges", "boundary_loops",
           "non_manifold_edges", "inconsistent_orientation_edges", "degenerate_faces", "sliver_faces",
           "non_manifold_vertices")


def nonzero(c) -> dict:
    return {k: v for k, v in c.counts().items() if v and k not in ("vertices", "faces", "components")}


def tetra(offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) + offset
    return v, np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def test_closed_cube_is_clean():
    c = census(CUBE_V, CUBE_F)
    assert c.clean and nonzero(c) == {} and c.counts()["components"] == 1
    assert len(c.defect_faces(margin_rings=2, faces=CUBE_F)) == 0
    assert not census(CUBE_V, CUBE_F, broad_phase=False).clean  # intersections not looked for: not known clean


def test_cube_with_one_side_removed_has_one_hole_of_four_edges():
    f = CUBE_F[2:]  # the bottom gone
    # an open box: its rim, 4 / sqrt(5) = 1.79 times the square root of its area, is an outer border under the
    # default rule (open_border_ratio 1.5: a crop deeper than a hemisphere is a scan's border) ...
    opened = census(CUBE_V, f)
    assert nonzero(opened) == {"boundary_edges": 4, "boundary_loops": 1, "outer_borders": 1}
    assert opened.loop_outer[0] and opened.loop_length[0] == pytest.approx(4.0)
    # ... and a hole to fill under a stricter one
    c = census(CUBE_V, f, open_border_ratio=2.0)
    assert nonzero(c) == {"boundary_edges": 4, "boundary_loops": 1, "holes": 1}
    assert list(c.loop_edges) == [4] and c.loop_length[0] == pytest.approx(4.0)
    assert not c.loop_outer[0] and not c.clean  # a closed model's hole (short for its area), to be filled
    assert sorted(map(tuple, np.sort(c.boundary_edges, axis=1))) == [(0, 1), (0, 3), (1, 2), (2, 3)]
    # the faces along the hole: the lower triangle of each side; a ring more: every face
    near = c.defect_faces(faces=f)
    assert len(near) == 4 and (f[near] < 4).sum(axis=1).min() == 2
    assert len(c.defect_faces(margin_rings=1, faces=f)) == len(f)


def test_open_scan_border_is_kept_not_a_hole():
    n = 12
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    c = census(v, f)
    assert c.counts()["outer_borders"] == 1 and c.counts()["holes"] == 0 and c.loop_edges[0] == 4 * (n - 1)
    assert c.clean  # a flat open scan: nothing to repair, its border stays open


def test_two_tetrahedra_sharing_a_vertex_make_a_non_manifold_vertex():
    v1, f1 = tetra()
    v2, f2 = tetra((-1.0, -1.0, -1.0))
    v = np.vstack([v1, v2[:3]])  # the second tetrahedron's corner (0, 0, 1) - 1 is the first's vertex 0
    f = np.vstack([f1, np.where(f2 == 3, 0, f2 + 4)])
    c = census(v, f)
    assert list(c.non_manifold_vertices) == [0]
    # (a tetrahedron's corners other than the right-angled one are creases sharper than the fold cone)
    assert nonzero(c) == {"non_manifold_vertices": 1, "fold_vertices": 7}
    assert audit_mesh(Mesh(v, f))["non_manifold_vertices"] == 1
    flat = census(v, f).defect_mask()
    assert not flat.any()  # no face-level defect; the vertex defects need the faces:
    assert len(c.defect_faces(faces=f)) == 8


def test_three_triangles_on_one_edge_make_a_non_manifold_edge():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0.3], [0.5, 0, 1]], float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    c = census(v, f)
    assert c.non_manifold_edges.tolist() == [[0, 1]] and c.non_manifold_edge_faces.tolist() == [0, 1, 2]
    assert c.counts()["non_manifold_edges"] == 1 and c.counts()["non_manifold_vertices"] == 0
    # faces 0 and 2 traverse the edge the same way
    assert c.inconsistent_edges.tolist() == [[0, 1]]
    assert audit_mesh(Mesh(v, f))["non_manifold_edges"] == 1


def test_degenerate_faces_and_a_sliver():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [10, 0.05, 0], [20, 0, 0]], float)
    f = np.array([[0, 1, 3], [0, 1, 2], [1, 1, 3], [0, 4, 5]])  # a good face, collinear, repeated index, a cap
    c = census(v, f)
    assert c.degenerate_faces.tolist() == [1, 2]
    assert c.sliver_faces.tolist() == [1, 2, 3]  # zero-area faces count as slivers too, as in the audit
    assert census(v, f, sliver_angle_deg=0.1).sliver_faces.tolist() == [1, 2]  # the cap's angle is 0.57 deg
    assert c.counts()["degenerate_faces"] == 2 and c.counts()["sliver_faces"] == 3


def test_duplicates_and_unreferenced_vertices():
    v = np.vstack([CUBE_V, CUBE_V[[6]], [[5.0, 5.0, 5.0]]])  # vertex 8 at vertex 6's place; 9 unused
    f = np.vstack([CUBE_F, CUBE_F[[3]][:, [1, 2, 0]]])  # face 12: face 3 again
    c = census(v, f)
    assert c.duplicate_vertices.tolist() == [8] and c.unreferenced_vertices.tolist() == [8, 9]
    assert c.duplicate_faces.tolist() == [12] and not c.clean
    # the same position written as -0.0 is the same position
    w = np.array([[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0], [1.0, 0.0, 0.0]])
    assert census(w, np.array([[0, 1, 2]])).duplicate_vertices.tolist() == [1]


def test_small_components_are_the_ones_the_repair_removes():
    v2, f2 = tetra((5.0, 0.0, 0.0))
    v = np.vstack([CUBE_V, 0.01 * v2 + 5.0])
    f = np.vstack([CUBE_F, f2 + 8])
    c = census(v, f)
    assert list(c.component_faces) == [12, 4] and c.small_components.tolist() == [1]
    assert c.component_area[0] == pytest.approx(6.0)
    assert set(c.defect_faces(faces=f)) == set(range(12, 16))
    assert census(v, f, min_component_share=0.0).small_components.tolist() == []


def test_two_crossing_triangles_are_one_candidate_pair_and_adjacent_faces_never():
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, -1], [0.5, 0.5, 1], [3, 3, 0.5],
                  [5, 5, 5], [6, 5, 5], [5, 6, 5]], float)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    c = census(v, f)
    assert c.intersection_candidates.tolist() == [[0, 1]] and c.candidate_faces.tolist() == [0, 1]
    # faces sharing a vertex or an edge are never candidates, even folded flat onto each other
    g = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 4]])
    assert len(census(v, g).intersection_candidates) == 0
    assert intersections(Mesh(v, g)).count > 0  # (the exact test counts the fold ...)
    assert 0 in census(v, g).fold_vertices  # (... and the census reports where: a fold vertex)
    # a face folded onto its neighbour across an edge they traverse the same way, and a duplicated face: the
    # exact test counts both; the census gives their pairs to test
    h = np.array([[0, 1, 2], [0, 1, 5], [6, 7, 8], [6, 7, 8]])
    w = v.copy()
    w[5] = [1.0, 1.5, 0.0]
    for g in (h[:2], h[2:]):
        assert intersections(Mesh(w, g)).count == 2
        assert_exact_on_census_pairs(w, g, census(w, g))
        assert len(census(w, g).pairs_to_test(g)) == 1
    # apart: no candidate; a plane between them: none either, though their boxes overlap
    far = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.1], [1, 0, 0.1], [0, 1, 0.1]], float)
    assert len(intersection_candidates(far, np.array([[0, 1, 2], [3, 4, 5]]))) == 0
    box = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.9, 0.9, -1], [0.9, 0.9, 1], [2, 2, 0]], float)
    assert len(intersection_candidates(box, np.array([[0, 1, 2], [3, 4, 5]]))) == 1


def sphere(subdiv: int = 3) -> tuple[np.ndarray, np.ndarray]:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.create_sphere(subdiv=subdiv)
    m = ms.current_mesh()
    return m.vertex_matrix(), m.face_matrix().astype(np.int64)


def exact_pairs(v, f) -> tuple[np.ndarray, np.ndarray]:
    """The exact test's intersecting pairs, split into those sharing no vertex index and the others."""
    ex = intersections(Mesh(np.asarray(v, float), np.asarray(f))).pairs
    share = (f[ex[:, 0]][:, :, None] == f[ex[:, 1]][:, None, :]).any(axis=(1, 2))
    return ex[~share], ex[share]


@pytest.mark.parametrize("case", ["two spheres", "jittered", "soup"])
def test_candidates_cover_every_intersecting_pair(case):
    """Every pair the exact test finds is a candidate (no shared vertex) or meets at a fold vertex."""
    v, f = sphere(3)
    rng = np.random.default_rng(1)
    if case == "two spheres":
        v, f = np.vstack([v, v + [0.5, 0.2, 0.1]]), np.vstack([f, f + len(v)])
    elif case == "jittered":
        v = v + rng.normal(0, 0.06, v.shape)
    else:
        v, f = rng.normal(size=(300, 3)), np.arange(300).reshape(-1, 3)
    apart, sharing = exact_pairs(v, f)
    c = census(v, f)
    assert len(apart) > 10
    found = set(map(tuple, c.intersection_candidates.tolist()))
    assert set(map(tuple, apart.tolist())) <= found
    folds = set(c.fold_vertices.tolist())
    assert all(set(f[i]) & set(f[j]) & folds for i, j in sharing)
    # the exact test run on the census's pairs only finds the same faces as on the whole mesh
    assert_exact_on_census_pairs(v, f, c)


def assert_exact_on_census_pairs(v, f, c):
    from scanreg.mesh.intersect import _pair_hits, _welded

    vw, fw, _ = _welded(np.asarray(v, float), f)
    pairs = c.pairs_to_test(f)
    assert len(np.unique(pairs, axis=0)) == len(pairs) and (pairs[:, 0] < pairs[:, 1]).all()
    hit = _pair_hits(vw[fw], fw, pairs[:, 0], pairs[:, 1])
    assert set(np.unique(pairs[hit]).tolist()) == set(np.flatnonzero(intersections(Mesh(v, f)).mask).tolist())


def test_a_fan_that_covers_itself_is_a_fold_vertex():
    """Pymeshfix's bunny has five pairs of faces that meet beyond a shared vertex, all nearly coplanar with the
    rest of their fan (it turns twice): the census reports those vertices."""
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    apart, sharing = exact_pairs(m.vertices, m.faces)
    assert len(apart) == 0 and len(sharing) == 5
    folds = set(fold_vertices(m.vertices, m.faces).tolist())
    assert all(set(m.faces[i]) & set(m.faces[j]) & folds for i, j in sharing)
    assert_exact_on_census_pairs(m.vertices, m.faces, census(m.vertices, m.faces))


def assert_agrees_with_audit(mesh: Mesh, expect: dict | None = None):
    c = census(mesh.vertices, mesh.faces).counts()
    quick = census(mesh.vertices, mesh.faces, broad_phase=False).counts()
    assert {k: quick[k] for k in AUDITED} == {k: c[k] for k in AUDITED}
    a = audit_mesh(Mesh(mesh.vertices.copy(), mesh.faces.copy()), self_intersections=False)
    assert {k: c[k] for k in AUDITED} == {k: a[k] for k in AUDITED}
    for k, value in (expect or {}).items():
        assert c[k] == value, k
    return c


def test_agrees_with_the_audit_on_pymeshfix_bunny():
    c = assert_agrees_with_audit(read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply"),
                                 {"boundary_loops": 70, "holes": 70, "non_manifold_edges": 132})
    assert c["outer_borders"] == 0


@pytest.mark.parametrize("name", ["bunny.obj", "bone.ply", "cow.obj", "airplane.obj", "rangemaps/face000.ply"])
def test_agrees_with_the_audit_on_pymeshlab_samples(name):
    assert_agrees_with_audit(read_mesh(f"pkg:pymeshlab/tests/sample_meshes/{name}"))


@pytest.mark.parametrize("rel", ["meshlab_defects/many_small_holes.ply", "meshlab_defects/non_manif_hole.ply",
                                 "meshlab_defects/screwdriver.ply", "stanford_bunny/bun000.ply",
                                 "stanford_bunny/top3.ply", "open_full_jaw_p26/maxilla/tooth_1.ply"])
def test_agrees_with_the_audit_on_shared_data(rel):
    c = assert_agrees_with_audit(read_mesh(str(shared(rel))))
    if rel.startswith("stanford_bunny"):
        assert c["outer_borders"] >= 1  # a raw range scan: its outer border(s) kept open (one per large part)
    if rel.endswith("many_small_holes.ply"):  # an open scan: 31 holes in it, and its border
        assert (c["boundary_loops"], c["holes"], c["outer_borders"]) == (32, 31, 1)


def test_a_census_without_the_broad_phase_is_the_full_ones_rest():
    """Asked for without the broad phase after the full census of the same mesh (the repair's input test made in
    place, then the backend's census), the census is taken from it: every class the same as measured afresh."""
    from dataclasses import fields

    from scanreg.mesh.census import mesh_census

    mesh = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    full = mesh_census(mesh)
    rest = mesh_census(mesh, broad_phase=False)
    fresh = mesh_census(Mesh(mesh.vertices.copy(), mesh.faces.copy()), broad_phase=False)
    assert len(full.intersection_candidates) and len(full.fold_vertices) and not rest.broad_phase
    assert rest.component is full.component  # taken from it, not measured again
    for f in fields(fresh):
        a, b = getattr(rest, f.name), getattr(fresh, f.name)
        assert np.array_equal(a, b) and np.asarray(a).dtype == np.asarray(b).dtype, f.name
