"""Known answers that kill the mutants of the rigid-transform maths (./run mutants, issue #38): Horn's fit with
weights, the fit with normals and the batched fit against an SVD written here, rotation angles in closed form near
0 and 180 degrees, the inverse."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scanreg.geometry import (apply_T, horn_quaternion, invert_T, kabsch_batch, make_T, rigid_points_normals,
                              rotation_angle_deg, transform_errors)


def svd_fit(P0, P1, w=None, N0=None, N1=None, wn=0.0):
    """argmin over rigid (R, t) of sum w_i |R p1_i + t - p0_i|^2 + wn sum |R n1 - n0|^2 (SVD of the weighted
    cross-covariance, reflection corrected)."""
    w = np.ones(len(P0)) if w is None else np.asarray(w, float)
    m1, m0 = w @ P1 / w.sum(), w @ P0 / w.sum()
    H = ((P1 - m1) * w[:, None]).T @ (P0 - m0)
    if N0 is not None:
        H = H + wn * N1.T @ N0
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, m0 - R @ m1
    return T


def case(n, seed, noise=0.05):
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 5)
    P1 = rng.normal(size=(n, 3)) * [3.0, 2.0, 1.0] + [10.0, -4.0, 2.0]
    return apply_T(T, P1) + rng.normal(scale=noise, size=(n, 3)), P1, rng


def test_weighted_horn_is_the_weighted_least_squares_fit():
    P0, P1, rng = case(40, 1)
    w = rng.uniform(0.1, 3.0, 40)
    assert np.allclose(horn_quaternion(P0, P1, w), svd_fit(P0, P1, w), atol=1e-10)
    assert np.allclose(horn_quaternion(P0, P1), svd_fit(P0, P1), atol=1e-10)
    # integer weights are repeated points
    k = rng.integers(1, 4, 40)
    assert np.allclose(horn_quaternion(P0, P1, k.astype(float)),
                       horn_quaternion(np.repeat(P0, k, axis=0), np.repeat(P1, k, axis=0)), atol=1e-10)
    assert np.allclose(horn_quaternion(P0[:3], P1[:3]), svd_fit(P0[:3], P1[:3]), atol=1e-10)  # 3 are enough
    with pytest.raises(ValueError, match="at least 3"):
        horn_quaternion(P0[:2], P1[:2])
    with pytest.raises(ValueError, match="at least 3"):
        horn_quaternion(P0[:5], P1[:4])


def test_fit_with_normals_is_the_least_squares_fit_of_points_and_normals():
    P0, P1, rng = case(30, 2, noise=0.2)
    T = horn_quaternion(P0, P1)
    N1 = rng.normal(size=(30, 3))
    N1 /= np.linalg.norm(N1, axis=1, keepdims=True)
    N0 = N1 @ Rotation.from_rotvec([0.05, -0.03, 0.02]).as_matrix().T @ T[:3, :3].T  # normals a little off
    for wn in (0.0, 0.5, 20.0):
        got = rigid_points_normals(P0, P1, N0, N1, wn)
        assert np.allclose(got, svd_fit(P0, P1, N0=N0, N1=N1, wn=wn), atol=1e-10), wn
    assert np.allclose(rigid_points_normals(P0, P1), svd_fit(P0, P1), atol=1e-10)
    # normals on one side only: the points-only fit
    assert np.allclose(rigid_points_normals(P0, P1, N0, None, 20.0), svd_fit(P0, P1), atol=1e-10)
    assert np.allclose(rigid_points_normals(P0, P1, None, N1, 20.0), svd_fit(P0, P1), atol=1e-10)
    assert np.abs(rigid_points_normals(P0, P1, N0, N1, 20.0) - svd_fit(P0, P1)).max() > 1e-3


def test_kabsch_batch_fits_each_triple_and_never_reflects():
    rng = np.random.default_rng(3)
    B = 20
    src = rng.normal(size=(B, 3, 3)) * 2 + 5
    tgt = np.stack([apply_T(make_T(Rotation.random(random_state=i).as_matrix(), rng.normal(size=3)), s)
                    for i, s in enumerate(src)]) + rng.normal(scale=0.1, size=(B, 3, 3))
    tgt[0] = src[0] * [1.0, 1.0, -1.0]  # a mirror image: the best rotation, not the reflection
    Ts = kabsch_batch(tgt, src)
    for b in range(B):
        assert np.allclose(Ts[b], svd_fit(tgt[b], src[b]), atol=1e-10), b
        assert np.linalg.det(Ts[b, :3, :3]) == pytest.approx(1.0)
    assert np.array_equal(Ts[:, 3], np.tile([0.0, 0, 0, 1], (B, 1)))


@pytest.mark.parametrize("deg", [0.0, 1e-6, 0.5, 37.0, 90.0, 179.9, 180.0])
def test_rotation_angle_in_closed_form(deg):
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    R = Rotation.from_rotvec(axis * np.radians(deg)).as_matrix()
    assert rotation_angle_deg(R) == pytest.approx(deg, abs=1e-9)
    T_gt = make_T(Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), [1.0, 2.0, 3.0])
    T_est = make_T(R, np.zeros(3)) @ T_gt
    T_est[:3, 3] = T_gt[:3, 3] + [0.3, 0.0, -0.4]
    rot, trans = transform_errors(T_est, T_gt)
    assert rot == pytest.approx(deg, abs=1e-9) and trans == pytest.approx(0.5)


def test_inverse_and_application():
    P0, P1, _ = case(10, 4)
    T = horn_quaternion(P0, P1)
    assert np.allclose(invert_T(T) @ T, np.eye(4), atol=1e-12) and np.allclose(T @ invert_T(T), np.eye(4), atol=1e-12)
    assert np.allclose(apply_T(T, P1), P1 @ T[:3, :3].T + T[:3, 3])
    assert np.allclose(apply_T(invert_T(T), apply_T(T, P1)), P1, atol=1e-12)
