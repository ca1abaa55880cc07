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
import errno
import importlib.util
import os
import re
import stat
import struct
from pathlib import Path

import numpy as np

from scanreg.errors import InputError
from scanreg.geometry import (Cloud, Geometry, Mesh, make_T, rows_all, rows_any, submesh, validate_mesh,
                              validate_points)

MESH_EXTS = {".ply", ".stl", ".obj", ".off"}
CLOUD_EXTS = {".ply", ".pcd", ".xyz", ".txt", ".npy", ".pts", ".csv", ".asc"}


def resolve_path(path: str | os.PathLike, what: str = "file") -> Path:
    """Resolve ``pkg:`` names and check that ``path`` is an existing, non-empty regular file."""
    s = str(path)
    if s.startswith("pkg:"):
        pkg, _, rel = s[4:].partition("/")
        spec = importlib.util.find_spec(pkg)
        if spec is None or not spec.submodule_search_locations:
            raise InputError(f"{what} {s}: Python package '{pkg}' is not installed")
        p = Path(list(spec.submodule_search_locations)[0]) / rel
    else:
        p = Path(os.path.expanduser(s))
    try:
        st = p.stat()
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise InputError(f"{what} {s}: symbolic link loop (too many levels of symbolic links)") from None
        if e.errno == errno.ENOENT and p.is_symlink():
            raise InputError(f"{what} {s}: broken symbolic link (to '{os.readlink(p)}', which does not exist)") \
                from None
        if e.errno == errno.ENOENT:
            full = p.absolute()
            raise InputError(f"{what} {s}: no such file" + ("" if str(full) == s else f" ({full})")) from None
        raise InputError(f"{what} {s}: cannot read ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{what} {s}: is a directory, expected a file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{what} {s}: not a regular file (a device, pipe or socket)")
    if st.st_size == 0:
        raise InputError(f"{what} {s}: file is empty (0 bytes)")
    if not os.access(p, os.R_OK):
        raise InputError(f"{what} {s}: permission denied")
    return p


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
    except Exception as e:  # noqa: BLE001: a parser's or a library's own exception is one line naming the file
        raise InputError(f"{label}: corrupt or unreadable file ({_one_line(e)})") from None
    if isinstance(g, Mesh):
        g.source = label
        g, dropped = _drop_invalid_mesh(g, label)
    else:
        g, dropped = _drop_invalid_cloud(g, label)
        g.source = label
    return g, dropped


def _one_line(e: BaseException, limit: int = 160) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:limit]}" if text else type(e).__name__


def _warn(msg: str) -> None:
    print(f"warning: {msg}", flush=True)


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
    _warn(f"{label}: dropped {n_bad} of {len(v)} vertices with NaN or infinite coordinates and the "
          f"{int((~keep).sum())} face(s) that use them")
    return validate_mesh(out), n_bad


def _drop_invalid_cloud(c: Cloud, label: str) -> tuple[Cloud, int]:
    pts = np.asarray(c.points)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        validate_points(pts, label)  # raises the shape / empty error
    good_p = rows_all(np.isfinite(pts))
    normals = None if c.normals is None else np.asarray(c.normals, dtype=np.float64)
    if normals is not None and normals.shape != pts.shape:
        raise InputError(f"{label}: {len(normals)} normals for {len(pts)} points")
    good_n = np.ones(len(pts), bool) if normals is None else rows_all(np.isfinite(normals))
    good = good_p & good_n
    n, n_bad = len(pts), int((~good).sum())
    parts = [f"{int((~good_p).sum())} point(s) with NaN or infinite coordinates"]
    if normals is not None and (~good_n & good_p).any():
        parts = parts[:1] if (~good_p).any() else []
        parts.append(f"{int((~good_n & good_p).sum())} point(s) with NaN or infinite normals")
    what = " and ".join(parts)
    if n_bad and good.sum() < MIN_VALID_POINTS:
        raise InputError(f"{label}: {what} (of {n}); {int(good.sum())} valid left, at least {MIN_VALID_POINTS} "
                         "are needed")
    extra = dict(c.extra)
    if n_bad:
        _warn(f"{label}: dropped {what} (of {n})")
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


def _clean_normals(n: np.ndarray, label: str) -> np.ndarray | None:
    n = np.asarray(n, dtype=np.float64)
    if n.shape[1] != 3 or not np.isfinite(n).all():
        raise InputError(f"{label}: normals contain NaN or infinite values")
    norm = np.linalg.norm(n, axis=1)
    if (norm < 1e-12).any():
        return None  # zero normals: treat the cloud as unoriented
    return n / norm[:, None]


# ------------------------------------------------------------------------------------------------------ PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _parse_ply_header(f, label: str):
    magic = f.readline().strip()
    if magic != b"ply":
        raise InputError(f"{label}: not a PLY file (first line is not 'ply')")
    fmt, elements, info = None, [], {}
    while True:
        line = f.readline()
        if not line:
            raise InputError(f"{label}: truncated PLY header (no 'end_header')")
        words = line.decode("ascii", "replace").split()
        if not words:
            continue
        key = words[0]
        if key == "format":
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"{label}: bad PLY element line '{line.strip().decode(errors='replace')}'")
            elements.append((words[1], int(words[2]), []))
        elif key == "property":
            if not elements:
                raise InputError(f"{label}: PLY property before any element")
            if words[1] == "list":
                if len(words) != 5 or words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                    raise InputError(f"{label}: bad PLY list property '{' '.join(words)}'")
                elements[-1][2].append((words[4], _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
            else:
                if len(words) != 3 or words[1] not in _PLY_TYPES:
                    raise InputError(f"{label}: bad PLY property '{' '.join(words)}'")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]], None))
        elif key == "obj_info" and len(words) >= 3:
            info[words[1]] = words[2]
        elif key == "end_header":
            break
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{label}: unknown PLY format '{fmt}'")
    return fmt, elements, info


