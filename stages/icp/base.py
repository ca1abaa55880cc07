"""Fine registration (ICP variants).

All variants share one correspondence search (:class:`ClosestPoints`), one set of pair rejections, one pair-limit
schedule, one set of robust kernels and one acceptance test, and report the same numbers, defined once:

- ``rms_history`` (MLflow step metric ``icp_rms_step``): at each iterate, the RMS distance of the pairs used
  (after rejection and trimming, unweighted), before the update; the last entry is at the final pose
  (coarse-to-fine, ``initial_share`` < 1: the subset's iterates, then every point's; always ``iterations`` + 1
  entries);
- ``icp_rms``: the last entry of that history;
- ``icp_fitness``: the share of source points whose closest target point at the kept pose lies within
  ``max_correspondence_distance`` (the final pair limit; every point when it is null);
- ``icp_inlier_rms``: the RMS distance of those points (input units);
- ``icp_points_source``: the source points the stage worked on (at most ``max_points``);
- ``icp_accepted``: 1 when ICP's final pose is kept, 0 when it explained the data worse than the start pose
  (see :meth:`IcpBase.accept`) and the start pose was kept instead;
- ``icp_accept_start_fitness``, ``icp_accept_end_fitness``, ``icp_accept_start_rms``, ``icp_accept_end_rms``
  (input units): that test's numbers, the share of source points within ``accept_distance`` and their RMS
  distance, at the start pose and at ICP's final pose;
- ``icp_pair_limit_start_spacings``, ``icp_pair_limit_end_spacings``: the pair limit at the first and the last
  iterate, in sampling spacings.

The pair limit (``schedule: adaptive``) starts at ``initial_distance`` (a share of the target's diagonal, wide
enough for where a coarse stage, or none, leaves the source) and is halved (``shrink``) each time the fit has
settled at the current limit (RMS change below ``settle`` times the RMS), down to ``max_correspondence_distance``;
the stopping rule (RMS change < ``tau``) applies only once the limit has reached that floor, and compares two RMS
values taken at the same limit.

That schedule finds the end point near a start pose that a coarse stage estimated. Without such an estimate
(``coarse=none``: the inputs' own pose, possibly far off), ``basin: auto`` also searches the widest basin ICP has:
the paper's Besl-McKay loop with every pair (point-to-point; its RMS never increases), then the variant's own
schedule from where that loop ends. Of the two end points, the one that explains clearly more of the source
(:meth:`IcpBase.accept`'s rule, at ``accept_distance``) is kept; on a tie the schedule's own, so that partial
overlap, where every pair pulls the source off, keeps the local end point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.errors import ConfigError, StageError
from scanreg.geometry import (ClosestPoints, Cloud, Mesh, apply_T, bbox_diagonal, half_turns, horn_quaternion,
                              morton_order, rotate_normals)
from scanreg.process import blas_single_thread
from scanreg.stages.pair import thinned_pair
from scanreg.types import Correspondences, Distances, IcpResult, RunContext, to_abs


KERNELS = ("none", "huber", "tukey", "geman_mcclure", "cauchy")

THIN_SALT = 7100
"""Salts of the run's generators (:meth:`~scanreg.types.RunContext.rng`) that draw the points a large target
(this one) and source (the next) are thinned to (``max_points``)."""


def kernel_weights(kernel: str, r: np.ndarray, scale: float) -> np.ndarray | None:
    """IRLS weights of residuals ``r`` (distances >= 0) for an M-estimator with scale ``scale`` (same units);
    None for ``none`` (least squares). Huber: 1 inside the scale, scale/r outside; Tukey's biweight:
    (1 - (r/s)^2)^2 inside, 0 outside; Geman-McClure: 1/(1 + (r/s)^2)^2; Cauchy: 1/(1 + (r/s)^2)."""
    if kernel == "none":
        return None
    x2 = (r / scale) ** 2
    if kernel == "huber":
        return np.where(r <= scale, 1.0, scale / np.maximum(r, 1e-300))
    if kernel == "tukey":
        return np.where(x2 < 1.0, (1.0 - x2) ** 2, 0.0)
    if kernel == "geman_mcclure":
        return 1.0 / (1.0 + x2) ** 2
    if kernel == "cauchy":
        return 1.0 / (1.0 + x2)
    raise ConfigError(f"unknown kernel '{kernel}'; choose one of {', '.join(KERNELS)}")


class PairLimit:
    """The pair-limit schedule of one run: ``limit`` starts at ``start`` and shrinks by ``shrink`` towards
    ``floor`` whenever the fit has settled at the current limit; ``settled`` once it is at the floor. Input
    units. The robust kernel's scale (``kernel_scale`` at the floor) grows in proportion to the limit."""

    def __init__(self, start: float | None, floor: float | None, shrink: float = 0.5, settle: float = 0.01,
                 kernel_scale: float | None = None):
        self.limit, self.floor, self.shrink, self.settle = start, floor, shrink, settle
        self.start = start
        self.kernel_scale = kernel_scale

    def scale(self) -> float:
        """The kernel's scale at the current limit."""
        return self.kernel_scale * (self.limit / self.floor if self.limit and self.floor else 1.0)

    @property
    def settled(self) -> bool:
        return self.limit is None or self.floor is None or self.limit <= self.floor

    def advance(self, prev_rms: float, rms: float, tau: float) -> bool:
        """After an iterate whose RMS is ``rms`` (the previous one, at the same limit, ``prev_rms``): tighten the
        limit when the fit has settled at it. True when the limit changed."""
        if self.settled or abs(prev_rms - rms) >= max(tau, self.settle * prev_rms):
            return False
        self.limit = max(self.floor, self.limit * self.shrink)
        return True


