"""Known answers that kill the mutants of the descriptors (./run mutants, issue #38): local reference frames
against their definition written out here (SHOT weights, the 128-neighbour cap, the sign rules), on
millimetre-scale data, with and without normals, and the reuse of a neighbour search only when it covers the
frame's neighbourhood."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from scanreg.geometry import Cloud
from scanreg.stages.descriptor import Histogram3P, local_frames


def brute_frames(points, normals, keypoints, radius, cap=128):
    """The frames by their definition: for each keypoint, its ``cap`` nearest points (itself included) closer than
    ``radius``, weights radius - d, C = sum w X X^T / sum w with X the offsets from the keypoint; x the
    eigenvector of the largest eigenvalue, z of the smallest; x turned towards the weighted mean offset, z
    towards the keypoint's normal (without normals: the weighted mean offset); y = z x x."""
    out = []
    for i in keypoints:
        d = np.linalg.norm(points - points[i], axis=1)
        nb = np.argsort(d)[:cap]
        nb = nb[d[nb] < radius]
        w = radius - d[nb]
        X = points[nb] - points[i]
        _, vec = np.linalg.eigh((X * w[:, None]).T @ X / w.sum())
        x, z = vec[:, 2], vec[:, 0]
        x = x if w @ (X @ x) >= 0 else -x
        ref = normals[i] @ z if normals is not None else w @ (X @ z)
        z = z if ref >= 0 else -z
        out.append([x, np.cross(z, x), z])
    return np.array(out)


def strip(n, seed):
    """A curved strip in millimetres (3 x 0.3 x ~0.02; weighted sums far below 1), longer than wide so that
    every neighbourhood has a clear long axis, its normals, and point 0 far off: a padding column of a
    neighbour search points at index 0, and no keypoint is there."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (n, 2)) * [3.0, 0.3]
    z = 0.02 * np.sin(2 * xy[:, 0]) + 0.01 * xy[:, 1] ** 2
    pts = np.c_[xy, z]
    nrm = np.c_[-0.04 * np.cos(2 * xy[:, 0]), -0.02 * xy[:, 1], np.ones(n)]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pts[0], nrm[0] = [50.0, 50.0, 50.0], [1.0, 0.0, 0.0]
    return pts, nrm


@pytest.mark.parametrize("with_normals", [True, False])
@pytest.mark.parametrize("radius, n", [(0.25, 600), (0.25, 3000)])  # ~40 and ~200 neighbours: padded, capped
def test_local_frames_by_their_definition(radius, n, with_normals):
    pts, nrm = strip(n, 1)
    normals = nrm if with_normals else None
    kp = np.arange(5, n, n // 40)
    counts = (np.linalg.norm(pts[kp, None] - pts[None], axis=2) < radius).sum(axis=1)
    assert (counts.max() < 128) if n == 600 else (counts.min() > 128)
    got = local_frames(pts, normals, kp, radius)
    assert np.allclose(got, brute_frames(pts, normals, kp, radius), atol=1e-9)


def test_local_frames_reuse_a_search_only_when_it_covers_the_cap():
    """A search with at least 128 columns (nearest first, radius at least the frame's) gives the frames of a fresh
    search; one with fewer columns is not used (it would miss neighbours). More keypoints (150) than the cap, so
    that the rows are not mistaken for the columns."""
    pts, nrm = strip(3000, 2)
    kp = np.arange(5, 3000, 20)
    want = local_frames(pts, nrm, kp, 0.25)
    tree = cKDTree(pts)
    for k in (256, 10):
        d, j = tree.query(pts[kp], k=k, distance_upper_bound=0.4)
        valid = j < len(pts)
        nb = (np.where(valid, j, 0), np.where(valid, d, np.inf), valid)
        assert np.allclose(local_frames(pts, nrm, kp, 0.25, neighbours=nb), want, atol=1e-12), k


def test_histogram3p_with_a_frame_radius_beyond_the_support_radius():
    """frame_radius (20 spacings) > radius (15): the frames come from a search of their own, not from the support
    radius's neighbours; and a density radius (8 spacings) whose points exceed the cap of 64. The descriptor
    equals the straightforward implementation kept in test_fast_paths."""
    from test_fast_paths import reference_histogram3p

    pts, nrm = strip(3000, 3)
    cloud = Cloud(pts, nrm)
    p = Histogram3P.Params(radius=15.0, frame_radius=20.0, density_radius=8.0)
    spacing = 0.0125
    kp = np.arange(5, 3000, 61)
    assert np.median(cKDTree(pts).query_ball_point(pts[kp], 8.0 * spacing, return_length=True)) > 64
    got = Histogram3P(p).compute(cloud, kp, spacing)
    assert np.allclose(got, reference_histogram3p(p, cloud, kp, spacing), atol=1e-12)


def test_fpfh_does_not_depend_on_the_input_units():
    """FPFH in spacings on the same bunny sampling in two units, 0.1 and 100 times the mesh's: the support voxel
    (3 spacings) is below 1 in one and above it in the other, and both are thinned alike. Open3D's search and
    voxel grid round differently at the two scales: the histograms (entries up to ~170) measured 2.4 apart at
    most; without the support voxel they are 68 apart."""
    from scanreg.geometry import barycentric_sample, estimate_spacing
    from scanreg.io import read_mesh
    from scanreg.stages.descriptor import FPFH

    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    p, n, _ = barycentric_sample(m, 4000, np.random.default_rng(5))
    sp = estimate_spacing(p, np.random.default_rng(0))
    kp = np.arange(0, 4000, 50)
    small, large = (FPFH(FPFH.Params()).compute(Cloud(p * s, n), kp, sp * s) for s in (0.1, 100.0))
    assert 3 * sp * 0.1 < 1 < 3 * sp * 100
    assert np.abs(small - large).max() < 7.0
    unthinned = FPFH(FPFH.Params(support_voxel=0.0)).compute(Cloud(p * 0.1, n), kp, sp * 0.1)
    assert np.abs(unthinned - large).max() > 30.0


def test_histogram3p_frames_see_the_frame_radius_in_a_sparse_cloud():
    """A sparse strip (400 points): about 50 points within the support radius (15 spacings) and 90 within the
    frame radius (20), both under the 128-neighbour cap, so the frames need their own, wider search. The
    descriptor equals the straightforward implementation kept in test_fast_paths."""
    from test_fast_paths import reference_histogram3p

    pts, nrm = strip(400, 4)
    spacing = 0.0125
    kp = np.arange(5, 400, 13)
    counts = cKDTree(pts).query_ball_point(pts[kp], 20.0 * spacing, return_length=True)
    assert np.median(counts) < 128 and np.median(counts) > 1.3 * np.median(
        cKDTree(pts).query_ball_point(pts[kp], 15.0 * spacing, return_length=True))
    p = Histogram3P.Params(radius=15.0, frame_radius=20.0)
    cloud = Cloud(pts, nrm)
    assert np.allclose(Histogram3P(p).compute(cloud, kp, spacing), reference_histogram3p(p, cloud, kp, spacing),
                       atol=1e-12)
