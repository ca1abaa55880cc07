"""Keypoint detectors (salience measures).

The paper's measures: for each point p, the neighbours within radius s give the weighted covariance of the
points, ``C_p = sum w_i (p_i - mu)(p_i - mu)^T / sum w_i``, and of the normals, ``C_n = sum w_i n_i n_i^T /
sum w_i``, with eigenvalues l1 <= l2 <= l3. The salience ``h(p)`` is one of min(l1/l2, l2/l3), l1, l2, l3,
l1/l2 or l2/l3, of either matrix. That gives 12 registered names, ``cp_min_ratio`` ... ``cn_l2_l3``.

Points with fewer than ``min_neighbors`` neighbours are never keypoints. A keypoint is a non-maximum-suppressed
maximum: p is kept when ``h(p) >= h(i)`` for every neighbour i within the suppression radius. Deviation from the
paper: both the covariances and the suppression see only the ``max_neighbors`` (64) nearest points within their
radius, so a more salient point farther than the 64th nearest does not suppress p (pinned by
``tests/test_paper_equations.py``). Optionally only the ``top_k`` most salient are kept. ``uniform`` (voxel
grid) and ``iss`` (Open3D's ISS) are the comparators.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.errors import StageError
from scanreg.geometry import Cloud, far_offset, neighbourhoods, to_o3d, voxel_representatives
from scanreg.stages.registry import SALIENCE
from scanreg.types import Distances, to_abs

MEASURES = {
    "min_ratio": "min(l1/l2, l2/l3)",
    "l1": "l1 (smallest eigenvalue)",
    "l2": "l2 (middle eigenvalue)",
    "l3": "l3 (largest eigenvalue)",
    "l1_l2": "l1/l2",
    "l2_l3": "l2/l3",
}
MATRICES = {"cp": "point covariance C_p", "cn": "normal covariance C_n"}


def eigen_features(points, normals, radius, max_neighbors, gaussian, queries=None, batch=20000):
    """Eigenvalues (ascending) of C_p and C_n at every query point, and the neighbour counts.
    Returns ``(lp (N, 3), ln (N, 3) or None, counts (N,))``."""
    n = len(points) if queries is None else len(queries)
    lp = np.empty((n, 3))
    ln = None if normals is None else np.empty((n, 3))
    counts = np.empty(n, np.int64)
    for s in range(0, n, batch):
        qs = (points if queries is None else queries)[s:s + batch]
        j, d, valid = neighbourhoods(points, radius, max_neighbors, qs)
        w = valid.astype(np.float64)
        if gaussian:
            sig = radius / 2.0
            w = w * np.exp(-np.where(valid, d, 0.0) ** 2 / (2 * sig * sig))
        wsum = w.sum(axis=1)
        counts[s:s + batch] = valid.sum(axis=1)
        P = points[j]
        mu = np.einsum("nk,nkd->nd", w, P) / wsum[:, None]
        X = P - mu[:, None, :]
        C = np.einsum("nk,nki,nkj->nij", w, X, X) / wsum[:, None, None]
        lp[s:s + batch] = np.linalg.eigvalsh(C)
        if normals is not None:
            N = normals[j]
            Cn = np.einsum("nk,nki,nkj->nij", w, N, N) / wsum[:, None, None]
            ln[s:s + batch] = np.linalg.eigvalsh(Cn)
    return np.maximum(lp, 0.0), None if ln is None else np.maximum(ln, 0.0), counts


def measure_values(lam: np.ndarray, measure: str) -> np.ndarray:
    l1, l2, l3 = lam[:, 0], lam[:, 1], lam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r12 = np.where(l2 > 0, l1 / l2, 0.0)
        r23 = np.where(l3 > 0, l2 / l3, 0.0)
    return {"min_ratio": np.minimum(r12, r23), "l1": l1, "l2": l2, "l3": l3, "l1_l2": r12, "l2_l3": r23}[measure]


def non_maximum_suppression(points: np.ndarray, h: np.ndarray, radius: float, max_neighbors: int = 64) -> np.ndarray:
    """Indices p with finite h(p) >= h(i) for every i among the ``max_neighbors`` nearest within ``radius`` (ties
    keep both); with more points than that within the radius, the farther ones are not compared."""
    j, _, valid = neighbourhoods(points, radius, max_neighbors)
    hn = np.where(valid, h[j], -np.inf)
    keep = np.isfinite(h) & (h >= hn.max(axis=1))
    return np.flatnonzero(keep)


@dataclass
class SalienceParams:
    radius: float = 5.0
    """Neighbourhood radius s of the covariances (see ``distances``)."""
    nms_radius: float = 5.0
    """Non-maximum suppression radius sigma: p is a keypoint only if no point within it is more salient (see
    ``distances``)."""
    weights: str = "uniform"
    """Weights of the neighbours: ``uniform``, or ``gaussian`` in the distance (sigma = radius / 2)."""
    min_neighbors: int = 10
    """Points with fewer neighbours (themselves included) within the radius are never keypoints."""
    max_neighbors: int = 64
    """At most this many (nearest) neighbours per point enter the covariance."""
    top_k: Optional[int] = None
    """Keep only the k most salient keypoints (null: all maxima)."""
    distances: Distances = Distances.spacing
    """Unit of ``radius`` and ``nms_radius``: multiples of the sampling spacing, or input units."""

    def check(self):
        if self.weights not in ("uniform", "gaussian"):
            raise ValueError(f"weights must be uniform or gaussian, got '{self.weights}'")
        if self.min_neighbors < 3 or self.max_neighbors < self.min_neighbors:
            raise ValueError("need 3 <= min_neighbors <= max_neighbors")


class EigenSalience:
    """Base of the 12 eigenvalue measures (see the module doc). A new measure of the eigenvalues of ``C_p`` (or
    of ``C_n``, with ``matrix = "cn"``) is a subclass that overrides :meth:`salience`."""

    Params = SalienceParams
    matrix = "cp"
    measure = "min_ratio"

    def __init__(self, params: SalienceParams):
        self.p = params

    def values(self, cloud: Cloud, spacing: float) -> np.ndarray:
        """Salience h of every point; -inf where there are fewer than ``min_neighbors`` neighbours."""
        if self.matrix == "cn" and cloud.normals is None:
            raise StageError(f"salience={self.name}: needs normals; {cloud.source} has none")
        r = to_abs(self.p.radius, self.p.distances, spacing)
        lp, ln, counts = eigen_features(cloud.points, cloud.normals if self.matrix == "cn" else None, r,
                                        self.p.max_neighbors, self.p.weights == "gaussian")
        h = self.salience(lp if self.matrix == "cp" else ln)
        return np.where(counts >= self.p.min_neighbors, h, -np.inf)

    def salience(self, lam: np.ndarray) -> np.ndarray:
        """The salience of each point from the eigenvalues (N, 3) of its covariance, ascending (l1, l2, l3)."""
        return measure_values(lam, self.measure)

    def keypoints(self, cloud: Cloud, spacing: float) -> np.ndarray:
        h = self.values(cloud, spacing)
        idx = non_maximum_suppression(cloud.points, h, to_abs(self.p.nms_radius, self.p.distances, spacing),
                                      self.p.max_neighbors)
        if self.p.top_k is not None and len(idx) > self.p.top_k:
            idx = idx[np.argsort(-h[idx], kind="stable")[: self.p.top_k]]
        return np.sort(idx)


for _mat, _mdoc in MATRICES.items():
    for _meas, _desc in MEASURES.items():
        _name = f"{_mat}_{_meas}"
        _cls = type(_name, (EigenSalience,), {
            "matrix": _mat, "measure": _meas,
            "__doc__": f"Salience {_desc} of the {_mdoc}; keypoints are its non-maximum-suppressed maxima.",
        })
        SALIENCE.register(_name)(_cls)


@SALIENCE.register("uniform")
class Uniform:
    """Voxel-grid keypoints: in every occupied voxel, the point nearest to the voxel's centroid."""

    @dataclass
    class Params:
        voxel: float = 5.0
        """Voxel edge length (see ``distances``)."""
        distances: Distances = Distances.spacing
        """Unit of ``voxel``: multiples of the sampling spacing, or absolute input units."""

    def __init__(self, params: Params):
        self.p = params

    def keypoints(self, cloud: Cloud, spacing: float) -> np.ndarray:
        return voxel_representatives(cloud.points, to_abs(self.p.voxel, self.p.distances, spacing))


