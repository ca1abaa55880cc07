"""Issue #13, items 4 and 5: an ICP basin that matches the coarse stage (the adaptive pair-limit schedule, robust
kernels) and a fine stage that never makes a pose worse unnoticed (the acceptance test, ``icp_accepted``)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import shared
from scanreg.types import RunContext as Context
from scanreg.errors import ConfigError
from scanreg.geometry import Cloud, apply_T, barycentric_sample, bbox_diagonal, make_T, random_pose, transform_errors
from scanreg.io import read_mesh
from scanreg.geometry import estimate_spacing
from scanreg.stages.icp.base import IcpBase, kernel_weights


def icp_stage(name, **kw):
    from scanreg.stages.registry import ICP, load_all, make_params

    load_all()
    cls = ICP.get(name)
    return cls(make_params(cls.Params, kw, f"icp={name}"))


CTX = Context(seed=0, run_dir=None)
"""The run context of every refinement here (read-only; the spacing is an argument of ``refine``)."""


def sampled(mesh, n, seed):
    pts, nrm, _ = barycentric_sample(mesh, n, np.random.default_rng(seed))
    return Cloud(pts, nrm)


def moved_pose(points, angle_deg, shift_share, seed):
    """A rotation of ``angle_deg`` about a random axis through the points' centre, then a shift of
    ``shift_share`` of their bounding-box diagonal in a random direction."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    t = rng.normal(size=3)
    t *= shift_share * bbox_diagonal(points) / np.linalg.norm(t)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(angle_deg)).as_matrix()
    c = points.mean(0)
    return make_T(R, c + t - R @ c)


@pytest.fixture(scope="module")
def bunny_10deg():
    """pymeshlab's closed bunny, two independent samplings; the target moved 10 degrees and 2 % of the diagonal."""
    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    a, b = sampled(m, 30000, 1), sampled(m, 30000, 2)
    T = moved_pose(a.points, 10.0, 0.02, 0)
    tgt = Cloud(apply_T(T, a.points), a.normals @ T[:3, :3].T)
    return tgt, b, T, estimate_spacing(tgt.points, np.random.default_rng(0))


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["horn", "point_to_plane", "anderson", "gicp", "open3d"])
def test_icp_alone_converges_from_10_degrees_and_2_percent(variant, bunny_10deg):
    """coarse=none: the pair limit starts at 5 % of the diagonal and tightens to 3 spacings; every variant
    reaches the truth (< 0.1 deg). With the limit fixed at 3 spacings Besl-McKay stays degrees off."""
    tgt, src, T, sp = bunny_10deg
    assert transform_errors(np.eye(4), T)[0] == pytest.approx(10.0)
    res = icp_stage(variant).refine(tgt, src, np.eye(4), sp, CTX)
    rot, trans = transform_errors(res.T_target_source, T)
    assert rot < 0.1 and trans < 1e-3 * bbox_diagonal(tgt.points), (variant, rot, trans)
    assert res.converged and res.metrics["icp_accepted"] == 1.0
    # the stopping rule held at the final limit, after the limit had tightened from 5 % of the diagonal
    assert res.metrics["icp_pair_limit_end_spacings"] == pytest.approx(3.0)
    assert res.metrics["icp_pair_limit_start_spacings"] * sp == pytest.approx(0.05 * bbox_diagonal(tgt.points))
    assert res.metrics["icp_fitness"] > 0.99 and len(res.rms_history) == res.iterations + 1
    if variant == "horn":
        fixed = icp_stage(variant, schedule="fixed", accept=False).refine(tgt, src, np.eye(4), sp, CTX)
        assert transform_errors(fixed.T_target_source, T)[0] > 5.0


