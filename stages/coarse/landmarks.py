"""``coarse=landmarks``: the paper's rough registration from user-picked landmark pairs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.errors import ConfigError, StageError
from scanreg.geometry import Cloud, apply_T, horn_quaternion
from scanreg.stages.coarse.base import CoarseBase
from scanreg.stages.registry import COARSE
from scanreg.types import CoarseResult, Distances, RunContext, to_abs


@COARSE.register("landmarks")
class Landmarks(CoarseBase):
    """User-picked landmark pairs (``data.landmarks``, at least 3) solved in closed form (Horn). It reports each
    landmark's residual and its leave-one-out error (the residual when the transform is fitted without it), so
    that a bad pick stands out: the paper's rough registration."""

    @dataclass
    class Params:
        max_residual: Optional[float] = None
        """Fail when a landmark's leave-one-out error exceeds this (see ``distances``); null: only report."""
        distances: Distances = Distances.absolute
        """Unit of ``max_residual``: input units (default) or multiples of the sampling spacing."""


    def align(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext,
              landmarks: Optional[tuple[np.ndarray, np.ndarray]] = None) -> CoarseResult:
        lm = landmarks
        if lm is None:
            raise ConfigError("coarse=landmarks: no landmark pairs; give data.landmarks=FILE.csv "
                              "(rows: target x,y,z, source x,y,z)")
        T, metrics, loo = landmark_fit(lm[0], lm[1])
        histories = {"landmark_residual": metrics.pop("_residuals"), "landmark_loo_error": loo.tolist()}
        lim = to_abs(self.p.max_residual, self.p.distances, spacing)
        if lim is not None and loo.max() > lim:
            i = int(np.argmax(loo))
            raise StageError(f"coarse=landmarks: landmark {i + 1} has a leave-one-out error of {loo[i]:.4g} "
                             f"(limit {lim:.4g}): probably picked wrongly", metrics=metrics)
        return CoarseResult(T, metrics, histories=histories)


def landmark_fit(target_pts: np.ndarray, source_pts: np.ndarray) -> tuple[np.ndarray, dict, np.ndarray]:
    """Horn's fit of landmark pairs with per-landmark residuals and leave-one-out errors."""
    k = len(target_pts)
    centred = source_pts - source_pts.mean(axis=0)
    if k < 3 or np.linalg.matrix_rank(centred, tol=1e-9 * max(1.0, np.abs(centred).max())) < 2:
        raise StageError(f"coarse=landmarks: {k} landmark pair(s) that are collinear or coincide; need at "
                         "least 3 non-collinear pairs")
    T = horn_quaternion(target_pts, source_pts)
    res = np.linalg.norm(apply_T(T, source_pts) - target_pts, axis=1)
    loo = np.full(k, np.nan)
    if k >= 4:
        for i in range(k):
            keep = np.arange(k) != i
            Ti = horn_quaternion(target_pts[keep], source_pts[keep])
            loo[i] = np.linalg.norm(apply_T(Ti, source_pts[i:i + 1]) - target_pts[i:i + 1])
    metrics = {"landmark_count": k, "landmark_rms": float(np.sqrt(np.mean(res ** 2))),
               "landmark_residual_max": float(res.max()), "_residuals": res.tolist()}
    if k >= 4:
        metrics["landmark_loo_max"] = float(np.nanmax(loo))
    return T, metrics, np.nan_to_num(loo, nan=0.0)
