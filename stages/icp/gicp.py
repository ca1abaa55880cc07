"""``icp=gicp``: generalised ICP (plane-to-plane) by small_gicp."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.errors import ConfigError
from scanreg.geometry import ClosestPoints, bbox_diagonal
from scanreg.stages.icp.base import IcpBase, IcpParams
from scanreg.stages.registry import ICP
from scanreg.types import IcpResult


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

    searches_with_closest = False  # its iterates are measured against the target points, whatever the target

    def iterate(self, target, source, T_init, cp, tau, limit, update=None) -> IcpResult:
        import small_gicp

        if self.p.target == "mesh":
            raise ConfigError("icp=gicp: works on points only; set icp.target=points or auto")
        if self.p.trim < 1.0 or self.p.max_normal_angle_deg is not None:
            raise ConfigError("icp=gicp: trim and max_normal_angle_deg are not supported; leave them at 1 and null")
        if self.p.kernel != "none":
            raise ConfigError("icp=gicp: small_gicp's Python binding has no robust kernel; set icp.kernel=none")
        n, th = self.p.num_neighbors, self.p.num_threads
        tgt = small_gicp.PointCloud(np.ascontiguousarray(target.points))
        small_gicp.estimate_covariances(tgt, num_neighbors=n, num_threads=th)
        tree = small_gicp.KdTree(tgt, num_threads=th)
        src = small_gicp.PointCloud(np.ascontiguousarray(source.points))
        small_gicp.estimate_covariances(src, num_neighbors=n, num_threads=th)
        diag = bbox_diagonal(target.points)

        def gicp_step(T, moved, q, qn, ok, w, limit) -> np.ndarray:  # one small_gicp iteration at the limit
            r = small_gicp.align(tgt, src, tree, T, registration_type="GICP",
                                 max_correspondence_distance=limit.limit if limit.limit is not None else diag,
                                 num_threads=th, max_iterations=1)
            return np.asarray(r.T_target_source).copy()

        # the RMS of each iterate is measured against the target points, like GICP's own matching
        return super().iterate(target, source, T_init, ClosestPoints(target), tau, limit, gicp_step)
