"""Slivers and their removal: MeshLab's T-vertex collapse, and the check that a collapse folds nothing (no
self-intersection, non-manifold edge or vertex added, measured on the neighbourhood of the change)."""

from __future__ import annotations

import heapq
import math
import struct

import numpy as np

from scanreg.geometry import Mesh, col_max, col_min, rows_any, submesh
from scanreg.mesh.intersect import intersections_among
from scanreg.mesh.topology import (SLIVER_ANGLE_DEG, _cached, _mesh_edges, _min_angles_deg, _per_face, intersections,
                                   known, min_angles_deg, non_manifold_vertex_mask, non_manifold_vertices,
                                   remember, self_intersecting_count, self_intersecting_faces)


def collapse_slivers(mesh: Mesh, angle_deg: float = SLIVER_ANGLE_DEG, rounds: int = 3,
                     frozen: np.ndarray | None = None) -> Mesh:
    """``mesh`` without slivers (smallest angle below ``angle_deg``), as the paper removes degenerate triangles:
    MeshLab's T-vertex removal by edge collapse (:func:`tvertex_collapse`: a cap's apex onto its long edge, a
    needle's short edge to a point, at the ratio of a face's edge to its height of the limit angle), then null
    faces and unreferenced vertices; ``frozen``: a mask of ``mesh``'s vertices that do not move (the slivers
    whose apex they are stay). The mesh is returned unchanged when it has no sliver."""
    ang = min_angles_deg(mesh)
    if not (ang < angle_deg).any():
        return mesh
    threshold = 1.0 / np.tan(np.radians(angle_deg))
    # the faces that can pass the T-vertex test: its height / longest side <= tan(limit) bounds the smallest
    # angle by atan(2 tan(limit)) (2.0 degrees for 1; the margin covers rounding), and zero-area faces
    maybe = ang < min(90.0, 1.5 * np.degrees(np.arctan(2 * np.tan(np.radians(angle_deg)))))
    thin = maybe | (ang <= 0)
    v, f = mesh.vertices, mesh.faces
    vid, fid = np.arange(len(v)), np.arange(len(f))  # each vertex's and face's index in ``mesh``
    touched = np.zeros(len(v), bool)  # input vertices moved onto another or joined by one
    for _ in range(rounds):
        v, f, kv, kf, joined = tvertex_collapse(v, f, threshold, maybe, None if frozen is None else frozen[vid])
        vid, fid = vid[kv], fid[kf]
        touched[vid[joined]] = True
        changed = rows_any(touched[vid[f]])
        # null faces (MeshLab's meshing_remove_null_faces): among the changed faces and the input's thinnest
        look = np.flatnonzero(changed | thin[fid])
        P = v[f[look]]
        null = look[np.sqrt(_sq_norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))) <= 0]
        if len(null):
            keep = np.ones(len(f), bool)
            keep[null] = False
            f, fid, changed = f[keep], fid[keep], changed[keep]
        used = np.zeros(len(v), bool)
        used[f.ravel()] = True
        if not used.all():  # unreferenced vertices
            v, vid, f = v[used], vid[used], (np.cumsum(used) - 1)[f]
        out = Mesh(v, f, mesh.source)
        # the unchanged faces keep their smallest angle (the same corners, the same bits)
        a = np.empty(len(f))
        a[~changed] = min_angles_deg(mesh)[fid[~changed]]
        a[changed] = _min_angles_deg(Mesh(v, f[changed]))
        remember(out, "min_angles", a)
        if not (a < angle_deg).any():
            break
        maybe = None  # another round (rare): every face tested
    kept = np.zeros(len(mesh.faces), bool)
    kept[fid[~changed]] = True
    # the input face each kept face of ``out`` is (for collapse_folds, which reuses its centre)
    remember(out, "collapsed_from", ((mesh.vertices, mesh.faces), ~kept, changed, fid[~changed]))
    return out


def _sq_norm(x: np.ndarray) -> np.ndarray:
    """Squared norms of rows of 3, summed as vcglib's ``SquaredNorm`` (x*x + y*y + z*z, left to right)."""
    return x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1] + x[:, 2] * x[:, 2]


