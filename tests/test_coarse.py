"""Feature-based coarse registration: salience measures, keypoints, frames, descriptors, LO-RANSAC, landmarks."""

import numpy as np
import pytest

from conftest import build, build_coarse, shared
from scanreg.types import Distances, RunContext
from scanreg.errors import StageError
from scanreg.geometry import Cloud, apply_T, random_pose, transform_errors
from scanreg.io import read_mesh
from scanreg.geometry import estimate_spacing
from scanreg.stages.coarse.ransac import lo_ransac
from scanreg.stages.registry import DESCRIPTOR, MATCHER, SALIENCE, load_all
from scanreg.stages.salience import MATRICES, MEASURES
from scanreg.geometry import barycentric_sample

load_all()


@pytest.fixture(scope="module")
def bunny():
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    p, n, _ = barycentric_sample(m, 8000, np.random.default_rng(0))
    return Cloud(p, n), estimate_spacing(p, np.random.default_rng(0))


def direct(points, normals, i, radius, gaussian):
    """Eigenvalues of C_p and C_n at point i, computed the plain way."""
    d = np.linalg.norm(points - points[i], axis=1)
    nb = d <= radius
    w = np.exp(-d[nb] ** 2 / (2 * (radius / 2) ** 2)) if gaussian else np.ones(nb.sum())
    P, N = points[nb], normals[nb]
    mu = (w @ P) / w.sum()
    Cp = ((P - mu) * w[:, None]).T @ (P - mu) / w.sum()
    Cn = (N * w[:, None]).T @ N / w.sum()
    return np.linalg.eigvalsh(Cp), np.linalg.eigvalsh(Cn), nb.sum()


@pytest.mark.parametrize("matrix", list(MATRICES))
@pytest.mark.parametrize("measure", list(MEASURES))
@pytest.mark.parametrize("weights", ["uniform", "gaussian"])
def test_salience_matches_a_direct_eigenvalue_computation(bunny, matrix, measure, weights):
    cloud, sp = bunny
    st = build(SALIENCE, f"{matrix}_{measure}", radius=4.0, weights=weights, max_neighbors=512)
    h = st.values(cloud, sp)
    for i in np.random.default_rng(1).choice(len(cloud.points), 25, replace=False):
        lp, ln, cnt = direct(cloud.points, cloud.normals, i, 4.0 * sp, weights == "gaussian")
        lam = lp if matrix == "cp" else ln
        l1, l2, l3 = np.maximum(lam, 0)
        want = {"min_ratio": min(l1 / l2, l2 / l3), "l1": l1, "l2": l2, "l3": l3, "l1_l2": l1 / l2,
                "l2_l3": l2 / l3}[measure]
        if cnt < 10:
            assert h[i] == -np.inf
        else:
            assert h[i] == pytest.approx(want, rel=1e-6, abs=1e-12 * max(1.0, l3))


def test_isolated_points_are_never_keypoints_and_nms_holds(bunny):
    cloud, sp = bunny
    far = cloud.points.max(0) + 100 * sp
    pts = np.vstack([cloud.points, far + np.arange(5)[:, None] * sp * 0.1])  # a tight cluster of 5 points
    nrm = np.vstack([cloud.normals, np.tile([0, 0, 1.0], (5, 1))])
    st = build(SALIENCE, "cp_l1", radius=4.0, nms_radius=4.0)
    c = Cloud(pts, nrm)
    h = st.values(c, sp)
    assert (h[-5:] == -np.inf).all()
    kp = st.keypoints(c, sp)
    assert not (kp >= len(cloud.points)).any() and len(kp) > 10
    for i in kp[:50]:
        nb = np.linalg.norm(pts - pts[i], axis=1) <= 4.0 * sp
        assert h[i] >= h[nb].max()
    top = build(SALIENCE, "cp_l1", radius=4.0, nms_radius=4.0, top_k=7).keypoints(c, sp)
    assert len(top) == 7 and set(top) <= set(kp)


