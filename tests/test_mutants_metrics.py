"""Known answers that kill the mutants of the evaluation metrics (./run mutants, issue #38): each distance threshold
at its exact boundary (every "within" is inclusive), the fit metrics, the success rule's translation half, the
unsigned and the empty cases of the surface deviation, and the metrics a partial trace leaves out. Distances are
chosen exactly representable, so that "exactly at the threshold" is exact."""

import numpy as np
import pytest

from scanreg.eval.metrics import (EvalParams, alignment_metrics, field_metrics, gt_metrics, keypoint_repeatability,
                                  match_inliers, overlap_mask, registration_recall, surface_deviation)
from scanreg.types import CoarseTrace, Distances


def shift(x=0.0, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def test_alignment_metrics_count_a_distance_equal_to_the_threshold_as_inlier():
    d = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    m = alignment_metrics(d, EvalParams(inlier_distance=1.5), spacing=2.0)  # 1.5 spacings of 2: 3, inclusive
    assert m == {"rms": pytest.approx(np.sqrt(14 / 4)), "fitness": 0.8, "mean_distance": 2.0}
    m = alignment_metrics(d, EvalParams(inlier_distance=0.5, distances=Distances.absolute), spacing=2.0)
    assert m["fitness"] == 0.2 and m["rms"] == 0.0
    far = alignment_metrics(d + 10, EvalParams(inlier_distance=1.0), spacing=1.0)
    assert np.isnan(far["rms"]) and far["fitness"] == 0.0 and far["mean_distance"] == 12.0


def test_overlap_and_repeatability_are_inclusive_at_their_radii():
    # the source keypoints moved by +1 in x: (1, 0, 0) exactly 1 from the target point (0, 0, 0) (the overlap
    # radius) and exactly 0.5 from the target keypoint (0.5, 0, 0) (epsilon); (-0.25, 0, 0) in the overlap,
    # 0.75 from the keypoint; (2.5, 0, 0) outside
    kt = np.array([[0.5, 0, 0]])
    ks = np.array([[0.0, 0, 0], [-1.25, 0, 0], [1.5, 0, 0]])
    target = np.array([[0.0, 0, 0]])
    assert overlap_mask(ks, target, shift(1.0), 1.0).tolist() == [True, True, False]
    r = keypoint_repeatability(kt, ks, shift(1.0), eps=0.5, overlap_radius=1.0, target_points=target)
    assert r.source_in_overlap.tolist() == [True, True, False]
    assert r.source_repeatable.tolist() == [True, False, False]
    assert r.target_repeatable.tolist() == [True]
    assert r.repeatability == 0.5
    # without target keypoints nothing is repeatable (0 of the overlap), and empty inputs give empty masks
    r = keypoint_repeatability(np.zeros((0, 3)), ks, shift(1.0), 0.5, 1.0, target)
    assert r.repeatability == 0.0 and not r.source_repeatable.any() and len(r.target_repeatable) == 0
    assert overlap_mask(np.zeros((0, 3)), target, np.eye(4), 1.0).shape == (0,)
    assert overlap_mask(ks, np.zeros((0, 3)), np.eye(4), 1.0).tolist() == [False, False, False]


def test_repeatability_metrics_with_a_prefix():
    r = keypoint_repeatability(np.zeros((1, 3)), np.zeros((2, 3)), np.eye(4), 0.1, 1.0)
    assert r.metrics("coarse_") == {"coarse_keypoint_repeatability": 1.0, "coarse_n_keypoints_overlap": 2,
                                    "coarse_n_keypoints_repeatable": 2}


def test_match_inliers_inclusive_at_tau1():
    P_src = np.array([[0.0, 0, 0], [0.0, 0, 0], [0.0, 0, 0]])
    P_tgt = np.array([[0.25, 0, 0], [0.0, 0.5, 0], [0.0, 0, 0.75]])
    assert match_inliers(P_tgt, P_src, np.eye(4), 0.5).tolist() == [True, True, False]


def test_success_needs_the_translation_under_its_share_of_the_diagonal():
    p = EvalParams()  # success: rotation < 2 deg and translation < 1 % of the diagonal
    ok = gt_metrics(shift(0.06, 0.08), np.eye(4), 20.0, p)  # 0.1 off, 0.2 allowed
    assert ok["success"] == 1.0 and ok["translation_error"] == pytest.approx(0.1)
    assert ok["translation_error_rel"] == pytest.approx(0.1 / 20.0) and ok["rotation_error_deg"] == 0.0
    bad = gt_metrics(shift(0.3), np.eye(4), 20.0, p)  # 0.3 off
    assert bad["success"] == 0.0 and bad["registration_recall"] == 1.0
    assert "success" not in gt_metrics(shift(0.3), np.eye(4), 20.0, p, prefix="coarse_")
    # both halves strict: exactly 1 % of a diagonal of 50 (0.5) is not a success, nor is a rotation error equal
    # to the limit
    assert gt_metrics(shift(0.5), np.eye(4), 50.0, p)["success"] == 0.0
    assert gt_metrics(shift(0.25), np.eye(4), 50.0, p)["success"] == 1.0
    turned = np.eye(4)
    turned[:2, :2] = [[np.cos(0.02), -np.sin(0.02)], [np.sin(0.02), np.cos(0.02)]]
    rot = gt_metrics(turned, np.eye(4), 50.0, p)["rotation_error_deg"]
    assert gt_metrics(turned, np.eye(4), 50.0, EvalParams(success_rotation_deg=rot))["success"] == 0.0
    assert gt_metrics(turned, np.eye(4), 50.0, EvalParams(success_rotation_deg=rot * 1.001))["success"] == 1.0


def test_registration_recall_is_strict_at_both_thresholds():
    p = EvalParams(recall_translation_abs=0.5)  # 15 degrees and 0.5 exactly
    assert registration_recall(15.0, 0.1, 100.0, p) == 0.0 and registration_recall(14.5, 0.1, 100.0, p) == 1.0
    assert registration_recall(1.0, 0.5, 100.0, p) == 0.0 and registration_recall(1.0, 0.25, 100.0, p) == 1.0


def test_surface_deviation_unsigned_at_the_boundary_and_empty():
    # closest points on the plane z = 5 (normal +z), the aligned points above or below them
    q = np.array([[1.0, 2.0, 5.0], [3.0, -1.0, 5.0], [0.0, 0.0, 5.0], [-2.0, 4.0, 5.0]])
    aligned = q + [[0.0, 0, 0.5], [0.0, 0, -1.0], [0.0, 0, 2.0], [0.0, 0, 0.25]]
    d = np.array([0.5, 1.0, 2.0, 0.25])
    p = EvalParams(inlier_distance=1.0, distances=Distances.absolute)
    m = surface_deviation(aligned, (q, d, None), p, spacing=7.0)  # no normals: unsigned; 1.0 is an inlier
    a = np.array([0.5, 1.0, 0.25])
    assert m == pytest.approx({"p2s_mean": a.mean(), "p2s_median": 0.5, "p2s_rms": np.sqrt(np.mean(a ** 2)),
                               "p2s_p95_abs": np.quantile(a, 0.95), "p2s_max_abs": 1.0, "p2s_signed": 0.0})
    n = np.tile([0.0, 0.0, 1.0], (4, 1))  # signed: below the plane negative
    m = surface_deviation(aligned, (q, d, n), p, spacing=7.0)
    s = np.array([0.5, -1.0, 0.25])
    assert m["p2s_signed"] == 1.0 and m["p2s_mean"] == pytest.approx(s.mean()) and m["p2s_max_abs"] == 1.0
    assert m["p2s_median"] == pytest.approx(0.25)
    assert surface_deviation(aligned, (q, d + 5, n), p, spacing=7.0) == {"p2s_signed": 1.0}


def test_field_metrics_leave_out_what_the_trace_does_not_give():
    p = EvalParams(repeatability_distance=0.1, overlap_distance=1.0, match_inlier_distance=0.1)
    k = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    base = dict(keypoints_target=k, keypoints_source=k, matches_target=k, matches_source=k)
    # RANSAC's mask of another length, or accepting nothing: no precision (not 0, not a crash)
    for acc in (np.array([True, True]), np.zeros(3, bool)):
        m, _ = field_metrics(CoarseTrace(**base, ransac_inliers=acc), np.eye(4), np.eye(4), np.eye(4), k, k, p, 1.0)
        assert "ransac_inlier_precision" not in m and m["n_matches"] == 3 and m["inlier_ratio"] == 1.0
    m, _ = field_metrics(CoarseTrace(**base, ransac_inliers=np.array([True, False, False])), np.eye(4), np.eye(4),
                         np.eye(4), k, k, p, 1.0)
    assert m["ransac_inlier_precision"] == 1.0
    # keypoints or matches of one side only: no keypoint or match metrics (not a crash)
    for one in (dict(keypoints_target=k), dict(keypoints_source=k), dict(matches_target=k), dict(matches_source=k)):
        m, masks = field_metrics(CoarseTrace(**one), np.eye(4), np.eye(4), np.eye(4), k, k, p, 1.0)
        assert "n_keypoints_target" not in m and "n_matches" not in m and masks == {}
    # only matches: no keypoint metrics; nothing: only the ground-truth RMSEs and the overlap share
    m, masks = field_metrics(CoarseTrace(matches_target=k, matches_source=k), np.eye(4), np.eye(4), np.eye(4), k, k,
                             p, 1.0)
    assert "keypoint_repeatability" not in m and "n_keypoints_source" not in m and "repeatability" not in masks
    m, masks = field_metrics(None, shift(0.5), np.eye(4), np.eye(4), k, k, p, 1.0)
    assert m == {"gt_rmse": 0.0, "coarse_gt_rmse": 0.5, "overlap_share_gt": 1.0} and masks == {}


def test_field_metrics_of_an_empty_target_cloud():
    """No target points: nothing of the source is in the overlap (and no search is built on no points)."""
    pts = np.random.default_rng(1).normal(size=(20, 3))
    m, _ = field_metrics(None, np.eye(4), np.eye(4), np.eye(4), pts, np.zeros((0, 3)), EvalParams(), 1.0)
    assert m["overlap_share_gt"] == 0.0


def test_repeatability_without_target_points_measures_the_overlap_on_the_target_keypoints():
    """Without target_points the overlap's reference is the target keypoints, even when a search (here on points
    far away) is passed: keypoints 0.1 apart at eps 0.5 and overlap radius 1 are all repeatable."""
    from scanreg.geometry import ClosestPoints, Cloud

    kp = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 2.0, 0]])
    far = ClosestPoints(Cloud(kp + 100.0))
    rep = keypoint_repeatability(kp, kp + [0.1, 0, 0], np.eye(4), 0.5, 1.0, None, far)
    assert rep.repeatability == 1.0 and rep.source_in_overlap.all()
