"""Data providers: what a run registers (source, target, optional ground truth and landmarks)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from scanreg.config import Context, expand_path
from scanreg.errors import ConfigError, InputError
from scanreg.geometry import (
    Cloud, Geometry, Mesh, apply_T, bbox_diagonal, invert_T, points_of, random_pose, transform_geometry,
)
from scanreg.io import read_geometry, read_input, read_landmarks, read_mesh, read_stanford_conf, read_transform, resolve_path
from scanreg.registry import DATA
from scanreg.geometry import barycentric_sample, triangle_areas_normals


@dataclass
class Inputs:
    """A registration problem: find ``T_target_source``."""

    source: Geometry
    target: Geometry
    T_gt: Optional[np.ndarray] = None
    """Ground-truth ``T_target_source`` when known."""
    landmarks: Optional[tuple[np.ndarray, np.ndarray]] = None
    """Picked pairs ``(target points (K, 3), source points (K, 3))``."""
    info: dict | None = None
    """Numbers about the case, logged as metrics (e.g. ``gt_overlap``)."""
    target_labels: Optional[np.ndarray] = None
    """A part number per face of a target mesh (e.g. tooth numbers), for per-part deviation statistics."""
    label_name: str = "part"
    """What a part is called in metric names (``tooth``)."""


UNIT_FACTORS = {1000.0: "mm vs m", 10.0: "mm vs cm", 100.0: "cm vs m", 25.4: "mm vs inches",
                39.37: "inches vs m", 304.8: "mm vs feet", 12.0: "inches vs feet"}
"""Common ratios between length units, to name the likely cause of a size mismatch."""


def scale_geometry(g: Geometry, s: float) -> Geometry:
    """``g`` with its coordinates multiplied by ``s`` (normals unchanged)."""
    if s == 1.0:
        return g
    if isinstance(g, Mesh):
        return Mesh(g.vertices * s, g.faces, g.source)
    return Cloud(g.points * s, g.normals, g.source, dict(g.extra))


def check_pair(src: Geometry, tgt: Geometry, max_size_ratio: float | None) -> None:
    """Before any expensive stage: the two inputs' sizes agree to within ``max_size_ratio``, else one line
    naming both extents and the likely unit factor (counts and flatness: ``scanreg.checks``)."""
    if min(len(points_of(src)), len(points_of(tgt))) < 10:
        return  # too few points: scanreg.checks says so
    ds, dt = bbox_diagonal(points_of(src)), bbox_diagonal(points_of(tgt))
    if max_size_ratio is None or not (ds > 0 and dt > 0):
        return
    r = ds / dt
    if 1 / max_size_ratio <= r <= max_size_ratio:
        return
    big, f = ("source", r) if r > 1 else ("target", 1 / r)
    unit, factor = min(((u, k) for k, u in UNIT_FACTORS.items()), key=lambda uk: abs(np.log(f / uk[1])))
    if abs(np.log(f / factor)) > np.log(1.3):  # no common unit ratio: suggest the measured one
        unit, factor = "different units or a different object", float(f"{f:.3g}")
    fix = (f"data.source_scale={1 / factor:g}" if big == "source" else f"data.target_scale={1 / factor:g}")
    raise InputError(
        f"{src.source or 'source'} is {ds:.4g} across (bounding-box diagonal) and {tgt.source or 'target'} {dt:.4g}: "
        f"{f:.3g}x apart, likely {unit}; set {fix} (or data.max_size_ratio=null to register them as they are)")


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


def perturb_inputs(inputs: Inputs, p: PerturbParams) -> Inputs:
    """``inputs`` with the perturbations of ``p`` applied (unchanged when none is set). The ground truth and
    landmarks stay valid: nothing is moved as a whole. Logs ``perturb_<role>_points``, ``..._outliers``,
    ``..._crop_kept`` and the noise in input units (``perturb_noise_std``) in ``info``."""
    if not p.perturbing():
        return inputs
    info = dict(inputs.info or {})
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
    return Inputs(roles["source"], roles["target"], inputs.T_gt, inputs.landmarks, info, labels, inputs.label_name)


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
        from scanreg.closest import estimate_normals

        est = estimate_normals(pts)
        if clean_n is not None:
            ref = clean_n[cKDTree(clean).query(pts)[1]]
            est *= np.where(np.einsum("ij,ij->i", est, ref) < 0, -1.0, 1.0)[:, None]
        nrm = est
    return Cloud(pts, nrm, cloud.source), kept, n_out


@DATA.register("files")
class Files:
    """Source and target read from files (meshes or point clouds), with optional ground truth and landmarks."""

    @dataclass
    class Params(PoseParams):
        max_angle_deg: float = 0.0
        """Largest rotation of a further random pose of the source, degrees (0 with ``max_translation`` 0: the
        source as read; >= 180: any rotation); the ground truth and landmarks follow it."""
        max_translation: float = 0.0
        """Largest translation of that pose, as a share of the target's bounding-box diagonal."""
        source: Optional[str] = None
        """Path of the source (the scan to move): mesh (.ply .stl .obj .off) or cloud (.ply .pcd .xyz .txt .pts .csv
        .asc .npy).
        ``pkg:PACKAGE/PATH`` names a file inside an installed package, ``shared:PATH`` one under ../shared/data."""
        target: Optional[str] = None
        """Path of the target (the fixed scan), same formats."""
        gt: Optional[str] = None
        """Optional ground-truth T_target_source: 4x4 text or .npy, mapping source points into the target frame
        (translation in input units)."""
        landmarks: Optional[str] = None
        """Optional CSV of picked pairs: target x,y,z then source x,y,z per row (input units)."""
        source_scale: float = 1.0
        """Multiply the source's coordinates (and its landmarks) by this on reading: a unit fix, e.g. 0.001 for
        a source in mm registered to a target in m. ``data.gt`` maps the scaled source into the target."""
        target_scale: float = 1.0
        """Multiply the target's coordinates (and its landmarks) by this on reading (see ``source_scale``)."""
        max_size_ratio: Optional[float] = 10.0
        """Stop, before any repair or registration, when the bounding-box diagonals of source and target (after
        scaling) differ by more than this factor: such inputs are almost always in different units, and the
        message names the likely unit factor. null: no check (a small part registered into a large scene)."""
        columns: Optional[str] = None
        """What the columns of a text (.xyz .txt .pts .csv) or .npy cloud are, e.g. 'x y z nx ny nz' or
        'x y z r g b a' (names x y z nx ny nz r g b a; - ignores a column). Unset: a header line's names, or
        detected from the values (unit vectors are normals, 0..1 or integer 0..255 values are colours). Applies to
        the source and the target when they are such files (see source_columns, target_columns)."""
        source_columns: Optional[str] = None
        """The columns of the source alone (overrides ``columns`` for it)."""
        target_columns: Optional[str] = None
        """The columns of the target alone (overrides ``columns`` for it)."""

    def check(self):
        super().check()
        for key in ("source_scale", "target_scale"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
        if self.max_size_ratio is not None and not self.max_size_ratio > 1:
            raise ValueError(f"max_size_ratio must be > 1 or null, got {self.max_size_ratio}")

    def __init__(self, params: Params):
        self.p = params

    def require(self) -> None:
        """Both files named (checked before a run starts)."""
        for key in ("source", "target"):
            if not getattr(self.p, key):
                raise ConfigError(
                    f"data=files: data.{key} is not set; run e.g. 'scanreg data.source=A.ply data.target=B.ply', "
                    "or the demo: 'scanreg data=synthetic'"
                )

    def load(self, ctx: Context) -> Inputs:
        self.require()
        src, n_src_bad = read_input(expand_path(self.p.source), "source", self.p.source_columns or self.p.columns)
        tgt, n_tgt_bad = read_input(expand_path(self.p.target), "target", self.p.target_columns or self.p.columns)
        info = {"n_source_invalid_points": n_src_bad, "n_target_invalid_points": n_tgt_bad}
        src, tgt = scale_geometry(src, self.p.source_scale), scale_geometry(tgt, self.p.target_scale)
        check_pair(src, tgt, self.p.max_size_ratio)
        gt = read_transform(expand_path(self.p.gt), "ground truth data.gt") if self.p.gt else None
        lm = read_landmarks(expand_path(self.p.landmarks)) if self.p.landmarks else None
        if lm is not None:
            lm = (lm[0] * self.p.target_scale, lm[1] * self.p.source_scale)
        if self.p.max_angle_deg > 0 or self.p.max_translation > 0:  # a further seeded pose of the source
            P = self.p.pose(808, points_of(src), bbox_diagonal(points_of(tgt)))
            src = transform_geometry(P, src)
            gt = None if gt is None else gt @ invert_T(P)
            lm = None if lm is None else (lm[0], apply_T(P, lm[1]))
        return Inputs(src, tgt, gt, lm, info)


@DATA.register("synthetic")
class Synthetic:
    """A second "scan" made from one mesh: the source is the mesh itself (repaired and sampled by the run);
    the target an independent resampling of the same surface with part cut away, Gaussian noise and outliers,
    placed under a random pose that is the ground truth. The default mesh is pymeshfix's defective Stanford
    bunny (units: mm-like, about 50 across)."""

    @dataclass
    class Params(PoseParams):
        mesh: str = "pkg:pymeshfix/examples/StanfordBunny.ply"
        """Mesh to make the case from (path, ``pkg:`` or ``shared:`` name)."""
        n_points: int = 20000
        """Points sampled on the surface for the target (before cropping)."""
        keep: float = 0.8
        """Share of the target's points kept; the rest, beyond a random plane, is cut away (partial overlap)."""
        noise: float = 0.1
        """Standard deviation of Gaussian noise per coordinate, in multiples of the target's sampling
        spacing sqrt(area / n_points)."""
        outliers: float = 0.0
        """Share of outlier points added uniformly in the target's bounding box."""
        seed: int = 1
        """Seed of the target's sampling, cropping, noise and outliers."""

        def check(self):
            super().check()
            if not 0.05 <= self.keep <= 1.0:
                raise ValueError(f"keep must be in [0.05, 1], got {self.keep}")
            if self.n_points < 3:
                raise ValueError(f"n_points must be >= 3, got {self.n_points}")

    def __init__(self, params: Params):
        self.p = params

    def load(self, ctx: Context) -> Inputs:
        p = self.p
        mesh = read_mesh(expand_path(p.mesh), "data.mesh")
        rng = np.random.default_rng([p.seed, 101])
        pts, normals, _ = barycentric_sample(mesh, p.n_points, rng)
        spacing = float(np.sqrt(triangle_areas_normals(mesh)[0].sum() / p.n_points))
        if p.keep < 1.0:
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            h = pts @ d
            keep = h <= np.quantile(h, p.keep)
            pts, normals = pts[keep], normals[keep]
        pts = pts + rng.normal(scale=p.noise * spacing, size=pts.shape)
        n_out = int(round(p.outliers * len(pts)))
        if n_out:
            lo, hi = pts.min(0), pts.max(0)
            out = rng.uniform(lo, hi, size=(n_out, 3))
            on = rng.normal(size=(n_out, 3))
            pts = np.vstack([pts, out])
            normals = np.vstack([normals, on / np.linalg.norm(on, axis=1, keepdims=True)])
        T = p.pose(202, pts, bbox_diagonal(mesh.vertices))
        target = transform_geometry(T, Cloud(pts, normals, f"synthetic scan of {p.mesh}"))
        return Inputs(mesh, target, T, None, {"synthetic_spacing": spacing})


@DATA.register("stanford")
class Stanford:
    """Two scans of a Stanford range-scan folder with a ``.conf`` (default: the bunny in ../shared/data); the
    ground truth comes from the ``.conf`` poses, and the source is moved by a seeded random initial pose."""

    @dataclass
    class Params(PerturbParams):
        folder: str = "shared:stanford_bunny"
        """Folder with the scans and the .conf (``shared:NAME`` = ../shared/data/NAME beside the project)."""
        conf: str = "bun.conf"
        """Name of the .conf file in the folder."""
        source: str = "bun045.ply"
        """Scan to move (file name in the folder)."""
        target: str = "bun000.ply"
        """Fixed scan (file name in the folder)."""
        pair: Optional[str] = None
        """``TARGET:SOURCE`` scan names without extension (e.g. ``bun000:bun045``); when set it replaces
        ``target`` and ``source``, so that pairs can be swept: ``data.pair=bun000:bun045,top2:bun180``."""
        pre_align: bool = False
        """Move the source into the target's frame by the ground truth before the random pose, so that the
        pose alone is the error to recover (small poses then start ICP near the truth); false: the scan's own
        frame, as scanned."""
        overlap_distance: float = 3.0
        """Distance under which a source point counts as overlapping the target for the logged ``gt_overlap``
        (share of source points near the target at the true pose), in multiples of the target's median
        nearest-neighbour spacing."""

    def __init__(self, params: Params):
        self.p = params

    def load(self, ctx: Context) -> Inputs:
        folder = Path(expand_path(self.p.folder))
        if not folder.is_dir():
            raise InputError(
                f"data.folder {self.p.folder}: no such folder ({folder}); the Stanford scans live in ../shared/data"
            )
        poses = read_stanford_conf(folder / self.p.conf)
        target, source = self.p.target, self.p.source
        if self.p.pair:
            names = self.p.pair.split(":")
            if len(names) != 2 or not all(names):
                raise ConfigError(f"data.pair '{self.p.pair}': expected TARGET:SOURCE, e.g. bun000:bun045")
            stems = {Path(k).stem: k for k in poses}
            for n in names:
                if n not in stems and n not in poses:
                    raise ConfigError(f"data=stanford: scan '{n}' is not in {self.p.conf}; known: "
                                      f"{', '.join(stems)}")
            target, source = (stems.get(n, n) for n in names)
        for scan in (source, target):
            if scan not in poses:
                raise ConfigError(f"data=stanford: scan '{scan}' is not in {self.p.conf}; known: {', '.join(poses)}")
        src = read_geometry(folder / source, "source")
        tgt = read_geometry(folder / target, "target")
        T_t_s = invert_T(poses[target]) @ poses[source]
        tgt_pts = points_of(tgt)
        tree = cKDTree(tgt_pts)
        spacing = float(np.median(tree.query(tgt_pts[:: max(1, len(tgt_pts) // 5000)], k=2)[0][:, 1]))
        overlap = float(np.mean(tree.query(apply_T(T_t_s, points_of(src)))[0] <= self.p.overlap_distance * spacing))
        if self.p.pre_align:
            src, T_t_s = transform_geometry(T_t_s, src), np.eye(4)
        P = self.p.pose(303, points_of(src), bbox_diagonal(tgt_pts))
        src = transform_geometry(P, src)
        return perturb_inputs(Inputs(src, tgt, T_t_s @ invert_T(P), None, {"gt_overlap": overlap}), self.p)


@DATA.register("pairs_3dmatch")
class Pairs3DMatch:
    """The real RGB-D fragment pair from 3DMatch in ../shared/data/3dmatch_pair (indoor room, points in metres,
    about 2.5 cm apart, 45 % overlap): ``src.npy`` is the source, ``ref.npy`` the target, ``gt.npy`` the true
    T_target_source; the source is further moved by a seeded random pose. A hard case for feature matching
    (sparse, largely planar); judge it with 3DMatch tolerances (``evaluate.success_rotation_deg=15``,
    ``evaluate.success_translation`` about 0.3 m / diagonal)."""

    @dataclass
    class Params(PerturbParams):
        folder: str = "shared:3dmatch_pair"
        """Folder with src.npy, ref.npy and gt.npy (``shared:NAME`` = ../shared/data/NAME)."""

    def __init__(self, params: Params):
        self.p = params

    def load(self, ctx: Context) -> Inputs:
        folder = Path(expand_path(self.p.folder))
        if not folder.is_dir():
            raise InputError(f"data.folder {self.p.folder}: no such folder ({folder}); the 3DMatch pair lives in "
                             "../shared/data/3dmatch_pair")
        src = read_geometry(folder / "src.npy", "source")
        tgt = read_geometry(folder / "ref.npy", "target")
        T_gt = read_transform(folder / "gt.npy", "ground truth gt.npy")
        P = self.p.pose(707, points_of(src), bbox_diagonal(points_of(tgt)))
        return perturb_inputs(Inputs(transform_geometry(P, src), tgt, T_gt @ invert_T(P), None), self.p)
