"""Reading and writing meshes, point clouds, transforms, Stanford ``.conf`` poses and landmark pairs.

Every reader validates what it reads and raises :class:`InputError` with one line naming the file and the
problem (missing, a link loop, a directory, empty, truncated, wrong counts, indices out of range). Header counts
are checked against the file's size before anything is allocated, and any parser's or library's exception
becomes such a line. Points with NaN/inf coordinates or normals are dropped and counted (:func:`read_input`).

Formats:
- meshes: PLY (ASCII and binary; ``face`` lists of any size are triangulated: fans for convex polygons, ear clipping otherwise, other list properties read
  and ignored; the Stanford scanner's ``range_grid`` element is triangulated as vcglib/MeshLab do), STL (ASCII
  and binary), OBJ (with ``\\`` line continuation), OFF (COFF, NOFF, CNOFF, STOFF; counts on the keyword line);
- point clouds: PLY without faces, PCD (via Open3D), text (.xyz .txt .pts .csv .asc) and NPY with columns
  x y z [nx ny nz] [r g b [a]], named by a header line or ``columns``, or detected (:func:`detect_columns`);
- ``pkg:DIST/REL/PATH`` names a file shipped inside an installed Python package (e.g.
  ``pkg:pymeshfix/examples/StanfordBunny.ply``).
"""

from __future__ import annotations

import csv
import os

import numpy as np

from scanreg.errors import InputError, one_line, warn
from scanreg.geometry import (Cloud, Geometry, Mesh, make_T, rows_all, rows_any, submesh, validate_mesh,
                              validate_points)
from scanreg.io.clouds import _read_npy, _read_pcd, _read_xyz
from scanreg.io.meshes import _read_obj, _read_off, _read_stl
from scanreg.io.paths import resolve_path
from scanreg.io.ply import _read_ply

MESH_EXTS = {".ply", ".stl", ".obj", ".off"}


CLOUD_EXTS = {".ply", ".pcd", ".xyz", ".txt", ".npy", ".pts", ".csv", ".asc"}


MIN_VALID_POINTS = 3
"""Fewest valid (finite) points a file may keep after its invalid ones are dropped."""


def read_geometry(path: str | os.PathLike, what: str = "input", columns: str | None = None) -> Geometry:
    """Read a mesh or a point cloud, deciding by extension and content (a PLY without faces is a cloud).
    Points with NaN/inf coordinates (or normals) are dropped with a warning (see :func:`read_input`)."""
    return read_input(path, what, columns)[0]


def read_input(path: str | os.PathLike, what: str = "input", columns: str | None = None) -> tuple[Geometry, int]:
    """Read a mesh or a point cloud and drop its invalid points: ``(geometry, number of points dropped)``.

    A cloud's points with NaN/inf coordinates or NaN/inf normals are removed (depth cameras write NaN for
    missing pixels); a mesh's NaN/inf vertices are removed with the faces that use them. The count is printed as
    a warning. ``columns`` names the columns of a text or ``.npy`` cloud (``"x y z nx ny nz r g b"``, ``-`` for
    a column to ignore); without it they are detected from the values (:func:`detect_columns`)."""
    p = resolve_path(path, what)
    ext = p.suffix.lower()
    label = f"{what} {path}"
    try:
        if ext == ".ply":
            g = _read_ply(p, label)
        elif ext == ".stl":
            g = _read_stl(p, label)
        elif ext == ".obj":
            g = _read_obj(p, label)
        elif ext == ".off":
            g = _read_off(p, label)
        elif ext in (".xyz", ".txt", ".pts", ".csv", ".asc"):
            g = _read_xyz(p, label, columns)
        elif ext == ".npy":
            g = _read_npy(p, label, columns)
        elif ext == ".pcd":
            g = _read_pcd(p, label)
        else:
            raise InputError(
                f"{label}: unsupported file type '{ext}' (meshes: .ply .stl .obj .off; clouds: .ply .pcd .xyz .txt "
                ".pts .csv .asc .npy)"
            )
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{label}: not enough memory to read it") from None
    except OSError as e:
        raise InputError(f"{label}: cannot read ({e.strerror or e})") from None
    except Exception as e:  # noqa: BLE001  # a parser's or a library's own exception is one line naming the file
        raise InputError(f"{label}: corrupt or unreadable file ({one_line(e)})") from None
    if isinstance(g, Mesh):
        g.source = label
        g, dropped = _drop_invalid_mesh(g, label)
    else:
        g, dropped = _drop_invalid_cloud(g, label)
        g.source = label
    check_resolution(g.vertices if isinstance(g, Mesh) else g.points, label)
    return g, dropped


