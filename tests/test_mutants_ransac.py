"""Known answers that kill the mutants of LO-RANSAC (./run mutants, issue #38): the final fit with normals in closed
form (SVD, written here) over the inliers it returns, with three inliers and with thirty; the guided sampler's
all-inlier probability against its formula counted by brute force; the iteration count's edge cases; local
optimisation from the candidate (lo_iterations=0, fewer than 3 inliers: the finding the mutants made); and the
thresholds' ties, placed exactly with integer points and dyadic distances."""

import math

import numpy as np
import pytest

from conftest import build_coarse
from scanreg.geometry import apply_T, random_pose
from scanreg.stages.coarse.ransac import PER_SEED, _Search, inliers_at, lo_ransac


def fit_points_normals(P0, P1, N0, N1, w):
    """argmin over rigid (R, t) of sum |R p1 + t - p0|^2 + w sum |R n1 - n0|^2, by SVD (Kabsch with the normals'
    term added to the cross-covariance; a reflection corrected)."""
    m1, m0 = P1.mean(axis=0), P0.mean(axis=0)
    H = (P1 - m1).T @ (P0 - m0) + w * N1.T @ N0
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, m0 - R @ m1
    return T


def noisy_case(n_in, n_out, seed):
    """n_in correspondences of a pose with 0.01 of noise on the points and a few degrees on the normals (some
    source normals given the other way round), then n_out random ones far from agreeing."""
    rng = np.random.default_rng(seed)
    T = random_pose(rng, 180, 5.0)
    P1 = rng.uniform(-3, 3, (n_in + n_out, 3))
    N1 = rng.normal(size=P1.shape)
    N1 /= np.linalg.norm(N1, axis=1, keepdims=True)
    P0 = apply_T(T, P1) + rng.normal(scale=0.01, size=P1.shape)
    N0 = N1 @ T[:3, :3].T + rng.normal(scale=0.05, size=P1.shape)
    N0 /= np.linalg.norm(N0, axis=1, keepdims=True)
    P0[n_in:] = rng.uniform(-20, 20, (n_out, 3))
    N1[::3] *= -1  # unoriented: the fit turns them to agree with the current pose
    return P0, P1, N0, N1, T


@pytest.mark.parametrize("weight", [1.0, 100.0])  # the default, and normals weighing as much as points 1 apart
@pytest.mark.parametrize("n_in, n_out", [(3, 5), (30, 30)])
@pytest.mark.parametrize("sampling", ["guided", "uniform"])
def test_the_final_fit_is_the_points_and_normals_least_squares_over_the_inliers(n_in, n_out, sampling, weight):
    thr = 0.1
    P0, P1, N0, N1, T = noisy_case(n_in, n_out, 7)
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute", sampling=sampling, seed=2,
                      normal_weight=weight)
    r = lo_ransac(P0, P1, N0, N1, thr, st.p, st.p.seed)
    inl = r.inliers
    assert inl[:n_in].all() and not inl[n_in:].any()
    R = r.T_target_source[:3, :3]
    n1 = np.where((np.einsum("ij,ij->i", N1 @ R.T, N0) < 0)[:, None], -N1, N1)
    want = fit_points_normals(P0[inl], P1[inl], N0[inl], n1[inl], st.p.normal_weight * thr * thr)
    assert np.allclose(r.T_target_source, want, atol=1e-9)
    points_only = fit_points_normals(P0[inl], P1[inl], N0[inl], n1[inl], 0.0)
    assert np.abs(want - points_only).max() > (1e-4 if weight > 1 else 1e-8)  # the normals' term matters here


