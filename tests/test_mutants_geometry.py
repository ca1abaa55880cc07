"""Known answers that kill the mutants of the surface helpers and the samplers (./run mutants, issue #38): face and
vertex normals, areas, barycentric points, the area threshold at its boundary, the density count, the cloud voxel
check. Every expected value is written out or computed here with cross products, never with the code under test."""

import numpy as np
import pytest

from scanreg.errors import ConfigError
from scanreg.geometry import (Cloud, Mesh, barycentric_sample, face_normals, points_on_faces, triangle_areas_normals,
                              vertex_normals)
from scanreg.stages.sampler import Barycentric, Vertices
from scanreg.types import RunContext

P = np.array([1.0, 2.0, 3.0])  # away from the origin, so that a - b and a + b differ
# face 0: legs 0.2 (x) and 0.3 (y), cross product (0, 0, 0.06); face 1: legs 0.1 (z) and 0.4 (x), cross product
# (0, 0.04, 0); face 2: three collinear corners, no area
SMALL = Mesh(np.array([P, P + [0.2, 0, 0], P + [0, 0.3, 0], P + [0, 0, 0.1], P + [0.4, 0, 0],
                       P + [0.5, 0.5, 0.5], P + [1.0, 1.0, 1.0]]),
             np.array([[0, 1, 2], [0, 3, 4], [0, 5, 6]]))


def crosses(mesh):
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def test_face_normals_unit_by_default_and_area_weighted_on_request():
    assert np.allclose(face_normals(SMALL), [[0, 0, 1], [0, 1, 0], [0, 0, 0]], atol=1e-15)
    assert np.allclose(face_normals(SMALL, unit=False), [[0, 0, 0.06], [0, 0.04, 0], [0, 0, 0]], atol=1e-15)
    assert np.isfinite(face_normals(SMALL)).all()  # the degenerate face: a zero normal, not 0/0


def test_vertex_normals_are_the_normalised_sums_of_the_faces_cross_products():
    # two faces of different areas and directions around vertex 0, a third with another normal around vertex 2
    m = Mesh(np.array([P, P + [0.2, 0, 0], P + [0, 0.3, 0], P + [0, 0, 0.1], P + [0.1, 0.3, 0.2]]),
             np.array([[0, 1, 2], [0, 3, 1], [2, 1, 4]]))
    cr = crosses(m)
    want = np.zeros((5, 3))
    for f, c in zip(m.faces, cr):
        want[f] += c
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert np.allclose(vertex_normals(m), want, atol=1e-12)
    # a triangle given twice with opposite windings: its corners' normals cancel to zero, not 0/0
    twice = Mesh(m.vertices[:3], np.array([[0, 1, 2], [0, 2, 1]]))
    assert np.array_equal(vertex_normals(twice), np.zeros((3, 3)))


def test_triangle_areas_and_unit_normals_with_a_degenerate_face():
    areas, normals = triangle_areas_normals(SMALL)
    assert np.allclose(areas, [0.03, 0.02, 0.0], atol=1e-15)
    assert np.allclose(normals, [[0, 0, 1], [0, 1, 0], [0, 0, 0]], atol=1e-15)
    assert np.isfinite(normals).all()