def test_schedule_tightens_only_when_settled_and_stops_only_at_the_floor():
    from scanreg.stages.icp.base import PairLimit

    lim = PairLimit(16.0, 3.0, shrink=0.5, settle=0.01)
    assert not lim.advance(1.0, 0.9, tau=1e-4)  # 10 % change: not settled, the limit stays
    assert lim.limit == 16.0 and not lim.settled
    assert lim.advance(1.0, 0.995, tau=1e-4) and lim.limit == 8.0
    assert lim.advance(1.0, 1.0, 1e-4) and lim.limit == 4.0
    assert lim.advance(1.0, 1.0, 1e-4) and lim.limit == 3.0 and lim.settled
    assert not lim.advance(1.0, 1.0, 1e-4) and lim.limit == 3.0
    assert PairLimit(None, None).settled
    with pytest.raises(Exception, match="schedule"):
        icp_stage("horn", schedule="kiss")
    with pytest.raises(Exception, match="shrink"):
        icp_stage("horn", shrink=1.0)


def test_kernel_weights():
    r = np.array([0.0, 0.5, 1.0, 2.0, 4.0])
    assert np.allclose(kernel_weights("huber", r, 1.0), [1, 1, 1, 0.5, 0.25])
    assert np.allclose(kernel_weights("tukey", r, 1.0), [1, 0.5625, 0, 0, 0])
    assert np.allclose(kernel_weights("geman_mcclure", r, 1.0), [1, 1 / 1.5625, 0.25, 1 / 25, 1 / 289])
    assert np.allclose(kernel_weights("cauchy", r, 2.0), [1, 1 / 1.0625, 0.8, 0.5, 0.2])
    assert kernel_weights("none", r, 1.0) is None
    with pytest.raises(Exception, match="kernel"):
        icp_stage("horn", kernel="welsch")
    with pytest.raises(ConfigError, match="kernel"):
        icp_stage("gicp", kernel="huber").refine(Cloud(np.random.default_rng(0).normal(size=(100, 3))),
                                                 Cloud(np.random.default_rng(1).normal(size=(100, 3))), np.eye(4),
                                                 0.1, CTX)
    with pytest.raises(ConfigError, match="kernel"):
        icp_stage("open3d", kernel="huber").refine(Cloud(np.zeros((10, 3))), Cloud(np.zeros((10, 3))), np.eye(4),
                                                   0.1, CTX)


def partial_overlap_case():
    """Target: 40 % of the bunny under a 5-degree pose T; source: an independent sampling of all of it.
    Returns (target, source, T, the target's spacing)."""
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    a, b = sampled(m, 20000, 1), sampled(m, 20000, 2)
    keep = a.points[:, 1] < np.quantile(a.points[:, 1], 0.4)
    T = random_pose(np.random.default_rng(5), 5, 1.0)
    tgt = Cloud(apply_T(T, a.points[keep]), a.normals[keep] @ T[:3, :3].T)
    return tgt, b, T, estimate_spacing(tgt.points, np.random.default_rng(0))


@pytest.mark.parametrize("variant", ["horn", "point_to_plane", "open3d_plane"])
def test_robust_kernels_hold_a_partial_overlap(variant):
    """Target: 40 % of the bunny; source: all of it, started 5 deg off. With a wide fixed limit (20 spacings)
    least squares is pulled by the source's unmatched part; a Geman-McClure kernel at 1 spacing holds the truth
    (weighted Horn, the weighted 6x6 solve, Open3D's GMLoss)."""
    tgt, b, T, sp = partial_overlap_case()
    name, kw = ("open3d", dict(estimation="point_to_plane")) if variant == "open3d_plane" else (variant, {})
    kw.update(schedule="fixed", max_correspondence_distance=20.0, accept=False, max_iterations=200)
    ls = icp_stage(name, kernel="none", **kw).refine(tgt, b, np.eye(4), sp, CTX)
    gm = icp_stage(name, kernel="geman_mcclure", kernel_scale=1.0, **kw).refine(tgt, b, np.eye(4), sp, CTX)
    e_ls, e_gm = transform_errors(ls.T_target_source, T)[0], transform_errors(gm.T_target_source, T)[0]
    assert e_gm < 0.3 and e_gm < 0.5 * e_ls, (variant, e_gm, e_ls)