def guided_shares(n_in, M=400, thr=0.05):
    """n_in noisy inliers of a pose among M matches, found by guided LO-RANSAC: the result, and per inlier i the
    share of inliers in C_i = {c : |d1(i, c) - d0(i, c)| < 2 thr} (i included), by brute force."""
    rng = np.random.default_rng(11)
    T = random_pose(rng, 180, 5.0)
    P1 = rng.uniform(0, 10, (M, 3))
    P0 = rng.uniform(-5, 15, (M, 3))
    P0[:n_in] = apply_T(T, P1[:n_in]) + rng.normal(scale=0.005, size=(n_in, 3))
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute", seed=1)
    r = lo_ransac(P0, P1, None, None, thr, st.p, st.p.seed)
    assert r.inliers[:n_in].all() and r.inliers.sum() == n_in
    d1 = np.linalg.norm(P1[:, None] - P1[None], axis=2)
    d0 = np.linalg.norm(P0[:, None] - P0[None], axis=2)
    C = np.abs(d1 - d0)[:n_in] < 2 * thr
    return r, C[:, :n_in].sum(axis=1) / C.sum(axis=1)


def test_guided_all_inlier_probability_by_brute_force():
    """q = w (1 - (1 - r^2)^8): w the final model's inlier share, r the mean over its inliers of their shares
    (guided_shares). With at most 32 inliers every one of them enters the mean."""
    r, share = guided_shares(32)  # 32: the most that enter the mean all
    r_share = share.mean()
    assert 0.5 < r_share < 0.99  # outliers in the compatible sets (measured 0.92): the share is not 1
    assert r.all_inlier_probability == pytest.approx(32 / 400 * (1 - (1 - r_share ** 2) ** PER_SEED), rel=1e-12)


def test_guided_sampling_with_exactly_three_correspondences():
    """Three correspondences of a pose: each seed's compatible set is the other two, enough for a sample."""
    rng = np.random.default_rng(3)
    T = random_pose(rng, 180, 5.0)
    P1 = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 3.0, 0]])
    st = build_coarse("lo_ransac", distance_threshold=0.1, distances="absolute", seed=0)
    r = lo_ransac(apply_T(T, P1), P1, None, None, 0.1, st.p, st.p.seed)
    assert r.inliers.all() and np.allclose(r.T_target_source, T, atol=1e-9)
    # every inlier's compatible set is all inliers (r = 1) and w = 1: q = 1, one batch of 64 x 8 is enough
    assert r.all_inlier_probability == 1.0 and r.hypotheses == 512


def test_hypotheses_needed_for_an_all_inlier_probability():
    st = build_coarse("lo_ransac", miss_probability=0.01, max_iterations=5000)
    s = _Search(np.zeros((3, 3)), np.zeros((3, 3)), 0.1, st.p)
    assert s.needed_for(0.5) == math.ceil(math.log(0.01) / math.log(0.5)) == 7
    assert s.needed_for(0.0) == 5000 and s.needed_for(-0.1) == 5000  # no model yet: the most
    assert s.needed_for(1.0) == 1  # certain: log(1 - q) held at log(1e-12), one hypothesis


def test_a_sample_is_valid_when_its_sides_agree_within_thr_and_it_is_not_near_collinear():
    """Samples (source triangle a, target triangle b): b is a moved 10 away, its sides agree exactly, or one
    side is 0.9 thr or exactly thr longer (strict); a's cross product |(a1 - a0) x (a2 - a0)| must exceed thr^2
    / 2 (thr = 1: right triangles with legs 1 and h, cross product h)."""
    st = build_coarse("lo_ransac")
    s = _Search(np.zeros((3, 3)), np.zeros((3, 3)), 1.0, st.p)
    tri = lambda h, stretch=0.0: np.array([[0.0, 0, 0], [1.0 + stretch, 0, 0], [0, h, 0]]) + [3.0, 2.0, 1.0]  # noqa: E731
    a = np.stack([tri(1.0), tri(0.4), tri(0.75), tri(2.0), tri(2.0)])
    b = np.stack([tri(1.0), tri(0.4), tri(0.75), tri(2.0, 0.9), tri(2.0, 1.0)]) + [10.0, 0, 0]
    # sides of the 4th: 1.9 vs 1 (0.9 off), sqrt(1.9^2 + 4) vs sqrt(5) (0.52 off); of the 5th: 2 vs 1, exactly 1 off
    assert s.valid(a, b).tolist() == [True, False, True, True, False]


