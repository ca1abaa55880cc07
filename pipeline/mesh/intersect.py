"""Exact self-intersection test of a triangle mesh (NumPy; its box search by a compiled kernel when built).

A face is self-intersecting when it has a point in common with another face beyond the vertices they share
(vertices at the same position count as one: two faces that touch only at a duplicated vertex do not intersect):

* no shared vertex: the two closed triangles touch or cross anywhere;
* one shared vertex ``v``: they meet at a point other than ``v`` (one folds into the other);
* a shared edge: they are coplanar and lie on the same side of that edge (folded flat onto each other);
* the same three vertices: a duplicated face.

Degenerate faces (repeated vertex indices or collinear corners, exactly) take no part; the audit counts them
separately. Every decision rests on the exact predicates of :mod:`scanreg.mesh.predicates`, so the result is
exact for the floating-point coordinates as given and depends on nothing but them: not on the order of the
faces, on what was tested before, or on the scale of the coordinates (a ``2^k`` scaling gives the same answer).

Candidate pairs are the faces whose bounding boxes overlap (:func:`scanreg.mesh.boxes.candidate_pairs`).
Pairs that share a vertex whose fan turns once around it (:func:`regular_vertices`, decided with the same
predicates) cannot intersect and are not tested: that settles most neighbours. A mesh that shares most faces
with one tested before can be tested from that outcome (:func:`self_intersections` with ``previous``): the
pairs both have keep their outcome and only pairs with a new face are tested, which gives the same result.
Tests: tests/test_intersect.py (a rational brute-force reference).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scanreg.geometry import col_max, col_min, rows_all, rows_any
from scanreg.mesh import native
from scanreg.mesh.boxes import _near_boxes, candidate_pairs, face_boxes, mesh_face_boxes
from scanreg.mesh.predicates import orient2d, orient3d, projection_axes, segment_meets_triangle, take2


@dataclass
class Intersections:
    """The outcome of a self-intersection test: the mesh's arrays as tested and its intersecting face pairs."""

    vertices: np.ndarray
    faces: np.ndarray
    pairs: np.ndarray
    """Rows ``(i, j)`` of faces that intersect, ``i < j``."""
    keys: np.ndarray | None = field(default=None, repr=False)
    """A hash of each face's corner coordinates (:func:`face_keys`) for a later incremental test; None for a
    mesh too small to be worth one."""
    _sorted: tuple | None = field(default=None, repr=False)

    @property
    def mask(self) -> np.ndarray:
        """Which faces intersect another."""
        out = np.zeros(len(self.faces), bool)
        out[self.pairs.ravel()] = True
        return out

    @property
    def count(self) -> int:
        """The number of self-intersecting faces."""
        return int(np.count_nonzero(self.mask))

    def sorted_keys(self) -> tuple[np.ndarray, np.ndarray]:
        """``(order, keys[order])``, the keys sorted (stably), computed once."""
        if self._sorted is None:
            order = stable_order(self.keys)
            self._sorted = (order, self.keys[order])
        return self._sorted


MIN_FACES = 1000
"""Smaller meshes (the neighbourhood of an edit) are always tested in full: hashing their faces for an
incremental test would cost more than it saves."""
MAX_RATIO = 8
"""A previous mesh with more than this many times the faces is not used for an incremental test."""
PROBE = 512
"""Faces (every k-th) that first tell whether a previous mesh may share half of the faces. A wrong call costs
only speed: the test then runs in full, with the same result."""


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boolean mask of the self-intersecting faces (see the module docstring for the definition)."""
    return self_intersections(vertices, faces).mask


def self_intersections(vertices: np.ndarray, faces: np.ndarray,
                       previous: Intersections | None = None) -> Intersections:
    """The self-intersection test of a mesh. With ``previous`` (the outcome for a mesh that shares more than
    half of these faces, the same corner coordinates: a repair's input and its output, a loop that cuts out
    and refills a few faces), only the pairs with a face the previous mesh did not have are tested; the
    outcome of a pair depends on its two faces' coordinates alone, so the result is the same as a full test, bit
    for bit (tests/test_intersect.py checks it). Otherwise, or when it shares fewer faces, the test is full."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if len(f) < 2:
        return Intersections(v, f, np.zeros((0, 2), np.int64))
    keys = face_keys(v, f) if len(f) >= MIN_FACES else None
    out = Intersections(v, f, np.zeros((0, 2), np.int64), keys)
    if keys is not None and previous is not None and previous.keys is not None and _shares_half(out, previous):
        out.pairs = _incremental(v, f, out, previous)
    else:
        out.pairs = _all_pairs(*_welded(v, f))
    return out


