"""Fast paths of issue #16 against the straightforward code they replaced (kept here verbatim as references):
histogram3p's votes (per-plane matrix products over blocks of keypoints) to 1e-12, and voxel_representatives (one
int64 key per voxel, bincount sums) bit for bit."""

import numpy as np
import pytest

from scanreg.types import RunContext as Context, to_abs
from scanreg.geometry import Cloud, barycentric_sample
from scanreg.io import read_mesh
from scanreg.geometry import estimate_spacing
from scanreg.stages.registry import DESCRIPTOR, SALIENCE, load_all

load_all()


def reference_histogram3p(p, cloud: Cloud, keypoints: np.ndarray, spacing: float) -> np.ndarray:
    """The implementation before issue #16 (24 bincount scatters over every vote), unchanged."""
    from scanreg.geometry import estimate_normals
    from scanreg.stages.descriptor import local_frames
    from scanreg.geometry import neighbourhoods

    u, s = p.distances, spacing
    R = to_abs(p.radius, u, s)
    pts = cloud.points
    nrm = cloud.normals if cloud.normals is not None else estimate_normals(pts)
    frames = local_frames(pts, cloud.normals, keypoints, to_abs(p.frame_radius, u, s))
    j, d, valid = neighbourhoods(pts, R, p.max_neighbors, pts[keypoints])
    used = np.unique(j[valid])
    _, _, vd = neighbourhoods(pts, to_abs(p.density_radius, u, s), 64, pts[used])
    dens = np.zeros(len(pts))
    dens[used] = vd.sum(axis=1)
    w = np.where(valid, (1.0 - np.minimum(d, R) / R) / np.maximum(dens[j], 1.0), 0.0)
    L = np.einsum("nkj,nij->nki", pts[j] - pts[keypoints][:, None, :], frames)
    Ln = np.einsum("nkj,nij->nki", nrm[j], frames)
    n = len(keypoints)
    hist = np.zeros(n * 216)
    rows = np.repeat(np.arange(n), j.shape[1]).reshape(j.shape)
    for plane, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        ua = (L[:, :, a] + R) / (2 * R / 3) - 0.5
        ub = (L[:, :, b] + R) / (2 * R / 3) - 0.5
        ang = np.arctan2(Ln[:, :, b], Ln[:, :, a])
        uo = (ang + np.pi) / (2 * np.pi / 8) - 0.5
        ia, ib, io = np.floor(ua).astype(int), np.floor(ub).astype(int), np.floor(uo).astype(int)
        fa, fb, fo = ua - ia, ub - ib, uo - io
        for da, wa in ((0, 1 - fa), (1, fa)):
            for db, wb in ((0, 1 - fb), (1, fb)):
                ca, cb = ia + da, ib + db
                inside = valid & (ca >= 0) & (ca < 3) & (cb >= 0) & (cb < 3)
                for do, wo in ((0, 1 - fo), (1, fo)):
                    co = (io + do) % 8
                    wt = w * wa * wb * wo
                    m = inside & (wt > 0)
                    flat = (((rows[m] * 3 + plane) * 3 + ca[m]) * 3 + cb[m]) * 8 + co[m]
                    hist += np.bincount(flat, weights=wt[m], minlength=n * 216)
    out = hist.reshape(n, 216)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(norm > 0, norm, 1.0)


@pytest.fixture(scope="module")
def case():
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    p, n, _ = barycentric_sample(m, 6000, np.random.default_rng(5))
    cloud = Cloud(p, n)
    sp = estimate_spacing(p, np.random.default_rng(0))
    kp = SALIENCE.build({"name": "uniform", "voxel": 6.0}).keypoints(cloud, sp)
    return cloud, kp, sp


@pytest.mark.parametrize("params", [{}, {"radius": 8.0, "max_neighbors": 64, "frame_radius": 5.0}])
def test_histogram3p_equals_the_reference_implementation(case, params):
    cloud, kp, sp = case
    st = DESCRIPTOR.build({"name": "histogram3p", **params})
    got = st.compute(cloud, kp, sp)
    want = reference_histogram3p(st.p, cloud, kp, sp)
    assert len(kp) > 100 and got.shape == want.shape == (len(kp), 216)
    assert np.count_nonzero(want) > 0.3 * want.size  # real histograms, not mostly empty ones
    assert np.abs(got - want).max() < 1e-12