def _read_ply(p: Path, label: str) -> Geometry:
    with open(p, "rb") as f:
        fmt, elements, info = _parse_ply_header(f, label)
        data = f.read()
    _check_ply_claims(fmt, elements, len(data), label)
    if fmt == "ascii":
        parsed = _read_ply_ascii(data, elements, label)
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        parsed, pos = {}, 0
        for name, n, props in elements:
            parsed[name], pos = _read_ply_element_binary(data, pos, endian, name, n, props, label)
    if "vertex" not in parsed:
        raise InputError(f"{label}: PLY has no 'vertex' element")
    vert = parsed["vertex"]
    for c in "xyz":
        if c not in vert:
            raise InputError(f"{label}: PLY vertices lack the '{c}' property")
    pts = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    if "face" in parsed:
        face = parsed["face"]
        key = "vertex_indices" if "vertex_indices" in face else ("vertex_index" if "vertex_index" in face else None)
        if key is None:
            raise InputError(f"{label}: PLY faces lack a 'vertex_indices' list")
        tris = _triangulate(face[key], pts, label)
        if len(tris):
            return Mesh(pts, tris)
    if "range_grid" in parsed:
        try:
            cols, rows = int(info["num_cols"]), int(info["num_rows"])
        except (KeyError, ValueError):
            raise InputError(f"{label}: PLY range_grid without obj_info num_cols/num_rows") from None
        grid = parsed["range_grid"]
        lists = next(iter(grid.values()))
        if len(lists) != cols * rows:
            raise InputError(f"{label}: range_grid has {len(lists)} cells, header says {cols} x {rows}")
        return Mesh(pts, _triangulate_range_grid(lists, cols, rows, len(pts), label))
    normals = None
    if all(k in vert for k in ("nx", "ny", "nz")):
        normals = np.stack([vert["nx"], vert["ny"], vert["nz"]], axis=1)
    extra = {}
    for names in (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue"), ("r", "g", "b")):
        if all(k in vert for k in names):
            rgb = np.stack([np.asarray(vert[k], dtype=np.float64) for k in names], axis=1)
            extra["colors"] = _to_rgb8(rgb)
            break
    return Cloud(pts, normals, extra=extra)


def _check_ply_claims(fmt: str, elements, size: int, label: str) -> None:
    """The header's element counts against the bytes that follow it, before anything is allocated: a binary
    row takes at least its scalars' and list counts' bytes, an ASCII value at least a character and a separator."""
    need = 0
    for name, n, props in elements:
        per = 2 * len(props) if fmt == "ascii" else sum(np.dtype(t1).itemsize for _, t1, _ in props)
        need += n * per
        if need - (fmt == "ascii") > size:
            raise InputError(
                f"{label}: truncated PLY data: the header announces {n} '{name}' element(s), which need at least "
                f"{need} bytes, but {size} bytes follow the header"
            )


class _AsciiTokens:
    def __init__(self, data: bytes, label: str):
        self.tokens = data.split()
        self.pos = 0
        self.label = label

    def take(self, n: int) -> list[bytes]:
        if self.pos + n > len(self.tokens):
            raise InputError(f"{self.label}: truncated PLY data (fewer values than the header announces)")
        out = self.tokens[self.pos : self.pos + n]
        self.pos += n
        return out


def _read_ply_ascii(data: bytes, elements, label: str) -> dict:
    """ASCII PLY data as one stream of values; when that does not match the header (values left over, or a
    list count that is not an integer), row by row, one line per element, values past the header's properties
    ignored with a warning (VCGLIB writes per-face colour lists that its header declares as scalars)."""
    error, parsed = None, None
    try:
        tok = _AsciiTokens(data, label)
        parsed = {name: _read_ply_element_ascii(tok, name, n, props, label) for name, n, props in elements}
        if tok.pos == len(tok.tokens):
            return parsed
    except (InputError, ValueError) as e:
        error = e
    try:
        parsed, extra_rows = _read_ply_ascii_lines(data, elements, label)
    except (InputError, ValueError):
        if parsed is not None:  # the stream was fine but for values after the last element
            _warn(f"{label}: {len(tok.tokens) - tok.pos} value(s) after the PLY's last element ignored")
            return parsed
        if isinstance(error, InputError):
            raise error from None
        raise InputError(f"{label}: PLY data do not match the header ({_one_line(error)})") from None
    if extra_rows:
        _warn(f"{label}: {extra_rows} PLY row(s) hold values past the header's properties; ignored")
    return parsed


def _read_ply_ascii_lines(data: bytes, elements, label: str) -> tuple[dict, int]:
    lines = [ln for ln in data.split(b"\n") if ln.strip()]
    need = sum(n for _, n, _ in elements)
    if len(lines) < need:
        raise InputError(f"{label}: truncated PLY data ({need} rows announced, {len(lines)} lines)")
    parsed, i, extra_rows = {}, 0, 0
    for name, n, props in elements:
        rows = lines[i : i + n]
        if not any(p[2] is not None for p in props):
            k = len(props)
            words = [r.split() for r in rows]
            if any(len(w) < k for w in words):
                raise InputError(f"{label}: a PLY '{name}' row has fewer than {k} values")
            extra_rows += sum(len(w) > k for w in words)
            vals = np.array([w[:k] for w in words], dtype=np.float64).reshape(n, k)
            parsed[name] = {pname: vals[:, j] for j, (pname, _, _) in enumerate(props)}
        else:
            out = {pname: [] for pname, _, _ in props}
            for r in rows:
                tok = _AsciiTokens(r, label)
                for key, v in _read_ply_element_ascii(tok, name, 1, props, label).items():
                    out[key].append(v[0])
                extra_rows += tok.pos < len(tok.tokens)
            parsed[name] = out
        i += n
    return parsed, extra_rows


def _read_ply_element_ascii(tok: _AsciiTokens, name, n, props, label):
    has_list = any(p[2] is not None for p in props)
    if not has_list:
        vals = np.array(tok.take(n * len(props)), dtype=np.float64).reshape(n, len(props))
        return {pname: vals[:, i] for i, (pname, _, _) in enumerate(props)}
    out = {pname: [] for pname, _, _ in props}
    for _ in range(n):
        for pname, t1, t2 in props:
            if t2 is None:
                out[pname].append(float(tok.take(1)[0]))
            else:
                k = int(tok.take(1)[0])
                if k < 0:
                    raise InputError(f"{label}: negative list length in PLY element '{name}'")
                out[pname].append(np.array(tok.take(k), dtype=np.float64 if t2[0] == "f" else np.int64))
    return out


def _read_ply_element_binary(data, pos, endian, name, n, props, label):
    has_list = any(p[2] is not None for p in props)
    if not has_list:
        dt = np.dtype([(pname, endian + t) for pname, t, _ in props])
        need = dt.itemsize * n
        if pos + need > len(data):
            raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
        arr = np.frombuffer(data, dtype=dt, count=n, offset=pos)
        return {pname: arr[pname].astype(np.float64) for pname, _, _ in props}, pos + need
    # Fast path: one list property with a fixed count on every row (typical 'face' of triangles).
    if len(props) == 1:
        pname, tcount, titem = props[0]
        cdt, idt = np.dtype(endian + tcount), np.dtype(endian + titem)
        if n == 0:
            return {pname: []}, pos
        if pos + cdt.itemsize > len(data):
            raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
        k = int(np.frombuffer(data, cdt, 1, pos)[0])
        row = cdt.itemsize + k * idt.itemsize
        if k > 0 and pos + row * n <= len(data):
            rec = np.dtype([("c", cdt), ("v", idt, (k,))])
            arr = np.frombuffer(data, rec, n, pos)
            if (arr["c"] == k).all():
                return {pname: arr["v"].astype(np.int64)}, pos + row * n
        if cdt.itemsize == 1:  # variable-length lists with byte counts (Stanford range_grid, mixed polygons)
            rows, end = _ragged_uchar_lists(data, pos, n, idt, name, label)
            return {pname: rows}, end
    out = {pname: [] for pname, _, _ in props}
    dv = memoryview(data)
    for _ in range(n):
        for pname, t1, t2 in props:
            if t2 is None:
                d = np.dtype(endian + t1)
                if pos + d.itemsize > len(data):
                    raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
                out[pname].append(float(np.frombuffer(dv, d, 1, pos)[0]))
                pos += d.itemsize
            else:
                cd, idt = np.dtype(endian + t1), np.dtype(endian + t2)
                if pos + cd.itemsize > len(data):
                    raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
                k = int(np.frombuffer(dv, cd, 1, pos)[0])
                pos += cd.itemsize
                if k < 0 or pos + k * idt.itemsize > len(data):
                    raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
                out[pname].append(np.frombuffer(dv, idt, k, pos).astype(np.float64 if idt.kind == "f" else np.int64))
                pos += k * idt.itemsize
    return out, pos


class Ragged:
    """Rows of different lengths stored flat: ``values[offsets[i]:offsets[i] + counts[i]]`` is row i."""

    def __init__(self, counts: np.ndarray, values: np.ndarray):
        self.counts, self.values = counts, values
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64) if len(counts) else counts

    def __len__(self) -> int:
        return len(self.counts)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.values[self.offsets[i]:self.offsets[i] + self.counts[i]]

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def _ragged_uchar_lists(data, pos: int, n: int, idt: np.dtype, name: str, label: str) -> tuple[Ragged, int]:
    """``n`` binary list rows ``[uchar count][count items]`` from byte ``pos``: one pass over the counts in
    Python (bytes indexing), then one vectorised gather of the items. Returns the rows and the end position."""
    size, end = idt.itemsize, len(data)
    starts, counts = [0] * n, [0] * n
    p = pos
    for r in range(n):
        if p >= end:
            raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
        c = data[p]
        starts[r], counts[r] = p + 1, c
        p += 1 + c * size
    if p > end:
        raise InputError(f"{label}: truncated PLY data in element '{name}' (file ends early)")
    counts_a = np.asarray(counts, dtype=np.int64)
    total = int(counts_a.sum())
    first = np.repeat(np.asarray(starts, dtype=np.int64), counts_a)
    within = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(counts_a) - counts_a, counts_a)
    byte_idx = (first + within * size)[:, None] + np.arange(size)
    raw = np.frombuffer(data, np.uint8)[byte_idx.ravel()] if total else np.zeros(0, np.uint8)
    return Ragged(counts_a, raw.view(idt).astype(np.int64)), p