@pytest.mark.parametrize("sampling", ["uniform", "guided"])
@pytest.mark.parametrize("seed", range(6))
def test_ransac_keeps_the_largest_consensus(seed, sampling):
    """Two rigid structures among the matches: 45 % follow one pose, 40 % another, the rest are random. Both
    samplers find samples of both in their first batch; the model kept is the one with more inliers, whichever
    they met first."""
    rng = np.random.default_rng(100 + seed)
    M, thr = 200, 0.05
    P1 = rng.uniform(0, 10, (M, 3))
    P0 = rng.uniform(-10, 20, (M, 3))
    T1, T2 = random_pose(rng, 180, 5.0), random_pose(rng, 180, 5.0)
    P0[:90] = apply_T(T1, P1[:90])
    P0[90:170] = apply_T(T2, P1[90:170])
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute", sampling=sampling, seed=seed)
    r = lo_ransac(P0, P1, None, None, thr, st.p, st.p.seed)
    assert r.inliers[:90].all() and r.inliers.sum() == 90
    assert np.allclose(r.T_target_source, T1, atol=1e-9)


def seed_0_batch(rng_seed, noise, scale=1.0):
    """300 matches, the first 120 inliers of a pose with noise ``noise`` x thr (thr 0.05 x scale), and one guided
    batch whose 64 seeds are all correspondence 0: the matches, thr, |d1 - d0| from each seed, the hypotheses
    and their counts."""
    rng = np.random.default_rng(rng_seed)
    M, thr = 300, 0.05 * scale
    T = random_pose(rng, 180, 5.0 * scale)
    P1 = rng.uniform(0, 10, (M, 3)) * scale
    P0 = rng.uniform(-5, 15, (M, 3)) * scale
    P0[:120] = apply_T(T, P1[:120]) + rng.normal(scale=noise * thr, size=(120, 3))
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute")
    s = _Search(P0, P1, thr, st.p)
    seeds = np.zeros(64, np.int64)
    diff = np.abs(s._d1(seeds) - s._d0(seeds))
    return (P0, P1, thr, diff) + s._guided_batch(np.random.default_rng(0), seeds, diff)


@pytest.mark.parametrize("scale", [1.0, 100.0])
def test_guided_hypotheses_are_scored_on_their_seeds_compatible_set(scale):
    """One guided batch whose 64 seeds are all correspondence 0 (an inlier): 512 samples, more hypotheses than
    one block of 64. Each hypothesis's count is, by brute force, the correspondences within thr of it (squared
    distance) among those compatible with the seed (|d1 - d0| < 2 thr); at two scales (thr 0.05 and 5), so that
    the pool's width is not mistaken for another expression of thr."""
    P0, P1, thr, diff, Ts, counts = seed_0_batch(5, 0.4, scale)
    assert len(Ts) > 64
    pool = np.flatnonzero(diff[0] < 2 * thr)
    for Th, c in zip(Ts, counts):
        r = apply_T(Th, P1[pool]) - P0[pool]
        assert c == (np.einsum("ij,ij->i", r, r) < thr * thr).sum()
    assert counts.max() >= 60  # the all-inlier hypotheses see most inliers