def test_acceptance_keeps_the_start_pose_when_icp_drifts():
    """Started at the truth on a 40 % partial overlap, Besl-McKay with a wide fixed limit (20 spacings) drifts
    degrees away: fewer source points within 3 spacings afterwards (accept_distance), so the start pose is kept
    and logged as icp_accepted = 0; with the default schedule ICP stays and is accepted (accept_distance null: the
    final pair limit, 3 spacings)."""
    tgt, b, T, sp = partial_overlap_case()
    kw = dict(schedule="fixed", max_correspondence_distance=20.0, accept_distance=3.0)
    drift = icp_stage("horn", accept=False, **kw).refine(tgt, b, T, sp, CTX)
    assert transform_errors(drift.T_target_source, T)[0] > 2.0 and drift.metrics["icp_accepted"] == 1.0
    kept = icp_stage("horn", **kw).refine(tgt, b, T, sp, CTX)
    assert kept.metrics["icp_accepted"] == 0.0
    assert np.array_equal(kept.T_target_source, T)
    assert kept.metrics["icp_accept_end_fitness"] < 0.99 * kept.metrics["icp_accept_start_fitness"]
    # the reported fitness is the kept pose's (at the final pair limit, 20 spacings), computed here with SciPy
    from scipy.spatial import cKDTree

    d = cKDTree(tgt.points).query(apply_T(T, b.points))[0]
    assert kept.metrics["icp_fitness"] == pytest.approx(float((d <= 20.0 * sp).mean()), abs=1e-9)
    good = icp_stage("horn").refine(tgt, b, T, sp, CTX)
    assert good.metrics["icp_accepted"] == 1.0 and transform_errors(good.T_target_source, T)[0] < 0.3


def test_accept_rule():
    """The truncated least-squares cost at distance D: (1 - f) D^2 + f rms^2, f the share within D."""
    s = {"icp_fitness": 0.5, "icp_inlier_rms": 1.0}  # cost at D = 2: 0.5 * 4 + 0.5 * 1 = 2.5
    assert IcpBase.accept(s, {"icp_fitness": 0.6, "icp_inlier_rms": 1.2}, 2.0)  # 1.6 + 0.864 = 2.464
    assert IcpBase.accept(s, {"icp_fitness": 0.5, "icp_inlier_rms": 0.9}, 2.0)  # as many, closer
    assert IcpBase.accept(s, {"icp_fitness": 0.45, "icp_inlier_rms": 0.5}, 2.0)  # 2.2 + 0.1125: fewer, tighter
    assert not IcpBase.accept(s, {"icp_fitness": 0.45, "icp_inlier_rms": 0.5}, 3.0)  # 4.95 + 0.11 > 4.5 + 0.5
    assert not IcpBase.accept(s, {"icp_fitness": 0.501, "icp_inlier_rms": 1.1}, 2.0)  # 1.996 + 0.606 > 1.01 x 2.5
    assert IcpBase.accept(s, {"icp_fitness": 0.5, "icp_inlier_rms": 1.004}, 2.0)  # within 1 %: not clearly worse
    assert not IcpBase.accept(s, {"icp_fitness": 0.0, "icp_inlier_rms": float("nan")}, 2.0)
    assert IcpBase.accept({"icp_fitness": 0.0, "icp_inlier_rms": float("nan")}, s, 2.0)


@pytest.mark.parametrize("variant", ["point_to_plane", "gicp", "anderson"])
def test_same_seed_same_transform(variant, bunny_10deg):
    tgt, src, T, sp = bunny_10deg
    sub = Cloud(src.points[::4], src.normals[::4])
    r1 = icp_stage(variant).refine(tgt, sub, np.eye(4), sp, CTX)
    r2 = icp_stage(variant).refine(tgt, sub, np.eye(4), sp, CTX)
    assert np.array_equal(r1.T_target_source, r2.T_target_source) and r1.rms_history == r2.rms_history
    # and the right pose (measured: 0.0019, 0.0021 and 0.052 deg)
    bound = {"point_to_plane": 0.006, "gicp": 0.0065, "anderson": 0.16}[variant]
    assert transform_errors(r1.T_target_source, T)[0] < bound


