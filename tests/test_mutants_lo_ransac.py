"""Known answers that kill the mutants of coarse=lo_ransac's stage logic (./run mutants, issue #38): the counts it
needs at their exact boundaries (3 keypoints each side, 3 matches, min_inliers inliers), the normals it hands to
RANSAC's final fit, the isolated-point removal's size condition and the voxel it thins with. The keypoint,
descriptor and matcher stages are stand-ins written here, so that every count is known."""

import numpy as np
import pytest

from scanreg.errors import StageError
from scanreg.geometry import Cloud, apply_T, random_pose
from scanreg.stages.coarse.lo_ransac import LoRansac
from scanreg.types import RunContext


class EveryKth:
    """Keypoints: every k-th point, or the first ``n`` when given."""

    name = "stand-in"

    def __init__(self, k=7, n=None):
        self.k, self.n = k, n

    def keypoints(self, cloud, spacing):
        return np.arange(self.n) if self.n is not None else np.arange(0, cloud.n_points, self.k)


class Coordinates:
    """Descriptors: the keypoints' own coordinates in a frame the two clouds share (so that a keypoint matches
    its counterpart when the source is the target moved back)."""

    def __init__(self, T_back=np.eye(4)):
        self.T_back = T_back
        self.calls = 0

    def compute(self, cloud, keypoints, spacing):
        self.calls += 1
        pts = cloud.points[keypoints]
        return pts if self.calls % 2 == 1 else apply_T(self.T_back, pts)


class Pairs:
    """Matches: (i, i) for the first ``n`` keypoints (all of them when None)."""

    def __init__(self, n=None):
        self.n = n

    def match(self, dt, ds):
        m = min(len(dt), len(ds)) if self.n is None else self.n
        return np.c_[np.arange(m), np.arange(m)]


def surface(n, seed, outliers=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 10, (n, 2))
    pts = np.c_[xy, np.sin(xy[:, 0]) * np.cos(0.7 * xy[:, 1])]
    nrm = np.c_[-np.cos(xy[:, 0]) * np.cos(0.7 * xy[:, 1]), 0.7 * np.sin(xy[:, 0]) * np.sin(0.7 * xy[:, 1]),
                np.ones(n)]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    if outliers:
        pts = np.vstack([pts, rng.uniform([0, 0, 5], [10, 10, 15], (outliers, 3))])
        nrm = np.vstack([nrm, np.tile([0, 0, 1.0], (outliers, 1))])
    return pts, nrm


def stage(salience, descriptor, matcher, **kw):
    p = LoRansac.Params(**{"distances": "absolute", "distance_threshold": 0.05, "voxel": None,
                           "fallback_voxel": None, **kw})
    return LoRansac(p, salience, descriptor, matcher)


def moved_pair(n=400, seed=0):
    pts, nrm = surface(n, seed)
    T = random_pose(np.random.default_rng(seed + 1), 180, 3.0)
    T_back = np.linalg.inv(T)
    return Cloud(pts, nrm), Cloud(apply_T(T_back, pts), nrm @ T_back[:3, :3].T), T


def aligned_or_refused(st, tgt, src, T, ok: bool, message: str):
    """The stage's result when ``ok`` (its pose T to 1e-8), else None after checking it refuses with ``message``."""
    if not ok:
        with pytest.raises(StageError, match=message):
            st.align(tgt, src, 1.0, RunContext(seed=0))
        return None
    res = st.align(tgt, src, 1.0, RunContext(seed=0))
    assert np.allclose(res.T_target_source, T, atol=1e-8)
    return res


@pytest.mark.parametrize("n_target, n_source, ok", [(3, 3, True), (2, 3, False), (3, 2, False), (2, 2, False)])
def test_three_keypoints_on_each_side_are_enough(n_target, n_source, ok):
    tgt, src, T = moved_pair()

    class Sides(EveryKth):
        calls = 0

        def keypoints(self, cloud, spacing):
            Sides.calls += 1
            return np.arange(n_target if Sides.calls == 1 else n_source)

    res = aligned_or_refused(stage(Sides(), Coordinates(np.linalg.inv(T)), Pairs(), min_inliers=3), tgt, src, T, ok,
                             "too few keypoints")
    assert res is None or res.metrics["coarse_inliers"] == 3


@pytest.mark.parametrize("n_pairs, ok", [(3, True), (2, False)])
def test_three_matches_are_enough(n_pairs, ok):
    tgt, src, T = moved_pair()
    res = aligned_or_refused(stage(EveryKth(), Coordinates(np.linalg.inv(T)), Pairs(n_pairs), min_inliers=3), tgt,
                             src, T, ok, "only 2 descriptor matches")
    assert res is None or (res.metrics["coarse_correspondences"] == 3 and res.metrics["coarse_inlier_ratio"] == 1.0)