def _polygon_normal(P: np.ndarray) -> np.ndarray:
    """Newell's normal of polygons ``P`` (M, k, 3): robust for non-planar and non-convex polygons."""
    Q = np.roll(P, -1, axis=1)
    return np.stack([((P[..., 1] - Q[..., 1]) * (P[..., 2] + Q[..., 2])).sum(1),
                     ((P[..., 2] - Q[..., 2]) * (P[..., 0] + Q[..., 0])).sum(1),
                     ((P[..., 0] - Q[..., 0]) * (P[..., 1] + Q[..., 1])).sum(1)], axis=1)


def _convex(P: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Which polygons ``P`` (M, k, 3) turn the same way (or not at all) at every corner about their normal ``n``."""
    e = np.roll(P, -1, axis=1) - P
    turn = np.einsum("mkj,mj->mk", np.cross(e, np.roll(e, -1, axis=1)), n)
    scale = np.abs(turn).max(axis=1, keepdims=True) + 1e-300
    return (turn >= -1e-9 * scale).all(axis=1)


def _ear_clip(poly: np.ndarray, P: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Triangles of one polygon (vertex ids ``poly``, points ``P``) by ear clipping (mapbox_earcut) in the plane
    normal to ``n``, wound like the polygon."""
    import mapbox_earcut

    a = np.eye(3)[np.argmin(np.abs(n))]
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    v = np.cross(n / np.linalg.norm(n), u)
    xy = np.stack([(P - P[0]) @ u, (P - P[0]) @ v], axis=1)
    idx = mapbox_earcut.triangulate_float64(xy, np.array([len(P)], dtype=np.uint32)).reshape(-1, 3)
    if len(idx) != len(P) - 2:  # a self-touching or degenerate outline: earcut gives up; a fan keeps the faces
        idx = np.stack([np.zeros(len(P) - 2, int), np.arange(1, len(P) - 1), np.arange(2, len(P))], axis=1)
    tris = poly[idx]
    # keep the polygon's winding: earcut's triangles turn one way in the (u, v) plane, which faces +n
    return tris if _polygon_normal(P[None])[0] @ n >= 0 else tris[:, ::-1]


def _triangulate(faces, pts: np.ndarray, label: str) -> np.ndarray:
    """Triangles from polygon index lists (an (M, k) array or a list of arrays). Convex polygons become fans
    (vectorised); non-convex ones (an L-shaped hexagon, say) are ear-clipped in their best-fit plane, so that
    the triangles cover exactly the polygon. Winding follows the polygon's."""
    groups: dict[int, list] = {}
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        groups = {faces.shape[1]: [faces]}
    elif isinstance(faces, Ragged):  # vectorised per polygon size
        for k in np.unique(faces.counts):
            rows = np.flatnonzero(faces.counts == k)
            groups[int(k)] = [faces.values[faces.offsets[rows][:, None] + np.arange(k)]]
    else:
        for poly in faces:
            groups.setdefault(len(poly), []).append(poly)
    out = []
    for k, polys in sorted(groups.items()):
        F = np.asarray(polys[0] if len(polys) == 1 and isinstance(polys[0], np.ndarray) and polys[0].ndim == 2
                       else polys, dtype=np.int64).reshape(-1, k)
        if k < 3:
            raise InputError(f"{label}: a face with {k} vertices (need at least 3)")
        if k == 3:
            out.append(F)
            continue
        if F.size and (F.min() < 0 or F.max() >= len(pts)):
            out.append(F[:, [0, 1, 2]])  # index errors are reported by the mesh validation
            continue
        P = pts[F]
        n = _polygon_normal(P)
        convex = _convex(P, n)
        out += [F[convex][:, [0, i, i + 1]] for i in range(1, k - 1)]
        out += [_ear_clip(F[j], P[j], n[j]) for j in np.flatnonzero(~convex)]
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 3), np.int64)


