"""Second-order spatial compatibility (SC2-PCR; Chen et al., CVPR 2022) over point correspondences: the
estimator of ``coarse=lo_ransac`` with ``estimator: sc2``, built for low inlier ratios.

Two correspondences are compatible when they keep their distance under a rigid motion (the distance between
their source points equals that between their target points to within the inlier threshold): the 0/1 matrix C.
Two inliers are compatible, and so are both with every other inlier, whereas an outlier is compatible with an
inlier only by chance and with few others; the second-order compatibility SC2 = C * (C C) (elementwise times
the number of correspondences compatible with both) therefore separates inliers from outliers far more sharply
than C, even when inliers are a few per cent. The estimator

1. scores every correspondence by the leading eigenvector of C (spectral matching) and keeps as seeds the best
   ones, at most ``seed_share`` of them, none within the inlier threshold of a better seed's source point;
2. grows each seed's consensus set in two stages: the ``sc2_k1`` correspondences of highest SC2 with the seed,
   then among those the ``sc2_k2`` of highest SC2 with the seed recomputed within that set;
3. fits each set by least squares weighted with the leading eigenvector of its own SC2 matrix (one hypothesis
   per seed, no random draws);
4. keeps the hypothesis with the most inliers over all correspondences (ties: the lower truncated squared
   residual sum), refines it by least squares on its inliers as LO-RANSAC does, and refits with normals.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

from scanreg.geometry import kabsch_batch
from scanreg.stages.coarse.ransac import RansacResult, final_fit, refine


def sc2_pcr(P0: np.ndarray, P1: np.ndarray, N0: np.ndarray | None, N1: np.ndarray | None, thr: float,
            p) -> RansacResult:
    """The best rigid transform for the correspondences ``P1[i] -> P0[i]`` (target points ``P0``, source points
    ``P1``, normals ``N0``, ``N1`` or None) at inlier threshold ``thr`` (input units), with the parameters ``p``
    of ``coarse=lo_ransac`` (``seed_share``, ``sc2_k1``, ``sc2_k2``, ``lo_iterations``, ``normal_weight``).
    Deterministic: no random draws. ``hypotheses`` counts the seeds."""
    M = len(P0)
    d1 = cdist(P1, P1)
    C = (np.abs(d1 - cdist(P0, P0)) < thr).astype(np.float32)
    np.fill_diagonal(C, 0.0)
    seeds = spread_seeds(leading_eigenvector(C), d1, thr, int(np.ceil(p.seed_share * M)))  # >= 1: share > 0
    sets = consensus_sets(C, seeds, min(p.sc2_k1, M - 1), min(p.sc2_k2, M - 1))
    # the weights of each set: the leading eigenvector of its own SC2 matrix
    Cl = C[sets[:, :, None], sets[:, None, :]]
    W = np.stack([leading_eigenvector(c * (c @ c)) for c in Cl]).astype(np.float64)
    Ts = weighted_kabsch_batch(P0[sets], P1[sets], W)
    T, inl = best_hypothesis(Ts, P0, P1, thr)
    if inl.sum() >= 3:
        T, inl = refine(P0, P1, thr, T, p.lo_iterations)
        T, inl = final_fit(P0, P1, N0, N1, thr, p.normal_weight, T, inl)
    return RansacResult(T, inl, len(seeds))


def leading_eigenvector(A: np.ndarray, iterations: int = 20) -> np.ndarray:
    """The leading eigenvector of a symmetric non-negative matrix by power iteration from the all-ones vector
    (entries >= 0, unit length; zeros when ``A`` is zero)."""
    v = np.ones(len(A), A.dtype)
    for _ in range(iterations):
        w = A @ v
        n = np.linalg.norm(w)
        if not n > 0:
            return np.zeros(len(A), A.dtype)
        v = w / n
    return v


def spread_seeds(score: np.ndarray, d1: np.ndarray, radius: float, most: int) -> np.ndarray:
    """Non-maximum suppression: correspondences by decreasing ``score``, each kept unless a kept one's source
    point lies within ``radius`` of its own (``d1``: source-point distances); at most ``most``."""
    order = np.argsort(-score, kind="stable")
    kept: list[int] = []
    blocked = np.zeros(len(score), bool)
    for i in order:
        if blocked[i]:
            continue
        kept.append(int(i))
        if len(kept) == most:
            break
        blocked |= d1[i] < radius
    return np.array(kept, np.int64)


def consensus_sets(C: np.ndarray, seeds: np.ndarray, k1: int, k2: int) -> np.ndarray:
    """Each seed's consensus set (S, k2 + 1), the seed first: its ``k1`` correspondences of highest SC2 with it,
    then the ``k2`` of those of highest SC2 with it within the ``k1`` and the seed."""
    Cs = C[seeds]
    sc2 = Cs * (Cs @ C)
    sc2[np.arange(len(seeds)), seeds] = -np.inf  # the seed itself joins as the first member, not as a candidate
    first = np.argsort(-sc2, axis=1, kind="stable")[:, :k1]
    pool = np.concatenate([seeds[:, None], first], axis=1)  # (S, k1 + 1), the seed at 0
    Cl = C[pool[:, :, None], pool[:, None, :]]
    local = np.einsum("sj,sj->sj", Cl[:, 0, :], np.einsum("sk,skj->sj", Cl[:, 0, :], Cl))
    local[:, 0] = -np.inf
    second = np.argsort(-local, axis=1, kind="stable")[:, :k2]
    return np.concatenate([seeds[:, None], np.take_along_axis(pool, second, axis=1)], axis=1)


def weighted_kabsch_batch(target: np.ndarray, source: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Batched weighted least-squares rigid transforms: ``target, source`` (B, k, 3), weights (B, k) >= 0 ->
    ``T_target_source`` (B, 4, 4); a set whose weights are all zero is fitted unweighted."""
    return kabsch_batch(target, source, np.where(w.sum(axis=1, keepdims=True) > 0, w, 1.0))


def best_hypothesis(Ts: np.ndarray, P0: np.ndarray, P1: np.ndarray, thr: float,
                    chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The hypothesis with the most correspondences within ``thr`` (ties: the lower sum of squared residuals
    truncated at ``thr``) and its inlier mask."""
    counts, cost = np.zeros(len(Ts), np.int64), np.zeros(len(Ts))
    for c0 in range(0, len(Ts), chunk):
        T = Ts[c0:c0 + chunk]
        r = P1 @ T[:, :3, :3].transpose(0, 2, 1) + (T[:, None, :3, 3] - P0)
        sq = np.einsum("bmi,bmi->bm", r, r)
        counts[c0:c0 + chunk] = (sq < thr * thr).sum(axis=1)
        cost[c0:c0 + chunk] = np.minimum(sq, thr * thr).sum(axis=1)
    T = Ts[np.lexsort((cost, -counts))[0]]  # the most inliers, then the lowest cost, then the first
    d = P1 @ T[:3, :3].T + T[:3, 3] - P0
    return T, np.einsum("ij,ij->i", d, d) < thr * thr