FLOAT32_ERROR = 2e-3
"""A file whose coordinates are all 32-bit floats stops when their spacing at its largest coordinate exceeds this
share of its bounding-box diagonal (:func:`check_resolution`)."""
FLOAT32_WARN = 1e-5
"""... and is read with a warning above this share."""


def check_resolution(points: np.ndarray, label: str) -> None:
    """Stop (or warn) when a file's coordinates are 32-bit floats far from the origin: at a georeferenced offset
    (UTM metres, ~4e6) 32-bit floats are 0.25 apart, which can be the size of the scan itself. Such a file
    rounded its shape away when it was written (MeshFix then spent minutes and 24 GB on 0.15 m of bunny in lines,
    and a larger scan registered 34 deg off without a word). Judged from the values: every coordinate a float32
    and the float32 spacing at the largest magnitude above :data:`FLOAT32_ERROR` (:data:`FLOAT32_WARN`) of the
    diagonal. Double-precision files pass whatever their offset. (Judged by the values, it catches the binary
    formats that store 32-bit floats, PLY, PCD, STL, NPY; a text file written from 32-bit floats with 7-8
    significant digits, such as pandas' or ``%.8g``'s, is not caught. Whole numbers where 32-bit floats are less than
    1 apart pass: integer data, which such floats hold exactly.)"""
    if len(points) < 2:
        return
    lo, hi = points.min(axis=0), points.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    big = float(max(np.abs(lo).max(), np.abs(hi).max()))
    step = float(np.spacing(np.float32(big)))
    if not diag > 0 or step <= FLOAT32_WARN * diag:
        return
    if not (points.astype(np.float32) == points).all():
        return  # stored with more precision than 32-bit floats have
    if step < 1 and (np.round(points) == points).all():
        return  # whole numbers where 32-bit floats have fractions: no such float rounded them (integer text)
    share = step / diag
    what = (f"{label}: its coordinates are 32-bit floats up to {big:.4g}, where such floats are {step:.3g} apart: "
            f"{share:.2g} of its size ({diag:.4g} across)")
    if share > FLOAT32_ERROR:
        raise InputError(f"{what}: too coarse to register it (its shape was rounded when it was written); write it "
                         "with double precision, or subtract an offset (the same for every scan) first")
    warn(f"{what}: the registration can be no finer than that; write it with double precision or without the "
         "offset")


def _drop_invalid_mesh(m: Mesh, label: str) -> tuple[Mesh, int]:
    v = np.asarray(m.vertices)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        validate_points(v, label)  # raises the shape / empty error
    bad = ~rows_all(np.isfinite(v))
    if not bad.any():
        return validate_mesh(m), 0
    # the index checks first, on finite stand-ins, so that a bad index is reported as such
    checked = validate_mesh(Mesh(np.where(bad[:, None], 0.0, v), m.faces, label))
    keep = ~rows_any(bad[checked.faces])
    n_bad = int(bad.sum())
    if not keep.any():
        raise InputError(f"{label}: {n_bad} point(s) with NaN or infinite coordinates, and every face uses one: "
                         "no face left")
    out = submesh(Mesh(np.where(bad[:, None], 0.0, v).astype(np.float64), checked.faces, label), keep)
    warn(f"{label}: dropped {n_bad} of {len(v)} vertices with NaN or infinite coordinates and the "
          f"{int((~keep).sum())} face(s) that use them")
    return validate_mesh(out), n_bad


