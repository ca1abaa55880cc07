"""The exact self-intersection test (scanreg.mesh.intersect) against known answers and against a brute-force
reference in rational arithmetic that uses a different algorithm (separating axes, every pair of faces)."""

from __future__ import annotations

import itertools
from fractions import Fraction

import numpy as np
import pytest

from scanreg.mesh.intersect import (Intersections, candidate_pairs, intersecting_across, orient2d, orient3d,
                                    self_intersecting_faces, self_intersections)


# ------------------------------------------------------------------------------------- rational reference

def _q(p):
    return tuple(Fraction(float(x)) for x in p)


def _sub(a, b):
    return tuple(x - y for x, y in zip(a, b))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return sum(x * y for x, y in zip(a, b))


def _convex_sets_meet(A: list, B: list) -> bool:
    """Closed convex hulls of the point lists ``A`` and ``B`` (a segment or a non-degenerate triangle each)
    have a common point: no separating axis among the face normals, the edge cross products and the in-plane
    edge normals (the complete candidate set for such polytopes, also when they are coplanar)."""
    def edges(P):
        return [_sub(P[(k + 1) % len(P)], P[k]) for k in range(len(P) if len(P) == 3 else 1)]

    eA, eB = edges(A), edges(B)
    normals = [_cross(eA[0], eA[1])] if len(A) == 3 else []
    normals += [_cross(eB[0], eB[1])] if len(B) == 3 else []
    axes = list(normals) + [_cross(a, b) for a in eA for b in eB]
    axes += [_cross(n, e) for n in normals for e in eA + eB]
    for ax in axes:
        if not any(ax):
            continue
        pa = [_dot(ax, p) for p in A]
        pb = [_dot(ax, p) for p in B]
        if max(pa) < min(pb) or max(pb) < min(pa):
            return False
    return True


