"""A scan far sparser than the other (a few dozen points against tens of thousands): the coarse stage thins the
dense one to near the sparse one's density instead of describing all its points at the sparse spacing (81 s for
51 points against 40 000, 41 s for 101), and the run warns that a fitness measured at the sparse spacing says
little."""

from __future__ import annotations

import numpy as np
import pytest

import scanreg
from conftest import shared
from scanreg.eval.metrics import sparse_pair_warning
from scanreg.geometry import Cloud, estimate_spacing, random_pose
from scanreg.stages.coarse.thinning import DENSITY_GAP, downsampled
from scanreg.stages.pair import pair_spacing
from scanreg.types import RunContext


def plane(n, seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (n, 2))
    return Cloud(np.c_[xy, 0.05 * np.sin(4 * xy[:, 0])])


def ctx(tmp_path):
    return RunContext(seed=0, run_dir=tmp_path)


def test_a_dense_cloud_is_thinned_towards_a_sparse_ones_density(tmp_path):
    sparse, dense = plane(100, 1), plane(40000, 2)
    spacing = pair_spacing(dense.points, sparse.points, ctx(tmp_path))
    t, s, sp = downsampled(dense, sparse, spacing, ctx(tmp_path), 4 * spacing, None, 2000)
    assert s is sparse and sp == spacing  # the sparse cloud whole, the pair's spacing as it was
    own = estimate_spacing(t.points, np.random.default_rng(0))
    # one point per voxel of spacing / DENSITY_GAP: its nearest neighbours about 0.7 voxel apart
    assert t.n_points < dense.n_points / 4 and 0.5 * spacing / DENSITY_GAP <= own < spacing
    # the other way round alike
    s2, t2, _ = downsampled(sparse, dense, spacing, ctx(tmp_path), 4 * spacing, None, 2000)
    assert s2 is sparse and t2.n_points == t.n_points


def test_a_density_ratio_up_to_16_is_left_as_it_was(tmp_path):
    """8 times the points (the density-robustness experiments' largest ratio): both clouds as given."""
    sparse, dense = plane(1500, 3), plane(12000, 4)
    spacing = pair_spacing(dense.points, sparse.points, ctx(tmp_path))
    t, s, sp = downsampled(dense, sparse, spacing, ctx(tmp_path), 4 * spacing, None, 2000)
    assert t is dense and s is sparse and sp == spacing


def test_the_warning_names_the_sparse_scan_above_the_ratio():
    line = sparse_pair_warning(0.0114, 0.000516, 51, 40256, 4.0)
    assert line.startswith("the source is 22x sparser than the target") and "51 points" in line
    assert "target is 5x sparser than the source" in sparse_pair_warning(1.0, 5.0, 10, 10, 4.0)
    assert sparse_pair_warning(2.8, 1.0, 1500, 12000, 4.0) is None  # 8 times the points: no warning
    assert sparse_pair_warning(100.0, 1.0, 10, 10, 0.0) is None  # 0: never
    # a user's trial: a crop in cm beside the whole in mm (9.4x the size, under data.max_size_ratio) was told
    # to give the source more points; the line names the units first when the sparse scan is also larger
    line = sparse_pair_warning(0.02521, 0.003143, 20000, 20000, 4.0, source_diagonal=2.35, target_diagonal=0.25)
    assert "it is also 9.4x as large, so the two may be in different units (likely mm vs cm: set " \
           "data.source_scale=0.1); else the pair" in line
    assert "different units" not in sparse_pair_warning(0.025, 0.003, 2000, 20000, 4.0, 0.25, 0.25)  # same size
    assert "different units" not in sparse_pair_warning(0.05, 0.003, 2000, 20000, 4.0, 2.5, 0.25)  # 17x: no unit


@pytest.mark.slow
def test_a_hundred_points_of_a_scan_register_onto_the_whole_other(tmp_path):
    """Every 400th vertex of bun045 (101 points) onto bun000's 40 256: 0.14 deg (before the thinning, the
    same pose in 41 s of coarse stage)."""
    from scanreg.io import read_geometry
    from scanreg.io.readers import read_stanford_conf

    poses = read_stanford_conf(shared("stanford_bunny/bun.conf"))
    src = read_geometry(shared("stanford_bunny/bun045.ply"))
    tgt = read_geometry(shared("stanford_bunny/bun000.ply"))
    s, t = src.vertices[np.unique(src.faces)][::400], tgt.vertices[np.unique(tgt.faces)]
    T_pose = random_pose(np.random.default_rng(1), 180, 0.1)
    gt = np.linalg.inv(poses["bun000.ply"]) @ poses["bun045.ply"] @ np.linalg.inv(T_pose)
    r = scanreg.register(s @ T_pose[:3, :3].T + T_pose[:3, 3], t, gt=gt, run_dir=tmp_path / "run")
    assert r.metrics["coarse_points_target"] < len(t) / 4
    assert r.metrics["rotation_error_deg"] < 0.5