def _triangulate_range_grid(lists, cols: int, rows: int, nverts: int, label: str) -> np.ndarray:
    """Faces of a scanner range grid, as vcglib's FaceGrid builds them on PLY import.

    Each grid cell (a, b / c, d) = (r, c), (r, c+1) / (r+1, c), (r+1, c+1) gives triangles (a, d, c) and
    (a, b, d) when their three samples exist; if neither does, it tries the other diagonal: (c, a, b), (b, d, c).
    """
    idx = np.full(cols * rows, -1, dtype=np.int64)
    if isinstance(lists, Ragged):
        if len(lists) > len(idx):
            raise InputError(f"{label}: range_grid has {len(lists)} cells for a {cols} x {rows} grid")
        has = np.flatnonzero(lists.counts > 0)
        idx[has] = lists.values[lists.offsets[has]]
    else:
        for i, cell in enumerate(lists):
            if len(cell):
                idx[i] = cell[0]
    if idx.max() >= nverts:
        raise InputError(f"{label}: range_grid refers to vertex {idx.max()} of {nverts}")
    g = idx.reshape(rows, cols)
    a, b, c, d = g[:-1, :-1].ravel(), g[:-1, 1:].ravel(), g[1:, :-1].ravel(), g[1:, 1:].ravel()
    ok = lambda *xs: np.logical_and.reduce([x >= 0 for x in xs])  # noqa: E731
    t1, t2 = ok(a, d, c), ok(a, b, d)
    none = ~(t1 | t2)
    t3, t4 = none & ok(c, a, b), none & ok(b, d, c)
    cells = [(t1, (a, d, c)), (t2, (a, b, d)), (t3, (c, a, b)), (t4, (b, d, c))]
    # keep vcglib's face order: per cell in row-major order, then by triangle kind
    order_cell, order_kind, tris = [], [], []
    for kind, (m, (x, y, z)) in enumerate(cells):
        sel = np.flatnonzero(m)
        order_cell.append(sel)
        order_kind.append(np.full(len(sel), kind))
        tris.append(np.stack([x[sel], y[sel], z[sel]], axis=1))
    order = np.lexsort((np.concatenate(order_kind), np.concatenate(order_cell)))
    return np.concatenate(tris)[order]


