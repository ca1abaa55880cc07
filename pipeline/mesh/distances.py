"""Distances between surfaces: exact point-to-triangle distances (Open3D's raycasting scene, libigl's AABB tree)
and the area-weighted samples they are measured from."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Mesh, area_weighted_draws, barycentric_sample, points_on_faces
from scanreg.mesh.topology import _face_areas


def raycasting_scene(mesh: Mesh):
    """Open3D's raycasting scene of ``mesh``'s triangles (exact point-to-triangle distances)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene


def point_distances(scene, points: np.ndarray) -> np.ndarray:
    """Distances from ``points`` to the surface in ``scene`` (:func:`raycasting_scene`)."""
    import open3d as o3d

    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def surface_distances(a: Mesh, b: Mesh, n: int, seed: int) -> np.ndarray:
    """Distances from ``n`` area-weighted random points on ``a`` (:func:`area_samples`) to the surface of ``b``
    (:func:`distances_to`)."""
    return distances_to(b)(area_samples(a, n, seed))


def distances_to(mesh: Mesh):
    """The function of points (n, 3) that gives their exact distances to the surface of ``mesh`` (the nearest
    point on any face, in double precision; libigl's AABB tree, built here once). Open3D's raycasting scene
    (:func:`raycasting_scene`) computes in single precision."""
    import igl

    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    tree = igl.AABB()
    tree.init(v, f)

    def distances(points: np.ndarray) -> np.ndarray:
        return np.sqrt(tree.squared_distance(v, f, np.ascontiguousarray(points, dtype=np.float64))[0])
    return distances


def area_samples(mesh: Mesh, n: int, seed: int) -> np.ndarray:
    """``n`` area-weighted random points on ``mesh`` for :func:`surface_distances` (seeded by ``seed``)."""
    return _area_sample(mesh, n, np.random.default_rng([seed, 77]))


def _area_sample(mesh: Mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """The points :func:`~scanreg.geometry.barycentric_sample` draws with ``rng`` (the same draws, the same
    arithmetic, the same points bit for bit), from the face areas the audit has already measured: the
    triangles' cross products are computed once per mesh, and the corners only for the sampled faces."""
    areas = _face_areas(mesh)
    # barycentric_sample's weights: |cross|, twice the area (exact); its own error when there is nothing to draw
    drawn = area_weighted_draws(np.where(areas > 0, 2.0 * areas, 0.0), n, rng)
    if drawn is None:
        return barycentric_sample(mesh, n, rng)[0]
    return points_on_faces(mesh, *drawn)
