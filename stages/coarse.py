"""Coarse (global) registration: an initial ``T_target_source`` from any starting pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config import Context, Distances, to_abs
from pipeline.errors import StageError
from pipeline.geometry import Cloud
from pipeline.registry import COARSE
from stages.descriptor import to_o3d


@COARSE.register("none")
class NoCoarse:
    """Start fine registration from the identity (the inputs are assumed roughly aligned)."""

    uses: tuple[str, ...] = ()

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        return np.eye(4), {}


@COARSE.register("open3d_fpfh_ransac")
class Open3dFpfhRansac:
    """Open3D's global registration recipe, the comparator: voxel downsampling, normals, FPFH features, and
    RANSAC on nearest-feature matches with edge-length and distance checks."""

    uses: tuple[str, ...] = ()

    @dataclass
    class Params:
        voxel: float = 3.0
        """Voxel size of the downsampled clouds (see ``distances``)."""
        normal_radius: float = 6.0
        """Normal estimation radius (see ``distances``); Open3D's recipe uses 2 voxels."""
        feature_radius: float = 15.0
        """FPFH radius (see ``distances``); Open3D's recipe uses 5 voxels."""
        feature_max_nn: int = 100
        """At most this many neighbours per FPFH histogram."""
        distance_threshold: float = 4.5
        """Largest distance of an inlier pair (see ``distances``); Open3D's recipe uses 1.5 voxels."""
        edge_length_ratio: float = 0.9
        """Edge-length checker: corresponding edges of a sample must agree to this ratio."""
        mutual_filter: bool = False
        """Keep only mutual nearest feature matches."""
        max_iterations: int = 100000
        """Maximum RANSAC iterations."""
        confidence: float = 0.999
        """RANSAC stops early when the best model holds with this probability."""
        seed: int = 0
        """Seed of Open3D's random generator."""
        distances: Distances = Distances.spacing
        """Unit of the distances above: multiples of the sampling spacing, or absolute input units."""

    def __init__(self, params: Params):
        self.p = params

    def _prepare(self, cloud: Cloud, ctx: Context):
        import open3d as o3d

        p, u, s = self.p, self.p.distances, ctx.spacing
        down = to_o3d(cloud.points, cloud.normals).voxel_down_sample(to_abs(p.voxel, u, s))
        if len(down.points) < 3:
            raise StageError(f"coarse=open3d_fpfh_ransac: {cloud.source}: fewer than 3 points after downsampling")
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(p.normal_radius, u, s), max_nn=30))
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(p.feature_radius, u, s), max_nn=p.feature_max_nn)
        )
        return down, feat

    def run(self, target: Cloud, source: Cloud, ctx: Context) -> tuple[np.ndarray, dict]:
        import open3d as o3d

        reg = o3d.pipelines.registration
        p = self.p
        o3d.utility.random.seed(p.seed)
        tgt, ft = self._prepare(target, ctx)
        src, fs = self._prepare(source, ctx)
        dist = to_abs(p.distance_threshold, p.distances, ctx.spacing)
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, fs, ft, p.mutual_filter, dist,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(p.edge_length_ratio),
             reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(p.max_iterations, p.confidence),
        )
        metrics = {
            "coarse_keypoints_target": len(tgt.points),
            "coarse_keypoints_source": len(src.points),
            "coarse_fitness": float(res.fitness),
            "coarse_inlier_rmse": float(res.inlier_rmse),
            "coarse_inliers": len(res.correspondence_set),
        }
        return np.asarray(res.transformation).copy(), metrics
