"""Real scans with ground truth from ../shared/data: ``data=stanford`` (pairs of the Stanford bunny's range
scans) and ``data=pairs_3dmatch`` (a 3DMatch RGB-D fragment pair)."""

from __future__ import annotations

import os

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from scanreg.errors import ConfigError, InputError
from scanreg.geometry import apply_T, bbox_diagonal, invert_T, points_of, transform_geometry
from scanreg.io import expand_path, read_geometry, read_stanford_conf, read_transform, resolve_path
from scanreg.stages.data.perturb import PerturbParams, perturb_inputs
from scanreg.stages.data.base import Provider
from scanreg.stages.registry import DATA
from scanreg.types import Problem, RunContext


@DATA.register("stanford")
class Stanford(Provider):
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


    def preflight(self) -> None:
        """The folder, its .conf, the two scans' names and files (reads only the .conf)."""
        folder, _, source, target = self._scans()
        resolve_path(folder / source, "source")
        resolve_path(folder / target, "target")

    def _scans(self) -> tuple[Path, dict, str, str]:
        """``(folder, poses of the .conf, source name, target name)``, or one line that says what is wrong."""
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
        source, target = (self._named(scan, poses, folder) for scan in (source, target))
        return folder, poses, source, target

    def load(self, ctx: RunContext) -> Problem:
        folder, poses, source, target = self._scans()
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
        return perturb_inputs(Problem(src, tgt, T_t_s @ invert_T(P), None, {"gt_overlap": overlap},
                                             target_generated=True), self.p)


    def _named(self, scan: str, poses: dict, folder: Path) -> str:
        """``scan`` as the .conf names it: a name of it, or a path to that file in ``folder`` (``scanreg.register``
        passes the files it is given as paths); else one line that says what is known."""
        if scan in poses:
            return scan
        path = Path(expand_path(str(scan)))
        stems = {Path(k).stem: k for k in poses}
        name = path.name if path.name in poses else stems.get(path.name, stems.get(path.stem))
        given_as_path = "/" in str(scan) or os.sep in str(scan)  # ('./bun000.ply' too: a file here, not a name)
        if name is not None and given_as_path and path.parent.resolve() != folder.resolve():
            raise ConfigError(f"data=stanford: scan {scan} is not in data.folder ({folder}), where the scans of "
                              f"{self.p.conf} are read from: set data.folder to its folder, or use data=files "
                              "with data.gt for files of your own")
        if name is None:
            raise ConfigError(f"data=stanford: scan '{scan}' is not in {self.p.conf}; known: {', '.join(poses)}")
        return name


@DATA.register("pairs_3dmatch")
class Pairs3DMatch(Provider):
    """The real RGB-D fragment pair from 3DMatch in ../shared/data/3dmatch_pair (indoor room, points in metres,
    about 2.5 cm apart, 45 % overlap): ``src.npy`` is the source, ``ref.npy`` the target, ``gt.npy`` the true
    T_target_source; the source is further moved by a seeded random pose. A hard case for feature matching
    (sparse, largely planar); judge it with 3DMatch tolerances (``evaluate.success_rotation_deg=15``,
    ``evaluate.success_translation`` about 0.3 m / diagonal)."""

    @dataclass
    class Params(PerturbParams):
        folder: str = "shared:3dmatch_pair"
        """Folder with src.npy, ref.npy and gt.npy (``shared:NAME`` = ../shared/data/NAME)."""


    def preflight(self) -> None:
        """The pair's folder is there."""
        self._folder()

    def _folder(self) -> Path:
        folder = Path(expand_path(self.p.folder))
        if not folder.is_dir():
            raise InputError(f"data.folder {self.p.folder}: no such folder ({folder}); the 3DMatch pair lives in "
                             "../shared/data/3dmatch_pair")
        return folder

    def load(self, ctx: RunContext) -> Problem:
        folder = self._folder()
        src = read_geometry(folder / "src.npy", "source")
        tgt = read_geometry(folder / "ref.npy", "target")
        T_gt = read_transform(folder / "gt.npy", "ground truth gt.npy")
        P = self.p.pose(707, points_of(src), bbox_diagonal(points_of(tgt)))
        return perturb_inputs(Problem(transform_geometry(P, src), tgt, T_gt @ invert_T(P), None,
                                             target_generated=True), self.p)
