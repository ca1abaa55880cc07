"""The compiled mesh kernels (scanreg.mesh.native, pipeline/mesh/_native.c) against their NumPy versions and
brute force: the same pairs of boxes, the same instances and sheets of the census's broad phase, bit for bit, on
random boxes, hand-built meshes and real ones."""

from __future__ import annotations

import numpy as np
import pytest

import scanreg.mesh.broad_phase as broad_phase
from scanreg.io import read_mesh
from scanreg.mesh import native
from scanreg.mesh.census import census
from scanreg.mesh.boxes import candidate_pairs, candidate_pairs_numpy, face_boxes
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


@pytest.mark.filterwarnings("ignore:invalid value encountered")  # NumPy's own, on the way to its error
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
    with pytest.raises(TypeError, match="among"):
        native.kernels.box_pairs(lo.astype(float), lo.astype(float), np.zeros(3, np.uint8), 1.0)
    with pytest.raises(TypeError, match="rows of 3"):
        native.kernels.box_pairs(np.zeros(6), np.zeros(6), None, 1.0)
    with pytest.raises(ValueError, match="not finite"):
        native.kernels.box_pairs(np.array([[-1.7e308, 0, 0], [0, 0, 0]]), np.array([[0, 1, 1], [1e308, 1, 1]]),
                                 None, 1.0)


