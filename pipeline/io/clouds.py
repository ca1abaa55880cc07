"""Point-cloud readers: text (.xyz .txt .pts .csv .asc), NPY and PCD, with their columns named by a header
line, by ``columns``, or detected from the values (:func:`detect_columns`)."""

from __future__ import annotations

import io
import re
import struct
from pathlib import Path

import numpy as np

from scanreg.errors import InputError, note, one_line
from scanreg.geometry import Cloud

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
    if arr.shape == (4, 4) and np.array_equal(arr[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{where}: a 4x4 matrix, a rigid transform, not a point cloud (a known transform is "
                         "given as data.gt=FILE, or data.poses for a scan set)")
    example = " ".join(["x", "y", "z"] + ["-"] * (n - 3)) if n < 6 else "x y z nx ny nz" + " -" * (n - 6)
    hint = f" (set data.columns, e.g. data.columns='{example}' with - for a column to ignore)"  # (n names)
    rest = arr[:, 3:]

    def colours_ok(block):
        return block.shape[1] in (3, 4) and _colour_scale(block) is not None

    said = "set data.columns to say what they are"
    if n == 6 and not np.nan_to_num(rest).any():  # black, or no normals: nothing either way
        note(f"{where}: columns 4-6 are all zero: ignored, neither normals nor colours ({said})")
        return ["x", "y", "z", "-", "-", "-"]
    if n in (6, 7, 9, 10):
        if rest.shape[1] >= 3 and _are_normals(rest[:, :3]) and (n == 6 or colours_ok(rest[:, 3:])):
            cols = ["x", "y", "z", "nx", "ny", "nz"] + ["r", "g", "b", "a"][: n - 6]
        else:
            k = 3 if n in (6, 9) else 4
            if not (colours_ok(rest[:, :k]) and (n - 3 - k == 0 or _are_normals(rest[:, k:]))):
                raise InputError(f"{where}: cannot tell what its {n} columns are: after x y z they are neither "
                                 f"unit normals nor colours (0..1 or integers 0..255){hint}")
            cols = ["x", "y", "z"] + ["r", "g", "b", "a"][:k] + (["nx", "ny", "nz"] if n - 3 - k else [])
        if "r" in cols:  # values in 0..1 or 0..255 could be other things (an intensity): said, not guessed silently
            note(f"{where}: columns read as {' '.join(cols)} from their values ({said} otherwise)")
        return cols
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
    head = data[:HEAD_BYTES].splitlines(keepends=True)
    header, start = _header_and_start(head)
    arr = _parsed_at_once(data[sum(map(len, head[:start])):]) if start < len(head) else None
    if arr is None:  # line by line: comments among the rows, several count lines, or a bad row to name
        lines = data.splitlines()
        header, start = _header_and_start(lines)
        arr = _parsed_by_line(lines, start, label)
    if columns:
        cols = _parse_columns(columns, arr.shape[1], f"{label}: data.columns")
    elif header and {"x", "y", "z"} <= {h.lower() for h in header} and len(header) == arr.shape[1]:
        # named columns; names other than x y z nx ny nz r g b a (intensity, a scalar field...) are ignored
        cols = _parse_columns([COLUMN_NAMES.get(h.lower(), "-") for h in header], arr.shape[1],
                              f"{label}: header line")
    elif p.suffix.lower() == ".pts" and arr.shape[1] in (4, 7):  # Leica PTS: x y z intensity [r g b]
        cols = ["x", "y", "z", "-", "r", "g", "b"][:arr.shape[1]]
    else:
        cols = detect_columns(arr, label)
    return _cloud_from_columns(arr, cols, label)


HEAD_BYTES = 1 << 20
"""A text cloud's header (column names, comments) is looked for in its first this many bytes; the rows after it
are parsed at once (:func:`_parsed_at_once`), unless the header runs on beyond them."""


def _header_and_start(lines: list[bytes]) -> tuple[list[str] | None, int]:
    """The column names of a header line (None: none) and the number of the first line of values (or of a second
    line of text, reported as a bad row; ``len(lines)`` when there is none)."""
    header, start = None, len(lines)
    for i, ln in enumerate(lines):
        s = ln.strip()
        if not s:
            continue
        comment = s.startswith((b"#", b"//"))
        words = _words(s.lstrip(b"/#"))
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
    return header, start


def _parsed_at_once(body: bytes) -> np.ndarray | None:
    """The rows of ``body`` (from the first line of values on) parsed in one call, as :func:`_parsed_by_line`
    parses them (a leading point-count line skipped, the delimiter and decimal commas as its first row has them),
    four times as fast on a million rows; None when they need the line-by-line reading: comments among them,
    rows of unequal length (a bad row, or a later count line), anything the parser refuses."""
    if b"#" in body or b"//" in body:
        return None
    first, _, rest = body.partition(b"\n")
    words = _words(first)
    count = None
    if _is_count(words):  # a point count (Leica's PTS)
        body, count = rest, int(words[0])
        first = body.partition(b"\n")[0]
    body = _as_spaced(body, first)
    if not body.strip():
        return None  # nothing after the count: said by the line-by-line reading ("contains no points")
    try:
        arr = np.loadtxt(io.BytesIO(body), dtype=np.float64, ndmin=2, comments=None, encoding="latin-1")
    except ValueError:
        return None
    if count is not None and count != len(arr):  # not the count of the rows after it: read line by line
        return None
    return arr if arr.size else None


def _as_spaced(text: bytes, first: bytes) -> bytes:
    """``text`` with its values split by spaces as the first row ``first`` splits them: by commas or semicolons
    (replaced), and with both, by semicolons with decimal commas (``0,37;-0,11``: commas made points)."""
    if b";" in first and b"," in first:
        return text.replace(b";", b" ").replace(b",", b".")
    for delim in (b",", b";"):
        if delim in first:
            return text.replace(delim, b" ")
    return text


def _parsed_by_line(lines: list[bytes], start: int, label: str) -> np.ndarray:
    """The rows from line ``start`` on, one by one: comments and point-count lines skipped, the first bad row
    named."""
    keep = [i for i in range(start, len(lines)) if lines[i].strip() and not lines[i].lstrip().startswith((b"#", b"//"))]
    if not keep:
        raise InputError(f"{label}: contains no points")
    keep = _without_counts(lines, keep)
    body = [lines[i] for i in keep]
    text = [_as_spaced(ln, body[0]).decode("ascii", "replace") for ln in body]
    try:
        arr = np.loadtxt(text, dtype=np.float64, ndmin=2)
    except ValueError:
        n0 = len(text[0].split())
        for i, t in zip(keep, text):  # the first offending line, numbered and quoted as in the file
            w = t.split()
            if len(w) != n0 or not all(_NUMBER.match(x.encode()) for x in w):
                raise InputError(f"{label}: line {i + 1}: '{lines[i].decode('ascii', 'replace').strip()[:60]}' is "
                                 f"not a row of {n0} numbers like the first") from None
        raise
    return arr


def _without_counts(lines: list[bytes], keep: list[int]) -> list[int]:
    """``keep`` (numbers of the lines that hold values) without point-count lines: a line of one integer among
    rows of three or more values that is followed by that many rows (up to the next such line or the end), as
    Leica's PTS starts each scan with its count. Another lone integer (a file cut short) stays, a bad row."""
    if not any(len(_words(lines[i])) >= 3 for i in keep[:3]):
        return keep
    lone = [k for k, i in enumerate(keep) if _is_count(_words(lines[i]))]
    ends = lone[1:] + [len(keep)]
    counts = {k for k, end in zip(lone, ends) if int(_words(lines[keep[k]])[0]) == end - k - 1}
    return [i for k, i in enumerate(keep) if k not in counts]


def _words(line: bytes) -> list[bytes]:
    """The values of a text cloud's line (split by spaces, tabs, commas or semicolons)."""
    return [w for w in re.split(rb"[\s,;]+", line.strip()) if w]


def _is_count(words: list[bytes]) -> bool:
    """Whether a line's values are one whole number (a point count, as Leica's PTS has before each scan)."""
    return len(words) == 1 and re.fullmatch(rb"\+?\d+", words[0]) is not None


def _read_npy(p: Path, label: str, columns=None) -> Cloud:
    fmt = np.lib.format
    with open(p, "rb") as f:
        try:
            version = fmt.read_magic(f)
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, _, dtype = read_header(f)
        except ValueError as e:
            raise InputError(f"{label}: not a .npy file ({one_line(e)})") from None
        need, body = int(np.prod(shape, dtype=object)) * dtype.itemsize, p.stat().st_size - f.tell()
    if not dtype.hasobject and need > body:
        raise InputError(f"{label}: truncated .npy data: the header's shape {shape} needs {need} bytes, but {body} "
                         "bytes follow the header")
    try:
        arr = np.load(p, allow_pickle=False, mmap_mode="r")
    except ValueError as e:
        raise InputError(f"{label}: not a plain numeric .npy array ({one_line(e)})") from None
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
