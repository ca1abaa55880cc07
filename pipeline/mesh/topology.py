"""Mesh topology and measurements: edges, borders and holes, connected components, non-manifold and
degenerate elements, smallest angles, self-intersections, and the statistics the repair audit reports.

Measurements of a mesh are remembered on it (:func:`remember`, :func:`known`) for as long as its arrays are the
same objects, so that the repair's steps share one edge table, one labelling of components, one test.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from scanreg.geometry import Mesh, rows_any
from scanreg.mesh import native
from scanreg.mesh.intersect import Intersections, self_intersections


def _cached(mesh: Mesh, name: str, compute):
    """``compute()``, remembered on ``mesh`` for as long as its vertex and face arrays are the same objects
    (the repair's audit, border plan, component split and sliver check share one edge table, one component
    labelling, one set of face angles per mesh). Meshes are not edited in place anywhere; one that were would
    need a new array to be measured again."""
    hit = known(mesh, name)
    if hit is not None:
        return hit
    value = compute()
    remember(mesh, name, value)
    return value


def remember(mesh: Mesh, name: str, value) -> None:
    """Record a measurement of ``mesh`` made elsewhere (a backend that has just run the same test, e.g.
    ``self_intersecting_faces``) so that the audit does not repeat it."""
    mesh.__dict__.setdefault("_topology_cache", {})[name] = ((mesh.vertices, mesh.faces), value)


class _Later:
    """A measurement still being made: ``produce()`` returns it (waiting for it if need be)."""

    def __init__(self, produce: Callable[[], Any]):
        self.produce = produce


def remember_later(mesh: Mesh, name: str, produce: Callable[[], Any]) -> None:
    """Record that a measurement of ``mesh`` is being made elsewhere: the first :func:`known` that asks for it
    takes ``produce()`` (e.g. the value of a test running beside the repair backend) and keeps it."""
    remember(mesh, name, _Later(produce))


def forget(mesh: Mesh, name: str) -> None:
    """Drop what :func:`remember` or :func:`remember_later` recorded under ``name`` (a test that was called off)."""
    mesh.__dict__.get("_topology_cache", {}).pop(name, None)


def known(mesh: Mesh, name: str):
    """A measurement :func:`remember`-ed (or cached) for ``mesh`` as it is now, or None."""
    hit = mesh.__dict__.get("_topology_cache", {}).get(name)
    if hit is None or hit[0][0] is not mesh.vertices or hit[0][1] is not mesh.faces:
        return None  # never measured, or the mesh was given new arrays since
    if isinstance(hit[1], _Later):  # taken now, and kept
        value = hit[1].produce()
        remember(mesh, name, value)
        return value
    return hit[1]


SLIVER_ANGLE_DEG = 1.0
"""A face whose smallest angle is below this many degrees is a sliver (a cap, with one angle near 180 degrees,
or a needle, with one edge near zero length)."""


def min_angles_deg(mesh: Mesh) -> np.ndarray:
    """The smallest interior angle of each face, in degrees (0 for a face with a repeated or coincident vertex)."""
    return _cached(mesh, "min_angles", lambda: _min_angles_deg(mesh))


def _min_angles_deg(mesh: Mesh) -> np.ndarray:
    return _per_face(mesh, _min_angles_of, 1)[0]


def _min_angles_of(c: list[list[np.ndarray]]) -> list[np.ndarray]:
    """The smallest angle (degrees) of faces given as corner columns (:func:`_per_face`)."""
    e = [[c[(i + 1) % 3][k] - c[i][k] for k in range(3)] for i in range(3)]  # edge i: corner i to corner i+1
    L = [np.sqrt(_dot3(x, x)) for x in e]
    # the smallest angle has the largest cosine (arccos decreases): one arccos per face, the same value
    n = len(L[0])
    cmax = np.full(n, -1.0)
    for i in range(3):  # the cosine at corner i, between edge i and the reversed edge i-1
        den = L[i] * L[i - 1]
        cos = np.divide(-_dot3(e[i], e[i - 1]), den, out=np.ones(n), where=den > 0)
        np.maximum(cmax, cos, out=cmax)
    return [np.degrees(np.arccos(np.clip(cmax, -1.0, 1.0)))]


FACE_BLOCK = 8192
"""Faces per block of :func:`_per_face`: each temporary (64 KB) stays in the cache and is reused from the heap
instead of mapped afresh."""


def _per_face(mesh: Mesh, fn, n_out: int) -> list[np.ndarray]:
    """``n_out`` values per face, computed block by block by ``fn(c)`` from the corner columns ``c[i][k]``
    (coordinate k of corner i, each a contiguous 1-D array: arithmetic on these is quicker than on
    (n, 3) rows). Element by element, so the values do not depend on the blocks."""
    v, f = mesh.vertices, mesh.faces
    cols = [np.ascontiguousarray(v[:, k]) for k in range(3)]
    outs = [np.empty(len(f)) for _ in range(n_out)]
    for s in range(0, len(f), FACE_BLOCK):
        fb = f[s:s + FACE_BLOCK]
        idx = [np.ascontiguousarray(fb[:, i]) for i in range(3)]
        for out, value in zip(outs, fn([[cols[k][j] for k in range(3)] for j in idx])):
            out[s:s + FACE_BLOCK] = value
    return outs


def _dot3(a: list[np.ndarray], b: list[np.ndarray]) -> np.ndarray:
    """Row-wise dot products of vectors given as three coordinate columns, summed as NumPy's
    ``einsum("ij,ij->i")`` does on rows of 3 on x86-64 ((x + z) + y, its two-lane loop without fused
    multiply-add): the same bits as before this was column-wise, and a fixed order on any machine."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def mesh_stats(mesh: Mesh) -> dict[str, float]:
    """Topology and size of a triangle mesh (NumPy only, fast).

    - ``components``: connected components of faces sharing a vertex;
    - ``boundary_edges``: edges with one face;
    - ``boundary_loops``: connected chains of boundary edges (holes and outer borders);
    - ``non_manifold_edges``: edges with more than two faces;
    - ``inconsistent_orientation_edges``: edges that two faces traverse in the same direction;
    - ``degenerate_faces``: faces with a repeated vertex or zero area;
    - ``sliver_faces``: faces whose smallest angle is below :data:`SLIVER_ANGLE_DEG` (caps, needles; zero-area
      faces included), the paper's degenerate triangles found "by their corners";
    - ``area``: in input units squared;
    - ``watertight``: 1 when there are no boundary and no non-manifold edges;
    - ``volume``: signed, in input units cubed, positive when outward oriented; only when watertight.
    """
    f = mesh.faces
    nv, nf = len(mesh.vertices), len(f)
    areas = _face_areas(mesh)
    directed, edge, counts = _mesh_edges(mesh)
    # two faces traversing an edge in the same direction: the same (edge, direction) twice
    forward = directed[:, 0] < directed[:, 1]
    dcounts = np.bincount(2 * edge + forward, minlength=2 * len(counts))
    bnd = directed[counts[edge] == 1]
    used = np.flatnonzero(np.bincount(f.ravel(), minlength=nv)) if nf else np.zeros(0, np.int64)
    n_comp = int(_face_components(mesh).max()) + 1 if nf else 0
    loops = len(_loop_sizes(bnd))
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    out = {
        "vertices": nv,
        "faces": nf,
        "unreferenced_vertices": nv - len(used),
        "components": int(n_comp),
        "boundary_edges": int(len(bnd)),
        "boundary_loops": int(loops),
        "non_manifold_edges": int((counts > 2).sum()),
        "inconsistent_orientation_edges": int((dcounts > 1).sum()),
        "degenerate_faces": int((repeated | (areas <= 0)).sum()),
        "sliver_faces": int((min_angles_deg(mesh) < SLIVER_ANGLE_DEG).sum()),
        "area": float(areas.sum()),
    }
    out["watertight"] = int(out["boundary_edges"] == 0 and out["non_manifold_edges"] == 0)
    if out["watertight"]:
        # the triple products column by column, in einsum's order, summed at once: the same bits
        triple = _per_face(mesh, lambda c: [_dot3(c[0], _cross_columns(c[1], c[2]))], 1)[0]
        out["volume"] = float(triple.sum() / 6.0)
    return out


