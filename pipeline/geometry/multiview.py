"""Multi-view refinement: every scan aligned to the others at once (point-to-plane, all poses together).

For each linked pair of scans, points of one (a spread subset) are paired with their closest points on the
other, in both directions; the squared point-to-plane distances of all pairs, robustly weighted, are minimised
over all poses but the anchor's, linearised about the current poses (Gauss-Newton), and the pairs found again,
as ICP does for two scans. This is the simultaneous form of Pulli's (1999) and MeshLab's global alignment: no
scan is aligned to one neighbour only, so no error is left concentrated on one edge.
"""

from __future__ import annotations

import numpy as np

from scanreg.geometry.containers import Cloud
from scanreg.geometry.neighbours import ClosestPoints
from scanreg.geometry.posegraph import gauss_newton_step
from scanreg.geometry.transforms import apply_T, invert_T
from scanreg.geometry.voxels import morton_order


def spread_subset(cloud: Cloud, k: int) -> Cloud:
    """At most ``k`` points of ``cloud`` spread over it (every m-th along a Morton curve)."""
    if cloud.n_points <= k:
        return cloud
    order = morton_order(cloud.points)
    return cloud.subset(np.sort(order[:: int(np.ceil(cloud.n_points / k))]))


def refine_jointly(clouds: list[Cloud], poses: list[np.ndarray], links: list[tuple[int, int]],
                   max_distances: list[float], kernel_scale: float, anchor: int = 0, samples: int = 5000,
                   iterations: int = 10, tol: float = 1e-9,
                   link_scales: list[float] | None = None) -> tuple[list[np.ndarray], dict[str, float]]:
    """The poses ``T_world_scan`` refined jointly over the ``links`` (pairs of scan indices that overlap), at each
    pair limit of ``max_distances`` in turn (input units, widest first) for up to ``iterations`` Gauss-Newton
    steps; Geman-McClure weights at ``kernel_scale`` (input units); ``link_scales``: a factor per link on both
    (scans sampled more coarsely pair at their own spacing; None: 1). ``clouds`` need normals. Returns the poses
    and the final RMS point-to-plane distance (``multiview_rms``) and the pairs used (``multiview_pairs``)."""
    poses = [np.array(T, dtype=float) for T in poses]
    n = len(clouds)
    free = [k for k in range(n) if k != anchor]
    col = {k: 6 * m for m, k in enumerate(free)}
    search = {k: ClosestPoints(clouds[k]) for k in {a for link in links for a in link}}
    subsets = {k: spread_subset(clouds[k], samples) for k in search}
    rms, used = float("nan"), 0
    for limit in max_distances:
        for _ in range(iterations):
            H = np.zeros((6 * len(free), 6 * len(free)))
            g = np.zeros(6 * len(free))
            sq, used = 0.0, 0
            for (a, b), f in zip(links, link_scales or [1.0] * len(links), strict=True):
                for i, j in ((a, b), (b, a)):  # points of j paired on scan i
                    J, r = _pairs(search[i], subsets[j], poses[i], poses[j], limit * f)
                    if not len(r):
                        continue
                    w = 1.0 / (1.0 + (r / (kernel_scale * f)) ** 2) ** 2
                    sq, used = sq + float(r @ r), used + len(r)
                    blocks = [(j, J), (i, -J)]
                    for node, Jn in blocks:
                        if node == anchor:
                            continue
                        g[col[node]:col[node] + 6] += (Jn * w[:, None]).T @ r
                        for other, Jo in blocks:
                            if other != anchor:
                                H[col[node]:col[node] + 6, col[other]:col[other] + 6] += (Jn * w[:, None]).T @ Jo
            rms = float(np.sqrt(sq / used)) if used else float("nan")
            if not free or not used or gauss_newton_step(H, g, poses, free, col, tol):
                break
    return poses, {"multiview_rms": rms, "multiview_pairs": float(used)}


def _pairs(search: ClosestPoints, points: Cloud, pose_i: np.ndarray, pose_j: np.ndarray,
           limit: float) -> tuple[np.ndarray, np.ndarray]:
    """The point-to-plane residuals of ``points`` (of scan j) on scan i (``search``, in scan i's frame) within
    ``limit``, and their Jacobians (N, 6) for left perturbations ``(w, v)`` of scan j's pose in the world frame
    (scan i's are their negatives): ``r = N . (P - Q)``, ``dr/dw = P x N``, ``dr/dv = N`` in world coordinates."""
    p = apply_T(invert_T(pose_i) @ pose_j, points.points)
    q, d, qn = search(p, limit)
    ok = d <= limit
    if qn is None or not ok.any():
        return np.zeros((0, 6)), np.zeros(0)
    R = pose_i[:3, :3]
    P, Q, N = apply_T(pose_i, p[ok]), apply_T(pose_i, q[ok]), qn[ok] @ R.T
    r = np.einsum("ij,ij->i", P - Q, N)
    return np.hstack([np.cross(P, N), N]), r
