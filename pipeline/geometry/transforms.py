"""Rigid transforms: building, applying, inverting and comparing them, and the closed-form least-squares fits.

A transform ``T_a_b`` is a 4x4 matrix mapping points given in frame ``b`` into frame ``a`` (``p_a = R p_b + t``).
Functions that relate two point sets take ``(target, source)`` in that order and return ``T_target_source``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.geometry.containers import Cloud, Geometry, Mesh


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def apply_T(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    # R^T as a contiguous array: NumPy hands (N, 3) @ (3, 3) to BLAS only then (a transposed view takes its own
    # loop, an order of magnitude slower on large clouds), with the same result
    return pts @ np.ascontiguousarray(T[:3, :3].T) + T[:3, 3]


def rotate_normals(T: np.ndarray, normals: np.ndarray | None) -> np.ndarray | None:
    return None if normals is None else normals @ np.ascontiguousarray(T[:3, :3].T)


def transform_geometry(T: np.ndarray, g: Geometry) -> Geometry:
    if isinstance(g, Mesh):
        return Mesh(apply_T(T, g.vertices), g.faces, g.source)
    return Cloud(apply_T(T, g.points), rotate_normals(T, g.normals), g.source, dict(g.extra))


def invert_T(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(centre, axes)``: the points' centroid and their principal axes as the columns of a rotation (the
    smallest spread first; the sign of the last flipped when needed for determinant +1). The frame follows the
    points in any pose, up to the axes' signs."""
    centre = points.mean(axis=0)
    centred = points - centre
    axes = np.linalg.eigh(centred.T @ centred)[1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return centre, axes


def half_turns(points: np.ndarray) -> list[np.ndarray]:
    """The three half-turns (4x4, rotations by 180 degrees) about the points' principal axes through their centroid
    (:func:`principal_axes`): the poses a nearly symmetric shape (a long bone, a box-like part) fits almost as
    well as its own, whichever the axes' signs."""
    centre, axes = principal_axes(np.asarray(points, float))
    out = []
    for k in range(3):
        a = axes[:, k]
        H = np.eye(4)
        H[:3, :3] = 2.0 * np.outer(a, a) - np.eye(3)
        H[:3, 3] = centre - H[:3, :3] @ centre
        out.append(H)
    return out


def principal_box_diagonal(points: np.ndarray) -> float:
    """The diagonal of the points' bounding box along their principal axes (:func:`principal_axes`): unlike
    :func:`~scanreg.geometry.bbox_diagonal`, the same however the points are rotated or moved (up to rounding;
    a shape without unique principal axes, such as a sphere or a cube, gets the box of whichever axes rounding
    picks). 0 for fewer than two points."""
    points = np.asarray(points, float)
    if len(points) < 2:
        return 0.0
    centre, axes = principal_axes(points)
    along = (points - centre) @ axes
    return float(np.linalg.norm(along.max(axis=0) - along.min(axis=0)))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (robust near 0 and 180)."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(s, np.clip(c, -1.0, 1.0))))


def transform_errors(T_est: np.ndarray, T_gt: np.ndarray, at: np.ndarray | None = None) -> tuple[float, float]:
    """(rotation error in degrees, translation error in input units) of ``T_est`` against ``T_gt``. The
    translation error is how far the two move the origin apart, or with ``at`` that point (where the scan is, e.g.
    its centre: then it does not depend on where its frame has its origin, and a scan far from the origin does
    not see a rotation error of 1e-8 rad as 1e-8 times its distance)."""
    dR = T_est[:3, :3] @ T_gt[:3, :3].T
    if at is None or not np.any(at):
        return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))
    moved = (T_est[:3, :3] - T_gt[:3, :3]) @ np.asarray(at, float) + (T_est[:3, 3] - T_gt[:3, 3])
    return rotation_angle_deg(dR), float(np.linalg.norm(moved))


