"""Known answers that kill the mutants of the SC2-PCR estimator (./run mutants, issue #38): the seeds of matches
that all agree, the number of hypotheses, ties at the inlier threshold and between hypotheses (exact in
binary), and the refinement of a hypothesis with exactly three inliers."""

import math

import numpy as np
import pytest

from conftest import build_coarse
from scanreg.geometry import apply_T, horn_quaternion, random_pose
from scanreg.stages.coarse.sc2 import (best_hypothesis, consensus_sets, leading_eigenvector, sc2_pcr, spread_seeds,
                                       weighted_kabsch_batch)
from scanreg.types import Distances


def exact_matches(M, seed, n_in=None):
    """M matches whose first n_in (all by default) follow a pose exactly, source points at least 0.2 apart."""
    rng = np.random.default_rng(seed)
    T = random_pose(rng, 180, 20)
    P1 = np.zeros((0, 3))
    while len(P1) < M:  # rejection: every source point at least 0.2 from the others
        c = rng.uniform(0, 10, 3)
        if not len(P1) or np.linalg.norm(P1 - c, axis=1).min() > 0.2:
            P1 = np.vstack([P1, c])
    P0 = apply_T(T, P1)
    n_in = M if n_in is None else n_in
    P0[n_in:] = rng.uniform(-10, 20, size=(M - n_in, 3))
    return P0, P1, T


def test_matches_that_all_agree_give_one_hypothesis_per_seed_share():
    """50 exact matches: every pair is compatible, the compatibility matrix is all ones off the diagonal, no
    source point is within thr of another, so ceil(0.07 x 50) = 4 seeds (hypotheses) and the exact pose."""
    P0, P1, T = exact_matches(50, 1)
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances=Distances.absolute, estimator="sc2",
                      seed_share=0.07)
    r = sc2_pcr(P0, P1, None, None, 0.05, st.p)
    assert r.hypotheses == math.ceil(0.07 * 50) == 4
    assert r.inliers.all() and np.allclose(r.T_target_source, T, atol=1e-9)


def test_a_tiny_seed_share_still_gives_one_seed():
    """seed_share 0.001 of 20 matches is 0.02 seeds: at least one is kept."""
    P0, P1, T = exact_matches(20, 2)
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances=Distances.absolute, estimator="sc2",
                      seed_share=0.001)
    r = sc2_pcr(P0, P1, None, None, 0.05, st.p)
    assert r.hypotheses == 1 and r.inliers.all() and np.allclose(r.T_target_source, T, atol=1e-9)


def test_spread_seeds_blocks_strictly_within_the_radius():
    """A point exactly the radius (1.0) from a kept seed is not blocked; 0.75 from it is."""
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 0.75, 0]])
    d1 = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    assert spread_seeds(np.array([1.0, 0.5, 0.25]), d1, 1.0, 10).tolist() == [0, 1]


def test_best_hypothesis_inliers_are_strictly_within_thr_and_ties_keep_the_first():
    """Residuals 0.25 and 0.5 at thr 0.5 (exact): one inlier. Two hypotheses with no inlier have the same
    truncated cost (every residual counts thr^2): the first is kept."""
    P1 = np.zeros((2, 3))
    P0 = np.array([[0.25, 0.0, 0.0], [0.0, 0.5, 0.0]])
    T, inl = best_hypothesis(np.stack([np.eye(4)]), P0, P1, 0.5)
    assert inl.tolist() == [True, False]
    far = np.stack([np.eye(4), np.eye(4)])
    far[0, :3, 3], far[1, :3, 3] = [10.0, 0, 0], [0, 20.0, 0]
    T, inl = best_hypothesis(far, P0, P1, 0.5)
    assert not inl.any() and np.array_equal(T, far[0])


