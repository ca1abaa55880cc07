"""Known-answer tests of the paper's equations (issue #17 item 3): eq. 4, the histogram3p bins, the RANSAC
iteration count from mu, the ICP loop and its stopping rule, barycentric sampling, point-to-triangle distances,
non-maximum suppression and the 64-neighbour salience cap. Each compares the code with a direct computation or
a closed form, on small hand-made inputs."""

import math

import numpy as np
import pytest
from scipy import optimize, stats
from scipy.spatial.transform import Rotation

from scanreg.geometry import ClosestPoints
from scanreg.geometry import (Cloud, Mesh, apply_T, barycentric_sample, horn_quaternion, make_T, random_pose,
                              rigid_points_normals)
from scanreg.stages.registry import DESCRIPTOR, ICP, SALIENCE, load_all
from scanreg.stages import descriptor as descriptor_mod
from scanreg.stages.coarse.ransac import lo_ransac
from scanreg.stages.salience import non_maximum_suppression
from scanreg.types import RunContext

from conftest import build, build_coarse

load_all()


# ------------------------------------------------------------------------------------------ eq. 4


def eq4(T, p0, p1, n0, n1, w):
    R, t = T[:3, :3], T[:3, 3]
    return float(((p1 @ R.T + t - p0) ** 2).sum() + w * ((n1 @ R.T - n0) ** 2).sum())


@pytest.mark.parametrize("w", [0.0, 0.5, 5.0])
def test_eq4_closed_form_is_the_numerical_minimum(w):
    """rigid_points_normals(p0, p1, n0, n1, w) reaches the minimum of sum |R p1 + t - p0|^2 + w |R n1 - n0|^2
    found by BFGS over (rotation vector, t) from several starts, on noisy points and noisy normals."""
    rng = np.random.default_rng(3)
    T_true = random_pose(rng, 120, 2.0)
    p1 = rng.normal(size=(30, 3))
    n1 = rng.normal(size=(30, 3))
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    p0 = apply_T(T_true, p1) + rng.normal(scale=0.2, size=p1.shape)
    R_off = Rotation.from_rotvec([0.0, 0.0, 0.5]).as_matrix()  # normals agree with another rotation (29 deg off)
    n0 = n1 @ (T_true[:3, :3] @ R_off).T + rng.normal(scale=0.2, size=n1.shape)
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    T = rigid_points_normals(p0, p1, n0, n1, w)
    f = lambda x: eq4(make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:]), p0, p1, n0, n1, w)
    best = min((optimize.minimize(f, np.r_[Rotation.random(random_state=s).as_rotvec(), rng.normal(size=3)],
                                  method="BFGS", options={"gtol": 1e-10}) for s in range(6)), key=lambda r: r.fun)
    T_num = make_T(Rotation.from_rotvec(best.x[:3]).as_matrix(), best.x[3:])
    assert eq4(T, p0, p1, n0, n1, w) <= best.fun + 1e-7
    assert np.abs(T - T_num).max() < 1e-4
    if w > 0:  # the normal term matters here: the points-only fit is not the minimum
        assert eq4(rigid_points_normals(p0, p1), p0, p1, n0, n1, w) > best.fun + 1e-3


# ------------------------------------------------------------------------------------------ histogram3p


def hist_index(plane, ca, cb, co):
    return ((plane * 3 + ca) * 3 + cb) * 8 + co


def patch_frames(monkeypatch, F):
    """Every keypoint's local frame is F (rows x, y, z)."""
    monkeypatch.setattr(descriptor_mod, "local_frames", lambda p, n, kp, r, *a, **k: np.tile(F, (len(kp), 1, 1)))


