"""The census's broad phase: where the faces of a mesh may intersect. The self-intersection *candidates*, pairs
of faces sharing no vertex index that a grid of cells and the sheets of faces in each cell cannot prove apart
(:func:`intersection_candidates`), and the *fold vertices*, around which two faces sharing the vertex may meet
beyond it (:func:`fold_vertices`). The exact test (:mod:`scanreg.mesh.intersect`) decides among them
(:meth:`scanreg.mesh.census.Census.pairs_to_test`).

The loops (the sheets of each level, the pairs a level looks at, their filter, the fold vertices) run in the
compiled kernels of :mod:`scanreg.mesh.native` when they were built, with the same result (the fold vertices:
up to a fan turning within rounding of the margin, :func:`fold_vertices`); their NumPy versions stay here as
the reference (tests/test_native.py compares them). A pure function of the arrays: no processes,
threads or files.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from scanreg.geometry import Mesh, col_max, col_min, rows_any
from scanreg.mesh import native
from scanreg.mesh.boxes import candidate_pairs
from scanreg.mesh.predicates import orient3d_filter
from scanreg.mesh.topology import _cross_columns, _mesh_edges_sorted

CELL_EXTENTS = 4.0
"""The broad phase's cell side, in 90th-percentile face box extents (:func:`intersection_candidates`)."""


CONE_COS = 0.1
"""A face belongs to its cell's sheet only when its unit normal's dot product with the sheet's mean normal
exceeds this (84 degrees): the sheet is then a graph over its mean plane."""


def fold_vertices(vertices: np.ndarray, faces: np.ndarray, live: np.ndarray | None = None,
                  geometry: tuple | None = None) -> np.ndarray:
    """Vertices around which two faces sharing the vertex may intersect (:func:`fold_vertices_numpy`), by the
    compiled kernel when there is one (:mod:`scanreg.mesh.native`): the same vertices, but for a fan whose turning
    lies within rounding of the margin (its angles are glibc's ``atan2``, NumPy's ``arctan2`` differs from it in
    the last bit for some arguments, and between machines), which a fan built for it shows and no scanned mesh
    tried has."""
    v, f, nv = _live_faces(vertices, faces, live)
    if native.kernels is None or not len(f) or nv > len(v) or f.min() < 0:  # (an index past the vertices: NumPy's
        return fold_vertices_numpy(vertices, faces, live, geometry)             # IndexError)
    return np.flatnonzero(np.frombuffer(native.kernels.fold_vertices(v, np.ascontiguousarray(f), nv), np.uint8))