@SALIENCE.register("iss")
class ISS:
    """Open3D's Intrinsic Shape Signatures detector (Zhong 2009), the comparator."""

    @dataclass
    class Params:
        salient_radius: float = 5.0
        """Neighbourhood radius of the scatter matrix (see ``distances``)."""
        non_max_radius: float = 5.0
        """Non-maximum suppression radius (see ``distances``)."""
        gamma_21: float = 0.975
        """Upper bound of l2/l3 (Open3D's ratio of the 2nd to the 1st largest eigenvalue)."""
        gamma_32: float = 0.975
        """Upper bound of l1/l2."""
        min_neighbors: int = 10
        """Points with fewer neighbours are never keypoints."""
        distances: Distances = Distances.spacing
        """Unit of the radii: multiples of the sampling spacing, or input units."""

    def __init__(self, params: Params):
        self.p = params

    def keypoints(self, cloud: Cloud, spacing: float) -> np.ndarray:
        import open3d as o3d
        from pykdtree.kdtree import KDTree

        p, u, s = self.p, self.p.distances, spacing
        points = cloud.points - far_offset(cloud.points)  # (the same points near the origin)
        pc = to_o3d(points)
        kp = o3d.geometry.keypoint.compute_iss_keypoints(
            pc, salient_radius=to_abs(p.salient_radius, u, s), non_max_radius=to_abs(p.non_max_radius, u, s),
            gamma_21=p.gamma_21, gamma_32=p.gamma_32, min_neighbors=p.min_neighbors)
        pts = np.asarray(kp.points)
        if len(pts) == 0:
            return np.zeros(0, np.int64)
        _, j = KDTree(points).query(pts, k=1)
        return np.unique(j.astype(np.int64))