@pytest.mark.slow
def test_3dmatch_pair_icp_keeps_a_good_coarse_pose():
    """The real 3DMatch RGB-D pair (45 % overlap), started where a good coarse stage lands (0.9 deg, 0.8 cm off
    gt.npy): point-to-plane ICP (the default) reaches the pose it reaches from gt.npy itself, and that pose
    explains the data better than the start (accepted). Translation: every ICP variant, also Open3D's, also started at gt.npy
    itself, settles about 9-11 cm (at the camera origin; 5-6 cm at the overlap's centre) from gt.npy, at a pose
    with more points within 3 spacings and a lower RMS than gt.npy's (README): the data's optimum, not the
    schedule's; the test bounds it at 10 cm."""
    folder = shared("3dmatch_pair")
    src = np.load(folder / "src.npy")[:, :3].astype(float)
    ref = np.load(folder / "ref.npy")[:, :3].astype(float)
    gt = np.load(folder / "gt.npy")
    sp = max(estimate_spacing(ref, np.random.default_rng(1)), estimate_spacing(src, np.random.default_rng(2)))
    T0 = moved_pose(apply_T(gt, src), 0.9, 0.008 / bbox_diagonal(apply_T(gt, src)), 1) @ gt
    r0, t0 = transform_errors(T0, gt)
    assert r0 == pytest.approx(0.9, abs=1e-3) and t0 < 0.05
    res = icp_stage("point_to_plane").refine(Cloud(ref), Cloud(src), T0, sp, CTX)
    # the data's optimum: the pose ICP reaches when started at gt.npy itself (measured: the two poses 7e-6 deg and
    # 1e-7 m apart; ICP that does not move stays 0.9 deg and 4.2 cm away)
    at_gt = icp_stage("point_to_plane").refine(Cloud(ref), Cloud(src), gt, sp, CTX)
    rot, trans = transform_errors(res.T_target_source, at_gt.T_target_source)
    assert rot < 1e-3 and trans < 1e-5, (rot, trans)
    assert res.metrics["icp_accepted"] == 1.0
    assert res.metrics["icp_accept_end_fitness"] > res.metrics["icp_accept_start_fitness"]
    assert res.metrics["icp_accept_end_rms"] < res.metrics["icp_accept_start_rms"]


def elongated_blob():
    """Issue #35's first case: 4,000 Gaussian points with axes 3:2:1 (a volume, not a surface)."""
    return np.random.default_rng(0).normal(size=(4000, 3)) * np.array([3.0, 2.0, 1.0])


@pytest.mark.parametrize("variant", ["horn", "point_to_plane", "anderson", "gicp"])
@pytest.mark.parametrize("pose", ["21deg", "30deg_5pct"])
def test_without_a_coarse_estimate_icp_searches_the_widest_basin(variant, pose):
    """coarse=none on an elongated blob against itself moved 21 degrees (rotation vector (0.2, -0.1, 0.3)) or 30
    degrees and 5 % of its diagonal: from 21 degrees the pair-limit schedule alone stops 9-19 degrees off (it pairs
    each point with a neighbour inside the volume and settles); with the start pose flagged as the inputs' own,
    the Besl-McKay basin is searched too and every variant lands on the truth (measured: < 1e-12 deg, the same
    points)."""
    pts = elongated_blob()
    if pose == "21deg":
        T = make_T(Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([0.5, -0.3, 0.2]))
    else:
        T = moved_pose(pts, 30.0, 0.05, 3)
    tgt, src = Cloud(apply_T(T, pts)), Cloud(pts)
    sp = estimate_spacing(tgt.points, np.random.default_rng(0))
    local = icp_stage(variant).refine(tgt, src, np.eye(4), sp, CTX)  # a coarse estimate: the schedule only
    assert "icp_basin_wide" not in local.metrics
    if pose == "21deg":
        assert transform_errors(local.T_target_source, T)[0] > 5.0
    res = icp_stage(variant).refine(tgt, src, np.eye(4), sp, CTX, start_is_estimate=False)
    rot, trans = transform_errors(res.T_target_source, T)
    assert rot < 1e-6 and trans < 1e-6, (variant, rot, trans)
    assert len(res.rms_history) == res.iterations + 1
    # kept when clearly better; where the schedule reaches the truth too (gicp from 30 degrees), its own end point
    assert res.metrics["icp_basin_wide"] == float(transform_errors(local.T_target_source, T)[0] > 1e-6)