def test_points_on_faces_with_and_without_precomputed_edges():
    rng = np.random.default_rng(3)
    face = rng.integers(0, 2, 50)
    uv = rng.random((50, 2)) * 0.5
    a, b, c = (SMALL.vertices[SMALL.faces[face, k]] for k in range(3))
    want = a + uv[:, :1] * (b - a) + uv[:, 1:] * (c - a)
    assert np.allclose(points_on_faces(SMALL, face, uv), want, atol=1e-14)
    v, f = SMALL.vertices, SMALL.faces
    edges = (v[f[:, 0]], v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.allclose(points_on_faces(SMALL, face, uv, edges), want, atol=1e-14)


def test_barycentric_sample_of_a_small_mesh_and_of_one_without_area():
    """Weights summing to less than 1 (areas 0.03 and 0.02) still draw; only a mesh without area cannot."""
    from scanreg.errors import InputError

    pts, normals, face = barycentric_sample(SMALL, 400, np.random.default_rng(0))
    assert set(np.unique(face)) == {0, 1}  # the degenerate face never
    assert 0.5 < np.mean(face == 0) < 0.7  # 0.03 / 0.05 = 0.6 of the points
    assert np.allclose(normals, np.where((face == 0)[:, None], [0, 0, 1.0], [0, 1.0, 0]))
    flat = Mesh(SMALL.vertices, SMALL.faces[2:])
    with pytest.raises(InputError, match="no triangle has an area above"):
        barycentric_sample(flat, 10, np.random.default_rng(0))


# Three triangles in the plane z = 0: areas 0.5, 0.5 and 2.0 exactly (right triangles with legs 1 x 1 and 2 x 2)
THREE = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0], [10, 0, 0], [12, 0, 0],
                       [10, 2, 0]]), np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]]))


def test_barycentric_sample_never_draws_a_triangle_whose_area_equals_the_threshold():
    pts, normals, face = barycentric_sample(THREE, 300, np.random.default_rng(0), min_area=0.5)
    assert np.all(face == 2) and np.allclose(normals, [0, 0, 1])
    assert np.all(pts[:, 0] >= 10) and np.all(pts[:, 0] + pts[:, 1] <= 12 + 1e-12)


def test_barycentric_sampler_counts_density_over_the_area_above_the_threshold():
    p = Barycentric.Params(n_points=None, density=10.0, min_triangle_area=0.5)
    c = Barycentric(p).sample(THREE, RunContext(seed=0))
    assert c.n_points == 20  # 10 points per unit area over the 2.0 of the one triangle above 0.5
    assert c.extra["skipped_faces"] == 2  # the two of area exactly 0.5
    assert Barycentric(Barycentric.Params(n_points=None, density=0.5, min_triangle_area=0.5)).sample(
        THREE, RunContext(seed=0)).n_points == 1  # 0.5 x 2.0: one point is enough
    with pytest.raises(ConfigError, match="gives no point"):  # 0.2 x 2.0 rounds to none
        Barycentric(Barycentric.Params(n_points=None, density=0.2, min_triangle_area=0.5)).sample(
            THREE, RunContext(seed=0))


@pytest.mark.parametrize("voxel", [0.0, -1.0])
def test_cloud_voxel_must_be_positive(voxel):
    cloud = Cloud(np.random.default_rng(0).random((500, 3)))
    with pytest.raises(ConfigError, match="cloud_voxel must be > 0"):
        Barycentric(Barycentric.Params(cloud_voxel=voxel, cloud_distances="absolute")).sample(cloud, RunContext(seed=0))


def test_vertices_sampler_normals_are_area_weighted_and_zero_where_faces_cancel():
    # an open fan of three faces of different areas (vertex 0 in all), an unreferenced vertex 4, and a triangle
    # given twice with opposite windings (its corners' normals cancel: zero, not 0/0)
    v = np.array([P, P + [0.2, 0, 0], P + [0, 0.3, 0], P + [0, 0, 0.1], P + [9, 9, 9],
                  P + [3, 0, 0], P + [3.5, 0, 0], P + [3, 0.5, 0]])
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [5, 6, 7], [5, 7, 6]])
    m = Mesh(v, f)
    c = Vertices(Vertices.Params()).sample(m, RunContext(seed=0))
    used = [0, 1, 2, 3, 5, 6, 7]
    assert np.array_equal(c.points, v[used])
    want = np.zeros_like(v)
    for face, cr in zip(f, crosses(m)):
        want[face] += cr
    n = np.linalg.norm(want, axis=1, keepdims=True)
    want = np.divide(want, n, out=np.zeros_like(want), where=n > 0)[used]
    assert np.allclose(c.normals, want, atol=1e-12)
    assert np.array_equal(c.normals[4:], np.zeros((3, 3)))
