"""Descriptor matchers: pairs (target keypoint, source keypoint) of similar descriptors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipeline.config import Context
from pipeline.registry import MATCHER


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

    def match(self, desc_target: np.ndarray, desc_source: np.ndarray, ctx: Context) -> np.ndarray:
        """(M, 2) int array of (target index, source index), sorted."""
        k_t = min(self.p.k, len(desc_target))
        _, nn_t = cKDTree(desc_target).query(desc_source, k=k_t)
        nn_t = nn_t.reshape(len(desc_source), -1)
        pairs_st = np.stack([nn_t.ravel(), np.repeat(np.arange(len(desc_source)), k_t)], axis=1)
        if self.p.mutual:
            k_s = min(self.p.k, len(desc_source))
            _, nn_s = cKDTree(desc_source).query(desc_target, k=k_s)
            nn_s = nn_s.reshape(len(desc_target), -1)
            pairs_ts = np.stack([np.repeat(np.arange(len(desc_target)), k_s), nn_s.ravel()], axis=1)
            n = max(len(desc_source), 1)
            codes = np.intersect1d(pairs_st[:, 0] * n + pairs_st[:, 1], pairs_ts[:, 0] * n + pairs_ts[:, 1])
            return np.stack([codes // n, codes % n], axis=1)
        return np.unique(pairs_st, axis=0)
