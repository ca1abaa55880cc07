"""Faces that bridge a depth jump: a range scan triangulated as a grid (a scanner's ``range_grid``, a depth
image) joins neighbouring samples even where the surface behind jumps away from the one in front (the bunny's
ears, one before the other). Such faces are long and thin across the jump, much longer than the edges at their
corners, which lie on the real surfaces on either side; merged into a model of many scans they make a sheet
between the parts. Adaptive meshes (a decimated CT surface) change their edge lengths gradually and keep every
face. Tests: tests/test_scanset.py."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Mesh, row_norms


def edge_lengths(mesh: Mesh) -> np.ndarray:
    """(F, 3) lengths of each face's edges; edge k joins corner k and corner k+1."""
    v, f = mesh.vertices, mesh.faces
    return row_norms(v[f[:, [1, 2, 0]]] - v[f])


def corner_edge_lengths(mesh: Mesh, q: float = 0.25, length: np.ndarray | None = None) -> np.ndarray:
    """Per vertex, the ``q`` quantile (lower) of the lengths of the face edges at it (each face's two edges at the
    corner; 0 for a vertex no face uses); ``length``: :func:`edge_lengths` of ``mesh`` when already computed."""
    v, f = mesh.vertices, mesh.faces
    if not len(f):
        return np.zeros(len(v))
    length = edge_lengths(mesh) if length is None else length
    vert = np.concatenate([f.ravel(), f[:, [1, 2, 0]].ravel()])
    lens = np.concatenate([length.ravel(), length.ravel()])
    order = np.lexsort((lens, vert))
    vert, lens = vert[order], lens[order]
    counts = np.bincount(vert, minlength=len(v))
    start = np.cumsum(counts) - counts
    out = np.zeros(len(v))
    used = counts > 0
    out[used] = lens[start[used] + np.floor(q * (counts[used] - 1)).astype(np.int64)]
    return out


def depth_jump_faces(mesh: Mesh, ratio: float) -> np.ndarray:
    """Which faces bridge a depth jump: their longest edge is more than ``ratio`` times the edges at each of their
    three corners (the lower quartile of the edge lengths there, :func:`corner_edge_lengths`; the largest of the
    three counts)."""
    if not len(mesh.faces):
        return np.zeros(0, bool)
    length = edge_lengths(mesh)
    local = corner_edge_lengths(mesh, length=length)[mesh.faces].max(axis=1)
    return length.max(axis=1) > ratio * local