def _tvertex_test(P: np.ndarray, threshold: np.float32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """vcglib's T-vertex test of faces ``P`` (n, 3 corners, 3): whether the corner opposite the longest side
    (side i runs from corner i to corner i+1; the first of equal longest in float, as vcglib stores the
    lengths) lies within that side's length / ``threshold`` of it (``PSDist * threshold <= side``), the side i,
    and the corner of that side nearer to the corner's foot (j: i, or i+1 when not strictly nearer to corner i).
    The same arithmetic as vcglib's, in double precision, operation by operation."""
    n = len(P)
    sides = np.stack([np.sqrt(_sq_norm(P[:, (k + 1) % 3] - P[:, k])) for k in range(3)], 1).astype(np.float32)
    i = np.argmax(sides, axis=1)
    r = np.arange(n)
    a, b, p = P[r, i], P[r, (i + 1) % 3], P[r, (i + 2) % 3]
    e = b - a
    pa = p - a
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero-length side: NaN, no T-vertex (as vcglib)
        t = (pa[:, 0] * e[:, 0] + pa[:, 1] * e[:, 1] + pa[:, 2] * e[:, 2]) / _sq_norm(e)
        t = np.where(t < 0, 0.0, np.where(t > 1, 1.0, t))  # NaN stays NaN
        q = a + e * t[:, None]
        hit = np.sqrt(_sq_norm(p - q)) * np.float64(threshold) <= sides[r, i].astype(np.float64)
    j = np.where(np.sqrt(_sq_norm(q - a)) < np.sqrt(_sq_norm(q - b)), i, (i + 1) % 3)
    return hit, i, j


def _tvertex_test_one(P: list, threshold: float) -> tuple[bool, int, int]:
    """:func:`_tvertex_test` of one face ``P`` (three corners as lists of three floats), in Python's floats: the
    same IEEE double operations in the same order (the sides rounded to float32 as vcglib stores them), without
    NumPy's per-call overhead (the collapse re-tests faces one by one as their corners move). Faces with a
    side that is non-finite, beyond float32 or squares to zero go to :func:`_tvertex_test`, whose NaN rules it
    does not repeat."""
    lengths = []
    for k in range(3):
        a, b = P[k], P[(k + 1) % 3]
        d0, d1, d2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        lengths.append(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
    if not all(x < _F32_MAX for x in lengths):  # (a NaN fails too)
        return _tvertex_test_array(P, threshold)
    sides = [_F32.unpack(_F32.pack(x))[0] for x in lengths]  # rounded to float32, as NumPy's astype
    i = 0 if sides[0] >= sides[1] and sides[0] >= sides[2] else (1 if sides[1] >= sides[2] else 2)
    a, b, p = P[i], P[(i + 1) % 3], P[(i + 2) % 3]
    e0, e1, e2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ee = e0 * e0 + e1 * e1 + e2 * e2
    if ee == 0:  # a zero-length side (or one whose square underflows): as _tvertex_test's NaN rules decide
        return _tvertex_test_array(P, threshold)
    t = ((p[0] - a[0]) * e0 + (p[1] - a[1]) * e1 + (p[2] - a[2]) * e2) / ee
    t = 0.0 if t < 0 else (1.0 if t > 1 else t)
    q0, q1, q2 = a[0] + e0 * t, a[1] + e1 * t, a[2] + e2 * t
    d0, d1, d2 = p[0] - q0, p[1] - q1, p[2] - q2
    hit = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * threshold <= sides[i]
    x0, x1, x2 = q0 - a[0], q1 - a[1], q2 - a[2]
    y0, y1, y2 = q0 - b[0], q1 - b[1], q2 - b[2]
    nearer_a = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) < math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    return hit, i, i if nearer_a else (i + 1) % 3


def _tvertex_test_array(P: list, threshold: float) -> tuple[bool, int, int]:
    """:func:`_tvertex_test` of one face given as lists (the rare face with a side that is non-finite, beyond
    float32 or too short to square)."""
    with np.errstate(over="ignore"):  # a side beyond float32 is inf, as in the array test
        h, s, n = (x[0] for x in _tvertex_test(np.asarray(P, np.float64)[None], np.float32(threshold)))
    return bool(h), int(s), int(n)


_F32 = struct.Struct("f")
_F32_MAX = float(np.finfo(np.float32).max)


def tvertex_collapse(v: np.ndarray, f: np.ndarray, threshold: float,
                     maybe: np.ndarray | None = None, frozen: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """vcglib's ``Clean::RemoveTVertexByCollapse(m, threshold, repeat=true)`` (MeshLab's "Remove T-vertices by
    edge collapse"), computed on the faces that take part only (``maybe``: a mask of the faces that can pass
    the test at the start, None: any); ``frozen``: a mask of vertices never moved (no face with such an apex
    is a candidate).

    Each round visits the faces in order; a face whose corner opposite its longest side (its apex) is not
    marked and lies within the side's length / ``threshold`` of it has the apex moved onto the side's corner
    nearer to the apex's foot; both are marked (the apex moves once per round, and later faces see it moved).
    At the end of the round the moved vertices are joined to the ones they were moved onto (the lowest index
    kept), faces with a repeated vertex are deleted, and rounds repeat until one moves nothing.

    One difference from vcglib: it joins every pair of coincident vertices in the mesh after each round
    (``RemoveDuplicateVertex``), here only the collapsed ones are joined, so that vertices the mesh already had
    twice (a seam, a pinch split by a non-manifold repair) stay apart. On meshes without coincident vertices
    the result is MeshLab's (tests/test_slivers.py compares the two).

    Returns the vertices and faces, the indices of the kept input vertices and faces (in order), and which
    output vertices were moved or joined."""
    thr, v, f = np.float32(threshold), np.asarray(v, np.float64), np.asarray(f, np.int64)
    thr64 = float(thr)  # (the scalar test's threshold: the float32 value, exactly)
    kv, kf = np.arange(len(v)), np.arange(len(f))
    joined = np.zeros(len(v), bool)
    look = np.arange(len(f)) if maybe is None else np.flatnonzero(maybe)
    while len(look):
        hit, side, near = _tvertex_test(v[f[look]], thr)
        if frozen is not None:
            hit &= ~frozen[kv][f[look, (side + 2) % 3]]
        cand = look[hit]
        if not len(cand):
            break
        hit_of = dict(zip(cand.tolist(), zip(side[hit].tolist(), near[hit].tolist())))
        # the fans of the candidates' corners (a moved apex's later faces are visited again); a vertex
        # outside them (the apex of a face that only became a candidate) is looked up on its own
        inner = np.zeros(len(v), bool)
        inner[f[cand].ravel()] = True
        near_faces = np.flatnonzero(rows_any(inner[f]))
        corner = f[near_faces].ravel()
        order = np.argsort(corner, kind="stable")
        start = np.searchsorted(corner[order], np.arange(len(v) + 1))

        def fan(x: int) -> np.ndarray:
            if inner[x]:
                return near_faces[order[start[x]:start[x + 1]] // 3]
            return np.flatnonzero(rows_any(f == x))

        pos = v.copy()
        marked = np.zeros(len(v), bool) if frozen is None else frozen[kv]
        dirty = set()  # faces with a corner moved in this round
        onto = {}  # apex -> the vertex it was moved onto
        heap = cand.tolist()
        queued = set(heap)
        while heap:
            fi = heapq.heappop(heap)
            if fi in dirty:
                h, s, n = _tvertex_test_one(pos[f[fi]].tolist(), thr64)
                if not h:
                    continue
            else:
                s, n = hit_of[fi]
            apex = int(f[fi, (s + 2) % 3])
            if marked[apex]:
                continue
            to = int(f[fi, n])
            marked[apex] = marked[to] = True
            pos[apex] = pos[to]
            onto[apex] = to
            for g in fan(apex).tolist():
                if g > fi:
                    dirty.add(g)
                    if g not in queued:
                        queued.add(g)
                        heapq.heappush(heap, g)
        members, remap = _joined(onto, len(v))
        keep_v = remap == np.arange(len(v))
        F = remap[f]
        keep_f = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0])
        touched = np.zeros(len(v), bool)
        touched[members] = True
        v, f = pos[keep_v], (np.cumsum(keep_v) - 1)[F[keep_f]]
        kv, kf = kv[keep_v], kf[keep_f]
        joined = (joined | touched)[keep_v]
        # the next round: the faces with a joined corner and the candidates left (their apex was marked)
        again = np.zeros(len(F), bool)
        again[cand] = True
        look = np.flatnonzero((again[keep_f]) | rows_any(joined[f]))
    return v, f, kv, kf, joined


def _joined(onto: dict[int, int], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each moved vertex joined with the one it was moved onto (``onto``; chains into one group, the lowest
    index kept): the vertices involved, and each of the ``n`` vertices' index after the join."""
    root: dict[int, int] = {}

    def find(x: int) -> int:
        while root.get(x, x) != x:
            x = root[x]
        return x

    for a, b in onto.items():
        ra, rb = find(a), find(b)
        if ra != rb:
            root[max(ra, rb)] = min(ra, rb)
    members = np.array(sorted(set(onto) | set(onto.values())), np.int64)
    remap = np.arange(n)
    remap[members] = [find(int(x)) for x in members]
    return members, remap


def fold_counts(mesh: Mesh) -> np.ndarray:
    """``[self-intersecting faces, non-manifold edges, non-manifold vertices]``: what an edge collapse can add."""
    counts = _mesh_edges(mesh)[2]  # (mesh_stats' non_manifold_edges, without the rest of its statistics)
    return np.array([self_intersecting_count(mesh), int((counts > 2).sum()), non_manifold_vertices(mesh)])


def collapse_folds(before: Mesh, after: Mesh, sites: bool = False) -> tuple[np.ndarray, ...]:
    """:func:`fold_counts` of ``before`` and ``after`` (the same mesh before and after a local edit such as
    :func:`collapse_slivers`) where they differ: both restricted to the faces near a face that is in one mesh
    and not in the other (centroids within the sum of the two faces' circumradii), so that the comparison costs a
    self-intersection test of that neighbourhood, not of the whole mesh. Faces elsewhere are the same in both
    and would add the same count to each. Both are zeros when no face differs. With ``sites``, also where
    ``after`` has folds there: the corners of its self-intersecting faces, its non-manifold vertices and the
    ends of its non-manifold edges, as points (k, 3)."""
    near = _near_changes(before, after)
    if near is None:
        zero = np.zeros(3, np.int64)
        return (zero, zero, np.zeros((0, 3))) if sites else (zero, zero)
    sb, sub = _tested_part(before, near[0]), submesh(after, near[1])
    intersections(sub, previous=sb)  # from the neighbourhood's test before the edit: the changed faces only
    counts = fold_counts(sb), fold_counts(sub)
    return (*counts, _fold_points(sub)) if sites else counts


def _tested_part(mesh: Mesh, mask: np.ndarray) -> Mesh:
    """``submesh(mesh, mask)``, with its self-intersection test taken from ``mesh``'s when that is known (the
    pairs of two faces in the part), else made."""
    sub = submesh(mesh, mask)
    whole = known(mesh, "intersections")
    if whole is not None and whole.faces is mesh.faces:
        pos = np.cumsum(mask) - 1
        pairs = whole.pairs[mask[whole.pairs].all(axis=1)] if len(whole.pairs) else whole.pairs
        remember(sub, "intersections", intersections_among(sub.vertices, sub.faces, pos[pairs]))
    else:
        intersections(sub)
    return sub


def _fold_points(mesh: Mesh) -> np.ndarray:
    """The corners of ``mesh``'s self-intersecting faces, its non-manifold vertices and the ends of its
    non-manifold edges (points (k, 3); the tests :func:`fold_counts` made, reused)."""
    directed, edge, counts = _mesh_edges(mesh)
    at = np.zeros(len(mesh.vertices), bool)
    at[mesh.faces[self_intersecting_faces(mesh)].ravel()] = True
    at[directed[counts[edge] > 2].ravel()] = True
    at |= non_manifold_vertex_mask(mesh)
    return mesh.vertices[at]


def _near_changes(before: Mesh, after: Mesh) -> tuple[np.ndarray, np.ndarray] | None:
    """Masks of the faces of ``before`` and of ``after`` near a face that is in one mesh and not in the other
    (:func:`collapse_folds`); None when no face differs."""
    fb, fa = before.faces, after.faces
    track = known(after, "collapsed_from")  # set by collapse_slivers: the faces it changed
    tracked = track is not None and track[0][0] is before.vertices and track[0][1] is before.faces
    if tracked:
        gone, new = track[1], track[2]
    else:
        gone, new = _changed_faces(before, after)
    if not gone.any() and not new.any():
        return None

    xb, rb = _cached(before, "centres", lambda: _centres(before))
    if tracked:  # the faces the collapse kept have before's centres (computed once), and get before's verdict
        x_new, r_new = _centres(Mesh(after.vertices, fa[new]))
        ra = np.empty(len(fa))
        ra[~new], ra[new] = rb[track[3]], r_new
    else:
        xa, ra = _centres(after)
    bound = max(np.quantile(rb, 0.99), np.quantile(ra, 0.99)) if len(fa) else np.quantile(rb, 0.99)
    # the changed faces as points with a reach: a small face its centroid and circumradius, a large one (a long
    # sliver) a grid of points on it at most ``step`` apart, each reaching ``step`` (covering the face)
    tris = np.concatenate([before.vertices[fb[gone]], after.vertices[fa[new]]])
    radii = np.concatenate([rb[gone], ra[new]])
    small = radii <= bound
    centroids = tris[small].mean(axis=1)
    grid_points = _face_grids(tris[~small], bound)
    seeds = np.concatenate([centroids, grid_points])
    reach = np.concatenate([radii[small], np.full(len(grid_points), bound)])
    seed_tree = _unbalanced_tree(seeds)
    n_small = len(centroids)  # the first seeds: the small faces' centroids; then the large faces' grids
    grid_tree = _unbalanced_tree(grid_points) if len(grid_points) else None
    # every reach is at most the bound, so a centroid within a seed's reach plus the bound lies in the seed's
    # cell of a grid of side 2 bound or in a neighbouring cell: only the centroids in those cells are looked at
    # (those around the centroids for the centroids' reaches, those around the grid points for the grids')
    parts = [xb, x_new, seeds] if tracked else [xb, xa, seeds]  # (a kept face's centre is one of xb's)
    cell = 2 * bound
    lo = np.min([col_min(q) for q in parts if len(q)], axis=0) - cell
    dims = np.floor((np.max([col_max(q) for q in parts if len(q)], axis=0) - lo) / cell).astype(np.int64) + 3 \
        if cell > 0 else None
    gridded = dims is not None and float(np.prod(dims.astype(float))) < 2.0 ** 62

    def keys(g: np.ndarray) -> np.ndarray:
        return (g[..., 0] * dims[1] + g[..., 1]) * dims[2] + g[..., 2]

    def cells_around(points: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None:
        """The keys of the cells of ``points`` and of their neighbours, and the box of cells they lie in."""
        if not len(points):
            return None
        k = np.unique(keys(np.floor((points - lo) / cell).astype(np.int64)))
        occupied = np.stack([k // (dims[1] * dims[2]), k // dims[2] % dims[1], k % dims[2]], axis=1)
        off = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3)
        return np.unique(keys(occupied[:, None] + off)), (col_min(occupied) - 1, col_max(occupied) + 1)

    around = (cells_around(centroids), cells_around(grid_points)) if gridded else (None, None)

    def candidates(g: list[np.ndarray] | None, n: int, cells) -> np.ndarray:
        """Of ``n`` faces whose centroids lie in the cells ``g`` (per axis), those in a cell of ``cells``
        (:func:`cells_around`; first those in its box, axis by axis)."""
        if g is None:
            return np.arange(n)
        if cells is None:
            return np.zeros(0, np.int64)
        keep, (b0, b1) = cells
        idx = np.flatnonzero((g[0] >= b0[0]) & (g[0] <= b1[0]) & (g[1] >= b0[1]) & (g[1] <= b1[1])
                             & (g[2] >= b0[2]) & (g[2] <= b1[2]))
        return idx[np.isin(keys(np.stack([q[idx] for q in g], axis=1)), keep)]

    def near(x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Faces (centroids ``x``, circumradii ``r``) that can touch a changed face: centroids within the sum of
        the two reaches; faces up to the common bound found around the seeds, the few larger ones (1 %)
        looked up the other way. Each search looks only at the faces no search before it has found (the
        cheapest first)."""
        mask = np.zeros(len(x), bool)
        big = np.flatnonzero(r > bound)
        if len(big):  # every reach is at most the bound
            mask[big[seed_tree.query_ball_point(x[big], r[big] + bound, return_length=True) > 0]] = True
        g = [np.floor((x[:, k] - lo[k]) / cell).astype(np.int64) for k in range(3)] if gridded else None
        cand = candidates(g, len(x), around[1])
        cand = cand[~mask[cand]]
        if len(cand) and grid_tree is not None:  # the grid points all reach the bound: the nearest one decides
            d = grid_tree.query(x[cand], distance_upper_bound=np.nextafter(2 * bound, np.inf))[0]
            mask[cand[d <= 2 * bound]] = True
        cand = candidates(g, len(x), around[0])
        cand = cand[~mask[cand]]
        if len(cand) and n_small:  # the small faces' own reaches
            hits = _unbalanced_tree(x[cand]).query_ball_point(centroids, reach[:n_small] + bound)
            mask[cand[np.concatenate([np.asarray(h, np.int64) for h in hits])]] = True
        return mask

    near_b = near(xb, rb)
    if tracked:  # a face's verdict depends on its own centre and radius alone
        near_a = np.empty(len(fa), bool)
        near_a[~new], near_a[new] = near_b[track[3]], near(x_new, r_new)
    else:
        near_a = near(xa, ra)
    return near_b, near_a


def _unbalanced_tree(points: np.ndarray):
    """A k-d tree of ``points`` split at the middle of each cell (scipy's ``balanced_tree=False``) rather than at
    the median: the same answers, but quicker to build and to search where the points cluster, as the grids
    along a raw scan's long border faces do (the fold check's neighbourhood in half the time on the raw
    Stanford scans: experiments/benchmarks/repair_speed.md)."""
    from scipy.spatial import cKDTree

    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def _centres(m: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Each face's centroid and circumradius (the largest distance from the centroid to a corner)."""
    def centre_radius(p: list[list[np.ndarray]]) -> list[np.ndarray]:
        c = [(p[0][k] + p[1][k] + p[2][k]) / 3.0 for k in range(3)]  # the mean of the corners, added in order
        r2 = None
        for q in p:  # squared distances summed as _sq_norm (x*x + y*y + z*z, left to right)
            d = [q[k] - c[k] for k in range(3)]
            s = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            r2 = s if r2 is None else np.maximum(r2, s)
        return c + [np.sqrt(r2)]
    cx, cy, cz, r = _per_face(m, centre_radius, 4)
    return np.stack([cx, cy, cz], axis=1), r


def _face_grids(tris: np.ndarray, step: float) -> np.ndarray:
    """Points covering each triangle of ``tris`` (k, 3, 3), at most ``step`` apart along its edges: with n the
    longest edge over ``step``, rounded up, the points ``t0 + (a / n) (t1 - t0) + (b / n) (t2 - t0)`` for whole
    a, b >= 0 with a + b <= n (b the slower), triangle after triangle."""
    if not len(tris):
        return np.zeros((0, 3))
    longest = np.max([np.linalg.norm(tris[:, (k + 1) % 3] - tris[:, k], axis=1) for k in range(3)], axis=0)
    n = np.ceil(longest / step).astype(np.int64)
    out = np.empty((int(((n + 1) * (n + 2) // 2).sum()), 3))
    start = np.r_[0, np.cumsum((n + 1) * (n + 2) // 2)[:-1]]
    for m in np.unique(n):  # the triangles of one n together: one pattern of (a, b)
        a, b = (g.ravel() for g in np.meshgrid(np.arange(m + 1), np.arange(m + 1)))
        a, b = a[a + b <= m] / m, b[a + b <= m] / m
        which = np.flatnonzero(n == m)
        t = tris[which]
        pts = t[:, None, 0] + a[None, :, None] * (t[:, None, 1] - t[:, None, 0]) \
            + b[None, :, None] * (t[:, None, 2] - t[:, None, 0])
        out[(start[which][:, None] + np.arange(len(a))).ravel()] = pts.reshape(-1, 3)
    return out


def _changed_faces(before: Mesh, after: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the faces of ``before`` that are not in ``after`` and of the faces of ``after`` that are not in
    ``before``, faces compared by their vertices' coordinates."""
    def coords(m: Mesh) -> np.ndarray:  # each vertex's coordinates hashed into one int64
        b = np.ascontiguousarray(m.vertices, dtype=np.float64).view(np.int64)
        return b[:, 0] * np.int64(-7046029254386353131) + b[:, 1] * np.int64(-4658895280553007687) + b[:, 2]

    cb, fb = coords(before), before.faces
    ca, fa = coords(after), after.faces
    # faces compared by their vertices' coordinates (vertex indices differ after a collapse), any corner order;
    # vertices at the same coordinates (a backend's duplicates) told apart by their order, which the edit keeps
    _, inv = np.unique(np.concatenate([cb, ca]), return_inverse=True)
    inv = inv.ravel().astype(np.int64)

    def ranked(ids: np.ndarray) -> np.ndarray:
        order = np.argsort(ids, kind="stable")
        s = ids[order]
        start = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1]
        rank = np.empty(len(ids), np.int64)
        rank[order] = np.arange(len(ids)) - np.repeat(start, np.diff(np.r_[start, len(ids)]))
        return ids * 4 + np.minimum(rank, 3)

    vb, va = ranked(inv[:len(cb)]), ranked(inv[len(cb):])
    n = int(max(vb.max(), va.max())) + 1

    def face_keys(ids: np.ndarray) -> np.ndarray:
        s = np.sort(ids, axis=1)
        return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]  # wraps around for huge meshes: a hash, collisions rare

    kb, ka = face_keys(vb[fb]), face_keys(va[fa])
    return ~np.isin(kb, ka), ~np.isin(ka, kb)