def test_histogram3p_bins_by_hand(monkeypatch):
    """Identity local frame (patched), support radius R = 3: spatial bins of width 2 centred at -2, 0, 2 on each
    axis of the planes (x, y), (y, z), (z, x); orientation bins of width 45 degrees centred at -180 + 22.5 +
    45 k degrees of atan2(second, first) of the projected normal. Every vote is bilinear (1 - f, f) into the two
    nearest bins per axis, weighted (1 - d / R) / density (points within the density radius, itself included);
    votes into spatial bins outside the 3x3 grid are dropped. The expected 216 values are written out by hand."""
    patch_frames(monkeypatch, np.eye(3))
    a22 = np.radians(-180 + 22.5 + 45 * 4)  # centre of orientation bin 4 (22.5 degrees)
    a45 = np.radians(45.0)  # between bins 4 (22.5) and 5 (67.5): half each
    pts = np.array([
        [0.0, 0.0, 0.0],     # the keypoint
        [1.0, 0.5, 0.0],     # probe A: d = sqrt(1.25)
        [0.0, 0.0, -2.5],    # probe B: d = 2.5, its z bin half outside the grid
        [0.0, 0.0, -2.55],   # B's twin within the density radius: B and B' each have density 2
    ])
    nrm = np.array([
        [math.cos(a22), math.sin(a22), 0.0],   # angle in (x, y) 22.5: bin 4; (y, z): 0; (z, x): 90
        [math.cos(a45), math.sin(a45), 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 0.0, 1.0],
    ])
    d = Cloud(pts, nrm)
    st = build(DESCRIPTOR, "histogram3p", radius=3.0, frame_radius=3.0, density_radius=0.1, distances="absolute")
    got = st.compute(d, np.array([0]), 1.0)[0]

    want = np.zeros(216)

    def vote(plane, ca, cb, co, w):
        want[hist_index(plane, ca, cb, co)] += w

    # orientation coordinate uo = (angle + 180) / 45 - 0.5: 0 deg -> 3.5 (bins 3, 4 half each); 90 -> 5.5 (5, 6);
    # 22.5 -> 4 (bin 4); 45 -> 4.5 (4, 5); atan2(0, 0) = 0 -> 3.5; atan2(1, 0) = 90; atan2(0, 1) = 0
    # spatial coordinate u = (x + 3) / 2 - 0.5: 0 -> 1 (bin 1); 1 -> 1.5 (1, 2 half each); 0.5 -> 1.25 (1: 0.75,
    # 2: 0.25); -2.5 -> -0.25 (bin -1: 0.25 dropped, bin 0: 0.75); -2.55 -> -0.275 (bin -1 dropped, 0: 0.725)
    # keypoint: d = 0, weight 1, density 1
    vote(0, 1, 1, 4, 1.0)                                   # (x, y) = (0, 0), angle 22.5
    vote(1, 1, 1, 3, 0.5); vote(1, 1, 1, 4, 0.5)            # (y, z) = (0, 0), angle atan2(0, sin 22.5) = 0
    vote(2, 1, 1, 5, 0.5); vote(2, 1, 1, 6, 0.5)            # (z, x) = (0, 0), angle atan2(cos 22.5, 0) = 90
    # probe A: weight 1 - sqrt(1.25) / 3, density 1
    wA = 1 - math.sqrt(1.25) / 3
    for ca, fa in ((1, 0.5), (2, 0.5)):                       # (x, y) = (1, 0.5), angle 45
        for cb, fb in ((1, 0.75), (2, 0.25)):
            for co, fo in ((4, 0.5), (5, 0.5)):
                vote(0, ca, cb, co, wA * fa * fb * fo)
    for ca, fa in ((1, 0.75), (2, 0.25)):                     # (y, z) = (0.5, 0), angle atan2(0, sin 45) = 0
        for co in (3, 4):
            vote(1, ca, 1, co, wA * fa * 0.5)
    for cb, fb in ((1, 0.5), (2, 0.5)):                       # (z, x) = (0, 1), angle atan2(cos 45, 0) = 90
        for co in (5, 6):
            vote(2, 1, cb, co, wA * fb * 0.5)
    # probes B and B': normal (0, 0, 1), density 2 each
    for z in (-2.5, -2.55):
        wB = (1 - abs(z) / 3) / 2
        share0 = {-2.5: 0.75, -2.55: 0.725}[z]  # share of spatial bin 0 (the rest falls outside the grid)
        vote(0, 1, 1, 3, wB * 0.5); vote(0, 1, 1, 4, wB * 0.5)   # (x, y) = (0, 0), angle atan2(0, 0) = 0
        vote(1, 1, 0, 5, wB * share0 * 0.5); vote(1, 1, 0, 6, wB * share0 * 0.5)  # (y, z) = (0, z), angle 90
        vote(2, 0, 1, 3, wB * share0 * 0.5); vote(2, 0, 1, 4, wB * share0 * 0.5)  # (z, x) = (z, 0), angle 0
    want /= np.linalg.norm(want)
    assert np.abs(got - want).max() < 1e-12


