"""Exact self-intersection test of a triangle mesh (the geometry core; NumPy, no compiled code of its own).

A face is self-intersecting when it has a point in common with another face beyond the vertices they share
(vertices at the same position count as one: two faces that touch only at a duplicated vertex do not intersect):

* no shared vertex: the two closed triangles touch or cross anywhere;
* one shared vertex ``v``: they meet at a point other than ``v`` (one folds into the other);
* a shared edge: they are coplanar and lie on the same side of that edge (folded flat onto each other);
* the same three vertices: a duplicated face.

Degenerate faces (repeated vertex indices or collinear corners, exactly) take no part; the audit counts them
separately. Every decision rests on the signs of 3x3 and 2x2 orientation determinants, computed in floating
point with Shewchuk's static error bounds (orient3d: ``(7 + 56 eps) eps`` times the permanent, orient2d:
``(3 + 16 eps) eps``) and exactly, with Python integers, where the bound cannot certify the sign. The result is
therefore exact for the floating-point coordinates as given and depends on nothing but them: not on the order of
the faces, the process's history or the scale of the coordinates (a ``2^k`` scaling gives the same answer).

Candidate pairs are the faces whose bounding boxes overlap (k-d trees over the box centres, by size level).
Pairs that share a vertex whose fan turns once around it (:func:`regular_vertices`, decided with the same
predicates) cannot intersect and are not tested: that settles most neighbours. A mesh that shares most faces
with one tested shortly before in the process reuses that outcome for the pairs both have
(:func:`self_intersecting_faces`). Tests: tests/test_intersect.py (a rational brute-force reference).
"""

from __future__ import annotations

import functools

import numpy as np

from scanreg.geometry import col_max, col_min, rows_all, rows_any
from scanreg.isolate import fork_with_pipes, forking, keep_from_children, kill, read_value, release, send_value
from scanreg.isolate import send_message as _send

_EPS = np.ldexp(1.0, -53)  # half an ulp of 1.0: Shewchuk's epsilon
_O3_BOUND = (7.0 + 56.0 * _EPS) * _EPS
_O2_BOUND = (3.0 + 16.0 * _EPS) * _EPS


# ---------------------------------------------------------------------------------------------- predicates

def _as_ints(rows: np.ndarray) -> np.ndarray:
    """Each row's floats as Python integers of one common power-of-two scale per row (exact: the signs of
    the homogeneous determinants below do not change under a positive scale), as an object array."""
    mant, expo = np.frexp(rows)
    ints = (mant * 2.0 ** 53).astype(np.int64)  # exact: |mant| < 1
    expo = np.where(mant == 0, expo.max(axis=1, keepdims=True), expo)
    shift = (expo - expo.min(axis=1, keepdims=True)).astype(object)
    return ints.astype(object) << shift


def _signs(det: np.ndarray) -> np.ndarray:
    """The signs (int8) of an object array of Python integers."""
    return np.array([(x > 0) - (x < 0) for x in det], np.int8)