def _meshset(mesh: Mesh):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(mesh.vertices, mesh.faces.astype(np.int32)))
    return ms


def dilate_faces(faces: np.ndarray, mask: np.ndarray, rings: int = 1) -> np.ndarray:
    """``mask`` grown ``rings`` times by the faces that share a vertex with a face in it (MeshLab's selection
    dilation)."""
    mask = mask.copy()
    for _ in range(rings):
        if not mask.any():
            break
        hot = np.zeros(int(faces.max()) + 1, bool)
        hot[faces[mask].ravel()] = True
        mask = rows_any(hot[faces])
    return mask


def non_manifold_vertices(mesh: Mesh) -> int:
    """The number of vertices whose faces do not form one fan (:func:`non_manifold_vertex_mask`)."""
    return int(non_manifold_vertex_mask(mesh).sum())


def non_manifold_vertex_mask(mesh: Mesh) -> np.ndarray:
    """Which vertices' faces do not form one fan (two cones meeting at a point), not counting the vertices of
    non-manifold edges: MeshLab's ``non_two_manifold_vertices`` (vcg's CountNonManifoldVertexFF), in NumPy.
    The corners of a vertex are joined across each edge with two faces; a vertex whose corners fall into
    more than one group is non-manifold. One entry per vertex (at least ``len(mesh.vertices)``). The groups by
    the compiled kernel when there is one (:mod:`scanreg.mesh.native`), else by pointer doubling
    (:func:`_fans_turning`) or the graph's components."""
    f = mesh.faces
    nf = len(f)
    if not nf:
        return np.zeros(len(mesh.vertices), bool)
    directed, edge, counts, order = _mesh_edges_sorted(mesh)
    rows = order[counts[edge[order]] == 2]  # grouped by edge (the pair's order does not matter: links are symmetric)
    r1, r2 = rows[0::2], rows[1::2]  # the two faces' directed copies of each two-face edge
    vert = f.ravel()  # corner 3 * face + k is vertex f[face, k]
    nv = max(len(mesh.vertices), int(vert.max()) + 1)
    if native.kernels is not None:  # the same groups by a union of the corners (scanreg.mesh.native)
        several = np.frombuffer(native.kernels.several_fans(np.ascontiguousarray(f, dtype=np.int64),
                                                            np.ascontiguousarray(r1), np.ascontiguousarray(r2), nv),
                                np.bool_).copy()
    else:
        several = _several_fans_numpy(nf, vert, r1, r2, nv)
    several[directed[counts[edge] > 2].ravel()] = False
    return several