# ------------------------------------------------------------------------------------------------ STL / OBJ / OFF


def _merge_vertices(tri_pts: np.ndarray) -> Mesh:
    flat = tri_pts.reshape(-1, 3)
    uniq, inv = np.unique(flat, axis=0, return_inverse=True)
    return Mesh(uniq.astype(np.float64), inv.reshape(-1, 3).astype(np.int64))


def _read_stl(p: Path, label: str) -> Mesh:
    data = p.read_bytes()
    if len(data) >= 84:
        n = struct.unpack("<I", data[80:84])[0]
        if 84 + 50 * n == len(data):
            rec = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
            arr = np.frombuffer(data, rec, n, 84)
            if n == 0:
                raise InputError(f"{label}: STL has no triangles")
            return _merge_vertices(arr["v"].astype(np.float64))
    head = data[:512].lstrip().lower()
    if not head.startswith(b"solid"):
        raise InputError(f"{label}: not an STL file (binary size does not match its triangle count, and no 'solid')")
    verts = re.findall(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", data)
    if not verts:
        raise InputError(f"{label}: ASCII STL has no vertices")
    if len(verts) % 3:
        raise InputError(f"{label}: truncated ASCII STL ({len(verts)} vertices, not a multiple of 3)")
    return _merge_vertices(np.array(verts, dtype=np.float64).reshape(-1, 3, 3))


def _read_obj(p: Path, label: str) -> Geometry:
    verts, normals, polys = [], [], []
    text = p.read_text(errors="replace")
    if "\\" in text:  # a line ending in a backslash continues on the next one
        text = re.sub(r"\\[ \t]*\r?\n", " ", text)
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.startswith("v "):
            w = line.split()
            if len(w) < 4:
                raise InputError(f"{label}: line {lineno}: vertex needs 3 coordinates")
            verts.append(w[1:4])
        elif line.startswith("vn "):
            normals.append(line.split()[1:4])
        elif line.startswith("f "):
            idx = []
            for tok in line.split()[1:]:
                i = int(tok.split("/")[0])
                if i == 0:
                    raise InputError(f"{label}: line {lineno}: face index 0 (OBJ indices start at 1)")
                idx.append(i - 1 if i > 0 else len(verts) + i)
            if len(idx) < 3:
                raise InputError(f"{label}: line {lineno}: a face with fewer than 3 vertices")
            polys.append(idx)
    if not verts:
        raise InputError(f"{label}: OBJ has no vertices")
    pts = np.array(verts, dtype=np.float64)
    if not polys:
        n = np.array(normals, dtype=np.float64) if len(normals) == len(verts) else None
        return Cloud(pts, n)
    return Mesh(pts, _triangulate(polys, pts, label))


_OFF_KEY = re.compile(r"^(ST)?(C)?(N)?(4)?(n)?OFF$")


def _read_off(p: Path, label: str) -> Mesh:
    """OFF and its variants with per-vertex texture coordinates, colours or normals (``STOFF``, ``COFF``,
    ``NOFF``, ``CNOFF``); the counts may follow the keyword on its line. Only x y z of a vertex line are used."""
    text = p.read_text(errors="replace")
    lines = [ln.split("#")[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    glued = re.match(r"^((ST)?C?N?4?n?OFF)(?=\d|\s|$)(.*)$", lines[0]) if lines else None  # 'OFF8 6 12' too
    first = [glued.group(1), *glued.group(3).split()] if glued else []
    key = _OFF_KEY.match(first[0]) if first else None
    if key is None:
        raise InputError(f"{label}: not an OFF file (first word is not OFF, COFF, NOFF, CNOFF or STOFF)")
    if key.group(4) or key.group(5):
        raise InputError(f"{label}: '{first[0]}' (4D or n-dimensional OFF) is not supported; only 3D OFF is")
    head, rest = first[1:], lines[1:]
    if not head:
        if not rest:
            raise InputError(f"{label}: truncated OFF (no vertex and face counts)")
        head, rest = rest[0].split(), rest[1:]
    if len(head) < 2:
        raise InputError(f"{label}: OFF counts line needs the numbers of vertices and faces, found '{' '.join(head)}'")
    nv, nf = int(head[0]), int(head[1])
    if nv < 0 or nf < 0:
        raise InputError(f"{label}: negative OFF counts ({nv} vertices, {nf} faces)")
    if len(rest) < nv + nf:
        raise InputError(f"{label}: truncated OFF ({nv} vertices and {nf} faces announced, {len(rest)} lines)")
    pts = np.array([ln.split()[:3] for ln in rest[:nv]], dtype=np.float64)
    polys = []
    for ln in rest[nv : nv + nf]:
        w = ln.split()
        k = int(w[0])
        if len(w) < k + 1:
            raise InputError(f"{label}: OFF face line '{ln}' has fewer than {k} indices")
        polys.append([int(x) for x in w[1 : k + 1]])
    if not polys:
        raise InputError(f"{label}: OFF has no faces")
    return Mesh(pts, _triangulate(polys, pts, label))


# ------------------------------------------------------------------------------------------------ clouds

COLUMN_NAMES = {
    "x": "x", "y": "y", "z": "z", "nx": "nx", "ny": "ny", "nz": "nz",
    "normal_x": "nx", "normal_y": "ny", "normal_z": "nz", "r": "r", "g": "g", "b": "b", "a": "a",
    "red": "r", "green": "g", "blue": "b", "alpha": "a", "-": "-", "_": "-", "skip": "-",
}
"""Column names accepted by ``data.columns`` and in a text file's header line (``-``: ignore the column)."""


def _parse_columns(spec, n: int, where: str) -> list[str]:
    names = spec.replace(",", " ").split() if isinstance(spec, str) else [str(x) for x in spec]
    out = []
    for w in names:
        if w.lower() not in COLUMN_NAMES:
            raise InputError(f"{where}: unknown column '{w}' (use x y z nx ny nz r g b a, or - to ignore one)")
        out.append(COLUMN_NAMES[w.lower()])
    if len(out) != n:
        raise InputError(f"{where}: names {len(out)} column(s) ({' '.join(out)}), the file has {n}")
    named = [c for c in out if c != "-"]
    if len(named) != len(set(named)):
        raise InputError(f"{where}: a column is named twice ({' '.join(out)})")
    for group in (("x", "y", "z"), ("nx", "ny", "nz"), ("r", "g", "b")):
        have = [c in out for c in group]
        if any(have) and not all(have) or group[0] == "x" and not all(have):
            raise InputError(f"{where}: needs all of {' '.join(group)} or none ({' '.join(out)})")
    if "a" in out and "r" not in out:
        raise InputError(f"{where}: an alpha column needs r g b ({' '.join(out)})")
    return out


def _are_normals(a: np.ndarray) -> bool:
    """Unit vectors (or zero, for 'no normal'), to three decimals."""
    a = a[np.isfinite(a).all(axis=1)]
    if not len(a):
        return False
    norm = np.linalg.norm(a, axis=1)
    return bool((np.abs(norm - 1) < 1e-2).all() or ((np.abs(norm - 1) < 1e-2) | (norm == 0)).all() and norm.any())


def _colour_scale(a: np.ndarray) -> float | None:
    """255 for integer colours 0..255, 1 for colours 0..1, None when the values are not colours."""
    a = a[np.isfinite(a).all(axis=1)]
    if not len(a) or a.min() < 0:
        return None
    if a.max() <= 1:
        return 1.0
    if a.max() <= 255 and (a == np.round(a)).all():
        return 255.0
    return None


def detect_columns(arr: np.ndarray, where: str) -> list[str]:
    """The meaning of a cloud's columns from their values: x y z, then any of unit normals (nx ny nz) and colours
    (r g b [a], integers 0..255 or values 0..1), in either order. Unit vectors are taken for normals."""
    n = arr.shape[1]
    if n < 3:
        raise InputError(f"{where}: {n} column(s); a point needs at least x y z")
    if n == 3:
        return ["x", "y", "z"]
    hint = " (set data.columns, e.g. data.columns='x y z nx ny nz' with - for a column to ignore)"
    rest = arr[:, 3:]

    def colours_ok(block):
        return block.shape[1] in (3, 4) and _colour_scale(block) is not None

    if n in (6, 7, 9, 10):
        if rest.shape[1] >= 3 and _are_normals(rest[:, :3]) and (n == 6 or colours_ok(rest[:, 3:])):
            return ["x", "y", "z", "nx", "ny", "nz"] + ["r", "g", "b", "a"][: n - 6]
        k = 3 if n in (6, 9) else 4
        if colours_ok(rest[:, :k]) and (n - 3 - k == 0 or _are_normals(rest[:, k:])):
            return ["x", "y", "z"] + ["r", "g", "b", "a"][:k] + (["nx", "ny", "nz"] if n - 3 - k else [])
        raise InputError(f"{where}: cannot tell what its {n} columns are: after x y z they are neither unit "
                         f"normals nor colours (0..1 or integers 0..255){hint}")
    raise InputError(f"{where}: {n} columns; expected x y z [nx ny nz] [r g b [a]] (3, 6, 7, 9 or 10 columns){hint}")


def _to_rgb8(rgb: np.ndarray, scale: float | None = None) -> np.ndarray:
    rgb = np.asarray(rgb, dtype=np.float64)
    if scale is None:
        scale = 1.0 if np.nanmax(rgb, initial=0) <= 1 else 255.0
    return np.clip(np.round(np.nan_to_num(rgb) * (255.0 / scale)), 0, 255).astype(np.uint8)


def _cloud_from_columns(arr: np.ndarray, cols: list[str], where: str) -> Cloud:
    at = {c: i for i, c in enumerate(cols)}
    pts = arr[:, [at["x"], at["y"], at["z"]]]
    normals = arr[:, [at["nx"], at["ny"], at["nz"]]] if "nx" in at else None
    extra = {"columns": " ".join(cols)}
    if "r" in at:
        rgb = arr[:, [at["r"], at["g"], at["b"]]]
        scale = _colour_scale(rgb)
        if scale is None:
            raise InputError(f"{where}: colour columns r g b hold values outside 0..1 and 0..255")
        extra["colors"] = _to_rgb8(rgb, scale)
    return Cloud(pts, normals, extra=extra)


_NUMBER = re.compile(rb"^[+-]?(\d+\.?\d*([eE][+-]?\d+)?|\.\d+([eE][+-]?\d+)?|nan|inf|infinity)$", re.IGNORECASE)


def _read_xyz(p: Path, label: str, columns=None) -> Cloud:
    """A text cloud: one point per line, values separated by spaces, tabs, commas or semicolons; ``#`` and ``//``
    start comments; a first line that is not numbers is a header (its column names are used if known)."""
    data = p.read_bytes()
    if b"\0" in data[:4096]:
        raise InputError(f"{label}: binary data, not a text point cloud (.xyz .txt .pts .csv .asc hold x y z per line)")
    lines = data.splitlines()
    header, start = None, len(lines)
    for i, ln in enumerate(lines):
        s = ln.strip()
        if not s:
            continue
        comment = s.startswith((b"#", b"//"))
        words = [w for w in re.split(rb"[\s,;]+", s.lstrip(b"/#").strip()) if w]
        if not comment and all(_NUMBER.match(w) for w in words):
            start = i
            break
        names = [w.decode("ascii", "replace") for w in words]
        if comment and not {"x", "y", "z"} <= {n.lower() for n in names}:
            continue  # a comment, not a list of column names
        if header is not None and not comment:
            start = i  # a second line of text: reported below as a bad row
            break
        header = names
    keep = [i for i in range(start, len(lines)) if lines[i].strip() and not lines[i].lstrip().startswith((b"#", b"//"))]
    if not keep:
        raise InputError(f"{label}: contains no points")
    body = [lines[i] for i in keep]
    delim = b"," if b"," in body[0] else (b";" if b";" in body[0] else None)
    text = [(ln if delim is None else ln.replace(delim, b" ")).decode("ascii", "replace") for ln in body]
    try:
        arr = np.loadtxt(text, dtype=np.float64, ndmin=2)
    except ValueError:
        n0 = len(text[0].split())
        for i, t in zip(keep, text):  # the first offending line, numbered as in the file
            w = t.split()
            if len(w) != n0 or not all(_NUMBER.match(x.encode()) for x in w):
                raise InputError(f"{label}: line {i + 1}: '{t.strip()[:60]}' is not a row of {n0} numbers like "
                                 "the first") from None
        raise
    if columns:
        cols = _parse_columns(columns, arr.shape[1], f"{label}: data.columns")
    elif header and {"x", "y", "z"} <= {h.lower() for h in header} and len(header) == arr.shape[1]:
        # named columns; names other than x y z nx ny nz r g b a (intensity, a scalar field...) are ignored
        cols = _parse_columns([COLUMN_NAMES.get(h.lower(), "-") for h in header], arr.shape[1],
                              f"{label}: header line")
    else:
        cols = detect_columns(arr, label)
    return _cloud_from_columns(arr, cols, label)


def _read_npy(p: Path, label: str, columns=None) -> Cloud:
    fmt = np.lib.format
    with open(p, "rb") as f:
        try:
            version = fmt.read_magic(f)
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, _, dtype = read_header(f)
        except ValueError as e:
            raise InputError(f"{label}: not a .npy file ({_one_line(e)})") from None
        need, body = int(np.prod(shape, dtype=object)) * dtype.itemsize, p.stat().st_size - f.tell()
    if not dtype.hasobject and need > body:
        raise InputError(f"{label}: truncated .npy data: the header's shape {shape} needs {need} bytes, but {body} "
                         "bytes follow the header")
    try:
        arr = np.load(p, allow_pickle=False, mmap_mode="r")
    except ValueError as e:
        raise InputError(f"{label}: not a plain numeric .npy array ({_one_line(e)})") from None
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.number) or not (3 <= arr.shape[1] <= 10):
        raise InputError(f"{label}: expected a numeric (N, 3..10) array (x y z [nx ny nz] [r g b [a]]), got "
                         f"{arr.dtype} {arr.shape}")
    arr = np.asarray(arr, dtype=np.float64)
    cols = _parse_columns(columns, arr.shape[1], f"{label}: data.columns") if columns else detect_columns(arr, label)
    return _cloud_from_columns(arr, cols, label)


def _pcd_header(p: Path, label: str) -> dict:
    """The PCD header's fields, checked against the file's size before anything is read."""
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(1 << 16)
    fields, pos = {}, 0
    for raw in head.split(b"\n"):
        pos += len(raw) + 1
        words = raw.decode("ascii", "replace").split()
        if not words or words[0].startswith("#"):
            continue
        fields[words[0].upper()] = words[1:]
        if words[0].upper() == "DATA":
            break
    else:
        raise InputError(f"{label}: not a PCD file (no FIELDS/DATA header)")
    if "FIELDS" not in fields:
        raise InputError(f"{label}: not a PCD file (no FIELDS/DATA header)")
    names = fields["FIELDS"]
    if not {"x", "y", "z"} <= set(names):
        raise InputError(f"{label}: PCD has no x y z fields (FIELDS {' '.join(names)[:80]}): not a point cloud")
    try:
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(names))]
        sizes = [int(c) for c in fields.get("SIZE", ["4"] * len(names))]
        if "POINTS" in fields:
            npts = int(fields["POINTS"][0])
        else:
            npts = int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
    except (ValueError, IndexError, KeyError):
        raise InputError(f"{label}: bad PCD header (COUNT, SIZE, POINTS or WIDTH/HEIGHT)") from None
    if len(counts) != len(names) or len(sizes) != len(names) or npts < 0 or min(counts + sizes, default=0) < 0:
        raise InputError(f"{label}: bad PCD header ({len(names)} fields, {len(sizes)} sizes, {len(counts)} counts)")
    kind = (fields["DATA"] or ["?"])[0].lower()
    body = size - pos
    rec = sum(c * s for c, s in zip(counts, sizes))
    if kind == "binary":
        need = npts * rec
    elif kind == "ascii":
        need = npts * 2 * sum(counts) - 1
    elif kind == "binary_compressed":
        with open(p, "rb") as f:
            f.seek(pos)
            sizes8 = f.read(8)
        if len(sizes8) < 8:
            raise InputError(f"{label}: truncated PCD data (no compressed block)")
        comp, raw = struct.unpack("<II", sizes8)
        if comp > body - 8 or raw != npts * rec or raw > 128 * comp + 1024:
            raise InputError(f"{label}: PCD compressed block sizes ({comp} -> {raw} bytes) do not match the header "
                             f"({npts} points of {rec} bytes) and the file")
        need = 0
    else:
        raise InputError(f"{label}: unknown PCD DATA type '{kind}' (ascii, binary or binary_compressed)")
    if need > body:
        raise InputError(f"{label}: truncated PCD data: the header announces {npts} points, which need at least "
                         f"{need} bytes, but {body} bytes follow the header")
    return {"fields": names, "points": npts, "data": kind}