def test_histogram3p_equals_the_reference_without_normals(case):
    """Estimated normals (and, with ``orient_normals=false``, frames oriented by the mean offset) take the same
    path in both."""
    cloud, kp, sp = case
    bare = Cloud(cloud.points)
    st = DESCRIPTOR.build({"name": "histogram3p", "radius": 10.0, "orient_normals": False})
    assert np.abs(st.compute(bare, kp[:80], sp) - reference_histogram3p(st.p, bare, kp[:80], sp)).max() < 1e-12


def reference_voxel_representatives(points: np.ndarray, voxel: float) -> np.ndarray:
    """The implementation before issue #16 (np.unique over rows, np.add.at), unchanged."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv, points)
    centroids = sums / counts[:, None]
    d = np.linalg.norm(points - centroids[inv], axis=1)
    order = np.lexsort((d, inv))
    first = np.ones(len(order), bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return np.sort(order[first])


@pytest.mark.parametrize("n, voxel", [(20000, 0.05), (3000, 0.7), (7, 10.0)])
def test_voxel_representatives_equal_the_reference(n, voxel):
    from scanreg.geometry import voxel_representatives

    rng = np.random.default_rng(n)
    pts = rng.normal(size=(n, 3)) * [1.0, 3.0, 0.2] + [5.0, -2.0, 0.0]
    got, want = voxel_representatives(pts, voxel), reference_voxel_representatives(pts, voxel)
    assert len(want) > (1 if n > 7 else 0) and np.array_equal(got, want)
    # centroid ties broken the same way: a grid of duplicated points
    grid = np.repeat(np.stack(np.meshgrid(*[np.arange(4.0)] * 3), -1).reshape(-1, 3), 2, axis=0)
    assert np.array_equal(voxel_representatives(grid, 2.0), reference_voxel_representatives(grid, 2.0))


@pytest.mark.parametrize("voxel", [0.05, 0.7, 1e-17])
def test_voxel_count_is_the_number_of_representatives(voxel):
    """The thinning loop chooses its voxel by counts alone; each count is what the representatives would number
    (the last voxel: a grid too fine for a 62-bit cell index, counted over rows)."""
    from scanreg.geometry import voxel_count, voxel_representatives

    pts = np.random.default_rng(3).normal(size=(5000, 3)) * [1.0, 3.0, 0.2]
    assert voxel_count(pts, voxel) == len(reference_voxel_representatives(pts, voxel)) == \
        len(voxel_representatives(pts, voxel)) > 1


@pytest.mark.parametrize("voxel", [0.01, 0.3, 2.0])
def test_occupied_cells_and_counts_equal_numpy_unique(voxel):
    """occupied_cells marks a grid of few cells instead of sorting (and sorts a grid of many): both give what
    np.unique gives, and voxel_count and distinct_count count what it counts."""
    from scanreg.geometry.voxels import distinct_count, occupied_cells, voxel_cells, voxel_count

    pts = np.random.default_rng(8).normal(size=(4000, 3)) * [1.0, 3.0, 0.2]
    flat, _, span = voxel_cells(pts, voxel, margin=1)
    want = np.unique(flat, return_inverse=True, return_counts=True)
    dense = np.prod(span) <= 4 * len(flat)
    assert dense == (voxel > 0.1)  # both paths taken
    got = occupied_cells(flat, span)
    assert all(np.array_equal(g, w) and g.dtype == w.dtype for g, w in zip(got, want))
    assert voxel_count(pts, voxel) == len(np.unique(voxel_cells(pts, voxel)[0])) == \
        distinct_count(voxel_cells(pts, voxel)[0])
    assert distinct_count(np.array([3, 3, 1, 7, 1], np.int64)) == 3 and distinct_count(np.zeros(0, np.int64)) == 0


def test_coarse_thinning_keeps_min_points_and_caps_max_points():
    """The coarse stage's voxel thinning (stages/coarse/thinning.py ``downsampled``): a sparse pair is left as it is, the
    thinner cloud keeps at least ``min_points`` (the voxel shrinks), and ``max_points`` bounds a dense one."""
    from scanreg.stages.coarse.thinning import downsampled

    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    dense, sparse = (Cloud(*barycentric_sample(m, n, np.random.default_rng(n))[:2]) for n in (40_000, 3_000))
    ctx = Context(seed=0, run_dir=None)
    sp = estimate_spacing(dense.points, np.random.default_rng(0))
    t, s, c = downsampled(dense, sparse, sp, ctx, 4 * sp, 12000, 3000)
    assert t is dense and s is sparse and c == sp  # 3 000 points: not thinned at all, the spacing as given
    t, s, c = downsampled(dense, dense, sp, ctx, 4 * sp, None, None)
    n4 = t.n_points
    assert n4 < dense.n_points // 2 and c > sp  # the plain 4-spacing voxel
    # by the definition, written here: one point per occupied voxel of edge 4 spacings, the one nearest the
    # centroid of that voxel's points; and the spacing the thinned pair has (median nearest-neighbour distance)
    from scipy.spatial import cKDTree

    keys = np.floor((dense.points - dense.points.min(axis=0)) / (4 * sp)).astype(np.int64)
    _, voxel_of = np.unique(keys, axis=0, return_inverse=True)
    voxel_of = voxel_of.ravel()
    expected = []
    for v in range(voxel_of.max() + 1):
        members = np.flatnonzero(voxel_of == v)
        centroid = dense.points[members].mean(axis=0)
        expected.append(members[np.argmin(np.linalg.norm(dense.points[members] - centroid, axis=1))])
    assert np.array_equal(t.points, dense.points[np.sort(expected)])
    nn = cKDTree(t.points).query(t.points, k=2)[0][:, 1]
    assert c == pytest.approx(np.median(nn), rel=0.05)
    t, s, c = downsampled(dense, dense, sp, ctx, 4 * sp, None, 20000)
    assert min(t.n_points, s.n_points) >= 0.8 * 20000 and t.n_points > n4  # shrunk towards min_points
    t, s, c = downsampled(dense, dense, sp, ctx, sp, 5000, None)
    assert max(t.n_points, s.n_points) <= 1.25 * 5000  # grown towards max_points


def test_apply_T_gives_what_the_transposed_view_gave():
    """apply_T multiplies by a contiguous copy of R^T (so that NumPy uses BLAS): the same numbers, bit for bit,
    as the product with the transposed view, and as the rotation applied point by point."""
    from scipy.spatial.transform import Rotation

    from scanreg.geometry import apply_T, make_T, rotate_normals

    rng = np.random.default_rng(7)
    p = rng.normal(size=(20000, 3)) * 100.0
    T = make_T(Rotation.random(random_state=3).as_matrix(), rng.normal(size=3))
    assert np.array_equal(apply_T(T, p), p @ T[:3, :3].T + T[:3, 3])
    assert np.array_equal(rotate_normals(T, p), p @ T[:3, :3].T)
    assert np.allclose(apply_T(T, p[:5]), [T[:3, :3] @ x + T[:3, 3] for x in p[:5]], rtol=0, atol=1e-12)


def test_estimate_spacing_is_the_median_nearest_neighbour_distance():
    """By brute force on a cloud with a duplicated point (distance 0, left out) and on a seeded subset."""
    from scipy.spatial.distance import cdist

    from scanreg.geometry import estimate_spacing

    pts = np.random.default_rng(5).normal(size=(800, 3)) * [1.0, 2.0, 0.1]
    pts = np.vstack([pts, pts[:1]])
    D = cdist(pts, pts)
    np.fill_diagonal(D, np.inf)
    nn = D.min(axis=1)
    assert estimate_spacing(pts, np.random.default_rng(0)) == float(np.median(nn[nn > 0]))
    idx = np.random.default_rng(1).choice(len(pts), size=300, replace=False)
    sub = nn[idx]
    assert estimate_spacing(pts, np.random.default_rng(1), n=300) == float(np.median(sub[sub > 0]))
