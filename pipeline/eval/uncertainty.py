"""How sure the alignment is: the pose covariance of a point-to-plane registration, its degeneracy, and what it
means for each compared point's signed deviation (geometry core: imports no stage).

At the final pose, a pair (aligned source point ``p``, closest target point ``q``, target normal ``n``) has the
point-to-plane residual ``r = n . (p - q)``. A small rigid motion of the source about the centroid ``c`` of the
paired points, rotation vector ``w`` (radians) and translation ``t`` (input units), changes it by
``J x = ((p - c) x n) . w + n . t`` with ``x = (w, t)``. The fine stage's normal equations have the information
matrix ``H = J^T J``; with the residual variance ``s2 = sum r^2 / (N - 6)`` the pose covariance is
``C = s2 H^-1`` (Gauss-Newton, residuals independent and of equal variance). Reported:

- ``pose_sigma_rot_deg = sqrt(trace C_ww)`` in degrees: the RMS angle of the rotation error;
- ``pose_sigma_trans = sqrt(trace C_tt)`` in input units: the RMS length of the translation error of the centroid;
- ``pose_condition``: smallest over largest eigenvalue of ``H`` with the rotation scaled by the RMS radius of the
  pairs about ``c`` (so both parts are lengths): 1 when every direction is equally constrained, near 0 when
  some motion (sliding along a cylinder or a plane, turning a sphere) leaves the residuals unchanged;
- per point, the standard deviation of its signed deviation due to the pose, ``sqrt(J_i C J_i^T)``.

Neighbouring residuals of a real scan are correlated (shape differences, not only noise), which makes ``C`` an
optimistic lower bound; ``bootstrap_pose`` checks it by re-registering resampled sources.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PoseCovariance:
    cov: np.ndarray
    """6 x 6 covariance of ``(w [rad], t [input units])``, the motion about ``centre`` in the target frame."""
    centre: np.ndarray
    """Centroid of the paired points (target frame): the rotation's pivot and the point whose shift ``t`` is."""
    radius: float
    """RMS distance of the paired points from ``centre`` (input units): the length that scales rotations."""
    info_eigvals: np.ndarray
    """Eigenvalues of the scaled information matrix, ascending (dimensionless counts of pairs)."""
    info_eigvecs: np.ndarray
    """Their unit eigenvectors as columns: ``(w * radius, t)`` directions."""
    residual_sigma: float
    """Standard deviation of the point-to-plane residuals (input units)."""
    n_pairs: int

    @property
    def sigma_rot_deg(self) -> float:
        return float(np.degrees(np.sqrt(max(np.trace(self.cov[:3, :3]), 0.0))))

    @property
    def sigma_trans(self) -> float:
        return float(np.sqrt(max(np.trace(self.cov[3:, 3:]), 0.0)))

    @property
    def condition(self) -> float:
        lo, hi = self.info_eigvals[0], self.info_eigvals[-1]
        return float(max(lo, 0.0) / hi) if hi > 0 else 0.0

    def jacobian(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Rows ``((p - c) x n, n)``: how each point's signed deviation along ``n`` changes with ``(w, t)``."""
        return np.hstack([np.cross(points - self.centre, normals), normals])

    def point_sigma(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Standard deviation of each point's signed deviation along its target normal due to the pose (input
        units)."""
        J = self.jacobian(points, normals)
        return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", J, self.cov, J), 0.0))

    def mean_sigma(self, points: np.ndarray, normals: np.ndarray) -> float:
        """Standard deviation of the *mean* signed deviation of these points due to the pose (input units): the
        pose moves them together, so it does not shrink with their number."""
        j = self.jacobian(points, normals).mean(axis=0)
        return float(np.sqrt(max(j @ self.cov @ j, 0.0)))

    def free_directions(self, threshold: float) -> list[str]:
        """The motions whose scaled information is below ``threshold`` times the largest: ``'rotation about
        (x, y, z)'`` or ``'translation along (x, y, z)'`` (whichever part of the eigenvector dominates)."""
        out = []
        hi = self.info_eigvals[-1]
        for lam, v in zip(self.info_eigvals, self.info_eigvecs.T):
            if hi > 0 and lam >= threshold * hi:
                continue
            rot, tr = v[:3], v[3:]
            part, what = (rot, "rotation about") if np.linalg.norm(rot) >= np.linalg.norm(tr) else (tr, "translation along")
            d = part / np.linalg.norm(part)
            d = d if d[np.argmax(np.abs(d))] > 0 else -d
            out.append(f"{what} ({d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f})")
        return out

    def metrics(self) -> dict[str, float]:
        return {"pose_sigma_rot_deg": self.sigma_rot_deg, "pose_sigma_trans": self.sigma_trans,
                "pose_condition": self.condition, "pose_residual_sigma": self.residual_sigma,
                "pose_pairs": float(self.n_pairs)}


def pose_covariance(points: np.ndarray, closest: np.ndarray, normals: np.ndarray) -> PoseCovariance:
    """Pose covariance from the final pairs: aligned source ``points``, their ``closest`` target points and the
    target unit ``normals`` there (all N x 3, target frame, N >= 7)."""
    n = len(points)
    if n < 7:
        raise ValueError(f"pose covariance: {n} pair(s); at least 7 are needed")
    c = points.mean(axis=0)
    J = np.hstack([np.cross(points - c, normals), normals])
    r = np.einsum("ij,ij->i", points - closest, normals)
    s2 = float(r @ r) / (n - 6)
    H = J.T @ J
    L = float(np.sqrt(np.mean(np.sum((points - c) ** 2, axis=1))))
    L = L if L > 0 else 1.0
    D = np.diag([1 / L] * 3 + [1.0] * 3)  # (w L, t) = D^-1 x: both parts are lengths
    Hs = D @ H @ D
    lam, vec = np.linalg.eigh(Hs)
    # C = s2 H^-1 = s2 D Hs^-1 D, the inverse through the eigen decomposition (a free direction gets a huge
    # but finite variance instead of a failed inversion)
    inv = vec @ np.diag(1.0 / np.maximum(lam, lam[-1] * 1e-15 if lam[-1] > 0 else 1e-300)) @ vec.T
    cov = s2 * D @ inv @ D
    return PoseCovariance(cov, c, L, lam, vec, float(np.sqrt(s2)), n)


def pairs_covariance(pairs) -> PoseCovariance | None:
    """:func:`pose_covariance` of a fine stage's final pairs (``source``, ``target``, ``normals`` arrays), on the
    pairs whose values are all finite (a degenerate face's normal is NaN, and one NaN row stopped the eigen
    decomposition: an internal error); None without normals or with fewer than 7 such pairs."""
    if pairs is None or pairs.normals is None or len(pairs.source) < 7:
        return None
    src, tgt, nrm = pairs.source, pairs.target, pairs.normals
    finite = np.isfinite(src).all(axis=1) & np.isfinite(tgt).all(axis=1) & np.isfinite(nrm).all(axis=1)
    if not finite.all():
        src, tgt, nrm = src[finite], tgt[finite], nrm[finite]
    return pose_covariance(src, tgt, nrm) if len(src) >= 7 else None


def degeneracy_warning(pc: PoseCovariance, threshold: float) -> str | None:
    """One line naming the unconstrained motions when ``pose_condition`` is below ``threshold``, else None."""
    if pc.condition >= threshold:
        return None
    free = pc.free_directions(threshold)
    return (f"pose poorly constrained (pose_condition {pc.condition:.2g} < {threshold:g}): the surface lets the "
            f"source slide; free: {'; '.join(free)} (through {np.array2string(pc.centre, precision=3)})")


def relative_motion(T: np.ndarray, T_ref: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """Rotation angle (degrees) and shift of ``centre`` (input units) of ``T`` relative to ``T_ref``, both
    target <- source: the quantities whose RMS ``pose_sigma_rot_deg`` / ``pose_sigma_trans`` predict."""
    D = T @ np.linalg.inv(T_ref)
    ang = float(np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1.0, 1.0))))
    shift = float(np.linalg.norm(D[:3, :3] @ centre + D[:3, 3] - centre))
    return ang, shift


def bootstrap_spread(Ts: list[np.ndarray], T_ref: np.ndarray, centre: np.ndarray) -> dict[str, float]:
    """RMS rotation angle (degrees) and RMS centre shift (input units) of re-registered poses ``Ts`` about
    ``T_ref``: the bootstrap counterparts of ``pose_sigma_rot_deg`` and ``pose_sigma_trans``."""
    mot = np.array([relative_motion(T, T_ref, centre) for T in Ts])
    return {"pose_bootstrap_rot_deg": float(np.sqrt(np.mean(mot[:, 0] ** 2))),
            "pose_bootstrap_trans": float(np.sqrt(np.mean(mot[:, 1] ** 2))),
            "pose_bootstrap_runs": float(len(Ts))}
