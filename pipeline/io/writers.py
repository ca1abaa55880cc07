"""Writers: PLY (meshes, clouds, line sets, with colours and scalars) and 4x4 transforms as text."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from scanreg.geometry import Cloud, Geometry, Mesh


def write_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all (parallel jobs of a sweep never read half a file): a
    temporary file in the same folder, with an ordinary file's permissions (mkstemp makes it private), renamed into
    place; on any failure the temporary is removed and the error raised. Makes the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


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


def write_transform(path: str | os.PathLike, T: np.ndarray) -> None:
    np.savetxt(path, T, fmt="%.17g")