def _several_fans_numpy(nf: int, vert: np.ndarray, r1: np.ndarray, r2: np.ndarray, nv: int) -> np.ndarray:
    """Which of ``nv`` vertices have corners in more than one group, the corners (``vert``: the flat faces) joined
    across each two-face edge (``r1``, ``r2``: its rows in the directed edge table of ``nf`` faces)."""
    nxt = np.array([1, 2, 0])
    j1, k1 = np.divmod(r1, nf)  # local edge j runs from corner j to corner j + 1 of face r % nf
    j2, k2 = np.divmod(r2, nf)
    c1s, c1e = 3 * k1 + j1, 3 * k1 + nxt[j1]
    c2s, c2e = 3 * k2 + j2, 3 * k2 + nxt[j2]
    same = vert[c1s] == vert[c2s]  # traversed the same way (inconsistent orientation)
    if not same.any():
        fan = _fans_turning(nf, vert, c1s, c1e, c2s, c2e)
    else:
        a = np.concatenate([c1s, c1e])
        b = np.concatenate([np.where(same, c2s, c2e), np.where(same, c2e, c2s)])
        g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(3 * nf, 3 * nf)).tocsr()
        fan = connected_components(g, directed=True, connection="weak")[1]  # weak: as undirected, no transpose
    one = np.empty(nv, fan.dtype)
    one[vert] = fan  # one of each vertex's groups; a corner in another group makes the vertex non-manifold
    several = np.zeros(nv, bool)
    several[vert[fan != one[vert]]] = True
    return several


