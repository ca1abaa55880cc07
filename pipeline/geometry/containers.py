"""The geometry containers: triangle meshes and point clouds, and their validation.

Conventions: points are ``(N, 3)`` float64 arrays in the input's units; faces ``(M, 3)`` int64 vertex indices,
counter-clockwise seen from outside.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scanreg.errors import InputError
from scanreg.geometry.arrays import col_max, col_min, rows_all, rows_any


@dataclass
class Mesh:
    """Triangle mesh: ``vertices`` (N, 3) float64, ``faces`` (M, 3) int64 (counter-clockwise = outward)."""

    vertices: np.ndarray
    faces: np.ndarray
    source: str = ""
    """Where it came from (path or description), for messages."""
    closure_faces: int = 0
    """The last this-many faces were added to close an open scan into a thin shell (``repair.open_border=shell``):
    they are not scanned surface, and :meth:`scanned` leaves them out."""

    @property
    def n_points(self) -> int:
        return len(self.vertices)

    def scanned(self) -> "Mesh":
        """The mesh without its closure faces (and the vertices only they use): what samplers and the
        evaluation see."""
        if not self.closure_faces:
            return self
        keep = np.arange(len(self.faces)) < len(self.faces) - self.closure_faces
        return submesh(self, keep)


def submesh(mesh: Mesh, face_mask: np.ndarray | None = None) -> Mesh:
    """The faces where ``face_mask`` holds (every face when None), without the vertices no kept face uses."""
    f = mesh.faces if face_mask is None else mesh.faces[face_mask]
    used, inv = np.unique(f, return_inverse=True)
    return Mesh(mesh.vertices[used], inv.reshape(-1, 3).astype(np.int64), mesh.source)


@dataclass
class Cloud:
    """Point cloud with optional unit normals (N, 3)."""

    points: np.ndarray
    normals: np.ndarray | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def subset(self, idx) -> "Cloud":
        """The points (and normals, and per-point ``extra`` arrays such as colours) at ``idx`` (indices, a mask or
        a slice), in that order."""
        n = len(self.points)
        extra = {k: v[idx] for k, v in self.extra.items() if isinstance(v, np.ndarray) and len(v) == n}
        return Cloud(self.points[idx], None if self.normals is None else self.normals[idx], self.source, extra)

    def thinned(self, max_points: int, rng: np.random.Generator) -> "Cloud":
        """At most ``max_points`` of the points (:meth:`subset`): a uniform random subset drawn with ``rng``, in
        the cloud's order; the cloud itself when it has no more, or ``max_points`` is 0."""
        n = len(self.points)
        if not max_points or n <= max_points:
            return self
        return self.subset(random_subset(n, max_points, rng))


def random_subset(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """Ascending indices of a uniform random subset of ``k`` of ``range(n)``, drawn with ``rng``; every index
    (``rng`` untouched) when ``n <= k``."""
    return np.sort(rng.choice(n, size=k, replace=False)) if n > k else np.arange(n)


Geometry = Mesh | Cloud


def points_of(g: Geometry) -> np.ndarray:
    return g.vertices if isinstance(g, Mesh) else g.points


def validate_points(pts: np.ndarray, what: str) -> np.ndarray:
    """Check a coordinate array: (N, 3), non-empty, finite. Returns it as contiguous float64."""
    pts = np.asarray(pts)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{what}: expected N x 3 coordinates, got an array of shape {pts.shape}")
    if len(pts) == 0:
        raise InputError(f"{what}: contains no points")
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    bad = ~rows_all(np.isfinite(pts))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{what}: {int(bad.sum())} point(s) with NaN or infinite coordinates (first: index {i})")
    return pts


def validate_mesh(mesh: Mesh) -> Mesh:
    what = mesh.source or "mesh"
    v = validate_points(mesh.vertices, what)
    f = np.asarray(mesh.faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"{what}: expected M x 3 triangle indices, got an array of shape {f.shape}")
    if len(f) == 0:
        raise InputError(f"{what}: mesh has no faces")
    f = f.astype(np.int64, copy=False)
    if f.min() < 0 or f.max() >= len(v):
        bad = int(rows_any((f < 0) | (f >= len(v))).sum())
        raise InputError(
            f"{what}: {bad} face(s) index missing vertices (indices must be in 0..{len(v) - 1}, found {f.min()}..{f.max()})"
        )
    return Mesh(v, np.ascontiguousarray(f), mesh.source)


def bbox_diagonal(pts: np.ndarray) -> float:
    return float(np.linalg.norm(col_max(pts) - col_min(pts)))


def bbox_centre(pts: np.ndarray) -> np.ndarray:
    """The centre of the points' axis-aligned bounding box (3,)."""
    return 0.5 * (col_min(pts) + col_max(pts))
