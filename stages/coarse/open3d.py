"""Open3D's global registration recipes, the comparators: ``coarse=open3d_fpfh_ransac`` (FPFH features and
RANSAC) and ``coarse=open3d_fgr`` (Fast Global Registration)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.errors import StageError
from scanreg.geometry import Cloud, to_o3d
from scanreg.stages.coarse.base import CoarseBase
from scanreg.stages.registry import COARSE
from scanreg.types import CoarseResult, CoarseTrace, Distances, RunContext, to_abs


@dataclass
class Open3dFeatureParams:
    voxel: float = 3.0
    """Voxel size of the downsampled clouds (see ``distances``)."""
    normal_radius: float = 6.0
    """Normal estimation radius (see ``distances``); Open3D's recipe uses 2 voxels."""
    feature_radius: float = 15.0
    """FPFH radius (see ``distances``); Open3D's recipe uses 5 voxels."""
    feature_max_nn: int = 100
    """At most this many neighbours per FPFH histogram."""
    seed: int = 0
    """Seed of Open3D's random generator."""
    distances: Distances = Distances.spacing
    """Unit of the distances: multiples of the sampling spacing, or absolute input units."""


@COARSE.register("open3d_fpfh_ransac")
class Open3dFpfhRansac(CoarseBase):
    """Open3D's global registration recipe, the comparator: voxel downsampling, normals, FPFH features, and
    RANSAC on nearest-feature matches with edge-length and distance checks."""

    @dataclass
    class Params(Open3dFeatureParams):
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


    def _prepared_pair(self, target: Cloud, source: Cloud, spacing: float):
        """Open3D's registration module, then the target and the source downsampled with their FPFH features
        (Open3D's random generator seeded first, for the matching that follows)."""
        import open3d as o3d

        o3d.utility.random.seed(self.p.seed)
        tgt, ft = self._prepare(target, spacing)
        src, fs = self._prepare(source, spacing)
        return o3d.pipelines.registration, tgt, ft, src, fs

    def _prepare(self, cloud: Cloud, spacing: float):
        import open3d as o3d

        p, u, s = self.p, self.p.distances, spacing
        down = to_o3d(cloud.points, cloud.normals).voxel_down_sample(to_abs(p.voxel, u, s))
        if len(down.points) < 3:
            raise StageError(f"coarse=open3d_fpfh_ransac: {cloud.source}: fewer than 3 points after downsampling")
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(p.normal_radius, u, s), max_nn=30))
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(p.feature_radius, u, s), max_nn=p.feature_max_nn)
        )
        return down, feat

    def align(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext,
              landmarks=None) -> CoarseResult:
        reg, tgt, ft, src, fs = self._prepared_pair(target, source, spacing)
        p = self.p
        dist = to_abs(p.distance_threshold, p.distances, spacing)
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, fs, ft, p.mutual_filter, dist,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(p.edge_length_ratio),
             reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(p.max_iterations, p.confidence),
        )
        trace = _open3d_trace(tgt, src, ft, fs, p.mutual_filter, res)
        metrics = {
            "coarse_keypoints_target": len(tgt.points),
            "coarse_keypoints_source": len(src.points),
            "coarse_fitness": float(res.fitness),
            "coarse_inlier_rmse": float(res.inlier_rmse),
            "coarse_inliers": len(res.correspondence_set),
        }
        return CoarseResult(np.asarray(res.transformation).copy(), metrics, trace)


def _open3d_trace(tgt, src, ft, fs, mutual: bool, res) -> CoarseTrace:
    """What Open3D's feature RANSAC compared, for the evaluation: its downsampled points as keypoints, and the
    matches it draws from (each source point's nearest target feature, mutual when ``mutual``), recomputed
    here since Open3D returns only the final inliers (``ransac_inliers``: a match among them)."""
    from scipy.spatial import cKDTree

    F0, F1 = np.asarray(ft.data).T, np.asarray(fs.data).T
    pt, ps = np.asarray(tgt.points), np.asarray(src.points)
    j = cKDTree(F0).query(F1)[1]
    i = np.arange(len(F1))
    if mutual:
        keep = cKDTree(F1).query(F0[j])[1] == i
        i, j = i[keep], j[keep]
    acc = {(int(a), int(b)) for b, a in np.asarray(res.correspondence_set)}  # rows are (source, target)
    return CoarseTrace(keypoints_target=pt, keypoints_source=ps, matches_target=pt[j], matches_source=ps[i],
                       ransac_inliers=np.array([(int(a), int(b)) in acc for a, b in zip(j, i)], bool))


@COARSE.register("open3d_fgr")
class Open3dFGR(Open3dFpfhRansac):
    """Open3D's Fast Global Registration (Zhou et al. 2016) on FPFH features of voxel-downsampled clouds, the
    second comparator."""

    @dataclass
    class Params(Open3dFeatureParams):
        distance_threshold: float = 1.5
        """FGR's maximum correspondence distance (see ``distances``); Open3D's recipe uses 0.5 voxels."""
        iterations: int = 64
        """FGR iterations."""

    def align(self, target: Cloud, source: Cloud, spacing: float, ctx: RunContext,
              landmarks=None) -> CoarseResult:
        reg, tgt, ft, src, fs = self._prepared_pair(target, source, spacing)
        p = self.p
        opt = reg.FastGlobalRegistrationOption(
            maximum_correspondence_distance=to_abs(p.distance_threshold, p.distances, spacing),
            iteration_number=p.iterations)
        res = reg.registration_fgr_based_on_feature_matching(src, tgt, fs, ft, opt)
        trace = CoarseTrace(keypoints_target=np.asarray(tgt.points), keypoints_source=np.asarray(src.points))
        return CoarseResult(np.asarray(res.transformation).copy(), {
            "coarse_keypoints_target": len(tgt.points), "coarse_keypoints_source": len(src.points),
            "coarse_fitness": float(res.fitness), "coarse_inlier_rmse": float(res.inlier_rmse)}, trace)
