"""Fine registration (ICP variants).

All variants share one correspondence search (:class:`ClosestPoints`) and one set of pair rejections, and report
the same numbers, defined once:

- ``rms_history`` (MLflow step metric ``icp_rms_step``): at each iterate, the RMS distance of the pairs used
  (after rejection and trimming), before the update; the last entry is at the final pose (coarse-to-fine,
  ``initial_share`` < 1: the subset's iterates, then every point's; always ``iterations`` + 1 entries);
- ``icp_rms``: the last entry of that history;
- ``icp_fitness``: the share of source points whose closest target point at the final pose lies within
  ``max_correspondence_distance`` (every point when it is null);
- ``icp_inlier_rms``: the RMS distance of those points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.config import Context, Distances, to_abs
from scanreg.errors import ConfigError, StageError
from scanreg.geometry import (Cloud, apply_T, blas_single_thread, cross3, horn_quaternion, make_T,
                               morton_order)
from scanreg.closest import ClosestPoints, estimate_normals  # noqa: F401  (estimate_normals: re-exported)
from scanreg.registry import ICP


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


@dataclass
class IcpParams:
    max_iterations: int = 100
    """Maximum number of iterations."""
    tau: float = 1e-4
    """Stop when the RMS error changes by less than this between iterations (see ``distances``)."""
    max_correspondence_distance: Optional[float] = 3.0
    """Pairs farther apart are ignored (see ``distances``); null keeps every pair (pure Besl-McKay, whose RMS
    never increases)."""
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
    """Unit of ``tau`` and ``max_correspondence_distance``: multiples of the sampling spacing, or input units."""
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


class IcpBase:
    """Shared machinery: correspondence search, pair selection, stopping, final metrics."""

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
                f"(max_correspondence_distance {maxd if maxd is not None else 'none'}); the coarse alignment is "
                "too far off or the distance too small"
            )
        return q, d, qn, ok

    def final_metrics(self, d: np.ndarray, maxd) -> dict:
        inl = np.ones(len(d), bool) if maxd is None else d <= maxd
        return {
            "icp_fitness": float(inl.mean()),
            "icp_inlier_rms": float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("nan"),
        }

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        p = self.p
        tau = to_abs(p.tau, p.distances, ctx.spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, ctx.spacing)
        cp = self.closest(target, ctx)
        order = morton_order(source.points)  # cache-coherent queries; the result does not depend on the order
        source = source.subset(order)
        with blas_single_thread():
            step = int(round(1.0 / p.initial_share))
            if step > 1 and len(source.points) >= 3 * step:
                first = self.iterate(target, source.subset(slice(None, None, step)), T_init, cp, tau, maxd, ctx)
                res = self.iterate(target, source, first.T_target_source, cp, tau, maxd, ctx)
                res.iterations += first.iterations
                # the subset's last entry is at the pose where every point's first one is: keep the latter
                res.rms_history = first.rms_history[:-1] + res.rms_history
            else:
                res = self.iterate(target, source, T_init, cp, tau, maxd, ctx)
        ctx.step_metrics["icp_rms"] = res.rms_history
        res.metrics = self.final_metrics(res.final_distances, maxd)
        return res

    def step(self, moved, q, qn, ok) -> np.ndarray:  # pragma: no cover - per variant
        raise NotImplementedError

    def iterate(self, target, source, T_init, cp, tau, maxd, ctx) -> IcpResult:
        """Plain fixed-point iteration: pairs at T, an update dT from ``step``, T <- dT T."""
        src = source.points
        sn = source.normals if self.p.max_normal_angle_deg is not None else None
        T = T_init.copy()
        history: list[float] = []
        converged, iterations = False, 0
        for it in range(self.p.max_iterations + 1):
            moved = apply_T(T, src)
            mn = None if sn is None else sn @ T[:3, :3].T
            q, d, qn, ok = self.pairs(moved, mn, cp, maxd, it)
            history.append(float(np.sqrt(np.mean(d[ok] ** 2))))
            if it > 0 and abs(history[-2] - history[-1]) < tau:
                converged = True
                break
            if it == self.p.max_iterations:
                break
            T = self.update(T, moved, q, qn, ok)
            iterations += 1
        return IcpResult(T, iterations, history, converged, final_distances=d)

    def update(self, T, moved, q, qn, ok) -> np.ndarray:
        """The next iterate from the current one and its pairs."""
        return self.step(moved, q, qn, ok) @ T


@ICP.register("horn")
class Horn(IcpBase):
    """Besl-McKay point-to-point ICP: closest target point (or closest point on the target's triangles) for
    every source point, the rigid transform by Horn's quaternion closed form, until the RMS error changes by
    less than ``tau``."""

    @dataclass
    class Params(IcpParams):
        pass

    def step(self, moved, q, qn, ok):
        return horn_quaternion(q, moved) if ok.all() else horn_quaternion(*_compress(ok, q, moved))


@ICP.register("point_to_plane")
class PointToPlane(IcpBase):
    """Point-to-plane ICP (Chen & Medioni 1992): minimises the squared distances of source points to the
    tangent planes at their closest target points, linearised in the rotation, one 6x6 solve per iteration.
    Needs target normals: the triangles' (mesh target), the cloud's, or estimated (Open3D, 20 neighbours)."""

    @dataclass
    class Params(IcpParams):
        pass

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        if target.normals is None and getattr(ctx, "target_mesh", None) is None:
            target = Cloud(target.points, estimate_normals(target.points), target.source)
        return super().run(target, source, T_init, ctx)

    def step(self, moved, q, qn, ok):
        if not ok.all():
            moved, q, qn = _compress(ok, moved, q, qn)
        A = np.hstack([cross3(moved, qn), qn])
        b = -np.einsum("ij,ij->i", moved - q, qn)
        AtA = A.T @ A  # 6x6 normal equations; a flat or symmetric match leaves them singular. Checked with unit
        d = np.sqrt(np.diag(AtA))  # diagonal, so that units and far-off coordinates (UTM) do not count as singular
        if not (d.min() > 1e-12 * d.max() and np.linalg.eigvalsh(AtA / np.outer(d, d))[0] > 1e-14):
            raise StageError("icp=point_to_plane: the matched points do not determine a rigid transform (their "
                             "point-to-plane system is singular: flat, or symmetric about an axis)")
        x = np.linalg.solve(AtA, A.T @ b)
        return make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:])


@ICP.register("anderson")
class Anderson(IcpBase):
    """Point-to-point ICP accelerated by Anderson mixing (AA-ICP; Pavlov et al. 2018, with the energy safeguard
    of Zhang et al. 2021). The fixed point is Besl-McKay/Horn's. The transform is a 6-vector (rotation vector,
    translation); each iterate mixes the last ``memory`` ICP updates. A mixed iterate whose RMS is not below the
    last accepted one is replaced by the plain ICP step, so the accepted RMS never increases."""

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

    def iterate(self, target, source, T_init, cp, tau, maxd, ctx) -> IcpResult:
        src = source.points
        sn = source.normals if self.p.max_normal_angle_deg is not None else None
        x = self._vec(T_init)
        G_hist: list[np.ndarray] = []
        F_hist: list[np.ndarray] = []
        history: list[float] = []
        accepted_rms, x_acc, g_acc = np.inf, x, None
        converged, iterations = False, 0
        for it in range(self.p.max_iterations + 1):
            T = self._mat(x)
            moved = apply_T(T, src)
            mn = None if sn is None else sn @ T[:3, :3].T
            q, d, qn, ok = self.pairs(moved, mn, cp, maxd, it)
            rms = float(np.sqrt(np.mean(d[ok] ** 2)))
            if rms > accepted_rms and g_acc is not None:
                # the mixed iterate made things worse: take the plain ICP step from the last accepted iterate
                G_hist, F_hist = [], []
                x = g_acc
                T = self._mat(x)
                moved = apply_T(T, src)
                mn = None if sn is None else sn @ T[:3, :3].T
                q, d, qn, ok = self.pairs(moved, mn, cp, maxd, it)
                rms = float(np.sqrt(np.mean(d[ok] ** 2)))
            history.append(rms)
            if it > 0 and abs(history[-2] - history[-1]) < tau:
                converged = True
                break
            if it == self.p.max_iterations:
                break
            g = self._vec(horn_quaternion(*_compress(ok, q, moved)) @ T)  # plain ICP map G(x)
            accepted_rms, x_acc, g_acc = rms, x, g
            G_hist.append(g)
            F_hist.append(g - x)
            if len(G_hist) > self.p.memory + 1:
                G_hist.pop(0)
                F_hist.pop(0)
            if len(G_hist) > 1:
                dF = np.diff(np.array(F_hist), axis=0).T
                dG = np.diff(np.array(G_hist), axis=0).T
                gamma = np.linalg.lstsq(dF, F_hist[-1], rcond=None)[0]
                x = g - dG @ gamma
            else:
                x = g
            iterations += 1
        return IcpResult(self._mat(x), iterations, history, converged, final_distances=d)


@ICP.register("gicp")
class GeneralizedICP(IcpBase):
    """Generalised ICP (Segal et al. 2009, plane-to-plane) by small_gicp: local covariances from
    ``num_neighbors`` neighbours on both clouds, Gauss-Newton on the Mahalanobis distances. Target points only
    (no mesh). One small_gicp iteration per step, so that the RMS of each iterate can be recorded."""

    @dataclass
    class Params(IcpParams):
        num_neighbors: int = 20
        """Neighbours for the local covariances."""
        num_threads: int = 2
        """Threads small_gicp uses."""

    def iterate(self, target, source, T_init, cp, tau, maxd, ctx) -> IcpResult:
        import small_gicp

        if self.p.target == "mesh":
            raise ConfigError("icp=gicp: works on points only; set icp.target=points or auto")
        if self.p.trim < 1.0 or self.p.max_normal_angle_deg is not None:
            raise ConfigError("icp=gicp: trim and max_normal_angle_deg are not supported; leave them at 1 and null")
        n, th = self.p.num_neighbors, self.p.num_threads
        self._tgt = small_gicp.PointCloud(np.ascontiguousarray(target.points))
        small_gicp.estimate_covariances(self._tgt, num_neighbors=n, num_threads=th)
        self._tree = small_gicp.KdTree(self._tgt, num_threads=th)
        self._src = small_gicp.PointCloud(np.ascontiguousarray(source.points))
        small_gicp.estimate_covariances(self._src, num_neighbors=n, num_threads=th)
        self._dist = maxd if maxd is not None else float(np.linalg.norm(np.ptp(target.points, axis=0)))
        # the RMS of each iterate is measured against the target points, like GICP's own matching
        return super().iterate(target, source, T_init, ClosestPoints(target), tau, maxd, ctx)

    def update(self, T, moved, q, qn, ok) -> np.ndarray:
        import small_gicp

        r = small_gicp.align(self._tgt, self._src, self._tree, T, registration_type="GICP",
                             max_correspondence_distance=self._dist, num_threads=self.p.num_threads,
                             max_iterations=1)
        return np.asarray(r.T_target_source).copy()


@ICP.register("open3d")
class Open3dIcp(IcpBase):
    """Open3D's ``registration_icp`` as a comparator (point-to-point or point-to-plane on the target points).
    Run one Open3D iteration per call so that the RMS of every iterate is recorded and the stopping rule is the
    same as the other variants' (RMS change < ``tau``); trimming and normal rejection are not available."""

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

    def run(self, target: Cloud, source: Cloud, T_init: np.ndarray, ctx: Context) -> IcpResult:
        import open3d as o3d

        p = self.p
        if p.target == "mesh" or p.trim < 1.0 or p.max_normal_angle_deg is not None or p.initial_share < 1.0:
            raise ConfigError("icp=open3d: points only, without trim, normal rejection or coarse-to-fine; leave "
                              "icp.target=auto, trim=1, max_normal_angle_deg=null and initial_share=1")
        reg = o3d.pipelines.registration
        tau = to_abs(p.tau, p.distances, ctx.spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, ctx.spacing)
        maxd_o3d = maxd if maxd is not None else float(np.linalg.norm(np.ptp(target.points, axis=0)))
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.points))
        if p.estimation == "point_to_plane":
            nrm = target.normals if target.normals is not None else estimate_normals(target.points,
                                                                                     p.normal_neighbors)
            tgt.normals = o3d.utility.Vector3dVector(nrm)
            est = reg.TransformationEstimationPointToPlane()
        else:
            est = reg.TransformationEstimationPointToPoint()
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source.points))
        T = T_init.copy()
        ev = reg.evaluate_registration(src, tgt, maxd_o3d, T)
        history = [float(ev.inlier_rmse)]
        crit = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
        converged, iterations = False, 0
        for _ in range(p.max_iterations):
            r = reg.registration_icp(src, tgt, maxd_o3d, T, est, crit)
            T = np.asarray(r.transformation).copy()
            iterations += 1
            history.append(float(r.inlier_rmse))
            if abs(history[-2] - history[-1]) < tau:
                converged = True
                break
        if len(r.correspondence_set) == 0:  # max_iterations >= 1: r is the last call's result
            raise StageError(f"icp=open3d: no source point within {maxd_o3d:.4g} of the target; the coarse "
                             "alignment is too far off or max_correspondence_distance too small")
        ctx.step_metrics["icp_rms"] = history
        d = ClosestPoints(target)(apply_T(T, source.points), maxd)[1]
        res = IcpResult(T, iterations, history, converged, final_distances=d)
        res.metrics = self.final_metrics(d, maxd)
        return res


def _compress(mask: np.ndarray, *arrays: np.ndarray) -> list[np.ndarray]:
    """The rows of each array where ``mask`` holds (``np.compress``: 10x faster than boolean indexing of rows)."""
    return [np.compress(mask, a, axis=0) for a in arrays]