def intersections_among(vertices: np.ndarray, faces: np.ndarray, pairs: np.ndarray) -> Intersections:
    """The self-intersection test of a mesh decided on the face ``pairs`` (P, 2; smaller first, each once) only,
    exactly as the full test decides each: the full test's outcome when the pairs include every intersecting
    one (a broad phase's candidates, :meth:`scanreg.mesh.census.Census.pairs_to_test`). Pairs with a
    degenerate face take no part, as in the full test."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    out = Intersections(v, f, np.zeros((0, 2), np.int64), face_keys(v, f) if len(f) >= MIN_FACES else None)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(f) < 2 or not len(pairs):
        return out
    vw, fw, live = _welded(v, f)
    pairs = pairs[live[pairs].all(axis=1)]
    hit = np.concatenate([_pair_hits(vw[fw], fw, pairs[s:s + PAIR_BLOCK, 0], pairs[s:s + PAIR_BLOCK, 1])
                          for s in range(0, len(pairs), PAIR_BLOCK)] or [np.zeros(0, bool)])
    out.pairs = pairs[hit]
    return out


def degenerate_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces with a repeated vertex index or three collinear corners (exactly)."""
    f = faces
    bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    _, projects = projection_axes(*(vertices[f[:, k]] for k in range(3)))
    return bad | ~projects