def _fans_turning(nf: int, vert: np.ndarray, c1s, c1e, c2s, c2e) -> np.ndarray:
    """A label per corner, equal for the corners of one fan (the groups :func:`non_manifold_vertices` finds as
    connected components), for consistently oriented faces: there each corner has at most one next corner
    around its vertex (across its outgoing edge: ``c1s`` -> ``c2e``, ``c2s`` -> ``c1e``), so the fans are chains
    and cycles of that map. Pointer doubling: after k rounds a corner knows the smallest corner among its next
    2^k and the corner 2^k ahead (a chain's last corner stays put); with 2^k at least the most corners of one
    vertex, a chain's corners all reach its last corner, a cycle's all know its smallest. Several times faster
    than the graph's components on 100k faces, the same groups."""
    nc = 3 * nf
    ptr = np.arange(nc)
    ptr[c1s], ptr[c2s] = c2e, c1e
    lab = np.arange(nc)
    longest = int(np.bincount(vert).max())
    for _ in range(max(longest - 1, 1).bit_length()):
        np.minimum(lab, lab[ptr], out=lab)
        ptr = ptr[ptr]
    end = np.ones(nc, bool)
    end[c1s] = end[c2s] = False  # corners with a next one
    return np.where(end[ptr], ptr, lab)


def audit_mesh(mesh: Mesh, self_intersections: bool = True) -> dict[str, float]:
    """:func:`mesh_stats` plus ``non_manifold_vertices`` (MeshLab's count, :func:`non_manifold_vertices`) and
    ``self_intersecting_faces`` (faces with a point in common with another face beyond the vertices they share;
    exact, :mod:`scanreg.mesh.intersect`). The self-intersection test, the costly part, is skipped when a backend has
    just made it on this very mesh (:func:`remember`), and left out when ``self_intersections`` is false (the
    caller adds it)."""
    out = mesh_stats(mesh)
    out["non_manifold_vertices"] = non_manifold_vertices(mesh)
    if self_intersections:
        out["self_intersecting_faces"] = self_intersecting_count(mesh)
    return out


def _face_areas(mesh: Mesh) -> np.ndarray:
    """Each face's area, as :func:`~scanreg.geometry.triangle_areas_normals` computes it (the same
    arithmetic, without the normals), once per mesh."""
    def areas() -> np.ndarray:  # column by column, in cross3's and einsum's order: the same bits
        def area(c: list[list[np.ndarray]]) -> list[np.ndarray]:
            a, b = [c[1][k] - c[0][k] for k in range(3)], [c[2][k] - c[0][k] for k in range(3)]
            cross = _cross_columns(a, b)
            return [0.5 * np.sqrt(_dot3(cross, cross))]
        return _per_face(mesh, area, 1)[0]
    return _cached(mesh, "areas", areas)


def _cross_columns(a: list[np.ndarray], b: list[np.ndarray]) -> list[np.ndarray]:
    """:func:`~scanreg.geometry.cross3` of vectors given as three coordinate columns (the same arithmetic)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _mesh_edges(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_edge_table` of ``mesh``'s faces, computed once per mesh."""
    return _mesh_edges_sorted(mesh)[:3]


