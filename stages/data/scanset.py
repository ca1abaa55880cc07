"""``data=scanset``: many scans of one object (a folder, a glob or a list of files), to register into one model."""

from __future__ import annotations

import glob as globbing
import hashlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from scanreg.errors import ConfigError, InputError, note, warn
from scanreg.eval.checks import likely_units
from scanreg.geometry import bbox_diagonal, invert_T, points_of, principal_box_diagonal, transform_geometry
from scanreg.io import (CLOUD_EXTS, MESH_EXTS, expand_path, read_geometry, read_input, read_stanford_conf,
                        read_transform, resolve_path)
from scanreg.stages.data.base import Provider
from scanreg.stages.data.files import MAX_SIZE_RATIO
from scanreg.stages.data.perturb import PoseParams
from scanreg.stages.registry import DATA
from scanreg.types import RunContext, ScanSet

SCAN_EXTS = MESH_EXTS | CLOUD_EXTS
ORDERS = ("unordered", "sequential", "turntable")


@DATA.register("scanset")
class ScanSetProvider(Provider):
    """Many scans of one object, meshes or clouds as scanned, to register into one model: ``data.scans`` is a
    folder (every scan file in it), a glob, or a list of files. Optional ground truth (``data.poses``) and a
    reference surface (``data.reference``) for the evaluation; each scan may be moved by a seeded random pose
    (``max_angle_deg``, ``max_translation``), the ground truth following it."""

    @dataclass
    class Params(PoseParams):
        max_angle_deg: float = 0.0
        """Largest rotation of a random pose given to every scan, degrees (0 with ``max_translation`` 0: the
        scans as read; >= 180: any rotation); the ground truth follows."""
        max_translation: float = 0.0
        """Largest translation of those poses, as a share of the bounding-box diagonal of all scans together."""
        scans: Any = None
        """The scans: a folder (its scan files, .ply .stl .obj .off .pcd .xyz .pts .asc in any mix; .txt .csv
        .npy only in a folder of no other scan file; a scan in two formats once), a glob (``scans/*.ply``), or a
        list of paths; ``shared:`` and ``pkg:`` names allowed. Sorted by file name, numbers by value (``scan_2``
        before ``scan_10``); the first is the world frame of the result."""
        poses: Optional[str] = None
        """Ground truth (optional): a Stanford ``.conf`` file (``bmesh NAME tx ty tz qx qy qz qw`` lines), or a
        folder or glob of 4x4 files (text or .npy), one per scan, matched by file stem; each maps the scan into
        one common world frame (``T_world_scan``, input units). A scan without one is registered, not evaluated
        (at least two need one)."""
        order: str = "unordered"
        """What the order of the scans says: ``sequential`` (neighbours in sorted order overlap), ``turntable`` (and
        the last overlaps the first), or ``unordered``: which pairs are registered (``multiview.pairs``)."""
        reference: Optional[str] = None
        """A reference surface (a mesh in the world frame of ``poses``) that the reconstruction is measured
        against (optional)."""
        columns: Optional[str] = None
        """The columns of text and .npy clouds (as ``data=files``' ``columns``)."""
        max_size_ratio: Optional[float] = MAX_SIZE_RATIO
        """Stop, before any registration, when a scan's size (the diagonal of its box along its principal axes, the
        same in any pose) differs from the median of the
        set's by more than this factor: such a scan is almost always in other units (the message names the
        likely factor); one scan in mm among scans in m left 4 of 5 scans unplaced after two minutes. null: no
        check (scans of very different extents, e.g. a detail scan among overviews)."""

        def check(self):
            super().check()
            if self.order not in ORDERS:
                raise ValueError(f"order must be one of {', '.join(ORDERS)}, got '{self.order}'")
            if self.max_size_ratio is not None and not self.max_size_ratio > 1:
                raise ValueError(f"max_size_ratio must be > 1 or null, got {self.max_size_ratio}")

    def require(self) -> None:
        if not self.p.scans:
            raise ConfigError("data=scanset: data.scans is not set; give a folder, a glob or a list of scans, e.g. "
                              "'scanreg data=scanset data.scans=scans/'")

    def preflight(self) -> None:
        """The scans named and there (at least two), and the reference surface and a ``.conf`` of poses when
        named."""
        self.require()
        scan_paths(self.p.scans)
        if self.p.reference:
            resolve_path(expand_path(self.p.reference), "reference")
        if self.p.poses and self.p.poses.endswith(".conf"):
            resolve_path(expand_path(self.p.poses), "Stanford .conf")

    def load(self, ctx: RunContext) -> ScanSet:
        self.require()
        paths = scan_paths(self.p.scans)
        scans, info = [], {}
        names = scan_names(paths)
        for path, name in zip(paths, names):
            g, bad = read_input(str(path), "scan", self.p.columns)
            g.source = name
            scans.append(g)
            info["n_invalid_points"] = info.get("n_invalid_points", 0) + bad
        check_sizes(scans, self.p.max_size_ratio)
        warn_copies(scans)
        poses = read_poses(self.p.poses, names) if self.p.poses else None
        if poses is None:
            for item, conf in unread_pose_files(self.p.scans):
                note(f"data.scans {item}: {conf.name} beside the scans looks like their poses (a Stanford .conf); "
                     f"it is not read unless named: add data.poses={conf} to score the registration against it")
        if self.p.max_angle_deg > 0 or self.p.max_translation > 0:
            diagonal = bbox_diagonal(np.vstack([points_of(g) for g in scans]))
            for k, g in enumerate(scans):
                P = self.p.pose(900 + k, points_of(g), diagonal)
                scans[k] = transform_geometry(P, g)
                scans[k].source = g.source
                if poses is not None and poses[k] is not None:
                    poses[k] = poses[k] @ invert_T(P)
        reference = read_geometry(expand_path(self.p.reference), "reference") if self.p.reference else None
        info["n_scans"] = len(scans)
        return ScanSet(scans, names, poses, self.p.order, info, reference)


