"""Known answers that kill the mutants of the ICP maths (./run mutants, issue #38): the least-norm solve of the
normal equations against NumPy's solve and pseudo-inverse, the kernel scale along the pair-limit schedule, and the
schedule's settle rule at its exact boundary."""

import numpy as np
import pytest

from scanreg.stages.icp.base import PairLimit, least_norm_solve


def spd(rng, scales):
    """A symmetric positive definite 6x6 matrix whose coordinates have very different scales (as rotation and
    translation columns do)."""
    A = rng.normal(size=(40, 6)) * scales
    return A.T @ A


def scaled_pinv_solution(H, g, rcond):
    """The least-norm solution on the unit-diagonal scaling of H, written with NumPy's pseudo-inverse."""
    d = np.sqrt(np.diag(H))
    return np.linalg.pinv(H / np.outer(d, d), rcond=rcond) @ (g / d) / d


def test_least_norm_solve_is_the_solution_when_every_direction_is_determined():
    rng = np.random.default_rng(0)
    H = spd(rng, [1e3, 1.0, 1e-2, 5.0, 1e2, 0.3])
    g = rng.normal(size=6)
    assert np.allclose(least_norm_solve(H, g), np.linalg.solve(H, g), rtol=1e-9, atol=0)


def test_least_norm_solve_gives_undetermined_directions_no_motion():
    rng = np.random.default_rng(1)
    # a direction with no weight at all (its row and column zero): zero there, the rest solved without it
    H = spd(rng, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    H[2, :] = H[:, 2] = 0.0
    g = rng.normal(size=6)
    g[2] = 0.0
    keep = [0, 1, 3, 4, 5]
    x = least_norm_solve(H, g)
    assert x[2] == 0.0 and np.allclose(x[keep], np.linalg.solve(H[np.ix_(keep, keep)], g[keep]), rtol=1e-9)
    # nothing determined: no motion
    assert np.array_equal(least_norm_solve(np.zeros((6, 6)), np.ones(6)), np.zeros(6))
    # a direction determined 1e12 times more weakly than the rest: below the relative cut-off 1e-10 it is
    # dropped as undetermined (NumPy's own cut-off, machine precision, would keep it and move far along it)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    H = Q @ np.diag([1.0, 0.8, 0.5, 0.3, 0.2, 1e-12]) @ Q.T
    g = rng.normal(size=6)
    x = least_norm_solve(H, g)
    assert np.allclose(x, scaled_pinv_solution(H, g, 1e-10), rtol=1e-6, atol=1e-9)
    assert np.linalg.norm(x) < 100 < np.linalg.norm(scaled_pinv_solution(H, g, 1e-15))


def test_least_norm_solve_drops_a_column_with_almost_no_weight():
    # a diagonal entry 1e-30 of the largest (its scale 1e-15 of the largest's, under the 1e-12 cut-off): dropped,
    # as a zero column is; one of 1e-20 (scale 1e-10) is kept
    H = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 1e-30])
    g = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1e-30])
    assert np.allclose(least_norm_solve(H, g), [1.0, 0.5, 1 / 3, 0.25, 0.2, 0.0], rtol=1e-12)
    H[5, 5], g[5] = 1e-20, 2e-20
    assert np.allclose(least_norm_solve(H, g), [1.0, 0.5, 1 / 3, 0.25, 0.2, 2.0], rtol=1e-9)
    # the cut-off is relative to the largest scale: with a largest diagonal entry of 1e6 (scale 1e3), an entry of
    # 1e-20 (scale 1e-10) is below 1e-12 of it and dropped
    H = np.diag([1e6, 2.0, 3.0, 4.0, 5.0, 1e-20])
    g = np.array([1e6, 1.0, 1.0, 1.0, 1.0, 2e-20])
    assert np.allclose(least_norm_solve(H, g), [1.0, 0.5, 1 / 3, 0.25, 0.2, 0.0], rtol=1e-12)