@pytest.mark.parametrize("name", ["histogram3p", "fpfh"])
def test_descriptor_invariant_to_rotation(bunny, name):
    cloud, sp = bunny
    kp = build(SALIENCE, "cp_min_ratio").keypoints(cloud, sp)
    T = random_pose(np.random.default_rng(2), 180, 50)
    moved = Cloud(apply_T(T, cloud.points), cloud.normals @ T[:3, :3].T)
    kw = {"support_voxel": 0.0, "radius": 8.0} if name == "fpfh" else {}
    st = build(DESCRIPTOR, name, **kw)
    d0, d1 = st.compute(cloud, kp, sp), st.compute(moved, kp, sp)
    assert d0.shape == (len(kp), 216 if name == "histogram3p" else 33)
    rel = np.linalg.norm(d0 - d1, axis=1) / np.linalg.norm(d0, axis=1)
    assert np.median(rel) < 1e-6 and np.quantile(rel, 0.95) < 1e-3


def test_local_frames_by_construction():
    """A keypoint whose neighbours form a grid symmetric about its axes (3 wide, 1.5 deep, flat), plus one point
    on the +x side, all turned by a known rotation R: the frame's rows are R's columns, x along the long side
    (towards the extra point), z along the given normal, y = z x x. Also without normals: z then points along the
    weighted mean offset, here lifted by a point above the plane."""
    from scipy.spatial.transform import Rotation

    from scanreg.stages.descriptor import local_frames

    g = np.array([(x, y, 0.0) for x in np.linspace(-3, 3, 7) for y in np.linspace(-1.5, 1.5, 5)])
    local = np.vstack([[0.0, 0.0, 0.0], g[np.any(g != 0, axis=1)], [4.0, 0.0, 0.0]])
    R = Rotation.from_rotvec([0.3, -0.7, 0.5]).as_matrix()
    pts = local @ R.T + [5.0, -2.0, 1.0]
    nrm = np.tile(R[:, 2], (len(pts), 1))
    F = local_frames(pts, nrm, np.array([0]), 10.0)[0]
    assert np.allclose(F, R.T, atol=1e-9), F @ R
    F_flip = local_frames(pts, -nrm, np.array([0]), 10.0)[0]  # the normal turned: z and y turn with it
    assert np.allclose(F_flip, np.diag([1.0, -1.0, -1.0]) @ R.T, atol=1e-9)
    above = np.vstack([pts, R @ [0.0, 0.0, 0.01] + [5.0, -2.0, 1.0]])
    assert np.allclose(local_frames(above, None, np.array([0]), 10.0)[0], R.T, atol=1e-4)


def test_local_frames_repeat_across_scans(bunny):
    from scanreg.stages.descriptor import local_frames

    cloud, sp = bunny
    kp = np.arange(0, len(cloud.points), 97)
    T = random_pose(np.random.default_rng(3), 180, 10)
    F0 = local_frames(cloud.points, cloud.normals, kp, 10 * sp)
    F1 = local_frames(apply_T(T, cloud.points), cloud.normals @ T[:3, :3].T, kp, 10 * sp)
    assert np.allclose(np.einsum("nij,kj->nik", F0, T[:3, :3]), F1, atol=1e-6)
    assert np.allclose(np.einsum("nij,nkj->nik", F0, F0), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(F0), 1.0)


