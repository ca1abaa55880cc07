"""Exact geometric predicates: the signs of the 3x3 and 2x2 orientation determinants, and the segment-triangle
tests built on them.

Each sign is computed in floating point with Shewchuk's static error bounds (orient3d: ``(7 + 56 eps) eps``
times the permanent, orient2d: ``(3 + 16 eps) eps``) and exactly, with Python integers, where the bound cannot
certify it: exact for the floating-point coordinates as given, whatever their scale.
"""

from __future__ import annotations

import numpy as np

from scanreg.geometry import rows_all, rows_any
from scanreg.mesh import native

EPS = np.ldexp(1.0, -53)  # half an ulp of 1.0: Shewchuk's epsilon
_O3_BOUND = (7.0 + 56.0 * EPS) * EPS
_O2_BOUND = (3.0 + 16.0 * EPS) * EPS


def _as_ints(rows: np.ndarray) -> np.ndarray:
    """Each row's floats as Python integers of one common power-of-two scale per row (exact: the signs of
    the homogeneous determinants below do not change under a positive scale), as an object array."""
    mant, expo = np.frexp(rows)
    ints = (mant * 2.0 ** 53).astype(np.int64)  # exact: |mant| < 1
    expo = np.where(mant == 0, expo.max(axis=1, keepdims=True), expo)
    shift = (expo - expo.min(axis=1, keepdims=True)).astype(object)
    return ints.astype(object) << shift


def _signs(det: np.ndarray) -> np.ndarray:
    """The signs (int8) of an object array of Python integers."""
    return np.array([(x > 0) - (x < 0) for x in det], np.int8)