def test_best_hypothesis_by_brute_force():
    """Integer points, translations by dyadic steps (every residual exact), thr 0.5 (thr^2 = 0.25), the last 4
    target points moved 0.75 along x. Hypotheses in blocks of 3: the most inliers wins, then the lowest sum of
    squared residuals truncated at thr^2, then the first; checked against that rule applied by hand."""
    rng = np.random.default_rng(3)
    P1 = rng.integers(0, 10, size=(8, 3)).astype(float)
    P0 = P1.copy()
    P0[4:, 0] += 0.75
    steps = np.array([[1.0, 0, 0], [0, 0, 0], [0.375, 0, 0], [0, 0.25, 0], [0.5, 0, 0], [0.25, 0, 0], [0, 0, 0.25],
                      [0.75, 0, 0], [0, 0, -0.25]])
    Ts = np.stack([np.eye(4)] * len(steps))
    Ts[:, :3, 3] = steps

    def by_hand(ids):
        res = [np.sum((P1 + steps[b] - P0) ** 2, axis=1) for b in ids]
        key = [(-int((r < 0.25).sum()), float(np.minimum(r, 0.25).sum()), i) for i, r in enumerate(res)]
        return ids[min(key)[2]], res[min(key)[2]] < 0.25

    for ids, want in (([0, 1, 2, 3, 4, 5, 6, 7, 8], 2),  # 0.375: all 8 within thr
                      ([8, 7, 6, 5, 4, 3, 2, 1, 0], 2),
                      ([0, 1, 3, 4, 5, 6, 7, 8], 1),  # 4 inliers each; 0 and 0.75 cost 1, the others 1.25: the first
                      ([0, 7, 3, 1], 7),
                      ([0, 3, 6, 8], 0)):  # 4 inliers each and the same cost: the first
        assert by_hand(ids)[0] == want
        T, inl = best_hypothesis(Ts[ids], P0, P1, 0.5, chunk=3)
        assert np.array_equal(T, Ts[want]) and np.array_equal(inl, by_hand(ids)[1])


def test_consensus_sets_by_hand_with_a_seed_of_few_compatible_matches():
    """A random compatibility matrix in which seed 0 is compatible with only two matches: its first stage takes
    those two, then matches of zero SC2 in index order, never the seed itself (k1 = 5); the second stage picks the
    k2 = 3 highest SC2 with the seed within that pool. Against the definition in loops."""
    rng = np.random.default_rng(7)
    M = 12
    C = np.triu((rng.random((M, M)) < 0.5).astype(float), 1)
    C = C + C.T
    C[0, :] = C[:, 0] = 0.0
    C[0, [4, 7]] = C[[4, 7], 0] = 1.0
    for seeds in (np.array([0]), np.array([0, 5, 9]), np.arange(M)):
        got = consensus_sets(C.astype(np.float32), seeds, 5, 3)
        for s, row in zip(seeds, got):
            sc2 = np.array([C[s, j] * sum(C[s, k] * C[k, j] for k in range(M)) for j in range(M)])
            sc2[s] = -1
            pool = np.concatenate([[s], np.argsort(-sc2, kind="stable")[:5]])
            local = np.array([C[s, j] * sum(C[s, k] * C[k, j] for k in pool) for j in pool])
            local[0] = -1
            assert np.array_equal(row, np.concatenate([[s], pool[np.argsort(-local, kind="stable")[:3]]]))
    assert got[0].tolist()[:1] == [0] and 0 not in got[0].tolist()[1:]


def test_weighted_kabsch_with_small_weights_and_a_row_without_weight():
    """Weights summing to less than 1 weigh the pairs (not replaced by uniform ones); a row whose weights are all
    zero is fitted unweighted whatever the other rows hold."""
    rng = np.random.default_rng(8)
    src = rng.normal(size=(2, 10, 3))
    T = random_pose(rng, 90, 5)
    tgt = apply_T(T, src.reshape(-1, 3)).reshape(2, 10, 3) + rng.normal(scale=0.05, size=(2, 10, 3))
    w = np.zeros((2, 10))
    w[0] = rng.random(10) * 0.05  # sum about 0.25
    got = weighted_kabsch_batch(tgt, src, w)
    assert np.allclose(got[0], horn_quaternion(tgt[0], src[0], w[0]), atol=1e-9)
    assert np.allclose(got[1], horn_quaternion(tgt[1], src[1]), atol=1e-9)
    assert np.abs(horn_quaternion(tgt[0], src[0], w[0]) - horn_quaternion(tgt[0], src[0])).max() > 1e-3


