"""Seeded poses and perturbations that make harder cases out of any provider's inputs (random initial pose,
crop, noise, outliers, a sparser source)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from scanreg.geometry import Cloud, Mesh, barycentric_sample, bbox_diagonal, estimate_normals, points_of, random_pose
from scanreg.types import Problem


@dataclass
class PoseParams:
    max_angle_deg: float = 180.0
    """Largest rotation of the random initial pose of the source, in degrees (>= 180: any rotation)."""
    max_translation: float = 0.5
    """Largest translation of the random initial pose, as a share of the bounding-box diagonal."""
    pose_seed: int = 0
    """Seed of the random initial pose; the same seed repeats the same case."""
    min_angle_deg: float = 0.0
    """Smallest rotation angle of the random initial pose (degrees; ignored for any rotation)."""
    rotate_about: str = "origin"
    """Centre of the random rotation: ``origin`` of the coordinates, or the ``centroid`` of the source (so that
    a small angle is a small displacement, e.g. to start ICP near the truth)."""

    def check(self):
        if self.rotate_about not in ("origin", "centroid"):
            raise ValueError(f"rotate_about must be origin or centroid, got '{self.rotate_about}'")
        if not 0 <= self.min_angle_deg <= self.max_angle_deg:
            raise ValueError(f"min_angle_deg must be in [0, max_angle_deg], got {self.min_angle_deg}")

    def pose(self, salt: int, source_points: np.ndarray, diagonal: float) -> np.ndarray:
        """The seeded random pose ``P`` applied to the source (its ground truth becomes ``T_gt @ inv(P)``)."""
        P = random_pose(np.random.default_rng([self.pose_seed, salt]), self.max_angle_deg,
                        self.max_translation * diagonal, self.min_angle_deg)
        if self.rotate_about == "centroid":
            c = source_points.mean(axis=0)
            P[:3, 3] += c - P[:3, :3] @ c
        return P


@dataclass
class PerturbParams(PoseParams):
    """Harder cases made from any provider's inputs, seeded (``perturb_seed``): the perturbed roles (``perturb``)
    become point clouds (a mesh is first sampled, area-weighted), then cropped, noised and given outliers; the
    source can be made sparser than the target (``density_ratio``). All off (the defaults): the inputs as read."""

    perturb: str = "source"
    """Which input the noise, outliers and crop apply to: ``source``, ``target`` or ``both``."""
    add_noise: float = 0.0
    """Standard deviation of the Gaussian noise added to every coordinate of each perturbed point, as a share of
    the target's bounding-box diagonal (0.01 = 1 % of the diagonal)."""
    add_outliers: float = 0.0
    """Share (0 to < 1) of each perturbed cloud's points that are outliers after perturbing: points drawn
    uniformly in its bounding box are added so that they make up this share (0.5: as many outliers as surface
    points)."""
    density_ratio: float = 1.0
    """The source gets ``1 / density_ratio`` as many points as the target (>= 1; 8: eight times sparser): a
    source mesh is sampled with ``cloud_points / density_ratio`` points, a source cloud keeps that share of its
    points (seeded random subset)."""
    crop: float = 1.0
    """Share (0.05 to 1) of each perturbed cloud's points kept on one side of a random plane (a partial scan);
    1: no crop."""
    cloud_points: int = 20000
    """Points sampled on a perturbed mesh (area-weighted barycentric, seeded), before crop and outliers; match it
    to ``sampler.n_points`` so that an unperturbed target and the source are equally dense."""
    perturb_seed: int = 0
    """Seed of the perturbations (sampling, crop plane, noise, outliers); the same seed repeats them exactly."""

    def check(self):
        super().check()
        if self.perturb not in ("source", "target", "both"):
            raise ValueError(f"perturb must be source, target or both, got '{self.perturb}'")
        if not 0 <= self.add_noise <= 0.2:
            raise ValueError(f"add_noise must be in [0, 0.2] (share of the diagonal), got {self.add_noise}")
        if not 0 <= self.add_outliers < 1:
            raise ValueError(f"add_outliers must be in [0, 1), got {self.add_outliers}")
        if not self.density_ratio >= 1:
            raise ValueError(f"density_ratio must be >= 1, got {self.density_ratio}")
        if not 0.05 <= self.crop <= 1:
            raise ValueError(f"crop must be in [0.05, 1], got {self.crop}")
        if self.cloud_points < 10:
            raise ValueError(f"cloud_points must be >= 10, got {self.cloud_points}")

    def perturbing(self) -> bool:
        return self.add_noise > 0 or self.add_outliers > 0 or self.density_ratio > 1 or self.crop < 1