def check_sizes(scans: list, max_size_ratio: float | None) -> None:
    """Before any registration: every scan's extent (the diagonal of its box along its principal axes, the same in
    any pose) within ``max_size_ratio`` of the
    median scan's, else one line naming the scan, the sizes and the likely unit factor (the first scan the
    furthest off)."""
    if max_size_ratio is None or len(scans) < 2:
        return
    d = np.array([principal_box_diagonal(points_of(g)) for g in scans])  # (any pose: the same sizes)
    if (d > 0).sum() == 2:  # two scans: which one is off cannot be told, so both are named
        a, b = np.flatnonzero(d > 0)
        f = max(d[a], d[b]) / min(d[a], d[b])
        if f > max_size_ratio:
            unit, factor = likely_units(float(f))
            raise InputError(f"scans {scans[a].source} and {scans[b].source} are {d[a]:.4g} and {d[b]:.4g} across "
                             f"(diagonals of their boxes along their principal axes): {f:.3g}x apart, likely "
                             f"{unit}; multiply the larger one's coordinates by {1 / factor:g} or the smaller "
                             f"one's by {factor:g} (or set data.max_size_ratio=null to register the scans as they "
                             "are)")
        return
    med = float(np.median(d[d > 0])) if (d > 0).any() else 0.0
    if not med > 0:
        return
    ratio = np.where(d > 0, d / med, 1.0)
    off = np.maximum(ratio, 1 / ratio)
    k = int(np.argmax(off))
    if off[k] <= max_size_ratio:
        return
    unit, factor = likely_units(float(off[k]))
    scale = 1 / factor if ratio[k] > 1 else factor
    raise InputError(
        f"scan {scans[k].source} is {d[k]:.4g} across (the diagonal of its box along its principal axes) and the "
        f"set's median scan {med:.4g}: {off[k]:.3g}x apart, likely {unit}; multiply its coordinates by {scale:g} "
        "(or set data.max_size_ratio=null to register the scans as they are)")