def test_kernel_scale_grows_with_the_pair_limit():
    assert PairLimit(16.0, 4.0, kernel_scale=2.0).scale() == 8.0  # 4 times the floor: 4 times the scale
    assert PairLimit(4.0, 4.0, kernel_scale=2.0).scale() == 2.0
    assert PairLimit(None, None, kernel_scale=2.0).scale() == 2.0
    assert PairLimit(5.0, None, kernel_scale=2.0).scale() == 2.0  # no floor: no schedule, the scale as given
    assert PairLimit(5.0, None).settled and PairLimit(None, 3.0).settled
    lim = PairLimit(16.0, 4.0, shrink=0.5, settle=0.01, kernel_scale=1.0)
    assert lim.advance(1.0, 1.0, 1e-4) and lim.scale() == 2.0


@pytest.mark.parametrize("prev, rms, tau, settle, tightens", [
    (1.0, 0.5, 0.5, 0.01, False),     # a change of exactly tau is not settled
    (1.0, 0.75, 0.5, 0.01, True),     # 0.25 < tau: settled, though 25 % of the RMS
    (2.0, 1.85, 1e-4, 0.1, True),     # 0.15 < 10 % of the previous RMS (0.2)
    (2.0, 1.75, 1e-4, 0.125, False),  # exactly 12.5 % of 2: not settled
    (0.5, 0.55, 1e-4, 0.125, True),   # a rise: its size counts, 0.05 < 12.5 % of 0.5
])
def test_the_limit_tightens_when_the_change_is_below_tau_or_settle_times_the_rms(prev, rms, tau, settle, tightens):
    lim = PairLimit(16.0, 3.0, shrink=0.5, settle=settle)
    assert lim.advance(prev, rms, tau) == tightens
    assert lim.limit == (8.0 if tightens else 16.0)


# --------------------------------------------------------------------------------------- the update steps


def paired_case(seed, n=200):
    """Pairs on a bumpy surface: target points q with unit normals, source points p = q moved off by a small
    rigid motion plus noise, a kept mask and IRLS weights for the kept pairs."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-3, 3, (n, 2))
    q = np.c_[xy, np.sin(xy[:, 0]) * np.cos(xy[:, 1])] + [20.0, -5.0, 3.0]  # far from the origin
    nq = np.c_[-np.cos(xy[:, 0]) * np.cos(xy[:, 1]), np.sin(xy[:, 0]) * np.sin(xy[:, 1]), np.ones(n)]
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    from scipy.spatial.transform import Rotation

    from scanreg.geometry import apply_T, make_T

    off = make_T(Rotation.from_rotvec([0.02, -0.01, 0.015]).as_matrix(), [0.05, -0.03, 0.02])
    p = apply_T(off, q) + rng.normal(scale=0.01, size=(n, 3))
    ok = rng.random(n) > 0.2
    w = rng.uniform(0.2, 1.0, ok.sum())
    return p, q, nq, ok, w


def rotvec_matrix(v):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix()


@pytest.mark.parametrize("weighted", [False, True])
def test_point_to_plane_step_is_the_linearised_least_squares_about_the_centroid(weighted):
    """One update: over the kept pairs, x = (w, t) minimising sum w_i (((p_i - c) x n_i) . w + n_i . t + (p_i -
    q_i) . n_i)^2, c the kept points' centroid (lstsq here), applied as p -> c + R(w) (p - c) + t."""
    from scanreg.stages.icp.plane import PointToPlane

    p, q, nq, ok, w = paired_case(1)
    w = w if weighted else None
    pk, qk, nk = p[ok], q[ok], nq[ok]
    c = pk.mean(axis=0)
    A = np.c_[np.cross(pk - c, nk), nk]
    b = -np.einsum("ij,ij->i", pk - qk, nk)
    sw = np.ones(len(pk)) if w is None else np.sqrt(w)
    x = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)[0]
    R = rotvec_matrix(x[:3])
    want = np.eye(4)
    want[:3, :3], want[:3, 3] = R, x[3:] + c - R @ c
    got = PointToPlane(PointToPlane.Params()).step(p, q, nq, ok, w)
    assert np.allclose(got, want, atol=1e-10)


