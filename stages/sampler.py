"""Samplers: turn a triangle mesh into a point cloud (point clouds pass through unchanged)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from pipeline.config import Context
from pipeline.errors import ConfigError, InputError
from pipeline.geometry import Cloud, Mesh
from pipeline.registry import SAMPLER


def triangle_areas_normals(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per-face areas and unit normals (counter-clockwise winding = outward); degenerate faces get area 0."""
    v, f = mesh.vertices, mesh.faces
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
    return 0.5 * norm, normals


def barycentric_sample(
    mesh: Mesh, n_points: int, rng: np.random.Generator, min_area: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted random points on a mesh: ``(points, normals, face index)``.

    A triangle is drawn with probability proportional to its area (triangles with area <= ``min_area`` never);
    on it, ``u, v ~ U(0, 1)``, reflected to ``1 - u, 1 - v`` when ``u + v > 1``, and the point is
    ``a + u (b - a) + v (c - a)``. The normal is the triangle's.
    """
    areas, normals = triangle_areas_normals(mesh)
    w = np.where(areas > min_area, areas, 0.0)
    total = w.sum()
    if not total > 0:
        raise InputError(f"{mesh.source or 'mesh'}: no triangle has an area above {min_area:g}: nothing to sample")
    cdf = np.cumsum(w)
    cdf /= cdf[-1]
    face = np.searchsorted(cdf, rng.random(n_points), side="right")
    face = np.minimum(face, len(cdf) - 1)
    uv = rng.random((n_points, 2))
    flip = uv.sum(axis=1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    tri = mesh.faces[face]
    a = mesh.vertices[tri[:, 0]]
    pts = a + uv[:, :1] * (mesh.vertices[tri[:, 1]] - a) + uv[:, 1:] * (mesh.vertices[tri[:, 2]] - a)
    return pts, normals[face], face


@SAMPLER.register("barycentric")
class Barycentric:
    """Area-weighted random barycentric sampling (the paper's method), vectorised with NumPy."""

    @dataclass
    class Params:
        n_points: Optional[int] = 20000
        """Number of points to draw; leave null to use ``density`` instead."""
        density: Optional[float] = None
        """Points per unit area (input units squared, e.g. points/mm^2); used when ``n_points`` is null."""
        min_triangle_area: float = 0.0
        """Triangles with an area at or below this are never sampled. Absolute area in input units squared,
        or, when ``min_area_quantile`` is true, a quantile in [0, 1) of the mesh's triangle areas."""
        min_area_quantile: bool = False
        """Read ``min_triangle_area`` as a quantile of the triangle areas instead of an absolute area."""
        seed: int = 0
        """Random seed; the same seed gives the same points bit for bit."""

        def check(self):
            if (self.n_points is None) == (self.density is None):
                raise ValueError("give exactly one of n_points and density (set the other to null)")
            if self.n_points is not None and self.n_points < 1:
                raise ValueError(f"n_points must be >= 1, got {self.n_points}")
            if self.density is not None and not self.density > 0:
                raise ValueError(f"density must be > 0, got {self.density}")
            if self.min_area_quantile and not 0 <= self.min_triangle_area < 1:
                raise ValueError("min_triangle_area must be in [0, 1) when min_area_quantile is true")

    def __init__(self, params: Params):
        self.p = params

    def run(self, mesh: Mesh, ctx: Context) -> Cloud:
        areas, _ = triangle_areas_normals(mesh)
        min_area = self.p.min_triangle_area
        if self.p.min_area_quantile:
            min_area = float(np.quantile(areas, min_area))
        n = self.p.n_points
        if n is None:
            n = int(round(self.p.density * float(areas[areas > min_area].sum())))
            if n < 1:
                raise ConfigError(f"sampler=barycentric: density {self.p.density:g} gives no point on this mesh")
        pts, normals, face = barycentric_sample(mesh, n, np.random.default_rng(self.p.seed), min_area)
        return Cloud(pts, normals, mesh.source, {"face": face, "skipped_faces": int((areas <= min_area).sum())})
