"""The field's registration metrics (README "Metrics") against hand computations on small cases, the PLY line
sets they are shown with, and a run with ground truth that logs them all."""

import json
from dataclasses import replace

import numpy as np
import pytest

from conftest import shared
from scanreg.geometry import Cloud
from scanreg.io import write_ply
from scanreg.types import CoarseTrace
from scanreg.eval.metrics import (EvalParams, feature_match_recall, field_metrics, gt_metrics, gt_rmse, inlier_ratio,
                             keypoint_repeatability, match_inliers, overlap_mask, registration_recall)


def shift(x=0.0, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def rot_z(deg):
    T = np.eye(4)
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T[:2, :2] = [[c, -s], [s, c]]
    return T


# Target keypoints on the x axis; T_gt moves the source by +10 in x. Source keypoints, once moved:
#   (0, 0.05, 0)   -> 0.05 from target (0,0,0): repeatable at eps 0.1
#   (1, 0.5, 0)    -> 0.5 from target (1,0,0): in the overlap (radius 1), not repeatable
#   (2, 0, 0.09)   -> 0.09 from target (2,0,0): repeatable
#   (50, 0, 0)     -> 47 from the nearest target point: outside the overlap
KT = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
KS = np.array([[-10.0, 0.05, 0], [-9, 0.5, 0], [-8, 0, 0.09], [40, 0, 0]])
T_GT = shift(10.0)


def test_keypoint_repeatability_by_hand():
    r = keypoint_repeatability(KT, KS, T_GT, eps=0.1, overlap_radius=1.0)
    assert r.source_in_overlap.tolist() == [True, True, True, False]
    assert r.source_repeatable.tolist() == [True, False, True, False]
    assert r.repeatability == pytest.approx(2 / 3)
    assert r.target_repeatable.tolist() == [True, False, True, False]
    assert r.metrics() == {"keypoint_repeatability": pytest.approx(2 / 3), "n_keypoints_overlap": 3,
                           "n_keypoints_repeatable": 2}
    # a larger epsilon takes in the keypoint 0.5 away; the overlap is measured against the dense target cloud
    assert keypoint_repeatability(KT, KS, T_GT, eps=0.6, overlap_radius=1.0).repeatability == pytest.approx(1.0)
    dense = np.array([[x, 0, 0] for x in np.arange(0, 51.0)])
    r = keypoint_repeatability(KT, KS, T_GT, eps=0.1, overlap_radius=1.0, target_points=dense)
    assert r.source_in_overlap.all() and r.repeatability == pytest.approx(2 / 4)
    # nothing in the overlap: undefined, not zero
    assert np.isnan(keypoint_repeatability(KT, KS, shift(1000.0), 0.1, 1.0).repeatability)


def test_overlap_mask_by_hand():
    pts = np.array([[0.0, 0, 0], [0, 0, 2.0], [0, 0, 3.5]])
    assert overlap_mask(pts, np.zeros((1, 3)), shift(z=-1.0), 1.0).tolist() == [True, True, False]


def test_inlier_ratio_and_feature_match_recall_by_hand():
    # 5 matches; under T_gt (rotation by 90 deg about z) the source point (1,0,0) goes to (0,1,0)
    P_src = np.array([[1.0, 0, 0], [2, 0, 0], [0, 1, 0], [1, 0, 0], [3, 0, 0]])
    P_tgt = np.array([[0.0, 1, 0], [0, 2.05, 0], [-1, 0, 0], [5, 5, 5], [0, 3.2, 0]])
    T = rot_z(90)
    assert match_inliers(P_tgt, P_src, T, 0.1).tolist() == [True, True, True, False, False]
    assert inlier_ratio(P_tgt, P_src, T, 0.1) == pytest.approx(3 / 5)
    assert inlier_ratio(P_tgt, P_src, T, 0.25) == pytest.approx(4 / 5)
    assert np.isnan(inlier_ratio(np.zeros((0, 3)), np.zeros((0, 3)), T, 0.1))
    assert feature_match_recall(0.06) == 1.0 and feature_match_recall(0.05) == 0.0
    assert feature_match_recall(0.3, tau2=0.5) == 0.0 and np.isnan(feature_match_recall(float("nan")))


def test_registration_recall_thresholds():
    p = EvalParams()  # RRE < 15 deg, RTE < 7 % of the diagonal
    assert registration_recall(14.9, 0.69, 10.0, p) == 1.0
    assert registration_recall(15.1, 0.1, 10.0, p) == 0.0
    assert registration_recall(1.0, 0.71, 10.0, p) == 0.0
    metric = EvalParams(recall_translation_abs=0.3)  # 3DMatch's 30 cm for data in metres, whatever the diagonal
    assert registration_recall(1.0, 0.29, 100.0, metric) == 1.0 and registration_recall(1.0, 0.31, 100.0, metric) == 0.0
    # beside the stricter success: 5 deg off is recalled but not a success
    m = gt_metrics(rot_z(5.0), np.eye(4), 10.0, p)
    assert m["registration_recall"] == 1.0 and m["success"] == 0.0 and m["rotation_error_deg"] == pytest.approx(5.0)
    assert gt_metrics(rot_z(20.0), np.eye(4), 10.0, p, prefix="coarse_")["coarse_registration_recall"] == 0.0
    with pytest.raises(ValueError, match="match_recall_ratio"):
        EvalParams(match_recall_ratio=1.5).check()


def test_gt_rmse_by_hand():
    pts = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 0]])
    # a pure translation error of 0.3: every point off by 0.3
    assert gt_rmse(shift(0.3), np.eye(4), pts) == pytest.approx(0.3)
    # a rotation by 90 deg about z: (1,0,0) off by sqrt 2, (0,1,0) by sqrt 2, the origin by 0 -> RMSE sqrt(4/3)
    assert gt_rmse(rot_z(90), np.eye(4), pts) == pytest.approx(np.sqrt(4 / 3))
    assert gt_rmse(rot_z(90), np.eye(4), pts, np.array([False, False, True])) == 0.0
    assert np.isnan(gt_rmse(rot_z(90), np.eye(4), pts, np.zeros(3, bool)))


