"""What the pairwise stages (coarse and fine) share about a pair of clouds: its spacing, measured as the runner
measures a run's, and a large pair thinned to a seeded random subset with the spacing measured again on it."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Cloud, estimate_spacing
from scanreg.types import RunContext


def pair_spacing(target_points: np.ndarray, source_points: np.ndarray, ctx: RunContext) -> float:
    """The spacing of a pair of clouds as the runner measures a run's: the larger of the two median
    nearest-neighbour distances, each estimated with the run's seeded generators (``ctx.rng(1)``, ``ctx.rng(2)``)."""
    return max(estimate_spacing(target_points, ctx.rng(1)), estimate_spacing(source_points, ctx.rng(2)))


def thinned_pair(target: Cloud, source: Cloud, spacing: float, max_points: int, ctx: RunContext, salt: int,
                 thin_target: bool = True) -> tuple[Cloud, Cloud, float]:
    """Both clouds thinned to at most ``max_points`` points (:meth:`scanreg.geometry.Cloud.thinned`, drawn with
    ``ctx.rng(salt)`` for the target and ``ctx.rng(salt + 1)`` for the source; the target kept whole unless
    ``thin_target``) and the pair's spacing measured on the clouds the stage then works on (:func:`pair_spacing`):
    a thinned cloud's points lie farther apart, and every distance a stage takes in spacings scales with it. The
    clouds and ``spacing`` as given when neither is larger."""
    t = target.thinned(max_points, ctx.rng(salt)) if thin_target else target
    s = source.thinned(max_points, ctx.rng(salt + 1))
    if t is target and s is source:
        return target, source, spacing
    thinned = pair_spacing(t.points, s.points, ctx)
    return t, s, thinned if thinned > 0 else spacing