MISSING_NORMALS_SHARE = 0.05
"""A cloud whose points lack a normal (zero, NaN or infinite) at up to this share loses those points (a mesh's
vertices that no face uses, exported with its vertex normals); above it, the cloud loses its normals instead and
keeps every point (a third of a scan's points were dropped for their zero normals)."""


def _drop_invalid_cloud(c: Cloud, label: str) -> tuple[Cloud, int]:
    pts = np.asarray(c.points)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        validate_points(pts, label)  # raises the shape / empty error
    good_p = rows_all(np.isfinite(pts))
    normals = None if c.normals is None else np.asarray(c.normals, dtype=np.float64)
    if normals is not None and normals.shape != pts.shape:
        raise InputError(f"{label}: {len(normals)} normals for {len(pts)} points")
    good_n = np.ones(len(pts), bool) if normals is None else rows_all(np.isfinite(normals))
    zero_n = np.zeros(len(pts), bool)
    if normals is not None:
        zero_n = good_n & (np.linalg.norm(np.where(good_n[:, None], normals, 1.0), axis=1) < 1e-12)
        if zero_n[good_n].all():  # every normal zero (an exporter's placeholder): an unoriented cloud
            normals, good_n, zero_n = None, np.ones(len(pts), bool), np.zeros(len(pts), bool)
        missing = int(((~good_n | zero_n) & good_p).sum())
        if missing > MISSING_NORMALS_SHARE * good_p.sum():  # many: the normals go, not the points
            warn(f"{label}: {missing} of {int(good_p.sum())} point(s) have zero, NaN or infinite normals: the "
                 "normals are ignored (the cloud is read as one without normals) and every such point kept")
            normals, good_n, zero_n = None, np.ones(len(pts), bool), np.zeros(len(pts), bool)
    # a few zero normals (vertices no face uses, pixels without a surface): those points go, not every normal
    good = good_p & good_n & ~zero_n
    n, n_bad = len(pts), int((~good).sum())
    parts = [f"{int((~good_p).sum())} point(s) with NaN or infinite coordinates"] if (~good_p).any() else []
    if (~good_n & good_p).any():
        parts.append(f"{int((~good_n & good_p).sum())} point(s) with NaN or infinite normals")
    if (zero_n & good_p).any():
        parts.append(f"{int((zero_n & good_p).sum())} point(s) with zero normals")
    what = " and ".join(parts) or "no point"
    if n_bad and good.sum() < MIN_VALID_POINTS:
        raise InputError(f"{label}: {what} (of {n}); {int(good.sum())} valid left, at least {MIN_VALID_POINTS} "
                         "are needed")
    extra = dict(c.extra)
    if n_bad:
        warn(f"{label}: dropped {what} (of {n})")
        pts, normals = pts[good], None if normals is None else normals[good]
        extra = {k: (v[good] if isinstance(v, np.ndarray) and len(v) == n else v) for k, v in extra.items()}
    out = Cloud(validate_points(pts, label), None, c.source, extra)
    if normals is not None:
        out.normals = _clean_normals(normals, label)
    return out, n_bad


def read_mesh(path: str | os.PathLike, what: str = "mesh") -> Mesh:
    g = read_geometry(path, what)
    if not isinstance(g, Mesh):
        raise InputError(f"{what} {path}: has no faces (a point cloud), expected a triangle mesh")
    return g


def _clean_normals(n: np.ndarray, label: str) -> np.ndarray:
    """Normals as unit vectors (the points with NaN or zero normals already dropped, :func:`_drop_invalid_cloud`)."""
    n = np.asarray(n, dtype=np.float64)
    if n.shape[1] != 3 or not np.isfinite(n).all():
        raise InputError(f"{label}: normals contain NaN or infinite values")
    return n / np.linalg.norm(n, axis=1)[:, None]