def warn_copies(scans: list) -> None:
    """One warning naming the scans that hold exactly the same points as an earlier one (a file copied under
    another name, or the same scan exported twice): a copy pairs with its original perfectly and adds nothing
    to the model; both are kept."""
    first: dict[bytes, str] = {}
    copies = []
    for g in scans:
        key = hashlib.sha256(np.ascontiguousarray(points_of(g), dtype=np.float64).tobytes()).digest()
        if key in first:
            copies.append(f"{g.source} (of {first[key]})")
        else:
            first[key] = g.source
    if copies:
        warn(f"scan set: {len(copies)} scan{'s are copies' if len(copies) > 1 else ' is a copy'}, the same points "
             f"as an earlier one: {', '.join(copies[:3])}{', ...' if len(copies) > 3 else ''}; a copy adds "
             "nothing to the model (both are kept)")


def scan_paths(spec: Any) -> list[Path]:
    """The scan files ``spec`` names (a folder, a glob, a list), sorted by name (numbers by value: ``scan_2``
    before ``scan_10``, :func:`natural_key`); one :class:`InputError` line for a path that is missing or names no
    scan."""
    items = _items(spec)
    out: list[Path] = []
    for item in items:
        s = expand_path(str(item))
        p = Path(s).expanduser()
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in SCAN_EXTS)
            scans = _folder_scans(found, str(item)) if found else []
            if not scans:
                raise InputError(_no_scans(p, str(item), found))
            out += scans
        elif any(c in s for c in "*?["):
            found = sorted(Path(q) for q in globbing.glob(str(p)) if Path(q).is_file())
            if not found:
                raise InputError(f"data.scans {item}: the pattern matches no file")
            out += found
        elif s.startswith("pkg:") or p.is_file():
            out.append(Path(s) if s.startswith("pkg:") else p)
        else:
            raise InputError(f"data.scans {item}: no such file or folder ({p.absolute()})")
    out = sorted(dict.fromkeys(out), key=lambda q: (natural_key(q.name), [natural_key(x) for x in q.parts]))
    if len(out) < 2:
        what = ", ".join(str(i) for i in items)
        raise InputError(f"data.scans {what}: {len(out)} scan{'' if len(out) == 1 else 's'}"
                         + (f" ({out[0].name})" if out else "") + "; a scan set needs at least 2")
    return out


def _items(spec: Any) -> list:
    """``data.scans`` as a list of its items (one path, folder or glob; or a list of them)."""
    return list(spec) if isinstance(spec, (list, tuple)) or hasattr(spec, "__iter__") and not isinstance(spec, str) \
        else [spec]


def unread_pose_files(spec: Any) -> list[tuple[str, Path]]:
    """The Stanford ``.conf`` files (each scan's pose) in the folders ``spec`` names, with the item that named
    each folder: ground truth that ``data.poses`` would read, which a folder alone does not."""
    items = _items(spec)
    out = []
    for item in items:
        p = Path(expand_path(str(item))).expanduser()
        if p.is_dir():
            out += [(str(item), q) for q in sorted(p.glob("*.conf")) if q.is_file()]
    return out


GENERIC_TEXT = {".txt", ".csv", ".npy"}
"""Generic formats that are scans only in a folder without other scan files (a README.txt, notes.csv or a 4x4
T.npy beside scans is none); among themselves, the most common one."""