def _orient3d_exact(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    r = _as_ints(np.hstack([a, b, c, d])).T
    adx, ady, adz = r[0] - r[9], r[1] - r[10], r[2] - r[11]
    bdx, bdy, bdz = r[3] - r[9], r[4] - r[10], r[5] - r[11]
    cdx, cdy, cdz = r[6] - r[9], r[7] - r[10], r[8] - r[11]
    det = adz * (bdx * cdy - cdx * bdy) + bdz * (cdx * ady - adx * cdy) + cdz * (adx * bdy - bdx * ady)
    return _signs(det)


def orient3d(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact sign (+1, 0, -1, int8) of ``det[a - d; b - d; c - d]`` for rows of (n, 3) float64 arrays: positive
    when ``d`` lies below the plane through ``a, b, c`` seen counter-clockwise from above (Shewchuk's
    convention), zero when the four points are coplanar."""
    sign, unsure, perm = _orient3d_filtered(a, b, c, d)
    if len(unsure):
        a, b, c, d = a[unsure], b[unsure], c[unsure], d[unsure]
        # every product zero (axis-aligned coplanar points): the determinant is exactly zero, unless a product
        # underflowed, which the exact path settles
        zero = (perm[unsure] == 0) & _no_underflow((a, b, c), d, 1e-90)
        sign[unsure[zero]] = 0
        rest = ~zero
        if rest.any():
            sign[unsure[rest]] = _orient3d_exact(a[rest], b[rest], c[rest], d[rest])
    return sign


def orient3d_filter(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """:func:`orient3d`'s sign where the floating-point filter alone certifies it, 0 where it cannot (no exact
    arithmetic): a nonzero sign is exact, a zero one may hide either sign. For conservative tests that only
    need to know when a point is certainly off a plane."""
    sign, unsure, _ = _orient3d_filtered(a, b, c, d)
    sign[unsure] = 0
    return sign


def _orient3d_filtered(a, b, c, d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The floating-point sign of :func:`orient3d`'s determinant, the rows where Shewchuk's bound cannot
    certify it, and the permanent the bound scales."""
    adx, ady, adz = (a - d).T
    bdx, bdy, bdz = (b - d).T
    cdx, cdy, cdz = (c - d).T
    bc, cb = bdx * cdy, cdx * bdy
    ca, ac = cdx * ady, adx * cdy
    ab, ba = adx * bdy, bdx * ady
    det = adz * (bc - cb) + bdz * (ca - ac) + cdz * (ab - ba)
    perm = (np.abs(bc) + np.abs(cb)) * np.abs(adz) + (np.abs(ca) + np.abs(ac)) * np.abs(bdz) \
        + (np.abs(ab) + np.abs(ba)) * np.abs(cdz)
    sign = np.sign(det).astype(np.int8)
    return sign, np.flatnonzero(np.abs(det) <= _O3_BOUND * perm), perm


def _no_underflow(pts: tuple[np.ndarray, ...], base: np.ndarray, floor: float) -> np.ndarray:
    """Rows whose nonzero coordinate differences from ``base`` are all above ``floor``: no product of the
    determinant's terms (three differences: 1e-90, two: 1e-150) underflows, so a zero permanent means a zero
    determinant."""
    ok = np.ones(len(base), bool)
    for p in pts:
        diff = np.abs(p - base)
        ok &= rows_all((diff == 0) | (diff > floor))
    return ok


def _orient2d_exact(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    r = _as_ints(np.hstack([a, b, c])).T
    det = (r[0] - r[4]) * (r[3] - r[5]) - (r[1] - r[5]) * (r[2] - r[4])
    return _signs(det)


def orient2d(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact sign (int8) of ``det[a - c; b - c]`` for rows of (n, 2) float64 arrays: positive when ``a, b, c``
    run counter-clockwise."""
    left = (a[:, 0] - c[:, 0]) * (b[:, 1] - c[:, 1])
    right = (a[:, 1] - c[:, 1]) * (b[:, 0] - c[:, 0])
    det = left - right
    perm = np.abs(left) + np.abs(right)
    sign = np.sign(det).astype(np.int8)
    unsure = np.flatnonzero(np.abs(det) <= _O2_BOUND * perm)
    if len(unsure):
        a, b, c = a[unsure], b[unsure], c[unsure]
        zero = (perm[unsure] == 0) & _no_underflow((a, b), c, 1e-150)
        sign[unsure[zero]] = 0
        rest = ~zero
        if rest.any():
            sign[unsure[rest]] = _orient2d_exact(a[rest], b[rest], c[rest])
    return sign


def projection_axes(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle, the two coordinates kept by a projection along one axis that keeps it non-degenerate (the
    axis of the normal's largest component among those that are exactly nonzero), and whether it has one. By
    the compiled kernel when there is one (:mod:`scanreg.mesh.native`: the same filter and arithmetic), the rows
    its filter cannot certify by :func:`projection_axes_numpy`: the same answers."""
    if native.kernels is None or not len(p):
        return projection_axes_numpy(p, q, r)
    p, q, r = (np.ascontiguousarray(x, dtype=np.float64) for x in (p, q, r))
    sign, drop = native.kernels.orient2d_projections(p, q, r)
    ok = rows_any(np.frombuffer(sign, np.int8).reshape(-1, 3) != 0)
    drop = np.frombuffer(drop, np.int8).astype(np.int64)
    unsure = np.flatnonzero(drop < 0)
    if len(unsure):
        keep_u, ok[unsure] = projection_axes_numpy(p[unsure], q[unsure], r[unsure])
        drop[unsure] = 3 - keep_u.sum(axis=1)  # the axis not kept
    return np.array([[1, 2], [0, 2], [0, 1]])[drop], ok


def projection_axes_numpy(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`projection_axes` in NumPy."""
    n = np.cross(q - p, r - p)
    ok = np.zeros((len(p), 3), bool)
    for k in range(3):
        keep = [j for j in range(3) if j != k]
        ok[:, k] = orient2d(p[:, keep], q[:, keep], r[:, keep]) != 0
    score = np.where(ok, np.abs(n), -1.0)
    drop = np.argmax(score, axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[drop]
    return keep, rows_any(ok)


def take2(x: np.ndarray, keep: np.ndarray) -> np.ndarray:
    return np.take_along_axis(x, keep, axis=1)


def _on_segment(x, y, c) -> np.ndarray:
    """``c`` (collinear with ``x, y``) within the closed segment's bounding box."""
    lo, hi = np.minimum(x, y), np.maximum(x, y)
    return rows_all((lo <= c) & (c <= hi))


def _segments_meet_2d(x, y, u, w) -> np.ndarray:
    """Closed 2-D segments ``xy`` and ``uw`` have a common point."""
    d1, d2 = orient2d(x, y, u), orient2d(x, y, w)
    d3, d4 = orient2d(u, w, x), orient2d(u, w, y)
    hit = (d1.astype(np.int16) * d2 < 0) & (d3.astype(np.int16) * d4 < 0)
    hit |= (d1 == 0) & _on_segment(x, y, u)
    hit |= (d2 == 0) & _on_segment(x, y, w)
    hit |= (d3 == 0) & _on_segment(u, w, x)
    hit |= (d4 == 0) & _on_segment(u, w, y)
    return hit


def _inside_2d(p, q, r, x) -> np.ndarray:
    """``x`` in the closed 2-D triangle ``p, q, r`` (non-degenerate)."""
    s = np.stack([orient2d(p, q, x), orient2d(q, r, x), orient2d(r, p, x)], axis=1)
    return rows_all(s >= 0) | rows_all(s <= 0)


def _coplanar_segment_triangle(p, q, r, x, y) -> np.ndarray:
    """Closed segment ``xy`` lying in the plane of the closed triangle ``p, q, r`` meets it."""
    keep, ok = projection_axes(p, q, r)
    p2, q2, r2, x2, y2 = (take2(a, keep) for a in (p, q, r, x, y))
    hit = _inside_2d(p2, q2, r2, x2) | _inside_2d(p2, q2, r2, y2)
    for u, w in ((p2, q2), (q2, r2), (r2, p2)):
        hit |= _segments_meet_2d(x2, y2, u, w)
    return hit & ok


def segment_meets_triangle(p, q, r, x, y, sx: np.ndarray | None = None,
                           sy: np.ndarray | None = None) -> np.ndarray:
    """Rows where the closed segment ``xy`` and the closed triangle ``p, q, r`` (non-degenerate) have a common
    point. ``sx``, ``sy``: ``orient3d(p, q, r, x)`` and ``(…, y)`` when already known."""
    sx = orient3d(p, q, r, x) if sx is None else sx
    sy = orient3d(p, q, r, y) if sy is None else sy
    hit = np.zeros(len(p), bool)
    cross = (sx.astype(np.int16) * sy <= 0) & ((sx != 0) | (sy != 0))  # the line meets the plane once, in xy
    if cross.any():
        i = np.flatnonzero(cross)
        o = np.stack([orient3d(x[i], y[i], p[i], q[i]), orient3d(x[i], y[i], q[i], r[i]),
                      orient3d(x[i], y[i], r[i], p[i])], axis=1)
        hit[i] = rows_all(o >= 0) | rows_all(o <= 0)
    flat = (sx == 0) & (sy == 0)
    if flat.any():
        i = np.flatnonzero(flat)
        hit[i] = _coplanar_segment_triangle(p[i], q[i], r[i], x[i], y[i])
    return hit
