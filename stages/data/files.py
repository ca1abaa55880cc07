"""``data=files``: source and target read from files, with optional ground truth and landmarks."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.errors import ConfigError, InputError, warn
from scanreg.eval.checks import likely_units
from scanreg.geometry import (Cloud, Geometry, Mesh, apply_T, bbox_diagonal, invert_T, points_of,
                              principal_box_diagonal, transform_geometry)
from scanreg.io import expand_path, read_input, resolve_path, read_landmarks, read_transform
from scanreg.stages.data.perturb import PoseParams
from scanreg.stages.data.base import Provider
from scanreg.stages.registry import DATA
from scanreg.types import Problem, RunContext


def scale_geometry(g: Geometry, s: float) -> Geometry:
    """``g`` with its coordinates multiplied by ``s`` (normals unchanged)."""
    if s == 1.0:
        return g
    if isinstance(g, Mesh):
        return Mesh(g.vertices * s, g.faces, g.source)
    return Cloud(g.points * s, g.normals, g.source, dict(g.extra))


MAX_SIZE_RATIO = 10.0
"""The default ``data.max_size_ratio`` (``data=files``, ``data=scanset``): sizes further apart are taken for
other units."""


def check_pair(src: Geometry, tgt: Geometry, max_size_ratio: float | None, source_scale: float = 1.0) -> None:
    """Before any expensive stage: the two inputs' sizes agree to within ``max_size_ratio``, else one line
    naming both extents and the likely unit factor (counts and flatness: ``scanreg.eval.checks``). ``src`` is
    as read times ``source_scale``, which the suggested value includes."""
    if min(len(points_of(src)), len(points_of(tgt))) < 10:
        return  # too few points: scanreg.eval.checks says so
    # sizes along the principal axes: the same verdict and numbers in any pose of either input
    ds, dt = principal_box_diagonal(points_of(src)), principal_box_diagonal(points_of(tgt))
    if max_size_ratio is None or not (ds > 0 and dt > 0):
        return
    r = ds / dt
    if 1 / max_size_ratio <= r <= max_size_ratio:
        return
    big, f = ("source", r) if r > 1 else ("target", 1 / r)
    unit, factor = likely_units(f)
    # the source is scaled either way: the target is the fixed frame, whose units the result keeps (the transform
    # and aligned_source.ply then overlay the target file as it is)
    fix = f"data.source_scale={source_scale * (1 / factor if big == 'source' else factor):g}"
    raise InputError(
        f"{src.source or 'source'} is {ds:.4g} across (the diagonal of its box along its principal axes) and "
        f"{tgt.source or 'target'} {dt:.4g}: {f:.3g}x apart, likely {unit}; set {fix} to bring the source into the "
        "target's units (or data.max_size_ratio=null to register them as they are)")


def _same_file(a: str, b: str) -> bool:
    """Whether the paths ``a`` and ``b`` (as configured) name one file."""
    try:
        return os.path.samefile(resolve_path(expand_path(a)), resolve_path(expand_path(b)))
    except Exception:  # noqa: BLE001  # (read already: a path that cannot be compared is not the same)
        return False


@DATA.register("files")
class Files(Provider):
    """Source and target read from files (meshes or point clouds), with optional ground truth and landmarks."""

    @dataclass
    class Params(PoseParams):
        max_angle_deg: float = 0.0
        """Largest rotation of a further random pose of the source, degrees (0 with ``max_translation`` 0: the
        source as read; >= 180: any rotation); the ground truth and landmarks follow it (without ``gt``, a source
        and target that are one file read alike have the identity as their truth)."""
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
        max_size_ratio: Optional[float] = MAX_SIZE_RATIO
        """Stop, before any repair or registration, when the sizes of source and target (after scaling; the
        diagonals of their boxes along their principal axes, the same in any pose) differ by more than this
        factor: such inputs are almost always in different units, and the message names the likely unit factor.
        null: no check (a small part registered into a large scene)."""
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

    def require(self) -> None:
        """Both files named (checked before a run starts)."""
        for key in ("source", "target"):
            if not getattr(self.p, key):
                raise ConfigError(
                    f"data=files: data.{key} is not set; run e.g. 'scanreg data.source=A.ply data.target=B.ply', "
                    "or the demo: 'scanreg data=synthetic'"
                )

    def preflight(self) -> None:
        """Both files named and there, and the ground truth and landmarks files when named."""
        self.require()
        for label, path in (("source", self.p.source), ("target", self.p.target), ("ground truth data.gt", self.p.gt),
                            ("data.landmarks", self.p.landmarks)):
            if path:
                resolve_path(expand_path(path), label)

    def load(self, ctx: RunContext) -> Problem:
        self.require()
        src, n_src_bad = read_input(expand_path(self.p.source), "source", self.p.source_columns or self.p.columns)
        tgt, n_tgt_bad = read_input(expand_path(self.p.target), "target", self.p.target_columns or self.p.columns)
        info = {"n_source_invalid_points": n_src_bad, "n_target_invalid_points": n_tgt_bad}
        src, tgt = scale_geometry(src, self.p.source_scale), scale_geometry(tgt, self.p.target_scale)
        check_pair(src, tgt, self.p.max_size_ratio, self.p.source_scale)
        gt = read_transform(expand_path(self.p.gt), "ground truth data.gt") if self.p.gt else None
        lm = read_landmarks(expand_path(self.p.landmarks)) if self.p.landmarks else None
        if lm is not None:
            lm = (lm[0] * self.p.target_scale, lm[1] * self.p.source_scale)
        posed = self.p.max_angle_deg > 0 or self.p.max_translation > 0
        same_reading = (self.p.source_scale == self.p.target_scale and
                        (self.p.source_columns or self.p.columns) == (self.p.target_columns or self.p.columns))
        same = same_reading and _same_file(self.p.source, self.p.target)
        if gt is None and same:  # one file read alike: the source lies on the target, the truth is the identity
            gt = np.eye(4)
        if not posed and same:
            warn(f"data.source and data.target are the same file ({self.p.source}): the source lies on the target "
                 "already, so the result is the identity; to test the registration, move the source with "
                 "data.max_angle_deg=A data.max_translation=T (the truth follows the pose)")
        if posed:  # a further seeded pose of the source
            P = self.p.pose(808, points_of(src), bbox_diagonal(points_of(tgt)))
            src = transform_geometry(P, src)
            gt = None if gt is None else gt @ invert_T(P)
            lm = None if lm is None else (lm[0], apply_T(P, lm[1]))
        return Problem(src, tgt, gt, lm, info)