def _lookup(srt: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``a``, a position in the sorted ``srt`` (non-empty) and whether ``srt`` holds it there."""
    k = np.minimum(np.searchsorted(srt, a), len(srt) - 1)
    return k, srt[k] == a


def _member(a: np.ndarray, srt: np.ndarray) -> np.ndarray:
    """``np.isin(a, srt)`` for integer arrays, ``srt`` sorted: by binary search."""
    return _lookup(srt, a)[1]


def _once(srt: np.ndarray) -> np.ndarray:
    """Which entries of the sorted ``srt`` occur only once."""
    dup = srt[1:] == srt[:-1]
    once = np.ones(len(srt), bool)
    once[1:] &= ~dup
    once[:-1] &= ~dup
    return once


def _same_ray(v2, a2, b2) -> np.ndarray:
    """``a`` and ``b`` (2-D, collinear with ``v``) lie on the same half-line from ``v`` (exact comparisons)."""
    return rows_all(np.sign(a2 - v2) == np.sign(b2 - v2))


def regular_vertices(v: np.ndarray, fl: np.ndarray) -> np.ndarray:
    """Vertices around which no two of the faces ``fl`` can intersect beyond the vertex (nor fold flat onto
    each other across an edge at it): the faces, each turned to start at the vertex, ``(v, x, y)``, project
    along one axis with the same non-zero orientation; their edges chain up (every end ``y`` is another face's
    start ``x``, except at most one of each, a border), and the chain's wedges turn once around the vertex (one
    wedge contains the first start's direction, counting each wedge from its start, and a border's last end
    is not on the first start's ray). The wedges then meet only along the edges consecutive faces share.
    Every decision is made with the exact predicates; a vertex that fails any is simply tested pair by pair."""
    nv = len(v)
    if not len(fl):
        return np.zeros(nv, bool)
    c = np.concatenate([fl, fl[:, [1, 2, 0]], fl[:, [2, 0, 1]]])  # rows (v, x, y): each corner's wedge
    vid, x, y = c[:, 0], c[:, 1], c[:, 2]
    # the projection axis per vertex: the largest component of the sum of its faces' normals
    e1, e2 = v[fl[:, 1]] - v[fl[:, 0]], v[fl[:, 2]] - v[fl[:, 0]]
    n = [e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
         e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]]
    fid = np.tile(np.arange(len(fl)), 3)
    nsum = np.stack([np.bincount(vid, nk[fid], minlength=nv) for nk in n], axis=1)
    drop = np.argmax(np.abs(nsum), axis=1)[vid]
    proj = np.stack([v[:, [1, 2]], v[:, [0, 2]], v[:, [0, 1]]])  # (3, nv, 2): every vertex along each axis

    def flat(ids):
        return proj[drop, ids]

    v2, x2, y2 = flat(vid), flat(x), flat(y)
    o = orient2d(v2, x2, y2)
    ok = np.ones(nv, bool)
    ok[vid[o == 0]] = False
    pos = np.bincount(vid, o > 0, minlength=nv)
    deg = np.bincount(vid, minlength=nv)
    ok &= (pos == 0) | (pos == deg)
    sigma = np.where(pos[vid] > 0, 1, -1).astype(np.int8)
    # the chain: starts and ends each once per vertex; at most one start that is no end
    start_key, end_key = vid * nv + x, vid * nv + y
    s_order, e_order = np.argsort(start_key), np.argsort(end_key)
    starts, ends = start_key[s_order], end_key[e_order]
    for srt in (starts, ends):
        ok[(srt[1:][srt[1:] == srt[:-1]]) // nv] = False

    def member(order: np.ndarray, srt: np.ndarray, other: np.ndarray) -> np.ndarray:
        """Which keys (sorted ``srt``, ``order`` their rows) occur in the sorted ``other``: searched in order,
        which keeps the binary search in cache."""
        out = np.empty(len(srt), bool)
        out[order] = _member(srt, other)
        return out

    matched = member(s_order, starts, ends)
    loose = np.bincount(vid, ~matched, minlength=nv)
    ok &= loose <= 1
    # the reference direction: the loose start, else any start
    ref = np.full(nv, -1, np.int64)
    ref[vid] = x  # any
    ref[vid[~matched]] = x[~matched]
    r2 = flat(ref[vid])
    o_xr = orient2d(v2, x2, r2)
    at_start = (ref[vid] == x) | ((o_xr == 0) & _same_ray(v2, x2, r2))
    inside = (sigma * o_xr > 0) & (sigma * orient2d(v2, r2, y2) > 0)
    count = np.bincount(vid, at_start | inside, minlength=nv)
    ok &= count == 1
    # a border's last end on the first start's ray: the fan closes onto itself through two distinct edges
    last = ~member(e_order, ends, starts)
    if last.any():
        k = np.flatnonzero(last)
        closes = (orient2d(v2[k], y2[k], r2[k]) == 0) & _same_ray(v2[k], y2[k], r2[k])
        ok[vid[k[closes]]] = False
    ok &= deg > 0
    return ok


def _pair_hits(P: np.ndarray, fl: np.ndarray, i: np.ndarray, j: np.ndarray,
               regular: np.ndarray | None = None) -> np.ndarray:
    """Which candidate pairs ``(i, j)`` of the faces ``fl`` (vertex ids, one per position; corners ``P``)
    intersect. Pairs that share a vertex of ``regular`` (:func:`regular_vertices`) cannot, and are not tested."""
    Fi, Fj = fl[i], fl[j]
    # in_j[a]: corner a of i is a corner of j (column by column: NumPy's reductions over axes of 3 are slow);
    # a live face's corners are distinct, so their count is the number of shared vertices
    in_j = [(Fi[:, a] == Fj[:, 0]) | (Fi[:, a] == Fj[:, 1]) | (Fi[:, a] == Fj[:, 2]) for a in range(3)]
    shared = in_j[0].astype(np.int8) + in_j[1] + in_j[2]
    if regular is not None:
        at_regular = (regular[Fi[:, 0]] & in_j[0]) | (regular[Fi[:, 1]] & in_j[1]) | (regular[Fi[:, 2]] & in_j[2])
        shared[at_regular & (shared < 3)] = -1  # settled, no hit

    def corners_equal(s: np.ndarray) -> np.ndarray:  # e[p, a, b]: corner a of i is corner b of j
        return Fi[s][:, :, None] == Fj[s][:, None, :]

    hit = np.zeros(len(i), bool)
    hit[shared == 3] = True  # the same face twice

    # one shared vertex: the edge opposite it in either face meets the other face
    s = np.flatnonzero(shared == 1)
    if len(s):
        e = corners_equal(s)
        ca = e.any(axis=2).argmax(axis=1)  # the shared corner's position in i
        cb = e.any(axis=1).argmax(axis=1)  # ... in j
        r = np.arange(len(s))
        Pi, Pj = P[i[s]], P[j[s]]
        xa, ya = Pi[r, (ca + 1) % 3], Pi[r, (ca + 2) % 3]
        xb, yb = Pj[r, (cb + 1) % 3], Pj[r, (cb + 2) % 3]
        # the faces meet only at v when one of them has both its other corners strictly on one side of the
        # other's plane (the plane cuts it in v alone)
        sxa, sya = (orient3d(Pj[:, 0], Pj[:, 1], Pj[:, 2], x) for x in (xa, ya))
        apart = sxa.astype(np.int16) * sya > 0
        t = np.flatnonzero(~apart)
        sxb, syb = (orient3d(Pi[t, 0], Pi[t, 1], Pi[t, 2], x[t]) for x in (xb, yb))
        apart = sxb.astype(np.int16) * syb > 0
        t, sxb, syb = t[~apart], sxb[~apart], syb[~apart]
        h1 = segment_meets_triangle(Pj[t, 0], Pj[t, 1], Pj[t, 2], xa[t], ya[t], sxa[t], sya[t])
        h2 = segment_meets_triangle(Pi[t, 0], Pi[t, 1], Pi[t, 2], xb[t], yb[t], sxb, syb)
        hit[s[t]] = h1 | h2

    # a shared edge: coplanar and on the same side of it
    s = np.flatnonzero(shared == 2)
    if len(s):
        e = corners_equal(s)
        ca = (~e.any(axis=2)).argmax(axis=1)  # i's corner not in j
        cb = (~e.any(axis=1)).argmax(axis=1)
        r = np.arange(len(s))
        Pi, Pj = P[i[s]], P[j[s]]
        c, d = Pi[r, ca], Pj[r, cb]
        x, y = Pi[r, (ca + 1) % 3], Pi[r, (ca + 2) % 3]
        flat = orient3d(x, y, c, d) == 0
        if flat.any():
            k = np.flatnonzero(flat)
            keep, ok = projection_axes(x[k], y[k], c[k])
            x2, y2, c2, d2 = (take2(a[k], keep) for a in (x, y, c, d))
            same = orient2d(x2, y2, c2).astype(np.int16) * orient2d(x2, y2, d2) > 0
            hit[s[k]] = same & ok

    # no shared vertex: rejected when one face lies strictly on one side of the other's plane, else an edge of
    # one meets the other (closed triangles that are not coplanar meet only so; coplanar ones too)
    s = np.flatnonzero(shared == 0)
    if len(s):
        Pi, Pj = P[i[s]], P[j[s]]
        sj = np.stack([orient3d(Pi[:, 0], Pi[:, 1], Pi[:, 2], Pj[:, k]) for k in range(3)], axis=1)
        apart = rows_all(sj > 0) | rows_all(sj < 0)
        t = np.flatnonzero(~apart)
        si = np.stack([orient3d(Pj[t, 0], Pj[t, 1], Pj[t, 2], Pi[t, k]) for k in range(3)], axis=1)
        apart = rows_all(si > 0) | rows_all(si < 0)
        t, si, sj = t[~apart], si[~apart], sj[t[~apart]]
        Pi, Pj = Pi[t], Pj[t]
        h = np.zeros(len(t), bool)
        for k in range(3):
            k1 = (k + 1) % 3
            h |= segment_meets_triangle(Pi[:, 0], Pi[:, 1], Pi[:, 2], Pj[:, k], Pj[:, k1], sj[:, k], sj[:, k1])
            h |= segment_meets_triangle(Pj[:, 0], Pj[:, 1], Pj[:, 2], Pi[:, k], Pi[:, k1], si[:, k], si[:, k1])
        hit[s[t]] = h

    return hit


def _welded(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh welded (:func:`_weld`: vertices at the same position are one), and which faces are live (not
    degenerate, :func:`degenerate_faces`)."""
    vw, canon = _weld(v)
    fw = canon[f]
    return vw, fw, ~degenerate_faces(vw, fw)


def intersecting_across(vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Boolean mask of the faces that intersect a face of another group (``groups``: a label 0, 1, ... per
    face), by the module's definition: the pairs across groups that :func:`self_intersecting_faces` tests, decided
    the same way. For a mesh whose groups are each free of self-intersections (parts repaired one by one, each
    certified by its backend), this is its full mask, at the cost of testing only the faces that lie in the box
    of another group's faces (a CT dentition's 16 separately repaired teeth, 440k faces: 0.08 s, where the full
    test takes 2 s). Labels are integers; ``ValueError`` unless there is one per face."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    g = np.asarray(groups, dtype=np.int64)
    if g.shape != (len(f),):
        raise ValueError(f"groups: one label per face expected ({len(f)}), got an array of shape {g.shape}")
    out = np.zeros(len(f), bool)
    if len(f) < 2:
        return out
    if g.min() < 0 or g.max() >= len(f):  # other labels: numbered 0, 1, ... in their order
        g = np.unique(g, return_inverse=True)[1].ravel()
    k = int(g.max()) + 1
    face_order = np.arange(len(f)) if (g[1:] >= g[:-1]).all() else np.argsort(g, kind="stable")
    start = np.searchsorted(g[face_order], np.arange(k + 1))
    lo, hi = mesh_face_boxes(v, f[face_order])  # the faces by group
    present = np.flatnonzero(start[1:] > start[:-1])
    if len(present) < 2:
        return out
    glo = np.minimum.reduceat(lo, start[present], axis=0)  # each group's box (the groups with faces)
    ghi = np.maximum.reduceat(hi, start[present], axis=0)

    def within(sel: np.ndarray, blo: np.ndarray, bhi: np.ndarray) -> np.ndarray:  # positions in the box
        return sel[rows_all(lo[sel] <= bhi) & rows_all(hi[sel] >= blo)]

    # for each two groups whose boxes overlap, the faces of each within the other's box, then within the box of
    # the other's faces so found, until that settles: a face that meets one of another group stays
    near = np.zeros(len(f), bool)
    for a, b in zip(*candidate_pairs(glo, ghi)):
        x, y = present[a], present[b]
        A = within(np.arange(start[x], start[x + 1]), glo[b], ghi[b])
        B = within(np.arange(start[y], start[y + 1]), glo[a], ghi[a])
        while len(A) and len(B):  # (stopping early keeps more faces than needed: the same answer)
            n = len(A) + len(B)
            A = within(A, col_min(lo[B]), col_max(hi[B]))
            B = within(B, col_min(lo[A]), col_max(hi[A])) if len(A) else B[:0]
            if len(A) + len(B) > 0.9 * n:  # settled, or settling slowly (long parts side by side)
                break
        if len(A) and len(B):
            near[A] = near[B] = True
    idx = face_order[near]
    if len(idx) < 2:
        return out
    # those faces welded (coincident vertices are one, as in the full test) and their pairs across groups tested
    ids, own = np.unique(f[idx], return_inverse=True)  # their vertices, and the faces on them
    vw, fw, live = _welded(v[ids], own.reshape(-1, 3))
    idx, fw = idx[live], fw[live]
    Pw = vw[fw]
    i, j = candidate_pairs(*face_boxes(Pw))
    across = g[idx[i]] != g[idx[j]]
    i, j = i[across], j[across]
    if not len(i):
        return out
    # every pair that shares a vertex gets the exact test (no vertex settles a pair here: the same answer)
    hit = np.concatenate([_pair_hits(Pw, fw, i[s:s + PAIR_BLOCK], j[s:s + PAIR_BLOCK])
                          for s in range(0, len(i), PAIR_BLOCK)])
    out[idx[i[hit]]] = True
    out[idx[j[hit]]] = True
    return out


def _weld(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of the vertices ``v`` (n, 3) in lexicographic order, and each row's index among them:
    the values of ``np.unique(v, axis=0, return_inverse=True)`` (rows equal as numbers are one, so of 0.0 and
    -0.0 either may stand for both, which no predicate tells apart), by a lexsort of the columns."""
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    s = v[order]
    new = np.ones(len(s), bool)
    new[1:] = (s[1:, 0] != s[:-1, 0]) | (s[1:, 1] != s[:-1, 1]) | (s[1:, 2] != s[:-1, 2])
    inv = np.empty(len(v), np.int64)
    inv[order] = np.cumsum(new) - 1
    return s[new], inv


PAIR_BLOCK = 32768
"""Candidate pairs per call of the exact pair test in :func:`_all_pairs`."""


def _all_pairs(v: np.ndarray, f: np.ndarray, live: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """The intersecting pairs of faces (rows of face indices, the smaller first), among the live ones; with
    ``among``, only pairs with at least one face in it."""
    idx = np.flatnonzero(live)
    fl = f[idx]
    P = v[fl]  # (m, 3 corners, 3)
    lo, hi = face_boxes(P)
    i, j = candidate_pairs(lo, hi, None if among is None else among[idx])
    if not len(i):
        return np.zeros((0, 2), np.int64)
    if among is None:
        regular = regular_vertices(v, fl)
    else:
        # a pair has a face in ``among``, so the vertices it shares are that face's: only theirs are looked up,
        # and each depends on its own fan alone (the faces around it, in the same order), so the fans of these
        # vertices give the same answer for them as the whole mesh (an edit's test: a fraction of the time)
        near = np.zeros(len(v), bool)
        near[fl[among[idx]].ravel()] = True
        regular = regular_vertices(v, fl[rows_any(near[fl])]) & near
    # in blocks of pairs: the same hits (pair by pair), with temporaries that stay in the cache; less memory
    hit = np.concatenate([_pair_hits(P, fl, i[s:s + PAIR_BLOCK], j[s:s + PAIR_BLOCK], regular)
                          for s in range(0, len(i), PAIR_BLOCK)])
    return np.stack([idx[i[hit]], idx[j[hit]]], axis=1)


def stable_order(keys: np.ndarray) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` of uint64 keys (:func:`face_keys`), by the compiled kernel's radix sort
    when there is one (the same order: a stable sort's is unique)."""
    if native.kernels is None or keys.dtype != np.uint64:
        return np.argsort(keys, kind="stable")
    return np.frombuffer(native.kernels.stable_order(np.ascontiguousarray(keys)), np.int64)


def _mix(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 arrays (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def face_keys(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each face's set of corner coordinates (not of its indices or corner order); equal
    keys are confirmed by comparing the coordinates before a face counts as the same. By the compiled kernel
    when there is one (:mod:`scanreg.mesh.native`: the same keys), else :func:`face_keys_numpy`."""
    f = np.ascontiguousarray(f, dtype=np.int64)
    if native.kernels is None or not len(f):
        return face_keys_numpy(v, f)
    return np.frombuffer(native.kernels.face_keys(np.ascontiguousarray(v, dtype=np.float64), f), np.uint64)


def face_keys_numpy(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """:func:`face_keys` in NumPy: SplitMix64's finaliser (:func:`_mix`) over each vertex's coordinate bits, the
    face's three vertex hashes sorted and mixed again."""
    bits = np.ascontiguousarray(v).view(np.uint64).reshape(-1, 3)
    hv = _mix(bits[:, 0] ^ _mix(bits[:, 1] ^ _mix(bits[:, 2] ^ np.uint64(0x9E3779B97F4A7C15))))
    c = np.sort(hv[f], axis=1)
    return _mix(c[:, 0] ^ _mix(c[:, 1] ^ _mix(c[:, 2])))


def same_corners(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Whether the triangles ``P`` and ``Q`` (m, 3 corners, 3) have the same set of corners: every corner of each
    equals a corner of the other. (For faces with three distinct corners, the same as comparing the corners
    sorted, at a fraction of its cost.) By the compiled kernel when there is one (the same answers), else
    :func:`same_corners_numpy`."""
    if native.kernels is None or not len(P):
        return same_corners_numpy(P, Q)
    return np.frombuffer(native.kernels.same_corners(np.ascontiguousarray(P, dtype=np.float64),
                                                     np.ascontiguousarray(Q, dtype=np.float64)), np.bool_)


def same_faces(va: np.ndarray, fa: np.ndarray, ia: np.ndarray, vb: np.ndarray, fb: np.ndarray,
               ib: np.ndarray) -> np.ndarray:
    """:func:`same_corners` of the faces ``fa[ia]`` of the vertices ``va`` and ``fb[ib]`` of ``vb``: by the compiled
    kernel without gathering the triangles when there is one (the same answers)."""
    if native.kernels is None or not len(ia):
        return same_corners(va[fa[ia]], vb[fb[ib]])
    c = [np.ascontiguousarray(x, dtype=t) for x, t in ((va, np.float64), (fa, np.int64), (ia, np.int64),
                                                        (vb, np.float64), (fb, np.int64), (ib, np.int64))]
    return np.frombuffer(native.kernels.same_corners_at(*c), np.bool_)


def same_corners_numpy(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """:func:`same_corners` in NumPy, coordinate by coordinate."""
    pc = [[np.ascontiguousarray(P[:, k, x]) for x in range(3)] for k in range(3)]
    qc = [[np.ascontiguousarray(Q[:, k, x]) for x in range(3)] for k in range(3)]
    eq = [[(pc[k][0] == qc[m][0]) & (pc[k][1] == qc[m][1]) & (pc[k][2] == qc[m][2]) for m in range(3)]
          for k in range(3)]
    same = np.ones(len(P), bool)
    for k in range(3):
        same &= eq[k][0] | eq[k][1] | eq[k][2]  # corner k of P is one of Q's
        same &= eq[0][k] | eq[1][k] | eq[2][k]  # and corner k of Q one of P's
    return same


def _shares_half(new: Intersections, old: Intersections) -> bool:
    """Whether ``old`` has more than half of ``new``'s faces (by key), and is not so large that sorting it would
    cost more than the incremental test saves."""
    n_new, n_old = len(new.keys), len(old.keys)
    if not n_new // 2 < n_old <= MAX_RATIO * n_new:
        return False
    old_sorted = old.sorted_keys()[1]
    probe = new.keys[::max(1, n_new // PROBE)]
    if len(probe) < n_new and _member(probe, old_sorted).mean() < 0.25:
        return False  # a spread-out sample of the faces says: far from half shared
    return int(_member(new.sorted_keys()[1], old_sorted).sum()) > n_new // 2


def _incremental(v: np.ndarray, f: np.ndarray, new: Intersections, old: Intersections) -> np.ndarray:
    """The intersecting pairs of the mesh ``(v, f)`` (``new``: its keys) from ``old``'s, testing only the pairs
    with a face ``old`` did not have (:func:`_pairs_with`)."""
    order, srt = new.sorted_keys()
    old_order, old_srt = old.sorted_keys()
    # a face matches when its key occurs once in each mesh and the corner coordinates are equal
    once_new = np.empty(len(f), bool)
    once_new[order] = _once(srt)
    k_sorted, hit_sorted = _lookup(old_srt, srt)  # searched in sorted order, put back
    k, hit = np.empty_like(k_sorted), np.empty_like(hit_sorted)
    k[order], hit[order] = k_sorted, hit_sorted
    match = hit & _once(old_srt)[k] & once_new
    old_of = np.where(match, old_order[k], -1)
    m = np.flatnonzero(match)
    # (a face with a repeated corner is degenerate in both, so tested in neither: sets of corners suffice)
    same = same_faces(v, f, m, old.vertices, old.faces, old_of[m])
    old_of[m[~same]] = -1
    new_of_old = np.full(len(old.faces), -1, np.int64)
    kept = old_of >= 0
    new_of_old[old_of[kept]] = np.flatnonzero(kept)
    # the earlier outcome of pairs whose faces are both still here
    mapped = new_of_old[old.pairs] if len(old.pairs) else np.zeros((0, 2), np.int64)
    mapped = mapped[rows_all(mapped >= 0)]
    mapped = np.sort(mapped, axis=1)
    if kept.all():
        return mapped
    return np.concatenate([mapped, _pairs_with(v, f, ~kept)])


def _pairs_with(v: np.ndarray, f: np.ndarray, fresh: np.ndarray) -> np.ndarray:
    """The intersecting pairs of the mesh ``(v, f)`` with at least one face in ``fresh`` (a mask), found among the
    faces whose boxes can reach a fresh face (:func:`_near_boxes`), welded and tested for degeneracy among
    themselves only: a pair's outcome depends on its two faces and on the fans of the vertices they share, and
    a face of such a fan shares a point with a fresh face, so its box reaches it. The same pairs as the test of
    the whole mesh (an edit's test: the cost of its neighbourhood)."""
    sub = _near_boxes(*mesh_face_boxes(v, f), fresh)
    ids, own = np.unique(f[sub], return_inverse=True)
    vw, fw, live = _welded(v[ids], own.reshape(-1, 3))
    pairs = _all_pairs(vw, fw, live, among=fresh[sub] & live)
    return sub[pairs] if len(pairs) else pairs
