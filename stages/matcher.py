"""Descriptor matchers: pairs (target keypoint, source keypoint) of similar descriptors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from scanreg.stages.registry import MATCHER


@MATCHER.register("mutual_knn")
class MutualKNN:
    """A pair (t, s) when the target descriptor t is among the k nearest of s and, if ``mutual``, s among the
    k nearest of t (Euclidean distance between descriptors)."""

    @dataclass
    class Params:
        k: int = 3
        """Number of nearest descriptors considered on each side."""
        mutual: bool = True
        """Require the relation both ways; false keeps every k-nearest pair of each source descriptor."""

        def check(self):
            if self.k < 1:
                raise ValueError(f"k must be >= 1, got {self.k}")

    def __init__(self, params: Params):
        self.p = params

    def match(self, desc_target: np.ndarray, desc_source: np.ndarray) -> np.ndarray:
        """(M, 2) int array of (target index, source index), sorted."""
        k_t = min(self.p.k, len(desc_target))
        nn_t = knn(desc_target, desc_source, k_t)
        pairs_st = np.stack([nn_t.ravel(), np.repeat(np.arange(len(desc_source)), k_t)], axis=1)
        if self.p.mutual:
            k_s = min(self.p.k, len(desc_source))
            nn_s = knn(desc_source, desc_target, k_s)
            pairs_ts = np.stack([np.repeat(np.arange(len(desc_target)), k_s), nn_s.ravel()], axis=1)
            n = max(len(desc_source), 1)
            codes = np.intersect1d(pairs_st[:, 0] * n + pairs_st[:, 1], pairs_ts[:, 0] * n + pairs_ts[:, 1])
            return np.stack([codes // n, codes % n], axis=1)
        return np.unique(pairs_st, axis=0)


def knn(data: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """Indices (Q, k) of the k nearest rows of ``data`` for every query row, nearest first (exact, k-d tree:
    descriptors lie near a low-dimensional set, where k-d trees stay fast)."""
    _, j = cKDTree(data).query(queries, k=k, workers=-1)
    return np.asarray(j, dtype=np.int64).reshape(len(queries), -1)