def test_guided_lo_ransac_draws_what_its_stopping_rule_says():
    """5 % inliers among 2000 matches: guided sampling needs more than one batch of 64 seeds x 8 samples, and
    stops at the first whole batch past N = ceil(log(mu) / log(1 - q)) * 8, q = w (1 - (1 - r^2)^8) the
    probability of an all-inlier hypothesis (w the best model's inlier share: q cannot exceed it)."""
    from scanreg.stages.coarse.ransac import PER_SEED, SEEDS

    rng = np.random.default_rng(4)
    M, n_in = 2000, 100
    P1 = rng.uniform(0, 10, size=(M, 3))
    T = random_pose(rng, 180, 20)
    P0 = rng.uniform(-10, 20, size=(M, 3))
    P0[:n_in] = apply_T(T, P1[:n_in]) + rng.normal(scale=0.005, size=(n_in, 3))
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances=Distances.absolute, seed=3)
    r = lo_ransac(P0, P1, None, None, 0.05, st.p, st.p.seed)
    assert transform_errors(r.T_target_source, T)[0] < 0.05 and r.inliers[:n_in].all()
    q = r.all_inlier_probability
    assert 0 < q <= r.inliers.sum() / M
    N = int(np.ceil(np.log(st.p.miss_probability) / np.log(1 - q))) * 8
    batch = SEEDS * PER_SEED
    assert r.hypotheses > batch and r.hypotheses == batch * int(np.ceil(max(N, st.p.min_iterations) / batch))


def test_lo_ransac_recovers_a_pose_from_matches_with_70_percent_outliers():
    rng = np.random.default_rng(0)
    P1 = rng.uniform(0, 10, size=(300, 3))
    T = random_pose(rng, 180, 20)
    P0 = apply_T(T, P1) + rng.normal(scale=0.01, size=P1.shape)
    out = rng.choice(300, 210, replace=False)
    P0[out] = rng.uniform(-20, 20, size=(210, 3))
    st = build_coarse("lo_ransac", distance_threshold=0.05, distances=Distances.absolute, seed=3)
    r = lo_ransac(P0, P1, None, None, 0.05, st.p, st.p.seed)
    T_est, inl, drawn = r.T_target_source, r.inliers, r.hypotheses
    rot, trans = transform_errors(T_est, T)
    assert rot < 0.05 and trans < 0.02 and 85 <= inl.sum() <= 95
    assert drawn < 5000  # adaptive stopping: w = 0.3 needs ~170 samples for mu = 0.01
    T2 = lo_ransac(P0, P1, None, None, 0.05, st.p, st.p.seed).T_target_source
    assert np.array_equal(T_est, T2)  # seeded: bit for bit


def stanford_case(pose_seed: int, n: int, salience):
    """bun045 -> bun000 sampled with n points each, the source under a random pose: (target, source, truth,
    the pair's spacing, the coarse stage's helper stages: ``salience``, FPFH and mutual kNN)."""
    from scanreg.io import read_stanford_conf
    from scanreg.geometry import invert_T

    folder = shared("stanford_bunny")
    poses = read_stanford_conf(folder / "bun.conf")
    t, s = read_mesh(folder / "bun000.ply"), read_mesh(folder / "bun045.ply")
    P = random_pose(np.random.default_rng(pose_seed), 180, 0.1)
    T_gt = invert_T(poses["bun000.ply"]) @ poses["bun045.ply"] @ invert_T(P)
    tp, tn, _ = barycentric_sample(t, n, np.random.default_rng(0))
    sp_, sn, _ = barycentric_sample(s, n, np.random.default_rng(1))
    tgt, src = Cloud(tp, tn), Cloud(apply_T(P, sp_), sn @ P[:3, :3].T)
    sp = max(estimate_spacing(tp, np.random.default_rng(0)), estimate_spacing(sp_, np.random.default_rng(0)))
    helpers = {"salience": salience, "descriptor": build(DESCRIPTOR, "fpfh"), "matcher": build(MATCHER, "mutual_knn")}
    return tgt, src, T_gt, sp, helpers


def test_lo_ransac_end_to_end_on_stanford_scans():
    tgt, src, T_gt, sp, helpers = stanford_case(7, 20000, build(SALIENCE, "uniform"))
    res = build_coarse("lo_ransac", helpers).align(tgt, src, sp, RunContext(seed=0))
    T, m = res.T_target_source, res.metrics
    rot, trans = transform_errors(T, T_gt)
    # measured: 0.144 deg with 299 inliers (one-way or 1-NN matching, 0.90 deg, fails)
    assert rot < 0.45 and m["coarse_inliers"] >= 100, (rot, m)


