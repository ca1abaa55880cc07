"""Polygon faces as triangles: fans for convex polygons, ear clipping (mapbox_earcut) otherwise."""

from __future__ import annotations

import numpy as np

from scanreg.errors import InputError
from scanreg.geometry import Mesh

def _polygon_normal(P: np.ndarray) -> np.ndarray:
    """Newell's normal of polygons ``P`` (M, k, 3): robust for non-planar and non-convex polygons."""
    Q = np.roll(P, -1, axis=1)
    return np.stack([((P[..., 1] - Q[..., 1]) * (P[..., 2] + Q[..., 2])).sum(1),
                     ((P[..., 2] - Q[..., 2]) * (P[..., 0] + Q[..., 0])).sum(1),
                     ((P[..., 0] - Q[..., 0]) * (P[..., 1] + Q[..., 1])).sum(1)], axis=1)


def _convex(P: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Which polygons ``P`` (M, k, 3) turn the same way (or not at all) at every corner about their normal ``n``."""
    e = np.roll(P, -1, axis=1) - P
    turn = np.einsum("mkj,mj->mk", np.cross(e, np.roll(e, -1, axis=1)), n)
    scale = np.abs(turn).max(axis=1, keepdims=True) + 1e-300
    return (turn >= -1e-9 * scale).all(axis=1)


def _ear_clip(poly: np.ndarray, P: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Triangles of one polygon (vertex ids ``poly``, points ``P``) by ear clipping (mapbox_earcut) in the plane
    normal to ``n``, wound like the polygon."""
    import mapbox_earcut

    a = np.eye(3)[np.argmin(np.abs(n))]
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    v = np.cross(n / np.linalg.norm(n), u)
    xy = np.stack([(P - P[0]) @ u, (P - P[0]) @ v], axis=1)
    idx = mapbox_earcut.triangulate_float64(xy, np.array([len(P)], dtype=np.uint32)).reshape(-1, 3)
    if len(idx) != len(P) - 2:  # a self-touching or degenerate outline: earcut gives up; a fan keeps the faces
        idx = np.stack([np.zeros(len(P) - 2, int), np.arange(1, len(P) - 1), np.arange(2, len(P))], axis=1)
    tris = poly[idx]
    # keep the polygon's winding: earcut's triangles turn one way in the (u, v) plane, which faces +n
    return tris if _polygon_normal(P[None])[0] @ n >= 0 else tris[:, ::-1]


def _triangulate(faces, pts: np.ndarray, label: str) -> np.ndarray:
    """Triangles from polygon index lists (an (M, k) array or a list of arrays). Convex polygons become fans
    (vectorised); non-convex ones (an L-shaped hexagon, say) are ear-clipped in their best-fit plane, so that
    the triangles cover exactly the polygon. Winding follows the polygon's."""
    groups: dict[int, list] = {}
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        groups = {faces.shape[1]: [faces]}
    elif isinstance(faces, Ragged):  # vectorised per polygon size
        for k in np.unique(faces.counts):
            rows = np.flatnonzero(faces.counts == k)
            groups[int(k)] = [faces.values[faces.offsets[rows][:, None] + np.arange(k)]]
    else:
        for poly in faces:
            groups.setdefault(len(poly), []).append(poly)
    out = []
    for k, polys in sorted(groups.items()):
        F = np.asarray(polys[0] if len(polys) == 1 and isinstance(polys[0], np.ndarray) and polys[0].ndim == 2
                       else polys, dtype=np.int64).reshape(-1, k)
        if k < 3:
            raise InputError(f"{label}: a face with {k} vertices (need at least 3)")
        if k == 3:
            out.append(F)
            continue
        if F.size and (F.min() < 0 or F.max() >= len(pts)):
            out.append(F[:, [0, 1, 2]])  # index errors are reported by the mesh validation
            continue
        P = pts[F]
        n = _polygon_normal(P)
        convex = _convex(P, n)
        out += [F[convex][:, [0, i, i + 1]] for i in range(1, k - 1)]
        out += [_ear_clip(F[j], P[j], n[j]) for j in np.flatnonzero(~convex)]
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 3), np.int64)


def _merge_vertices(tri_pts: np.ndarray) -> Mesh:
    flat = tri_pts.reshape(-1, 3)
    uniq, inv = np.unique(flat, axis=0, return_inverse=True)
    return Mesh(uniq.astype(np.float64), inv.reshape(-1, 3).astype(np.int64))


class Ragged:
    """Rows of different lengths stored flat: ``values[offsets[i]:offsets[i] + counts[i]]`` is row i."""

    def __init__(self, counts: np.ndarray, values: np.ndarray):
        self.counts, self.values = counts, values
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64) if len(counts) else counts

    def __len__(self) -> int:
        return len(self.counts)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.values[self.offsets[i]:self.offsets[i] + self.counts[i]]

    def __iter__(self):
        return (self[i] for i in range(len(self)))