@pytest.mark.parametrize("weighted", [False, True])
def test_horn_step_is_the_least_squares_fit_of_the_kept_pairs(weighted):
    """One Besl-McKay update: the rigid transform moving the kept source points onto their closest points in
    the (weighted) least-squares sense, by SVD here; some pairs dropped, or every pair kept."""
    from scanreg.stages.icp.point import Horn

    p, q, nq, ok, w = paired_case(2)
    for keep in (ok, np.ones(len(p), bool)):
        ww = (w if keep is ok else np.linspace(0.2, 1.0, len(p))) if weighted else np.ones(keep.sum())
        pk, qk = p[keep], q[keep]
        mp, mq = ww @ pk / ww.sum(), ww @ qk / ww.sum()
        U, _, Vt = np.linalg.svd(((pk - mp) * ww[:, None]).T @ (qk - mq))
        R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        got = Horn(Horn.Params()).step(p, q, nq, keep, ww if weighted else None)
        assert np.allclose(got[:3, :3], R, atol=1e-10) and np.allclose(got[:3, 3], mq - R @ mp, atol=1e-9)


def test_point_to_plane_estimates_the_normals_a_bare_target_lacks():
    """A target cloud without normals (and no mesh): point-to-plane estimates them and still recovers the pose
    (the source an independent sampling of the same bunny, 3 degrees and half a spacing off)."""
    from scanreg.geometry import Cloud, apply_T, barycentric_sample, estimate_spacing, make_T, transform_errors
    from scanreg.io import read_mesh
    from scanreg.stages.icp.plane import PointToPlane
    from scanreg.types import RunContext

    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    tp, _, _ = barycentric_sample(m, 8000, np.random.default_rng(0))
    sp_, sn, _ = barycentric_sample(m, 8000, np.random.default_rng(1))
    T = make_T(rotvec_matrix([0.03, -0.02, 0.04]), [0.5, -0.3, 0.2])
    sp = estimate_spacing(tp, np.random.default_rng(0))
    res = PointToPlane(PointToPlane.Params(max_correspondence_distance=10.0)).refine(
        Cloud(tp), Cloud(sp_, sn), T, sp, RunContext(seed=0))
    rot, trans = transform_errors(res.T_target_source, np.eye(4))
    assert rot < 0.025 and trans < 0.02 * sp  # reached 0.007 deg and 0.006 spacings, from 3 deg off


# ------------------------------------------------------------------------------------------------ Anderson


def anderson_case(seed=0):
    """An anisotropic blob, and 120 of its points moved back by a pose 8-12 degrees off, with noise."""
    from scanreg.geometry import apply_T, random_pose

    rng = np.random.default_rng(seed)
    target = rng.normal(size=(150, 3)) * [3.0, 2.0, 1.0]
    T = random_pose(rng, 12, 0.3, min_angle_deg=8)
    src = apply_T(np.linalg.inv(T), target[:120]) + rng.normal(scale=0.02, size=(120, 3))
    return target, src