@pytest.mark.slow
def test_lo_ransac_falls_back_to_uniform_keypoints():
    """When the configured keypoints fail (here ISS with a support radius so small that no point is salient),
    lo_ransac retries with uniform keypoints, solves the Stanford pair and logs coarse_fallback = 1; with the
    fallback off it fails with the keypoint message."""
    tgt, src, T_gt, sp, helpers = stanford_case(11, 15000, build(SALIENCE, "iss", salient_radius=0.1,
                                                                  non_max_radius=0.1))
    res = build_coarse("lo_ransac", helpers).align(tgt, src, sp, RunContext(seed=0))
    T, m = res.T_target_source, res.metrics
    assert m["coarse_fallback"] == 1 and transform_errors(T, T_gt)[0] < 0.35, m  # measured: 0.107 deg
    with pytest.raises(StageError, match="too few keypoints"):
        build_coarse("lo_ransac", helpers, fallback_voxel=None).align(tgt, src, sp, RunContext(seed=0))
    # with fallback_k, the fallback matches each keypoint's 5 nearest descriptors: more matches than the matcher's
    # own 3 (the default), the configured matcher left as it was
    wide = build_coarse("lo_ransac", helpers, fallback_k=5).align(tgt, src, sp, RunContext(seed=0)).metrics
    assert wide["coarse_correspondences"] > 1.4 * m["coarse_correspondences"], (m, wide)
    assert helpers["matcher"].p.k == 3


@pytest.mark.slow
def test_fallback_k_leaves_a_pair_that_needs_no_fallback_as_it_was():
    """ISS serves on bun045 -> bun000 (no fallback): with fallback_k = 5 the same matches and pose, bit for bit."""
    tgt, src, T_gt, sp, helpers = stanford_case(7, 20000, build(SALIENCE, "iss"))
    base = build_coarse("lo_ransac", helpers).align(tgt, src, sp, RunContext(seed=0))
    wide = build_coarse("lo_ransac", helpers, fallback_k=5).align(tgt, src, sp, RunContext(seed=0))
    assert base.metrics["coarse_fallback"] == 0 and transform_errors(base.T_target_source, T_gt)[0] < 2.0
    assert np.array_equal(wide.T_target_source, base.T_target_source) and wide.metrics == base.metrics


def test_the_fallback_matcher_is_the_configured_one_with_fallback_k():
    from scanreg.stages.matcher import MutualKNN

    matcher = build(MATCHER, "mutual_knn", mutual=True)
    wide = build_coarse("lo_ransac", {"matcher": matcher}, fallback_k=5)._fallback_matcher()
    assert isinstance(wide, MutualKNN) and wide.p.k == 5 and wide.p.mutual and matcher.p.k == 3
    assert build_coarse("lo_ransac", {"matcher": matcher})._fallback_matcher() is matcher  # (default: null)
    other = object()  # a matcher without a k is used as it is
    assert build_coarse("lo_ransac", {"matcher": other}, fallback_k=5)._fallback_matcher() is other
    with pytest.raises(Exception, match="fallback_k must be >= 1 or null"):
        build_coarse("lo_ransac", fallback_k=0)


