"""The compiled mesh kernels (scanreg.mesh.native, pipeline/mesh/_native.c) against their NumPy versions and
brute force: the same pairs of boxes, the same instances and sheets of the census's broad phase, bit for bit, on
random boxes, hand-built meshes and real ones."""

from __future__ import annotations

import numpy as np
import pytest

import scanreg.mesh.census as census_module
from scanreg.io import read_mesh
from scanreg.mesh import native
from scanreg.mesh.census import census
from scanreg.mesh.intersect import candidate_pairs, candidate_pairs_numpy, face_boxes
from tests.test_census import sphere


def bunny():
    import pymeshfix
    from pathlib import Path

    return read_mesh(str(Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply"))


def test_the_kernels_are_built():
    """./run builds them (it installs gcc and Python's headers where it can): a build that failed would make every
    comparison below pass by comparing NumPy with itself."""
    assert native.kernels is not None, "scanreg.mesh._native was not built: install a C compiler and Python's " \
                                       "headers, then reinstall scanreg (pip install -e .)"


def as_set(i: np.ndarray, j: np.ndarray, m: int) -> np.ndarray:
    return np.sort(np.asarray(i, np.int64) * m + np.asarray(j, np.int64))


def brute_force(lo, hi, among) -> np.ndarray:
    over = np.all((lo[:, None, :] <= hi[None, :, :]) & (lo[None, :, :] <= hi[:, None, :]), axis=2)
    i, j = np.nonzero(np.triu(over, 1))
    if among is not None:
        keep = among[i] | among[j]
        i, j = i[keep], j[keep]
    return as_set(i, j, len(lo))


@pytest.mark.parametrize("seed", range(6))
def test_box_pairs_are_every_overlapping_pair_once(seed):
    """Boxes of many sizes (points, slabs, a few spanning everything), at several scales and offsets, on a grid
    of shared coordinates (boxes that touch): each overlapping pair once, i < j, with and without a mask."""
    rng = np.random.default_rng(seed)
    for trial in range(40):
        n = int(rng.integers(2, 250))
        scale, offset = rng.choice([1e-6, 1.0, 1e4]), rng.choice([0.0, 1e3])
        lo = rng.random((n, 3))
        if trial % 3 == 0:
            lo = np.round(lo, 1)  # touching boxes
        side = rng.random((n, 3)) ** rng.integers(1, 6) * rng.choice([0.01, 0.3, 3.0])
        side[rng.random(n) < 0.2] = 0  # points and flat boxes
        lo, hi = offset + scale * lo, offset + scale * (lo + side)
        among = None if trial % 2 else rng.random(n) < 0.2
        i, j = candidate_pairs(lo, hi, among)
        assert (i < j).all()
        got = as_set(i, j, n)
        assert len(np.unique(got)) == len(got)
        np.testing.assert_array_equal(got, brute_force(lo, hi, among))


def test_box_pairs_match_numpy_on_the_bunny():
    m = bunny()
    lo, hi = face_boxes(m.vertices[m.faces])
    among = np.random.default_rng(0).random(len(lo)) < 0.01
    for mask in (None, among):
        n = len(lo)
        np.testing.assert_array_equal(as_set(*candidate_pairs(lo, hi, mask), n),
                                      as_set(*candidate_pairs_numpy(lo, hi, mask), n))


def test_a_non_finite_box_is_refused_as_numpy_refuses_it():
    """The kernel's grids need finite boxes: others go to the NumPy version, which refuses them (the readers
    refuse non-finite coordinates before)."""
    lo = np.array([[0, 0, 0], [0.5, 0.5, 0.5], [np.nan, 0, 0]], float)
    with pytest.raises(ValueError, match="finite"):
        candidate_pairs(lo, lo + 1)


def test_box_pairs_refuse_other_types():
    lo = np.zeros((4, 3), np.float32)
    with pytest.raises(TypeError, match="float64"):
        native.kernels.box_pairs(lo, lo, None, 1.0)
    with pytest.raises(ValueError, match="among"):
        native.kernels.box_pairs(lo.astype(float), lo.astype(float), np.zeros(3, np.uint8), 1.0)


def meshes():
    v, f = sphere(3)
    rng = np.random.default_rng(1)
    yield "two spheres", np.vstack([v, v + [0.5, 0.2, 0.1]]), np.vstack([f, f + len(v)])
    yield "jittered", v + rng.normal(0, 0.06, v.shape), f
    yield "soup", rng.normal(size=(600, 3)), np.arange(600).reshape(-1, 3)
    m = bunny()
    yield "bunny", m.vertices, m.faces


def test_sheets_are_numpy_s_bit_for_bit(monkeypatch):
    """Every level of the broad phase on each mesh: the kernel's instances, cell keys, plane tests and sheet labels
    equal the NumPy version's, and so do the census's candidates and fold vertices."""
    calls = []

    def both(*args):
        got = census_module._sheets_kernel(*args)
        want = census_module._sheets_numpy(*args)
        for g, w in zip(got[:4], want[:4]):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
        assert got[4] == want[4]
        calls.append(len(got[0]))
        return got

    for name, v, f in meshes():
        monkeypatch.setattr(native, "kernels", None)
        plain = census(v, f)
        monkeypatch.undo()
        monkeypatch.setattr(census_module, "_sheets", both)
        fast = census(v, f)
        monkeypatch.undo()
        np.testing.assert_array_equal(fast.intersection_candidates, plain.intersection_candidates, err_msg=name)
        np.testing.assert_array_equal(fast.fold_vertices, plain.fold_vertices, err_msg=name)
    assert len(calls) >= 4 and min(calls) > 0