def reference_self_intersecting(v: np.ndarray, f: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
    """The faces that meet another (with ``groups``: another of a different group), in rational arithmetic."""
    V = [_q(p) for p in v]
    first = {}
    f = np.array([[first.setdefault(V[x], x) for x in t] for t in f])  # one vertex per position
    out = np.zeros(len(f), bool)
    live = [k for k, t in enumerate(f) if len(set(t)) == 3
            and any(_cross(_sub(V[t[1]], V[t[0]]), _sub(V[t[2]], V[t[0]])))]
    for a, b in itertools.combinations(live, 2):
        if groups is not None and groups[a] == groups[b]:
            continue
        ta, tb = list(f[a]), list(f[b])
        shared = set(ta) & set(tb)
        A, B = [V[x] for x in ta], [V[x] for x in tb]
        if len(shared) == 3:
            hit = True
        elif len(shared) == 0:
            hit = _convex_sets_meet(A, B)
        elif len(shared) == 1:
            s = shared.pop()
            oa = [V[x] for x in ta if x != s]
            ob = [V[x] for x in tb if x != s]
            hit = _convex_sets_meet(oa, B) or _convex_sets_meet(ob, A)
        else:
            x, y = [V[k] for k in ta if k in shared]
            c = V[[k for k in ta if k not in shared][0]]
            d = V[[k for k in tb if k not in shared][0]]
            e = _sub(y, x)
            n1, n2 = _cross(e, _sub(c, x)), _cross(e, _sub(d, x))
            coplanar = _dot(_cross(e, _sub(c, x)), _sub(d, x)) == 0
            hit = coplanar and _dot(n1, n2) > 0
        if hit:
            out[a] = out[b] = True
    return out


# ------------------------------------------------------------------------------------------ known answers

def _check(v, f, expected):
    v, f = np.asarray(v, float), np.asarray(f)
    got = self_intersecting_faces(v, f)
    assert got.tolist() == expected
    assert reference_self_intersecting(v, f).tolist() == expected


def test_crossing_touching_and_apart():
    tri = [[0, 0, 0], [4, 0, 0], [0, 4, 0]]
    _check(tri + [[1, 1, -1], [1, 1, 1], [3, 3, 1]], [[0, 1, 2], [3, 4, 5]], [True, True])  # pierces
    _check(tri + [[1, 1, 0], [1, 1, 1], [2, 1, 1]], [[0, 1, 2], [3, 4, 5]], [True, True])  # vertex on it
    _check(tri + [[1, 1, 0.5], [1, 2, 1], [2, 1, 1]], [[0, 1, 2], [3, 4, 5]], [False, False])  # above
    _check(tri + [[3, 3, -1], [3, 3, 1], [5, 5, 0]], [[0, 1, 2], [3, 4, 5]], [False, False])  # beside
    _check(tri + [[2, 2, -1], [2, 2, 1], [5, 5, 0]], [[0, 1, 2], [3, 4, 5]], [True, True])  # touches hypotenuse


def test_coplanar():
    tri = [[0, 0, 0], [4, 0, 0], [0, 4, 0]]
    _check(tri + [[1, 1, 0], [5, 1, 0], [1, 5, 0]], [[0, 1, 2], [3, 4, 5]], [True, True])  # overlapping
    _check(tri + [[3, 3, 0], [6, 3, 0], [3, 6, 0]], [[0, 1, 2], [3, 4, 5]], [False, False])  # apart in plane
    _check(tri + [[0.5, 0.5, 0], [1, 0.5, 0], [0.5, 1, 0]], [[0, 1, 2], [3, 4, 5]], [True, True])  # inside


def test_shared_vertex_fan_and_fold():
    # a flat fan around the origin: neighbours meet only at the shared vertex
    v = [[0, 0, 0], [2, 0, 0], [0, 2, 0], [-2, 0, 0], [0, -2, 0]]
    _check(v, [[0, 1, 2], [0, 3, 4]], [False, False])
    # the second face folds back through the first (same wedge, tilted)
    v = [[0, 0, 0], [2, 0, 0], [0, 2, 0], [2, 1, 1], [1, 2, -1]]
    _check(v, [[0, 1, 2], [0, 3, 4]], [True, True])
    # tilted but only touching the shared vertex from above
    v = [[0, 0, 0], [2, 0, 0], [0, 2, 0], [2, 1, 1], [1, 2, 1]]
    _check(v, [[0, 1, 2], [0, 3, 4]], [False, False])


def test_shared_edge():
    v = [[0, 0, 0], [2, 0, 0], [0, 2, 0], [1, -2, 0], [1, 1, 0], [1, -2, 1]]
    _check(v, [[0, 1, 2], [1, 0, 3]], [False, False])  # flat, either side of the edge
    _check(v, [[0, 1, 2], [1, 0, 4]], [True, True])  # folded flat onto each other
    _check(v, [[0, 1, 2], [1, 0, 5]], [False, False])  # a hinge
    _check(v, [[0, 1, 2], [2, 1, 0]], [True, True])  # the same face twice


def test_coincident_vertices_are_one_vertex():
    # two fans split at a pinch (MeshLab's non-manifold vertex repair duplicates the vertex): touching there only
    v = [[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 0], [-2, 0, 0], [0, -2, 0], [0, 0, 0], [2, 1, 1], [1, 2, -1]]
    _check(v, [[0, 1, 2], [3, 4, 5]], [False, False])
    _check(v, [[0, 1, 2], [6, 7, 8]], [True, True])  # the duplicate's face folds through the first


def test_degenerate_faces_take_no_part():
    v = [[0, 0, 0], [4, 0, 0], [0, 4, 0], [1, 1, -1], [1, 1, 1], [1, 1, 2], [2, 2, 2]]
    f = [[0, 1, 2], [3, 4, 5], [3, 4, 4]]  # a needle through the triangle (collinear), a repeated index
    assert self_intersecting_faces(np.asarray(v, float), np.asarray(f)).tolist() == [False, False, False]


# ------------------------------------------------------------------------------------------- against it

def _random_soup(rng, n_faces, n_verts, grid):
    v = rng.integers(0, grid, size=(n_verts, 3)).astype(float)  # integer grid: many exact degeneracies
    f = np.array([rng.choice(n_verts, 3, replace=False) for _ in range(n_faces)])
    return v, f


@pytest.mark.parametrize("seed", range(6))
def test_random_meshes_match_the_rational_reference(seed):
    rng = np.random.default_rng(seed)
    v, f = _random_soup(rng, 40, 30, 6)
    assert np.array_equal(self_intersecting_faces(v, f), reference_self_intersecting(v, f))
    # rotated (inexact coordinates, near-degenerate contacts) and scaled by a power of two
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    w = v @ R.T * 0.37 + 0.001
    got = self_intersecting_faces(w, f)
    assert np.array_equal(got, reference_self_intersecting(w, f))
    assert np.array_equal(self_intersecting_faces(w * 2.0 ** -20, f), got)
    perm = rng.permutation(len(f))
    assert np.array_equal(self_intersecting_faces(w, f[perm]), got[perm])


def test_mesh_pairs_match_the_reference():
    """A realistic mesh: a sphere and a second, shifted sphere in one vertex array (their faces cross along a
    circle), with some shared vertices near the crossing; every face pair checked by the reference."""
    import open3d as o3d

    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=4)
    v1, f1 = np.asarray(s.vertices), np.asarray(s.triangles)
    v = np.vstack([v1, v1 * 0.9 + [0.8, 0.1, 0.05]])
    f = np.vstack([f1, f1 + len(v1)])
    got = self_intersecting_faces(v, f)
    assert got.any() and not got.all()
    assert np.array_equal(got, reference_self_intersecting(v, f))
    assert not self_intersecting_faces(v1, f1).any()  # one closed sphere: none