def test_local_optimisation_refits_a_candidate_until_its_inliers_settle():
    """A candidate 0.8 degrees off the pose of 40 noisy inliers (thr 0.05): it holds part of them; local
    optimisation refits on its inliers until they stop changing, and the best model is that fit (Kabsch by SVD
    here, over its own inliers) with more inliers than the candidate."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(8)
    M, thr = 60, 0.05
    T = random_pose(rng, 180, 2.0)
    P1 = rng.uniform(-3, 3, (M, 3))
    P0 = rng.uniform(-10, 10, (M, 3))
    P0[:40] = apply_T(T, P1[:40]) + rng.normal(scale=0.01, size=(40, 3))
    cand = T.copy()
    cand[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(0.8)]).as_matrix() @ T[:3, :3]
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute")
    s = _Search(P0, P1, thr, st.p)
    n_cand = int(inliers_at(cand, P0, P1, thr).sum())
    s.accept(cand)
    assert n_cand < 40 and s.best_n == 40 and s.best_inl[:40].all()
    P0i, P1i = P0[s.best_inl], P1[s.best_inl]
    m1, m0 = P1i.mean(axis=0), P0i.mean(axis=0)
    U, _, Vt = np.linalg.svd((P1i - m1).T @ (P0i - m0))
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    assert np.allclose(s.best_T[:3, :3], R, atol=1e-9) and np.allclose(s.best_T[:3, 3], m0 - R @ m1, atol=1e-9)
    # a candidate 0.05 degrees off already holds all 40: the refit, as many inliers, replaces it
    near = T.copy()
    near[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(0.05)]).as_matrix() @ T[:3, :3]
    s = _Search(P0, P1, thr, st.p)
    s.accept(near)
    assert s.best_n == 40 and np.allclose(s.best_T[:3, :3], R, atol=1e-9) and not np.allclose(s.best_T, near)


def test_uniform_ransac_draws_exactly_max_iterations_without_a_model():
    """Random correspondences (no rigid triple agrees within a tight thr): no model, the identity, and exactly
    max_iterations hypotheses drawn in batches of 64 (64 + 36)."""
    rng = np.random.default_rng(9)
    P0, P1 = rng.uniform(0, 10, (50, 3)), rng.uniform(0, 10, (50, 3))
    st = build_coarse("lo_ransac", distance_threshold=1e-4, distances="absolute", sampling="uniform", batch=64,
                      min_iterations=1, max_iterations=100)
    r = lo_ransac(P0, P1, None, None, 1e-4, st.p, st.p.seed)
    assert r.hypotheses == 100 and not r.inliers.any() and np.array_equal(r.T_target_source, np.eye(4))
    assert r.all_inlier_probability == 0.0


def test_guided_sampling_stops_at_max_iterations_and_goes_on_past_barren_batches():
    """Six exact inliers among 300 (thr 1e-3): many batches of 64 seeds hold no inlier seed and yield no
    hypothesis; the search goes on past them, finds the pose, and since its all-inlier probability (w = 2 %)
    asks for more hypotheses than max_iterations (1024, two batches of 512), it stops there."""
    for seed in range(3):
        rng = np.random.default_rng(20 + seed)
        M = 300
        T = random_pose(rng, 180, 5.0)
        P1 = rng.uniform(0, 10, (M, 3))
        P0 = rng.uniform(-5, 15, (M, 3))
        P0[:6] = apply_T(T, P1[:6])
        st = build_coarse("lo_ransac", distance_threshold=1e-3, distances="absolute", seed=seed, max_iterations=1024,
                          min_iterations=1)
        r = lo_ransac(P0, P1, None, None, 1e-3, st.p, st.p.seed)
        assert r.inliers.sum() == 6 and np.allclose(r.T_target_source, T, atol=1e-9), seed
        assert r.hypotheses == 1024 and 0 < r.all_inlier_probability <= 6 / M


def exact_case(seed, n_in=150, n_out=50):
    """n_in exact correspondences of a pose about 120 degrees from the identity, then n_out random ones."""
    rng = np.random.default_rng(seed)
    T = random_pose(rng, 180, 5.0)
    P1 = rng.uniform(-3, 3, (n_in + n_out, 3))
    P0 = apply_T(T, P1)
    P0[n_in:] = rng.uniform(-20, 20, (n_out, 3))
    return P0, P1, T


@pytest.mark.parametrize("estimator, sampling", [("ransac", "guided"), ("ransac", "uniform"), ("sc2", "guided")])
def test_without_local_optimisation_the_pose_is_the_best_candidates(estimator, sampling):
    """coarse.lo_iterations=0 (LO-RANSAC without its local optimisation): the pose of 150 exact inliers among 200
    matches, not the identity with the inliers of the pose (what local optimisation starting from the identity
    returned when its loop did not run: a pose 121 degrees off reported with all 150 inliers)."""
    from scanreg.geometry import rotation_angle_deg
    from scanreg.stages.coarse.sc2 import sc2_pcr

    thr = 0.05
    P0, P1, T = exact_case(31)
    assert rotation_angle_deg(T[:3, :3]) > 60  # the identity is far from the pose
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute", sampling=sampling,
                      estimator=estimator, lo_iterations=0)
    r = (lo_ransac(P0, P1, None, None, thr, st.p, st.p.seed) if estimator == "ransac"
         else sc2_pcr(P0, P1, None, None, thr, st.p))
    assert r.inliers[:150].all() and r.inliers.sum() == 150
    assert np.allclose(r.T_target_source, T, atol=1e-9)


def test_a_candidate_with_fewer_than_three_inliers_is_kept_as_it_is():
    """A first candidate that holds only 2 correspondences cannot be refitted (3 are needed): the best model is
    that candidate and its 2 inliers, not the identity with them."""
    rng = np.random.default_rng(4)
    T = random_pose(rng, 180, 5.0)
    P1 = rng.uniform(-3, 3, (20, 3))
    P0 = rng.uniform(-20, 20, (20, 3))
    P0[:2] = apply_T(T, P1[:2])
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances="absolute")
    s = _Search(P0, P1, 0.05, st.p)
    assert not inliers_at(np.eye(4), P0, P1, 0.05).any()
    s.accept(T)
    assert s.best_n == 2 and s.best_inl[:2].all() and np.array_equal(s.best_T, T)


def test_inliers_are_strictly_within_the_threshold():
    """Residuals 0.25, 0.5 and 0.75 at thr 0.5, exact in binary: a residual equal to thr is not an inlier."""
    P1 = np.zeros((3, 3))
    P0 = np.array([[0.25, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.75]])
    assert inliers_at(np.eye(4), P0, P1, 0.5).tolist() == [True, False, False]


def test_a_sample_of_area_exactly_half_thr_squared_is_near_collinear():
    """The area test is strict: legs 1 and 0.5 (thr 1) give a cross product of exactly 0.5 = thr^2 / 2: rejected;
    legs 1 and 0.5 + 2^-20 pass."""
    st = build_coarse("lo_ransac")
    s = _Search(np.zeros((3, 3)), np.zeros((3, 3)), 1.0, st.p)
    a = np.array([[[0.0, 0, 0], [1.0, 0, 0], [0, h, 0]] for h in (0.5, 0.5 + 2.0 ** -20)]) + [3.0, 2.0, 1.0]
    assert s.valid(a, a + [10.0, 0, 0]).tolist() == [False, True]


def test_every_guided_sample_of_exact_correspondences_is_a_hypothesis():
    """40 exact correspondences of a pose (every pair compatible, none near-collinear at thr 0.01): each of the
    64 seeds x 8 samples draws j and k among the others and yields a valid sample, so there are exactly 512
    hypotheses, each the pose with all 40 correspondences counted. A sample that repeats a correspondence (the
    seed drawn as j, or j as k) has no area and would be dropped."""
    rng = np.random.default_rng(12)
    M, thr = 40, 0.01
    T = random_pose(rng, 180, 5.0)
    P1 = rng.uniform(0, 10, (M, 3))
    P0 = apply_T(T, P1)
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute")
    s = _Search(P0, P1, thr, st.p)
    seeds = rng.integers(0, M, size=64)
    diff = np.abs(s._d1(seeds) - s._d0(seeds))
    Ts, counts = s._guided_batch(np.random.default_rng(1), seeds, diff)
    assert len(Ts) == 64 * PER_SEED and (counts == M).all()
    assert np.allclose(Ts, T, atol=1e-9)


def test_uniform_sampling_of_three_correspondences():
    """Three exact correspondences with uniform sampling (fewer than 8: drawn without repeats): the pose and all
    three inliers."""
    rng = np.random.default_rng(6)
    T = random_pose(rng, 180, 5.0)
    P1 = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 3.0, 0]])
    st = build_coarse("lo_ransac", distance_threshold=0.1, distances="absolute", sampling="uniform", seed=0)
    r = lo_ransac(apply_T(T, P1), P1, None, None, 0.1, st.p, st.p.seed)
    assert r.inliers.all() and np.allclose(r.T_target_source, T, atol=1e-9)


def test_the_final_fit_keeps_a_normal_exactly_perpendicular_to_its_target_as_given():
    """Five exact correspondences at the identity, their normals equal but one: a source normal x against a
    target normal y, perpendicular at the start (a dot product of exactly 0). Only a negative dot product
    turns a normal round, so x pulls towards y in every round: the fit is the closed form with x as given (the
    other sign pulls -x towards y, a rotation the other way)."""
    from scanreg.stages.coarse.ransac import final_fit

    P1 = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0]])
    N1 = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0], [0, 0, 1.0]])
    N0 = N1.copy()
    N0[0] = [0.0, 1.0, 0.0]
    thr, weight = 0.1, 1.0
    T, inl = final_fit(P1, P1, N0, N1, thr, weight, np.eye(4), np.ones(5, bool))
    want = fit_points_normals(P1, P1, N0, N1, weight * thr * thr)
    flipped = N1.copy()
    flipped[0] *= -1
    other = fit_points_normals(P1, P1, N0, flipped, weight * thr * thr)
    assert inl.all() and np.allclose(T, want, atol=1e-12)
    assert np.abs(want - other).max() > 1e-4  # the sign matters (measured 8e-3)


def test_local_optimisation_refits_three_inliers():
    """40 exact correspondences of a pose and a candidate far off that holds exactly 3 of them: local
    optimisation fits those 3 (the pose exactly), which then holds all 40."""
    from scanreg.stages.coarse.ransac import local_opt

    P0, P1, T = exact_case(13, n_in=40, n_out=20)
    inl = np.zeros(60, bool)
    inl[[3, 17, 29]] = True
    T_lo, inl_lo = local_opt(P0, P1, 0.05, np.eye(4), inl, 10)
    assert inl_lo[:40].all() and inl_lo.sum() == 40 and np.allclose(T_lo, T, atol=1e-9)


def test_the_final_fit_does_not_refit_fewer_than_three_inliers():
    """A model holding 2 correspondences: too few to fit, returned as it is with those 2."""
    from scanreg.stages.coarse.ransac import final_fit

    P0, P1, T = exact_case(14, n_in=2, n_out=10)
    got, inl = final_fit(P0, P1, None, None, 0.05, 1.0, T, inliers_at(T, P0, P1, 0.05))
    assert np.array_equal(got, T) and inl.tolist() == [True, True] + [False] * 10


def test_the_final_fit_uses_normals_only_when_both_sides_have_them():
    """Target normals without source normals: the points-only least squares over the inliers (SVD here)."""
    from scanreg.stages.coarse.ransac import final_fit

    P0, P1, N0, _, T = noisy_case(30, 30, 7)
    inl = inliers_at(T, P0, P1, 0.1)
    got, got_inl = final_fit(P0, P1, N0, None, 0.1, 1.0, T, inl)
    assert got_inl[:30].all() and not got_inl[30:].any()
    assert np.allclose(got, fit_points_normals(P0[:30], P1[:30], N0[:30], N0[:30], 0.0), atol=1e-9)


def tie_case():
    """Exact correspondences at the identity on integer points (every distance exact in binary; thr 0.5), and
    three built to tie: seen from the seed S, X's distance agrees to 0.03 (compatible) but from J it is 4 against
    4.5 (exactly thr off); Z's distance from S is 4 against 4.5 (exactly thr off)."""
    rng = np.random.default_rng(15)
    S, J = np.array([10.0, 10, 10]), np.array([6.0, 14, 10])
    X1, Z1 = S + [0, 4, 0], S + [0, 0, 4]
    P1 = np.vstack([S, J, X1, Z1, rng.integers(0, 21, size=(12, 3)).astype(float)])
    P0 = P1.copy()
    P0[2] += [0.5, 0, 0]
    P0[3] += [0, 0, 0.5]
    return P0, P1