def test_field_metrics_from_a_trace():
    p = EvalParams(repeatability_distance=0.1, overlap_distance=1.0, match_inlier_distance=0.1)
    trace = CoarseTrace(keypoints_target=KT, keypoints_source=KS,
                        matches_target=KT[:3], matches_source=KS[[0, 2, 1]],  # 1st right, 2nd and 3rd swapped: wrong
                        ransac_inliers=np.array([True, True, False]))
    dense = np.array([[x, 0, 0] for x in np.arange(0, 4.0)])
    m, masks = field_metrics(trace, shift(10.2), shift(10.0), T_GT, KS, dense, p, spacing=1.0)
    assert m["n_keypoints_target"] == 4 and m["n_keypoints_source"] == 4
    assert m["keypoint_repeatability"] == pytest.approx(2 / 3)
    assert m["inlier_ratio"] == pytest.approx(1 / 3) and m["feature_match_recall"] == 1.0
    assert m["ransac_inlier_precision"] == pytest.approx(1 / 2)  # of the 2 accepted matches, 1 is right
    assert m["gt_rmse"] == 0.0 and m["coarse_gt_rmse"] == pytest.approx(0.2)
    assert masks["match_inliers"].tolist() == [True, False, False]
    # a coarse stage that exposes only keypoints: the matching metrics are absent, not zero
    m, _ = field_metrics(CoarseTrace(keypoints_target=KT, keypoints_source=KS), np.eye(4), T_GT, T_GT, KS, dense, p, 1.0)
    assert "keypoint_repeatability" in m and "inlier_ratio" not in m and "feature_match_recall" not in m
    # spacings: tolerances scale with the spacing (eps 0.1 spacings of 6 = 0.6: the 0.5-away keypoint counts)
    m, _ = field_metrics(trace, T_GT, T_GT, T_GT, KS, dense, p, spacing=6.0)
    assert m["keypoint_repeatability"] == pytest.approx(1.0)
    # eps counts the spacing the detector ran on (the coarse stage's thinned clouds) when the trace names it
    m, _ = field_metrics(replace(trace, spacing=6.0), T_GT, T_GT, T_GT, KS, dense, p, spacing=1.0)
    assert m["keypoint_repeatability"] == pytest.approx(1.0)


def test_write_ply_edges_read_back_as_a_line_set(tmp_path):
    o3d = pytest.importorskip("open3d")
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    cols = np.array([[0, 170, 0], [220, 0, 0]], np.uint8)
    write_ply(tmp_path / "l.ply", Cloud(pts, None, "l"), colors=np.repeat(cols, 2, axis=0),
              scalars={"ransac_inlier": np.array([1, 1, 0, 0], np.float32)}, edges=[[0, 1], [2, 3]], edge_colors=cols)
    ls = o3d.io.read_line_set(str(tmp_path / "l.ply"))
    assert np.asarray(ls.lines).tolist() == [[0, 1], [2, 3]]
    assert np.allclose(np.asarray(ls.points), pts)
    assert np.allclose(np.asarray(ls.colors) * 255, cols, atol=0.5)
    from scanreg.io import read_geometry

    back = read_geometry(tmp_path / "l.ply", "l")  # the project's reader takes the vertices, skips the edges
    assert np.allclose(back.points, pts)
    with pytest.raises(ValueError, match="edge vertex indices"):
        write_ply(tmp_path / "bad.ply", Cloud(pts, None, "l"), edges=[[0, 4]])


STANFORD = ["data=stanford", "repair=none", "tracking=none", "evaluate.view_html=false",
            "evaluate.pose_uncertainty=false"]