def test_candidate_pairs_are_all_overlapping_boxes():
    rng = np.random.default_rng(3)
    lo = rng.uniform(0, 10, (300, 3))
    size = rng.uniform(0, 0.5, (300, 3)) * rng.choice([1, 1, 1, 8], (300, 1))  # a few long boxes
    hi = lo + size
    i, j = candidate_pairs(lo, hi)
    brute = {(a, b) for a, b in itertools.combinations(range(300), 2)
             if (lo[a] <= hi[b]).all() and (lo[b] <= hi[a]).all()}
    assert set(zip(i.tolist(), j.tolist())) == brute and len(i) == len(brute)


@pytest.mark.parametrize("n_wide", [3, 300])
def test_near_boxes_keep_every_box_that_overlaps_a_seed(n_wide):
    """The incremental test's search starts from the boxes near its new faces (_near_boxes): every box that
    overlaps a seed box is among them, with a few or many seeds far wider than most boxes (a long face across a
    filled hole), and most boxes far from the seeds are not."""
    from scanreg.mesh.boxes import WIDE_SEEDS, _near_boxes

    rng = np.random.default_rng(n_wide)
    n = 4000
    lo = rng.uniform(0, 100, (n, 3))
    hi = lo + rng.uniform(0, 1, (n, 3)) * rng.choice([1] * 99 + [30], (n, 1))  # 1 % long boxes
    seed = np.zeros(n, bool)
    seed[rng.choice(n, 40, replace=False)] = True
    wide = rng.choice(np.flatnonzero(~seed), n_wide, replace=False)
    hi[wide] = lo[wide] + rng.uniform(5, 20, (n_wide, 3))
    seed[wide] = True
    assert (n_wide > WIDE_SEEDS) == (n_wide == 300)
    near = _near_boxes(lo, hi, seed)
    assert (np.diff(near) > 0).all()
    s = np.flatnonzero(seed)
    overlap = ((lo[:, None] <= hi[s][None]) & (lo[s][None] <= hi[:, None])).all(axis=2).any(axis=1)
    assert np.isin(np.flatnonzero(overlap), near).all()
    if n_wide < WIDE_SEEDS:
        assert len(near) < 0.5 * n


def test_in_cells_around_keeps_every_point_within_a_cell_of_a_seed():
    """in_cells_around: every point within one cell side of a seed along each axis is kept (those exactly one
    side away too), and points farther than two sides are not."""
    from scanreg.geometry import in_cells_around

    rng = np.random.default_rng(1)
    pts = rng.uniform(-5, 5, (20000, 3))
    seeds = rng.uniform(-3, 3, (30, 3))
    h = 0.37
    pts[:30] = seeds + h * rng.choice([-1.0, 1.0], (30, 3))  # exactly one side away along every axis
    got = in_cells_around(pts, seeds, h)
    cheb = np.abs(pts[:, None] - seeds[None]).max(axis=2).min(axis=1)
    assert got[cheb <= h].all() and not got[cheb > 2 * h * (1 + 1e-6)].any()
    assert not in_cells_around(pts, seeds[:0], h).any()
    # seeds whose cells cannot be numbered in 63 bits, or not finite: None (take every point), never a wrong mask
    assert in_cells_around(np.array([[1e19, 0, 0]]), np.array([[0, 0, 0], [1e19, 0, 0]]), 1.0) is None
    assert in_cells_around(np.zeros((1, 3)), np.array([[0, 0, 0], [np.nan, 0, 0]]), 1.0) is None


