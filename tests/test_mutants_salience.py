"""Known answers that kill the mutants of the salience measures (./run mutants, issue #38): the eigenvalue ratios
where an eigenvalue is zero, and eigenvalues clipped at zero where round-off makes them negative."""

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.stages.salience import eigen_features, measure_values

# eigenvalues (l1 <= l2 <= l3) of a line (0, 0, 1), of a point (all zero), of a generic patch and of an isotropic
# blob; the ratios are 0, not 0/0, where the denominator is 0
LAM = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 2.0, 4.0], [2.0, 2.0, 2.0]])
WANT = {"l1": [0, 0, 1, 2], "l2": [0, 0, 2, 2], "l3": [1, 0, 4, 2], "l1_l2": [0, 0, 0.5, 1], "l2_l3": [0, 0, 0.5, 1],
        "min_ratio": [0, 0, 0.5, 1]}


def test_measure_values_by_hand():
    for measure, want in WANT.items():
        assert np.array_equal(measure_values(LAM, measure), np.array(want, float)), measure


def test_eigenvalues_of_a_tilted_plane_are_clipped_at_zero():
    """Points (and their normals) on a tilted plane: the smallest eigenvalue of C_p and the two smallest of C_n are
    0 up to round-off, which makes eigvalsh return values down to about -1e-16 at about half the points; the
    features clip them to 0, so that a ratio is never negative."""
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.3, 0.5, 0.1]).as_matrix()
    pts = np.c_[rng.uniform(0, 10, (2000, 2)), np.zeros(2000)] @ R.T + [5.0, -3.0, 2.0]
    normals = np.tile(R[:, 2], (2000, 1))
    lp, ln, counts = eigen_features(pts, normals, 1.5, 64, False)
    assert (lp >= 0).all() and (ln >= 0).all()
    assert lp[:, 0].max() < 1e-12 and ln[:, :2].max() < 1e-12
    assert np.allclose(ln[:, 2], 1.0)  # every normal the same: C_n = n n^T
    assert (lp[:, 1] > 0.1).all() and counts.min() >= 10


def test_nms_sees_exactly_the_64_nearest_itself_included():
    """The default cap of the suppression, exactly: point 0 and 80 others on a ray at distances 1..80, all within
    the radius. Its 64 nearest are itself and the 63 closest others; a more salient point 63rd closest
    suppresses it, one 64th closest does not."""
    from scanreg.stages.salience import non_maximum_suppression

    pts = np.zeros((81, 3))
    pts[1:, 0] = np.arange(1, 81)
    for rank, kept in ((63, False), (64, True)):
        h = np.zeros(81)
        h[0], h[rank] = 1.0, 2.0
        assert (0 in non_maximum_suppression(pts, h, 100.0)) == kept, rank


def test_eigen_features_of_every_row_including_the_first_by_brute_force():
    """Rows 0, 1 and the last of a bumpy patch (every radius holding fewer than 64 points, so no cap), uniform and
    Gaussian weights (sigma = radius / 2), against the weighted covariance written out here; with a batch of 7
    rows the same values."""
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 6, (300, 2))
    pts = np.c_[xy, 0.3 * np.sin(xy[:, 0]) * np.cos(xy[:, 1])]
    radius = 0.9
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    assert (dist < radius).sum(axis=1).max() < 64
    for gaussian in (False, True):
        lp, _, counts = eigen_features(pts, None, radius, 64, gaussian)
        lp7, _, counts7 = eigen_features(pts, None, radius, 64, gaussian, batch=7)
        assert np.array_equal(lp, lp7) and np.array_equal(counts, counts7)
        for i in (0, 1, 299):
            nb = dist[i] < radius
            w = np.exp(-dist[i, nb] ** 2 / (2 * (radius / 2) ** 2)) if gaussian else np.ones(nb.sum())
            X = pts[nb] - w @ pts[nb] / w.sum()
            C = (X * w[:, None]).T @ X / w.sum()
            assert counts[i] == nb.sum()
            assert np.allclose(lp[i], np.linalg.eigvalsh(C), rtol=1e-9, atol=1e-15), (i, gaussian)