def _orient3d_exact(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    r = _as_ints(np.hstack([a, b, c, d])).T
    adx, ady, adz = r[0] - r[9], r[1] - r[10], r[2] - r[11]
    bdx, bdy, bdz = r[3] - r[9], r[4] - r[10], r[5] - r[11]
    cdx, cdy, cdz = r[6] - r[9], r[7] - r[10], r[8] - r[11]
    det = adz * (bdx * cdy - cdx * bdy) + bdz * (cdx * ady - adx * cdy) + cdz * (adx * bdy - bdx * ady)
    return _signs(det)


def orient3d(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact sign (+1, 0, -1, int8) of ``det[a - d; b - d; c - d]`` for rows of (n, 3) float64 arrays: positive
    when ``d`` lies below the plane through ``a, b, c`` seen counter-clockwise from above (Shewchuk's
    convention), zero when the four points are coplanar."""
    adx, ady, adz = (a - d).T
    bdx, bdy, bdz = (b - d).T
    cdx, cdy, cdz = (c - d).T
    bc, cb = bdx * cdy, cdx * bdy
    ca, ac = cdx * ady, adx * cdy
    ab, ba = adx * bdy, bdx * ady
    det = adz * (bc - cb) + bdz * (ca - ac) + cdz * (ab - ba)
    perm = (np.abs(bc) + np.abs(cb)) * np.abs(adz) + (np.abs(ca) + np.abs(ac)) * np.abs(bdz) \
        + (np.abs(ab) + np.abs(ba)) * np.abs(cdz)
    sign = np.sign(det).astype(np.int8)
    unsure = np.flatnonzero(np.abs(det) <= _O3_BOUND * perm)
    if len(unsure):
        a, b, c, d = a[unsure], b[unsure], c[unsure], d[unsure]
        # every product zero (axis-aligned coplanar points): the determinant is exactly zero, unless a product
        # underflowed, which the exact path settles
        zero = (perm[unsure] == 0) & _no_underflow((a, b, c), d, 1e-90)
        sign[unsure[zero]] = 0
        rest = ~zero
        if rest.any():
            sign[unsure[rest]] = _orient3d_exact(a[rest], b[rest], c[rest], d[rest])
    return sign


def _no_underflow(pts: tuple[np.ndarray, ...], base: np.ndarray, floor: float) -> np.ndarray:
    """Rows whose nonzero coordinate differences from ``base`` are all above ``floor``: no product of the
    determinant's terms (three differences: 1e-90, two: 1e-150) underflows, so a zero permanent means a zero
    determinant."""
    ok = np.ones(len(base), bool)
    for p in pts:
        diff = np.abs(p - base)
        ok &= rows_all((diff == 0) | (diff > floor))
    return ok


def _orient2d_exact(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    r = _as_ints(np.hstack([a, b, c])).T
    det = (r[0] - r[4]) * (r[3] - r[5]) - (r[1] - r[5]) * (r[2] - r[4])
    return _signs(det)


def orient2d(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact sign (int8) of ``det[a - c; b - c]`` for rows of (n, 2) float64 arrays: positive when ``a, b, c``
    run counter-clockwise."""
    left = (a[:, 0] - c[:, 0]) * (b[:, 1] - c[:, 1])
    right = (a[:, 1] - c[:, 1]) * (b[:, 0] - c[:, 0])
    det = left - right
    perm = np.abs(left) + np.abs(right)
    sign = np.sign(det).astype(np.int8)
    unsure = np.flatnonzero(np.abs(det) <= _O2_BOUND * perm)
    if len(unsure):
        a, b, c = a[unsure], b[unsure], c[unsure]
        zero = (perm[unsure] == 0) & _no_underflow((a, b), c, 1e-150)
        sign[unsure[zero]] = 0
        rest = ~zero
        if rest.any():
            sign[unsure[rest]] = _orient2d_exact(a[rest], b[rest], c[rest])
    return sign


# ------------------------------------------------------------------------------------- segment vs triangle

def _projection_axes(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle, the two coordinates kept by a projection along one axis that keeps it non-degenerate (the
    axis of the normal's largest component among those that are exactly nonzero), and whether it has one."""
    n = np.cross(q - p, r - p)
    ok = np.zeros((len(p), 3), bool)
    for k in range(3):
        keep = [j for j in range(3) if j != k]
        ok[:, k] = orient2d(p[:, keep], q[:, keep], r[:, keep]) != 0
    score = np.where(ok, np.abs(n), -1.0)
    drop = np.argmax(score, axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[drop]
    return keep, rows_any(ok)


def _take2(x: np.ndarray, keep: np.ndarray) -> np.ndarray:
    return np.take_along_axis(x, keep, axis=1)


def _on_segment(x, y, c) -> np.ndarray:
    """``c`` (collinear with ``x, y``) within the closed segment's bounding box."""
    lo, hi = np.minimum(x, y), np.maximum(x, y)
    return rows_all((lo <= c) & (c <= hi))


def _segments_meet_2d(x, y, u, w) -> np.ndarray:
    """Closed 2-D segments ``xy`` and ``uw`` have a common point."""
    d1, d2 = orient2d(x, y, u), orient2d(x, y, w)
    d3, d4 = orient2d(u, w, x), orient2d(u, w, y)
    hit = (d1.astype(np.int16) * d2 < 0) & (d3.astype(np.int16) * d4 < 0)
    hit |= (d1 == 0) & _on_segment(x, y, u)
    hit |= (d2 == 0) & _on_segment(x, y, w)
    hit |= (d3 == 0) & _on_segment(u, w, x)
    hit |= (d4 == 0) & _on_segment(u, w, y)
    return hit


def _inside_2d(p, q, r, x) -> np.ndarray:
    """``x`` in the closed 2-D triangle ``p, q, r`` (non-degenerate)."""
    s = np.stack([orient2d(p, q, x), orient2d(q, r, x), orient2d(r, p, x)], axis=1)
    return rows_all(s >= 0) | rows_all(s <= 0)


def _coplanar_segment_triangle(p, q, r, x, y) -> np.ndarray:
    """Closed segment ``xy`` lying in the plane of the closed triangle ``p, q, r`` meets it."""
    keep, ok = _projection_axes(p, q, r)
    p2, q2, r2, x2, y2 = (_take2(a, keep) for a in (p, q, r, x, y))
    hit = _inside_2d(p2, q2, r2, x2) | _inside_2d(p2, q2, r2, y2)
    for u, w in ((p2, q2), (q2, r2), (r2, p2)):
        hit |= _segments_meet_2d(x2, y2, u, w)
    return hit & ok


def segment_meets_triangle(p, q, r, x, y, sx: np.ndarray | None = None,
                           sy: np.ndarray | None = None) -> np.ndarray:
    """Rows where the closed segment ``xy`` and the closed triangle ``p, q, r`` (non-degenerate) have a common
    point. ``sx``, ``sy``: ``orient3d(p, q, r, x)`` and ``(…, y)`` when already known."""
    sx = orient3d(p, q, r, x) if sx is None else sx
    sy = orient3d(p, q, r, y) if sy is None else sy
    hit = np.zeros(len(p), bool)
    cross = (sx.astype(np.int16) * sy <= 0) & ((sx != 0) | (sy != 0))  # the line meets the plane once, in xy
    if cross.any():
        i = np.flatnonzero(cross)
        o = np.stack([orient3d(x[i], y[i], p[i], q[i]), orient3d(x[i], y[i], q[i], r[i]),
                      orient3d(x[i], y[i], r[i], p[i])], axis=1)
        hit[i] = rows_all(o >= 0) | rows_all(o <= 0)
    flat = (sx == 0) & (sy == 0)
    if flat.any():
        i = np.flatnonzero(flat)
        hit[i] = _coplanar_segment_triangle(p[i], q[i], r[i], x[i], y[i])
    return hit


# ------------------------------------------------------------------------------------------------ the mesh

def degenerate_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces with a repeated vertex index or three collinear corners (exactly)."""
    f = faces
    bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    _, projects = _projection_axes(*(vertices[f[:, k]] for k in range(3)))
    return bad | ~projects


BOX_BLOCK = 65536
"""Pairs per block of :func:`candidate_pairs`' exact box test (the search's pairs, tested block by block: the
same pairs in the same order; 8 % faster on the bunny than all at once)."""


def candidate_pairs(lo: np.ndarray, hi: np.ndarray,
                    among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``, ``i < j``, of the closed boxes ``[lo, hi]`` (rows) that overlap, each once (with
    the mask ``among``: only the pairs with at least one box in it). Found with k-d trees over the box centres in
    the maximum norm, the boxes split into levels of twice the size (half the longest side) each, so that a few
    long boxes do not widen every search."""
    from scipy.spatial import cKDTree

    m = len(lo)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if m < 2 or (among is not None and not among.any()):
        return empty
    ctr = 0.5 * (lo + hi)
    d = hi - lo
    half = 0.5 * np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2])  # (0.5 d).max(axis=1), the same values
    # a margin for the rounding of the centres (the search only pre-filters; the boxes decide)
    margin = 4 * _EPS * float(np.abs(ctr).max() + half.max())
    # level 0 up to 1.5 times the median half-size: fewer searches between levels (measured on the bunny, raw
    # Stanford scans and a CT tooth: 8-11 % faster than levels from the median itself; from 2 or 3 times it,
    # slower again). Any choice finds the same pairs: the boxes decide.
    base = max(1.5 * float(np.median(half)), margin, 1e-300)
    level = np.ceil(np.log2(np.maximum(half / base, 1.0))).astype(np.int64)
    groups = [np.flatnonzero(level == k) for k in np.unique(level)]
    hmax = [float(half[g].max()) for g in groups]
    trees: dict = {}

    def tree(g: np.ndarray, key):
        if key not in trees:
            trees[key] = cKDTree(ctr[g]) if len(g) else None
        return trees[key]

    def between(ga, ka, gb, kb, r):
        ta, tb = tree(ga, ka), tree(gb, kb)
        if ta is None or tb is None:
            return None
        p = ta.sparse_distance_matrix(tb, r, p=np.inf, output_type="ndarray")
        return ga[p["i"]], gb[p["j"]]

    lo_of = [np.ascontiguousarray(lo[:, k]) for k in range(3)]  # one axis each: faster to gather from
    hi_of = [np.ascontiguousarray(hi[:, k]) for k in range(3)]
    ii, jj = [], []
    for a, ga in enumerate(groups):
        for b in range(a + 1):
            gb = groups[b]
            r = hmax[a] + hmax[b] + margin
            found = []
            if among is None:
                if a == b:
                    p = tree(ga, a).query_pairs(r, p=np.inf, output_type="ndarray")
                    found.append((ga[p[:, 0]], ga[p[:, 1]]))
                else:
                    found.append(between(ga, a, gb, b, r))
            else:
                sa, sb = ga[among[ga]], gb[among[gb]]
                if a == b:
                    got = between(sa, ("s", a), ga, a, r)
                    if got is not None:  # each pair once: not a box with itself, both in ``among`` once
                        A, B = got
                        keep = (A != B) & (~among[B] | (A < B))
                        found.append((A[keep], B[keep]))
                else:
                    found.append(between(sa, ("s", a), gb, b, r))
                    found.append(between(ga[~among[ga]], ("n", a), sb, ("s", b), r))
            for got in found:
                if got is None or not len(got[0]):
                    continue
                for s in range(0, len(got[0]), BOX_BLOCK):  # in blocks: temporaries that stay in the cache
                    A, B = got[0][s:s + BOX_BLOCK], got[1][s:s + BOX_BLOCK]
                    for k in range(3):  # the exact box test, one axis at a time on the pairs left
                        keep = (lo_of[k][A] <= hi_of[k][B]) & (lo_of[k][B] <= hi_of[k][A])
                        A, B = A[keep], B[keep]
                    ii.append(np.minimum(A, B))
                    jj.append(np.maximum(A, B))
    if not ii:
        return empty
    return np.concatenate(ii).astype(np.int64), np.concatenate(jj).astype(np.int64)


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
        which keeps the binary search in cache (1.5x faster than searching the rows as they come)."""
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
            keep, ok = _projection_axes(x[k], y[k], c[k])
            x2, y2, c2, d2 = (_take2(a[k], keep) for a in (x, y, c, d))
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


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boolean mask of the self-intersecting faces (see the module docstring for the definition).

    A mesh that shares most of its faces (the same corner coordinates) with one tested shortly before in this
    process (a repair's input and its output, a loop that cuts out and refills a few faces) is tested
    incrementally: the pairs of faces both meshes have keep their outcome, only pairs with a new face are
    tested. The outcome of a pair depends on its two faces' coordinates alone, so the result is the same as a
    full test, bit for bit (tests/test_intersect.py checks it). Meshes under ``_Memo.MIN_FACES`` faces (an
    edit's neighbourhood) are always tested in full."""
    job = _Job(vertices, faces)
    if job.entry is None:
        return job.mask(None)
    pairs = None
    try:
        job.welded()  # while the earlier mesh's test (in another process) may still run
        pairs = job.pairs(job.prev.wait() if job.prev is not None else None)
    finally:
        job.finish(pairs)
    return job.mask(pairs)


def _boxes(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounding boxes (lo, hi) of faces given by their corners ``P`` (m, 3, 3): ``P.min(axis=1)`` and
    ``P.max(axis=1)``, the same values, faster."""
    return np.minimum(np.minimum(P[:, 0], P[:, 1]), P[:, 2]), np.maximum(np.maximum(P[:, 0], P[:, 1]), P[:, 2])


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
    lo, hi = _boxes(v[f[face_order]])  # the faces by group
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
    i, j = candidate_pairs(*_boxes(Pw))
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
    -0.0 either may stand for both, which no predicate tells apart), 2-4x faster (a lexsort of the columns)."""
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    s = v[order]
    new = np.ones(len(s), bool)
    new[1:] = (s[1:, 0] != s[:-1, 0]) | (s[1:, 1] != s[:-1, 1]) | (s[1:, 2] != s[:-1, 2])
    inv = np.empty(len(v), np.int64)
    inv[order] = np.cumsum(new) - 1
    return s[new], inv


class _Job:
    """One test's input and its place in the memo (``entry``; ``prev``: an earlier mesh sharing most faces). The
    faces' keys hash their corner coordinates, so they are computed on the input as given; the test welds it
    first (vertices at the same position are one vertex there: a split pinch, a seam of duplicated vertices)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.v = np.ascontiguousarray(vertices, dtype=np.float64)
        self.f = np.ascontiguousarray(faces, dtype=np.int64)
        self.n = len(self.f)
        self.entry = self.prev = self._welded = None
        if self.n < 2:
            return
        self.keys = _face_keys(self.v, self.f)
        self.entry, self.prev = _MEMO.begin(self.keys, use=self.n >= _MEMO.MIN_FACES)

    def welded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The welded vertices and faces (:func:`_weld`) and which faces are live (not degenerate), once: made
        before waiting for an earlier mesh's outcome (:func:`self_intersecting_faces`), they need none of it."""
        if self._welded is None:
            self._welded = _welded(self.v, self.f)
        return self._welded

    def pairs(self, old) -> np.ndarray:
        """The intersecting pairs, incrementally from ``old`` (``prev``'s outcome) when given."""
        v, f, live = self.welded()
        pairs = None
        if old is not None:
            pairs = _incremental(v, f, live, self.keys, self.entry, self.prev, old)
        return pairs if pairs is not None else _all_pairs(v, f, live)

    def finish(self, pairs: np.ndarray | None) -> None:
        """The outcome into the memo, with the input as given (a later test compares corner coordinates)."""
        _MEMO.finish(self.entry, None if pairs is None else (self.v, self.f, pairs))

    def mask(self, pairs: np.ndarray | None) -> np.ndarray:
        out = np.zeros(self.n, bool)
        if pairs is not None:
            out[pairs.ravel()] = True
        return out


@functools.cache
def _malloc_controls():
    """glibc's ``mallopt`` (``int mallopt(int, int)``) and ``malloc_trim`` (``int malloc_trim(size_t)``), or None
    where there are none; looked up once, in the parent (no dlopen in a forked child)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        fn, trim = libc.mallopt, libc.malloc_trim
        fn.argtypes, fn.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
        return fn, trim
    except Exception:  # noqa: BLE001: not glibc
        return None


def _keep_freed_memory(malloc) -> None:
    """In a child process's busy part: glibc's malloc keeps freed memory for reuse instead of returning it to
    the system (arrays up to 1 GB from its heap, no trimming), so that NumPy's temporaries do not fault in fresh
    pages again and again (measured: the bunny's self-intersection test 42 000 -> 26 000 page faults, 6 % less
    CPU time). :func:`_give_back_freed_memory` ends it. Nothing happens where glibc is absent."""
    try:
        if malloc is not None:
            malloc[0](-3, 1 << 30)  # M_MMAP_THRESHOLD
            malloc[0](-1, (1 << 31) - 1)  # M_TRIM_THRESHOLD
    except Exception:  # noqa: BLE001: only speed is at stake
        pass


def _give_back_freed_memory(malloc) -> None:
    """Before a child waits (for a request that comes after the backend): the heap's free memory returned to
    the system and trimmed again from then on (a 200k-face input's child held 444 MB while it waited, 51 MB
    after this)."""
    try:
        if malloc is not None:
            malloc[0](-1, 128 * 1024)  # M_TRIM_THRESHOLD: glibc's default
            malloc[1](0)
    except Exception:  # noqa: BLE001: only memory is at stake
        pass


class Beside:
    """:func:`self_intersecting_faces` of a mesh, computed beside the caller; :meth:`result` waits for the mask.
    ``extra``, a function of no arguments (more measurements of the same mesh), runs after the test in the same
    place (before it with ``test_last``); :meth:`extra_result` waits for its value (picklable). ``first``, another
    such function, runs first; :meth:`first_result` waits for its value only. ``then``, a function of no arguments
    run after ``extra`` in the same place (it prepares, e.g. a search tree of the mesh, while the caller is busy),
    returns a function of one request (a tuple of NumPy arrays the caller has only later): :meth:`ask` hands it the
    request, :meth:`then_result` waits for its answer (picklable), and :meth:`close` tells the child that no request
    will come (it exits; a child never asked also exits when this process does). ``test_last``, a function of
    ``first``'s value, says whether the test runs after ``extra`` and ``then``'s preparation rather than before them
    (a caller that needs the test's outcome only at its end: the test's memory traffic then meets the later, less
    sensitive part of a backend running beside it); it is asked in the child only (a thread, without a child, keeps
    the usual order), and if it fails the usual order is kept.

    On Linux the work runs in a forked child process (the same code on the same arrays, inherited; the results come
    back through a pipe), so that it uses another core even while the caller runs a library that keeps the GIL
    (pymeshlab's filters; pymeshfix with ``SCANREG_NO_FORK``, which otherwise runs in a child of its own,
    :mod:`scanreg.isolate`), which would leave a thread beside it waiting; elsewhere, or when the child fails, in a
    thread. This process's ends of its pipes are closed in children forked later
    (:func:`~scanreg.isolate.keep_from_children`). The memo of recent meshes gets the outcome as soon as it is
    known, so that a test in this process that shares most faces waits for it and goes on incrementally. The results
    are the same either way: functions of the input alone."""

    TIMEOUT_S = 120.0
    """A child that has not answered after this long plus :attr:`TIMEOUT_S_PER_FACE` per face (about 30 times
    the test's own time) is stopped and the work done in this process instead."""
    TIMEOUT_S_PER_FACE = 2e-4

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, extra=None, first=None, then=None,
                 test_last=None):
        import threading

        self._job = _Job(vertices, faces)
        self._extra_fn, self._first_fn, self._then_fn = extra, first, then
        self._test_last = test_last
        self._mask = self._error = None
        self._extra = self._first = self._first_error = None  # (value,) once known; the first one's failure
        self._answer = self._then_error = None  # then's answer (value,) once known; its failure
        self._first_known, self._known = threading.Event(), threading.Event()  # first; mask and extra
        self._request = None  # (arrays,) once asked; None: not yet, or closed
        self._asked = threading.Event()  # set by ask() and by close()
        self._ask_fd = None  # the write end of the child's request pipe, until asked or closed
        self._old = None
        if self._job.entry is not None:
            # an earlier mesh's outcome the child can use: only one already known (a child cannot wait for this
            # process's threads)
            prev = self._job.prev
            self._old = prev.result if prev is not None and prev.done.is_set() else None
            if prev is not None and self._old is None:
                self._job.prev = None
        elif extra is None and first is None and then is None:
            self._mask, self._thread = self._job.mask(None), None
            self._known.set()
            return
        self._child = self._fork()
        self._thread = threading.Thread(target=self._collect, daemon=True, name="scanreg-beside")
        self._thread.start()

    def _pairs(self) -> np.ndarray | None:
        return self._job.pairs(self._old) if self._job.entry is not None else None

    def _fork(self):
        """The child's pid and the pipe's read end, or None where forking is not used or failed."""
        import os
        import pickle

        if not forking():
            return None
        malloc = _malloc_controls()
        forked = fork_with_pipes(1 + int(self._then_fn is not None))  # results; requests (then)
        if forked is None:
            return None
        pid, fds = forked
        r, w = fds[:2]
        if pid == 0:  # the child: the first value, the pairs, the extra value, then's answer; it leaves without
            code = 1  # the parent's exit code
            try:
                os.close(r)
                if len(fds) > 2:
                    os.close(fds[3])
                _keep_freed_memory(malloc)
                first = None
                if self._first_fn is not None:
                    first = self._first_fn()
                    _send(w, pickle.dumps(first, protocol=pickle.HIGHEST_PROTOCOL))
                try:
                    last = self._test_last is not None and bool(self._test_last(first))
                except Exception:  # noqa: BLE001: the usual order, not the whole work moved to the caller
                    last = False

                def send_pairs():
                    pairs = self._pairs()
                    _send(w, b"" if pairs is None else np.ascontiguousarray(pairs, np.int64).tobytes())

                if not last:
                    send_pairs()
                extra = None if self._extra_fn is None else \
                    pickle.dumps(self._extra_fn(), protocol=pickle.HIGHEST_PROTOCOL)
                # then's preparation before the extra value is sent: a message larger than the pipe's buffer
                # waits until this process reads it, which a backend that keeps the GIL delays to its end
                answer = None if self._then_fn is None else self._then_fn()
                if last:  # the messages keep their order: the pairs before the extra value
                    send_pairs()
                if extra is not None:
                    _send(w, extra)
                if self._then_fn is not None:
                    del extra
                    _give_back_freed_memory(malloc)  # it may wait long
                    request, asked = read_value(fds[2])
                    if asked:  # else closed without a request
                        _send(w, pickle.dumps(answer(request), protocol=pickle.HIGHEST_PROTOCOL))
                code = 0
            finally:
                os._exit(code)
        os.close(w)
        if len(fds) > 2:
            os.close(fds[2])
            self._ask_fd = fds[3]
        keep_from_children(*fds[:1], *fds[3:])  # closed in children forked later (a backend's)
        return pid, r

    def _receive(self, pid: int, r: int) -> None:
        """The child's results, the memo told at once; any left unknown (the child failed or took too long, and
        was stopped) are computed here. Then's answer is waited for without a deadline until the request is
        sent (the caller's own work comes between), then within the same time limit again."""
        import os
        import pickle
        import select
        import time

        limit = self.TIMEOUT_S + self.TIMEOUT_S_PER_FACE * self._job.n
        deadline = time.monotonic() + limit
        k = int(self._first_fn is not None)  # the pairs' message: after the first value's, if any
        pre = k + 1 + int(self._extra_fn is not None)  # the messages before then's answer
        buf, want, got = b"", pre + int(self._then_fn is not None), []
        rearmed = False  # the deadline set again once then's request is sent
        try:
            while len(got) < want:
                waiting = len(got) == pre and not rearmed and not self._asked.is_set()
                if waiting:  # the caller's own work comes before its request: no deadline (the child may end)
                    if not select.select([r], [], [], 0.5)[0]:
                        continue
                else:
                    if len(got) == pre and not rearmed:
                        deadline, rearmed = time.monotonic() + limit, True
                    left = deadline - time.monotonic()
                    if left <= 0 or not select.select([r], [], [], left)[0]:
                        kill(pid)
                        break
                chunk = os.read(r, 1 << 20)
                if not chunk:
                    break
                buf += chunk
                while len(buf) >= 8 and len(buf) >= 8 + int.from_bytes(buf[:8], "little"):
                    n = int.from_bytes(buf[:8], "little")
                    got.append(buf[8:8 + n])
                    buf = buf[8 + n:]
                    if k and len(got) == 1:  # the caller may go on with it at once
                        self._first = (pickle.loads(got[0]),)
                        self._first_known.set()
                    if len(got) == k + 1 and self._job.entry is not None:
                        pairs = np.frombuffer(got[k], np.int64).reshape(-1, 2).copy()
                        self._mask = self._job.mask(pairs)
                        self._job.finish(pairs)
                    if len(got) == pre:
                        if self._extra_fn is not None:
                            self._extra = (pickle.loads(got[-1]),)
                        if self._mask is not None or self._job.entry is None:
                            if self._mask is None:
                                self._mask = self._job.mask(None)
                            self._known.set()  # result() need not wait for then's answer
                    if len(got) == want and self._then_fn is not None:
                        self._answer = (pickle.loads(got[-1]),)
        except BaseException:  # this side failed: the child may be waiting for a request; stopped, not waited for
            kill(pid)
            raise
        finally:
            release(r)
            os.waitpid(pid, 0)

    def _collect(self) -> None:
        done = False
        try:
            if self._child is not None:
                try:
                    self._receive(*self._child)
                except Exception:  # noqa: BLE001: the pipe or the child's data failed: what is missing, here
                    pass
            if self._first_fn is not None and self._first is None:  # no child, or it failed: here
                try:
                    self._first = (self._first_fn(),)
                except Exception as e:  # noqa: BLE001: first_result() raises it; the test goes on
                    self._first_error = e
                finally:
                    self._first_known.set()
            if self._mask is None:  # no child, or it failed: here
                pairs = self._pairs()
                self._mask = self._job.mask(pairs)
                if self._job.entry is not None:
                    self._job.finish(pairs)
            done = True
            if self._extra_fn is not None and self._extra is None:
                self._extra = (self._extra_fn(),)
        except BaseException as e:  # handed to the caller by result()
            self._error = e
        finally:
            self._first_known.set()
            self._known.set()
            if not done and self._job.entry is not None and not self._job.entry.done.is_set():
                self._job.finish(None)
        if self._then_fn is not None and self._answer is None:  # no child, or it failed: here
            try:
                if self._child is not None:  # the child failed: prepared only for a request that comes
                    self._asked.wait()
                if self._asked.is_set() and self._request is None:  # closed without a request
                    return
                answer = self._then_fn()  # without a child: prepared while the caller works, as there
                self._asked.wait()
                if self._request is not None:
                    self._answer = (answer(self._request),)
            except BaseException as e:  # noqa: BLE001: then_result() raises it
                self._then_error = e

    def ask(self, *arrays: np.ndarray) -> None:
        """Hand ``then``'s function its request (NumPy arrays; sent to the child by a thread of this process, so
        that the caller goes on at once). Once only."""
        import threading

        if self._then_fn is None or self._asked.is_set():
            raise ValueError("Beside.ask: no then function was given, or asked or closed already")
        self._request = tuple(np.ascontiguousarray(a) for a in arrays)
        fd, self._ask_fd = self._ask_fd, None
        self._asked.set()
        if fd is not None:
            threading.Thread(target=_send_request, args=(fd, self._request), daemon=True,
                             name="scanreg-beside-ask").start()

    def close(self) -> None:
        """No request will come (a child waiting for one exits). Nothing happens once asked."""
        fd, self._ask_fd = self._ask_fd, None
        self._asked.set()
        if fd is not None:
            release(fd)

    def then_result(self):
        """``then``'s answer to the request :meth:`ask` handed over (waits for it)."""
        if self._then_fn is None or self._request is None:
            raise ValueError("Beside.then_result: no then function was given, or it was not asked")
        if self._thread is not None:
            self._thread.join()
        if self._answer is None:
            if self._then_error is not None:
                raise self._then_error
            self.result()
        return self._answer[0]

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001: at interpreter exit
            pass

    def result(self) -> np.ndarray:
        if self._then_fn is None and self._thread is not None:
            self._thread.join()  # the child reaped too (its CPU time counted where it ran)
        else:
            self._known.wait()  # then's answer comes later
        if self._error is not None:
            raise self._error
        return self._mask

    def extra_result(self):
        self.result()
        return self._extra[0]

    def first_result(self):
        if self._first_fn is None:
            raise ValueError("Beside.first_result: no first function was given")
        self._first_known.wait()
        if self._first is None:  # it failed: its own error, or the one result() hands over
            if self._first_error is not None:
                raise self._first_error
            self.result()
        return self._first[0]


def _send_request(fd: int, arrays: tuple) -> None:
    """The request's arrays into the child's pipe (:func:`~scanreg.isolate.send_value`) and the pipe closed (its
    reader sees the end)."""
    try:
        send_value(fd, arrays)
    except OSError:  # the child is gone: then's answer is made here
        pass
    finally:
        release(fd)


PAIR_BLOCK = 32768
"""Candidate pairs per call of the exact pair test in :func:`_all_pairs`."""


def _all_pairs(v: np.ndarray, f: np.ndarray, live: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """The intersecting pairs of faces (rows of face indices, the smaller first), among the live ones; with
    ``among``, only pairs with at least one face in it."""
    idx = np.flatnonzero(live)
    fl = f[idx]
    P = v[fl]  # (m, 3 corners, 3)
    lo, hi = _boxes(P)
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
    # traffic for the backend running beside (pymeshfix's load 10-20 ms faster beside the bunny's test)
    hit = np.concatenate([_pair_hits(P, fl, i[s:s + PAIR_BLOCK], j[s:s + PAIR_BLOCK], regular)
                          for s in range(0, len(i), PAIR_BLOCK)])
    return np.stack([idx[i[hit]], idx[j[hit]]], axis=1)


# ------------------------------------------------------------------------------------- incremental tests

def _mix(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 arrays (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _face_keys(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each face's set of corner coordinates (not of its indices or corner order); equal
    keys are confirmed by comparing the coordinates before a face counts as the same."""
    bits = np.ascontiguousarray(v).view(np.uint64).reshape(-1, 3)
    hv = _mix(bits[:, 0] ^ _mix(bits[:, 1] ^ _mix(bits[:, 2] ^ np.uint64(0x9E3779B97F4A7C15))))
    c = np.sort(hv[f], axis=1)
    return _mix(c[:, 0] ^ _mix(c[:, 1] ^ _mix(c[:, 2])))


def _corner_sets(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Each face's corner coordinates in a canonical corner order (lexicographic), (n, 9)."""
    P = v[f]
    order = np.lexsort((P[:, :, 2], P[:, :, 1], P[:, :, 0]), axis=1)
    return np.take_along_axis(P, order[:, :, None], axis=1).reshape(len(f), 9)


class _Entry:
    def __init__(self, keys: np.ndarray):
        import threading

        self.keys = keys
        self._sorted = None  # (order, sorted keys): made when first needed (often in a child process only)
        self.done = threading.Event()
        self.result = None  # (v, f, pairs) once finished

    def _sort(self) -> tuple[np.ndarray, np.ndarray]:
        if self._sorted is None:  # two threads may both sort: the same arrays
            order = np.argsort(self.keys, kind="stable")
            self._sorted = (order, self.keys[order])
        return self._sorted

    @property
    def order(self) -> np.ndarray:
        return self._sort()[0]

    @property
    def sorted(self) -> np.ndarray:
        return self._sort()[1]

    def wait(self):
        self.done.wait()
        return self.result


class _Memo:
    """The last few meshes tested in this process (their face keys, corners and intersecting pairs); a test
    registers its mesh before it starts, so that a later one may wait for it instead of starting afresh."""

    SIZE = 4
    MIN_FACES = 1000
    """Smaller meshes (the neighbourhood of an edit, say) are tested in full: they neither use the memo nor take
    a place in it."""
    MAX_RATIO = 8
    """An earlier mesh with more than this many times the faces is not looked at."""
    PROBE = 512
    """Faces (every k-th) that first tell whether an earlier mesh may share half of them. A wrong call costs
    only speed: the test then runs in full, with the same result."""

    def __init__(self):
        import threading

        self._lock = threading.Lock()
        self._entries: list[_Entry] = []

    def begin(self, keys: np.ndarray, use: bool = True) -> tuple[_Entry, _Entry | None]:
        """The new mesh's entry (in the memo when ``use``) and the earlier mesh it shares most faces with, if
        more than half of them (None when not ``use``)."""
        entry = _Entry(keys)
        if not use:
            return entry, None
        with self._lock:
            earlier = list(self._entries)
            self._entries = (self._entries + [entry])[-self.SIZE:]
        best, best_n = None, len(keys) // 2  # worth it when more than half the faces are shared
        probe = keys[::max(1, len(keys) // self.PROBE)]
        for e in earlier:
            if not best_n < len(e.keys) <= self.MAX_RATIO * len(keys):
                continue  # too few faces to share half, or so many that sorting them costs more than it saves
            if len(probe) < len(keys) and _member(probe, e.sorted).mean() < 0.25:
                continue  # a spread-out sample of the faces says: far from half shared
            n = int(_member(entry.sorted, e.sorted).sum())  # sorted needles: the search stays in cache
            if n > best_n:
                best, best_n = e, n
        return entry, best

    def finish(self, entry: _Entry, result) -> None:
        entry.result = result
        entry.done.set()

    def clear(self) -> None:
        with self._lock:
            self._entries = []


_MEMO = _Memo()


def forget_recent() -> None:
    """Empty the memo of recently tested meshes (benchmarks that time a test as a run makes it, once)."""
    _MEMO.clear()


def _incremental(v, f, live, keys, entry: _Entry, prev: _Entry, old) -> np.ndarray:
    """The intersecting pairs of ``(v, f)`` (face ``keys``, memo ``entry``) from those of the earlier mesh ``prev``
    (``old``: its ``(v, f, pairs)``), testing only the pairs with a face the earlier mesh did not have."""
    v0, f0, pairs0 = old
    # a face matches when its key occurs once in each mesh and the corner coordinates are equal
    once_new = np.empty(len(f), bool)
    once_new[entry.order] = _once(entry.sorted)
    k_sorted, hit_sorted = _lookup(prev.sorted, entry.sorted)  # searched in sorted order (6x faster), put back
    k, hit = np.empty_like(k_sorted), np.empty_like(hit_sorted)
    k[entry.order], hit[entry.order] = k_sorted, hit_sorted
    match = hit & _once(prev.sorted)[k] & once_new
    old_of = np.where(match, prev.order[k], -1)
    m = np.flatnonzero(match)
    same = rows_all(_corner_sets(v, f[m]) == _corner_sets(v0, f0[old_of[m]]))
    old_of[m[~same]] = -1
    new_of_old = np.full(len(f0), -1, np.int64)
    kept = old_of >= 0
    new_of_old[old_of[kept]] = np.flatnonzero(kept)
    # the earlier outcome of pairs whose faces are both still here
    mapped = new_of_old[pairs0] if len(pairs0) else np.zeros((0, 2), np.int64)
    mapped = mapped[rows_all(mapped >= 0)]
    mapped = np.sort(mapped, axis=1)
    fresh = live & ~kept
    if not fresh.any():
        return mapped
    return np.concatenate([mapped, _all_pairs(v, f, live, among=fresh)])
