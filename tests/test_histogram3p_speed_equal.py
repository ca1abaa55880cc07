"""histogram3p's fast path (issue #16 item 4: one scipy k-d tree for both neighbour searches, the votes as dense
bilinear shares and one matrix product per plane) against the implementation it replaced, kept here verbatim
as the reference: the same descriptor values to 1e-12 and the same coarse registration on a real bunny scan.
(``tests/test_fast_paths.py`` pins the same against the straightforward code from before issue #16.)"""

import os

import numpy as np
import pytest

from conftest import shared, stage_ctx
from scanreg.config import to_abs
from scanreg.geometry import Cloud, apply_T, barycentric_sample, invert_T, random_pose
from scanreg.io import read_mesh, read_stanford_conf
from scanreg.metrics import estimate_spacing, transform_errors
from scanreg.registry import COARSE, DESCRIPTOR, MATCHER, SALIENCE, load_all

load_all()


# ------------------------------------------------------------------ the implementation before, verbatim
def reference_neighbourhoods(points, radius, max_neighbors, queries=None):
    """scanreg.stages.salience.neighbourhoods as histogram3p called it (pykdtree)."""
    from pykdtree.kdtree import KDTree

    q = points if queries is None else queries
    k = min(max_neighbors, len(points))
    d, j = KDTree(points).query(np.ascontiguousarray(q), k=k, distance_upper_bound=radius)
    d, j = d.reshape(len(q), k), j.reshape(len(q), k).astype(np.int64)
    valid = j < len(points)
    j = np.where(valid, j, 0)
    return j, np.where(valid, d, np.inf), valid


def _two_bins(u, nbins, wrap):
    i = np.floor(u)
    f = u - i
    lo = i.astype(np.int64)
    idx = np.stack([lo, lo + 1], axis=-1)
    share = np.stack([1 - f, f], axis=-1)
    if wrap:
        return idx % nbins, share
    outside = (idx < 0) | (idx >= nbins)
    return np.where(outside, 0, idx), np.where(outside, 0.0, share)


def reference_histogram3p(p, cloud, keypoints, spacing):
    """Histogram3P.compute before this change (pykdtree searches, every vote into one bincount per block)."""
    from scanreg.closest import estimate_normals
    from scanreg.stages.descriptor import local_frames

    u, s = p.distances, spacing
    R = to_abs(p.radius, u, s)
    pts = cloud.points
    nrm = cloud.normals if cloud.normals is not None else estimate_normals(pts)
    j, d, valid = reference_neighbourhoods(pts, R, p.max_neighbors, pts[keypoints])
    fr = to_abs(p.frame_radius, u, s)
    frames = local_frames(pts, cloud.normals, keypoints, fr, neighbours=(j, d, valid) if fr <= R else None)
    used = np.unique(j[valid])
    _, _, vd = reference_neighbourhoods(pts, to_abs(p.density_radius, u, s), 64, pts[used])
    dens = np.zeros(len(pts))
    dens[used] = vd.sum(axis=1)
    w = np.where(valid, (1.0 - np.minimum(d, R) / R) / np.maximum(dens[j], 1.0), 0.0)
    n = len(keypoints)
    out = np.empty((n, 216))

    def block(r0):
        rs = slice(r0, r0 + step)
        jj, F = j[rs], frames[rs].transpose(0, 2, 1)
        nb = len(jj)
        L = np.matmul(pts[jj] - pts[keypoints[rs]][:, None, :], F)
        Ln = np.matmul(nrm[jj], F)
        spatial = [_two_bins((L[:, :, c] + R) / (2 * R / 3) - 0.5, 3, wrap=False) for c in range(3)]
        wr = w[rs][..., None]
        base = (np.arange(nb) * 216)[:, None, None, None, None]
        idx = np.empty((3, nb, jj.shape[1], 2, 2, 2), np.int64)
        wts = np.empty(idx.shape)
        for plane, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
            (ia, sa), (ib, sb) = spatial[a], spatial[b]
            io, so = _two_bins((np.arctan2(Ln[:, :, b], Ln[:, :, a]) + np.pi) / (2 * np.pi / 8) - 0.5, 8,
                               wrap=True)
            np.add(base + plane * 72 + ia[..., :, None, None] * 24 + ib[..., None, :, None] * 8,
                   io[..., None, None, :], out=idx[plane])
            np.multiply((wr * sa)[..., :, None, None] * sb[..., None, :, None], so[..., None, None, :],
                        out=wts[plane])
        out[rs] = np.bincount(idx.ravel(), wts.ravel(), minlength=nb * 216).reshape(nb, 216)

    step = max(1, 2 ** 16 // max(j.shape[1], 1))
    starts = range(0, n, step)
    if len(starts) > 1 and (os.cpu_count() or 1) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(os.cpu_count() or 1, len(starts))) as pool:
            list(pool.map(block, starts))
    else:
        for r0 in starts:
            block(r0)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(norm > 0, norm, 1.0)


class ReferenceHistogram3P:
    """The reference as a descriptor stage, for the coarse stage."""

    def __init__(self, params):
        self.p = params

    def compute(self, cloud, keypoints, ctx):
        return reference_histogram3p(self.p, cloud, keypoints, ctx.spacing)