@pytest.mark.parametrize("min_inliers, ok", [(58, True), (59, False)])
def test_min_inliers_is_the_fewest_accepted(min_inliers, ok):
    """58 right matches (every 7th of 400 points) and 12 wrong ones (a shifted pairing of other keypoints)."""
    tgt, src, T = moved_pair()

    class Mixed(Pairs):
        def match(self, dt, ds):
            right = np.c_[np.arange(58), np.arange(58)]
            wrong = np.c_[np.arange(12) + 40, (np.arange(12) * 5 + 3) % 57]
            return np.vstack([right, wrong[wrong[:, 0] != wrong[:, 1]]])

    st = stage(EveryKth(), Coordinates(np.linalg.inv(T)), Mixed(), min_inliers=min_inliers)
    if ok:
        res = st.align(tgt, src, 1.0, RunContext(seed=0))
        assert res.metrics["coarse_inliers"] == 58 and res.metrics["coarse_keypoints_target"] == 58
    else:
        with pytest.raises(StageError, match="best model has 58 inliers"):
            st.align(tgt, src, 1.0, RunContext(seed=0))


def test_the_keypoints_normals_reach_the_final_fit():
    """Noisy keypoints with normals a few degrees off: the stage's pose is the points-and-normals least squares
    over RANSAC's inliers (SVD here), each match's target normal with its target point and source normal with
    its source point (the source's points in another order, so that a match pairs keypoints of different
    indices); without normals (clouds that have none) the points-only fit."""
    n, k, s = 406, 7, 5  # 58 keypoints; source keypoint (i + 5) mod 58 is target keypoint i's counterpart
    pts, nrm = surface(n, 3)
    rng = np.random.default_rng(4)
    T = random_pose(rng, 180, 3.0)
    T_back = np.linalg.inv(T)
    src_pts = apply_T(T_back, pts) + rng.normal(scale=0.01, size=pts.shape)
    src_nrm = nrm @ T_back[:3, :3].T + rng.normal(scale=0.05, size=pts.shape)
    src_nrm /= np.linalg.norm(src_nrm, axis=1, keepdims=True)
    src_pts, src_nrm = np.roll(src_pts, k * s, axis=0), np.roll(src_nrm, k * s, axis=0)

    class Shifted(Pairs):
        def match(self, dt, ds):
            i = np.arange(len(dt))
            return np.c_[i, (i + s) % len(ds)]

    thr, w = 0.05, 100.0
    kt = np.arange(0, n, k)
    ks = kt[(np.arange(len(kt)) + s) % len(kt)]
    for normals in (True, False):
        tgt = Cloud(pts, nrm if normals else None)
        src = Cloud(src_pts, src_nrm if normals else None)
        st = stage(EveryKth(k), Coordinates(), Shifted(), normal_weight=w, distance_threshold=thr, min_inliers=3)
        res = st.align(tgt, src, 1.0, RunContext(seed=0))
        inl = res.trace.ransac_inliers
        assert inl.sum() > 40
        P0, P1 = pts[kt][inl], src_pts[ks][inl]
        m1, m0 = P1.mean(axis=0), P0.mean(axis=0)
        H = (P1 - m1).T @ (P0 - m0)
        if normals:
            H = H + w * thr * thr * src_nrm[ks][inl].T @ nrm[kt][inl]
        U, _, Vt = np.linalg.svd(H)
        R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        assert np.allclose(res.T_target_source[:3, :3], R, atol=1e-9), normals
        assert np.allclose(res.T_target_source[:3, 3], m0 - R @ m1, atol=1e-9), normals


def occupied_voxels(points, voxel):
    """Cells of a grid of edge ``voxel`` anchored at the points' minimum corner that hold a point."""
    return len(np.unique(np.floor((points - points.min(axis=0)) / voxel).astype(np.int64), axis=0))


def test_isolated_points_are_looked_for_only_in_clouds_larger_than_min_points():
    """3000 surface points and 60 scattered above: with min_points below the clouds' size the 60 are found and
    dropped; with min_points equal to it (not larger) the clouds are left as they are."""
    pts, nrm = surface(3000, 5, outliers=60)
    cloud = Cloud(pts, nrm)
    for min_points, dropped in ((3059, True), (3060, False)):
        st = stage(EveryKth(), Coordinates(), Pairs(), voxel=4.0, isolated_ratio=0.25, min_points=min_points,
                   max_points=None, min_inliers=3, distance_threshold=0.05)
        m = st.align(cloud, cloud, 0.2, RunContext(seed=0)).metrics
        if dropped:
            assert m["coarse_isolated_target"] >= 55 and m["coarse_isolated_source"] >= 55
        else:
            assert m["coarse_isolated_target"] == 0 and m["coarse_isolated_source"] == 0
            assert m["coarse_points_target"] == 3060  # fewer than min_points: not thinned either


def test_without_isolated_point_removal_the_clouds_are_thinned_on_the_voxel_in_spacings():
    pts, nrm = surface(3000, 6)
    cloud = Cloud(pts, nrm)
    spacing = 0.2
    st = stage(EveryKth(), Coordinates(), Pairs(), voxel=4.0, isolated_ratio=None, min_points=None, max_points=None,
               min_inliers=3, distance_threshold=0.05)
    m = st.align(cloud, cloud, spacing, RunContext(seed=0)).metrics
    assert m["coarse_isolated_target"] == 0 and m["coarse_isolated_source"] == 0
    assert m["coarse_points_target"] == m["coarse_points_source"] == occupied_voxels(pts, 4.0 * spacing)
    assert m["coarse_points_target"] < 1000
