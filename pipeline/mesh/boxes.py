"""Boxes of faces: each face's axis-aligned bounding box, the pairs of boxes that overlap (the exact
self-intersection test's broad phase, :mod:`scanreg.mesh.intersect`) and the boxes near a few seeds (its
incremental test's neighbourhood). The compiled kernels of :mod:`scanreg.mesh.native` compute the boxes and the
overlapping pairs when they were built, with the same result; the NumPy versions stay as the reference.
"""

from __future__ import annotations

import numpy as np

from scanreg.geometry import col_max, col_min, in_cells_around
from scanreg.mesh import native
from scanreg.mesh.predicates import EPS

BOX_BLOCK = 65536
"""Pairs per block of :func:`candidate_pairs`' exact box test (the search's pairs, tested block by block: the
same pairs in the same order; 8 % faster on the bunny than all at once)."""


def candidate_pairs(lo: np.ndarray, hi: np.ndarray,
                    among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``, ``i < j``, of the closed boxes ``[lo, hi]`` (rows) that overlap, each once (with
    the mask ``among``: only the pairs with at least one box in it), in an order that depends on the boxes only.
    The compiled kernel's grids (``box_pairs`` of :mod:`scanreg.mesh.native`) when it was built and the boxes are finite,
    else :func:`candidate_pairs_numpy`: the same pairs, in another order."""
    m = len(lo)
    if native.kernels is None or m < 2 or not (np.isfinite(lo).all() and np.isfinite(hi).all()) \
            or not np.isfinite(col_max(hi) - col_min(lo)).all():  # (the grids need a finite extent)
        return candidate_pairs_numpy(lo, hi, among)
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    d = hi - lo
    side = np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2])
    # the first level's cells 1.5 times the median box side: fewer levels than from the median itself, fewer
    # boxes per cell than from 3 times it (any side gives the same pairs)
    base = 1.5 * float(np.median(side))
    mask = None if among is None else np.ascontiguousarray(among, dtype=np.uint8)
    pairs = np.frombuffer(native.kernels.box_pairs(lo, hi, mask, base), dtype=np.int64).reshape(-1, 2)
    return pairs[:, 0].copy(), pairs[:, 1].copy()


def candidate_pairs_numpy(lo: np.ndarray, hi: np.ndarray,
                          among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`candidate_pairs` in NumPy and SciPy: found with k-d trees over the box centres in the maximum norm,
    the boxes split into levels of twice the size (half the longest side) each, so that a few long boxes do not
    widen every search."""
    from scipy.spatial import cKDTree

    m = len(lo)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if m < 2 or (among is not None and not among.any()):
        return empty
    ctr = 0.5 * (lo + hi)
    d = hi - lo
    half = 0.5 * np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2])  # (0.5 d).max(axis=1), the same values
    # a margin for the rounding of the centres (the search only pre-filters; the boxes decide)
    margin = 4 * EPS * float(np.abs(ctr).max() + half.max())
    # level 0 up to 1.5 times the median half-size: fewer searches between levels (on the bunny, raw Stanford
    # scans and a CT tooth, quicker than levels from the median itself or from 2 or 3 times it). Any choice finds
    # the same pairs: the boxes decide.
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


def mesh_face_boxes(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`face_boxes` of the faces ``f`` of the vertices ``v`` (``face_boxes(v[f])``), by the compiled kernel
    without gathering the corners when there is one (the same boxes)."""
    f = np.asarray(f)
    if native.kernels is None or not len(f):
        return face_boxes(v[f])
    lo, hi = native.kernels.face_boxes(np.ascontiguousarray(v, dtype=np.float64),
                                       np.ascontiguousarray(f, dtype=np.int64))
    return np.frombuffer(lo, np.float64).reshape(-1, 3), np.frombuffer(hi, np.float64).reshape(-1, 3)


def face_boxes(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounding boxes (lo, hi) of faces given by their corners ``P`` (m, 3, 3): ``P.min(axis=1)`` and
    ``P.max(axis=1)``, the same values, faster."""
    return np.minimum(np.minimum(P[:, 0], P[:, 1]), P[:, 2]), np.maximum(np.maximum(P[:, 0], P[:, 1]), P[:, 2])


def _near_boxes(lo: np.ndarray, hi: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The positions of the boxes ``[lo, hi]`` that may overlap a ``seed`` box (a mask), in ascending order: every
    one that does. Two boxes that overlap, each no wider than ``w``, have their lower corners in neighbouring
    cells of a grid of side ``w``: the boxes up to the 99th percentile of the largest sides are so found around
    the seeds as narrow; the wider boxes are always taken; the wider seeds (a long face across a filled hole)
    are compared with every box, up to :data:`WIDE_SEEDS` of them (more: a grid as wide as the widest)."""
    if not seed.any():
        return np.zeros(0, np.int64)
    side, s = largest_sides(lo, hi)
    near = side > s
    narrow, wide = seed & ~near, np.flatnonzero(seed & near)
    groups = [narrow] if len(wide) <= WIDE_SEEDS else [narrow, seed & near]
    for group in groups:
        if group.any():
            found = in_cells_around(lo, lo[group], max(s, float(side[group].max())))
            if found is None:
                return np.arange(len(lo))
            near |= found
    if len(wide) <= WIDE_SEEDS and len(wide):
        lo_k = [np.ascontiguousarray(lo[:, k]) for k in range(3)]
        hi_k = [np.ascontiguousarray(hi[:, k]) for k in range(3)]
        for w in wide:  # the box test axis by axis, on the boxes left (few after the first axis)
            at = np.flatnonzero((lo_k[0] <= hi_k[0][w]) & (hi_k[0] >= lo_k[0][w]))
            for k in (1, 2):
                at = at[(lo_k[k][at] <= hi_k[k][w]) & (hi_k[k][at] >= lo_k[k][w])]
            near[at] = True
    return np.flatnonzero(near | seed)


WIDE_SEEDS = 256
""":func:`_near_boxes` compares at most this many seeds wider than most boxes with every box one by one."""


NARROW_QUANTILE = 0.99
"""The grids that find the faces near an edit (:func:`_near_boxes`, :func:`scanreg.mesh.distances.distances_near`)
are as wide as the faces' largest box sides up to this quantile; the wider faces are always taken."""


def largest_sides(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Each box's largest side, and their :data:`NARROW_QUANTILE`."""
    d = hi - lo
    side = np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2])
    return side, float(np.quantile(side, NARROW_QUANTILE))
