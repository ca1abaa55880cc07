"""Evaluation of a registration: one definition of every reported number."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from scanreg.config import Distances, to_abs
from scanreg.geometry import transform_errors


@dataclass
class EvalParams:
    inlier_distance: float = 3.0
    """A source point is an inlier when its closest target point, after alignment, lies within this distance
    (see ``distances``). ``fitness`` is the share of inliers, ``rms`` the RMS of their distances."""
    distances: Distances = Distances.spacing
    """Unit of ``inlier_distance``: multiples of the sampling spacing, or absolute input units."""
    success_rotation_deg: float = 2.0
    """A run with ground truth succeeds when its rotation error is below this (degrees) ..."""
    success_translation: float = 0.01
    """... and its translation error below this share of the target's bounding-box diagonal."""
    deviation_map: bool = False
    """Also write the deviation map of the aligned source (coloured PLY, histogram, picture) and log its
    statistics ``dev_*`` overall and per part of the target (see pipeline/deviation.py)."""
    deviation_range: float = 0.1
    """Colour-map range: deviations beyond ± this saturate (input units: 0.1 = 100 µm for mm data)."""
    deviation_max_distance: Optional[float] = 0.5
    """Source points farther than this from the target are not compared (input units; e.g. the gum of a cast
    that the CT lacks); null: every point."""
    deviation_max_angle_deg: Optional[float] = 60.0
    """Source points whose normal differs from the target's by more than this are not compared (degrees);
    null: no normal test."""
    deviation_bands: list[float] = field(default_factory=lambda: [0.05, 0.1])
    """Report the share of compared points within ± each of these (input units)."""
    deviation_scale: float = 1000.0
    """Display unit per input unit (1000: mm -> µm)."""
    deviation_unit: str = "um"
    """Name of the display unit, used in metric names (``dev_rms_um``) and legends."""
    view_html: bool = True
    """Write ``view3d.html``: one self-contained interactive 3D view (plotly, its JavaScript embedded, opens
    without network) of the target, the source before and after alignment coloured by deviation, and the
    per-part table (see pipeline/view3d.py)."""
    view_max_points: int = 40000
    """At most this many points per shown surface in ``view3d.html`` (seeded subsample; keeps it a few MB)."""
    pose_uncertainty: bool = True
    """Log the pose covariance of the final transform from the fine stage's point-to-plane normal equations at
    the final pairs (``pose_sigma_rot_deg`` in degrees, ``pose_sigma_trans`` in input units, ``pose_condition``
    dimensionless; see pipeline/uncertainty.py) and, with ``deviation_map``, each compared point's deviation
    uncertainty. Needs target normals (a mesh target, or a cloud with normals)."""
    pose_condition_warn: float = 1.0e-3
    """Warn (one line naming the free motions) when ``pose_condition`` (smallest over largest eigenvalue of the
    scaled information matrix, dimensionless) is below this."""
    pose_bootstrap: int = 0
    """Number of bootstrap re-registrations (the fine stage rerun from the final pose on the source points
    resampled with replacement, seeded) whose RMS spread is logged as ``pose_bootstrap_rot_deg`` (degrees) and
    ``pose_bootstrap_trans`` (input units) beside the analytic sigmas; 0: none (each costs one fine stage)."""
    deviation_tolerance: float = 0.05
    """Tolerance on |signed deviation| (input units; 0.05 = 50 µm for mm data): ``dev_over_<tol><unit>_share`` is
    the share of compared points beyond it, ``dev_over_<tol><unit>_sure_share`` the share beyond it with
    ``deviation_confidence`` given the pose uncertainty (|deviation| - z sigma > tolerance)."""
    deviation_confidence: float = 0.95
    """One-sided confidence (0..1) of the ``_sure_share`` above (0.95: z = 1.645)."""

    def check(self):
        if not 0.5 <= self.deviation_confidence < 1:
            raise ValueError(f"deviation_confidence must be in [0.5, 1), got {self.deviation_confidence}")
        if self.pose_bootstrap < 0:
            raise ValueError(f"pose_bootstrap must be >= 0, got {self.pose_bootstrap}")
        if not self.pose_condition_warn >= 0:
            raise ValueError(f"pose_condition_warn must be >= 0, got {self.pose_condition_warn}")


def estimate_spacing(points: np.ndarray, rng: np.random.Generator, n: int = 5000) -> float:
    """Median distance from a point to its nearest other point (over a seeded subset of at most ``n``)."""
    idx = rng.choice(len(points), size=min(n, len(points)), replace=False) if len(points) > n else np.arange(len(points))
    d, _ = cKDTree(points).query(points[idx], k=2, workers=-1)
    d = d[:, 1]
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.0


def alignment_metrics(distances: np.ndarray, p: EvalParams, spacing: float) -> dict[str, float]:
    """``rms`` and ``fitness`` (see :class:`EvalParams`) plus the mean distance over all points, from the
    distances of the aligned source points to their closest target points."""
    inl = distances <= to_abs(p.inlier_distance, p.distances, spacing)
    return {
        "rms": float(np.sqrt(np.mean(distances[inl] ** 2))) if inl.any() else float("nan"),
        "fitness": float(inl.mean()),
        "mean_distance": float(distances.mean()),
    }


def gt_metrics(T: np.ndarray, T_gt: np.ndarray, diagonal: float, p: EvalParams, prefix: str = "") -> dict[str, float]:
    rot, trans = transform_errors(T, T_gt)
    out = {
        f"{prefix}rotation_error_deg": rot,
        f"{prefix}translation_error": trans,
        f"{prefix}translation_error_rel": trans / diagonal,
    }
    if not prefix:
        out["success"] = float(rot < p.success_rotation_deg and trans < p.success_translation * diagonal)
    return out


def surface_deviation(aligned: np.ndarray, closest: tuple, p: EvalParams, spacing: float) -> dict[str, float]:
    """Point-to-surface distances of the aligned source points to the target, over the inliers (distance
    within ``inlier_distance``), in input units.

    ``closest`` is what :class:`scanreg.closest.ClosestPoints` returns for ``aligned``: closest points on the target
    mesh's triangles when the target is a mesh, else the nearest target points, their distances, and the
    target normals there. Distances are signed (positive outside, along the outward normal) when normals are
    known: a mesh, whose orientation the repair made coherent, or a cloud with normals; ``p2s_signed`` is then
    1. Reported: ``p2s_mean`` and ``p2s_median`` (signed when available), ``p2s_rms``, ``p2s_p95_abs``,
    ``p2s_max_abs``.
    """
    q, d, n = closest
    signed = n is not None
    if signed:
        d = np.where(np.einsum("ij,ij->i", aligned - q, n) < 0, -d, d)
    a = np.abs(d)
    inl = a <= to_abs(p.inlier_distance, p.distances, spacing)
    if not inl.any():
        return {"p2s_signed": float(signed)}
    d, a = d[inl], a[inl]
    return {
        "p2s_mean": float(d.mean()),
        "p2s_median": float(np.median(d)),
        "p2s_rms": float(np.sqrt(np.mean(a ** 2))),
        "p2s_p95_abs": float(np.quantile(a, 0.95)),
        "p2s_max_abs": float(a.max()),
        "p2s_signed": float(signed),
    }