def test_histogram3p_orientation_bins_wrap_around(monkeypatch):
    """An angle of 180 degrees (uo = 7.5) votes half into bin 7 and half into bin 0 (the circle closes)."""
    patch_frames(monkeypatch, np.eye(3))
    c = Cloud(np.zeros((1, 3)), np.array([[-1.0, 1e-300, 0.0]]))  # (x, y) angle atan2(+tiny, -1) = +180
    st = build(DESCRIPTOR, "histogram3p", radius=3.0, frame_radius=3.0, density_radius=0.1, distances="absolute")
    got = st.compute(c, np.array([0]), 1.0)[0]
    want = np.zeros(216)
    want[hist_index(0, 1, 1, 7)] = want[hist_index(0, 1, 1, 0)] = 0.5
    # (y, z): atan2(0, tiny) = 0 -> bins 3, 4; (z, x): atan2(-1, 0) = -90 -> uo = 1.5 -> bins 1, 2
    want[hist_index(1, 1, 1, 3)] = want[hist_index(1, 1, 1, 4)] = 0.5
    want[hist_index(2, 1, 1, 1)] = want[hist_index(2, 1, 1, 2)] = 0.5
    want /= np.linalg.norm(want)
    assert np.abs(got - want).max() < 1e-12


def test_histogram3p_expresses_neighbours_in_the_frame_rows(monkeypatch):
    """Local coordinates are F (p - k) and local normals F n, F the frame with rows x, y, z: the histogram of a
    cloud with frame F equals that of the cloud mapped by F with the identity frame."""
    rng = np.random.default_rng(11)
    pts = np.vstack([[0, 0, 0], rng.uniform(-2.5, 2.5, size=(40, 3))])
    nrm = rng.normal(size=(41, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    F = Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix()
    st = build(DESCRIPTOR, "histogram3p", radius=3.0, frame_radius=3.0, density_radius=0.8, distances="absolute")
    patch_frames(monkeypatch, F)
    got = st.compute(Cloud(pts, nrm), np.array([0]), 1.0)[0]
    patch_frames(monkeypatch, np.eye(3))
    want = st.compute(Cloud(pts @ F.T, nrm @ F.T), np.array([0]), 1.0)[0]
    assert np.count_nonzero(want) > 50 and np.abs(got - want).max() < 1e-12


def test_local_frame_of_a_crafted_patch():
    """A flat patch in z = 0 stretched along the direction 30 degrees from x, more points on its positive side,
    keypoint normal (0, 0, -1): z = the normal, x = the stretch direction (sign: the weighted mean offset),
    y = z cross x."""
    rng = np.random.default_rng(12)
    c, s_ = math.cos(math.radians(30)), math.sin(math.radians(30))
    a = np.r_[rng.uniform(-1.0, 2.0, 300)]          # along the stretch, skewed positive
    b = rng.uniform(-0.4, 0.4, 300)                 # across
    pts = np.vstack([[0, 0, 0], np.c_[a * c - b * s_, a * s_ + b * c, np.zeros(300)]])
    nrm = np.tile([0.0, 0.0, -1.0], (301, 1))
    F = descriptor_mod.local_frames(pts, nrm, np.array([0]), 2.5, max_neighbors=512)[0]
    x = np.array([c, s_, 0.0])
    assert np.abs(F[2] - [0, 0, -1]).max() < 1e-9
    assert np.abs(F[0] - x).max() < 0.05        # sampled: the covariance's axis within a few degrees
    assert np.abs(F[1] - np.cross(F[2], F[0])).max() < 1e-12 and np.linalg.det(F) == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------ RANSAC iterations


def ransac_problem(w, M=60, seed=0):
    """M correspondences of which exactly round(w M) are exact inliers of a pose; the rest far random."""
    rng = np.random.default_rng(seed)
    T = random_pose(rng, 90, 1.0)
    P1 = rng.uniform(-1, 1, size=(M, 3))
    P0 = apply_T(T, P1)
    k = int(round(w * M))
    P0[k:] = rng.uniform(-1, 1, size=(M - k, 3)) + 3.0 * rng.normal(size=(M - k, 3))
    return P0, P1, k


@pytest.mark.parametrize("w", [0.5, 0.35, 0.25])
def test_uniform_ransac_draws_the_closed_form_count(w):
    """With inlier share w and mu = 1/100, uniform RANSAC draws N = ceil(log(mu) / log(1 - w^3)) hypotheses:
    exactly N with batch 1 and min_iterations 1; with batch B and min_iterations m, the first multiple of B
    that is >= max(N, m)."""
    P0, P1, k = ransac_problem(w)
    N = math.ceil(math.log(0.01) / math.log(1 - (k / len(P0)) ** 3))
    st = build_coarse("lo_ransac", sampling="uniform", batch=1, min_iterations=1, distance_threshold=0.01,
                      distances="absolute", seed=1)
    r = lo_ransac(P0, P1, None, None, 0.01, st.p, st.p.seed)
    inl, drawn = r.inliers, r.hypotheses
    assert inl.sum() == k
    assert drawn == N
    st = build_coarse("lo_ransac", sampling="uniform", batch=64, min_iterations=100, distance_threshold=0.01,
                      distances="absolute", seed=1)
    r = lo_ransac(P0, P1, None, None, 0.01, st.p, st.p.seed)
    inl, drawn = r.inliers, r.hypotheses
    assert inl.sum() == k
    assert drawn == 64 * math.ceil(max(N, 100) / 64)


# ------------------------------------------------------------------------------------------ ICP


def nearest(q, target):
    d = np.linalg.norm(q[:, None, :] - target[None, :, :], axis=2)
    j = d.argmin(axis=1)
    return target[j], d[np.arange(len(q)), j]


def icp_case(seed=0):
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(150, 3)) * [3.0, 2.0, 1.0]
    T = random_pose(rng, 12, 0.3, min_angle_deg=8)
    src = apply_T(np.linalg.inv(T), target[:120]) + rng.normal(scale=0.02, size=(120, 3))
    return Cloud(target), Cloud(src)


def sliding_case(seed=0):
    """A smooth bowl: ICP slides slowly along it (nine updates of decreasing size before it settles)."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-2, 2, 15), np.linspace(-2, 2, 15))
    target = np.c_[x.ravel(), y.ravel(), 0.15 * x.ravel() ** 2 + 0.1 * y.ravel() ** 2]
    T = make_T(Rotation.from_rotvec([0, 0, 0.1]).as_matrix(), [0.3, 0.2, 0.0])
    src = apply_T(T, target[rng.choice(len(target), 120, replace=False)]) + rng.normal(scale=0.01, size=(120, 3))
    return Cloud(target), Cloud(src)


def direct_icp_history(target, source, n, maxd=None):
    """RMS closest-point distance (of the pairs within ``maxd``) at each of n + 1 Besl-McKay iterates, each
    T_{k+1} = Horn(Y_k, P0) from the original source: the loop written out plainly."""
    T, h = np.eye(4), []
    for _ in range(n + 1):
        Y, d = nearest(apply_T(T, source.points), target.points)
        ok = np.ones(len(d), bool) if maxd is None else d <= maxd
        h.append(math.sqrt(np.mean(d[ok] ** 2)))
        T = horn_quaternion(Y[ok], source.points[ok])
    return np.array(h)


def run_horn(target, source, **kw):
    """The paper's Besl-McKay loop: a fixed pair limit (no adaptive schedule), least squares, no acceptance test,
    no half-turns."""
    st = build(ICP, "horn", **{"max_correspondence_distance": None, "distances": "absolute", "schedule": "fixed",
                               "kernel": "none", "accept": False, "half_turns": None, **kw})
    return st.refine(target, source, np.eye(4), 1.0, RunContext(seed=0))


def test_icp_each_iterate_is_horn_from_the_original_source():
    """Besl-McKay: T_{k+1} = Q(P0, Y_k), the least-squares transform of the ORIGINAL source P0 onto its closest
    points Y_k at T_k. The code composes increments (T <- Q(T_k P0, Y_k) T_k), which is the same transform in
    exact arithmetic; checked per iterate (runs with max_iterations = k give T_k), and the rms_history entry k is
    the RMS closest-point distance at T_k (before the update)."""
    target, source = icp_case()
    full = run_horn(target, source, tau=0.0, max_iterations=8)
    T_k = np.eye(4)
    for k in range(1, 9):
        Y, d = nearest(apply_T(T_k, source.points), target.points)
        assert full.rms_history[k - 1] == pytest.approx(math.sqrt(np.mean(d ** 2)), rel=1e-12)
        T_next = run_horn(target, source, tau=0.0, max_iterations=k).T_target_source
        assert np.abs(T_next - horn_quaternion(Y, source.points)).max() < 1e-10
        T_k = T_next


def test_icp_stopping_rule_is_the_absolute_rms_change_before_each_update():
    """The code stops at the first iterate k > 0 with |rms_{k-1} - rms_k| < tau, where rms_k is the RMS
    closest-point distance at T_k before its update (so ``iterations`` = k updates, k + 1 history entries).
    The paper's rule, d_k - d_{k+1} < tau on Besl-McKay's mean-square error d_k, would stop at a different
    iterate on this case: pinned here as the code's documented deviation."""
    target, source = sliding_case()
    h = direct_icp_history(target, source, 30)
    dh = np.abs(np.diff(h))
    msd = np.diff(np.asarray(h) ** 2) * -1.0  # the paper's d_k - d_{k+1} on the mean-square error
    first = lambda change, tau: int(np.argmax(change < tau)) + 1
    # a tau (just above one of the RMS changes) at which the two rules stop at different iterates
    tau = next(t for t in dh[dh > 0] * 1.0001 if first(dh, t) != first(msd, t))
    res = run_horn(target, source, tau=float(tau), max_iterations=30)
    k_code = first(dh, tau)
    assert res.converged and res.iterations == k_code and len(res.rms_history) == k_code + 1
    assert res.rms_history == pytest.approx(h[:k_code + 1], rel=1e-9)
    assert first(msd, tau) != k_code


def test_icp_stopping_rule_takes_the_absolute_change_so_an_rms_increase_does_not_stop_it():
    """With max_correspondence_distance the RMS of the pairs used can rise (pairs enter and leave). The code's
    |rms_{k-1} - rms_k| < tau goes on through a rise larger than tau; the paper's signed d_k - d_{k+1} < tau
    would stop right there. Pinned: the code's count, and that the signed rule stops earlier, at a rise."""
    target, source = sliding_case()
    h = direct_icp_history(target, source, 30, maxd=0.15)
    first = lambda change, tau: int(np.argmax(change < tau)) + 1
    dh, signed = np.abs(np.diff(h)), h[:-1] - h[1:]
    tau = next(t for t in np.sort(dh[dh > 0]) * 1.0001 if first(dh, t) != first(signed, t))
    res = run_horn(target, source, tau=float(tau), max_iterations=30, max_correspondence_distance=0.15)
    k_code, k_signed = first(dh, tau), first(signed, tau)
    assert res.converged and res.iterations == k_code
    assert k_signed < k_code and h[k_signed] > h[k_signed - 1] + tau  # the signed rule stops at a rise


# ------------------------------------------------------------------------------------------ barycentric


TRI = Mesh(np.array([[1.0, 2.0, 0.5], [4.0, 2.5, 1.0], [2.0, 5.0, -1.0]]), np.array([[0, 1, 2]]))


def barycentric_uv(pts, mesh=TRI):
    a, b, c = mesh.vertices
    uv, *_ = np.linalg.lstsq(np.stack([b - a, c - a], axis=1), (pts - a).T, rcond=None)
    return uv.T


def uniformity_pvalues(uv):
    u, v = uv[:, 0], uv[:, 1]
    sub = np.where(u >= 0.5, 0, np.where(v >= 0.5, 1, np.where(u + v <= 0.5, 2, 3)))  # midpoint subdivision
    counts = np.bincount(sub, minlength=4)
    return stats.chisquare(counts).pvalue, stats.kstest(u, lambda x: 1 - (1 - np.clip(x, 0, 1)) ** 2).pvalue


def test_barycentric_sample_is_uniform_on_the_triangle():
    """Reflection (u + v > 1 -> 1 - u, 1 - v): every point on the triangle, equal counts in the 4 congruent
    midpoint sub-triangles (chi-square), and u with density 2 (1 - u) (KS). Wrong variants fail the same test."""
    n = 20000
    pts, _, _ = barycentric_sample(TRI, n, np.random.default_rng(5))
    uv = barycentric_uv(pts)
    assert (uv >= -1e-9).all() and (uv.sum(axis=1) <= 1 + 1e-9).all()
    p_chi, p_ks = uniformity_pvalues(uv)
    assert p_chi > 1e-3 and p_ks > 1e-3
    rng = np.random.default_rng(5)
    r = rng.random((n, 2))
    normalised = r / np.maximum(1.0, r.sum(axis=1, keepdims=True))  # "u, v normalised" instead of reflected
    assert min(uniformity_pvalues(normalised)) < 1e-6
    e = rng.exponential(size=(n, 3))
    wrong_dirichlet = np.sqrt(e[:, :2] / e.sum(axis=1, keepdims=True))  # a skewed variant
    assert min(uniformity_pvalues(wrong_dirichlet)) < 1e-6


# ------------------------------------------------------------------------------------------ point-to-triangle


def test_closest_points_on_a_triangle_edge_and_vertex():
    """Triangle A (0,0,0), B (1,0,0), C (0,1,0); exact closest points by hand: vertex region of B, interior of
    edge AB, interior of edge BC (the hypotenuse), vertex region of C, and the face interior."""
    mesh = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    cp = ClosestPoints(Cloud(mesh.vertices), mesh)
    q = np.array([[2.0, -0.5, 0.3],    # (q - B).(A - B) = -1, (q - B).(C - B) = -1.5: vertex B
                  [0.5, -1.0, 0.5],    # below edge AB: its point (0.5, 0, 0)
                  [1.0, 1.0, 0.2],     # beyond the hypotenuse: its midpoint (0.5, 0.5, 0)
                  [-0.5, 2.0, -1.0],   # vertex C
                  [0.2, 0.3, 0.7]])    # above the face
    want = np.array([[1.0, 0, 0], [0.5, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0.2, 0.3, 0]])
    want_d = np.array([math.sqrt(1 + 0.25 + 0.09), math.sqrt(1 + 0.25), math.sqrt(0.5 + 0.04),
                       math.sqrt(0.25 + 1 + 1), 0.7])
    got, d, _ = cp(q)
    assert np.abs(got - want).max() < 1e-6
    assert np.abs(d - want_d).max() < 1e-6


# ------------------------------------------------------------------------------------------ NMS and the cap


def brute_nms(points, h, radius):
    D = np.linalg.norm(points[:, None] - points[None], axis=2)
    return np.array([i for i in range(len(points))
                     if np.isfinite(h[i]) and all(h[i] >= h[j] for j in np.flatnonzero(D[i] <= radius))])


def test_nms_equals_the_brute_force_set():
    """With fewer than 64 points within the radius everywhere, the kept set is exactly {p : h(p) finite and
    h(p) >= h(i) for every i within the radius} (O(n^2) loop), ties (equal h) keeping both, -inf never kept."""
    rng = np.random.default_rng(4)
    pts = rng.uniform(0, 10, size=(400, 3))
    h = np.round(rng.normal(size=400), 1)  # many ties
    h[rng.choice(400, 40, replace=False)] = -np.inf
    kept = non_maximum_suppression(pts, h, 1.5)
    assert len(kept) > 20
    assert np.array_equal(kept, brute_nms(pts, h, 1.5))


def test_nms_only_sees_the_64_nearest_within_the_radius():
    """Deviation (pinned): suppression compares p with its ``max_neighbors`` (64) nearest neighbours within the
    radius, not with every point within it. A point with 80 neighbours within the radius, the most salient one
    the farthest, is kept by the code and not by the paper's rule."""
    rng = np.random.default_rng(6)
    d = np.sort(rng.uniform(0.1, 0.9, 80))
    dirs = rng.normal(size=(80, 3))
    pts = np.vstack([[0, 0, 0], dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * d[:, None]])
    h = np.zeros(81)
    h[0], h[80] = 1.0, 2.0  # the farthest point (the 81st nearest of point 0, itself included) is the most salient
    assert 0 in non_maximum_suppression(pts, h, 1.0)
    assert 0 not in brute_nms(pts, h, 1.0)
    assert 0 not in non_maximum_suppression(pts, h, 1.0, max_neighbors=128)


@pytest.mark.parametrize("weights", ["uniform", "gaussian"])
@pytest.mark.parametrize("measure", ["min_ratio", "l1", "l3"])
def test_salience_at_the_64_neighbour_cap(measure, weights):
    """EigenSalience's default cap: the weighted covariance of exactly the 64 nearest neighbours within the
    radius (itself included; weights 1 or exp(-d^2 / (2 (radius/2)^2)); divided by the sum of the weights) gives
    the code's value."""
    rng = np.random.default_rng(8)
    pts = rng.normal(size=(600, 3)) * [2.0, 1.0, 0.3]
    st = build(SALIENCE, f"cp_{measure}", radius=1.5, weights=weights, distances="absolute")
    assert st.p.max_neighbors == 64
    h = st.values(Cloud(pts), 1.0)
    checked = 0
    for i in rng.choice(600, 30, replace=False):
        dist = np.linalg.norm(pts - pts[i], axis=1)
        nb = np.argsort(dist)[:64]
        if dist[nb].max() > 1.5 or (dist <= 1.5).sum() <= 64:
            continue  # only points whose radius holds more than 64 neighbours
        P = pts[nb]
        w = np.exp(-dist[nb] ** 2 / (2 * 0.75 ** 2)) if weights == "gaussian" else np.ones(64)
        mu = w @ P / w.sum()
        C = ((P - mu) * w[:, None]).T @ (P - mu) / w.sum()
        l1, l2, l3 = np.linalg.eigvalsh(C)
        want = {"min_ratio": min(l1 / l2, l2 / l3), "l1": l1, "l3": l3}[measure]
        assert h[i] == pytest.approx(want, rel=1e-9)
        checked += 1
    assert checked >= 10
