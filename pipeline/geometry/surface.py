"""Triangle surfaces: face and vertex normals, areas, and area-weighted barycentric sampling (the paper's
sampler)."""

from __future__ import annotations

import math

import numpy as np

from scanreg.errors import InputError
from scanreg.geometry.arrays import cross3, row_norms
from scanreg.geometry.containers import Mesh


def face_normals(mesh: Mesh, unit: bool = True) -> np.ndarray:
    """Face normals (M, 3) by the right-hand rule (counter-clockwise = outward); area-weighted unless ``unit``."""
    v, f = mesh.vertices, mesh.faces
    n = cross3(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(row_norms(n)[:, None], 1e-300) if unit else n


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """Unit vertex normals: the area-weighted mean of the normals of the faces around each vertex."""
    fn = face_normals(mesh, unit=False)
    n = np.zeros_like(mesh.vertices)
    for k in range(3):
        np.add.at(n, mesh.faces[:, k], fn)
    return n / np.maximum(row_norms(n)[:, None], 1e-300)


def triangle_areas_normals(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per-face areas and unit normals (counter-clockwise winding = outward); degenerate faces get area 0."""
    v, f = mesh.vertices, mesh.faces
    cross = cross3(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
    return 0.5 * norm, normals


def barycentric_sample(
    mesh: Mesh, n_points: int, rng: np.random.Generator, min_area: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted random points on a mesh: ``(points, normals, face index)``.

    Each point falls on a triangle with probability proportional to its area (triangles with area <=
    ``min_area`` never): the per-triangle counts are drawn at once from the multinomial distribution, which is
    the same law as ``n_points`` independent area-weighted draws. On its triangle a point is
    ``a + u (b - a) + v (c - a)`` with ``u, v ~ U(0, 1)``, reflected to ``1 - u, 1 - v`` when ``u + v > 1``. The
    normal is the triangle's. Points come grouped by triangle (in face order).
    """
    v, f = mesh.vertices, mesh.faces
    a = v[f[:, 0]]
    e1, e2 = v[f[:, 1]] - a, v[f[:, 2]] - a
    cross = np.cross(e1, e2)
    norm = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    drawn = area_weighted_draws(np.where(0.5 * norm > min_area, norm, 0.0), n_points, rng)
    if drawn is None:
        raise InputError(f"{mesh.source or 'mesh'}: no triangle has an area above {min_area:g}: nothing to sample")
    face, uv = drawn
    normals = cross / np.where(norm > 0, norm, 1.0)[:, None]
    return points_on_faces(mesh, face, uv, (a, e1, e2)), normals[face], face


def area_weighted_draws(weights: np.ndarray, n_points: int,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`barycentric_sample`'s random draws: each point's face, drawn with probability proportional to
    ``weights`` (per-face counts from the multinomial, faces in order), and its ``(u, v)`` (N, 2), uniform and
    reflected to ``(1 - u, 1 - v)`` when ``u + v > 1``. None when no weight is positive."""
    total = math.fsum(weights)
    if not total > 0:
        return None
    counts = rng.multinomial(n_points, weights / total)
    face = np.repeat(np.arange(len(weights)), counts)
    uv = rng.random((n_points, 2))
    flip = uv[:, 0] + uv[:, 1] > 1.0
    uv[flip] = 1.0 - uv[flip]
    return face, uv


def points_on_faces(mesh: Mesh, face: np.ndarray, uv: np.ndarray,
                    edges: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The points ``a + u (b - a) + v (c - a)`` on the faces ``face`` (corners a, b, c) at ``uv`` (N, 2).
    ``edges``: every face's ``(a, b - a, c - a)`` when already computed (then gathered per point, the same
    values: many points per face are cheaper so than subtracting per point)."""
    if edges is None:
        v, f = mesh.vertices, mesh.faces[face]
        a = v[f[:, 0]]
        e1, e2 = v[f[:, 1]] - a, v[f[:, 2]] - a
    else:
        a, e1, e2 = (x[face] for x in edges)
    pts = a  # a fresh array (gathered), added to in place
    pts += uv[:, :1] * e1
    pts += uv[:, 1:] * e2
    return pts
