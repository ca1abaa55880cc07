"""Local shape descriptors computed at keypoints. Issue 4 adds the paper's ``histogram3p``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config import Context, Distances, to_abs
from pipeline.geometry import Cloud
from pipeline.registry import DESCRIPTOR


def to_o3d(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pc


@DESCRIPTOR.register("fpfh")
class FPFH:
    """Fast Point Feature Histograms (Rusu 2009, Open3D), 33 bins, over a voxel-downsampled support cloud."""

    @dataclass
    class Params:
        radius: float = 15.0
        """Support radius of the histogram (see ``distances``)."""
        max_nn: int = 100
        """At most this many neighbours within the radius."""
        normal_radius: float = 6.0
        """Radius for normal estimation on the support cloud (see ``distances``)."""
        support_voxel: float = 3.0
        """Voxel size of the support cloud the histograms are built from (see ``distances``); 0 uses every
        point of the cloud."""
        distances: Distances = Distances.spacing
        """Unit of the distances above: multiples of the sampling spacing, or absolute input units."""

    def __init__(self, params: Params):
        self.p = params

    def compute(self, cloud: Cloud, keypoints: np.ndarray, ctx: Context) -> np.ndarray:
        """(K, 33) descriptors of ``cloud.points[keypoints]``."""
        import open3d as o3d

        u, s = self.p.distances, ctx.spacing
        support = to_o3d(cloud.points, cloud.normals)
        voxel = to_abs(self.p.support_voxel, u, s)
        if voxel > 0:
            support = support.voxel_down_sample(voxel)
        kp = cloud.points[keypoints]
        both = to_o3d(np.vstack([np.asarray(support.points), kp]))
        if cloud.normals is not None:  # orient estimated normals like the given ones
            both.normals = o3d.utility.Vector3dVector(
                np.vstack([np.asarray(support.normals), cloud.normals[keypoints]])
            )
        both.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(self.p.normal_radius, u, s), max_nn=30))
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            both, o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(self.p.radius, u, s), max_nn=self.p.max_nn)
        )
        return np.asarray(feat.data).T[-len(kp):].copy()
