"""Keypoint detectors (salience measures). Issue 4 adds the covariance-eigenvalue measures; ``uniform`` is the
voxel-grid comparator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config import Context, Distances, to_abs
from pipeline.geometry import Cloud
from pipeline.registry import SALIENCE


def voxel_representatives(points: np.ndarray, voxel: float) -> np.ndarray:
    """Index of one point per occupied voxel: the point nearest to the centroid of the voxel's points.
    Sorted by voxel key, so the result does not depend on the order of equal keys (deterministic)."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv, points)
    centroids = sums / counts[:, None]
    d = np.linalg.norm(points - centroids[inv], axis=1)
    order = np.lexsort((d, inv))  # by voxel, then by distance to the centroid
    first = np.ones(len(order), bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return np.sort(order[first])


@SALIENCE.register("uniform")
class Uniform:
    """Voxel-grid keypoints: in every occupied voxel, the point nearest to the voxel's centroid."""

    @dataclass
    class Params:
        voxel: float = 3.0
        """Voxel edge length (see ``distances``)."""
        distances: Distances = Distances.spacing
        """Unit of ``voxel``: multiples of the sampling spacing, or absolute input units."""

    def __init__(self, params: Params):
        self.p = params

    def keypoints(self, cloud: Cloud, ctx: Context) -> np.ndarray:
        return voxel_representatives(cloud.points, to_abs(self.p.voxel, self.p.distances, ctx.spacing))