@pytest.fixture(scope="module")
def stanford_run(tmp_path_factory):
    """One run with ground truth (two Stanford scans, random pose): its result, result.json and folder."""
    shared("stanford_bunny/bun.conf")
    from scanreg.app.config import compose
    from scanreg.runner import run_pipeline

    run_dir = tmp_path_factory.mktemp("stanford")
    res = run_pipeline(compose(STANFORD), run_dir)
    return res, json.loads((run_dir / "result.json").read_text()), run_dir


def test_stanford_run_logs_the_field_metrics_and_writes_coloured_plys(stanford_run):
    res, r, tmp_path = stanford_run
    for k in ("keypoint_repeatability", "inlier_ratio", "feature_match_recall", "registration_recall",
              "coarse_registration_recall", "gt_rmse", "n_keypoints_source", "n_keypoints_target"):
        assert k in r and r[k] == res.metrics[k], k
    assert 0 < r["keypoint_repeatability"] <= 1 and 0 < r["inlier_ratio"] <= 1
    assert r["registration_recall"] == 1.0 and r["gt_rmse"] < 0.01 * r["diagonal"]  # the default pair registers
    names = {p.name for p in res.artifacts}
    assert {"keypoints_target.ply", "keypoints_source.ply", "matches.ply"} <= names
    import open3d as o3d

    ls = o3d.io.read_line_set(str(tmp_path / "matches.ply"))
    assert len(ls.lines) == r["n_matches"]
    green = np.isclose(np.asarray(ls.colors)[:, 1], 170 / 255)
    assert green.sum() == round(r["inlier_ratio"] * r["n_matches"])
    kp = o3d.io.read_point_cloud(str(tmp_path / "keypoints_source.ply"))
    assert np.isclose(np.asarray(kp.colors)[:, 1], 170 / 255).sum() == r["n_keypoints_repeatable"]


def test_repeatability_recomputed_from_the_keypoint_plys(stanford_run):
    """The run's keypoint repeatability recomputed from what it wrote, by brute force over all distances: the
    keypoint PLYs (the source keypoints already moved by the true transform), the run's spacings from
    result.json, and the target cloud the run sampled (made again with the run's stages and seed, its count
    checked against result.json). A source keypoint is in the overlap when a target sample lies within
    ``overlap_distance`` (3) run spacings, repeatable when in it and a target keypoint lies within
    ``repeatability_distance`` (2) spacings of the coarse stage's thinned clouds, where the detector ran
    (README "Metrics"; Tombari et al. 2013). The PLY colours must say the same keypoint by keypoint."""
    import open3d as o3d
    from scipy.spatial.distance import cdist

    from scanreg.app.config import compose
    from scanreg.runner.build import build_stages
    from scanreg.runner.steps import prepare_scan
    from scanreg.types import RunContext

    _, r, run_dir = stanford_run
    cfg = compose(STANFORD)
    stages = build_stages(cfg)
    ctx = RunContext(seed=int(cfg.seed))
    target = prepare_scan(stages.data.load(ctx).target, stages, ctx, "target", 1).cloud.points
    assert len(target) == r["n_target_points"]
    ev = EvalParams()
    overlap, eps = ev.overlap_distance * r["spacing"], ev.repeatability_distance * r["coarse_spacing"]

    ply_s = o3d.io.read_point_cloud(str(run_dir / "keypoints_source.ply"))
    ply_t = o3d.io.read_point_cloud(str(run_dir / "keypoints_target.ply"))
    ks, kt = np.asarray(ply_s.points), np.asarray(ply_t.points)
    assert (len(ks), len(kt)) == (r["n_keypoints_source"], r["n_keypoints_target"])
    inside = cdist(ks, target).min(axis=1) <= overlap
    d_kk = cdist(ks, kt)
    repeatable = inside & (d_kk.min(axis=1) <= eps)
    target_repeatable = (d_kk[inside] <= eps).any(axis=0)
    assert 50 < inside.sum() < len(ks) and 0 < repeatable.sum() < inside.sum()  # a case with every kind
    assert r["n_keypoints_overlap"] == inside.sum() and r["n_keypoints_repeatable"] == repeatable.sum()
    assert r["keypoint_repeatability"] == pytest.approx(repeatable.sum() / inside.sum(), rel=1e-12)

    # colours: green repeatable, red in the overlap but not repeatable, grey outside (source); green when a
    # repeatable source keypoint of the overlap lies within eps, else grey (target)
    green, red, grey = (np.array(c) / 255 for c in ((0, 170, 0), (220, 0, 0), (150, 150, 150)))
    want_s = np.where(repeatable[:, None], green, np.where(inside[:, None], red, grey))
    want_t = np.where(target_repeatable[:, None], green, grey)
    assert np.allclose(np.asarray(ply_s.colors), want_s, atol=1e-6)
    assert np.allclose(np.asarray(ply_t.colors), want_t, atol=1e-6)

