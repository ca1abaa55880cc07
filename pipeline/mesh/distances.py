"""Distances between surfaces: exact point-to-triangle distances in double precision (libigl's AABB tree), measured
on the whole surface or near the points only, the faces two meshes share, and the area-weighted samples the
distances are measured from."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Mesh, area_weighted_draws, barycentric_sample, in_cells_around, points_on_faces
from scanreg.mesh.boxes import largest_sides, mesh_face_boxes
from scanreg.mesh.intersect import face_keys, same_faces, stable_order
from scanreg.mesh.topology import _face_areas


def surface_distances(a: Mesh, b: Mesh, n: int, seed: int) -> np.ndarray:
    """Distances from ``n`` area-weighted random points on ``a`` (:func:`area_samples`) to the surface of ``b``
    (:func:`distances_to`)."""
    return distances_to(b)(area_samples(a, n, seed))


def distances_to(mesh: Mesh):
    """The function of points (n, 3) that gives their exact distances to the surface of ``mesh`` (the nearest
    point on any face, in double precision; libigl's AABB tree, built here once). (Open3D's raycasting scene
    computes in single precision, and a process that forks must not have used it: oneTBB.)"""
    import igl

    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    tree = igl.AABB()
    tree.init(v, f)

    def distances(points: np.ndarray) -> np.ndarray:
        return np.sqrt(tree.squared_distance(v, f, np.ascontiguousarray(points, dtype=np.float64))[0])
    return distances


def exact_distances(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Distances from ``points`` to the surface of ``mesh`` (:func:`distances_to`)."""
    return distances_to(mesh)(points)


def area_samples(mesh: Mesh, n: int, seed: int) -> np.ndarray:
    """``n`` area-weighted random points on ``mesh`` for :func:`surface_distances` (seeded by ``seed``)."""
    return _area_sample(mesh, n, np.random.default_rng([seed, 77]))


def area_samples_on_faces(mesh: Mesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`area_samples` and the face each point lies on."""
    return _area_sample(mesh, n, np.random.default_rng([seed, 77]), with_faces=True)


def _area_sample(mesh: Mesh, n: int, rng: np.random.Generator, with_faces: bool = False):
    """The points :func:`~scanreg.geometry.barycentric_sample` draws with ``rng`` (the same draws, the same
    arithmetic, the same points bit for bit), from the face areas the audit has already measured: the
    triangles' cross products are computed once per mesh, and the corners only for the sampled faces
    (``with_faces``: also each point's face)."""
    areas = _face_areas(mesh)
    # barycentric_sample's weights: |cross|, twice the area (exact); its own error when there is nothing to draw
    drawn = area_weighted_draws(np.where(areas > 0, 2.0 * areas, 0.0), n, rng)
    if drawn is None:
        points, _, face = barycentric_sample(mesh, n, rng)
    else:
        points, face = points_on_faces(mesh, *drawn), drawn[0]
    return (points, face) if with_faces else points


def shared_faces(a: Mesh, b: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the faces of ``a`` that ``b`` also has, and of the faces of ``b`` that ``a`` also has: the same
    triangle in space (the same set of corner coordinates, whatever the vertex indices and the corner order).
    Faces are paired by a hash of their corners (:func:`~scanreg.mesh.intersect.face_keys`) and count as shared
    only when their corners are equal too, so a hash collision costs a face its sharing, never a false one. Of a
    face ``b`` has twice, one copy is marked. (A repair's input and output: what it left as it was.)"""
    va, vb = (np.ascontiguousarray(m.vertices, dtype=np.float64) for m in (a, b))
    ka, kb = face_keys(va, a.faces), face_keys(vb, b.faces)
    order = stable_order(kb)
    sk = kb[order]
    at = np.minimum(np.searchsorted(sk, ka), max(len(sk) - 1, 0))
    i = np.flatnonzero(sk[at] == ka) if len(sk) else np.zeros(0, np.int64)
    j = order[at[i]]
    same = same_faces(va, a.faces, i, vb, b.faces, j)
    in_a, in_b = np.zeros(len(a.faces), bool), np.zeros(len(b.faces), bool)
    in_a[i[same]] = True
    in_b[j[same]] = True  # (of a face b has twice, the copy a's lookup found)
    return in_a, in_b


def distances_near(mesh: Mesh, points: np.ndarray, reach: float, measure, _retry: bool = True) -> np.ndarray:
    """The distances from ``points`` to the surface of ``mesh`` as ``measure(mesh, points)`` gives them, measured
    on the faces that can lie within ``reach`` of a point only: the same values wherever the distance is at most
    ``reach`` (the nearest face is then among those). The points farther than that from those faces are measured
    again on the faces within the largest such distance, then (should any be farther still) on the whole mesh. A
    repair's audit so measures the few points where the surface changed at the cost of their neighbourhood, not
    of the whole mesh.

    The faces kept are found on a grid of cells of side ``reach`` plus the faces' largest box side (at its
    :data:`~scanreg.mesh.boxes.NARROW_QUANTILE`, :func:`~scanreg.geometry.in_cells_around`): a face within
    ``reach`` of a point has its first corner in the point's cell or in a neighbouring one; the longer faces are
    always kept."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points) or not len(mesh.faces):
        return measure(mesh, points)
    side, s = largest_sides(*mesh_face_boxes(mesh.vertices, mesh.faces))
    cells = in_cells_around(mesh.vertices[mesh.faces[:, 0]], points, reach + s)
    if cells is None:
        return measure(mesh, points)
    near = (side > s) | cells
    if near.all():
        return measure(mesh, points)
    d = measure(Mesh(mesh.vertices, mesh.faces[near]), points) if near.any() else np.full(len(points), np.inf)
    far = ~(d <= reach)
    if far.any():
        # farther than the reach from the faces kept: no nearer than the reach from any face, and no farther than
        # from the faces kept; measured again on the faces within that bound (a hole filled far from its rim)
        bound = float(d[far].max())
        again = (_retry and np.isfinite(bound) and bound > reach)
        d[far] = distances_near(mesh, points[far], bound, measure, _retry=False) if again \
            else measure(mesh, points[far])
    return d
