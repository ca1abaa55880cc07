"""The coarse stage's outlier guard before voxel thinning (``coarse.isolated_ratio``), on known answers."""

import numpy as np
import pytest

from conftest import build, build_coarse
from scanreg.geometry import Cloud, bbox_diagonal, sparse_voxel_mask, transform_errors, voxel_occupancy
from scanreg.stages.registry import SALIENCE, load_all
from scanreg.types import RunContext

load_all()


def plane_with_outliers():
    """A 100 x 100 grid of spacing 1 in z = 0 (every 4 x 4 cell of a voxel-4 grid anchored at the origin holds 16
    points) and 5 x 5 x 5 = 125 outliers above it, 8 apart, each alone in its cell."""
    g = np.arange(100.0)
    plane = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), axis=-1).reshape(-1, 3)
    o = np.arange(5) * 8.0 + 2.5
    out = np.stack(np.meshgrid(o, o, o + 10, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.vstack([plane, out]), len(plane)


def test_voxel_occupancy_counts_the_points_of_each_cell():
    pts, n_plane = plane_with_outliers()
    occ = voxel_occupancy(pts, 4.0)
    assert (occ[:n_plane] == 16).all() and (occ[n_plane:] == 1).all()
    assert voxel_occupancy(np.zeros((0, 3)), 1.0).shape == (0,)


def test_sparse_voxel_mask_drops_exactly_the_outliers():
    pts, n_plane = plane_with_outliers()
    keep = sparse_voxel_mask(pts, 4.0, 0.25)  # median cell 16 points: cells of < 4 go
    assert keep[:n_plane].all() and not keep[n_plane:].any()
    # a sparse cloud (one point per cell: median 1) keeps everything, whatever the ratio
    assert sparse_voxel_mask(pts[::16], 1.0, 0.25).all()
    # cells of 3 points against a median of 16 stay with ratio 0.1 (>= 1.6) and go with 0.25 (>= 4)
    extra = np.array([[50.5, 50.5, 90.0], [50.6, 50.5, 90.0], [50.7, 50.5, 90.0]])
    both = np.vstack([pts, extra])
    assert sparse_voxel_mask(both, 4.0, 0.1)[-3:].all() and not sparse_voxel_mask(both, 4.0, 0.25)[-3:].any()


def test_near_drops_a_point_floating_next_to_the_surface_and_keeps_its_border():
    pts, n_plane = plane_with_outliers()
    # one point 5.5 above the plane (its cell is sparse, its block holds plane cells) and one on the plane's
    # border, 1 beyond its last row (a sparse cell too, with full neighbours)
    both = np.vstack([pts, [[50.5, 50.5, 5.5], [100.0, 50.0, 0.0]]])
    loose = sparse_voxel_mask(both, 4.0, 0.25)
    assert loose[-2] and loose[-1] and not loose[n_plane:-2].any()
    tight = sparse_voxel_mask(both, 4.0, 0.25, near=3.0)
    assert not tight[-2] and tight[-1] and tight[:n_plane].all() and not tight[n_plane:-2].any()


def test_lo_ransac_registers_scans_with_30_percent_outliers_on_thinned_clouds():
    """bun045 -> bun000 with 30 % of the source outliers uniform in its bounding box, uniform keypoints:
    on the voxel-thinned clouds the outlier guard drops (nearly) only outliers and the pose is found; without it
    the thinned source is mostly outliers, and the stage fails or lands far off."""
    from test_coarse import stanford_case

    from scanreg.errors import StageError

    tgt, src, T_gt, sp, helpers = stanford_case(3, 10000, build(SALIENCE, "uniform"))
    c = RunContext(seed=0)
    rng = np.random.default_rng(5)
    n_out = int(round(0.3 / 0.7 * src.n_points))
    lo, hi = src.points.min(axis=0), src.points.max(axis=0)
    out = rng.uniform(lo, hi, size=(n_out, 3))
    nrm = rng.normal(size=(n_out, 3))
    src = Cloud(np.vstack([src.points, out]), np.vstack([src.normals, nrm / np.linalg.norm(nrm, axis=1)[:, None]]))
    res = build_coarse("lo_ransac", helpers, fallback_voxel=None).align(tgt, src, sp, c)
    T, m = res.T_target_source, res.metrics
    rot, trans = transform_errors(T, T_gt)
    # measured: 1.10 deg and 0.77 % of the diagonal
    assert rot < 3.3 and trans < 0.023 * bbox_diagonal(tgt.points), (rot, trans, m)
    # nearly every outlier dropped (those within 3 spacings of the surface stay), few surface points
    assert 0.85 * n_out < m["coarse_isolated_source"] < 1.05 * n_out, (n_out, m)
    assert m["coarse_isolated_target"] < 0.01 * tgt.n_points, m
    try:
        T0 = build_coarse("lo_ransac", helpers, fallback_voxel=None, isolated_ratio=None).align(
            tgt, src, sp, c).T_target_source
    except StageError:
        return
    assert transform_errors(T0, T_gt)[0] > 5, "the case no longer shows the guard's effect"


def test_lo_ransac_remeasures_the_spacing_at_50_percent_outliers():
    """Half the source outliers and the run's spacing measured as the runner measures it, on the clouds with
    their outliers (1.5 times the surface's): the guard finds the outliers on the coarse grid, measures the
    spacing again without them, looks again on the finer grid, and the pose is found."""
    from test_coarse import stanford_case

    from scanreg.geometry import estimate_spacing

    tgt, src, T_gt, clean, helpers = stanford_case(3, 10000, build(SALIENCE, "uniform"))
    c = RunContext(seed=0)
    stage = build_coarse("lo_ransac", helpers, fallback_voxel=None)
    clean_coarse = stage.align(tgt, src, clean, c).metrics["coarse_spacing"]
    rng = np.random.default_rng(6)
    out = rng.uniform(src.points.min(axis=0), src.points.max(axis=0), size=(src.n_points, 3))
    nrm = rng.normal(size=out.shape)
    src = Cloud(np.vstack([src.points, out]), np.vstack([src.normals, nrm / np.linalg.norm(nrm, axis=1)[:, None]]))
    spacing = max(estimate_spacing(tgt.points, np.random.default_rng(1)),
                  estimate_spacing(src.points, np.random.default_rng(2)))
    assert spacing > 1.3 * clean  # the runner's spacing, inflated by the outliers
    res = build_coarse("lo_ransac", helpers, fallback_voxel=None).align(tgt, src, spacing, c)
    T, m = res.T_target_source, res.metrics
    assert transform_errors(T, T_gt)[0] < 3.7, m  # measured: 1.24 deg
    assert 0.8 * len(out) < m["coarse_isolated_source"] < 1.05 * len(out), m
    # thinned on the grid of the spacing measured again (coarse spacing 1.17 times the clean run's here), not
    # on the inflated one (one pass: 1.48 times)
    assert m["coarse_spacing"] < 1.3 * clean_coarse, (m["coarse_spacing"], clean_coarse)


def test_isolated_ratio_is_checked():
    from scanreg.errors import ConfigError

    with pytest.raises((ConfigError, ValueError), match="isolated_ratio"):
        build_coarse("lo_ransac", isolated_ratio=0.0)


def test_near_test_against_every_point_by_brute_force():
    """The near test of sparse_voxel_mask (a sparse cell's point with no other point within ``near`` goes)
    decided by brute force on a noisy cloud: its k-d tree holds only the sparse cells' blocks, which must give
    the same answer as every point."""
    from scipy.spatial.distance import cdist

    from scanreg.geometry import voxel_occupancy

    rng = np.random.default_rng(11)
    plane = np.c_[rng.uniform(0, 40, size=(3000, 2)), rng.normal(scale=0.2, size=3000)]
    pts = np.vstack([plane, rng.uniform([-5, -5, -6], [45, 45, 6], size=(150, 3))])
    voxel, ratio, near = 4.0, 0.25, 3.0
    base = sparse_voxel_mask(pts, voxel, ratio)
    got = sparse_voxel_mask(pts, voxel, ratio, near=near)
    occ = voxel_occupancy(pts, voxel)  # the grid without the margin: the same cells
    sparse = occ < ratio * np.quantile(occ, 0.9)
    D = cdist(pts, pts)
    np.fill_diagonal(D, np.inf)
    lonely = D.min(axis=1) > near
    expected = base & ~(sparse & lonely)
    assert np.array_equal(got, expected) and (got != base).sum() > 5
