"""The STL, OBJ and OFF readers."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from scanreg.errors import InputError, warn
from scanreg.geometry import Cloud, Geometry, Mesh
from scanreg.io.faces import _merge_vertices, _triangulate

def _read_stl(p: Path, label: str) -> Mesh:
    data = p.read_bytes()
    rec = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])

    def binary(count: int) -> Mesh:  # the first ``count`` triangles of a binary STL
        return _merge_vertices(np.frombuffer(data, rec, count, 84)["v"].astype(np.float64))

    n = struct.unpack("<I", data[80:84])[0] if len(data) >= 84 else None
    if n is not None and 84 + 50 * n == len(data):
        if n == 0:
            raise InputError(f"{label}: STL has no triangles")
        return binary(n)
    head = data[:512].lstrip().lower()
    if head.startswith(b"solid") and re.search(rb"\bvertex\s", data[:65536]):
        verts = re.findall(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", data)
        if len(verts) % 3:
            raise InputError(f"{label}: truncated ASCII STL ({len(verts)} vertices, not a multiple of 3)")
        return _merge_vertices(np.array(verts, dtype=np.float64).reshape(-1, 3, 3))
    if n is None:
        raise InputError(f"{label}: " + ("ASCII STL has no vertices" if head.startswith(b"solid") else
                                         "not an STL file (too short for a binary STL, and no 'solid')"))
    whole = (len(data) - 84) // 50
    if 0 < n <= whole:  # exporters that pad the file: the declared triangles, the rest left
        warn(f"{label}: binary STL declares {n} triangles ({84 + 50 * n} bytes) but the file has {len(data)} "
             "bytes: the declared triangles are read, the rest is ignored")
        return binary(n)
    if n == 0 and whole > 0 and 84 + 50 * whole == len(data):  # a count never filled in
        warn(f"{label}: binary STL declares 0 triangles but holds {whole} by its size: read them all")
        return binary(whole)
    if head.startswith(b"solid"):
        raise InputError(f"{label}: ASCII STL has no vertices")
    raise InputError(f"{label}: truncated or not an STL file: as binary STL it declares {n} triangles "
                     f"({84 + 50 * n} bytes) but has {len(data)} bytes, and it does not start with 'solid' (ASCII STL)")


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
