"""The PLY reader: ASCII and binary, faces of any size, other list properties read and ignored, and the
Stanford scanner's ``range_grid`` triangulated as vcglib/MeshLab do. Header counts are checked against the
file's size before anything is allocated."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanreg.errors import InputError, one_line, warn
from scanreg.geometry import Cloud, Geometry, Mesh
from scanreg.io.clouds import _to_rgb8
from scanreg.io.faces import Ragged, _triangulate

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
    if not any(n for name, n, _ in elements if name == "vertex"):  # (a header without properties too)
        raise InputError(f"{label}: contains no points (its header says 0 vertices)")
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
            warn(f"{label}: {len(tok.tokens) - tok.pos} value(s) after the PLY's last element ignored")
            return parsed
        if isinstance(error, InputError):
            raise error from None
        raise InputError(f"{label}: PLY data do not match the header ({one_line(error)})") from None
    if extra_rows:
        warn(f"{label}: {extra_rows} PLY row(s) hold values past the header's properties; ignored")
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