def perturb_inputs(inputs: Problem, p: PerturbParams) -> Problem:
    """``inputs`` with the perturbations of ``p`` applied (unchanged when none is set). The ground truth and
    landmarks stay valid: nothing is moved as a whole. Logs ``perturb_<role>_points``, ``..._outliers``,
    ``..._crop_kept`` and the noise in input units (``perturb_noise_std``) in ``info``."""
    if not p.perturbing():
        return inputs
    info = dict(inputs.info)
    diagonal = bbox_diagonal(points_of(inputs.target))
    info["perturb_noise_std"] = p.add_noise * diagonal
    roles = {"source": inputs.source, "target": inputs.target}
    for salt, role in enumerate(("source", "target")):
        perturbed = p.perturb in (role, "both")
        sparser = role == "source" and p.density_ratio > 1
        if not (perturbed or sparser):
            continue
        rng = np.random.default_rng([p.perturb_seed, 909, salt])
        g = roles[role]
        if isinstance(g, Mesh):
            n = p.cloud_points if role == "target" else max(10, int(round(p.cloud_points / p.density_ratio)))
            pts, nrm, _ = barycentric_sample(g, n, rng)
            cloud = Cloud(pts, nrm, g.source)
        else:
            cloud = g
            if sparser:
                k = max(10, int(round(cloud.n_points / p.density_ratio)))
                cloud = cloud.subset(np.sort(rng.choice(cloud.n_points, size=k, replace=False)))
        if perturbed:
            cloud, kept, n_out = perturb_cloud(cloud, p.add_noise * diagonal, p.add_outliers, p.crop, rng)
            info[f"perturb_{role}_crop_kept"] = kept
            info[f"perturb_{role}_outliers"] = n_out
        info[f"perturb_{role}_points"] = cloud.n_points
        roles[role] = Cloud(cloud.points, cloud.normals, f"{g.source or role} (perturbed)", cloud.extra)
    labels = inputs.target_labels if roles["target"] is inputs.target else None
    return Problem(roles["source"], roles["target"], inputs.T_gt, inputs.landmarks, info, labels, inputs.label_name,
                   inputs.target_generated)


def perturb_cloud(cloud: Cloud, noise_std: float, outlier_share: float, crop: float,
                  rng: np.random.Generator) -> tuple[Cloud, float, int]:
    """Crop (keep the share ``crop`` of the points below a random plane), add Gaussian noise of ``noise_std``
    (input units) per coordinate, then add uniform outliers in the bounding box so that they are the share
    ``outlier_share`` of the result. Normals of a noisy or outlier-laden cloud are re-estimated from the points
    (20 neighbours), oriented like the clean normal of the nearest original point, as a scanner's software
    would. Returns (cloud, kept share after the crop, number of outliers)."""
    pts, nrm = cloud.points, cloud.normals
    n0 = len(pts)
    if crop < 1:
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        h = pts @ d
        keep = np.argsort(h, kind="stable")[: max(10, int(round(crop * n0)))]
        keep.sort()
        pts, nrm = pts[keep], None if nrm is None else nrm[keep]
    kept = len(pts) / n0
    clean, clean_n = pts, nrm
    if noise_std > 0:
        pts = pts + rng.normal(scale=noise_std, size=pts.shape)
    n_out = int(round(outlier_share * len(pts) / (1 - outlier_share)))
    if n_out:
        lo, hi = pts.min(0), pts.max(0)
        pts = np.vstack([pts, rng.uniform(lo, hi, size=(n_out, 3))])
    if noise_std > 0 or n_out:
        est = estimate_normals(pts)
        if clean_n is not None:
            ref = clean_n[cKDTree(clean).query(pts)[1]]
            est *= np.where(np.einsum("ij,ij->i", est, ref) < 0, -1.0, 1.0)[:, None]
        nrm = est
    return Cloud(pts, nrm, cloud.source), kept, n_out