def aa_icp_history(target, source, memory, n):
    """RMS closest-point distance at each of n + 1 iterates of Anderson-accelerated point-to-point ICP, written
    out: x = (rotation vector, translation); G(x) the Besl-McKay step from x (brute-force closest points, the
    rigid fit by SVD); type-II mixing over the last memory + 1 steps, x = g - dG gamma with gamma the least-squares
    solution of dF gamma = f; an iterate whose RMS exceeds the last accepted one is replaced by that one's plain
    step, the history cleared."""
    from scipy.spatial.transform import Rotation

    from scanreg.geometry import apply_T, make_T

    vec = lambda T: np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]]  # noqa: E731
    mat = lambda x: make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:])  # noqa: E731

    def at(x):
        moved = apply_T(mat(x), source)
        D = np.linalg.norm(moved[:, None] - target[None], axis=2)
        j = D.argmin(axis=1)
        return moved, target[j], np.sqrt(np.mean(D[np.arange(len(moved)), j] ** 2))

    def step(moved, q, x):
        mp, mq = moved.mean(axis=0), q.mean(axis=0)
        U, _, Vt = np.linalg.svd((moved - mp).T @ (q - mq))
        R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        return vec(make_T(R, mq - R @ mp) @ mat(x))

    x, G, F, hist, accepted, g_acc = np.zeros(6), [], [], [], np.inf, None
    for it in range(n + 1):
        moved, q, rms = at(x)
        if rms > accepted and g_acc is not None:
            G, F, x = [], [], g_acc
            moved, q, rms = at(x)
        hist.append(rms)
        if it == n:
            break
        g = step(moved, q, x)
        accepted, g_acc = rms, g
        G.append(g)
        F.append(g - x)
        G, F = G[-(memory + 1):], F[-(memory + 1):]
        x = g
        if len(G) > 1:
            gamma = np.linalg.lstsq(np.diff(F, axis=0).T, F[-1], rcond=None)[0]
            x = g - np.diff(G, axis=0).T @ gamma
    return np.array(hist)


@pytest.mark.parametrize("memory", [1, 2])  # a wider window mixes nearly parallel steps: round-off then decides
def test_anderson_iterates_are_the_mixing_written_out(memory):
    from scanreg.geometry import Cloud
    from scanreg.stages.icp.point import Anderson
    from scanreg.types import RunContext

    from scanreg.geometry import ClosestPoints

    target, src = anderson_case()
    n = 12
    st = Anderson(Anderson.Params(memory=memory, max_iterations=n, distances="absolute"))
    res = st.iterate(Cloud(target), Cloud(src), np.eye(4), ClosestPoints(Cloud(target)), 0.0, PairLimit(None, None))
    want = aa_icp_history(target, src, memory, n)
    assert res.iterations == n and not res.converged and len(res.rms_history) == n + 1
    assert np.allclose(res.rms_history, want, rtol=1e-9, atol=1e-12)
    assert want[-1] < 0.5 * want[0]


def test_anderson_limit_tightens_only_when_settled_and_final_distances_stay_within_the_floor():
    """Three iterations from 10 degrees off with an adaptive limit far above its floor: the fit moves by more
    than 1 % per iteration, so the limit stays where it started; the final distances beyond the floor are inf."""
    from scanreg.geometry import ClosestPoints, Cloud
    from scanreg.stages.icp.point import Anderson

    target, src = anderson_case(1)
    st = Anderson(Anderson.Params(max_iterations=3, distances="absolute"))
    lim = PairLimit(6.0, 0.05, shrink=0.5, settle=0.01)
    res = st.iterate(Cloud(target), Cloud(src), np.eye(4), ClosestPoints(Cloud(target)), 1e-6, lim)
    assert res.final_limit == 6.0 and res.iterations == 3
    d = res.final_distances
    assert np.isinf(d).any() and np.all(np.isinf(d) | (d <= 0.05))


