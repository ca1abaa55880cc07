"""histogram3p's fast path (issue #16 item 4: one scipy k-d tree for both neighbour searches, the votes as dense
bilinear shares and one matrix product per plane) against the straightforward implementation from before issue
#16 (``tests/test_fast_paths.py``'s reference): the same descriptor values to 1e-12 and the same coarse
registration, bit for bit, on a real bunny scan; and scipy's searches against the pykdtree search they replaced."""

import numpy as np
import pytest

from conftest import build_coarse, shared
from scanreg.geometry import Cloud, apply_T, barycentric_sample, invert_T, random_pose
from scanreg.io import read_mesh, read_stanford_conf
from scanreg.geometry import estimate_spacing, transform_errors
from scanreg.stages.registry import DESCRIPTOR, MATCHER, SALIENCE, load_all
from scanreg.types import RunContext
# the references: the pykdtree search histogram3p used before (still the salience measures' search), and the
# straightforward implementation from before issue #16 that test_fast_paths keeps (the benchmark's "before")
from scanreg.geometry import neighbourhoods as reference_neighbourhoods
from test_fast_paths import reference_histogram3p

load_all()


class ReferenceHistogram3P:
    """The reference as a descriptor stage, for the coarse stage."""

    def __init__(self, params):
        self.p = params

    def compute(self, cloud, keypoints, spacing):
        return reference_histogram3p(self.p, cloud, keypoints, spacing)


# ------------------------------------------------------------------ the real case
@pytest.fixture(scope="module")
def bunny():
    """bun045 -> bun000 sampled at the default 20 000 points, the source under a random pose, and the thinned
    target the default coarse stage works on (voxel 4 spacings) with its uniform keypoints."""
    from scanreg.stages.coarse.thinning import downsampled

    folder = shared("stanford_bunny")
    poses = read_stanford_conf(folder / "bun.conf")
    P = random_pose(np.random.default_rng(3), 180, 0.1)
    T_gt = invert_T(poses["bun000.ply"]) @ poses["bun045.ply"] @ invert_T(P)
    tp, tn, _ = barycentric_sample(read_mesh(folder / "bun000.ply"), 20000, np.random.default_rng(0))
    sp_, sn, _ = barycentric_sample(read_mesh(folder / "bun045.ply"), 20000, np.random.default_rng(1))
    tgt, src = Cloud(tp, tn), Cloud(apply_T(P, sp_), sn @ P[:3, :3].T)
    sp = max(estimate_spacing(tp, np.random.default_rng(0)), estimate_spacing(sp_, np.random.default_rng(0)))
    thin, _, cc = downsampled(tgt, src, sp, RunContext(seed=0), 4 * sp, 12000, 2000)
    kp = SALIENCE.build({"name": "uniform"}).keypoints(thin, cc)
    return tgt, src, T_gt, sp, thin, kp, cc


def test_neighbour_search_equals_pykdtree_on_a_bunny_scan(bunny):
    """scipy's k-d tree gives the same neighbours, distances and order as the pykdtree search it replaced."""
    from scipy.spatial import cKDTree

    from scanreg.stages.descriptor import _knn

    *_, thin, kp, cc = bunny
    pts = thin.points
    for r, k, q, full in ((15 * cc, 256, pts[kp], True), (2 * cc, 64, pts, False)):
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
    want = reference_histogram3p(st.p, thin, kp, cc)
    assert len(kp) > 500 and got.shape == want.shape == (len(kp), 216)
    assert np.count_nonzero(want) > 0.3 * want.size  # real histograms, not mostly empty ones
    assert np.abs(got - want).max() < 1e-12


def test_histogram3p_equals_the_previous_implementation_without_normals(bunny):
    """A cloud without normals: with ``orient_normals=false`` as before; by default as the cloud with its
    estimated normals oriented (:func:`scanreg.geometry.orient_normals`)."""
    from scanreg.geometry import estimate_normals, orient_normals

    *_, thin, kp, cc = bunny
    bare = Cloud(thin.points)
    st = DESCRIPTOR.build({"name": "histogram3p", "orient_normals": False})
    got, want = st.compute(bare, kp[:100], cc), reference_histogram3p(st.p, bare, kp[:100], cc)
    assert np.count_nonzero(want) > 0.3 * want.size and np.abs(got - want).max() < 1e-12
    st = DESCRIPTOR.build({"name": "histogram3p"})
    oriented = Cloud(thin.points, orient_normals(thin.points, estimate_normals(thin.points)))
    got, want = st.compute(bare, kp[:100], cc), reference_histogram3p(st.p, oriented, kp[:100], cc)
    assert np.count_nonzero(want) > 0.3 * want.size and np.abs(got - want).max() < 1e-12


def test_coarse_registration_unchanged(bunny):
    """The default coarse stage with histogram3p: the same matches, inliers and transform, bit for bit, with
    the new implementation as with the reference; and the right answer."""
    tgt, src, T_gt, sp, *_ = bunny
    results = []
    for desc in (DESCRIPTOR.build({"name": "histogram3p"}), ReferenceHistogram3P(DESCRIPTOR.build({"name": "histogram3p"}).p)):
        helpers = {"salience": SALIENCE.build({"name": "uniform"}), "descriptor": desc,
                   "matcher": MATCHER.build({"name": "mutual_knn"})}
        res = build_coarse("lo_ransac", helpers).align(tgt, src, sp, RunContext(seed=0))
        results.append((res.T_target_source, res.metrics, res.trace))
    (T0, m0, tr0), (T1, m1, tr1) = results
    assert np.array_equal(tr0.matches_target, tr1.matches_target)
    assert np.array_equal(tr0.matches_source, tr1.matches_source)
    assert np.array_equal(tr0.ransac_inliers, tr1.ransac_inliers) and m0 == m1
    assert np.array_equal(T0, T1)
    rot, trans = transform_errors(T0, T_gt)
    assert rot < 1.1 and m0["coarse_inliers"] >= 40, (rot, m0)  # measured: 0.359 deg, 119 inliers