def _read_pcd(p: Path, label: str) -> Cloud:
    head = _pcd_header(p, label)
    if head["points"] == 0:
        raise InputError(f"{label}: PCD has no points (POINTS 0)")
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(p), format="pcd", remove_nan_points=False, remove_infinite_points=False)
    pts = np.asarray(pc.points)
    if len(pts) == 0:
        raise InputError(f"{label}: no points could be read (corrupt PCD, or no x y z fields)")
    extra = {"colors": _to_rgb8(np.asarray(pc.colors), 1.0)} if pc.has_colors() else {}
    return Cloud(pts, np.asarray(pc.normals) if pc.has_normals() else None, extra=extra)


# ------------------------------------------------------------------------------------------------ writing


def write_ply(path: str | os.PathLike, g: Geometry, colors: np.ndarray | None = None,
              scalars: dict[str, np.ndarray] | None = None, edges: np.ndarray | None = None,
              edge_colors: np.ndarray | None = None) -> None:
    """Write a mesh or cloud as binary little-endian PLY (float64 coordinates; normals, uchar RGB (given, or a
    cloud's own ``extra["colors"]``) and float per-vertex scalars if given: MeshLab shows ``quality`` and
    CloudCompare every scalar as a scalar field). ``edges`` (E, 2) vertex indices of a cloud are written as the
    standard ``edge`` element (``vertex1``, ``vertex2``, and uchar RGB from ``edge_colors`` (E, 3) if given): a
    line set, e.g. matches between keypoints."""
    pts = g.vertices if isinstance(g, Mesh) else g.points
    normals = None if isinstance(g, Mesh) else g.normals
    if colors is None and isinstance(g, Cloud):  # colours read with the cloud (text, PLY, PCD) go along
        carried = g.extra.get("colors")
        colors = carried if isinstance(carried, np.ndarray) and len(carried) == len(pts) else None
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    for name in scalars or {}:
        fields.append((name, "<f4"))
    rec = np.empty(len(pts), dtype=fields)
    for name, val in (scalars or {}).items():
        rec[name] = val
    rec["x"], rec["y"], rec["z"] = pts.T
    if normals is not None:
        rec["nx"], rec["ny"], rec["nz"] = normals.T
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = np.asarray(colors, dtype=np.uint8).T
    names = {"<f8": "double", "<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by scanreg", f"element vertex {len(pts)}"]
    header += [f"property {names[t]} {n}" for n, t in fields]
    if isinstance(g, Mesh):
        header += [f"element face {len(g.faces)}", "property list uchar int vertex_indices"]
    erec = None
    if edges is not None:
        if isinstance(g, Mesh):
            raise ValueError("write_ply: edges are written for clouds only")
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        if len(edges) and (edges.min() < 0 or edges.max() >= len(pts)):
            raise ValueError(f"write_ply: edge vertex indices must be in [0, {len(pts)})")
        efields = [("vertex1", "<i4"), ("vertex2", "<i4")]
        if edge_colors is not None:
            efields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        erec = np.empty(len(edges), dtype=efields)
        erec["vertex1"], erec["vertex2"] = edges.T
        if edge_colors is not None:
            erec["red"], erec["green"], erec["blue"] = np.asarray(edge_colors, dtype=np.uint8).reshape(-1, 3).T
        header += [f"element edge {len(edges)}"] + [f"property {'int' if t == '<i4' else 'uchar'} {n}"
                                                     for n, t in efields]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
        if isinstance(g, Mesh):
            frec = np.empty(len(g.faces), dtype=[("c", "u1"), ("v", "<i4", (3,))])
            frec["c"], frec["v"] = 3, g.faces
            f.write(frec.tobytes())
        if erec is not None:
            f.write(erec.tobytes())


# ------------------------------------------------------------------------------------------------ transforms etc.


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


def write_transform(path: str | os.PathLike, T: np.ndarray) -> None:
    np.savetxt(path, T, fmt="%.17g")


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