def _folder_scans(found: list[Path], item: str) -> list[Path]:
    """The scans among a folder's files of scan formats ``found`` (sorted): every one, in whatever format, but
    ``.txt``/``.csv``/``.npy`` files only when the folder has no other scan file (then those that hold rows of
    points, :func:`_rows_of_points`, of the most common format among them), and of files with the same stem (a
    scan exported twice, ``s1.ply`` and ``s1.stl``) the one in the folder's most common format; a note names the
    files left out. (The most common format alone was taken: a folder of .ply, .stl, .obj and .xyz scans gave one
    scan.)"""
    exts = [q.suffix.lower() for q in found]
    if any(e not in GENERIC_TEXT for e in exts):
        cand = [q for q in found if q.suffix.lower() not in GENERIC_TEXT]
    else:  # generic files alone: those of rows of points, of the most common format among them
        points = [q for q in found if _rows_of_points(q)]
        if not points:
            return []
        common = max(sorted({q.suffix.lower() for q in points}), key=[q.suffix.lower() for q in points].count)
        cand = [q for q in points if q.suffix.lower() == common]
    rank = {e: -exts.count(e) for e in set(exts)}  # the most common format first, then by name
    best: dict[str, Path] = {}
    for q in sorted(cand, key=lambda q: (rank[q.suffix.lower()], q.suffix.lower())):
        best.setdefault(q.stem, q)
    keep = sorted(best.values())
    other = [q.name for q in found if q not in best.values()]
    if other:
        note(f"data.scans {item}: the scans are its {len(keep)} files {_listed([q.name for q in keep])}; "
             f"{len(other)} file(s) left out ({_listed(other)}: text, a 4x4 transform or another format beside "
             "scans, or a scan's second format); "
             f"to choose, name them: data=scanset data.scans=[A,B,...]")
    return keep