def read_transform(path: str | os.PathLike, what: str = "transform") -> np.ndarray:
    """A 4x4 rigid transform from text (16 numbers, whitespace or comma separated) or ``.npy``."""
    p = resolve_path(path, what)
    label = f"{what} {path}"
    try:
        if p.suffix.lower() == ".npy":
            T = np.load(p, allow_pickle=False).astype(np.float64)
        else:
            T = np.array(p.read_text().replace(",", " ").split(), dtype=np.float64)
    except ValueError as e:
        raise InputError(f"{label}: not a numeric 4x4 matrix ({e})") from None
    if T.size != 16:
        raise InputError(f"{label}: expected 16 numbers (a 4x4 matrix), found {T.size}")
    T = T.reshape(4, 4)
    if not np.isfinite(T).all():
        raise InputError(f"{label}: contains NaN or infinite values")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise InputError(f"{label}: last row must be 0 0 0 1, found {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise InputError(f"{label}: the upper-left 3x3 block is not a rotation")
    # rotations stored in single precision (3DMatch's gt.npy: |R R^T - I| ~ 7e-5) are projected onto the
    # nearest rotation, so that errors measured against them are not biased by the rounding
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-12:
        U, _, Vt = np.linalg.svd(R)
        T = T.copy()
        T[:3, :3] = U @ Vt
    return T


def read_stanford_conf(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Poses of a Stanford ``.conf``: ``{scan file name: T_world_scan}``.

    Lines ``bmesh FILE tx ty tz qx qy qz qw``; with ``R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()`` a
    scan point maps to the common frame as ``p_world = R.T @ p + t`` (the convention verified for the bunny).
    """
    from scipy.spatial.transform import Rotation

    p = resolve_path(path, "Stanford .conf")
    poses = {}
    for line in p.read_text().splitlines():
        w = line.split()
        if not w or w[0] != "bmesh":
            continue
        if len(w) != 9:
            raise InputError(f"Stanford .conf {path}: bad line '{line}' (need: bmesh FILE tx ty tz qx qy qz qw)")
        t = np.array(w[2:5], dtype=np.float64)
        R = Rotation.from_quat(np.array(w[5:9], dtype=np.float64)).as_matrix()
        poses[w[1]] = make_T(R.T, t)
    if not poses:
        raise InputError(f"Stanford .conf {path}: no 'bmesh' lines")
    return poses


def read_landmarks(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Landmark pairs from CSV: ``(target (K, 3), source (K, 3))``.

    Six numeric columns per row, target x y z then source x y z; an optional header row is skipped; with a
    header whose names include ``target_x ... source_z``, columns are taken by name.
    """
    p = resolve_path(path, "landmarks")
    rows = list(csv.reader(p.read_text().splitlines()))
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise InputError(f"landmarks {path}: no rows")
    cols = None
    try:
        float(rows[0][0])
    except ValueError:
        header = [h.strip().lower() for h in rows[0]]
        rows = rows[1:]
        want = [f"{r}_{c}" for r in ("target", "source") for c in "xyz"]
        if all(w in header for w in want):
            cols = [header.index(w) for w in want]
    try:
        arr = np.array([[float(r[i]) for i in (cols or range(6))] for r in rows], dtype=np.float64)
    except (ValueError, IndexError):
        raise InputError(f"landmarks {path}: each row needs 6 numbers (target x y z, source x y z)") from None
    if len(arr) < 3:
        raise InputError(f"landmarks {path}: {len(arr)} pair(s); at least 3 are needed")
    if not np.isfinite(arr).all():
        raise InputError(f"landmarks {path}: contains NaN or infinite values")
    return arr[:, :3], arr[:, 3:]
