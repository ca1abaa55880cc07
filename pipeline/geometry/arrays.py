"""Small array helpers with the semantics of NumPy expressions that the hot loops call many times.

Each gives the same values as the NumPy expression its docstring names (min, max, any and all do not depend on
the order of evaluation; the products are evaluated in the same order); they exist because NumPy's reductions
along a short axis of 3 are slow (``experiments/benchmarks/icp_speed.md``).
"""

from __future__ import annotations

import numpy as np


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays: the values of ``np.cross(a, b)``."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def row_norms(a: np.ndarray) -> np.ndarray:
    """Euclidean norms along the last axis (of length 3) of any array: ``np.linalg.norm(a, axis=-1)``, summed
    x, y, z from left to right."""
    return np.sqrt(a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2])


def col_min(a: np.ndarray) -> np.ndarray:
    """``a.min(axis=0)`` of a non-empty (N, k) array."""
    return np.array([a[:, k].min() for k in range(a.shape[1])], dtype=a.dtype)


def col_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=0)`` of a non-empty (N, k) array."""
    return np.array([a[:, k].max() for k in range(a.shape[1])], dtype=a.dtype)


def rows_any(a: np.ndarray) -> np.ndarray:
    """``a.any(axis=1)`` of a (N, k) array, k >= 1."""
    out = a[:, 0].astype(bool)
    for k in range(1, a.shape[1]):
        out |= a[:, k].astype(bool, copy=False)
    return out


def rows_all(a: np.ndarray) -> np.ndarray:
    """``a.all(axis=1)`` of a (N, k) array, k >= 1."""
    out = a[:, 0].astype(bool)
    for k in range(1, a.shape[1]):
        out &= a[:, k].astype(bool, copy=False)
    return out