def test_the_kernels_refuse_inconsistent_input_before_writing():
    """From a review: a level's cells that do not add up, a grid too large to number, indices out of range or
    arrays of the wrong shape are refused with a Python exception (no write out of bounds, no crash)."""
    one, f = np.zeros((1, 3), np.int64), np.zeros((1, 3))
    empty = np.zeros(0, np.int64)
    good = dict(a=one, span=np.ones((1, 3), np.int64), cnt=np.ones(1, np.int64))
    cases = [dict(good, span=np.full((1, 3), 2, np.int64)),  # 8 cells, cnt says 1
             dict(good, cnt=np.full(1, -1, np.int64)), dict(good, a=np.full((1, 3), -1, np.int64))]
    for case in cases:
        with pytest.raises(ValueError, match="sheets"):
            native.kernels.sheets(case["a"], case["span"], case["cnt"], f, f, empty, empty, (3, 3, 3), (0, 0, 0),
                                  (0.0, 0.0, 0.0), 1.0)
    for dims in ((1, 0, 1), (2 ** 32, 2 ** 32, 1)):
        with pytest.raises(ValueError, match="dims"):
            native.kernels.sheets(one, good["span"], good["cnt"], f, f, empty, empty, dims, (0, 0, 0),
                                  (0.0, 0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="out of range"):
        native.kernels.face_keys(np.zeros((2, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(TypeError, match="n, 3, 3"):
        native.kernels.same_corners(np.zeros((2, 9)), np.zeros((2, 9)))
    with pytest.raises(ValueError, match="n_sheets"):
        native.kernels.cross_sheet_pairs(empty, empty, np.zeros(0, np.uint8), empty, -1, np.zeros(0, np.uint8), True,
                                         f, f, one)


def test_meshes_spanning_more_cells_than_int64_numbers_agree():
    """From a review: faces 2^22 to 2^64 cells apart made the cell keys (and, in the kernel, the buffers) overflow;
    the grid is now made coarser there, and both versions find the same candidates, the crossing pair among
    them."""
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float) * 0.25
    cross = [[0.8, 0.8, 0.5], [1.3, 0.8, 0.5], [0.8, 1.3, 0.5]], [[0.9, 0.9, 0.3], [1.2, 1, 0.7], [0.9, 1.2, 0.7]]
    far = np.vstack([tri, np.add(cross[0], 2.0 ** 22), np.add(cross[1], 2.0 ** 22)])
    row = np.concatenate([tri * 4 + [2.0 * k, 0, 0] for k in range(100)] + [[[0, 0, 0], [2.0 ** 64, 0, 0], [0, 12, 0]]])
    for v, want in ((far, [[1, 2]]), (row, None)):
        f = np.arange(len(v)).reshape(-1, 3)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(native, "kernels", None)
            plain = census(v, f)
        fast = census(v, f)
        np.testing.assert_array_equal(fast.intersection_candidates, plain.intersection_candidates)
        if want is not None:
            assert fast.intersection_candidates.tolist() == want


def meshes():
    v, f = sphere(3)
    rng = np.random.default_rng(1)
    yield "two spheres", np.vstack([v, v + [0.5, 0.2, 0.1]]), np.vstack([f, f + len(v)])
    yield "jittered", v + rng.normal(0, 0.06, v.shape), f
    yield "soup", rng.normal(size=(600, 3)), np.arange(600).reshape(-1, 3)
    m = bunny()
    yield "bunny", m.vertices, m.faces


def test_the_broad_phase_is_numpy_s_bit_for_bit(monkeypatch):
    """Every call of each kernel of the census's broad phase on each mesh gives the NumPy version's answer: the same
    instances, cell keys, plane tests and sheet labels (arrays equal), the same cross-sheet pairs (as a set), the
    same filtered candidates (arrays equal), the same fold vertices; and so the census's candidates and fold
    vertices are the same."""
    calls = {"sheets": 0, "cross": 0, "filter": 0}

    def sheets(*args):
        got, want = broad_phase._sheets_kernel(*args), broad_phase._sheets_numpy(*args)
        for g, w in zip(got[:4], want[:4]):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
        assert got[4] == want[4]
        calls["sheets"] += len(got[0]) > 0
        return got

    def cross(*args):
        with monkeypatch.context() as m:
            m.setattr(native, "kernels", None)
            want = cross_kernel(*args)  # the NumPy version, with the same filter
        got = cross_kernel(*args)
        n = len(args[0])
        np.testing.assert_array_equal(np.unique(got[0] * n + got[1]), np.unique(want[0] * n + want[1]))
        assert len(got[0]) == len(want[0])  # the same pairs, repeats included
        calls["cross"] += len(got[0]) > 0
        return got

    def among(*args):
        got, want = among_kernel(*args), broad_phase._candidates_among_numpy(*args)
        np.testing.assert_array_equal(np.stack(got), np.stack(want))
        calls["filter"] += len(got[0]) > 0
        return got

    cross_kernel, among_kernel = broad_phase._cross_sheet_pairs, broad_phase._candidates_among
    for name, v, f in meshes():
        with monkeypatch.context() as m:
            m.setattr(native, "kernels", None)
            plain = census(v, f)
            folds = broad_phase.fold_vertices(v, f)
        with monkeypatch.context() as m:
            m.setattr(broad_phase, "_sheets", sheets)
            m.setattr(broad_phase, "_cross_sheet_pairs", cross)
            m.setattr(broad_phase, "_candidates_among", among)
            fast = census(v, f)
        np.testing.assert_array_equal(fast.intersection_candidates, plain.intersection_candidates, err_msg=name)
        np.testing.assert_array_equal(fast.fold_vertices, plain.fold_vertices, err_msg=name)
        np.testing.assert_array_equal(broad_phase.fold_vertices(v, f), folds, err_msg=name)
    assert min(calls.values()) >= 3, calls


def test_fold_vertices_of_a_fan_that_covers_itself_and_of_a_crease():
    """Known answers: a flat fan around a vertex that turns more than twice (800 degrees), and two faces folded
    onto each other across their edge, are fold vertices; a flat fan turning once and two flat faces are not."""
    def fan(total_deg, n):
        a = np.radians(np.linspace(0, total_deg, n + 1))
        v = np.vstack([[0, 0, 0], np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)])
        f = np.stack([np.zeros(n, int), np.arange(1, n + 1), np.arange(2, n + 2)], 1)
        return v, f

    v, f = fan(800, 10)
    assert 0 in broad_phase.fold_vertices(v, f)
    v, f = fan(300, 5)
    assert 0 not in broad_phase.fold_vertices(v, f)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0.05]], float)  # two faces side by side, flat
    assert len(broad_phase.fold_vertices(v, np.array([[0, 1, 2], [1, 0, 3]]))) == 0
    v[3] = [0.3, 0.5, 0.05]  # the second folded over onto the first across their edge
    assert set(broad_phase.fold_vertices(v, np.array([[0, 1, 2], [1, 0, 3]]))) == {0, 1}