@dataclass
class IcpParams:
    max_iterations: int = 100
    """Maximum number of iterations (transform updates), over all pair limits."""
    tau: float = 1e-4
    """Stop when the RMS error changes by less than this between iterations at the final pair limit (see
    ``distances``). A deliberate deviation from the paper, whose rule is d_k - d_(k+1) < tau on Besl-McKay's
    signed mean-square error: here |rms_(k-1) - rms_k| < tau on the RMS distance of the pairs, measured before
    each update, so that tau is a distance (in spacings or input units, like every other distance) and a rise of
    the RMS (possible with a pair limit or trimming) does not stop the loop (tests/test_paper_equations.py)."""
    max_correspondence_distance: Optional[float] = 3.0
    """Pairs farther apart are ignored at the end (see ``distances``): the final pair limit, the floor of the
    adaptive schedule, and the distance of ``icp_fitness`` and of the acceptance test; null keeps every pair
    throughout (pure Besl-McKay, whose RMS never increases)."""
    schedule: str = "adaptive"
    """``adaptive``: the pair limit starts at ``initial_distance`` and halves each time the fit settles, down to
    ``max_correspondence_distance``; ``fixed``: ``max_correspondence_distance`` throughout."""
    initial_distance: float = 0.05
    """``schedule: adaptive``: the pair limit at the first iterate, as a share of the target's bounding-box
    diagonal (unitless; 0.05 covers about 10 degrees and 2 % of the diagonal off). Never below
    ``max_correspondence_distance``."""
    shrink: float = 0.5
    """``schedule: adaptive``: factor (unitless, in (0, 1)) applied to the pair limit when the fit has settled."""
    settle: float = 0.01
    """``schedule: adaptive``: the fit has settled at a pair limit when the RMS changes by less than this share of
    it (unitless) between iterations (or by less than ``tau``)."""
    kernel: str = "none"
    """Robust kernel (IRLS weights in the solver): ``none`` (least squares), ``huber``, ``tukey``,
    ``geman_mcclure`` or ``cauchy``."""
    kernel_scale: float = 1.0
    """The kernel's scale at the final pair limit (see ``distances``); while the adaptive limit is wider, the
    scale grows in proportion to it."""
    accept: bool = True
    """Keep the start pose when ICP's final pose explains the data worse (a higher truncated least-squares cost
    at ``accept_distance``: points outside it, and the RMS of those within; see :meth:`IcpBase.accept`); logs
    ``icp_accepted``."""
    accept_distance: Optional[float] = None
    """The fixed distance of the acceptance test (see ``distances``): the start and the final pose are compared
    by the share of source points within it and their RMS distance. null: ``max_correspondence_distance`` (the
    final pair limit), or 3 spacings when that is null too."""
    trim: float = 1.0
    """Keep only this share of the pairs, the closest ones, at each iteration (trimmed ICP; 1: keep all).
    Set it to the expected overlap."""
    max_normal_angle_deg: Optional[float] = None
    """Reject pairs whose normals differ by more than this angle (degrees; needs consistently oriented normals
    on both sides, as sampled from meshes); null: no normal test."""
    target: str = "auto"
    """Closest points on the target: ``points`` (nearest target point), ``mesh`` (exact closest point on the
    target's triangles; the target must be a mesh), ``auto`` (mesh when the target is one)."""
    distances: Distances = Distances.spacing
    """Unit of ``tau``, ``max_correspondence_distance``, ``kernel_scale`` and ``accept_distance``: multiples of the sampling spacing,
    or input units."""
    initial_share: float = 1.0
    """Coarse-to-fine: iterate first on this share of the source points (every k-th along a Morton curve, so
    spread evenly) until the stopping rule holds, then on every point until it holds again. The end point is
    full ICP's (its last iterations use every point), reached with fewer full searches. 1: every point
    throughout."""

    basin: str = "auto"
    """Where the end point is searched: ``local`` (the pair-limit schedule from the start pose), ``wide`` (also
    from where the paper's Besl-McKay loop, every pair, point-to-point, takes the start pose; the end point that
    explains clearly more of the source is kept, see the module's docstring), ``auto`` (``wide`` when the start
    pose is the inputs' own, as with ``coarse=none``; ``local`` after a coarse stage's estimate)."""
    basin_points: int = 5000
    """``wide``: the Besl-McKay loop runs on at most this many source points (every k-th along a Morton curve,
    so spread evenly); the variant's schedule then uses every point."""
    half_turns: Optional[float] = 0.9
    """When the pose found keeps at least this share of the source within ``accept_distance`` (unitless: the
    source lies almost entirely on the target), its three half-turns about the source's principal axes through
    its centroid are tried too: each that keeps at least half as large a share unrefined (screened on 1,000 of
    the points, against the target's points) is refined by the variant's schedule, and the end point with the
    lowest truncated least-squares cost (:meth:`IcpBase.accept`'s) is kept when at most half the pose's (a truly
    symmetric shape fits both alike). A nearly symmetric shape (a long bone, a box-like part) fits its half-turned
    pose almost as well as its own, and the coarse stage may find either (a bone moved onto itself: 180 degrees off
    at fitness 0.998 and a quarter spacing RMS, where the truth fits exactly). Logs ``icp_half_turns_refined``
    and ``icp_half_turn`` (1 when one was kept). null: not tried. (Not ``icp=open3d``, Open3D's own loop.)"""
    max_points: int = 200000
    """The stage works on at most this many points of each cloud: a larger cloud is thinned to a seeded uniform
    random subset of this many (:meth:`~scanreg.geometry.Cloud.thinned`) before anything else, its normals and
    k-d tree included; the pairs, ``icp_fitness`` and RMS are then the thinned clouds', and the distances given in
    spacings (``distances``) are in the thinned pair's spacing, measured again. A target whose closest points come
    from its triangles (``target``) is used whole. The pose's statistical error falls
    like one over the square root of the number of pairs; at this count it lies far below what the sampling
    resolves (``experiments/benchmarks/growth.md`` compares the rotation errors). 0: every point."""

    def check(self):
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if not self.tau >= 0:
            raise ValueError(f"tau must be >= 0, got {self.tau}")
        if not 0 < self.initial_share <= 1:
            raise ValueError(f"initial_share must be in (0, 1], got {self.initial_share}")
        if not 0 < self.trim <= 1:
            raise ValueError(f"trim must be in (0, 1], got {self.trim}")
        if self.target not in ("auto", "points", "mesh"):
            raise ValueError(f"target must be auto, points or mesh, got '{self.target}'")
        if self.schedule not in ("adaptive", "fixed"):
            raise ValueError(f"schedule must be adaptive or fixed, got '{self.schedule}'")
        if not self.initial_distance > 0:
            raise ValueError(f"initial_distance must be > 0, got {self.initial_distance}")
        if not 0 < self.shrink < 1:
            raise ValueError(f"shrink must be in (0, 1), got {self.shrink}")
        if self.accept_distance is not None and not self.accept_distance > 0:
            raise ValueError(f"accept_distance must be > 0 or null, got {self.accept_distance}")
        if not 0 <= self.settle < 1:
            raise ValueError(f"settle must be in [0, 1), got {self.settle}")
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got '{self.kernel}'")
        if not self.kernel_scale > 0:
            raise ValueError(f"kernel_scale must be > 0, got {self.kernel_scale}")
        if self.basin not in ("auto", "local", "wide"):
            raise ValueError(f"basin must be auto, local or wide, got '{self.basin}'")
        if self.basin_points < 3:
            raise ValueError(f"basin_points must be >= 3, got {self.basin_points}")
        if self.half_turns is not None and not 0 < self.half_turns <= 1:
            raise ValueError(f"half_turns must be in (0, 1] or null, got {self.half_turns}")
        if self.max_points != 0 and self.max_points < 100:
            raise ValueError(f"max_points must be 0 (every point) or >= 100, got {self.max_points}")