def test_anderson_rejects_pairs_whose_normals_disagree():
    """Two parallel sheets 0.1 apart facing away from each other (normals up on the upper one, down on the lower).
    The source faces up: 80 % of it 0.02 below the upper sheet, 20 % 0.02 above the lower one. With a 60-degree
    normal test the 20 % (paired with the lower sheet, normals opposed) are dropped and the source moves up
    0.02 onto the upper sheet; without, the two parts pull apart and it settles at 0.8 x 0.02 - 0.2 x 0.02 =
    0.012 (where the upper part's pull, 0.8 x 0.008, balances the lower part's, 0.2 x 0.032)."""
    from scanreg.geometry import Cloud
    from scanreg.stages.icp.point import Anderson
    from scanreg.types import RunContext

    rng = np.random.default_rng(2)
    n = 6000  # per sheet of 1 x 1: about 0.01 apart, closer than the sheets
    top = np.c_[rng.uniform(0, 1, (n, 2)), np.full(n, 0.1)]
    bottom = np.c_[rng.uniform(0, 1, (n, 2)), np.zeros(n)]
    target = Cloud(np.vstack([top, bottom]), np.vstack([np.tile([0, 0, 1.0], (n, 1)), np.tile([0, 0, -1.0], (n, 1))]))
    src_pts = np.c_[rng.uniform(0.2, 0.8, (500, 2)), np.r_[np.full(400, 0.08), np.full(100, 0.02)]]
    source = Cloud(src_pts, np.tile([0, 0, 1.0], (500, 1)))
    kw = dict(max_correspondence_distance=None, schedule="fixed", distances="absolute", accept=False)
    for angle, dz in ((60.0, 0.02), (None, 0.012)):
        res = Anderson(Anderson.Params(max_normal_angle_deg=angle, **kw)).refine(target, source, np.eye(4), 0.01,
                                                                               RunContext(seed=0))
        assert res.T_target_source[2, 3] == pytest.approx(dz, abs=0.002), angle


def test_anderson_with_a_normal_test_that_keeps_every_pair_iterates_as_without():
    """Normals all +z on both sides and a 90-degree normal test: every pair passes, so the iterates are those of
    the mixing written out, including the steps the safeguard replaces (where the normals are turned again)."""
    from scanreg.geometry import ClosestPoints, Cloud
    from scanreg.stages.icp.point import Anderson

    target, src = anderson_case()
    up = lambda n: np.tile([0.0, 0.0, 1.0], (n, 1))  # noqa: E731
    st = Anderson(Anderson.Params(memory=2, max_iterations=12, distances="absolute", max_normal_angle_deg=90.0))
    tc = Cloud(target, up(len(target)))
    res = st.iterate(tc, Cloud(src, up(len(src))), np.eye(4), ClosestPoints(tc), 0.0, PairLimit(None, None))
    want = aa_icp_history(target, src, 2, 12)
    assert np.allclose(res.rms_history, want, rtol=1e-9, atol=1e-12)
    assert (np.diff(want) > 0).any()  # the safeguard had a mixed step to replace


def test_anderson_history_starts_at_the_start_pose_when_the_limit_tightens():
    """The first entry is the RMS of the pairs within the start limit at the start pose (brute force here); an
    entry rewritten when the limit tightens is that iterate's own."""
    from scanreg.geometry import ClosestPoints, Cloud
    from scanreg.stages.icp.point import Anderson

    target, src = anderson_case(3)
    st = Anderson(Anderson.Params(max_iterations=40, distances="absolute"))
    lim = PairLimit(1.0, 0.1, shrink=0.5, settle=0.01)
    res = st.iterate(Cloud(target), Cloud(src), np.eye(4), ClosestPoints(Cloud(target)), 1e-9, lim)
    assert res.final_limit < 1.0  # it tightened
    d = np.linalg.norm(src[:, None] - target[None], axis=2).min(axis=1)
    assert res.rms_history[0] == pytest.approx(np.sqrt(np.mean(d[d <= 1.0] ** 2)), rel=1e-12)