def test_predicates_are_exact_near_degeneracy():
    # points on a plane through the origin with rounded coordinates: orient3d's float value is noise, the sign
    # must be the exact one (checked with fractions)
    rng = np.random.default_rng(0)
    n = np.array([0.3, -0.5, 0.8])
    pts = rng.normal(size=(4000, 3))
    pts -= np.outer(pts @ n / (n @ n), n)  # on the plane, up to rounding
    a, b, c, d = pts[:1000], pts[1000:2000], pts[2000:3000], pts[3000:]
    got = orient3d(a, b, c, d)
    ref = []
    for p, q, r, s in zip(a, b, c, d):
        P, Q, R, S = (_q(x) for x in (p, q, r, s))
        det = _dot(_sub(P, S), _cross(_sub(Q, S), _sub(R, S)))
        ref.append((det > 0) - (det < 0))
    assert got.tolist() == ref
    a2, b2, c2 = (x[:, :2] for x in (a, b, c))
    t = np.linspace(0, 1, 1000)[:, None]
    c2 = a2 + t * (b2 - a2)  # on the line ab, up to rounding
    got2 = orient2d(a2, b2, c2)
    ref2 = []
    for p, q, r in zip(a2, b2, c2):
        P, Q, R = (_q(x) for x in (p, q, r))
        det = (P[0] - R[0]) * (Q[1] - R[1]) - (P[1] - R[1]) * (Q[0] - R[0])
        ref2.append((det > 0) - (det < 0))
    assert got2.tolist() == ref2


def _fresh(v, f):
    """A full test: without ``previous`` every test is one (there is no memo of earlier tests any more)."""
    return self_intersecting_faces(v, f)


def _two_spheres():
    import open3d as o3d

    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=20)
    v1, f1 = np.asarray(s.vertices), np.asarray(s.triangles)
    return np.vstack([v1, v1 * 0.9 + [0.8, 0.1, 0.05]]), np.vstack([f1, f1 + len(v1)])


def _pair_set(res: Intersections) -> set:
    return set(map(tuple, res.pairs.tolist()))


def _spy_incremental(monkeypatch) -> list:
    """Count the incremental tests (``_incremental``) made from now on."""
    import scanreg.mesh.intersect as intersect

    calls = []
    incremental = intersect._incremental
    monkeypatch.setattr(intersect, "_incremental", lambda *a: calls.append(1) or incremental(*a))
    return calls


def test_pair_blocks_give_the_same_faces(monkeypatch):
    """The exact pair test runs in blocks of candidate pairs (PAIR_BLOCK): blocks of 7 pairs find the same
    faces as one block, on two interpenetrating spheres and on random triangles."""
    import scanreg.mesh.intersect as intersect

    rng = np.random.default_rng(11)
    cases = [_two_spheres(), (rng.random((90, 3)), rng.integers(0, 90, (60, 3)))]
    whole = [_fresh(v, f) for v, f in cases]
    monkeypatch.setattr(intersect, "PAIR_BLOCK", 7)
    assert all(np.array_equal(_fresh(v, f), w) for (v, f), w in zip(cases, whole))
    assert whole[0].sum() > 0 and whole[1].sum() > 0


def test_incremental_equals_full(monkeypatch):
    """An edited copy (faces cut out, new faces that cross others, the rest permuted, vertices renumbered)
    tested with the original's outcome as ``previous`` goes on from it (incrementally); the result equals a
    full test's bit for bit: the same intersecting pairs, the same mask. The previous outcome is left as it
    was."""
    rng = np.random.default_rng(5)
    v, f = _two_spheres()
    base = self_intersections(v, f)  # the original first, as a repair's input
    assert base.mask.any() and base.keys is not None
    base_pairs = base.pairs.copy()
    keep = rng.random(len(f)) > 0.05
    extra_v = rng.uniform(-1, 1.5, (30, 3))
    extra_f = len(v) + rng.integers(0, 30, (10, 3))
    extra_f = extra_f[(extra_f[:, 0] != extra_f[:, 1]) & (extra_f[:, 1] != extra_f[:, 2]) & (extra_f[:, 0] != extra_f[:, 2])]
    v2 = np.vstack([v, extra_v])
    f2 = np.vstack([f[keep], extra_f])
    renum = rng.permutation(len(v2))  # new vertex order
    inv = np.argsort(renum)
    v2, f2 = v2[renum], inv[f2]
    perm = rng.permutation(len(f2))
    f2 = f2[perm]
    calls = _spy_incremental(monkeypatch)
    inc = self_intersections(v2, f2, previous=base)
    assert calls == [1]  # incremental
    full = self_intersections(v2, f2)
    assert calls == [1]  # without previous: a full test
    assert np.array_equal(inc.mask, full.mask) and inc.count == full.count
    assert _pair_set(inc) == _pair_set(full) and len(inc.pairs) == len(full.pairs)
    assert np.array_equal(inc.mask, self_intersecting_faces(v2, f2))
    assert np.array_equal(base.pairs, base_pairs)
    assert (inc.mask & (perm >= keep.sum())).any()  # some of the new faces cross others