def test_guided_compatibility_is_strict_at_thr():
    """The tie case with every seed S: X may be j or k, but never with J (their distances differ by exactly thr),
    and Z is never drawn (exactly thr off from S). Every sample drawn is then valid (all sides agree within thr,
    no three source points collinear): exactly 64 x 8 hypotheses. Drawing J with X, or Z, would give samples
    with a side exactly thr off, which valid() rejects."""
    P0, P1 = tie_case()
    thr = 0.5
    d1 = np.linalg.norm(P1[:, None] - P1[None], axis=2)
    d0 = np.linalg.norm(P0[:, None] - P0[None], axis=2)
    diff = np.abs(d1 - d0)
    assert diff[1, 2] == thr and diff[0, 3] == thr and diff[0, 2] < thr  # the ties, exact
    close = np.flatnonzero(diff[0] < thr)[1:]
    assert all((diff[i, close] < thr).sum() >= 2 for i in close)  # each j has a k (itself included in the count)
    tri = [np.linalg.norm(np.cross(P1[b] - P1[a], P1[c] - P1[a])) for a in range(16) for b in range(a) for c in
           range(b)]
    assert min(tri) > thr * thr / 2  # no near-collinear triple
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute")
    s = _Search(P0, P1, thr, st.p)
    seeds = np.zeros(64, np.int64)
    Ts, _ = s._guided_batch(np.random.default_rng(2), seeds, np.abs(s._d1(seeds) - s._d0(seeds)))
    assert len(Ts) == 64 * PER_SEED


