"""Large clouds (issue #37): the coarse and the fine stage work on at most a bounded number of points of each
cloud, a random subset drawn with the run's seed, at the thinned pair's own spacing. Below the bounds nothing
changes (the reference runs, tests/test_reference_runs.py)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import scanreg
from conftest import stage_ctx
from scanreg.errors import ConfigError
from scanreg.geometry import Cloud, apply_T, barycentric_sample, estimate_spacing, make_T, rotation_angle_deg
from scanreg.io import read_mesh


@pytest.fixture(scope="module")
def bunny_pair():
    """Two independent samplings of pymeshlab's bunny (60,000 points each), the source moved by 3 deg and a bit:
    ``(target points, source points, true T_target_source, spacing)``."""
    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    tgt = barycentric_sample(m, 60000, np.random.default_rng(1))[0]
    src = barycentric_sample(m, 60000, np.random.default_rng(2))[0]
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    T = make_T(Rotation.from_rotvec(np.radians(3.0) * axis).as_matrix(), np.array([0.002, -0.001, 0.001]))
    src = apply_T(np.linalg.inv(T), src)
    spacing = max(estimate_spacing(tgt, np.random.default_rng(0)), estimate_spacing(src, np.random.default_rng(0)))
    return tgt, src, T, spacing


def test_thinned_is_a_seeded_random_subset_in_order():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(10000, 3))
    c = Cloud(pts, pts / np.linalg.norm(pts, axis=1, keepdims=True), "c", {"colors": rng.random((10000, 3))})
    assert c.thinned(10000, np.random.default_rng(1)) is c and c.thinned(0, np.random.default_rng(1)) is c
    t = c.thinned(1000, np.random.default_rng(1))
    idx = np.flatnonzero(np.isin(pts[:, 0], t.points[:, 0]))
    assert t.n_points == 1000 and len(idx) == 1000
    np.testing.assert_array_equal(t.points, pts[idx])  # the cloud's order kept
    np.testing.assert_array_equal(t.normals, c.normals[idx])
    np.testing.assert_array_equal(t.extra["colors"], c.extra["colors"][idx])
    np.testing.assert_array_equal(c.thinned(1000, np.random.default_rng(1)).points, t.points)  # seeded
    assert not np.array_equal(c.thinned(1000, np.random.default_rng(2)).points, t.points)
    # uniform: the subset's mean within 4 standard errors of the whole cloud's
    assert np.all(np.abs(t.points.mean(axis=0) - pts.mean(axis=0)) < 4 * pts.std(axis=0) / np.sqrt(1000))


def test_icp_on_a_thinned_pair_recovers_the_pose(bunny_pair):
    """Point-to-plane ICP bounded to 20,000 of 60,000 points: the pose within 3x of what it reaches (0.0014 deg, 6e-6),
    every thinned source point paired (the pair limit in the thinned pair's spacing), bit for bit the same twice."""
    tgt, src, T, spacing = bunny_pair
    stage = scanreg.build_stage("icp", "point_to_plane", max_points=20000)
    r = stage.refine(Cloud(tgt), Cloud(src), np.eye(4), spacing, stage_ctx())
    E = np.linalg.inv(T) @ r.T_target_source
    assert rotation_angle_deg(E[:3, :3]) < 0.0042 and np.linalg.norm(E[:3, 3]) < 1.8e-5
    assert r.metrics["icp_points_source"] == 20000 and len(r.final_pairs.source) > 0.99 * 20000
    again = stage.refine(Cloud(tgt), Cloud(src), np.eye(4), spacing, stage_ctx())
    np.testing.assert_array_equal(again.T_target_source, r.T_target_source)


def test_icp_pairs_at_the_thinned_spacing(bunny_pair):
    """Thinned 12-fold, the target's points lie about 3.5 times farther apart: pair limits in the full clouds'
    spacing would leave most source points unpaired (2,031 of 5,000 measured), in the thinned pair's keep them."""
    tgt, src, T, spacing = bunny_pair
    r = scanreg.build_stage("icp", "point_to_plane", max_points=5000).refine(Cloud(tgt), Cloud(src), np.eye(4),
                                                                            spacing, stage_ctx())
    assert r.metrics["icp_points_source"] == 5000 and len(r.final_pairs.source) > 0.95 * 5000
    E = np.linalg.inv(T) @ r.T_target_source
    assert rotation_angle_deg(E[:3, :3]) < 0.032


def test_icp_max_points_is_validated():
    with pytest.raises(ConfigError, match="max_points"):
        scanreg.build_stage("icp", "horn", max_points=50)


def test_coarse_stage_thins_large_inputs_first(bunny_pair):
    """The default pipeline with the coarse stage bounded to 20,000 input points: it starts from that many, and
    the pose is recovered from 60 deg as with every point (coarse 1.17 deg off, 0.44 deg with every point)."""
    tgt, src, T, _ = bunny_pair
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    T60 = make_T(Rotation.from_rotvec(np.radians(60.0) * axis).as_matrix(), np.zeros(3))
    src60 = apply_T(np.linalg.inv(T60), apply_T(T, src))  # T_target_source = T60
    res = scanreg.register(src60, tgt, gt=T60, overrides=["coarse.max_input_points=20000", "evaluate.view_html=false"])
    m = res.metrics
    assert m["coarse_input_points_target"] == 20000 and m["coarse_input_points_source"] == 20000
    assert m["success"] == 1 and m["coarse_rotation_error_deg"] < 2.0 and m["rotation_error_deg"] < 0.01


def test_ground_truth_metrics_on_a_sample_agree_with_every_point(bunny_pair):
    """``evaluate.max_points``: the ground-truth metrics over the source's points from 2,000 of its 60,000
    points agree with every point's within the sampling error the parameter states (the overlap share within
    4 standard errors); the registration itself does not change."""
    tgt, src, T, _ = bunny_pair
    over = ["evaluate.view_html=false", "coarse=none"]
    full = scanreg.register(src, tgt, gt=T, overrides=[*over, "evaluate.max_points=0"])
    part = scanreg.register(src, tgt, gt=T, overrides=[*over, "evaluate.max_points=2000"])
    np.testing.assert_array_equal(part.T_target_source, full.T_target_source)
    a, b = part.metrics, full.metrics
    assert a["overlap_share_gt"] != b["overlap_share_gt"]  # measured on the sample
    assert abs(a["overlap_share_gt"] - b["overlap_share_gt"]) < 4 * 0.5 / np.sqrt(2000)
    for k in ("gt_rmse", "coarse_gt_rmse"):
        assert abs(a[k] - b[k]) < 0.04 * b[k], (k, a[k], b[k])  # 1.2 % and 0.5 % measured