def test_point_to_plane_uses_the_normals_the_target_has():
    """A target cloud with normals of its own (here the surface's turned 10 degrees: not what an estimate would
    give), and a source sampled elsewhere on the surface: one update is the linearised least squares with those
    normals (written here, closest points by brute force), so they are not estimated again."""
    from scanreg.geometry import Cloud
    from scanreg.stages.icp.plane import PointToPlane
    from scanreg.types import RunContext

    _, q, nq, _, _ = paired_case(4, n=800)
    given = nq @ rotvec_matrix([np.radians(10.0), 0.0, 0.0]).T
    xy = np.random.default_rng(5).uniform(-2.5, 2.5, (150, 2))  # other points of the same surface, moved
    src = np.c_[xy, np.sin(xy[:, 0]) * np.cos(xy[:, 1])] + [20.0, -5.0, 3.0] + [0.02, -0.01, 0.05]
    D = np.linalg.norm(src[:, None] - q[None], axis=2)
    j = D.argmin(axis=1)
    qk, nk = q[j], given[j]
    c = src.mean(axis=0)
    x = np.linalg.lstsq(np.c_[np.cross(src - c, nk), nk], -np.einsum("ij,ij->i", src - qk, nk), rcond=None)[0]
    R = rotvec_matrix(x[:3])
    st = PointToPlane(PointToPlane.Params(max_iterations=1, initial_share=1.0, schedule="fixed", kernel="none",
                                          max_correspondence_distance=None, accept=False, distances="absolute"))
    res = st.refine(Cloud(q, given), Cloud(src), np.eye(4), 1.0, RunContext(seed=0))
    assert res.iterations == 1
    assert np.allclose(res.T_target_source[:3, :3], R, atol=1e-10)
    assert np.allclose(res.T_target_source[:3, 3], x[3:] + c - R @ c, atol=1e-10)


def test_anderson_started_at_its_fixed_point_converges_after_one_update():
    """Source = target and the identity: the first update changes nothing, so the RMS change after it (0) is
    below tau and the loop stops, converged, after exactly one update."""
    from scanreg.geometry import ClosestPoints, Cloud
    from scanreg.stages.icp.point import Anderson

    target, _ = anderson_case(4)
    st = Anderson(Anderson.Params(max_iterations=20, distances="absolute"))
    res = st.iterate(Cloud(target), Cloud(target.copy()), np.eye(4), ClosestPoints(Cloud(target)), 1e-9,
                     PairLimit(None, None))
    assert res.converged and res.iterations == 1 and len(res.rms_history) == 2
    assert np.allclose(res.T_target_source, np.eye(4), atol=1e-12)


def test_kernel_weights_between_their_breakpoints():
    """Huber below a scale under 1 (the weight scale / r, not scale / max(r, 1)), and Tukey's biweight just past
    its scale (0, not (1 - (r / s)^2)^2)."""
    from scanreg.stages.icp.base import kernel_weights

    r = np.array([0.05, 0.1, 0.5, 0.8])
    assert np.allclose(kernel_weights("huber", r, 0.1), [1.0, 1.0, 0.2, 0.125])
    assert np.array_equal(kernel_weights("tukey", np.array([1.2, 1.0, 0.5]), 1.0), [0.0, 0.0, 0.5625])


def icp(name, **kw):
    from scanreg.stages.registry import ICP, load_all, make_params

    load_all()
    cls = ICP.get(name)
    return cls(make_params(cls.Params, kw, f"icp={name}"))


def test_accept_distance_is_the_parameter_else_the_final_limit_else_three_spacings():
    assert icp("horn", accept_distance=None).accept_distance(None, 2.0) == 6.0
    assert icp("horn", accept_distance=None).accept_distance(1.5, 2.0) == 1.5
    assert icp("horn", accept_distance=4.0, distances="spacing").accept_distance(1.5, 2.0) == 8.0
    assert icp("horn", accept_distance=4.0, distances="absolute").accept_distance(None, 2.0) == 4.0


def test_the_accept_rule_counts_no_inlier_term_without_inliers():
    """Start pose with no point within the distance 2: cost 2^2 = 4. End pose with half of them at RMS 1.8:
    0.5 x 4 + 0.5 x 3.24 = 3.62, below 1.01 x 4: accepted. And an end pose of cost 4.08 (fitness 0.5, RMS
    2.02...: 0.5 x 4 + 0.5 x 4.16) above 1.01 x 4 is rejected."""
    from scanreg.stages.icp.base import IcpBase

    none = {"icp_fitness": 0.0, "icp_inlier_rms": float("nan")}
    assert IcpBase.accept(none, {"icp_fitness": 0.5, "icp_inlier_rms": 1.8}, 2.0)
    assert not IcpBase.accept(none, {"icp_fitness": 0.5, "icp_inlier_rms": np.sqrt(4.16)}, 2.0)
    assert IcpBase.accept(none, none, 2.0)
    perfect = {"icp_fitness": 1.0, "icp_inlier_rms": 0.0}
    assert IcpBase.accept(perfect, perfect, 2.0)  # cost 0 against 1.01 x 0: not clearly higher