def _mesh_edges_sorted(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_edge_table_sorted` of ``mesh``'s faces, computed once per mesh (the one edge table)."""
    return _cached(mesh, "edges", lambda: _edge_table_sorted(mesh.faces))


def _edge_table(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces' directed edges (3M, 2; face k's at rows k, M + k, 2M + k), the undirected edge of each, and
    the number of faces on each undirected edge (``np.unique``'s sorted order and inverse)."""
    return _edge_table_sorted(f)[:3]


def _edge_table_sorted(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_edge_table` and the rows in the order of their undirected edge (the rows of one edge in any
    order), the sort that ``np.unique`` makes and drops, kept for :func:`non_manifold_vertices`."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    lo, hi = np.minimum(directed[:, 0], directed[:, 1]), np.maximum(directed[:, 0], directed[:, 1])
    n = int(hi.max()) + 1 if len(hi) else 1
    keys = lo.astype(np.int64) * n + hi.astype(np.int64)  # _edge_keys of the sorted pairs
    bits = max(len(keys) - 1, 1).bit_length()
    if (n * n - 1).bit_length() + bits <= 63:
        # each key with its row in the low bits, sorted as plain integers (no argsort): the rows
        # in key order, those of one key ascending (the edges' ids do not depend on the order of equal keys)
        packed = np.sort((keys << bits) | np.arange(len(keys), dtype=np.int64))
        order, sk = packed & ((1 << bits) - 1), packed >> bits
    else:
        order = np.argsort(keys)
        sk = keys[order]
    first = np.ones(len(sk), bool)
    first[1:] = sk[1:] != sk[:-1]
    ids = np.cumsum(first) - 1
    edge = np.empty(len(keys), np.int64)
    edge[order] = ids
    counts = np.diff(np.r_[np.flatnonzero(first), len(sk)])
    return directed, edge, counts, order


def _edge_keys(e: np.ndarray) -> np.ndarray:
    """One int64 per vertex pair (a, b), ordered as the pairs are lexicographically (a 1-D ``np.unique`` is
    quicker than ``np.unique(axis=0)`` on the pairs)."""
    e = np.asarray(e, dtype=np.int64)
    n = int(e.max()) + 1 if e.size else 1
    return e[:, 0] * n + e[:, 1]


def _loop_sizes(bnd: np.ndarray) -> np.ndarray:
    """Number of edges of each boundary loop (connected chain) of the boundary edges ``bnd`` (E, 2)."""
    return np.bincount(loop_labels(bnd)) if len(bnd) else np.zeros(0, np.int64)


def loop_labels(bnd: np.ndarray) -> np.ndarray:
    """The boundary loop (connected chain of edges sharing a vertex) of each boundary edge ``bnd`` (E, 2),
    labelled from 0."""
    if not len(bnd):
        return np.zeros(0, np.int64)
    bv, binv = np.unique(bnd, return_inverse=True)
    binv = binv.reshape(-1, 2)
    g = coo_matrix((np.ones(len(bnd)), (binv[:, 0], binv[:, 1])), shape=(len(bv), len(bv)))
    return connected_components(g, directed=False)[1][binv[:, 0]]


def boundary_edges(mesh: Mesh, with_faces: bool = False):
    """Directed boundary edges (a, b), as their one face traverses them (and that face's index)."""
    directed, edge, counts = _mesh_edges(mesh)
    on = counts[edge] == 1
    return (directed[on], np.flatnonzero(on) % max(len(mesh.faces), 1)) if with_faces else directed[on]


def boundary_loop_sizes(mesh: Mesh) -> np.ndarray:
    """Number of edges of each boundary loop (connected chain of boundary edges)."""
    return _loop_sizes(boundary_edges(mesh))


def _face_components(mesh: Mesh) -> np.ndarray:
    """The connected component of each face (faces sharing a vertex are connected), labelled from 0 in the
    order of each component's first face."""
    return _cached(mesh, "components", lambda: _face_components_uncached(mesh))


def face_labels(faces: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """The connected component of each of ``faces`` (faces sharing a vertex are connected), labels in no
    particular order: the vertices joined along the faces' edges (cheaper than the face-face graph), a graph of
    ``n_vertices`` vertices (at least the faces' largest index + 1), or with None of the vertices the faces use
    (for a few faces of a large mesh)."""
    f = np.asarray(faces)
    if n_vertices is None:
        used, inv = np.unique(f, return_inverse=True)
        f, nv = inv.reshape(-1, 3), len(used)
    else:
        nv = max(n_vertices, int(f.max()) + 1)
    g = coo_matrix((np.ones(2 * len(f)), (np.concatenate([f[:, 0], f[:, 1]]), np.concatenate([f[:, 1], f[:, 2]]))),
                   shape=(nv, nv))
    return connected_components(g, directed=False)[1][f[:, 0]]


def _face_components_uncached(mesh: Mesh) -> np.ndarray:
    f = mesh.faces
    if not len(f):
        return np.zeros(0, np.int32)
    # relabelled so that the labels count up in the order of each component's first face
    lab = face_labels(f, len(mesh.vertices))
    if (lab == lab[0]).all():  # one part (unreferenced vertices are parts of their own)
        return np.zeros(len(f), np.int32)
    uniq, first = np.unique(lab, return_index=True)
    relabel = np.empty(int(uniq.max()) + 1, np.int32)
    relabel[uniq[np.argsort(first)]] = np.arange(len(uniq), dtype=np.int32)
    return relabel[lab]


def component_areas(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The connected component of each face (:func:`_face_components`) and each component's area (input units
    squared)."""
    if not len(mesh.faces):
        return np.zeros(0, np.int64), np.zeros(0)
    lab = _face_components(mesh)
    return lab, np.bincount(lab, _face_areas(mesh))


def large_components(mesh: Mesh, min_share: float) -> np.ndarray:
    """Mask of the faces on components whose area is at least ``min_share`` of the largest component's area
    (relative to the largest part, never to the bounding box: a speck far away does not make the model small).
    ``min_share`` 0 keeps every face, 1 the largest component only (and any of equal area)."""
    if not len(mesh.faces):
        return np.zeros(0, bool)
    if not _face_components(mesh).any():  # one part (label 0 everywhere): kept, its area not needed
        return np.ones(len(mesh.faces), bool)
    lab, ca = component_areas(mesh)
    return ca[lab] >= min_share * ca.max()


def border_loops(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boundary loops (connected chains of boundary edges) as ``(edges, ratio, component)``: each loop's
    number of edges, its length divided by the square root of the area of the component it bounds
    (dimensionless; see :func:`open_scan_borders`), and that component's label (:func:`_face_components`)."""
    bnd, bf = boundary_edges(mesh, with_faces=True)
    if not len(bnd):
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
    v = mesh.vertices
    loop = loop_labels(bnd)
    length = np.bincount(loop, np.linalg.norm(v[bnd[:, 0]] - v[bnd[:, 1]], axis=1))
    lab, ca = component_areas(mesh)
    comp = np.zeros(len(length), np.int64)
    comp[loop] = lab[bf]
    return np.bincount(loop), length / np.sqrt(np.maximum(ca[comp], 1e-300)), comp


def open_scan_borders(mesh: Mesh, min_ratio: float, loops: tuple | None = None) -> np.ndarray:
    """Mask of the boundary loops (in :func:`border_loops` order) that are the outer border of a one-sided
    scan rather than a hole. The rule: in each connected component, the longest loop (by length) is an outer
    border when its length is at least ``min_ratio`` times the square root of the component's area; every
    other loop is a hole.

    The ratio does not depend on size or resolution. A flat disc's rim has 2 sqrt(pi) = 3.5, a hemisphere's
    sqrt(2 pi) = 2.5; a sphere with a round hole of radius r has about sqrt(pi) r / R for small holes (0.9 for
    r = R / 2; 1.6 when 80 % of the sphere is left, 1.4 at 85 %), a tooth crown cut off at 40 % of its height
    1.7. Measured: the outer borders of the 10 raw Stanford range scans 8.5-10.9 (their other loops
    under 1.7), meshlab_defects' open scans 4.6-6.0; the largest of the 70 holes of pymeshfix's closed
    StanfordBunny 0.47. ``loops``: :func:`border_loops` of ``mesh`` when already computed."""
    _, ratio, comp = loops if loops is not None else border_loops(mesh)
    out = np.zeros(len(ratio), bool)
    for c in np.unique(comp):
        idx = np.flatnonzero(comp == c)
        best = idx[np.argmax(ratio[idx])]
        out[best] = ratio[best] >= min_ratio
    return out



def intersections(mesh: Mesh, previous: Mesh | None = None) -> Intersections:
    """``mesh``'s self-intersection test (:func:`scanreg.mesh.intersect.self_intersections`), remembered on it;
    made incrementally from ``previous``'s when that mesh has been tested (a repair's input for its output)."""
    def test() -> Intersections:
        before = None if previous is None else known(previous, "intersections")
        return self_intersections(mesh.vertices, mesh.faces, before)
    return _cached(mesh, "intersections", test)


def self_intersecting_faces(mesh: Mesh, previous: Mesh | None = None) -> np.ndarray:
    """Boolean mask of ``mesh``'s self-intersecting faces (exact; see :mod:`scanreg.mesh.intersect`)."""
    return intersections(mesh, previous).mask


def self_intersecting_count(mesh: Mesh, previous: Mesh | None = None) -> int:
    """The number of self-intersecting faces, from a backend's :func:`remember`-ed count when it has one."""
    si = known(mesh, "self_intersecting_faces")
    if si is None:
        si = intersections(mesh, previous).count
        remember(mesh, "self_intersecting_faces", si)
    return int(si)