def natural_key(name: str) -> tuple:
    """Sort key of a file name with its runs of digits compared as numbers (``scan_2`` before ``scan_10``)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(t) if k % 2 else t for k, t in enumerate(parts))


def _rows_of_points(path: Path) -> bool:
    """Whether a generic file (.txt .csv .npy) holds rows of at least 3 numbers that are not transforms
    (:func:`_transforms`), by its shape (.npy) or its first 64 kB (text): a README, notes or a ground-truth
    ``T.npy`` beside text scans are none."""
    try:
        if path.suffix.lower() == ".npy":
            shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
            return len(shape) == 2 and shape[1] >= 3 and shape != (4, 4)
        with open(path, "rb") as f:
            head = f.read(1 << 16).decode("utf-8", "replace")
    except (OSError, ValueError):
        return True  # unreadable: the reader says why, naming the file
    rows = []
    for line in head.splitlines():
        cells = [c for c in re.split(r"[,;\s]+", line.strip()) if c]
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            continue  # a header or a note
    rows = [r for r in rows if len(r) >= 3]
    return bool(rows) and not _transforms(rows, whole=len(head) < (1 << 16))


def _transforms(rows: list[list[float]], whole: bool) -> bool:
    """Whether numeric ``rows`` are rigid transforms rather than points: one 3x4 or 4x4 matrix (``whole``: the
    file's only rows), 4x4 matrices stacked (every 4th row 0 0 0 1), or rows of 12 (KITTI's poses, 3x4 each)."""
    widths = {len(r) for r in rows}
    if widths == {4} and whole and len(rows) in (3, 4):
        return True
    if widths == {4} and len(rows) % 4 == 0 and all(r == [0.0, 0.0, 0.0, 1.0] for r in rows[3::4]):
        return True
    return widths == {12}


def _no_scans(folder: Path, item: str, found: list[Path]) -> str:
    """The error line for a folder without scans (``found``: its generic files, none of them rows of points),
    naming its subfolders that hold some."""
    if found:
        msg = (f"data.scans {item}: no scans in this folder: its files {_listed([q.name for q in found])} hold no "
               "rows of 3 or more numbers (or a transform); name scan files: data=scanset data.scans=[A,B,...]")
    else:
        msg = f"data.scans {item}: no scan files in this folder (expected {' '.join(sorted(SCAN_EXTS))})"
    subs: dict[str, list[str]] = {}
    for d in sorted(folder.iterdir()):
        try:
            if d.is_dir():
                names = [q.suffix for q in d.iterdir() if q.is_file() and q.suffix.lower() in SCAN_EXTS]
                if names:
                    subs[d.name] = names
        except OSError:  # a folder that cannot be read (lost+found): not one of them
            continue
    if subs:
        exts = [e for names in subs.values() for e in names]
        common = max(sorted(set(exts)), key=exts.count)  # as the files spell it: a pattern matches case
        msg += (f"; its subfolders {_listed(list(subs))} hold some: name them, e.g. "
                f"data.scans='{item.rstrip('/')}/*/*{common}' (or one subfolder)")
    return msg


def _listed(names: list[str], k: int = 4) -> str:
    return ", ".join(names[:k]) + (", ..." if len(names) > k else "")


def scan_names(paths: list[Path]) -> list[str]:
    """One name per scan for the tables, ``poses.json`` and the messages: its file name, or where two scans'
    file names are the same (``a/scan.ply``, ``b/scan.ply``: per-scan export folders), as many of the folders
    above it as tell them apart."""
    parts = [Path(p).parts for p in paths]
    depth = [1] * len(paths)
    while True:
        names = ["/".join(q[-d:]) for q, d in zip(parts, depth)]
        seen: dict[str, list[int]] = {}
        for k, n in enumerate(names):
            seen.setdefault(n, []).append(k)
        clash = [k for ks in seen.values() if len(ks) > 1 for k in ks if depth[k] < len(parts[k])]
        if not clash:
            break
        for k in clash:
            depth[k] += 1
    return names


def read_poses(spec: str, names: list[str]) -> list[Optional[np.ndarray]]:
    """Each scan's ``T_world_scan`` from a Stanford ``.conf`` or from one 4x4 file per scan (by file stem); None
    for a scan without one (a note names them: they are registered, not evaluated), an error when fewer than two
    scans have one."""
    stems = [Path(n).stem for n in names]
    twice = sorted({n for n, st in zip(names, stems) if stems.count(st) > 1})
    if twice:
        raise InputError(f"data.poses {spec}: the scans {', '.join(twice)} have the same file stem, so their poses "
                         "cannot be told apart by name; give the scans distinct file names")
    s = expand_path(spec)
    if s.endswith(".conf"):
        conf = read_stanford_conf(s)
        by_stem = {Path(k).stem: v for k, v in conf.items()}
        poses = [conf.get(n, by_stem.get(Path(n).stem)) for n in names]
        return _some_poses(spec, names, poses, "no pose")
    p = Path(s).expanduser()
    files = sorted(p.iterdir()) if p.is_dir() else [Path(q) for q in sorted(globbing.glob(str(p)))]
    if not files:
        raise InputError(f"data.poses {spec}: no such file or folder ({p.absolute()})" if not any(c in s for c in "*?[")
                         else f"data.poses {spec}: the pattern matches no file")
    by_stem = {f.stem: f for f in files if f.is_file()}
    poses = [read_transform(by_stem[Path(n).stem], f"pose of {n}") if Path(n).stem in by_stem else None
             for n in names]
    return _some_poses(spec, names, poses, "no pose file (one 4x4 file per scan, named by the scan's stem)")


def _some_poses(spec: str, names: list[str], poses: list, missing_what: str) -> list[Optional[np.ndarray]]:
    """``poses`` when at least two scans have one (a note names the scans without: registered, not evaluated)."""
    missing = [n for n, T in zip(names, poses) if T is None]
    if len(names) - len(missing) < 2:
        raise InputError(f"data.poses {spec}: {missing_what} for {', '.join(missing[:5])}"
                         f"{', ...' if len(missing) > 5 else ''}: at least two scans need a pose to evaluate the set")
    if missing:
        note(f"data.poses {spec}: {missing_what} for {', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''}: "
             f"registered, not evaluated")
    return poses