class IcpBase:
    """Shared machinery: correspondence search, pair selection, pair-limit schedule, robust weights, stopping,
    acceptance, final metrics and pairs. A variant supplies its update (:meth:`step` or :meth:`update`), or its
    own :meth:`iterate`."""

    p: IcpParams
    searches_with_closest: bool = True
    """Whether the iterations pair through the search :meth:`refine` hands them (:meth:`closest`): then the last
    iterate's distances, measured at the pose returned, are the acceptance test's at that pose."""

    def __init__(self, params):
        self.p = params

    def closest(self, target: Cloud, mesh: Mesh | None) -> ClosestPoints:
        """The closest-point search the stage pairs with: on the target's triangles (``target: mesh``, or
        ``auto`` with a mesh target), else on its points."""
        if self.p.target == "mesh" and mesh is None:
            raise ConfigError(f"icp={self.name}: icp.target=mesh needs a target mesh, but the target is a point cloud")
        return ClosestPoints(target, mesh if self.p.target in ("mesh", "auto") and mesh is not None else None)

    def working_clouds(self, target: Cloud, source: Cloud, spacing: float, target_mesh: Mesh | None,
                       ctx: RunContext) -> tuple[Cloud, Cloud, float]:
        """The clouds the stage works on and their spacing: each thinned to at most ``max_points`` points
        (:func:`~scanreg.stages.pair.thinned_pair`, seeded by the run); the target whole when its closest points
        come from ``target_mesh``'s triangles."""
        whole_target = target_mesh is not None and self.p.target != "points"
        return thinned_pair(target, source, spacing, self.p.max_points, ctx, THIN_SALT, thin_target=not whole_target)

    def prepared_target(self, target: Cloud, target_mesh: Mesh | None) -> Cloud:
        """The (thinned) target cloud as the variant needs it, e.g. with normals; as it is by default."""
        return target

    def pairs(self, moved: np.ndarray, moved_normals, cp: ClosestPoints, maxd: float | None, it: int):
        """Closest points of ``moved`` and the mask of pairs kept."""
        q, d, qn = cp(moved, maxd)
        return q, d, qn, self.select(d, moved_normals, qn, maxd, it)

    def kept(self, d, moved_normals, qn, maxd: float | None) -> np.ndarray:
        """The mask of pairs kept: within ``maxd``, normals agreeing, trimmed."""
        ok = np.ones(len(d), bool) if maxd is None else d <= maxd
        if self.p.max_normal_angle_deg is not None and moved_normals is not None and qn is not None:
            ok &= np.einsum("ij,ij->i", moved_normals, qn) >= math.cos(math.radians(self.p.max_normal_angle_deg))
        if self.p.trim < 1.0 and ok.sum() > 3:
            keep = max(3, int(math.ceil(self.p.trim * ok.sum())))
            thr = np.partition(d[ok], keep - 1)[keep - 1]
            ok &= d <= thr
        return ok

    def select(self, d, moved_normals, qn, maxd: float | None, it: int) -> np.ndarray:
        """:meth:`kept`, and a :class:`StageError` when fewer than 3 pairs are."""
        ok = self.kept(d, moved_normals, qn, maxd)
        if ok.sum() < 3:
            raise StageError(
                f"icp={self.name}: only {int(ok.sum())} source point(s) paired with the target at iteration {it} "
                f"(pair limit {f'{maxd:.4g}' if maxd is not None else 'none'}); the coarse alignment is too far off "
                "or the distance too small"
            )
        return ok

    def weights(self, d_ok: np.ndarray, limit: PairLimit) -> np.ndarray | None:
        """IRLS weights of the kept pairs' distances (None: least squares); the kernel scale grows with the
        adaptive pair limit."""
        if self.p.kernel == "none":
            return None
        s = limit.scale()
        w = kernel_weights(self.p.kernel, d_ok, s)
        if not w.sum() > 0 or np.count_nonzero(w) < 3:
            raise StageError(f"icp={self.name}: fewer than 3 pairs inside the {self.p.kernel} kernel's scale "
                             f"{s:.4g}; raise icp.kernel_scale")
        return w

    def final_metrics(self, d: np.ndarray, maxd) -> dict:
        inl = np.ones(len(d), bool) if maxd is None else d <= maxd
        return {
            "icp_fitness": float(inl.mean()),
            "icp_inlier_rms": float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("nan"),
        }

    def schedule(self, target: Cloud, maxd: float | None, kernel_scale: float | None) -> PairLimit:
        p = self.p
        if p.schedule == "fixed" or maxd is None:
            return PairLimit(maxd, maxd, kernel_scale=kernel_scale)
        start = max(maxd, p.initial_distance * bbox_diagonal(target.points))
        return PairLimit(start, maxd, p.shrink, p.settle, kernel_scale)

    def refine(self, target: Cloud, source: Cloud, T_init: np.ndarray, spacing: float, ctx: RunContext,
               target_mesh: Mesh | None = None, start_is_estimate: bool = True) -> IcpResult:
        p = self.p
        target, source, spacing = self.working_clouds(target, source, spacing, target_mesh, ctx)
        target = self.prepared_target(target, target_mesh)
        tau = to_abs(p.tau, p.distances, spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, spacing)
        kscale = to_abs(p.kernel_scale, p.distances, spacing)
        cp = self.closest(target, target_mesh)
        order = morton_order(source.points)  # queries in Morton order; the result does not depend on the order
        moving = source.subset(order)
        start_limit = self.schedule(target, maxd, kscale).limit
        with blas_single_thread():  # the acceptance test's and final pairs' products too
            try:
                res = self.converge(target, moving, T_init, cp, tau, maxd, kscale)
                if p.basin == "wide" or (p.basin == "auto" and not start_is_estimate):
                    res = self.widest(target, moving, T_init, cp, tau, maxd, kscale, spacing, res)
            except (np.linalg.LinAlgError, ValueError) as e:
                raise StageError(f"icp={self.name}: the update failed ({e}); the pairs are degenerate") from e
            res = self.finish(res, cp, moving, T_init, maxd, start_limit, spacing, source)
            if p.half_turns is not None:
                res = self.half_turned(res, target, moving, source, cp, tau, maxd, kscale, spacing, start_limit)
            return res

    def half_turned(self, res: IcpResult, target: Cloud, moving: Cloud, source: Cloud, cp: ClosestPoints,
                    tau: float, maxd: float | None, kscale: float | None, spacing: float,
                    start_limit: float | None) -> IcpResult:
        """``res`` (:meth:`finish`-ed), or the end point of one of its half-turns (``half_turns``) that explains
        the source clearly better, finished from that half-turn (its iterations, RMS history and acceptance test
        are then the half-turn's refinement's, from the half-turned pose). A half-turn whose refinement fails
        (too few pairs) is passed over."""
        acc_d = self.accept_distance(maxd, spacing)
        which = "end" if res.metrics["icp_accepted"] else "start"  # the acceptance test's numbers at the pose kept
        here = {"icp_fitness": res.metrics[f"icp_accept_{which}_fitness"],
                "icp_inlier_rms": res.metrics[f"icp_accept_{which}_rms"]}
        res.metrics.update({"icp_half_turns_refined": 0.0, "icp_half_turn": 0.0})
        if here["icp_fitness"] < self.p.half_turns:
            return res
        # screened on a spread subset, by the target's points (a closest point on a mesh target is slow to find far
        # from its surface)
        few = moving.points[::max(1, -(-len(moving.points) // HALF_TURN_SCREEN_POINTS))]
        near = cp if cp.mesh is None else ClosestPoints(target)
        best, best_cost, refined = None, truncated_cost(here, acc_d), 0
        for H in half_turns(moving.points):
            T = res.T_target_source @ H
            if self.final_metrics(near(apply_T(T, few), acc_d)[1], acc_d)["icp_fitness"] < 0.5 * here["icp_fitness"]:
                continue  # far from fitting: not a symmetric pose
            refined += 1
            try:
                r = self.converge(target, moving, T, cp, tau, maxd, kscale)
            except (StageError, np.linalg.LinAlgError, ValueError):
                continue
            cost = truncated_cost(self.final_metrics(cp(apply_T(r.T_target_source, moving.points), acc_d)[1], acc_d),
                                  acc_d)
            if cost < HALF_TURN_GAIN * best_cost:
                best, best_cost = (r, T), cost
        if best is not None:
            found = res.metrics
            res = self.finish(best[0], cp, moving, best[1], maxd, start_limit, spacing, source)
            res.metrics = {**found, **res.metrics}  # (what only the first search reports, e.g. icp_basin_wide)
        res.metrics.update({"icp_half_turns_refined": float(refined), "icp_half_turn": float(best is not None)})
        return res

    def converge(self, target: Cloud, moving: Cloud, T_init: np.ndarray, cp: ClosestPoints, tau: float,
                 maxd: float | None, kscale: float | None) -> IcpResult:
        """The pair-limit schedule from ``T_init`` to its end point (coarse-to-fine when ``initial_share`` < 1)."""
        p = self.p
        step = int(round(1.0 / p.initial_share))
        if step > 1 and len(moving.points) >= 3 * step:
            first = self.iterate(target, moving.subset(slice(None, None, step)), T_init, cp, tau,
                                 self.schedule(target, maxd, kscale))
            # every point starts where the subset ended, at the subset's final (settled) limit
            res = self.iterate(target, moving, first.T_target_source, cp, tau,
                               PairLimit(maxd, maxd, kernel_scale=kscale))
            return _joined(first, res)
        return self.iterate(target, moving, T_init, cp, tau, self.schedule(target, maxd, kscale))

    def widest(self, target: Cloud, moving: Cloud, T_init: np.ndarray, cp: ClosestPoints, tau: float,
               maxd: float | None, kscale: float | None, spacing: float, local: IcpResult) -> IcpResult:
        """``basin: wide``: Besl-McKay (every pair, Horn's update) from ``T_init`` on at most ``basin_points``
        source points, then :meth:`converge` from there; that end point when it explains clearly more of the
        source than ``local`` (the schedule's from ``T_init``), else ``local``. Metric ``icp_basin_wide``: 1 when
        the wide basin's end point is kept."""
        step = max(1, -(-len(moving.points) // self.p.basin_points))
        basin = besl_mckay(cp, moving.points[::step], T_init, tau, self.p.max_iterations)
        wide = self.converge(target, moving, basin.T_target_source, cp, tau, maxd, kscale)
        acc_d = self.accept_distance(maxd, spacing)
        fit = [self.final_metrics(cp(apply_T(r.T_target_source, moving.points), acc_d)[1], acc_d) for r in (wide, local)]
        kept = local if self.accept(*fit, acc_d) else _joined(basin, wide)  # local unless clearly worse than wide
        kept.metrics["icp_basin_wide"] = float(kept is not local)
        return kept

    def accept_distance(self, maxd: float | None, spacing: float) -> float:
        """The acceptance test's distance (input units): ``accept_distance``, else the final pair limit, else 3
        spacings."""
        if self.p.accept_distance is not None:
            return to_abs(self.p.accept_distance, self.p.distances, spacing)
        return maxd if maxd is not None else 3.0 * spacing

    def finish(self, res: IcpResult, cp: ClosestPoints, moving: Cloud, T_init, maxd, start_limit, spacing: float,
               source: Cloud, pairs_cp: ClosestPoints | None = None) -> IcpResult:
        """Final metrics, the acceptance test against the start pose at ``accept_distance``, and the pairs kept
        at the pose returned (``source``: the source as given, ``moving``: the same points as iterated), found by
        ``pairs_cp`` (default ``cp``)."""
        m = self.final_metrics(res.final_distances, maxd)
        acc_d = self.accept_distance(maxd, spacing)
        m0 = self.final_metrics(cp(apply_T(T_init, moving.points), acc_d)[1], acc_d)
        if acc_d == maxd and self.searches_with_closest:  # the last search's, at the pose returned, bounded by maxd
            m1 = m
        else:
            m1 = self.final_metrics(cp(apply_T(res.T_target_source, moving.points), acc_d)[1], acc_d)
        accepted = self.accept(m0, m1, acc_d) if self.p.accept else True
        if not accepted:
            res.T_target_source = T_init.copy()
            res.final_distances = cp(apply_T(T_init, moving.points), maxd)[1]
            m = self.final_metrics(res.final_distances, maxd)
        res.metrics = {**res.metrics, **m, "icp_accepted": float(accepted),
                       "icp_points_source": float(source.n_points),
                       "icp_accept_start_fitness": m0["icp_fitness"], "icp_accept_end_fitness": m1["icp_fitness"],
                       "icp_accept_start_rms": m0["icp_inlier_rms"], "icp_accept_end_rms": m1["icp_inlier_rms"]}
        if start_limit is not None and spacing > 0:
            res.metrics["icp_pair_limit_start_spacings"] = start_limit / spacing
            res.metrics["icp_pair_limit_end_spacings"] = (res.final_limit or start_limit) / spacing
        res.final_pairs = self.pairs_at(res.T_target_source, source, pairs_cp or cp, maxd)
        return res

    def pairs_at(self, T: np.ndarray, source: Cloud, cp: ClosestPoints, maxd: float | None) -> Correspondences:
        """The pairs the stage keeps with ``source`` at ``T`` (the stage's closest-point search ``cp`` without a
        bound, then its distance, normal and trim rejections at ``maxd``), in ``source``'s order."""
        moved = apply_T(T, source.points)
        q, d, qn = cp(moved)
        mn = rotate_normals(T, source.normals)
        ok = self.kept(d, mn, qn, maxd)
        return Correspondences(moved[ok], q[ok], None if qn is None else qn[ok], d[ok])

    @staticmethod
    def accept(start: dict, end: dict, distance: float) -> bool:
        """Whether ICP's final pose explains the data at least as well as the start pose, both measured at
        ``accept_distance`` (``distance``, input units): by the truncated least-squares cost, the mean over the
        source points of min(d, distance)^2 = f rms^2 + (1 - f) distance^2 (``icp_fitness`` f: the share within
        it, ``icp_inlier_rms``: their RMS). Rejected when ICP's cost is clearly (1 %) higher. The cost weighs a
        point left outside the distance against how tightly the others fit: at low overlap a pose a few degrees
        off can keep a few more points within it, loosely, than the right one."""
        return not truncated_cost(end, distance) > 1.01 * truncated_cost(start, distance)

    def step(self, moved, q, qn, ok, w) -> np.ndarray:  # pragma: no cover - per variant
        raise NotImplementedError

    def iterate(self, target, source, T_init, cp, tau, limit: PairLimit, update=None) -> IcpResult:
        """Plain fixed-point iteration: pairs at T, the next iterate from ``update`` (:meth:`update` unless
        given); the pair limit tightens when the fit settles, and the stopping rule applies at the final
        limit."""
        update = update or self.update
        src = source.points
        sn = source.normals if self.p.max_normal_angle_deg is not None else None
        T = T_init.copy()
        history: list[float] = []
        converged, iterations = False, 0
        for it in range(self.p.max_iterations + 1):
            moved = apply_T(T, src)
            mn = rotate_normals(T, sn)
            q, d, qn, ok = self.pairs(moved, mn, cp, limit.limit, it)
            history.append(_rms(d, ok))
            if it > 0:
                if limit.settled and abs(history[-2] - history[-1]) < tau:
                    converged = True
                    break
                if limit.advance(history[-2], history[-1], tau):  # re-select at the tighter limit
                    ok = self.select(d, mn, qn, limit.limit, it)
                    history[-1] = _rms(d, ok)
            if it == self.p.max_iterations:
                break
            T = update(T, moved, q, qn, ok, self.weights(np.compress(ok, d), limit), limit)
            iterations += 1
        if limit.limit is not None and limit.floor is not None and limit.limit > limit.floor:
            d = np.where(d <= limit.floor, d, np.inf)  # final distances bounded by the final pair limit
        return IcpResult(T, iterations, history, converged, final_distances=d, final_limit=limit.limit)

    def update(self, T, moved, q, qn, ok, w, limit: PairLimit) -> np.ndarray:
        """The next iterate from the current one and its pairs (``w``: IRLS weights of the kept pairs)."""
        return self.step(moved, q, qn, ok, w) @ T


HALF_TURN_SCREEN_POINTS = 1000
"""The half-turns (``half_turns``) are screened on at most this many source points, spread along the Morton
curve."""
HALF_TURN_GAIN = 0.5
"""A refined half-turn replaces the pose found only when its truncated least-squares cost is at most this share of
the pose's: a truly symmetric shape fits both alike, and a refinement that merely went on longer (a loose
``tau``) must not turn the result over."""


def truncated_cost(m: dict, distance: float) -> float:
    """The truncated least-squares cost of a pose at ``distance`` (input units) from its ``icp_fitness`` f (the
    share of source points within it) and ``icp_inlier_rms`` (their RMS): the mean over the source points of
    min(d, distance)^2 = f rms^2 + (1 - f) distance^2."""
    return (1.0 - m["icp_fitness"]) * distance ** 2 + (m["icp_fitness"] * m["icp_inlier_rms"] ** 2
                                                       if m["icp_fitness"] > 0 else 0.0)


def least_norm_solve(H: np.ndarray, g: np.ndarray, rcond: float = 1e-10) -> np.ndarray:
    """The least-norm solution of the symmetric system ``H x = g`` (normal equations), on the unit-diagonal
    scaling of ``H`` so that units and far-off coordinates do not matter. Directions the pairs do not determine
    (a plane's slide and spin, a sphere's or a cylinder's turn) get no motion instead of a ``LinAlgError`` or a
    wild step: columns with no weight are dropped and singular values below ``rcond`` of the largest ignored."""
    d = np.sqrt(np.maximum(np.diag(H), 0.0))
    x = np.zeros(len(g))
    keep = d > 1e-12 * d.max() if d.max() > 0 else np.zeros(len(d), bool)
    if keep.any():
        dk = d[keep]
        x[keep] = np.linalg.lstsq(H[np.ix_(keep, keep)] / np.outer(dk, dk), g[keep] / dk, rcond=rcond)[0] / dk
    return x


def besl_mckay(cp: ClosestPoints, points: np.ndarray, T_init: np.ndarray, tau: float,
               max_iterations: int) -> IcpResult:
    """The paper's loop (Besl & McKay 1992): every point paired with its closest target point, the transform by
    Horn's quaternion, until the RMS changes by less than ``tau`` or after ``max_iterations`` updates. With every
    pair kept the RMS never increases, which gives the loop the widest basin of the ICP variants."""
    T, history, converged = T_init.copy(), [], False
    for it in range(max_iterations + 1):
        moved = apply_T(T, points)
        q, d, _ = cp(moved, None)
        history.append(float(np.sqrt(d @ d / len(d))))
        if it > 0 and abs(history[-2] - history[-1]) < tau:
            converged = True
            break
        if it == max_iterations:
            break
        T = horn_quaternion(q, moved) @ T
    return IcpResult(T, len(history) - 1, history, converged)


def _joined(first: IcpResult, then: IcpResult) -> IcpResult:
    """``then``, run from where ``first`` ended, with ``first``'s updates counted and its RMS history before
    ``then``'s (``first``'s last entry, at the pose where ``then``'s first is taken, dropped)."""
    then.iterations += first.iterations
    then.rms_history = first.rms_history[:-1] + then.rms_history
    return then


def _rms(d: np.ndarray, ok: np.ndarray) -> float:
    dk = np.compress(ok, d)
    return float(np.sqrt(dk @ dk / len(dk)))


def _compress(mask: np.ndarray, *arrays: np.ndarray) -> list[np.ndarray]:
    """The rows of each array where ``mask`` holds (``np.compress``, quicker than boolean indexing of rows)."""
    return [np.compress(mask, a, axis=0) for a in arrays]
