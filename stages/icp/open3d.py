"""``icp=open3d``: Open3D's ``registration_icp``, the comparator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.errors import ConfigError, StageError
from scanreg.geometry import ClosestPoints, Cloud, Mesh, apply_T, bbox_diagonal, estimate_normals
from scanreg.stages.icp.base import IcpBase, IcpParams
from scanreg.stages.registry import ICP
from scanreg.types import IcpResult, RunContext, to_abs


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
            if self.basin == "wide":
                raise ValueError("basin: Open3D's own loop searches no wide basin; leave it at auto (ignored) or local")

    def _kernel(self, scale: float):
        import open3d as o3d

        reg = o3d.pipelines.registration
        return {"huber": reg.HuberLoss, "tukey": reg.TukeyLoss, "geman_mcclure": reg.GMLoss,
                "cauchy": reg.CauchyLoss}[self.p.kernel](scale)

    def refine(self, target: Cloud, source: Cloud, T_init: np.ndarray, spacing: float, ctx: RunContext,
               target_mesh: Mesh | None = None, start_is_estimate: bool = True) -> IcpResult:
        import open3d as o3d

        p = self.p
        if p.target == "mesh" or p.trim < 1.0 or p.max_normal_angle_deg is not None or p.initial_share < 1.0:
            raise ConfigError("icp=open3d: points only, without trim, normal rejection or coarse-to-fine; leave "
                              "icp.target=auto, trim=1, max_normal_angle_deg=null and initial_share=1")
        if p.kernel != "none" and p.estimation == "point_to_point":
            raise ConfigError("icp=open3d: Open3D's point-to-point estimation takes no robust kernel; set "
                              "icp.kernel=none or icp.estimation=point_to_plane")
        target, source, spacing = self.working_clouds(target, source, spacing, None, ctx)  # (points only)
        reg = o3d.pipelines.registration
        tau = to_abs(p.tau, p.distances, spacing)
        maxd = to_abs(p.max_correspondence_distance, p.distances, spacing)
        diag = bbox_diagonal(target.points)
        limit = self.schedule(target, maxd, to_abs(p.kernel_scale, p.distances, spacing))
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
            return reg.TransformationEstimationPointToPlane(self._kernel(limit.scale()))

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
        pairs = self.closest(target, target_mesh)  # the final pairs' search: on the target's triangles if any
        cp = pairs if pairs.mesh is None else ClosestPoints(target)  # the fit's distances: on its points
        d = cp(apply_T(T, source.points), maxd)[1]
        res = IcpResult(T, iterations, history, converged, final_distances=d, final_limit=limit.limit)
        return self.finish(res, cp, source, T_init, maxd, start_limit, spacing, source, pairs_cp=pairs)