def test_incremental_confirms_its_face_keys_by_the_corners(monkeypatch):
    """Faces whose keys match a previous mesh's count as kept only when their corners are the same: with keys
    made of the vertex indices alone (every moved face collides with its earlier self), a copy whose vertices
    moved into the other sphere is tested incrementally and equals the full test."""
    import scanreg.mesh.intersect as intersect

    v, f = _two_spheres()
    by_indices = lambda v_, f_: intersect._mix(np.sort(f_, axis=1).astype(np.uint64) @ np.array(  # noqa: E731
        [1, 1 << 20, 1 << 40], np.uint64))
    monkeypatch.setattr(intersect, "face_keys", by_indices)
    base = self_intersections(v, f)
    rng = np.random.default_rng(4)
    v2 = v.copy()
    moved = rng.choice(len(v) // 2, 25, replace=False)
    v2[moved] += [0.6, 0.0, 0.0]  # the first sphere's vertices pushed through the second
    calls = _spy_incremental(monkeypatch)
    inc = self_intersections(v2, f, previous=base)
    assert calls == [1]
    full = self_intersections(v2, f)
    assert _pair_set(inc) == _pair_set(full) and np.array_equal(inc.mask, full.mask)
    assert _pair_set(full) != _pair_set(base)


def test_same_corners_compares_the_sets_of_corners():
    from scanreg.mesh.intersect import same_corners

    a, b, c, d = np.eye(3), np.ones(3), np.zeros(3), np.full(3, 2.0)
    P = np.array([[a[0], a[1], a[2]], [a[0], a[1], a[2]], [a[0], a[1], a[2]], [b, b, c], [b, c, c]])
    Q = np.array([[a[2], a[0], a[1]], [a[1], a[0], a[2]], [a[0], a[1], d], [c, c, b], [b, c, d]])
    assert same_corners(P, Q).tolist() == [True, True, False, True, False]


def test_previous_is_used_only_when_it_shares_half_the_faces(monkeypatch):
    """``previous`` is used when it holds more than half of the new mesh's faces (a sampled pre-check, then
    the full count); an unrelated previous, one sharing too few faces, one more than MAX_RATIO times larger,
    and a mesh under MIN_FACES are tested in full; the result is the full test's in every case."""
    from scanreg.mesh.intersect import MAX_RATIO, MIN_FACES, PROBE, face_keys, _shares_half

    rng = np.random.default_rng(2)
    v, f = _two_spheres()
    keys = face_keys(v, f.astype(np.int64))
    assert len(keys) > 2 * PROBE  # the pre-check samples the faces

    def outcome(k):  # an outcome with these face keys (only the keys decide whether it is used)
        return Intersections(v, f, np.zeros((0, 2), np.int64), k)

    whole = outcome(keys)
    edited = outcome(keys[rng.permutation(len(keys))[: int(0.7 * len(keys))]])  # 70 % of the faces, reordered
    assert _shares_half(edited, whole)
    unrelated = outcome(keys[: int(0.4 * len(keys))] + 1)  # nothing shared
    assert not _shares_half(unrelated, whole) and not _shares_half(unrelated, edited)
    filler = (np.arange(1, len(keys) + 1, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)).astype(keys.dtype)
    few = np.concatenate([keys[: int(0.4 * len(keys))], filler])  # 40 % of these faces: too few
    assert few.dtype == keys.dtype
    assert not _shares_half(outcome(few), whole) and not _shares_half(outcome(few), edited)
    tenth = outcome(keys[: len(keys) // 10])  # all its faces in ``whole``, but ``whole`` is over 8 times larger
    assert len(keys) > MAX_RATIO * (len(keys) // 10) and not _shares_half(tenth, whole)
    # the same decisions in the test itself, with the full test's result
    full = self_intersections(v, f)
    calls = _spy_incremental(monkeypatch)
    far = self_intersections(v + 10.0, f)  # the same faces moved: no face shared
    assert np.array_equal(self_intersections(v + 10.0, f, previous=full).mask, far.mask) and calls == []
    small = f[: MIN_FACES // 2]  # an edit's neighbourhood: tested in full, no keys kept for it
    got = self_intersections(v, small, previous=full)
    assert got.keys is None and calls == [] and np.array_equal(got.mask, _fresh(v, small))
    # four copies of the spheres, the first in place: over 8 times the faces of 1200 of the first copy's
    vb = np.vstack([v + [5.0 * k, 0.0, 0.0] for k in range(4)])
    fb = np.vstack([f + k * len(v) for k in range(4)])
    big = self_intersections(vb, fb)
    part = f[:1200]
    assert len(part) >= MIN_FACES and len(fb) > MAX_RATIO * len(part)
    assert np.array_equal(self_intersections(v, part, previous=big).mask, _fresh(v, part)) and calls == []
    later = f[: int(0.7 * len(f))]
    assert np.array_equal(self_intersections(v, later, previous=full).mask, _fresh(v, later)) and calls == [1]


def test_mesh_intersections_go_on_from_a_tested_previous_mesh(monkeypatch):
    """scanreg.mesh.topology.intersections(mesh, previous=other): remembered on ``mesh``; incremental from
    ``other``'s remembered test when it has one (a repair's input for its output), a full test when it has
    none; the mask and count are the full test's either way."""
    from scanreg.geometry import Mesh
    from scanreg.mesh.topology import intersections, self_intersecting_count
    from scanreg.mesh.topology import self_intersecting_faces as faces_of

    v, f = _two_spheres()
    edited = f[7:]
    want = _fresh(v, edited)
    calls = _spy_incremental(monkeypatch)
    untested = Mesh(v, f)
    got = intersections(Mesh(v, edited), previous=untested)  # the previous mesh was never tested: full
    assert calls == [] and np.array_equal(got.mask, want)
    tested = Mesh(v, f)
    first = intersections(tested)
    assert intersections(tested) is first  # remembered
    out = Mesh(v, edited)
    assert np.array_equal(faces_of(out, previous=tested), want) and calls == [1]
    assert self_intersecting_count(out, previous=tested) == int(want.sum()) and calls == [1]  # remembered


@pytest.mark.parametrize("seed", range(4))
def test_folded_grids_match_the_reference(seed):
    """Height fields whose vertices are jittered sideways until triangles flip: fans that overlap themselves
    around a vertex, folds across edges; the fast path for vertices whose fan turns once must agree with the
    rational reference on every face."""
    rng = np.random.default_rng(seed)
    n = 6
    gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([gx.ravel(), gy.ravel(), np.zeros(n * n)], axis=1)
    v[:, :2] += rng.uniform(-1.2, 1.2, (n * n, 2)) * (rng.random((n * n, 1)) < 0.3)
    v[:, 2] = rng.normal(0, 0.3, n * n) * (seed % 2)
    q = np.arange(n * n).reshape(n, n)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, :-1].ravel(), q[1:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    got = _fresh(v, f)
    assert np.array_equal(got, reference_self_intersecting(v, f))
    if seed % 2 == 0:  # flat: the jitter folds some faces onto others
        assert got.any() and not got.all()


def test_regular_vertices_on_a_sphere_and_a_dent():
    import open3d as o3d
    from scanreg.mesh.intersect import regular_vertices

    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=10)
    v, f = np.asarray(s.vertices).copy(), np.asarray(s.triangles)
    assert regular_vertices(v, f).all()  # every fan turns once
    top = int(np.argmax(v[:, 2]))
    v[top] = [0.6, 0.0, 0.9]  # pushed sideways past its ring of neighbours: its fan folds over itself
    reg = regular_vertices(v, f)
    assert not reg[top]
    got = _fresh(v, f)
    assert got[(f == top).any(axis=1)].sum() >= 2
    small = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=4)
    v, f = np.asarray(small.vertices).copy(), np.asarray(small.triangles)
    v[int(np.argmax(v[:, 2]))] = [0.9, 0.1, 0.8]
    assert np.array_equal(_fresh(v, f), reference_self_intersecting(v, f))


def _fan(points, closed):
    """Faces (0, i, i+1) around vertex 0 at the origin over ``points`` (1-based), closed or open."""
    v = np.vstack([[0.0, 0.0, 0.0], points])
    k = len(points)
    f = [[0, 1 + i, 1 + (i + 1) % k] for i in range(k if closed else k - 1)]
    return v, np.array(f)


@pytest.mark.parametrize("case", ["twice_closed", "one_and_a_half_open", "closes_on_its_ray", "two_chains",
                                  "once_closed", "once_open"])
def test_fans_that_turn_more_than_once(case):
    """Fans built to defeat each condition of the fast path for regular vertices (each must be tested pair
    by pair, and the result must be the reference's), and two that turn once (no face intersects)."""
    from scanreg.mesh.intersect import regular_vertices

    if case == "twice_closed":  # a closed fan around twice; the blades' heights cross
        a = np.linspace(0, 4 * np.pi, 9)[:-1]
        pts = np.stack([np.cos(a), np.sin(a), np.sin(a / 2) * 0.5], 1)
        v, f = _fan(pts, closed=True)
    elif case == "one_and_a_half_open":  # an open fan around 1.5 times, its end climbing past its start
        a = np.linspace(0, 3 * np.pi, 8)
        pts = np.stack([np.cos(a), np.sin(a), 0.5 * np.cos(2 * a / 3)], 1)  # the two layers' heights cross
        v, f = _fan(pts, closed=False)
    elif case == "closes_on_its_ray":  # open, its last edge lies on its first edge (a different vertex)
        a = np.linspace(0, 2 * np.pi, 6)
        pts = np.stack([np.cos(a), np.sin(a), np.zeros(6)], 1)
        pts[-1] = [0.5, 0.0, 0.0]  # on the first edge, from (1, 0, 0) to the origin
        v, f = _fan(pts, closed=False)
    elif case == "two_chains":  # two open chains at one vertex overlapping in projection at crossing heights
        a = np.linspace(0, 0.8 * np.pi, 4)
        p1 = np.stack([np.cos(a), np.sin(a), np.linspace(-0.3, 0.3, 4)], 1)
        p2 = np.stack([np.cos(a - 0.3), np.sin(a - 0.3), np.linspace(0.3, -0.3, 4)], 1)
        v = np.vstack([[0.0, 0.0, 0.0], p1, p2])
        f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 5, 6], [0, 6, 7], [0, 7, 8]])
    else:
        a = np.linspace(0, 2 * np.pi, 8)[:-1] if case == "once_closed" else np.linspace(0, 1.5 * np.pi, 7)
        pts = np.stack([np.cos(a), np.sin(a), 0.3 * np.cos(3 * a)], 1)
        v, f = _fan(pts, closed=case == "once_closed")
    reg = regular_vertices(v, f)
    ref = reference_self_intersecting(v, f)
    assert np.array_equal(_fresh(v, f), ref)
    if case.startswith("once"):
        assert reg[0] and not ref.any()
    else:
        assert not reg[0] and ref.any()