def test_guided_all_inlier_probability_is_strict_at_twice_thr():
    """q = w (1 - (1 - r^2)^8) by brute force (as above) with a correspondence W whose distance to the inlier S
    is 3 against 4 (exactly 2 thr off): outside S's compatible set."""
    rng = np.random.default_rng(16)
    thr, n_in = 0.5, 20
    P1 = np.vstack([[10.0, 10, 10], rng.integers(0, 21, size=(n_in - 1, 3)), [10.0, 10, 13],
                    rng.uniform(0, 20, (40, 3))])
    P0 = P1.copy()
    P0[n_in] = [10.0, 10, 14]
    P0[n_in + 1:] = rng.uniform(-20, 40, (40, 3))
    d1 = np.linalg.norm(P1[:, None] - P1[None], axis=2)
    d0 = np.linalg.norm(P0[:, None] - P0[None], axis=2)
    assert np.abs(d1 - d0)[0, n_in] == 2 * thr
    st = build_coarse("lo_ransac", distance_threshold=thr, distances="absolute", seed=3)
    r = lo_ransac(P0, P1, None, None, thr, st.p, st.p.seed)
    assert r.inliers[:n_in].all() and r.inliers.sum() == n_in
    C = np.abs(d1 - d0)[:n_in] < 2 * thr
    r_share = np.mean(C[:, :n_in].sum(axis=1) / C.sum(axis=1))
    assert r.all_inlier_probability == pytest.approx(n_in / len(P0) * (1 - (1 - r_share ** 2) ** PER_SEED),
                                                     rel=1e-12)