def test_candidate_filter_decides_as_numpy_at_the_filters_bound():
    """Pairs of triangles whose second face lies within a few rounding errors of the first's plane, where the
    floating-point filter of orient3d (Shewchuk's bound) decides between 'certainly on one side' and 'unsure':
    the kernel keeps exactly the pairs the NumPy version keeps, and both keep some and drop some."""
    rng = np.random.default_rng(7)
    n = 4000
    a, b, c = (rng.random((n, 3)) for _ in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    offset = np.ldexp(1.0, -rng.integers(46, 56, n))[:, None] * rng.choice([-1.0, 1.0], (n, 1))
    # the second face: three points in the first's box, lifted off its plane by about ``offset``
    w = rng.dirichlet(np.ones(3), (n, 3))
    p = [w[:, k, :1] * a + w[:, k, 1:2] * b + w[:, k, 2:] * c + offset for k in range(3)]
    v = np.concatenate([a, b, c, *p])
    idx = np.arange(n)
    fl = np.stack([np.stack([idx, idx + n, idx + 2 * n], 1), np.stack([idx + 3 * n, idx + 4 * n, idx + 5 * n], 1)])
    fl = fl.reshape(-1, 3)
    lo, hi = face_boxes(v[fl])
    i, j = np.arange(n), np.arange(n) + n
    got = broad_phase._candidates_among(i, j, lo, hi, fl, v)
    want = broad_phase._candidates_among_numpy(i, j, lo, hi, fl, v)
    np.testing.assert_array_equal(np.stack(got), np.stack(want))
    assert 0.1 * n < len(got[0]) < 0.9 * n


def test_face_keys_and_same_corners_are_numpy_s():
    """The incremental self-intersection test's face matching: the same 64-bit keys (coordinate bits hashed) and
    the same verdicts on triangles with their corners permuted, moved by an ulp, one corner's -0.0 for 0.0
    (equal as numbers) and a NaN (equal to nothing)."""
    from scanreg.mesh.intersect import face_keys, face_keys_numpy, same_corners, same_corners_numpy

    m = bunny()
    np.testing.assert_array_equal(face_keys(m.vertices, m.faces), face_keys_numpy(m.vertices, m.faces))
    rng = np.random.default_rng(3)
    P = rng.integers(-2, 3, (3000, 3, 3)).astype(float)  # small integers: corners often repeat
    Q = P[:, rng.permutation(3)].copy()
    Q[rng.permutation(3000)[:300], rng.integers(0, 3, 300), rng.integers(0, 3, 300)] += 1e-12
    Q[:500] = P[:500][:, [0, 0, 1]]  # a corner twice: not the same set
    Q[500 + rng.permutation(2500)[:20], 1, 1] = np.nan
    zero = 500 + np.flatnonzero(P[500:, 0, 0] == 0)[:50]
    Q[zero] = P[zero]
    Q[zero, 0, 0] = -0.0
    got = same_corners(P, Q)
    np.testing.assert_array_equal(got, same_corners_numpy(P, Q))
    assert 0.2 < got.mean() < 0.9 and got[zero].all()
    # by index, without gathering: the faces of two meshes made of those triangles, paired in a shuffled order
    from scanreg.mesh.intersect import same_faces

    order = rng.permutation(3000)
    va, vb = P.reshape(-1, 3), Q[order].reshape(-1, 3)
    fa = np.arange(9000).reshape(-1, 3)
    back = np.argsort(order)
    np.testing.assert_array_equal(same_faces(va, fa, np.arange(3000), vb, fa, back), got)
    with pytest.raises(ValueError, match="out of range"):
        native.kernels.same_corners_at(va, fa, np.array([3000]), vb, fa, np.array([0]))


def test_stable_order_is_numpys_stable_argsort():
    """The radix sort of face keys: NumPy's stable argsort, equal keys in their order, on full-width keys, few
    distinct keys, keys alike in most bytes, the extremes and nothing."""
    from scanreg.mesh.intersect import stable_order

    rng = np.random.default_rng(5)
    for keys in (rng.integers(0, 2 ** 63, 5000, dtype=np.uint64) * np.uint64(2) + np.uint64(1),
                 rng.integers(0, 7, 5000).astype(np.uint64),
                 np.uint64(0xABCD000000000000) + rng.integers(0, 300, 5000).astype(np.uint64),
                 np.array([2 ** 64 - 1, 0, 2 ** 63, 0, 2 ** 64 - 1], np.uint64), np.zeros(0, np.uint64)):
        np.testing.assert_array_equal(stable_order(keys), np.argsort(keys, kind="stable"))


def test_non_manifold_vertices_are_numpy_s():
    """The fans of each vertex by the kernel's union of corners: the same non-manifold vertices as the NumPy
    version (pointer doubling on consistent orientation, the graph's components otherwise) on pymeshfix's bunny,
    the bunny with a fifth of its faces flipped, with two parts welded at a vertex, and a triangle soup welded."""
    from scanreg.geometry import Mesh
    from scanreg.mesh.topology import non_manifold_vertex_mask

    m = bunny()
    rng = np.random.default_rng(2)
    flipped = m.faces.copy()
    flip = rng.random(len(flipped)) < 0.2
    flipped[flip] = flipped[flip][:, ::-1]
    v2 = np.vstack([m.vertices, m.vertices + 1.0])
    pinched = np.vstack([m.faces, m.faces + len(m.vertices)])
    pinched[pinched == len(m.vertices) + 7] = 7  # the copy's vertex 7 is the original's: one vertex, two fans
    soup = rng.integers(0, 400, (3000, 3))
    soup = soup[(soup[:, 0] != soup[:, 1]) & (soup[:, 1] != soup[:, 2]) & (soup[:, 0] != soup[:, 2])]
    cases = [(m.vertices, m.faces), (m.vertices, flipped), (v2, pinched), (rng.random((400, 3)), soup)]
    found = []
    for v, f in cases:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(native, "kernels", None)
            want = non_manifold_vertex_mask(Mesh(v, f))
        got = non_manifold_vertex_mask(Mesh(v, f))
        np.testing.assert_array_equal(got, want)
        found.append(int(got.sum()))
    assert found[2] >= 1 + found[0] and found[3] > 10


def test_projection_axes_are_numpy_s_on_collinear_and_grid_triangles():
    """The degenerate-face and projection choice of the exact tests: the kernel's filter, its exact cases (exact
    differences and products, a zero permanent) and the rows it leaves to exact arithmetic give the NumPy
    version's axes and verdicts on triangles exactly collinear on a grid, nearly collinear in float32, partly
    axis-aligned, at scales from 1e-140 to 1e150 (where products underflow or the filter cannot decide)."""
    from scanreg.mesh.predicates import projection_axes, projection_axes_numpy

    rng = np.random.default_rng(11)
    unsure = []
    for trial in range(12):
        n = 3000
        p, q, t = rng.random((n, 3)), rng.random((n, 3)), rng.random((n, 1))
        r = p + t * (q - p)
        if trial % 3 == 0:
            p, q, r = (x.astype(np.float32).astype(float) for x in (p, q, r))
        elif trial % 3 == 1:
            g = rng.integers(-1000, 1000, (n, 3, 3)) / 1024.0
            p, q, r = g[:, 0], g[:, 1], g[:, 2]
            r[::2] = p[::2] + 2 * (q[::2] - p[::2])  # exactly collinear
            r[1::4, 2] = p[1::4, 2]
        scale, off = [1e-140, 1e-3, 1.0, 1e5, 1e150][trial % 5], [0.0, 1.0, 1e3][trial % 3]
        p, q, r = (x * scale + off for x in (p, q, r))
        got, want = projection_axes(p, q, r), projection_axes_numpy(p, q, r)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        unsure.append((np.frombuffer(native.kernels.orient2d_projections(p, q, r)[1], np.int8) < 0).mean())
    assert max(unsure) > 0.3 and min(unsure) == 0  # both paths taken


def test_face_boxes_are_numpy_s_to_the_bit():
    """Each face's box from the vertices and faces, as np.minimum / np.maximum give it from the gathered corners:
    the same values, the same signed zeros (NumPy keeps the second of two equal values), NaN propagated."""
    from scanreg.mesh.boxes import face_boxes, mesh_face_boxes

    m = bunny()
    v = m.vertices.copy()
    rng = np.random.default_rng(4)
    v[rng.permutation(len(v))[:2000]] = rng.choice([0.0, -0.0], (2000, 3))
    v[rng.permutation(len(v))[:50], 1] = np.nan
    for got, want in zip(mesh_face_boxes(v, m.faces), face_boxes(v[m.faces])):
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(want))