def test_weld_equals_numpy_unique_rows():
    """The weld before the test (a lexsort of the columns) gives ``np.unique(v, axis=0)``'s rows and inverse:
    duplicated rows, rows equal in their first one or two coordinates, -0.0 beside 0.0, a single row."""
    from scanreg.mesh.intersect import _weld

    rng = np.random.default_rng(3)
    base = rng.integers(-2, 3, (200, 3)).astype(float) * 0.25  # many ties in every column, negatives
    base[rng.random(base.shape) < 0.1] = -0.0  # equal to 0.0 as numbers (one vertex), not in bits
    for v in (base, np.vstack([base, base[::7]])[rng.permutation(229)], rng.random((50, 3)), base[:1]):
        u, inv = _weld(v)
        ru, rinv = np.unique(v, axis=0, return_inverse=True)
        assert np.array_equal(u, ru) and np.array_equal(inv, rinv.reshape(-1))


@pytest.mark.parametrize("seed", range(3))
def test_regular_vertices_from_their_fans_alone(seed):
    """An incremental test looks up only the vertices of the new faces, computed from the faces around them
    (each vertex's answer depends on its own fan, in the faces' order): the same answers as from the whole
    mesh, on folded grids where some fans turn more than once."""
    from scanreg.geometry import rows_any
    from scanreg.mesh.intersect import regular_vertices

    rng = np.random.default_rng(seed)
    n = 9
    gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([gx.ravel(), gy.ravel(), rng.normal(0, 0.2, n * n)], axis=1)
    v[:, :2] += rng.uniform(-1.2, 1.2, (n * n, 2)) * (rng.random((n * n, 1)) < 0.3)
    q = np.arange(n * n).reshape(n, n)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, :-1].ravel(), q[1:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])[rng.permutation(2 * (n - 1) ** 2)]
    whole = regular_vertices(v, f)
    assert whole.any() and not whole.all()
    for _ in range(5):
        near = np.zeros(len(v), bool)
        near[f[rng.random(len(f)) < 0.1].ravel()] = True
        assert np.array_equal(regular_vertices(v, f[rows_any(near[f])]) & near, whole & near)


