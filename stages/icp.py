"""Fine registration (ICP variants)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from pipeline.config import Context, Distances, to_abs
from pipeline.errors import StageError
from pipeline.geometry import Cloud, apply_T, horn_quaternion
from pipeline.registry import ICP


@dataclass
class IcpResult:
    T_target_source: np.ndarray
    iterations: int
    """Number of transform updates made."""
    rms_history: list[float]
    """RMS closest-point distance of the pairs used, before each update and after the last one."""
    converged: bool


@ICP.register("horn")
class Horn:
    """Besl-McKay point-to-point ICP: closest target point for every source point, the rigid transform by
    Horn's quaternion closed form, until the RMS error changes by less than ``tau``."""

    @dataclass
    class Params:
        max_iterations: int = 100
        """Maximum number of iterations."""
        tau: float = 1e-4
        """Stop when the RMS error changes by less than this between iterations (see ``distances``)."""
        max_correspondence_distance: Optional[float] = None
        """Pairs farther apart are ignored (see ``distances``); null keeps every pair (pure Besl-McKay, whose
        RMS never increases)."""
        distances: Distances = Distances.spacing
        """Unit of ``tau`` and ``max_correspondence_distance``: multiples of the sampling spacing, or absolute
        input units."""

        def check(self):
            if self.max_iterations < 1:
                raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
            if not self.tau >= 0:
                raise ValueError(f"tau must be >= 0, got {self.tau}")

    def __init__(self, params: Params):
        self.p = params

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        p = self.p
        tau = to_abs(p.tau, p.distances, ctx.spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, ctx.spacing)
        tree = cKDTree(target.points)
        src = source.points
        T = T_init.copy()
        history: list[float] = []
        converged = False
        iterations = 0
        for it in range(p.max_iterations + 1):
            moved = apply_T(T, src)
            d, j = tree.query(moved, distance_upper_bound=np.inf if maxd is None else maxd, workers=-1)
            ok = np.isfinite(d)
            if ok.sum() < 3:
                raise StageError(
                    f"icp=horn: only {int(ok.sum())} source point(s) within max_correspondence_distance "
                    f"{maxd:g} of the target at iteration {it}; the coarse alignment is too far off or the "
                    "distance too small"
                )
            history.append(float(np.sqrt(np.mean(d[ok] ** 2))))
            if it > 0 and abs(history[-2] - history[-1]) < tau:
                converged = True
                break
            if it == p.max_iterations:
                break
            T = horn_quaternion(target.points[j[ok]], moved[ok]) @ T
            iterations += 1
        ctx.step_metrics["icp_rms"] = history
        return IcpResult(T, iterations, history, converged)