def test_second_look_only_for_a_fallback_pose_that_keeps_little():
    """The coarse stage looks again only when its uniform keypoints served and the refined pose keeps less than
    second_look_fitness of the source, and only when it can match wider than it did."""
    from scanreg.types import CoarseResult

    def stage(helpers=None, **kw):  # its search replaced by one that says it ran, and with which matcher's k
        st = build_coarse("lo_ransac", helpers or {"matcher": build(MATCHER, "mutual_knn")}, **kw)
        st._attempt = lambda t, s, sp, salience, matcher: CoarseResult(np.eye(4), {"k": matcher.p.k})
        st._thinned_then = lambda run, t, s, sp, ctx: run(t, s, sp, ctx)
        return st

    fell_back, served = CoarseResult(np.eye(4), {"coarse_fallback": 1}), CoarseResult(np.eye(4), {"coarse_fallback": 0})
    c, ctx = Cloud(np.zeros((3, 3))), RunContext(seed=0)
    looked = stage().second_look(c, c, 1.0, ctx, fell_back, 0.149)
    assert looked is not None and looked.metrics == {"k": 5, "coarse_fallback": 1}, looked
    assert stage(second_look_k=7).second_look(c, c, 1.0, ctx, fell_back, 0.01).metrics["k"] == 7
    for res, fitness in ((served, 0.01), (fell_back, 0.15), (fell_back, 0.5), (fell_back, None)):
        assert stage().second_look(c, c, 1.0, ctx, res, fitness) is None, (res.metrics, fitness)
    for kw in ({"second_look_fitness": None}, {"fallback_k": 5}, {"second_look_k": 3}):
        assert stage(**kw).second_look(c, c, 1.0, ctx, fell_back, 0.01) is None, kw
    assert stage({"matcher": object()}).second_look(c, c, 1.0, ctx, fell_back, 0.01) is None  # (no k to widen)
    with pytest.raises(Exception, match="second_look_fitness must be in"):
        build_coarse("lo_ransac", second_look_fitness=0)
    with pytest.raises(Exception, match="second_look_k must be >= 1"):
        build_coarse("lo_ransac", second_look_k=0)


@pytest.mark.slow
def test_second_look_matches_the_uniform_keypoints_wider():
    """A pose from the fallback that keeps little of the source: the second look matches the same uniform
    keypoints with 5 nearest descriptors (more matches than the first look's 3), skipping the configured
    keypoints, and finds the pair's pose again."""
    tgt, src, T_gt, sp, helpers = stanford_case(11, 15000, build(SALIENCE, "iss", salient_radius=0.1,
                                                                  non_max_radius=0.1))
    stage = build_coarse("lo_ransac", helpers)
    first = stage.align(tgt, src, sp, RunContext(seed=0))
    again = stage.second_look(tgt, src, sp, RunContext(seed=0), first, 0.05)
    assert again is not None and again.metrics["coarse_fallback"] == 1
    assert again.metrics["coarse_correspondences"] > 1.4 * first.metrics["coarse_correspondences"], again.metrics
    assert again.metrics["coarse_keypoints_source"] == first.metrics["coarse_keypoints_source"]
    assert transform_errors(again.T_target_source, T_gt)[0] < 0.45  # measured: 0.149 deg


def test_landmarks_known_transform_and_a_bad_pick():
    from scanreg.stages.coarse.landmarks import landmark_fit

    rng = np.random.default_rng(0)
    src = rng.uniform(0, 50, size=(6, 3))
    T = random_pose(rng, 180, 30)
    tgt = apply_T(T, src) + rng.normal(scale=0.05, size=src.shape)
    T_est, m, loo = landmark_fit(tgt, src)
    assert transform_errors(T_est, T)[0] < 0.2 and m["landmark_rms"] < 0.1
    bad = tgt.copy()
    bad[2] += [3.0, 0, 0]  # one landmark clicked 3 mm off
    _, mb, loo_b = landmark_fit(bad, src)
    assert int(np.argmax(loo_b)) == 2 and loo_b[2] > 2.0 and loo_b[2] > 1.5 * np.delete(loo_b, 2).max()
    st = build_coarse("landmarks", max_residual=1.0)
    with pytest.raises(StageError, match="landmark 3 has a leave-one-out error"):
        st.align(Cloud(tgt), Cloud(src), 1.0, RunContext(seed=0), landmarks=(bad, src))
    with pytest.raises(StageError, match="collinear"):
        landmark_fit(tgt[:3], np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]))