@pytest.mark.parametrize("seed", [0, 2, 4, 6])
def test_incremental_on_folded_grids(seed, monkeypatch):
    """Faces added to a folded grid, tested from the grid without them (``previous``): the new faces fold over
    old ones around shared vertices whose whole fan (old faces too) turns more than once; the incremental
    result equals the full test's."""
    rng = np.random.default_rng(seed)
    n = 26  # 1250 faces, 1125 without the added ones: above the incremental test's smallest mesh
    gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([gx.ravel(), gy.ravel(), np.zeros(n * n)], axis=1)
    v[:, :2] += rng.uniform(-1.2, 1.2, (n * n, 2)) * (rng.random((n * n, 1)) < 0.3)
    q = np.arange(n * n).reshape(n, n)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, :-1].ravel(), q[1:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    full = self_intersections(v, f)
    added = rng.random(len(f)) < 0.1
    calls = _spy_incremental(monkeypatch)
    prev = self_intersections(v, f[~added])
    inc = self_intersections(v, f, previous=prev)
    assert calls == [1]  # the second test was incremental
    assert np.array_equal(inc.mask, full.mask) and _pair_set(inc) == _pair_set(full)
    assert (full.mask & added).any()


@pytest.mark.parametrize("seed", range(6))
def test_intersecting_across_groups_matches_the_rational_reference(seed):
    """Random soups on an integer grid (coincident vertices, shared vertices and duplicated faces across groups,
    degenerate faces), their faces in three groups: the faces that meet one of another group, as the rational
    reference finds them; rotated (inexact coordinates), with the faces shuffled (unsorted labels)."""
    rng = np.random.default_rng(100 + seed)
    v, f = _random_soup(rng, 40, 30, 10)
    g = rng.integers(0, 3, size=len(f))
    expected = reference_self_intersecting(v, f, g)
    assert expected.any() and not expected.all()
    assert np.array_equal(intersecting_across(v, f, g), expected)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    w = v @ R.T * 0.37 + 0.001
    got = intersecting_across(w, f, g)
    assert np.array_equal(got, reference_self_intersecting(w, f, g))
    perm = rng.permutation(len(f))
    assert np.array_equal(intersecting_across(w, f[perm], g[perm]), got[perm])


def test_intersecting_across_parts_free_of_intersections_is_the_full_test():
    """Two crossing spheres and a third far away, each free of self-intersections, as three groups: the full
    test's mask; with the third sphere touching the second at a coincident vertex only: still no hit there."""
    v, f = _two_spheres()
    n = len(f) // 2
    far_v = v[: len(v) // 2] + [10.0, 0.0, 0.0]
    v3, f3 = np.vstack([v, far_v]), np.vstack([f, f[:n] + len(v)])
    g = np.repeat([0, 1, 2], n)
    for k in range(3):
        assert not _fresh(v3, f3[g == k]).any()
    full = _fresh(v3, f3)
    assert full.any()
    assert np.array_equal(intersecting_across(v3, f3, g), full)
    # the far sphere moved to touch the second one at one vertex (the same coordinates, another vertex index)
    top2 = np.argmax(v[len(v) // 2:, 0]) + len(v) // 2
    bottom3 = np.argmin(far_v[:, 0])
    moved = np.vstack([v, far_v - far_v[bottom3] + v[top2]])
    assert np.array_equal(intersecting_across(moved, f3, g), _fresh(moved, f3))
    assert not intersecting_across(moved, f3, g)[2 * n:].any()


def test_intersecting_across_faces_that_touch_at_the_boxes_edge():
    """A corner of one group's face on another group's face, the two boxes meeting in a plane only: a hit; a
    third face (of the first group) elsewhere: none; the same faces as one group: none across."""
    v = np.array([[-1, -1, 0], [-1, 1, 0], [0, 0, 0],  # its corner (0, 0, 0) lies on the next face
                  [0, -1, -1], [0, 1, -1], [0, 0, 1],  # in the plane x = 0
                  [-3, 5, 5], [-3, 6, 5], [-3, 5, 6]], float)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    assert intersecting_across(v, f, np.array([0, 1, 0])).tolist() == [True, True, False]
    assert reference_self_intersecting(v, f, np.array([0, 1, 0])).tolist() == [True, True, False]
    assert not intersecting_across(v, f, np.zeros(3, int)).any()
    # any integer labels (negative, sparse), one per face
    assert intersecting_across(v, f, np.array([-1, 10**12, -1])).tolist() == [True, True, False]
    with pytest.raises(ValueError, match="one label per face"):
        intersecting_across(v, f, np.array([0, 1]))