def random_pose(rng: np.random.Generator, max_angle_deg: float, max_translation: float,
                min_angle_deg: float = 0.0) -> np.ndarray:
    """A random rigid transform: rotation about a uniformly random axis by an angle uniform in
    [min_angle_deg, max_angle_deg] (``max_angle_deg >= 180``: a rotation uniform over SO(3)), translation a
    uniformly random direction times a length uniform in [0, max_translation]."""
    if max_angle_deg >= 180.0:
        R = Rotation.from_quat(_unit(rng.normal(size=4))).as_matrix()
    else:
        axis = _unit(rng.normal(size=3))
        R = Rotation.from_rotvec(axis * np.radians(rng.uniform(min_angle_deg, max_angle_deg))).as_matrix()
    t = _unit(rng.normal(size=3)) * rng.uniform(0.0, max_translation)
    return make_T(R, t)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def horn_quaternion(target: np.ndarray, source: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform ``T_target_source`` by Horn's closed form (1987).

    With centred point sets and the cross-covariance ``S = sum w (s - s̄)(t - t̄)^T``, the rotation is the unit
    quaternion of the largest eigenvalue of the symmetric 4x4 matrix ``Q(S)``; then ``t = t̄ - R s̄``.
    """
    if len(target) != len(source) or len(source) < 3:
        raise ValueError("horn_quaternion needs at least 3 paired points")
    # means and sums as BLAS products (a short-axis reduction of (N, 3) arrays is slow in NumPy)
    if weights is None:
        one = np.full(len(source), 1.0 / len(source))
        mu_s, mu_t = one @ source, one @ target
        S = (source - mu_s).T @ (target - mu_t)
    else:
        w = np.asarray(weights, dtype=np.float64)
        wsum = w.sum()
        mu_s = (w @ source) / wsum
        mu_t = (w @ target) / wsum
        S = ((source - mu_s) * w[:, None]).T @ (target - mu_t)
    R = rotation_from_cross_covariance(S)
    return make_T(R, mu_t - R @ mu_s)


def rotation_from_cross_covariance(S: np.ndarray) -> np.ndarray:
    """Horn's quaternion solution: the rotation R maximising trace(R S) for S = sum (s_i)(t_i)^T."""
    (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = S
    Q = np.array(
        [
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ]
    )
    evals, evecs = np.linalg.eigh(Q)
    q0, qx, qy, qz = evecs[:, np.argmax(evals)]
    return np.array(
        [
            [q0 * q0 + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - q0 * qz), 2 * (qx * qz + q0 * qy)],
            [2 * (qy * qx + q0 * qz), q0 * q0 - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - q0 * qx)],
            [2 * (qz * qx - q0 * qy), 2 * (qz * qy + q0 * qx), q0 * q0 - qx * qx - qy * qy + qz * qz],
        ]
    )


def rigid_points_normals(target, source, target_normals=None, source_normals=None, normal_weight: float = 1.0):
    """``T_target_source`` minimising sum |R s + t - t_i|^2 + w |R n_s - n_t|^2 (closed form: the normals
    only add ``w sum n_s n_t^T`` to the cross-covariance; t from the centroids)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    S = (source - mu_s).T @ (target - mu_t)
    if target_normals is not None and source_normals is not None and normal_weight > 0:
        S = S + normal_weight * source_normals.T @ target_normals
    R = rotation_from_cross_covariance(S)
    return make_T(R, mu_t - R @ mu_s)


def kabsch_batch(target: np.ndarray, source: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Batched least-squares rigid transforms: ``target, source`` (B, k, 3) -> ``T_target_source`` (B, 4, 4);
    ``weights`` (B, k), each row with a positive sum, weigh the pairs."""
    if weights is None:
        mu_s, mu_t = source.mean(axis=1, keepdims=True), target.mean(axis=1, keepdims=True)
        H = np.einsum("bki,bkj->bij", source - mu_s, target - mu_t)
    else:
        w = weights / weights.sum(axis=1, keepdims=True)
        mu_s, mu_t = np.einsum("bk,bki->bi", w, source)[:, None], np.einsum("bk,bki->bi", w, target)[:, None]
        H = np.einsum("bk,bki,bkj->bij", w, source - mu_s, target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", Vt, U)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    R = np.einsum("bji,bjk,blk->bil", Vt, D, U)
    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_t[:, 0] - np.einsum("bij,bj->bi", R, mu_s[:, 0])
    T[:, 3, 3] = 1.0
    return T


def kabsch_svd(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform ``T_target_source`` by SVD (Kabsch/Umeyama), for cross-checks."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    H = (source - mu_s).T @ (target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, mu_t - R @ mu_s)