def test_pair_limit_defaults_halve_the_limit_once_the_rms_changes_by_less_than_one_percent():
    """PairLimit's defaults are IcpParams' (shrink 0.5, settle 0.01): from 16 towards 4, an RMS change of 0.5 %
    of the RMS halves the limit; one of 2 % does not."""
    from scanreg.stages.icp.base import IcpParams

    assert (IcpParams().shrink, IcpParams().settle) == (0.5, 0.01)
    lim = PairLimit(16.0, 4.0)
    assert not lim.advance(1.0, 0.98, 0.0) and lim.limit == 16.0
    assert lim.advance(1.0, 0.995, 0.0) and lim.limit == 8.0


def test_besl_mckay_stops_on_the_rms_change_and_records_the_rms_of_every_pair():
    """A noisy copy of 300 points turned 5 degrees (the RMS settles near the noise, 0.02, not at 0): the history
    starts at the RMS of every point's distance to its nearest target point at the start (brute force here),
    the loop stops at the first RMS change below tau, and none before it is below tau."""
    from scanreg.geometry import ClosestPoints, Cloud, apply_T, make_T
    from scanreg.stages.icp.base import besl_mckay
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    pts = rng.normal(size=(300, 3)) * [3.0, 2.0, 1.0]
    T = make_T(Rotation.from_rotvec([0.0, 0.05, 0.07]).as_matrix(), np.array([0.1, 0.0, -0.1]))
    tgt = apply_T(T, pts) + rng.normal(scale=0.02, size=pts.shape)
    tau = 1e-6
    res = besl_mckay(ClosestPoints(Cloud(tgt)), pts, np.eye(4), tau, 100)
    d0 = np.sqrt(((pts[:, None] - tgt[None]) ** 2).sum(axis=2)).min(axis=1)
    assert res.rms_history[0] == pytest.approx(np.sqrt(np.mean(d0 ** 2)), rel=1e-12)
    changes = np.abs(np.diff(res.rms_history))
    assert res.converged and changes[-1] < tau and (changes[:-1] >= tau).all()
    assert 0.02 < res.rms_history[-1] < 0.05  # measured 0.034
    again = besl_mckay(ClosestPoints(Cloud(tgt)), pts, res.T_target_source, tau, 100)  # from its end point
    assert again.converged and again.iterations == 1


@pytest.mark.parametrize("n, coarse_to_fine", [(6, True), (5, False)])
def test_coarse_to_fine_needs_three_points_per_step(n, coarse_to_fine):
    """initial_share 0.5 (every 2nd point first) applies from 3 x 2 = 6 source points. The even points lie on
    the target, the odd ones 0.37 off: the first RMS is 0 on every 2nd point (coarse to fine), else the RMS of
    all n points' distances to their nearest target point (brute force)."""
    from scanreg.geometry import ClosestPoints, Cloud

    rng = np.random.default_rng(5)
    tgt = rng.normal(size=(6, 3)) * 3.0
    src = tgt[:n].copy()
    src[1::2] += [0.3, -0.2, 0.1]
    res = icp("horn", initial_share=0.5).converge(Cloud(tgt), Cloud(src), np.eye(4), ClosestPoints(Cloud(tgt)),
                                                   1e-9, None, None)
    d = np.sqrt(((src[:, None] - tgt[None]) ** 2).sum(axis=2)).min(axis=1)
    if coarse_to_fine:
        assert res.rms_history[0] == 0.0
    else:
        assert res.rms_history[0] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-12) and d.max() > 0.3
