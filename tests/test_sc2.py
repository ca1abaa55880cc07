"""Issue #35, item 2: the second-order compatibility estimator (``coarse.estimator=sc2``, SC2-PCR): each piece
against a direct computation, and poses recovered from matches with few inliers."""

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from conftest import build_coarse
from scanreg.geometry import apply_T, horn_quaternion, random_pose, transform_errors
from scanreg.stages.coarse.sc2 import (best_hypothesis, consensus_sets, leading_eigenvector, sc2_pcr, spread_seeds,
                                       weighted_kabsch_batch)
from scanreg.types import Distances


def matches(M, n_in, seed, noise=0.005):
    """M matches of which the first n_in are inliers of a random pose T (noise sigma in units), the rest target
    points drawn anywhere in a box three times the source's."""
    rng = np.random.default_rng(seed)
    P1 = rng.uniform(0, 10, size=(M, 3))
    T = random_pose(rng, 180, 20)
    P0 = rng.uniform(-10, 20, size=(M, 3))
    P0[:n_in] = apply_T(T, P1[:n_in]) + rng.normal(scale=noise, size=(n_in, 3))
    return P0, P1, T


def compatibility(P0, P1, thr):
    """C by its definition, pair by pair."""
    M = len(P0)
    C = np.zeros((M, M))
    for i in range(M):
        for j in range(M):
            if i != j and abs(np.linalg.norm(P1[i] - P1[j]) - np.linalg.norm(P0[i] - P0[j])) < thr:
                C[i, j] = 1.0
    return C


def test_consensus_sets_follow_second_order_compatibility_by_hand():
    """SC2[s, j] = C[s, j] * #{k: C[s, k] and C[k, j]}, counted in loops; the first stage keeps the k1 largest,
    the second the k2 largest of SC2 recomputed among the seed and those k1."""
    P0, P1, _ = matches(60, 15, 1)
    C = compatibility(P0, P1, 0.05)
    seeds = np.array([0, 3, 40])
    k1, k2 = 12, 6
    got = consensus_sets(C.astype(np.float32), seeds, k1, k2)
    for s, row in zip(seeds, got):
        sc2 = np.array([C[s, j] * sum(C[s, k] * C[k, j] for k in range(60)) for j in range(60)])
        sc2[s] = -1
        first = np.argsort(-sc2, kind="stable")[:k1]
        pool = np.concatenate([[s], first])
        local = np.array([C[s, j] * sum(C[s, k] * C[k, j] for k in pool) for j in pool])
        local[0] = -1
        expected = np.concatenate([[s], pool[np.argsort(-local, kind="stable")[:k2]]])
        assert np.array_equal(row, expected)
    # an inlier seed gathers inliers only (15 inliers, compatible with each other and with few outliers)
    assert set(got[0]) <= set(range(15))


def test_leading_eigenvector_and_seeds_by_direct_computation():
    A = np.random.default_rng(2).random((30, 30))
    A = A + A.T
    w, V = np.linalg.eigh(A)
    assert np.allclose(leading_eigenvector(A, 200), np.abs(V[:, -1]), atol=1e-9)
    assert not leading_eigenvector(np.zeros((4, 4))).any()
    pts = np.array([[0.0, 0, 0], [0.5, 0, 0], [3.0, 0, 0], [3.2, 0, 0], [9.0, 0, 0]])
    score = np.array([0.9, 1.0, 0.2, 0.5, 0.1])
    # by score: 1 (blocks 0), 3 (blocks 2), 4
    assert spread_seeds(score, cdist(pts, pts), 1.0, 10).tolist() == [1, 3, 4]
    assert spread_seeds(score, cdist(pts, pts), 1.0, 2).tolist() == [1, 3]


def test_weighted_kabsch_matches_weighted_horn_and_ignores_zero_weights():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(2, 10, 3))
    T = random_pose(rng, 90, 5)
    tgt = apply_T(T, src.reshape(-1, 3)).reshape(2, 10, 3) + rng.normal(scale=0.01, size=(2, 10, 3))
    w = rng.random((2, 10))
    w[1, 7:] = 0.0
    tgt[1, 7:] += 100.0  # corrupted pairs without weight change nothing
    got = weighted_kabsch_batch(tgt, src, w)
    for b in range(2):
        assert np.allclose(got[b], horn_quaternion(tgt[b], src[b], w[b]), atol=1e-9)
    assert np.allclose(weighted_kabsch_batch(tgt[:1], src[:1], np.zeros((1, 10))), horn_quaternion(tgt[0], src[0]))


def test_best_hypothesis_counts_inliers_then_truncated_residuals():
    P1 = np.random.default_rng(5).normal(size=(8, 3))
    shifts = [0.0, 0.02, 0.5]  # all 8 within 0.1 for the first two; the first has the lower residual
    Ts = np.stack([np.eye(4)] * 3)
    for T, s in zip(Ts, shifts):
        T[0, 3] = s
    P0 = P1.copy()
    T, inl = best_hypothesis(Ts[::-1].copy(), P0, P1, 0.1, chunk=2)
    assert T[0, 3] == 0.0 and inl.all()


@pytest.mark.parametrize("n_in", [100, 40])
def test_sc2_recovers_a_pose_from_matches_with_few_inliers(n_in):
    """2000 matches, 5 % or 2 % inliers: the pose to within the inlier noise, every inlier found; the
    plain consensus of one seed's set (no second-order compatibility: the seed's k2 first-order neighbours)
    is what the estimator improves on, so the result is checked against the truth, not against itself."""
    P0, P1, T = matches(2000, n_in, 4)
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances=Distances.absolute, estimator="sc2")
    r = sc2_pcr(P0, P1, None, None, 0.05, st.p)
    rot, trans = transform_errors(r.T_target_source, T)
    assert rot < 0.02 and trans < 0.01, (rot, trans)  # measured 0.003 deg, 0.002 (noise 0.005)
    assert r.inliers[:n_in].all() and r.inliers.sum() <= n_in + 3
    assert np.array_equal(sc2_pcr(P0, P1, None, None, 0.05, st.p).T_target_source, r.T_target_source)


def test_estimator_is_checked():
    with pytest.raises(Exception, match="estimator"):
        build_coarse("lo_ransac", estimator="teaser")
    with pytest.raises(Exception, match="sc2_k2"):
        build_coarse("lo_ransac", estimator="sc2", sc2_k1=10, sc2_k2=20)