def test_guided_all_inlier_probability_uses_32_of_33_inliers():
    """With 33 inliers the share r is the mean over a random 32 of them (the rule of the brute-force test above):
    q matches r with one inlier left out, for one of the 33, and not the mean over all 33."""
    r, share = guided_shares(33)
    q = lambda r_share: 33 / 400 * (1 - (1 - r_share ** 2) ** PER_SEED)  # noqa: E731
    left_out = [q(np.delete(share, i).mean()) for i in range(33)]
    assert any(r.all_inlier_probability == pytest.approx(v, rel=1e-12) for v in left_out)
    assert r.all_inlier_probability != pytest.approx(q(share.mean()), rel=1e-9)


def test_guided_scores_count_inliers_up_to_twice_thr_from_the_seed():
    """As the scoring test above, with noise 0.6 thr: some hypotheses count inliers whose distance to the seed
    disagrees by between thr and 2 thr (both noisy), which the pool of width 2 thr keeps."""
    P0, P1, thr, diff, Ts, counts = seed_0_batch(6, 0.6)
    pool = np.flatnonzero(diff[0] < 2 * thr)
    far = 0
    for Th, c in zip(Ts, counts):
        res = apply_T(Th, P1[pool]) - P0[pool]
        inside = np.einsum("ij,ij->i", res, res) < thr * thr
        assert c == inside.sum()
        far += int((inside & (diff[0][pool] >= thr)).any())
    assert far > 0  # hypotheses counting such an inlier
