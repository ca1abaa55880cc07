"""Repair where the defects are: cut a mesh's defective regions out as submeshes with a margin, hand them to a
repair backend, and stitch what comes back into the untouched rest.

A *region* is a connected set of faces around defects (the faces along the holes to fill, at non-manifold
vertices and on non-manifold edges, :func:`defect_regions`) grown by a margin of face rings. Its border has
two kinds of loops: the holes to fill, and the *cut* where it meets the rest of the mesh. A backend that fills
holes up to a number of edges (MeshFix) must fill the first and leave the second: every cut loop is made longer
than the region's largest hole by growing the margin, and :func:`stitch` accepts a repaired region only when
the cut came back unchanged (the same vertices at the same coordinates, every cut edge still a border edge
in the same direction), so that the stitched mesh is manifold along it. Anything else, and the caller repairs
the whole mesh instead.

Pure functions of the arrays (no processes, no files); lengths and coordinates are the mesh's own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.geometry import Mesh, rows_any, submesh
from scanreg.mesh.topology import (_face_components, boundary_edges, dilate_faces, face_labels, loop_labels,
                                   non_manifold_vertex_mask)

MARGIN_RINGS = 2
"""Rings of faces around the defects that a region includes at first: the backend sees each defect with its
neighbourhood (hole filling sizes its new triangles from the border's)."""
MAX_RINGS = 8
"""The margin grows ring by ring up to this many until every cut loop is longer than the region's largest
hole; beyond it the regions are given up (the whole mesh is repaired)."""


@dataclass(frozen=True)
class Region:
    """One connected region: its faces (indices into the mesh's faces) and the largest number of edges of the
    holes in it that are to be filled (0: none to fill)."""

    faces: np.ndarray
    hole_edges: int


def defect_regions(mesh: Mesh, seeds: np.ndarray, holes: np.ndarray, margin_rings: int = MARGIN_RINGS,
                   max_rings: int = MAX_RINGS) -> list[Region] | None:
    """The regions around the defect faces ``seeds`` (a face mask) of ``mesh``, given which of its boundary
    loops are ``holes`` to fill (a mask over the loops of :func:`~scanreg.mesh.topology.loop_labels` of
    :func:`~scanreg.mesh.topology.boundary_edges`, in label order). Each region is the connected set of faces
    within ``margin_rings`` rings of the seeds (faces sharing a vertex), grown one ring at a time (at most
    ``max_rings``) until every loop of its border that is not one of its holes has more edges than its largest
    hole, with the fans of the vertices where it is pinched at its cut taken in (:func:`_unpinched`); None when no
    margin up to ``max_rings`` gives that (the caller repairs the whole mesh)."""
    if not seeds.any():
        return []
    n = len(mesh.vertices)
    bnd = boundary_edges(mesh)
    lab = loop_labels(bnd)
    size = np.bincount(lab) if len(lab) else np.zeros(0, np.int64)
    on_hole = holes[lab] if len(lab) else np.zeros(0, bool)
    hole_keys = _keys(bnd[on_hole], n)
    order = np.argsort(hole_keys)
    hole_keys, hole_loop = hole_keys[order], lab[on_hole][order]
    for rings in range(margin_rings, max_rings + 1):
        mask = _unpinched(mesh, dilate_faces(mesh.faces, seeds, rings))
        regions = None if mask is None else _regions(mesh, mask, hole_keys, hole_loop, size)
        if regions is not None:
            return regions
    return None


UNPINCH_ROUNDS = 4
"""How often :func:`_unpinched` takes in the fans of the vertices where the regions are pinched."""


def _unpinched(mesh: Mesh, mask: np.ndarray) -> np.ndarray | None:
    """The faces in ``mask`` and every face at a vertex where they are pinched at their cut (a vertex that faces
    outside share, whose faces in the mask form two fans: a backend would split it), until none is left (None
    after :data:`UNPINCH_ROUNDS` rounds)."""
    f = mesh.faces
    for grown in range(UNPINCH_ROUNDS + 1):
        outside = _used(f, ~mask, len(mesh.vertices))
        ids = np.unique(f[mask])  # submesh's vertex order
        pinched = ids[non_manifold_vertex_mask(submesh(mesh, mask))]
        pinched = pinched[outside[pinched]]
        if not len(pinched):
            return mask
        if grown == UNPINCH_ROUNDS:
            return None
        hot = np.zeros(len(mesh.vertices), bool)
        hot[pinched] = True
        mask = mask | hot[f].any(axis=1)
    return None


def _keys(e: np.ndarray, n: int) -> np.ndarray:
    """One int64 per directed edge (a, b) of a mesh with ``n`` vertices."""
    e = np.asarray(e, dtype=np.int64).reshape(-1, 2)
    return e[:, 0] * n + e[:, 1]


def _count_in(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """How often each of ``keys`` occurs in ``sorted_keys``."""
    return np.searchsorted(sorted_keys, keys, side="right") - np.searchsorted(sorted_keys, keys, side="left")


def _edges(f: np.ndarray) -> np.ndarray:
    """The directed edges of the faces ``f`` (3M, 2), face by face."""
    return f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def _regions(mesh: Mesh, mask: np.ndarray, hole_keys: np.ndarray, hole_loop: np.ndarray,
             size: np.ndarray) -> list[Region] | None:
    """The connected regions of the faces in ``mask``; None when one of them has a cut loop with no more edges
    than its largest hole (``hole_keys``: the holes' directed border edges' keys, sorted, ``hole_loop``: their
    loops, ``size``: every loop's edges)."""
    f, n = mesh.faces, len(mesh.vertices)
    idx = np.flatnonzero(mask)
    comp = face_labels(f[idx])
    out = []
    for c in np.unique(comp):
        faces = idx[comp == c]
        border = boundary_edges(Mesh(mesh.vertices, f[faces]))
        k = _keys(border, n)
        pos = np.minimum(np.searchsorted(hole_keys, k), max(len(hole_keys) - 1, 0))
        on_hole = (hole_keys[pos] == k) if len(hole_keys) else np.zeros(len(k), bool)
        # the holes wholly on the region's border are the ones it fills; the rest of its border is cut (or an
        # outer border, or a hole only partly in it) and must stay open
        loops = hole_loop[pos[on_hole]]
        whole = np.flatnonzero(np.bincount(loops, minlength=len(size)) == size) if len(loops) else loops
        filled = on_hole.copy()
        filled[on_hole] = np.isin(loops, whole)
        largest = int(size[whole].max()) if len(whole) else 0
        rest = border[~filled]
        if largest and len(rest) and np.bincount(loop_labels(rest)).min() <= largest:
            return None
        out.append(Region(faces, largest))
    return out


def stitch(mesh: Mesh, regions: list[Region], repaired: list[tuple[np.ndarray, np.ndarray]]) -> Mesh | None:
    """``mesh`` with each region's faces replaced by its repaired version (``repaired``: vertices and faces per
    region, as the backend returned them), without the vertices no face uses; None when a region's cut did not
    come back unchanged (module docstring).

    The result is ordered as a backend that keeps what it does not change orders the whole mesh (MeshFix): the
    faces the regions did not change (the faces outside them, and those a region gave back with the same
    vertices) in the mesh's order, as they were, then the new faces, region by region in the backend's order; a
    vertex the backend gave back once at its coordinates keeps its index (a cut vertex must), the others follow
    the mesh's, and every vertex keeps its coordinates."""
    v, f = mesh.vertices, mesh.faces
    inside = np.zeros(len(f), bool)
    for r in regions:
        inside[r.faces] = True
    n = len(v)
    outside = _used(f, ~inside, n)
    # the edges of the faces outside the regions that touch one (a cut edge's face outside is one of them)
    touch = ~inside & rows_any(_used(f, inside, n)[f])
    rest_keys = np.sort(_keys(_edges(f[touch]), n))
    kept = ~inside  # the mesh's faces in the result
    new_v, new_f, top = [v], [], n
    split = False  # a region given back in more pieces than it had
    for r, (rv, rf) in zip(regions, repaired):
        rv, rf = np.asarray(rv, dtype=np.float64), np.asarray(rf, dtype=np.int64)
        own = f[r.faces]
        ids = np.unique(own)
        match = _match_rows(v[ids], rv)
        times = np.bincount(match[match >= 0], minlength=len(ids))
        if (times[outside[ids]] != 1).any():
            return None  # a cut vertex lost, or doubled
        once = match >= 0
        once[once] = times[match[once]] == 1  # a vertex given back twice (split) is new, each copy
        index = np.empty(len(rv), np.int64)
        index[once] = ids[match[once]]
        fresh = ~once
        index[fresh] = top + np.arange(int(fresh.sum()))
        top += int(fresh.sum())
        faces = index[rf]
        # every cut edge (an edge of the region that a face outside has in the other direction) must still be
        # the border of exactly one of the region's faces, in its direction, and of none in the other
        got = np.sort(_keys(_edges(faces), top))
        e = _edges(own)
        e = e[outside[e].all(axis=1)]
        e = e[_count_in(rest_keys, _keys(e[:, ::-1], n)) > 0]
        if len(e) and not ((_count_in(got, _keys(e, top)) == 1).all() and
                           (_count_in(got, _keys(e[:, ::-1], top)) == 0).all()):
            return None
        cut = ids[outside[ids]]
        if len(cut):  # a piece the backend split off the region (no cut vertex): dropped, as MeshFix drops
            faces = faces[_touching(faces, np.isin(faces, cut).any(axis=1))]  # what it splits off a part
        split |= len(faces) and face_labels(faces).max() > face_labels(own).max()
        # the region's faces given back with the same vertices in the same turn stay where they were (a face
        # turned over is a new one)
        own_rot, got_rot = _rotated(own), _rotated(faces)
        old = _triples(own_rot, top)
        order = np.argsort(old)
        pos = np.minimum(np.searchsorted(old[order], _triples(got_rot, top)), len(old) - 1)
        same = (own_rot[order[pos]] == got_rot).all(axis=1)
        kept[r.faces[order[pos[same]]]] = True
        new_v.append(rv[fresh])
        new_f.append(faces[~same])
    vertices = np.vstack(new_v)
    faces = np.vstack([f[kept], *new_f])
    if not _seam_manifold(vertices, faces, outside & _used(f, inside, n)):
        return None
    if split:  # a part split in two (a vertex joining two sheets, split by the backend): its largest piece
        part = np.full(len(faces), -1, np.int64)  # stays, as MeshFix keeps one piece of each part it repairs
        part[:int(kept.sum())] = _face_components(mesh)[kept]
        faces = faces[_largest_piece(faces, part)]
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    return Mesh(vertices[used], (np.cumsum(used) - 1)[faces], mesh.source)


def _largest_piece(faces: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Which ``faces`` lie on the piece (connected component) with the most faces among the pieces of their
    part (``part``: each face's part in the input, -1 for a new face; a piece's part is that of its faces
    that have one, and a piece of new faces only is dropped)."""
    piece = face_labels(faces)
    n = int(piece.max()) + 1
    of = np.full(n, -1, np.int64)
    np.maximum.at(of, piece, part)
    if len(np.unique(of)) == n and (of >= 0).all():
        return np.ones(len(faces), bool)  # every part in one piece
    size = np.bincount(piece, minlength=n)
    order = np.lexsort((-size, of))
    best = order[np.r_[True, of[order][1:] != of[order][:-1]]]
    keep = np.zeros(n, bool)
    keep[best[of[best] >= 0]] = True
    return keep[piece]


def _used(f: np.ndarray, inside: np.ndarray, n: int) -> np.ndarray:
    """Which of ``n`` vertices a face in the mask ``inside`` uses."""
    out = np.zeros(n, bool)
    out[f[inside].ravel()] = True
    return out


def _seam_manifold(vertices: np.ndarray, faces: np.ndarray, cut: np.ndarray) -> bool:
    """Whether the faces at the ``cut`` vertices (a mask over the first ``len(cut)`` vertices) meet as a manifold,
    consistently oriented surface there: every edge with at most two faces, in opposite directions, and each cut
    vertex's faces one fan (a region given back with an edge the rest already has, or pinched at a cut vertex,
    would break it)."""
    at = np.zeros(len(vertices), bool)
    at[:len(cut)] = cut
    seam = faces[at[faces].any(axis=1)]
    if not len(seam):
        return True
    e = _edges(seam)
    n = len(vertices)
    undirected = np.sort(np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1]))
    directed = np.sort(_keys(e, n))
    if (np.diff(directed) == 0).any() or (_count_in(undirected, undirected) > 2).any():
        return False
    sub = Mesh(vertices, seam)
    return not (non_manifold_vertex_mask(sub) & at).any()


def _rotated(f: np.ndarray) -> np.ndarray:
    """Each face's corners turned (cyclically, the orientation kept) so that its smallest vertex comes first."""
    k = np.argmin(f, axis=1)
    r = np.arange(len(f))
    return np.stack([f[r, k], f[r, (k + 1) % 3], f[r, (k + 2) % 3]], axis=1)


def _triples(f: np.ndarray, n: int) -> np.ndarray:
    """One integer per face row in a mesh of ``n`` vertices, for sorting and looking up (a hash when n**3
    overflows 64 bits: equal rows, equal keys; a match is confirmed row by row)."""
    with np.errstate(over="ignore"):
        return (f[:, 0] * n + f[:, 1]) * n + f[:, 2]


def _touching(faces: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Which of ``faces`` are connected (through shared vertices) to a face in the mask ``seeds``."""
    comp = face_labels(faces)
    return np.isin(comp, comp[seeds])


def _match_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each row of ``b``, the index of the one row of ``a`` with exactly the same coordinates (-1: none, or
    several rows of ``a`` there, as a split vertex's copies)."""
    both = np.vstack([a, b])
    order = np.lexsort((both[:, 2], both[:, 1], both[:, 0]))
    s = both[order]
    new = np.r_[True, (s[1:] != s[:-1]).any(axis=1)]
    run = np.cumsum(new) - 1
    first = order[np.flatnonzero(new)][run]  # each run's first row: a's rows come first (lexsort is stable)
    from_a = np.bincount(run, order < len(a))[run]
    res = np.empty(len(both), np.int64)
    res[order] = np.where((first < len(a)) & (from_a == 1), first, -1)
    return res[len(a):]