# ------------------------------------------------------------------ the real case
@pytest.fixture(scope="module")
def bunny():
    """bun045 -> bun000 sampled at the default 20 000 points, the source under a random pose, and the thinned
    target the default coarse stage works on (voxel 4 spacings) with its uniform keypoints."""
    from scanreg.stages.coarse import downsampled

    folder = shared("stanford_bunny")
    poses = read_stanford_conf(folder / "bun.conf")
    P = random_pose(np.random.default_rng(3), 180, 0.1)
    T_gt = invert_T(poses["bun000.ply"]) @ poses["bun045.ply"] @ invert_T(P)
    tp, tn, _ = barycentric_sample(read_mesh(folder / "bun000.ply"), 20000, np.random.default_rng(0))
    sp_, sn, _ = barycentric_sample(read_mesh(folder / "bun045.ply"), 20000, np.random.default_rng(1))
    tgt, src = Cloud(tp, tn), Cloud(apply_T(P, sp_), sn @ P[:3, :3].T)
    c = stage_ctx(max(estimate_spacing(tp, np.random.default_rng(0)), estimate_spacing(sp_, np.random.default_rng(0))))
    thin, _, cc = downsampled(tgt, src, c, 4 * c.spacing, 12000, 2000)
    kp = SALIENCE.build({"name": "uniform"}).keypoints(thin, cc)
    return tgt, src, T_gt, c, thin, kp, cc


def test_neighbour_search_equals_pykdtree_on_a_bunny_scan(bunny):
    """scipy's k-d tree gives the same neighbours, distances and order as the pykdtree search it replaced."""
    from scipy.spatial import cKDTree

    from scanreg.stages.descriptor import _knn

    *_, thin, kp, cc = bunny
    pts = thin.points
    for r, k, q, full in ((15 * cc.spacing, 256, pts[kp], True), (2 * cc.spacing, 64, pts, False)):
        got, want = _knn(cKDTree(pts), q, r, k), reference_neighbourhoods(pts, r, k, q)
        count = want[2].sum(axis=1)
        assert count.min() >= 1 and (count.max() == k) == full  # the support search: the cap truncates some
        for g, w in zip(got, want):
            assert np.array_equal(g, w)


@pytest.mark.parametrize("radius, most", [(1.5, 19), (2.5, 64), (0.5, 1)])
def test_density_counts_equal_the_capped_search(radius, most):
    """The density count (points closer than the radius, itself included, at most 64), searched for 16 then
    for 64 where 16 are full, equals the valid count of the 64-neighbour search, on a grid where counts pass 16
    (radius 1.5: 19) and the cap (radius 2.5: 81 within, capped at 64), and points at exactly the radius (1 on
    the grid, which the strict bound leaves out)."""
    from scipy.spatial import cKDTree

    from scanreg.stages.descriptor import _count_within

    g = np.stack(np.meshgrid(*[np.arange(10.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    want = reference_neighbourhoods(g, radius, 64)[2].sum(axis=1)
    got = _count_within(cKDTree(g), g, radius, 64)
    assert want.max() == most and np.array_equal(got, want)
    assert np.array_equal(_count_within(cKDTree(g), g, 1.0, 64), np.ones(len(g)))  # neighbours at 1.0: out


@pytest.mark.parametrize("params", [{}, {"radius": 8.0, "max_neighbors": 64, "frame_radius": 10.0}])
def test_histogram3p_equals_the_previous_implementation_on_a_bunny_scan(bunny, params):
    """The default coarse stage's case (828 keypoints on 6 279 points); the second set has the frame radius
    beyond the support radius (frames from their own search) and a cap that truncates most neighbourhoods."""
    *_, thin, kp, cc = bunny
    st = DESCRIPTOR.build({"name": "histogram3p", **params})
    got = st.compute(thin, kp, cc)
    want = reference_histogram3p(st.p, thin, kp, cc.spacing)
    assert len(kp) > 500 and got.shape == want.shape == (len(kp), 216)
    assert np.count_nonzero(want) > 0.3 * want.size  # real histograms, not mostly empty ones
    assert np.abs(got - want).max() < 1e-12


def test_histogram3p_equals_the_previous_implementation_without_normals(bunny):
    *_, thin, kp, cc = bunny
    bare = Cloud(thin.points)
    st = DESCRIPTOR.build({"name": "histogram3p"})
    got, want = st.compute(bare, kp[:100], cc), reference_histogram3p(st.p, bare, kp[:100], cc.spacing)
    assert np.count_nonzero(want) > 0.3 * want.size and np.abs(got - want).max() < 1e-12


def test_coarse_registration_unchanged(bunny):
    """The default coarse stage with histogram3p: the same matches, inliers and transform, bit for bit, with
    the new implementation as with the reference; and the right answer."""
    tgt, src, T_gt, c, *_ = bunny
    results = []
    for desc in (DESCRIPTOR.build({"name": "histogram3p"}), ReferenceHistogram3P(DESCRIPTOR.build({"name": "histogram3p"}).p)):
        c.stages = {"salience": SALIENCE.build({"name": "uniform"}), "descriptor": desc,
                    "matcher": MATCHER.build({"name": "mutual_knn"})}
        T, m = COARSE.build({"name": "lo_ransac"}).run(tgt, src, c)
        results.append((T, m, c.coarse_trace))
    (T0, m0, tr0), (T1, m1, tr1) = results
    assert np.array_equal(tr0["matches_target"], tr1["matches_target"])
    assert np.array_equal(tr0["matches_source"], tr1["matches_source"])
    assert np.array_equal(tr0["ransac_inliers"], tr1["ransac_inliers"]) and m0 == m1
    assert np.array_equal(T0, T1)
    rot, trans = transform_errors(T0, T_gt)
    assert rot < 5 and m0["coarse_inliers"] >= 10, (rot, m0)