@pytest.fixture(scope="module")
def bunny_30deg():
    """Issue #35's second case: pymeshlab's bunny, two independent samplings of 20,000 points; the target turned
    30 degrees about (1, 1, 0) through the origin (off the bunny) and shifted 5 % of the diagonal along x."""
    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    a, b = sampled(m, 20000, 1), sampled(m, 20000, 2)
    R = Rotation.from_rotvec(np.radians(30.0) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)).as_matrix()
    T = make_T(R, 0.05 * bbox_diagonal(a.points) * np.array([1.0, 0.0, 0.0]))
    tgt = Cloud(apply_T(T, a.points), a.normals @ R.T)
    return tgt, b, T, estimate_spacing(tgt.points, np.random.default_rng(0))


# measured rotation errors (deg) from 30 degrees: point-to-point keeps the bias of two independent samplings
BUNNY_30DEG_BOUND = {"horn": 0.1, "anderson": 0.1, "point_to_plane": 0.0015, "gicp": 0.004}
"""horn, anderson 0.035; point_to_plane 0.0004; gicp 0.0011 (each bound about 3x, 0.1 the issue's)."""


@pytest.mark.parametrize("variant", ["horn", "point_to_plane", "anderson", "gicp"])
def test_icp_alone_converges_from_30_degrees_and_5_percent(variant, bunny_30deg):
    tgt, src, T, sp = bunny_30deg
    assert transform_errors(np.eye(4), T)[0] == pytest.approx(30.0)
    res = icp_stage(variant).refine(tgt, src, np.eye(4), sp, CTX, start_is_estimate=False)
    rot, trans = transform_errors(res.T_target_source, T)
    assert rot < BUNNY_30DEG_BOUND[variant] and trans < 1e-3 * bbox_diagonal(tgt.points), (variant, rot, trans)
    assert res.metrics["icp_basin_wide"] == 1.0 and res.metrics["icp_fitness"] > 0.99
    if variant == "point_to_plane":  # the schedule alone: about 30 degrees off
        local = icp_stage(variant, basin="local").refine(tgt, src, np.eye(4), sp, CTX, start_is_estimate=False)
        assert transform_errors(local.T_target_source, T)[0] > 20.0


def test_a_partial_overlap_keeps_the_schedules_end_point():
    """Target: 40 % of the bunny, 5 degrees off, no coarse estimate: every pair pulls the source off the overlap,
    so the wide basin's end point explains less of the source and the schedule's is kept, bit for bit."""
    tgt, src, T, sp = partial_overlap_case()
    local = icp_stage("point_to_plane", basin="local").refine(tgt, src, np.eye(4), sp, CTX)
    res = icp_stage("point_to_plane").refine(tgt, src, np.eye(4), sp, CTX, start_is_estimate=False)
    assert res.metrics["icp_basin_wide"] == 0.0
    assert np.array_equal(res.T_target_source, local.T_target_source)
    assert transform_errors(res.T_target_source, T)[0] < 0.1


