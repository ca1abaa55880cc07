"""The intervals beside every number of a report: bootstrap and interquartile intervals of a median, Wilson
intervals of a rate."""

from __future__ import annotations

import numpy as np

CI_LEVEL = 0.95
"""Confidence level of every interval in the reports."""


BOOTSTRAP_RESAMPLES = 2000
"""Resamples of the bootstrap percentile interval of a median (seeded: a report is reproducible)."""


def bootstrap_median_ci(x, level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
                        seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the median of ``x`` (NaNs dropped): the ``(1 - level) / 2`` and
    ``(1 + level) / 2`` quantiles of the medians of ``resamples`` resamples with replacement (seeded). One value:
    that value twice; none: NaN twice."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    if len(x) == 1 or np.all(x == x[0]):
        return float(x[0]), float(x[0])
    idx = np.random.default_rng(seed).integers(0, len(x), size=(resamples, len(x)))
    med = np.median(x[idx], axis=1)
    lo, hi = np.quantile(med, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def iqr_interval(x) -> tuple[float, float]:
    """The interquartile range of ``x`` (NaNs dropped): its 25th and 75th percentiles (linear interpolation)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    lo, hi = np.quantile(x, [0.25, 0.75])
    return float(lo), float(hi)


def wilson_interval(k: float, n: int, level: float = CI_LEVEL) -> tuple[float, float]:
    """Wilson score interval of a success rate ``k / n`` at ``level`` (z = 1.96 for 95 %): centre
    ``(p + z^2 / 2n) / (1 + z^2 / n)``, half-width ``z sqrt(p (1 - p) / n + z^2 / 4n^2) / (1 + z^2 / n)``.
    No runs: NaN twice."""
    from statistics import NormalDist

    if n <= 0:
        return float("nan"), float("nan")
    z = NormalDist().inv_cdf((1 + level) / 2)
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def interval(x, how: str = "bootstrap") -> tuple[float, float]:
    """The interval of the median of ``x`` named by ``how`` (``bootstrap`` or ``iqr``)."""
    if how == "bootstrap":
        return bootstrap_median_ci(x)
    if how == "iqr":
        return iqr_interval(x)
    raise ValueError(f"report.interval must be bootstrap or iqr, got '{how}'")


def interval_name(how: str) -> str:
    return "95 % bootstrap CI of the median" if how == "bootstrap" else "interquartile range"
