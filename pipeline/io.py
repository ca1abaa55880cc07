"""Reading and writing meshes, point clouds, transforms, Stanford ``.conf`` poses and landmark pairs.

Every reader validates what it reads and raises :class:`InputError` with one line naming the file and the
problem (missing, a directory, empty, truncated, wrong counts, indices out of range, NaN/inf coordinates).

Formats:
- meshes: PLY (ASCII and binary; ``face`` lists of any size are fan-triangulated; the Stanford scanner's
  ``range_grid`` element is triangulated as vcglib/MeshLab do), STL (ASCII and binary), OBJ, OFF;
- point clouds: PLY without faces, PCD (via Open3D), XYZ (text, 3 or 6 columns: with normals), NPY ((N, 3) or
  (N, 6));
- ``pkg:DIST/REL/PATH`` names a file shipped inside an installed Python package (e.g.
  ``pkg:pymeshfix/examples/StanfordBunny.ply``).
"""

from __future__ import annotations

import csv
import importlib.util
import os
import re
import struct
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.geometry import Cloud, Geometry, Mesh, make_T, validate_mesh, validate_points

MESH_EXTS = {".ply", ".stl", ".obj", ".off"}
CLOUD_EXTS = {".ply", ".pcd", ".xyz", ".txt", ".npy", ".pts"}


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
    if not p.exists():
        full = p.absolute()
        raise InputError(f"{what} {s}: no such file" + ("" if str(full) == s else f" ({full})"))
    if p.is_dir():
        raise InputError(f"{what} {s}: is a directory, expected a file")
    if p.stat().st_size == 0:
        raise InputError(f"{what} {s}: file is empty (0 bytes)")
    return p


def read_geometry(path: str | os.PathLike, what: str = "input") -> Geometry:
    """Read a mesh or a point cloud, deciding by extension and content (a PLY without faces is a cloud)."""
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
        elif ext in (".xyz", ".txt", ".pts"):
            g = _read_xyz(p, label)
        elif ext == ".npy":
            g = _read_npy(p, label)
        elif ext == ".pcd":
            g = _read_pcd(p, label)
        else:
            raise InputError(
                f"{label}: unsupported file type '{ext}' (meshes: .ply .stl .obj .off; clouds: .ply .pcd .xyz .npy)"
            )
    except InputError:
        raise
    except (ValueError, IndexError, struct.error, UnicodeDecodeError, OverflowError, MemoryError) as e:
        raise InputError(f"{label}: corrupt or unreadable file ({type(e).__name__}: {e})") from None
    if isinstance(g, Mesh):
        g.source = label
        return validate_mesh(g)
    g.points = validate_points(g.points, label)
    if g.normals is not None:
        g.normals = _clean_normals(g.normals, label)
    g.source = label
    return g


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
    if fmt == "ascii":
        values = _AsciiTokens(data, label)
        parsed = {name: _read_ply_element_ascii(values, name, n, props, label) for name, n, props in elements}
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
        tris = _fan_triangulate(face[key], label)
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
    return Cloud(pts, normals)


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
                out[pname].append(np.array(tok.take(k), dtype=np.int64))
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
                out[pname].append(np.frombuffer(dv, idt, k, pos).astype(np.int64))
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


def _fan_triangulate(faces, label: str) -> np.ndarray:
    """Triangles from polygon index lists (an (M, k) array or a list of arrays); polygons become fans."""
    if isinstance(faces, np.ndarray) and faces.ndim == 2:
        k = faces.shape[1]
        if k < 3:
            raise InputError(f"{label}: faces with fewer than 3 vertices")
        return np.concatenate([faces[:, [0, i, i + 1]] for i in range(1, k - 1)]).astype(np.int64) if k > 3 \
            else faces.astype(np.int64)
    tris = []
    for poly in faces:
        if len(poly) < 3:
            raise InputError(f"{label}: a face with {len(poly)} vertices (need at least 3)")
        for i in range(1, len(poly) - 1):
            tris.append((poly[0], poly[i], poly[i + 1]))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


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
    with open(p, "r", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
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
    return Mesh(pts, _fan_triangulate(polys, label))


def _read_off(p: Path, label: str) -> Mesh:
    text = p.read_text(errors="replace")
    lines = [ln.split("#")[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines or not lines[0].upper().endswith("OFF"):
        raise InputError(f"{label}: not an OFF file (first line is not 'OFF')")
    head = lines[0][3:].split() if len(lines[0]) > 3 else []
    rest = lines[1:]
    if not head:
        head, rest = rest[0].split(), rest[1:]
    nv, nf = int(head[0]), int(head[1])
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
    return Mesh(pts, _fan_triangulate(polys, label))


# ------------------------------------------------------------------------------------------------ clouds


def _read_xyz(p: Path, label: str) -> Cloud:
    try:
        arr = np.loadtxt(p, dtype=np.float64, ndmin=2, comments="#", delimiter=None)
    except ValueError:
        arr = np.loadtxt(p, dtype=np.float64, ndmin=2, comments="#", delimiter=",")
    if arr.size == 0:
        raise InputError(f"{label}: contains no points")
    if arr.shape[1] not in (3, 6):
        raise InputError(f"{label}: expected 3 (x y z) or 6 (x y z nx ny nz) columns, found {arr.shape[1]}")
    return Cloud(arr[:, :3], arr[:, 3:6] if arr.shape[1] == 6 else None)


def _read_npy(p: Path, label: str) -> Cloud:
    try:
        arr = np.load(p, allow_pickle=False)
    except ValueError as e:
        raise InputError(f"{label}: not a plain numeric .npy array ({e})") from None
    if arr.ndim != 2 or arr.shape[1] not in (3, 6) or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{label}: expected a numeric (N, 3) or (N, 6) array, got {arr.dtype} {arr.shape}")
    return Cloud(arr[:, :3], arr[:, 3:6] if arr.shape[1] == 6 else None)


def _read_pcd(p: Path, label: str) -> Cloud:
    head = p.read_bytes()[:2048]
    if b"FIELDS" not in head or b"DATA" not in head:
        raise InputError(f"{label}: not a PCD file (no FIELDS/DATA header)")
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(p), format="pcd")
    pts = np.asarray(pc.points)
    if len(pts) == 0:
        raise InputError(f"{label}: no points could be read (corrupt or empty PCD)")
    return Cloud(pts, np.asarray(pc.normals) if pc.has_normals() else None)


# ------------------------------------------------------------------------------------------------ writing


def write_ply(path: str | os.PathLike, g: Geometry, colors: np.ndarray | None = None,
              scalars: dict[str, np.ndarray] | None = None) -> None:
    """Write a mesh or cloud as binary little-endian PLY (float64 coordinates; normals, uchar RGB and float
    per-vertex scalars if given: MeshLab shows ``quality`` and CloudCompare every scalar as a scalar field)."""
    pts = g.vertices if isinstance(g, Mesh) else g.points
    normals = None if isinstance(g, Mesh) else g.normals
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
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
        if isinstance(g, Mesh):
            frec = np.empty(len(g.faces), dtype=[("c", "u1"), ("v", "<i4", (3,))])
            frec["c"], frec["v"] = 3, g.faces
            f.write(frec.tobytes())


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
