"""Evaluation of a registration: one definition of every reported number."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from scanreg.eval.checks import UNIT_FACTORS, likely_units
from scanreg.geometry import ClosestPoints, Cloud, apply_T, invert_T, transform_errors
from scanreg.types import CoarseTrace, Distances, to_abs


DISPLAY_UNITS = {"m": (1000.0, "mm"), "cm": (10.0, "mm"), "mm": (1000.0, "um"), "um": (1.0, "um")}
"""Input unit -> (display unit per input unit, display unit) of the deviations."""
METRES_PER_UNIT = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6}
"""The metric ``input_unit_m``: metres per input unit."""


def input_unit_name(metres_per_unit) -> str | None:
    """The input unit the metric ``input_unit_m`` (metres per input unit) says, as written for people (``µm``,
    :func:`~scanreg.eval.deviation.display_unit`); None for a value that names none."""
    from scanreg.eval.deviation import display_unit

    unit = {v: k for k, v in METRES_PER_UNIT.items()}.get(metres_per_unit)
    return None if unit is None else display_unit(unit)


def unit_metrics(p: EvalParams, size: float | None) -> dict[str, float]:
    """What a run's lengths are in: ``input_unit_m`` (metres per input unit, ``p.units`` or with ``auto`` the
    guess for a target or model ``size`` across, :meth:`EvalParams.shown`) and ``input_unit_guessed`` (1 when
    guessed)."""
    return {"input_unit_m": METRES_PER_UNIT[p.shown(size).units], "input_unit_guessed": float(p.units == "auto")}


METRES_BELOW = 5.0
"""``units=auto``: a target whose size (its diagonal across, along its principal axes) is below this is taken to be
in metres."""


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
    deviation_range: Optional[float] = None
    """Colour-map range of the deviation map and the 3D view: deviations beyond ± this saturate (input units:
    0.1 = 100 µm for mm data); null: from the data, the 95th percentile of the compared points' |deviation|
    rounded up to a readable step (:func:`scanreg.eval.deviation.colour_range`), named in the view's title."""
    deviation_max_distance: Optional[float] = 0.5
    """Source points farther than this from the target are not compared (input units; e.g. the gum of a cast
    that the CT lacks); null: every point."""
    deviation_max_angle_deg: Optional[float] = 60.0
    """Source points whose normal differs from the target's by more than this are not compared (degrees);
    null: no normal test."""
    deviation_bands: list[float] = field(default_factory=lambda: [0.05, 0.1])
    """Report the share of compared points within ± each of these (input units)."""
    units: str = "auto"
    """Length unit of the input files (``m``, ``cm``, ``mm``, ``um``), which sets the unit deviations are shown
    in: mm for m and cm input, µm for mm and µm input. ``auto``: guessed from the target's bounding-box diagonal
    (below 5: metres, as no scan is 5 mm across; else millimetres), the guess named in the 3D view's title."""
    deviation_scale: Optional[float] = None
    """Display unit per input unit, set together with ``deviation_unit``; null: from ``units`` (1000 for
    m -> mm and for mm -> µm)."""
    deviation_unit: Optional[str] = None
    """Name of the display unit, used in metric names (``dev_rms_um``) and legends, set together with
    ``deviation_scale``; null: from ``units``."""
    max_points: int = 200000
    """The ground-truth metrics over the source's points (``overlap_share_gt``, ``gt_rmse``, ``coarse_gt_rmse``)
    are measured on a random subset of at most this many of them, drawn with the run's seed: a share's standard
    error is then at most 0.5 / sqrt(n) (0.0011 at 200 000), and an RMS over the overlap moves by far less than
    its own size. The fit's numbers (``rms``, ``fitness``, ``p2s_*``, maxima included) and the deviation map use
    every point. 0: every point."""
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
    fitness_warn: float = 0.25
    """Warn (one line) when ``fitness`` is below this share (0..1; 0: never): so little of the source lies on
    the target after alignment that, unless the scans overlap that little, the registration failed; and at so
    little overlap a wrong pose can fit as well as the right one (Stanford bunny pairs at 15-18 % overlap came
    out 3-179 deg off at fitness 0.13-0.21, silently under the former 0.1)."""
    spacing_ratio_warn: float = 4.0
    """Warn (one line) when one scan's spacing is more than this many times the other's (0: never). The pair is
    registered and measured at the sparser scan's spacing, so that its fitness says little of the denser scan
    (51 points of a bunny scan onto its 40 000 came out 133 deg off at fitness 0.78). Up to 4 (16 times the
    points) the coarse stage compares like with like (density-ratio robustness experiments: 8 times the points
    succeed)."""
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
    repeatability_distance: float = 2.0
    """epsilon of ``keypoint_repeatability`` (see ``distances``): a source keypoint, moved by the true transform,
    is repeatable when a target keypoint lies within this distance (Tombari et al. 2013). In spacings it counts
    the spacing of the clouds the detector ran on: those of the coarse stage when it thins the clouds
    (``coarse.voxel``), so that the tolerance follows the keypoints' own resolution."""
    overlap_distance: float = 3.0
    """A source point (or keypoint), moved by the true transform, is in the overlap when a sampled target point
    lies within this distance (see ``distances``); used by ``keypoint_repeatability`` and ``gt_rmse``."""
    match_inlier_distance: float = 8.0
    """tau1 of ``inlier_ratio`` (see ``distances``): a descriptor match is correct when its source point, moved by
    the true transform, lies within this distance of its target point. 3DMatch's 10 cm is 4 voxels of 2.5 cm,
    and 8.3 spacings of the shared 3DMatch pair (median nearest-neighbour distance 1.2 cm): 8 spacings."""
    match_recall_ratio: float = 0.05
    """tau2 of ``feature_match_recall`` (share, 0..1): a pair's matching succeeds when its inlier ratio exceeds
    this (3DMatch: 5 %)."""
    recall_rotation_deg: float = 15.0
    """``registration_recall``: rotation error below this (degrees; 3DMatch: 15) ..."""
    recall_translation: float = 0.07
    """... and translation error below this share of the target's bounding-box diagonal: 3DMatch's 30 cm over
    its fragments' diagonal (4.45 m for the shared 3DMatch pair: 6.7 %), so the rule carries to objects of any
    size and unit. Ignored when ``recall_translation_abs`` is set."""
    recall_translation_abs: Optional[float] = None
    """Absolute translation threshold of ``registration_recall`` (input units, e.g. 0.3 for metric indoor data
    as in 3DMatch); null: ``recall_translation`` times the diagonal."""
    write_keypoints: bool = True
    """Write ``keypoints_target.ply``, ``keypoints_source.ply`` and ``matches.ply`` (coloured; see the documentation's
    Metrics section) when the coarse stage exposes keypoints and matches. Cheap: a few thousand points."""

    def shown(self, diagonal: float | None = None) -> "EvalParams":
        """These parameters with the deviations' display unit settled (``deviation_scale``, ``deviation_unit``,
        ``units`` from ``auto`` to the guess for a target ``diagonal`` across; without one, millimetres)."""
        units = self.units
        if units == "auto":
            units = "m" if diagonal is not None and diagonal < METRES_BELOW else "mm"
        scale, unit = DISPLAY_UNITS[units]
        if self.deviation_scale is not None and self.deviation_unit is not None:
            scale, unit = self.deviation_scale, self.deviation_unit
        return replace(self, units=units, deviation_scale=scale, deviation_unit=unit)

    def check(self):
        if self.units != "auto" and self.units not in DISPLAY_UNITS:
            raise ValueError(f"units must be auto, {', '.join(DISPLAY_UNITS)}; got {self.units!r}")
        if self.deviation_scale is not None and not self.deviation_scale > 0:
            raise ValueError(f"deviation_scale must be > 0 or null, got {self.deviation_scale}")
        if (self.deviation_scale is None) != (self.deviation_unit is None):
            raise ValueError("deviation_scale and deviation_unit go together (both set, e.g. 1000 and um for mm "
                             "input, or both null: from units)")
        if not 0.5 <= self.deviation_confidence < 1:
            raise ValueError(f"deviation_confidence must be in [0.5, 1), got {self.deviation_confidence}")
        if self.max_points != 0 and self.max_points < 1000:
            raise ValueError(f"max_points must be 0 (every point) or >= 1000, got {self.max_points}")
        if self.pose_bootstrap < 0:
            raise ValueError(f"pose_bootstrap must be >= 0, got {self.pose_bootstrap}")
        if not 0 <= self.match_recall_ratio <= 1:
            raise ValueError(f"match_recall_ratio must be in [0, 1], got {self.match_recall_ratio}")
        for name in ("inlier_distance", "success_rotation_deg", "success_translation", "deviation_tolerance",
                     "repeatability_distance", "overlap_distance", "match_inlier_distance", "recall_rotation_deg",
                     "recall_translation"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("deviation_range", "deviation_max_distance", "deviation_max_angle_deg"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 or null, got {getattr(self, name)}")
        if not all(b > 0 for b in self.deviation_bands):
            raise ValueError(f"deviation_bands must all be > 0, got {list(self.deviation_bands)}")
        if self.recall_translation_abs is not None and not self.recall_translation_abs > 0:
            raise ValueError(f"recall_translation_abs must be > 0 or null, got {self.recall_translation_abs}")
        if not 0 <= self.fitness_warn <= 1:
            raise ValueError(f"fitness_warn must be in [0, 1], got {self.fitness_warn}")
        if not self.spacing_ratio_warn >= 0:
            raise ValueError(f"spacing_ratio_warn must be >= 0, got {self.spacing_ratio_warn}")
        if not self.pose_condition_warn >= 0:
            raise ValueError(f"pose_condition_warn must be >= 0, got {self.pose_condition_warn}")


def low_fitness_warning(fitness: float, threshold: float) -> str | None:
    """One line when ``fitness`` (the share of the source on the target after alignment) is below
    ``threshold`` (``evaluate.fitness_warn``), else None."""
    if not fitness < threshold:
        return None
    return (f"only {fitness:.1%} of the source lies on the target after alignment (fitness < evaluate.fitness_warn "
            f"{threshold:g}): unless the scans overlap that little, the registration failed; and at so little "
            "overlap a wrong pose can fit as well as the right one, and its pose_sigma_* be as small (see "
            "view3d.html)")


def sparse_pair_warning(source_spacing: float, target_spacing: float, n_source: int, n_target: int,
                        threshold: float, source_diagonal: float = 0.0, target_diagonal: float = 0.0) -> str | None:
    """One line when one scan's spacing is more than ``threshold`` (``evaluate.spacing_ratio_warn``) times the
    other's, else None. When the sparser scan is also at least :data:`UNITS_HINT_SIZE_RATIO` times as large
    (bounding-box diagonals) and the spacings are a common unit ratio apart, the line says so first: a partial
    scan in cm beside one in mm passes the size check (a crop is smaller) and looks sparser."""
    lo, hi = sorted((source_spacing, target_spacing))
    if not threshold > 0 or not lo > 0 or not hi > threshold * lo:
        return None
    sparse, dense = ("source", "target") if source_spacing > target_spacing else ("target", "source")
    n = n_source if sparse == "source" else n_target
    line = (f"the {sparse} is {hi / lo:.0f}x sparser than the {dense} (spacing {hi:.4g} against {lo:.4g}; {n} "
            f"points): ")
    big, small = (source_diagonal, target_diagonal) if sparse == "source" else (target_diagonal, source_diagonal)
    unit, factor = likely_units(hi / lo)
    if small > 0 and big >= UNITS_HINT_SIZE_RATIO * small and unit in UNIT_FACTORS.values():
        line += (f"it is also {big / small:.3g}x as large, so the two may be in different units (likely {unit}: "
                 f"set data.{sparse}_scale={1 / factor:g}); else ")
    return line + (f"the pair is registered and measured at the sparser scan's spacing, so a high fitness says "
                   f"little and a wrong pose can score well; give the {sparse} more points if it has them (a mesh: "
                   f"sampler.n_points), and check view3d.html (evaluate.spacing_ratio_warn {threshold:g})")


UNITS_HINT_SIZE_RATIO = 3.0
""":func:`sparse_pair_warning` names other units as a likely cause when the sparser scan is at least this many
times as large as the other (a scan of the same object is about as large, or a crop smaller)."""


def alignment_metrics(distances: np.ndarray, p: EvalParams, spacing: float) -> dict[str, float]:
    """``rms`` and ``fitness`` (see :class:`EvalParams`) plus the mean distance over all points, from the
    distances of the aligned source points to their closest target points."""
    inl = distances <= to_abs(p.inlier_distance, p.distances, spacing)
    return {
        "rms": float(np.sqrt(np.mean(distances[inl] ** 2))) if inl.any() else float("nan"),
        "fitness": float(inl.mean()),
        "mean_distance": float(distances.mean()),
    }


def gt_metrics(T: np.ndarray, T_gt: np.ndarray, diagonal: float, p: EvalParams, prefix: str = "",
               at: np.ndarray | None = None) -> dict[str, float]:
    """The errors of ``T`` against the ground truth ``T_gt`` and the success and recall tests on them; the
    translation error is how far the two poses move the point ``at`` apart (the source's centre, where its
    points are: then it does not depend on where the source's frame has its origin; None: the origin)."""
    rot, trans = transform_errors(T, T_gt, at)
    out = {
        f"{prefix}rotation_error_deg": rot,
        f"{prefix}translation_error": trans,
        f"{prefix}translation_error_rel": trans / diagonal,
    }
    if not prefix:
        out["success"] = float(rot < p.success_rotation_deg and trans < p.success_translation * diagonal)
    out[f"{prefix}registration_recall"] = registration_recall(rot, trans, diagonal, p)
    return out


def inverted_gt_warning(T: np.ndarray, T_gt: np.ndarray, m: dict, diagonal: float, p: EvalParams,
                        at: np.ndarray | None = None) -> str | None:
    """One line when a pose that failed against the ground truth (``m``: its :func:`gt_metrics`) passes against
    the ground truth's inverse: the file most likely holds ``T_source_target`` (a user's trial: fitness 1,
    rotation error exactly twice the move, nothing said why)."""
    if m.get("success", 1.0):
        return None
    inv = gt_metrics(T, invert_T(T_gt), diagonal, p, at=at)
    if not inv["success"]:
        return None
    return (f"the pose is {m['rotation_error_deg']:.3g} deg off the ground truth but {inv['rotation_error_deg']:.2g} "
            "deg off its inverse: data.gt seems to hold T_source_target; it must be T_target_source, which maps "
            "source points into the target frame (invert the matrix)")


# ------------------------------------------------------------------------------- the field's registration metrics


def registration_recall(rotation_error_deg: float, translation_error: float, diagonal: float, p: EvalParams) -> float:
    """1.0 when the pose is within 3DMatch's thresholds (Zeng et al. 2017; RRE/RTE form of Huang et al. 2021, whose
    RTE is measured at the fragment's frame origin, ours at the source's centre, :func:`gt_metrics`):
    rotation error below ``recall_rotation_deg`` and translation error (input units) below
    ``recall_translation_abs``, or when that is null below ``recall_translation`` times ``diagonal``; else 0.0."""
    lim = p.recall_translation_abs if p.recall_translation_abs is not None else p.recall_translation * diagonal
    return float(rotation_error_deg < p.recall_rotation_deg and translation_error < lim)


def overlap_mask(points: np.ndarray, target_points: np.ndarray, T_gt: np.ndarray, radius: float,
                 search: ClosestPoints | None = None) -> np.ndarray:
    """Which of ``points`` (source frame) lie, after ``T_gt``, within ``radius`` of some ``target_points``
    (``search``: the closest-point search on them, when the caller has one)."""
    if not len(points) or not len(target_points):
        return np.zeros(len(points), bool)
    bound = np.nextafter(radius, np.inf)
    if search is not None:
        d = search(apply_T(T_gt, points), bound)[1]
    else:
        d, _ = cKDTree(target_points).query(apply_T(T_gt, points), distance_upper_bound=bound)
    return d <= radius


@dataclass
class Repeatability:
    """Keypoint repeatability of one pair and the per-keypoint masks behind it."""

    repeatability: float
    """Repeatable source keypoints over source keypoints in the overlap (NaN when none is in it)."""
    source_in_overlap: np.ndarray
    """Per source keypoint: moved by the true transform, it lies within the overlap radius of the target."""
    source_repeatable: np.ndarray
    """Per source keypoint: in the overlap and a target keypoint lies within epsilon of it."""
    target_repeatable: np.ndarray
    """Per target keypoint: a source keypoint of the overlap, moved by the true transform, lies within epsilon."""

    def metrics(self, prefix: str = "") -> dict[str, float]:
        return {f"{prefix}keypoint_repeatability": self.repeatability,
                f"{prefix}n_keypoints_overlap": int(self.source_in_overlap.sum()),
                f"{prefix}n_keypoints_repeatable": int(self.source_repeatable.sum())}


def keypoint_repeatability(kp_target: np.ndarray, kp_source: np.ndarray, T_gt: np.ndarray, eps: float,
                           overlap_radius: float, target_points: np.ndarray | None = None,
                           target_search: ClosestPoints | None = None) -> Repeatability:
    """Relative repeatability of Tombari et al. 2013 (IJCV, "Performance evaluation of 3D keypoint detectors").

    ``kp_target`` (K, 3) and ``kp_source`` (L, 3) are keypoint positions in their own frames, ``T_gt`` the true
    ``T_target_source``. A source keypoint is *in the overlap* when, moved by ``T_gt``, it lies within
    ``overlap_radius`` of a point of ``target_points`` (the sampled target cloud; the target keypoints when not
    given). It is *repeatable* when it is in the overlap and a target keypoint lies within ``eps`` of it. The
    repeatability is the share of repeatable keypoints among the source keypoints in the overlap (NaN when
    none is). Distances in input units. ``target_search``: the closest-point search on ``target_points``, when
    the caller has one."""
    kp_target, kp_source = np.asarray(kp_target, float).reshape(-1, 3), np.asarray(kp_source, float).reshape(-1, 3)
    ref = kp_target if target_points is None else target_points
    inside = overlap_mask(kp_source, ref, T_gt, overlap_radius, target_search if target_points is not None else None)
    rep = np.zeros(len(kp_source), bool)
    trep = np.zeros(len(kp_target), bool)
    if len(kp_target) and inside.any():
        moved = apply_T(T_gt, kp_source[inside])
        d, _ = cKDTree(kp_target).query(moved, distance_upper_bound=np.nextafter(eps, np.inf))
        rep[np.flatnonzero(inside)] = d <= eps
        d, _ = cKDTree(moved).query(kp_target, distance_upper_bound=np.nextafter(eps, np.inf))
        trep = d <= eps
    ratio = float(rep.sum() / inside.sum()) if inside.any() else float("nan")
    return Repeatability(ratio, inside, rep, trep)


def match_inliers(P_target: np.ndarray, P_source: np.ndarray, T_gt: np.ndarray, tau1: float) -> np.ndarray:
    """Per match (row of ``P_target`` (M, 3) and ``P_source`` (M, 3)): the source point moved by ``T_gt`` lies
    within ``tau1`` (input units) of its target point."""
    P_target, P_source = np.asarray(P_target, float).reshape(-1, 3), np.asarray(P_source, float).reshape(-1, 3)
    if not len(P_source):
        return np.zeros(0, bool)
    return np.linalg.norm(apply_T(T_gt, P_source) - P_target, axis=1) <= tau1


def inlier_ratio(P_target: np.ndarray, P_source: np.ndarray, T_gt: np.ndarray, tau1: float) -> float:
    """Share of descriptor matches (before any RANSAC) that are correct under the true transform: the source
    point moved by ``T_gt`` lies within ``tau1`` of its target point (Choy et al. 2019, Huang et al. 2021).
    NaN without matches."""
    inl = match_inliers(P_target, P_source, T_gt, tau1)
    return float(inl.mean()) if len(inl) else float("nan")


def feature_match_recall(ratio: float, tau2: float = 0.05) -> float:
    """3DMatch's feature-match recall of one pair (Deng et al. 2018, Choy et al. 2019): 1.0 when the inlier
    ratio exceeds ``tau2``, else 0.0 (NaN when the ratio is)."""
    return float("nan") if np.isnan(ratio) else float(ratio > tau2)


def gt_rmse(T: np.ndarray, T_gt: np.ndarray, source_points: np.ndarray, in_overlap: np.ndarray | None = None) -> float:
    """RMSE of the ground-truth correspondences (3DMatch, Zeng et al. 2017): over the source points in the
    overlap (``in_overlap``; all when None), the RMS distance between each point moved by ``T`` and the same
    point moved by ``T_gt`` (input units; NaN when no point is in the overlap)."""
    pts = np.asarray(source_points, float).reshape(-1, 3)
    if in_overlap is not None:
        pts = pts[in_overlap]
    if not len(pts):
        return float("nan")
    r = apply_T(T, pts) - apply_T(T_gt, pts)
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", r, r))))


def field_metrics(trace: CoarseTrace | None, T0: np.ndarray, T: np.ndarray, T_gt: np.ndarray,
                  source_points: np.ndarray, target_points: np.ndarray, p: EvalParams,
                  spacing: float, search: ClosestPoints | None = None) -> tuple[dict[str, float], dict]:
    """The field's metrics of one run with ground truth, and the per-keypoint / per-match masks for the PLYs
    (``search``: the closest-point search on ``target_points``, when the caller has one; else one is built).

    ``trace`` is what the coarse stage exposes (:class:`~scanreg.types.CoarseTrace`): keypoints, descriptor
    matches, RANSAC's inliers; any may be missing, and the metrics that need it are then absent. ``gt_rmse`` and
    ``coarse_gt_rmse`` are always given."""
    to = lambda v: to_abs(v, p.distances, spacing)
    if search is None and len(target_points):
        search = ClosestPoints(Cloud(target_points))  # one search for both overlap tests
    inside = overlap_mask(source_points, target_points, T_gt, to(p.overlap_distance), search)
    out = {"gt_rmse": gt_rmse(T, T_gt, source_points, inside), "coarse_gt_rmse": gt_rmse(T0, T_gt, source_points, inside),
           "overlap_share_gt": float(inside.mean())}
    masks: dict = {}
    trace = trace or CoarseTrace()
    kt, ks = trace.keypoints_target, trace.keypoints_source
    if kt is not None and ks is not None:
        out["n_keypoints_target"], out["n_keypoints_source"] = len(kt), len(ks)
        eps = to_abs(p.repeatability_distance, p.distances, spacing if trace.spacing is None else trace.spacing)  # the detector's
        rep = keypoint_repeatability(kt, ks, T_gt, eps, to(p.overlap_distance), target_points, search)
        out.update(rep.metrics())
        masks["repeatability"] = rep
    P0, P1 = trace.matches_target, trace.matches_source
    if P0 is not None and P1 is not None:
        inl = match_inliers(P0, P1, T_gt, to(p.match_inlier_distance))
        ratio = float(inl.mean()) if len(inl) else float("nan")
        out["n_matches"] = len(inl)
        out["inlier_ratio"] = ratio
        out["feature_match_recall"] = feature_match_recall(ratio, p.match_recall_ratio)
        masks["match_inliers"] = inl
        acc = trace.ransac_inliers
        if acc is not None and len(acc) == len(inl) and acc.any():  # how many of the accepted matches are right
            out["ransac_inlier_precision"] = float(inl[acc].mean())
    return out, masks


def surface_deviation(aligned: np.ndarray, closest: tuple, p: EvalParams, spacing: float) -> dict[str, float]:
    """Point-to-surface distances of the aligned source points to the target, over the inliers (distance
    within ``inlier_distance``), in input units.

    ``closest`` is what :class:`scanreg.geometry.ClosestPoints` returns for ``aligned``: closest points on the target
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