def _live_faces(vertices: np.ndarray, faces: np.ndarray, live: np.ndarray | None) -> tuple:
    """The vertices (float64), the ``live`` faces (int64) and the number of vertices they index (at least all)."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if live is not None:
        f = f[live]
    return v, f, max(len(v), int(f.max()) + 1) if len(f) else len(v)


def fold_vertices_numpy(vertices: np.ndarray, faces: np.ndarray, live: np.ndarray | None = None,
                        geometry: tuple | None = None) -> np.ndarray:
    """Vertices around which two faces sharing the vertex may intersect: their (``live``) faces' unit normals are
    not all within 84 degrees (:data:`CONE_COS`) of their area-weighted mean (a flipped face, a crease sharper
    than 96 degrees), or they are, but the faces' corners projected onto the mean's plane add up to more than one
    turn (a fan that covers itself, as pymeshfix's bunny has five of). A fan within the cone that turns once,
    manifold and consistently oriented (the census reports the vertices and edges that are not), is a graph
    over its mean plane: two of its faces meet only along what they share. ``geometry``: :func:`face_geometry`
    of the live faces when already made."""
    v, f, nv = _live_faces(vertices, faces, live)
    if not len(f):
        return np.zeros(0, np.int64)
    _, e, n = geometry if geometry is not None else face_geometry(v, f)
    vid = f.T.ravel()  # corner 0 of every face, then corner 1, then corner 2
    mean = [np.bincount(vid, np.tile(nk, 3), minlength=nv) for nk in n]
    length = np.sqrt(mean[0] * mean[0] + mean[1] * mean[1] + mean[2] * mean[2])
    unit = [mk / np.maximum(length, 1e-300) for mk in mean]
    fn = np.tile(np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), 3)
    dot = sum(np.tile(n[k], 3) * unit[k][vid] for k in range(3))
    folded = np.bincount(vid, dot <= CONE_COS * fn, minlength=nv) > 0
    # each corner's angle projected onto its vertex's mean plane: from the outgoing edge to the reversed
    # incoming one (positive for a face within the cone)
    out = [np.concatenate([e[i][k] for i in range(3)]) for k in range(3)]
    back = [-np.concatenate([e[i - 1][k] for i in range(3)]) for k in range(3)]
    u = [unit[k][vid] for k in range(3)]
    sin = dot  # (out x back) . u is the face's normal . u, the same for each corner of the face
    cos = sum(out[k] * back[k] for k in range(3)) - sum(out[k] * u[k] for k in range(3)) * sum(
        back[k] * u[k] for k in range(3))
    turns = np.bincount(vid, np.arctan2(sin, cos), minlength=nv)
    return np.flatnonzero(folded | (turns > 2 * np.pi + 1e-6))


def face_geometry(v: np.ndarray, f: np.ndarray) -> tuple[list, list, list]:
    """Per face, as contiguous columns: the corners ``c[i][k]`` (coordinate k of corner i), the edges
    ``e[i][k]`` (corner i to corner i + 1) and the normal ``n[k]`` (edge 0 x edge 1: twice the area long)."""
    cols = [np.ascontiguousarray(v[:, k]) for k in range(3)]
    c = [[cols[k][f[:, i]] for k in range(3)] for i in range(3)]
    e = [[c[(i + 1) % 3][k] - c[i][k] for k in range(3)] for i in range(3)]
    return c, e, _cross_columns(e[0], e[1])


def intersection_candidates(vertices: np.ndarray, faces: np.ndarray, live: np.ndarray | None = None,
                            cell: float | None = None, table: tuple | None = None,
                            folds: np.ndarray | None = None, geometry: tuple | None = None) -> np.ndarray:
    """Pairs of faces sharing no vertex index that may intersect: a conservative broad phase for the exact test
    of :mod:`scanreg.mesh.intersect` (``live``: the faces that take part, e.g. the non-degenerate ones).

    Space is cut into cubic cells (side ``cell``, by default :data:`CELL_EXTENTS` times the 90th percentile of
    the faces' largest box side); each face belongs to every cell its bounding box touches (of several, those
    its plane passes through). In each cell the faces there are joined across their manifold, consistently
    oriented edges into sheets. A sheet whose faces' normals all lie within 84 degrees of its mean normal
    (:data:`CONE_COS`) and that has no fold vertex projects onto its mean plane without folding, so two of its
    faces cannot meet beyond what they share unless the sheet winds around an axis inside the cell without a
    fold, as a helicoid's turn at the scale of a few edges (the one case taken not to happen). Two faces that
    meet at a point have that point in a common cell, so only these pairs are looked at: in each cell, those
    between a sheet and its cell's other sheets (a second surface passing, or a fringe of faces whose box
    reaches into the cell while their neighbours' do not), and within a sheet that is not a graph (curved more
    than the cone within the cell, folded, inconsistently oriented, or with a face at one of the ``folds``,
    :func:`fold_vertices`), whose faces are looked at again in cells of half the side, :data:`REFINE` times,
    then pair by pair. Of those pairs, the ones whose boxes overlap and that no face's plane separates (every
    corner of one face certainly on one side of the other's plane, by the exact predicates' floating-point
    filter) are the candidates. A face whose box touches more than :data:`MAX_CELLS` cells is paired by boxes
    with every face instead. ``table`` (the faces' edge table, :func:`~scanreg.mesh.topology._edge_table_sorted`),
    ``folds`` and ``geometry`` (:func:`face_geometry` of the live faces): when already made."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    idx = np.arange(len(f)) if live is None else np.flatnonzero(live)
    if len(idx) < 2:
        return np.zeros((0, 2), np.int64)
    fl = f[idx]
    # corner columns: coordinate k of corner i of each face, contiguous (quicker than (m, 3, 3) rows)
    if geometry is None:
        geometry = face_geometry(v, fl)
    corner = geometry[0]
    lo = np.stack([np.minimum(np.minimum(corner[0][k], corner[1][k]), corner[2][k]) for k in range(3)], axis=1)
    hi = np.stack([np.maximum(np.maximum(corner[0][k], corner[1][k]), corner[2][k]) for k in range(3)], axis=1)
    if cell is None:
        ext = (hi - lo)[::max(1, len(fl) // 4096)]  # a sample is enough for a scale
        cell = CELL_EXTENTS * float(np.quantile(np.maximum(np.maximum(ext[:, 0], ext[:, 1]), ext[:, 2]), 0.9))
    if not cell > 0:  # every face a point
        cell = 1.0
    nrm = np.stack(geometry[2], axis=1)
    if folds is None:
        folds = fold_vertices(v, f, live, geometry)
    at_fold = np.zeros(max(len(v), int(fl.max()) + 1), bool)
    at_fold[folds] = True
    suspect = rows_any(at_fold[fl])
    org = col_min(lo)
    p0 = np.stack([corner[0][k] for k in range(3)], axis=1)
    pos = np.full(len(f), -1, np.int64)
    pos[idx] = np.arange(len(idx))
    f1, f2 = (pos[x] for x in _manifold_neighbours(f, table))
    both = (f1 >= 0) & (f2 >= 0)
    f1, f2 = f1[both], f2[both]
    ii, jj = [], []
    sel = np.arange(len(fl))
    for level in range(REFINE + 1):
        a, span, cnt, cell = _cells(lo[sel], hi[sel], org, cell)
        huge = cnt == 0
        if huge.any():  # paired by their boxes with every face of this level
            i, j = candidate_pairs(lo[sel], hi[sel], huge)
            ii.append(sel[i])
            jj.append(sel[j])
        inside = np.zeros(len(fl), bool)
        inside[sel] = True
        link = inside[f1] & inside[f2]
        local = np.full(len(fl), -1, np.int64)
        local[sel] = np.arange(len(sel))
        i, j, bad = _sheet_pairs(a, span, cnt, nrm[sel], suspect[sel], local[f1[link]], local[f2[link]],
                                 level == REFINE, (org, cell, p0[sel]), (lo[sel], hi[sel], fl[sel]))
        ii.append(sel[i])
        jj.append(sel[j])
        if not len(bad):
            break
        sel, cell = sel[bad], cell / 2
    i, j = _candidates_among(np.concatenate(ii), np.concatenate(jj), lo, hi, fl, v)
    return np.stack([idx[i], idx[j]], axis=1).astype(np.int64)


def _candidates_among(i: np.ndarray, j: np.ndarray, lo: np.ndarray, hi: np.ndarray, fl: np.ndarray,
                      v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The end of :func:`intersection_candidates`: of the pairs ``(i, j)`` looked at (positions in the faces
    ``fl``, boxes ``lo``, ``hi``; repeats possible), those whose boxes overlap and that share no vertex index,
    each once, sorted, that no face's plane separates (:func:`_candidates_among_numpy`), by the compiled kernel
    when there is one (the same pairs)."""
    if native.kernels is None or not len(i):
        return _candidates_among_numpy(i, j, lo, hi, fl, v)
    pairs = np.frombuffer(native.kernels.candidate_filter(
        np.ascontiguousarray(i, dtype=np.int64), np.ascontiguousarray(j, dtype=np.int64),
        np.ascontiguousarray(lo), np.ascontiguousarray(hi), np.ascontiguousarray(fl, dtype=np.int64), v),
        np.int64).reshape(-1, 2)
    return pairs[:, 0], pairs[:, 1]


def _candidates_among_numpy(i: np.ndarray, j: np.ndarray, lo: np.ndarray, hi: np.ndarray, fl: np.ndarray,
                            v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_candidates_among` in NumPy."""
    if len(i):
        keep = _overlapping_apart(i, j, lo, hi, fl)
        i, j = i[keep], j[keep]
        key = np.unique(np.minimum(i, j) * len(fl) + np.maximum(i, j))
        i, j = key // len(fl), key % len(fl)
        Pi, Pj = v[fl[i]], v[fl[j]]
        keep = ~(_separated(Pi, Pj) | _separated(Pj, Pi))
        i, j = i[keep], j[keep]
    return i, j


def _overlapping_apart(i: np.ndarray, j: np.ndarray, lo: np.ndarray, hi: np.ndarray, fl: np.ndarray) -> np.ndarray:
    """Which pairs ``(i, j)`` of the faces ``fl`` (boxes ``lo``, ``hi``) have overlapping boxes and share no vertex
    index: the candidates' first two conditions."""
    keep = _boxes_overlap(lo, hi, i, j)
    fc = [np.ascontiguousarray(fl[:, k]) for k in range(3)]
    for x in range(3):
        fi = fc[x][i]
        for y in range(3):
            keep &= fi != fc[y][j]
    return keep


MAX_CELLS = 4096
"""A face whose bounding box touches more cells than this is paired by boxes instead of cells."""
MAX_KEYS = 2.0 ** 62
"""The cells of one level are numbered in int64: a grid with more cells than this is made coarser."""


def _cells(lo: np.ndarray, hi: np.ndarray, org: np.ndarray, cell: float) -> tuple:
    """The cells of the boxes ``[lo, hi]`` on a grid of side ``cell`` from ``org``: each box's first cell, its cells
    per axis and its cells in all (int64; 0 for a box touching more than :data:`MAX_CELLS`, paired by boxes
    instead, whose first cell and cells per axis are then placeholders within the others'), and the side used.
    The side is doubled until the block of cells the other boxes touch can be numbered in int64 (a mesh spanning
    more than about 2^20 of its cells per axis: faces far apart); counted in floating point, so that no product
    overflows."""
    while True:
        a = np.floor((lo - org) / cell)
        span = np.floor((hi - org) / cell) - a + 1
        kept = span[:, 0] * span[:, 1] * span[:, 2] <= MAX_CELLS
        if not kept.any():
            break
        first = col_min(a[kept])
        top = col_max(a[kept] + span[kept]) - first + 1
        if float(top[0]) * float(top[1]) * float(top[2]) < MAX_KEYS:
            break
        cell *= 2.0
    if not kept.all():  # the huge boxes' placeholders: a cell of the others, one cell per axis (cnt is 0)
        a[~kept] = first if kept.any() else 0.0
        span[~kept] = 1.0
    a, span = a.astype(np.int64), span.astype(np.int64)
    cnt = np.where(kept, span[:, 0] * span[:, 1] * span[:, 2], 0)
    return a, span, cnt, cell


REFINE = 2
"""How many times the faces of sheets that are not graphs are looked at again in cells of half the side."""


def _boxes_overlap(lo: np.ndarray, hi: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Whether the closed boxes ``i`` and ``j`` overlap (axis by axis, on the pairs left)."""
    keep = np.ones(len(i), bool)
    for k in range(3):
        lk, hk = lo[:, k], hi[:, k]
        keep &= (lk[i] <= hk[j]) & (lk[j] <= hk[i])
    return keep


def _separated(Pi: np.ndarray, Pj: np.ndarray) -> np.ndarray:
    """Whether every corner of each face ``Pj`` (corners (n, 3, 3)) lies certainly on one side of the plane of
    the face ``Pi`` beside it."""
    a, b, c = Pi[:, 0], Pi[:, 1], Pi[:, 2]
    s = np.stack([orient3d_filter(a, b, c, Pj[:, k]) for k in range(3)], axis=1)
    return (s > 0).all(axis=1) | (s < 0).all(axis=1)


def _sheet_pairs(a: np.ndarray, span: np.ndarray, cnt: np.ndarray, nrm: np.ndarray, suspect: np.ndarray,
                 f1: np.ndarray, f2: np.ndarray, last: bool, frame: tuple,
                 faces: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One level of :func:`intersection_candidates` on m faces: the pairs it looks at (face positions 0..m-1,
    repeats possible) and the faces of sheets that are not graphs, to be looked at in smaller cells (none when
    ``last``: their pairs are then among the pairs). ``a``: each face's first cell (integer coordinates),
    ``span``: its cells per axis, ``cnt``: its cells in all (0: the face takes no part), ``nrm``: normals (any
    length), ``suspect``: faces whose sheet is not a graph whatever their normals, ``f1``, ``f2``: the faces
    joined across an edge (:func:`_manifold_neighbours`), ``frame``: the grid's origin, the cell side and a corner
    of each face (a face spanning several cells is in those its plane passes through), ``faces``: their boxes
    (lo, hi) and vertex indices, to keep only the pairs that overlap and share no vertex (the candidates' first
    conditions, which the end applies anyway: fewer pairs to carry there)."""
    m = len(a)
    none = np.zeros(0, np.int64)
    if not cnt.any():
        return none, none, none
    base = col_min(a)
    a = a - base
    dims = col_max(a) + col_max(span) + 1
    face, ckey, present, sheet, n_sheets = _sheets(a, span, cnt, nrm, f1, f2, dims, base, frame)
    # a sheet is a graph when each face's unit normal is within the cone around the sheet's mean normal
    fn = nrm[face]
    norm = np.sqrt(nrm[:, 0] * nrm[:, 0] + nrm[:, 1] * nrm[:, 1] + nrm[:, 2] * nrm[:, 2])
    mean = np.stack([np.bincount(sheet, fn[:, k], minlength=n_sheets) for k in range(3)], axis=1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1), 1e-300)[:, None]
    dot = np.einsum("ij,ij->i", fn, mean[sheet])
    bad_sheet = np.bincount(sheet, (dot <= CONE_COS * norm[face]) | suspect[face], minlength=n_sheets) > 0
    bad_face = np.zeros(m, bool)
    bad_face[face[bad_sheet[sheet]]] = True
    bad = none if last else np.flatnonzero(bad_face)
    return (*_cross_sheet_pairs(face, ckey, present, sheet, n_sheets, bad_sheet, last, faces), bad)


def _sheets(a: np.ndarray, span: np.ndarray, cnt: np.ndarray, nrm: np.ndarray, f1: np.ndarray, f2: np.ndarray,
            dims: np.ndarray, base: np.ndarray, frame: tuple) -> tuple:
    """One level's instances and sheets: ``(face, ckey, present, sheet, n_sheets)`` (:func:`_sheets_numpy`), by
    the compiled kernel when there is one (:mod:`scanreg.mesh.native`: the same arrays)."""
    if native.kernels is None:
        return _sheets_numpy(a, span, cnt, nrm, f1, f2, dims, base, frame)
    return _sheets_kernel(a, span, cnt, nrm, f1, f2, dims, base, frame)


def _sheets_kernel(a: np.ndarray, span: np.ndarray, cnt: np.ndarray, nrm: np.ndarray, f1: np.ndarray,
                   f2: np.ndarray, dims: np.ndarray, base: np.ndarray, frame: tuple) -> tuple:
    """:func:`_sheets_numpy` by the compiled kernel ``sheets``."""
    org, cell, p0 = frame
    face, ckey, present, sheet, n_sheets = native.kernels.sheets(
        *(np.ascontiguousarray(x, dtype=np.int64) for x in (a, span, cnt)),
        *(np.ascontiguousarray(x, dtype=np.float64) for x in (nrm, p0)),
        *(np.ascontiguousarray(x, dtype=np.int64) for x in (f1, f2)),
        tuple(int(x) for x in dims), tuple(int(x) for x in base), tuple(float(x) for x in org), float(cell))
    return (np.frombuffer(face, np.int64), np.frombuffer(ckey, np.int64), np.frombuffer(present, np.bool_),
            np.frombuffer(sheet, np.int64), int(n_sheets))


def _sheets_numpy(a: np.ndarray, span: np.ndarray, cnt: np.ndarray, nrm: np.ndarray, f1: np.ndarray,
                  f2: np.ndarray, dims: np.ndarray, base: np.ndarray, frame: tuple) -> tuple:
    """The instances of one level of :func:`_sheet_pairs` (a face in each cell its box touches, face by face, its
    cells x-major) and its sheets: per instance its ``face``, cell key ``ckey``, whether it is ``present`` (the
    face's plane passes through the cell) and its ``sheet`` (labelled in the order of each sheet's first
    instance), and the number of sheets. ``a``: each face's first cell from ``base`` (the grid's cells in
    ``dims``), the other arguments :func:`_sheet_pairs`'."""
    m = len(a)
    # one instance per (face, cell its box touches), face by face; cell keys ckey (a face in one cell: its own)
    start = np.cumsum(cnt) - cnt
    face = np.repeat(np.arange(m), cnt)
    n_inst = len(face)
    fkey = (a[:, 0] * dims[1] + a[:, 1]) * dims[2] + a[:, 2]
    multi = np.flatnonzero(cnt > 1)
    ckey = fkey[face]
    present = np.ones(n_inst, bool)
    if len(multi):
        at = _expand(start[multi], cnt[multi])
        ckey[at] += _block_offsets(span[multi], cnt[multi], dims)
        wide = at[cnt[face[at]] > 2]  # a face whose box spans cells along more than one axis
        present[wide] = _on_plane(ckey[wide], dims, base, frame, nrm, face[wide])
    # sheets: instances in one cell joined across the faces' manifold, consistently oriented edges. Two faces in
    # one cell each: joined when it is the same cell. Otherwise each cell of f1 that f2's box touches too, f2's
    # instance there found by arithmetic (its cells are a block)
    one = cnt == 1
    simple = one[f1] & one[f2]
    same = simple & (fkey[f1] == fkey[f2])
    u, w = [start[f1[same]]], [start[f2[same]]]
    g1, g2 = f1[~simple & (cnt[f1] > 0) & (cnt[f2] > 0)], f2[~simple & (cnt[f1] > 0) & (cnt[f2] > 0)]
    inst1 = _expand(start[g1], cnt[g1])
    g2 = np.repeat(g2, cnt[g1])
    cx, r = np.divmod(ckey[inst1], dims[1] * dims[2])
    cy, cz = np.divmod(r, dims[2])
    rel = [cx - a[g2, 0], cy - a[g2, 1], cz - a[g2, 2]]
    ok = (rel[0] >= 0) & (rel[1] >= 0) & (rel[2] >= 0)
    for k in range(3):
        ok &= rel[k] < span[g2, k]
    u.append(inst1[ok])
    w.append(start[g2[ok]] + ((rel[0][ok] * span[g2[ok], 1] + rel[1][ok]) * span[g2[ok], 2] + rel[2][ok]))
    u, w = np.concatenate(u), np.concatenate(w)
    both = present[u] & present[w]
    u, w = u[both], w[both]
    g = coo_matrix((np.ones(len(u), np.int8), (u, w)), shape=(n_inst, n_inst))
    n_sheets, sheet = connected_components(g, directed=True, connection="weak")
    return face, ckey, present, sheet, n_sheets


def _cross_sheet_pairs(face, ckey, present, sheet, n_sheets, bad_sheet, last,
                       faces: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of faces one level of :func:`_sheet_pairs` looks at (:func:`_cross_sheet_pairs_numpy`) whose
    boxes overlap and that share no vertex (:func:`_overlapping_apart`; ``faces``: the level's boxes lo, hi and
    vertex indices), by the compiled kernel when there is one (the same pairs, in another order)."""
    if native.kernels is None:
        i, j = _cross_sheet_pairs_numpy(face, ckey, present, sheet, n_sheets, bad_sheet, last)
        keep = _overlapping_apart(i, j, *faces)
        return i[keep], j[keep]
    lo, hi, fl = (np.ascontiguousarray(x, dtype=t) for x, t in zip(faces, (np.float64, np.float64, np.int64)))
    pairs = np.frombuffer(native.kernels.cross_sheet_pairs(
        np.ascontiguousarray(face, dtype=np.int64), np.ascontiguousarray(ckey, dtype=np.int64),
        np.ascontiguousarray(present, dtype=np.uint8), np.ascontiguousarray(sheet, dtype=np.int64), int(n_sheets),
        np.ascontiguousarray(bad_sheet, dtype=np.uint8), bool(last), lo, hi, fl), np.int64).reshape(-1, 2)
    return pairs[:, 0], pairs[:, 1]


def _cross_sheet_pairs_numpy(face, ckey, present, sheet, n_sheets, bad_sheet, last) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of faces one level of :func:`_sheet_pairs` looks at: each cell's largest sheet is its main one;
    the instances of the others are paired with every instance of their cell of another sheet (and, on the
    ``last`` level, those of a sheet that is not a graph with every one). Per instance: its ``face``, its cell
    key ``ckey``, whether it is ``present`` (in a cell its face's plane passes through), its ``sheet``."""
    none = np.zeros(0, np.int64)
    cell_of = np.empty(n_sheets, np.int64)
    cell_of[sheet] = np.where(present, ckey, -1)  # an instance left out: a sheet of its own, in no cell
    by_cell = np.lexsort((-np.bincount(sheet, minlength=n_sheets), cell_of))
    head = np.r_[True, cell_of[by_cell][1:] != cell_of[by_cell][:-1]]
    main = np.zeros(n_sheets, bool)
    main[by_cell[head]] = True
    source = ~main | (bad_sheet & last)
    hot_cell = np.logical_or.reduceat(source[by_cell], np.flatnonzero(head))  # cells in by_cell's order
    hot_sheet = np.zeros(n_sheets, bool)
    hot_sheet[by_cell] = hot_cell[np.cumsum(head) - 1]
    hot = np.flatnonzero(hot_sheet[sheet] & present)
    if not len(hot):
        return none, none
    hot = hot[np.argsort(ckey[hot], kind="stable")]  # the instances of the hot cells, by cell
    hk, hs = ckey[hot], sheet[hot]
    first = np.r_[True, hk[1:] != hk[:-1]]
    begin = np.flatnonzero(first)
    cid = np.cumsum(first) - 1
    n = np.diff(np.r_[begin, len(hk)])
    src = np.flatnonzero(source[hs])
    I = np.repeat(src, n[cid[src]])
    J = np.arange(len(I)) + np.repeat(begin[cid[src]] - (np.cumsum(n[cid[src]]) - n[cid[src]]), n[cid[src]])
    keep = (hs[I] != hs[J]) | (bad_sheet[hs[I]] & (I != J) & last)
    return face[hot[I[keep]]], face[hot[J[keep]]]


def _on_plane(ckey: np.ndarray, dims: np.ndarray, base: np.ndarray, frame: tuple, nrm: np.ndarray,
              fm: np.ndarray) -> np.ndarray:
    """Whether the plane of face ``fm`` passes through the cell ``ckey`` (keys in ``dims``, offset by ``base``
    from the grid's ``frame``: origin, side, a corner per face), with a margin for rounding: the plane's
    distance from the cell's centre is at most the cell's half-extent along the normal."""
    org, cell, p0 = frame
    cx, r = np.divmod(ckey, dims[1] * dims[2])
    cy, cz = np.divmod(r, dims[2])
    d, reach, size = 0.0, 0.0, 0.0
    for k, ck in enumerate((cx, cy, cz)):
        centre = org[k] + (ck + base[k] + 0.5) * cell
        nk = nrm[fm, k]
        d = d + nk * (centre - p0[fm, k])
        reach = reach + np.abs(nk)
        size = size + np.abs(nk) * (np.abs(centre) + np.abs(p0[fm, k]))
    return np.abs(d) <= 0.5 * cell * reach * (1 + 1e-9) + 1e-12 * size


def _expand(first: np.ndarray, count: np.ndarray) -> np.ndarray:
    """``first[k], first[k] + 1, ..., first[k] + count[k] - 1`` for every k, concatenated."""
    return np.repeat(first - np.cumsum(count) + count, count) + np.arange(int(count.sum()))


def _block_offsets(span: np.ndarray, cnt: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """The cell key offsets (keys ``(x * dims[1] + y) * dims[2] + z``) of the cells of blocks of ``span`` cells
    per axis, block after block, x-major."""
    k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    sy, sz = np.repeat(span[:, 1], cnt), np.repeat(span[:, 2], cnt)
    ox, k = np.divmod(k, sy * sz)
    oy, oz = np.divmod(k, sz)
    return (ox * dims[1] + oy) * dims[2] + oz


def _manifold_neighbours(f: np.ndarray, table: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of faces on each edge with exactly two faces that traverse it in opposite directions
    (``table``: :func:`~scanreg.mesh.topology._edge_table_sorted` of ``f`` when already made)."""
    directed, edge, counts, order = table if table is not None else _mesh_edges_sorted(Mesh(np.zeros((0, 3)), f))
    rows = order[counts[edge[order]] == 2]
    r1, r2 = rows[0::2], rows[1::2]
    opposite = directed[r1, 0] == directed[r2, 1]
    return r1[opposite] % len(f), r2[opposite] % len(f)
