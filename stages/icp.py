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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.config import Context, Distances, to_abs
from scanreg.errors import ConfigError, StageError
from scanreg.geometry import (Cloud, apply_T, bbox_diagonal, blas_single_thread, cross3, horn_quaternion, make_T,
                               morton_order, row_norms)
from scanreg.closest import ClosestPoints, estimate_normals  # noqa: F401  (estimate_normals: re-exported)
from scanreg.registry import ICP

KERNELS = ("none", "huber", "tukey", "geman_mcclure", "cauchy")


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


@dataclass
class IcpResult:
    T_target_source: np.ndarray
    iterations: int
    """Number of transform updates made."""
    rms_history: list[float]
    """RMS distance of the pairs used at each iterate, before its update; the last entry at the final pose."""
    converged: bool
    final_distances: np.ndarray | None = None
    """Closest-point distances of the source at the final pose (every variant's loop ends right after pairing
    there), bounded by ``max_correspondence_distance`` (inf beyond)."""
    metrics: dict | None = None
    final_limit: float | None = None
    """The pair limit at the last iterate (input units; None: unlimited)."""


class PairLimit:
    """The pair-limit schedule: ``limit`` starts at ``start`` and shrinks by ``shrink`` towards ``floor``
    whenever the fit has settled at the current limit; ``settled`` once it is at the floor. Input units."""

    def __init__(self, start: float | None, floor: float | None, shrink: float = 0.5, settle: float = 0.01):
        self.limit, self.floor, self.shrink, self.settle = start, floor, shrink, settle
        self.start = start

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
    """Keep the start pose when ICP's final pose explains the data worse (fewer source points within
    ``accept_distance``, or as many at a higher RMS over them; see :meth:`IcpBase.accept`); logs
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


class IcpBase:
    """Shared machinery: correspondence search, pair selection, pair-limit schedule, robust weights, stopping,
    acceptance, final metrics."""

    p: IcpParams

    def __init__(self, params):
        self.p = params

    def closest(self, target: Cloud, ctx: Context) -> ClosestPoints:
        mesh = getattr(ctx, "target_mesh", None)
        if self.p.target == "mesh" and mesh is None:
            raise ConfigError(f"icp={self.name}: icp.target=mesh needs a target mesh, but the target is a point cloud")
        return ClosestPoints(target, mesh if self.p.target in ("mesh", "auto") and mesh is not None else None)

    def pairs(self, moved: np.ndarray, moved_normals, cp: ClosestPoints, maxd: float | None, it: int):
        """Closest points of ``moved`` and the mask of pairs kept."""
        q, d, qn = cp(moved, maxd)
        return q, d, qn, self.select(d, moved_normals, qn, maxd, it)

    def select(self, d, moved_normals, qn, maxd: float | None, it: int) -> np.ndarray:
        """The mask of pairs kept: within ``maxd``, normals agreeing, trimmed."""
        ok = np.ones(len(d), bool) if maxd is None else d <= maxd
        if self.p.max_normal_angle_deg is not None and moved_normals is not None and qn is not None:
            ok &= np.einsum("ij,ij->i", moved_normals, qn) >= math.cos(math.radians(self.p.max_normal_angle_deg))
        if self.p.trim < 1.0 and ok.sum() > 3:
            keep = max(3, int(math.ceil(self.p.trim * ok.sum())))
            thr = np.partition(d[ok], keep - 1)[keep - 1]
            ok &= d <= thr
        if ok.sum() < 3:
            raise StageError(
                f"icp={self.name}: only {int(ok.sum())} source point(s) paired with the target at iteration {it} "
                f"(pair limit {maxd if maxd is not None else 'none'}); the coarse alignment is too far off or the "
                "distance too small"
            )
        return ok

    def weights(self, d_ok: np.ndarray, limit: PairLimit) -> np.ndarray | None:
        """IRLS weights of the kept pairs' distances (None: least squares); the kernel scale grows with the
        adaptive pair limit."""
        if self.p.kernel == "none":
            return None
        s = self._kscale * (limit.limit / limit.floor if limit.limit and limit.floor else 1.0)
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

    def schedule(self, target: Cloud, maxd: float | None) -> PairLimit:
        p = self.p
        if p.schedule == "fixed" or maxd is None:
            return PairLimit(maxd, maxd)
        start = max(maxd, p.initial_distance * bbox_diagonal(target.points))
        return PairLimit(start, maxd, p.shrink, p.settle)

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        p = self.p
        tau = to_abs(p.tau, p.distances, ctx.spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, ctx.spacing)
        self._kscale = to_abs(p.kernel_scale, p.distances, ctx.spacing)
        cp = self.closest(target, ctx)
        order = morton_order(source.points)  # cache-coherent queries; the result does not depend on the order
        source = source.subset(order)
        start_limit = self.schedule(target, maxd).limit
        try:
            with blas_single_thread():
                step = int(round(1.0 / p.initial_share))
                if step > 1 and len(source.points) >= 3 * step:
                    first = self.iterate(target, source.subset(slice(None, None, step)), T_init, cp, tau,
                                         self.schedule(target, maxd), ctx)
                    # every point starts where the subset ended, at the subset's final (settled) limit
                    res = self.iterate(target, source, first.T_target_source, cp, tau, PairLimit(maxd, maxd), ctx)
                    res.iterations += first.iterations
                    # the subset's last entry is at the pose where every point's first one is: keep the latter
                    res.rms_history = first.rms_history[:-1] + res.rms_history
                else:
                    res = self.iterate(target, source, T_init, cp, tau, self.schedule(target, maxd), ctx)
        except (np.linalg.LinAlgError, ValueError) as e:
            raise StageError(f"icp={self.name}: the update failed ({e}); the pairs are degenerate") from e
        ctx.step_metrics["icp_rms"] = res.rms_history
        return self.finish(res, cp, source, T_init, maxd, start_limit, ctx)

    def finish(self, res: IcpResult, cp, source: Cloud, T_init, maxd, start_limit, ctx: Context) -> IcpResult:
        """Final metrics, and the acceptance test against the start pose at ``accept_distance``."""
        m = self.final_metrics(res.final_distances, maxd)
        acc_d = (to_abs(self.p.accept_distance, self.p.distances, ctx.spacing) if self.p.accept_distance is not None
                 else maxd if maxd is not None else 3.0 * ctx.spacing)
        m0 = self.final_metrics(cp(apply_T(T_init, source.points), acc_d)[1], acc_d)
        m1 = self.final_metrics(cp(apply_T(res.T_target_source, source.points), acc_d)[1], acc_d)
        accepted = self.accept(m0, m1) if self.p.accept else True
        if not accepted:
            res.T_target_source = T_init.copy()
            res.final_distances = cp(apply_T(T_init, source.points), maxd)[1]
            m = self.final_metrics(res.final_distances, maxd)
        res.metrics = {**m, "icp_accepted": float(accepted),
                       "icp_accept_start_fitness": m0["icp_fitness"], "icp_accept_end_fitness": m1["icp_fitness"],
                       "icp_accept_start_rms": m0["icp_inlier_rms"], "icp_accept_end_rms": m1["icp_inlier_rms"]}
        sp = ctx.spacing
        if start_limit is not None and sp > 0:
            res.metrics["icp_pair_limit_start_spacings"] = start_limit / sp
            res.metrics["icp_pair_limit_end_spacings"] = (res.final_limit or start_limit) / sp
        return res

    @staticmethod
    def accept(start: dict, end: dict) -> bool:
        """Whether ICP's final pose explains the data at least as well as the start pose, both measured at
        ``accept_distance`` (``icp_fitness``: share of source points within it, ``icp_inlier_rms``): fitness first, inlier RMS second. Rejected when it has clearly fewer points
        within that distance (1 % fewer), or about as many (within 1 %) at a clearly higher RMS (1 % higher)."""
        f0, f1 = start["icp_fitness"], end["icp_fitness"]
        r0, r1 = start["icp_inlier_rms"], end["icp_inlier_rms"]
        if not f0 > 0:
            return True
        if f1 < 0.99 * f0:
            return False
        return not (f1 <= 1.01 * f0 and r1 > 1.01 * r0)

    def step(self, moved, q, qn, ok, w) -> np.ndarray:  # pragma: no cover - per variant
        raise NotImplementedError

    def iterate(self, target, source, T_init, cp, tau, limit: PairLimit, ctx) -> IcpResult:
        """Plain fixed-point iteration: pairs at T, an update dT from ``step``, T <- dT T; the pair limit
        tightens when the fit settles, and the stopping rule applies at the final limit."""
        src = source.points
        sn = source.normals if self.p.max_normal_angle_deg is not None else None
        T = T_init.copy()
        history: list[float] = []
        converged, iterations = False, 0
        for it in range(self.p.max_iterations + 1):
            moved = apply_T(T, src)
            mn = None if sn is None else sn @ T[:3, :3].T
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
            T = self.update(T, moved, q, qn, ok, self.weights(np.compress(ok, d), limit), limit)
            iterations += 1
        if limit.limit is not None and limit.floor is not None and limit.limit > limit.floor:
            d = np.where(d <= limit.floor, d, np.inf)  # final distances bounded by the final pair limit
        return IcpResult(T, iterations, history, converged, final_distances=d, final_limit=limit.limit)

    def update(self, T, moved, q, qn, ok, w, limit: PairLimit) -> np.ndarray:
        """The next iterate from the current one and its pairs (``w``: IRLS weights of the kept pairs)."""
        return self.step(moved, q, qn, ok, w) @ T


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


def _rms(d: np.ndarray, ok: np.ndarray) -> float:
    dk = np.compress(ok, d)
    return float(np.sqrt(dk @ dk / len(dk)))


@ICP.register("horn")
class Horn(IcpBase):
    """Besl-McKay point-to-point ICP: closest target point (or closest point on the target's triangles) for
    every source point, the rigid transform by Horn's quaternion closed form (weighted under a robust kernel),
    until the RMS error changes by less than ``tau`` at the final pair limit."""

    @dataclass
    class Params(IcpParams):
        pass

    def step(self, moved, q, qn, ok, w):
        return horn_quaternion(q, moved, w) if ok.all() else horn_quaternion(*_compress(ok, q, moved), w)


@ICP.register("point_to_plane")
class PointToPlane(IcpBase):
    """Point-to-plane ICP (Chen & Medioni 1992): minimises the squared distances of source points to the
    tangent planes at their closest target points (weighted under a robust kernel), linearised in the rotation,
    one 6x6 solve per iteration. Needs target normals: the triangles' (mesh target), the cloud's, or estimated
    (Open3D, 20 neighbours)."""

    @dataclass
    class Params(IcpParams):
        kernel: str = "geman_mcclure"
        """Robust kernel (IRLS weights in the 6x6 solve): ``none``, ``huber``, ``tukey``, ``geman_mcclure`` or
        ``cauchy``. Geman-McClure at 1 spacing: on 5 Stanford pairs from 5 and 10 degrees off, median rotation
        error 0.06 deg against 0.11 deg with least squares (README)."""

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        if target.normals is None and getattr(ctx, "target_mesh", None) is None:
            target = Cloud(target.points, estimate_normals(target.points), target.source)
        return super().run(target, source, T_init, ctx)

    def step(self, moved, q, qn, ok, w):
        if not ok.all():
            moved, q, qn = _compress(ok, moved, q, qn)
        # linearised about the pairs' centroid c (p -> c + R (p - c) + t): the rotation and translation columns
        # stay apart however far the data lie from the origin (geo-referenced scans), so that only truly
        # undetermined directions are singular
        c = moved.mean(axis=0)
        A = np.hstack([cross3(moved - c, qn), qn])
        b = -np.einsum("ij,ij->i", moved - q, qn)
        Aw = A if w is None else A * w[:, None]
        H, g = Aw.T @ A, Aw.T @ b  # 6x6 normal equations
        x = least_norm_solve(H, g)
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        return make_T(R, x[3:] + c - R @ c)


@ICP.register("anderson")
class Anderson(IcpBase):
    """Point-to-point ICP accelerated by Anderson mixing (AA-ICP; Pavlov et al. 2018, with the energy safeguard
    of Zhang et al. 2021). The fixed point is Besl-McKay/Horn's. The transform is a 6-vector (rotation vector,
    translation); each iterate mixes the last ``memory`` ICP updates. A mixed iterate whose RMS is not below the
    last accepted one is replaced by the plain ICP step, so the accepted RMS never increases at a given pair
    limit; the mixing restarts when the limit tightens (the fixed-point map changes)."""

    @dataclass
    class Params(IcpParams):
        memory: int = 5
        """Number of past iterates mixed (Anderson window)."""

        def check(self):
            super().check()
            if self.memory < 1:
                raise ValueError(f"memory must be >= 1, got {self.memory}")

    @staticmethod
    def _vec(T):
        return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])

    @staticmethod
    def _mat(x):
        return make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:])

    def iterate(self, target, source, T_init, cp, tau, limit: PairLimit, ctx) -> IcpResult:
        src = source.points
        sn = source.normals if self.p.max_normal_angle_deg is not None else None
        x = self._vec(T_init)
        G_hist: list[np.ndarray] = []
        F_hist: list[np.ndarray] = []
        history: list[float] = []
        accepted_rms, g_acc = np.inf, None
        converged, iterations = False, 0
        for it in range(self.p.max_iterations + 1):
            T = self._mat(x)
            moved = apply_T(T, src)
            mn = None if sn is None else sn @ T[:3, :3].T
            q, d, qn, ok = self.pairs(moved, mn, cp, limit.limit, it)
            rms = _rms(d, ok)
            if rms > accepted_rms and g_acc is not None:
                # the mixed iterate made things worse: take the plain ICP step from the last accepted iterate
                G_hist, F_hist = [], []
                x = g_acc
                T = self._mat(x)
                moved = apply_T(T, src)
                mn = None if sn is None else sn @ T[:3, :3].T
                q, d, qn, ok = self.pairs(moved, mn, cp, limit.limit, it)
                rms = _rms(d, ok)
            history.append(rms)
            if it > 0:
                if limit.settled and abs(history[-2] - history[-1]) < tau:
                    converged = True
                    break
                if limit.advance(history[-2], history[-1], tau):
                    ok = self.select(d, mn, qn, limit.limit, it)
                    history[-1] = rms = _rms(d, ok)
                    G_hist, F_hist = [], []
            if it == self.p.max_iterations:
                break
            w = self.weights(np.compress(ok, d), limit)
            g = self._vec(horn_quaternion(*_compress(ok, q, moved), w) @ T)  # plain ICP map G(x)
            accepted_rms, g_acc = rms, g
            G_hist.append(g)
            F_hist.append(g - x)
            if len(G_hist) > self.p.memory + 1:
                G_hist.pop(0)
                F_hist.pop(0)
            x = g
            if len(G_hist) > 1:
                dF = np.diff(np.array(F_hist), axis=0).T
                dG = np.diff(np.array(G_hist), axis=0).T
                try:
                    gamma = np.linalg.lstsq(dF, F_hist[-1], rcond=None)[0]
                    if np.all(np.isfinite(gamma)):
                        x = g - dG @ gamma
                except np.linalg.LinAlgError:  # no mixing this time: the plain step
                    pass
            iterations += 1
        if limit.limit is not None and limit.floor is not None and limit.limit > limit.floor:
            d = np.where(d <= limit.floor, d, np.inf)
        return IcpResult(self._mat(x), iterations, history, converged, final_distances=d, final_limit=limit.limit)


@ICP.register("gicp")
class GeneralizedICP(IcpBase):
    """Generalised ICP (Segal et al. 2009, plane-to-plane) by small_gicp: local covariances from
    ``num_neighbors`` neighbours on both clouds, Gauss-Newton on the Mahalanobis distances. Target points only
    (no mesh). One small_gicp iteration per step, with the current pair limit as small_gicp's
    max_correspondence_distance, so that the RMS of each iterate is recorded and the schedule applies. small_gicp's
    Python binding has no robust kernel: ``kernel`` must be ``none``."""

    @dataclass
    class Params(IcpParams):
        num_neighbors: int = 20
        """Neighbours for the local covariances."""
        num_threads: int = 1
        """Threads small_gicp uses. With more than one its parallel sums run in varying order and the transform
        differs between runs in the last bits (measured: 2e-16 with 2 threads); 1 keeps runs bit-identical."""

    def iterate(self, target, source, T_init, cp, tau, limit, ctx) -> IcpResult:
        import small_gicp

        if self.p.target == "mesh":
            raise ConfigError("icp=gicp: works on points only; set icp.target=points or auto")
        if self.p.trim < 1.0 or self.p.max_normal_angle_deg is not None:
            raise ConfigError("icp=gicp: trim and max_normal_angle_deg are not supported; leave them at 1 and null")
        if self.p.kernel != "none":
            raise ConfigError("icp=gicp: small_gicp's Python binding has no robust kernel; set icp.kernel=none")
        n, th = self.p.num_neighbors, self.p.num_threads
        self._tgt = small_gicp.PointCloud(np.ascontiguousarray(target.points))
        small_gicp.estimate_covariances(self._tgt, num_neighbors=n, num_threads=th)
        self._tree = small_gicp.KdTree(self._tgt, num_threads=th)
        self._src = small_gicp.PointCloud(np.ascontiguousarray(source.points))
        small_gicp.estimate_covariances(self._src, num_neighbors=n, num_threads=th)
        self._diag = bbox_diagonal(target.points)
        # the RMS of each iterate is measured against the target points, like GICP's own matching
        return super().iterate(target, source, T_init, ClosestPoints(target), tau, limit, ctx)

    def update(self, T, moved, q, qn, ok, w, limit) -> np.ndarray:
        import small_gicp

        r = small_gicp.align(self._tgt, self._src, self._tree, T, registration_type="GICP",
                             max_correspondence_distance=limit.limit if limit.limit is not None else self._diag,
                             num_threads=self.p.num_threads, max_iterations=1)
        return np.asarray(r.T_target_source).copy()


@ICP.register("open3d")
class Open3dIcp(IcpBase):
    """Open3D's ``registration_icp`` as a comparator (point-to-point or point-to-plane on the target points).
    Run one Open3D iteration per call, with the current pair limit, so that the RMS of every iterate is recorded
    and the schedule and stopping rule are the same as the other variants'; trimming and normal rejection are not
    available; robust kernels only with ``point_to_plane`` (Open3D's own)."""

    @dataclass
    class Params(IcpParams):
        estimation: str = "point_to_point"
        """Open3D's transformation estimation: ``point_to_point`` or ``point_to_plane`` (target normals from the
        sampled mesh, else estimated from ``normal_neighbors`` neighbours)."""
        normal_neighbors: int = 20
        """Neighbours for target normals when the target has none."""

        def check(self):
            super().check()
            if self.estimation not in ("point_to_point", "point_to_plane"):
                raise ValueError(f"estimation must be point_to_point or point_to_plane, got '{self.estimation}'")

    def _kernel(self, scale: float):
        import open3d as o3d

        reg = o3d.pipelines.registration
        return {"huber": reg.HuberLoss, "tukey": reg.TukeyLoss, "geman_mcclure": reg.GMLoss,
                "cauchy": reg.CauchyLoss}[self.p.kernel](scale)

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        import open3d as o3d

        p = self.p
        if p.target == "mesh" or p.trim < 1.0 or p.max_normal_angle_deg is not None or p.initial_share < 1.0:
            raise ConfigError("icp=open3d: points only, without trim, normal rejection or coarse-to-fine; leave "
                              "icp.target=auto, trim=1, max_normal_angle_deg=null and initial_share=1")
        if p.kernel != "none" and p.estimation == "point_to_point":
            raise ConfigError("icp=open3d: Open3D's point-to-point estimation takes no robust kernel; set "
                              "icp.kernel=none or icp.estimation=point_to_plane")
        reg = o3d.pipelines.registration
        tau = to_abs(p.tau, p.distances, ctx.spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, ctx.spacing)
        self._kscale = to_abs(p.kernel_scale, p.distances, ctx.spacing)
        diag = bbox_diagonal(target.points)
        limit = self.schedule(target, maxd)
        start_limit = limit.limit
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.points))
        nrm = None
        if p.estimation == "point_to_plane":
            nrm = target.normals if target.normals is not None else estimate_normals(target.points,
                                                                                     p.normal_neighbors)
            tgt.normals = o3d.utility.Vector3dVector(nrm)

        def estimation():
            if p.estimation == "point_to_point":
                return reg.TransformationEstimationPointToPoint()
            if p.kernel == "none":
                return reg.TransformationEstimationPointToPlane()
            s = self._kscale * (limit.limit / limit.floor if limit.limit and limit.floor else 1.0)
            return reg.TransformationEstimationPointToPlane(self._kernel(s))

        def lim():
            return limit.limit if limit.limit is not None else diag

        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source.points))
        T = T_init.copy()
        history = [float(reg.evaluate_registration(src, tgt, lim(), T).inlier_rmse)]
        crit = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
        converged, iterations = False, 0
        for _ in range(p.max_iterations):
            r = reg.registration_icp(src, tgt, lim(), T, estimation(), crit)
            if len(r.correspondence_set) == 0:
                raise StageError(f"icp=open3d: no source point within {lim():.4g} of the target; the coarse "
                                 "alignment is too far off or max_correspondence_distance too small")
            T = np.asarray(r.transformation).copy()
            iterations += 1
            history.append(float(r.inlier_rmse))
            if limit.settled and abs(history[-2] - history[-1]) < tau:
                converged = True
                break
            if limit.advance(history[-2], history[-1], tau):
                history[-1] = float(reg.evaluate_registration(src, tgt, lim(), T).inlier_rmse)
        ctx.step_metrics["icp_rms"] = history
        cp = ClosestPoints(target)
        d = cp(apply_T(T, source.points), maxd)[1]
        res = IcpResult(T, iterations, history, converged, final_distances=d, final_limit=limit.limit)
        return self.finish(res, cp, source, T_init, maxd, start_limit, ctx)


def _compress(mask: np.ndarray, *arrays: np.ndarray) -> list[np.ndarray]:
    """The rows of each array where ``mask`` holds (``np.compress``: 10x faster than boolean indexing of rows)."""
    return [np.compress(mask, a, axis=0) for a in arrays]