def test_leading_eigenvector_of_a_matrix_of_small_norm():
    """0.1 (J - I) for 3 x 3: |A v| < 1 from the start, and the eigenvector is still the normalised ones."""
    A = 0.1 * (np.ones((3, 3)) - np.eye(3))
    assert np.allclose(leading_eigenvector(A), np.ones(3) / np.sqrt(3), atol=1e-12)
    for iterations in (1, 2, 20):  # a zero matrix: zeros, however many iterations
        assert np.array_equal(leading_eigenvector(np.zeros((4, 4)), iterations), np.zeros(4))


def test_three_inliers_are_refined_with_their_normals():
    """3 noisy inliers (with normals) among 20 matches far from agreeing: the estimator's hypothesis fits the 3
    points, and with exactly 3 inliers it is still refined: the result is the points-and-normals least squares
    over them (SVD here, normal weight 100 x thr^2), not the points-only fit."""
    from test_mutants_ransac import fit_points_normals

    rng = np.random.default_rng(10)
    thr, M = 0.05, 23
    T = random_pose(rng, 180, 20)
    P1 = rng.uniform(0, 10, size=(M, 3))
    P0 = rng.uniform(-10, 20, size=(M, 3))
    P0[:3] = apply_T(T, P1[:3]) + rng.normal(scale=0.003, size=(3, 3))
    N1 = rng.normal(size=(M, 3))
    N1 /= np.linalg.norm(N1, axis=1, keepdims=True)
    N0 = N1 @ T[:3, :3].T + rng.normal(scale=0.03, size=(M, 3))
    N0 /= np.linalg.norm(N0, axis=1, keepdims=True)
    st = build_coarse("lo_ransac", distance_threshold=thr, distances=Distances.absolute, estimator="sc2",
                      normal_weight=100.0)
    r = sc2_pcr(P0, P1, N0, N1, thr, st.p)
    assert r.inliers.tolist() == [True] * 3 + [False] * (M - 3)
    want = fit_points_normals(P0[:3], P1[:3], N0[:3], N1[:3], 100.0 * thr * thr)
    assert np.allclose(r.T_target_source, want, atol=1e-9)
    assert np.abs(want - fit_points_normals(P0[:3], P1[:3], N0[:3], N1[:3], 0.0)).max() > 1e-4


@pytest.mark.parametrize("n_in", [30, 12])
def test_sc2_finds_inliers_scattered_among_the_matches(n_in):
    """300 matches of which 30 or 12 (10 %, 4 %) are inliers of a pose (noise 0.005, thr 0.05) at random places
    in the list: every inlier is found and no outlier, and the pose is the least squares fit over them (SVD
    here): nothing in the estimator may lean on the inliers coming first."""
    rng = np.random.default_rng(9 + n_in)
    M = 300
    T = random_pose(rng, 180, 20)
    P1 = rng.uniform(0, 10, size=(M, 3))
    P0 = rng.uniform(-10, 20, size=(M, 3))
    idx = rng.permutation(M)[:n_in]
    P0[idx] = apply_T(T, P1[idx]) + rng.normal(scale=0.005, size=(n_in, 3))
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances=Distances.absolute, estimator="sc2")
    r = sc2_pcr(P0, P1, None, None, 0.05, st.p)
    assert sorted(np.flatnonzero(r.inliers)) == sorted(idx)
    m1, m0 = P1[idx].mean(axis=0), P0[idx].mean(axis=0)
    U, _, Vt = np.linalg.svd((P1[idx] - m1).T @ (P0[idx] - m0))
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    assert np.allclose(r.T_target_source[:3, :3], R, atol=1e-9)
    assert np.allclose(r.T_target_source[:3, 3], m0 - R @ m1, atol=1e-9)