def test_besl_mckay_never_raises_the_rms_and_counts_its_updates():
    """The paper's loop with every pair: the RMS of each iterate is at most the previous one's (Besl & McKay's
    monotone convergence), one history entry per update plus the start."""
    from scanreg.geometry import ClosestPoints
    from scanreg.stages.icp.base import besl_mckay

    pts = elongated_blob()
    T = make_T(Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([0.5, -0.3, 0.2]))
    res = besl_mckay(ClosestPoints(Cloud(apply_T(T, pts))), pts, np.eye(4), 1e-9, 200)
    assert res.converged and len(res.rms_history) == res.iterations + 1 and res.iterations > 10
    assert np.all(np.diff(res.rms_history) <= 1e-12)
    assert transform_errors(res.T_target_source, T)[0] < 1e-6
    capped = besl_mckay(ClosestPoints(Cloud(apply_T(T, pts))), pts, np.eye(4), 1e-9, 5)
    assert capped.iterations == 5 and not capped.converged and len(capped.rms_history) == 6


def test_basin_values_are_checked():
    with pytest.raises(Exception, match="basin"):
        icp_stage("horn", basin="global")
    with pytest.raises(Exception, match="basin_points"):
        icp_stage("horn", basin_points=2)
    with pytest.raises(Exception, match="basin"):
        icp_stage("open3d", basin="wide")


@pytest.mark.slow
def test_coarse_none_tells_icp_that_the_start_is_the_inputs_own(tmp_path):
    """Through the API as a user calls it: ``coarse=none`` hands ICP the inputs' own pose, flagged as no
    estimate, so the default ICP searches the wide basin too and recovers the blob's 21-degree pose."""
    import scanreg

    pts = elongated_blob()
    T = make_T(Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([0.5, -0.3, 0.2]))
    res = scanreg.register(pts, apply_T(T, pts), overrides=["coarse=none"], run_dir=tmp_path)
    assert res.metrics["icp_basin_wide"] == 1.0
    assert transform_errors(res.T_target_source, T)[0] < 1e-6


@pytest.mark.parametrize("variant", ["horn", "point_to_plane", "anderson", "gicp", "open3d"])
@pytest.mark.parametrize("on_mesh", [False, True])
def test_the_acceptance_test_measures_the_end_pose_as_a_fresh_search_does(variant, on_mesh):
    """The acceptance test's end-pose numbers (``icp_accept_end_*``) reuse the last iterate's distances when they
    were measured with the stage's own search at the same distance; they must equal a fresh search at the pose
    returned, bit for bit (the source in the stage's Morton order, one BLAS thread, as the stage measures): on
    points and on the target's triangles, where GICP still iterates on points and icp=open3d measures points."""
    from scanreg.geometry import ClosestPoints
    from scanreg.geometry.voxels import morton_order
    from scanreg.process import blas_single_thread

    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    tgt, src = sampled(m, 4000, 1), sampled(m, 4000, 2)
    T0 = moved_pose(src.points, 4.0, 0.01, 3)
    source = Cloud(apply_T(np.linalg.inv(T0), src.points), src.normals @ np.linalg.inv(T0)[:3, :3].T)
    sp = estimate_spacing(tgt.points, np.random.default_rng(0))
    st = icp_stage(variant, **({"kernel": "none"} if variant in ("gicp", "open3d") else {}))
    mesh = m if on_mesh else None
    res = st.refine(tgt, source, np.eye(4), sp, CTX, mesh)
    assert res.metrics["icp_accepted"] == 1.0 and transform_errors(res.T_target_source, T0)[0] < 0.5
    acc_d = st.accept_distance(st.p.max_correspondence_distance * sp, sp)
    search = ClosestPoints(tgt) if variant == "open3d" else st.closest(tgt, mesh)
    moving = source.points if variant == "open3d" else source.points[morton_order(source.points)]
    with blas_single_thread():
        fresh = st.final_metrics(search(apply_T(res.T_target_source, moving), acc_d)[1], acc_d)
    assert res.metrics["icp_accept_end_fitness"] == fresh["icp_fitness"] > 0.99
    assert res.metrics["icp_accept_end_rms"] == fresh["icp_inlier_rms"]
