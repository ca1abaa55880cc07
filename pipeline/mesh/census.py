"""The defect census of a triangle mesh: one vectorised pass that finds every defect class the repair's audit
reports, counts it as the audit counts it, and says where it is (vertex and face indices per class), so that a
repair can work on the defective regions only and pass a clean mesh untouched.

Counts are the audit's quantities (:func:`scanreg.mesh.topology.mesh_stats`,
:func:`~scanreg.mesh.topology.audit_mesh`), computed by the same helpers: ``components``, ``boundary_edges``,
``boundary_loops``, ``non_manifold_edges``, ``non_manifold_vertices``, ``inconsistent_orientation_edges``,
``degenerate_faces``, ``sliver_faces``, ``unreferenced_vertices``. Beyond them the census finds duplicate
vertices and faces, the components the repair removes (below ``min_component_share`` of the largest part's
area), which boundary loops are an open scan's outer border (kept open by ``open_border=auto``) and which are
holes, and where faces may intersect: the self-intersection *candidates*, pairs of faces sharing no vertex that
a broad phase cannot prove apart (:func:`intersection_candidates`), and the *fold vertices*, where two faces
sharing the vertex may meet beyond it (:func:`fold_vertices`). The exact self-intersection test (:mod:`scanreg.mesh.intersect`) decides among those
(:meth:`Census.pairs_to_test`); the census does not run it. On every mesh tested (tests/test_census.py:
interpenetrating and jittered spheres, a triangle soup, pymeshfix's bunny; experiments/benchmarks/census.md: the
raw Stanford scans, meshlab_defects, the dental meshes; also two overlaid raw scans) the exact test on those
pairs finds the same faces as on the whole mesh.

Lengths are in the mesh's units, areas in its units squared, angles in degrees. A pure function of the arrays:
no processes, threads or files.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from scanreg.geometry import Mesh, col_max, col_min, rows_any
from scanreg.mesh import native
from scanreg.mesh.intersect import candidate_pairs
from scanreg.mesh.predicates import orient3d_filter
from scanreg.mesh.topology import (SLIVER_ANGLE_DEG, _cached, _cross_columns, _face_areas, _mesh_edges_sorted,
                                   border_loops, boundary_edges, component_areas, dilate_faces, known,
                                   loop_labels, min_angles_deg, non_manifold_vertex_mask, open_scan_borders)

MIN_COMPONENT_SHARE = 0.01
"""The repair's default ``min_component_share`` (:class:`scanreg.stages.repair.audit.GuardParams`): parts with
less than this share of the largest part's area are removed."""
OPEN_BORDER_RATIO = 1.5
"""The repair's default ``open_border_ratio``: a boundary loop at least this many times as long as the square
root of its part's area is an open scan's outer border (:func:`~scanreg.mesh.topology.open_scan_borders`)."""
CELL_EXTENTS = 4.0
"""The broad phase's cell side, in 90th-percentile face box extents (:func:`intersection_candidates`)."""
CONE_COS = 0.1
"""A face belongs to its cell's sheet only when its unit normal's dot product with the sheet's mean normal
exceeds this (84 degrees): the sheet is then a graph over its mean plane."""


@dataclass(frozen=True, eq=False)
class Census:
    """The defects of one mesh: index arrays per class (vertex indices into the mesh's vertices, face indices
    into its faces) and the counts the repair's audit reports (:meth:`counts`)."""

    n_vertices: int
    n_faces: int
    component: np.ndarray
    """The connected component of each face (faces sharing a vertex are connected), labelled from 0 in the
    order of each component's first face."""
    component_faces: np.ndarray
    """Faces per component."""
    component_area: np.ndarray
    """Area per component (mesh units squared)."""
    small_components: np.ndarray
    """Components the repair removes: area below ``min_component_share`` of the largest component's."""
    boundary_edges: np.ndarray
    """Directed boundary edges (E, 2): edges with one face, as that face traverses them."""
    boundary_faces: np.ndarray
    """The face of each boundary edge."""
    boundary_loop: np.ndarray
    """The loop (connected chain of boundary edges) of each boundary edge."""
    loop_edges: np.ndarray
    """Edges per boundary loop."""
    loop_length: np.ndarray
    """Length per boundary loop (mesh units)."""
    loop_outer: np.ndarray
    """Whether each loop is an open scan's outer border (kept open by ``open_border=auto``) rather than a hole."""
    non_manifold_edges: np.ndarray
    """Edges with more than two faces (E, 2; vertex pairs, smaller index first)."""
    non_manifold_edge_faces: np.ndarray
    """The faces on those edges."""
    non_manifold_vertices: np.ndarray
    """Vertices whose faces form more than one fan (not counting those on non-manifold edges; MeshLab's count)."""
    inconsistent_edges: np.ndarray
    """Edges that two faces traverse in the same direction (E, 2; vertex pairs, smaller index first)."""
    inconsistent_edge_faces: np.ndarray
    """The faces on those edges."""
    unreferenced_vertices: np.ndarray
    """Vertices no face uses."""
    duplicate_vertices: np.ndarray
    """Vertices at exactly the same position as a vertex of lower index (referenced or not)."""
    degenerate_faces: np.ndarray
    """Faces with a repeated vertex index or zero area."""
    sliver_faces: np.ndarray
    """Faces whose smallest angle is below ``sliver_angle_deg`` (zero-area faces included)."""
    duplicate_faces: np.ndarray
    """Faces with the same three vertex indices as a face of lower index (any order)."""
    intersection_candidates: np.ndarray
    """Pairs (P, 2; smaller face first) of faces sharing no vertex index that may intersect
    (:func:`intersection_candidates`); the exact test decides."""
    fold_vertices: np.ndarray
    """Vertices around which two faces sharing the vertex may intersect (:func:`fold_vertices`); the exact test
    decides."""
    broad_phase: bool = True
    """Whether the self-intersection candidates and fold vertices were looked for (``census(..., broad_phase=
    False)`` leaves both empty, and the census then never calls a mesh clean)."""

    @property
    def holes(self) -> np.ndarray:
        """The boundary loops that are holes (every loop but the outer borders)."""
        return np.flatnonzero(~self.loop_outer)

    @property
    def candidate_faces(self) -> np.ndarray:
        """The faces in a self-intersection candidate pair."""
        return np.unique(self.intersection_candidates)

    def counts(self) -> dict[str, int]:
        """The census in numbers: the audit's keys (:func:`~scanreg.mesh.topology.mesh_stats`,
        ``non_manifold_vertices``) with the same values, and the census's own classes."""
        return {
            "vertices": self.n_vertices,
            "faces": self.n_faces,
            "unreferenced_vertices": len(self.unreferenced_vertices),
            "components": len(self.component_faces),
            "boundary_edges": len(self.boundary_edges),
            "boundary_loops": len(self.loop_edges),
            "non_manifold_edges": len(self.non_manifold_edges),
            "inconsistent_orientation_edges": len(self.inconsistent_edges),
            "degenerate_faces": len(self.degenerate_faces),
            "sliver_faces": len(self.sliver_faces),
            "non_manifold_vertices": len(self.non_manifold_vertices),
            "small_components": len(self.small_components),
            "holes": len(self.holes),
            "outer_borders": int(self.loop_outer.sum()),
            "duplicate_vertices": len(self.duplicate_vertices),
            "duplicate_faces": len(self.duplicate_faces),
            "intersection_candidate_pairs": len(self.intersection_candidates),
            "intersection_candidate_faces": len(self.candidate_faces),
            "fold_vertices": len(self.fold_vertices),
        }

    def defect_mask(self) -> np.ndarray:
        """Which faces carry a defect the repair would change: every face of a small component, the faces along
        hole (not along an outer border), on a non-manifold or inconsistently oriented edge, degenerate, sliver
        and duplicate faces, and the self-intersection candidates (the faces at non-manifold, duplicate and fold
        vertices are added by :meth:`defect_faces`, which has the faces)."""
        mask = np.zeros(self.n_faces, bool)
        mask[np.isin(self.component, self.small_components)] = True
        mask[self.boundary_faces[~self.loop_outer[self.boundary_loop]]] = True
        for faces in (self.non_manifold_edge_faces, self.inconsistent_edge_faces, self.degenerate_faces,
                      self.sliver_faces, self.duplicate_faces, self.intersection_candidates.ravel()):
            mask[faces] = True
        return mask

    def defect_faces(self, margin_rings: int = 0, faces: np.ndarray | None = None) -> np.ndarray:
        """The indices of the faces to repair (:meth:`defect_mask`) grown by ``margin_rings`` rings of faces
        sharing a vertex with them (a margin for cutting submeshes); ``faces``: the mesh's faces, needed for a
        margin and for the faces at non-manifold, duplicate and fold vertices."""
        mask = self.defect_mask()
        if faces is not None and len(faces):
            hot = np.zeros(max(self.n_vertices, int(faces.max()) + 1), bool)
            hot[self.non_manifold_vertices] = True
            hot[self.duplicate_vertices] = True
            hot[self.fold_vertices] = True
            if hot.any():
                mask |= rows_any(hot[faces])
            if margin_rings:
                mask = dilate_faces(faces, mask, margin_rings)
        elif margin_rings or len(self.non_manifold_vertices) or len(self.duplicate_vertices) \
                or len(self.fold_vertices):
            raise ValueError("defect_faces: pass the mesh's faces for a margin or for vertex defects")
        return np.flatnonzero(mask)

    def pairs_to_test(self, faces: np.ndarray) -> np.ndarray:
        """The face pairs (P, 2; smaller first, each once) the exact self-intersection test has to look at for
        this mesh's full answer: the candidates, and every pair of faces at a vertex whose fan is not a graph (a
        fold vertex, a non-manifold vertex, a vertex of a non-manifold or inconsistently oriented edge: there
        faces that share the vertex can cross, or lie folded onto each other) (``faces``: the mesh's faces;
        degenerate faces, which the exact test leaves out, are left out)."""
        f = np.asarray(faces, dtype=np.int64)
        fold = np.zeros(max(self.n_vertices, int(f.max()) + 1 if len(f) else 0), bool)
        for at in (self.fold_vertices, self.non_manifold_vertices, self.non_manifold_edges.ravel(),
                   self.inconsistent_edges.ravel()):
            fold[at] = True
        live = np.ones(len(f), bool)
        live[self.degenerate_faces] = False
        corner = np.flatnonzero(fold[f.ravel()] & np.repeat(live, 3))
        vid, fid = f.ravel()[corner], corner // 3
        order = np.argsort(vid, kind="stable")
        vid, fid = vid[order], fid[order]
        start = np.flatnonzero(np.r_[True, vid[1:] != vid[:-1]])
        size = np.diff(np.r_[start, len(vid)])
        # every pair within each vertex's group of faces: each face with the ones after it
        after = np.repeat(start + size, size) - np.arange(len(vid)) - 1
        i = np.repeat(np.arange(len(vid)), after)
        j = i + 1 + np.arange(len(i)) - np.repeat(np.cumsum(after) - after, after)
        a, b = fid[i], fid[j]
        pairs = np.concatenate([self.intersection_candidates, np.stack([np.minimum(a, b), np.maximum(a, b)], 1)])
        return np.unique(pairs, axis=0) if len(pairs) else pairs

    @property
    def clean(self) -> bool:
        """True when the census finds nothing the repair would change: no small component, no hole (an outer
        border is kept), no non-manifold edge or vertex, no inconsistent orientation, no unreferenced or
        duplicate vertex, no degenerate, sliver or duplicate face, no self-intersection candidate or fold vertex
        (never without the broad phase)."""
        c = self.counts()
        return self.broad_phase and not any(c[k] for k in (
            "small_components", "holes", "non_manifold_edges", "non_manifold_vertices",
            "inconsistent_orientation_edges", "unreferenced_vertices", "duplicate_vertices", "degenerate_faces",
            "sliver_faces", "duplicate_faces", "intersection_candidate_pairs", "fold_vertices"))


def census(vertices: np.ndarray, faces: np.ndarray, *, sliver_angle_deg: float = SLIVER_ANGLE_DEG,
           min_component_share: float = MIN_COMPONENT_SHARE,
           open_border_ratio: float = OPEN_BORDER_RATIO, broad_phase: bool = True) -> Census:
    """The defect census of the mesh ``vertices`` (N, 3), ``faces`` (M, 3) (module docstring). The thresholds
    are the repair's (:class:`scanreg.stages.repair.audit.GuardParams`): ``sliver_angle_deg`` (degrees),
    ``min_component_share`` (of the largest component's area), ``open_border_ratio`` (loop length over the
    square root of its component's area). ``broad_phase=False``: the topology and the faces' shapes only, no
    self-intersection candidates or fold vertices (for a caller that runs the exact test anyway)."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    return mesh_census(Mesh(v, f), sliver_angle_deg=sliver_angle_deg, min_component_share=min_component_share,
                       open_border_ratio=open_border_ratio, broad_phase=broad_phase)


def mesh_census(mesh: Mesh, *, sliver_angle_deg: float = SLIVER_ANGLE_DEG,
                min_component_share: float = MIN_COMPONENT_SHARE,
                open_border_ratio: float = OPEN_BORDER_RATIO, broad_phase: bool = True) -> Census:
    """:func:`census` of ``mesh`` itself: the census, and the topology it measures (edge table, components,
    border loops, face angles), are remembered on ``mesh`` (:mod:`scanreg.mesh.topology`), so that the repair's
    steps and audit of the same mesh reuse them. A mesh whose arrays are not contiguous float64 vertices and
    int64 (M, 3) faces is measured as :func:`census` converts it."""
    v, f = mesh.vertices, mesh.faces
    if not (v.dtype == np.float64 and f.dtype == np.int64 and f.shape[1:] == (3,) and v.flags.c_contiguous
            and f.flags.c_contiguous):
        return census(v, f, sliver_angle_deg=sliver_angle_deg, min_component_share=min_component_share,
                      open_border_ratio=open_border_ratio, broad_phase=broad_phase)
    key = ("census", sliver_angle_deg, min_component_share, open_border_ratio)
    if not broad_phase:
        full = known(mesh, (*key, True))  # made already with the broad phase: the rest of it is this census
        if full is not None:
            return _cached(mesh, (*key, False), lambda: replace(
                full, intersection_candidates=np.zeros((0, 2), np.int64), fold_vertices=np.zeros(0, np.int64),
                broad_phase=False) if full.n_faces else full)
    return _cached(mesh, (*key, broad_phase),
                   lambda: _mesh_census(mesh, sliver_angle_deg, min_component_share, open_border_ratio, broad_phase))


def _mesh_census(mesh: Mesh, sliver_angle_deg: float, min_component_share: float, open_border_ratio: float,
                 broad_phase: bool) -> Census:
    """:func:`mesh_census`, measured (contiguous float64 vertices and int64 faces)."""
    v, f = mesh.vertices, mesh.faces
    nv, nf = len(v), len(f)
    none_e, none_i = np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    dup_v = _duplicate_vertices(v)
    if not nf:
        return Census(nv, 0, none_i, none_i, np.zeros(0), none_i, none_e, none_i, none_i, none_i, np.zeros(0),
                      np.zeros(0, bool), none_e, none_i, none_i, none_e, none_i, np.arange(nv), dup_v, none_i,
                      none_i, none_i, none_e, none_i)
    directed, edge, counts, order = _mesh_edges_sorted(mesh)
    # components, by size
    lab, area = component_areas(mesh)
    small = np.flatnonzero(area < min_component_share * area.max())
    # boundary loops: holes and outer borders
    bnd, bf = boundary_edges(mesh, with_faces=True)
    loop = loop_labels(bnd)
    loops = border_loops(mesh)
    length = np.bincount(loop, np.linalg.norm(v[bnd[:, 0]] - v[bnd[:, 1]], axis=1)) if len(bnd) else np.zeros(0)
    outer = open_scan_borders(mesh, open_border_ratio, loops) if len(bnd) else np.zeros(0, bool)
    # non-manifold and inconsistently oriented edges (mesh_stats' quantities)
    many = counts[edge] > 2
    forward = directed[:, 0] < directed[:, 1]
    dcounts = np.bincount(2 * edge + forward, minlength=2 * len(counts))
    twice = (dcounts[0::2] > 1) | (dcounts[1::2] > 1)
    flipped = twice[edge]
    areas = _face_areas(mesh)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    degenerate = repeated | (areas <= 0)
    used = np.zeros(nv, bool)
    used[f.ravel()] = True
    live = ~degenerate
    if broad_phase:
        geometry = face_geometry(v, f[live])
        folds = fold_vertices(v, f, live, geometry)
        candidates = intersection_candidates(v, f, live, table=(directed, edge, counts, order), folds=folds,
                                             geometry=geometry)
    else:
        folds, candidates = none_i, none_e
    return Census(
        n_vertices=nv, n_faces=nf, component=lab, component_faces=np.bincount(lab), component_area=area,
        small_components=small, boundary_edges=bnd, boundary_faces=bf, boundary_loop=loop,
        loop_edges=loops[0], loop_length=length, loop_outer=outer,
        non_manifold_edges=_edge_pairs(directed[many]), non_manifold_edge_faces=np.unique(np.flatnonzero(many) % nf),
        non_manifold_vertices=np.flatnonzero(non_manifold_vertex_mask(mesh)),
        inconsistent_edges=_edge_pairs(directed[flipped]),
        inconsistent_edge_faces=np.unique(np.flatnonzero(flipped) % nf),
        unreferenced_vertices=np.flatnonzero(~used[:nv]), duplicate_vertices=dup_v,
        degenerate_faces=np.flatnonzero(degenerate),
        sliver_faces=np.flatnonzero(min_angles_deg(mesh) < sliver_angle_deg),
        duplicate_faces=_duplicate_faces(f),
        intersection_candidates=candidates, fold_vertices=folds, broad_phase=broad_phase,
    )


def fold_vertices(vertices: np.ndarray, faces: np.ndarray, live: np.ndarray | None = None,
                  geometry: tuple | None = None) -> np.ndarray:
    """Vertices around which two faces sharing the vertex may intersect: their (``live``) faces' unit normals are
    not all within 84 degrees (:data:`CONE_COS`) of their area-weighted mean (a flipped face, a crease sharper
    than 96 degrees), or they are, but the faces' corners projected onto the mean's plane add up to more than one
    turn (a fan that covers itself, as pymeshfix's bunny has five of). A fan within the cone that turns once,
    manifold and consistently oriented (the census reports the vertices and edges that are not), is a graph
    over its mean plane: two of its faces meet only along what they share. ``geometry``: :func:`face_geometry`
    of the live faces when already made."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if live is not None:
        f = f[live]
    if not len(f):
        return np.zeros(0, np.int64)
    _, e, n = geometry if geometry is not None else face_geometry(v, f)
    nv = max(len(v), int(f.max()) + 1)
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


def _edge_pairs(directed: np.ndarray) -> np.ndarray:
    """The distinct undirected edges (smaller vertex first) among directed edges (E, 2)."""
    if not len(directed):
        return np.zeros((0, 2), np.int64)
    return np.unique(np.sort(directed, axis=1), axis=0)


def _duplicate_vertices(v: np.ndarray) -> np.ndarray:
    """Vertices at exactly the position of a vertex of lower index (0.0 and -0.0 are one position). The
    coordinates are hashed into one integer, sorted, and equal hashes checked coordinate by coordinate."""
    if len(v) < 2:
        return np.zeros(0, np.int64)
    b = np.ascontiguousarray(v + 0.0).view(np.int64)  # + 0.0: -0.0 becomes 0.0
    with np.errstate(over="ignore"):
        h = b[:, 0] * np.int64(-7046029254386353131) + b[:, 1] * np.int64(-4658895280553007687) + b[:, 2]
    order = np.argsort(h, kind="stable")  # equal positions: ascending index
    hs = h[order]
    run = np.flatnonzero(hs[1:] == hs[:-1])  # a vertex after one of the same hash
    if not len(run):
        return np.zeros(0, np.int64)
    # the first of each run of equal hashes is the one the others are compared with
    start = np.maximum.accumulate(np.where(np.r_[True, hs[1:] != hs[:-1]], np.arange(len(hs)), 0))
    x, y = order[run + 1], order[start[run + 1]]
    same = (v[x] == v[y]).all(axis=1)
    return np.sort(x[same])


def _duplicate_faces(f: np.ndarray) -> np.ndarray:
    """Faces with the vertex indices of a face of lower index (any order)."""
    s = np.sort(f, axis=1)
    n = int(s.max()) + 1
    keys = (s[:, 0] * n + s[:, 1]) * n + s[:, 2]
    order = np.argsort(keys, kind="stable")
    same = np.zeros(len(f), bool)
    same[order[1:]] = keys[order[1:]] == keys[order[:-1]]
    return np.flatnonzero(same)


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
        a = np.floor((lo[sel] - org) / cell).astype(np.int64)
        span = np.floor((hi[sel] - org) / cell).astype(np.int64) - a + 1
        cnt = span[:, 0] * span[:, 1] * span[:, 2]
        huge = cnt > MAX_CELLS
        if huge.any():  # paired by their boxes with every face of this level
            cnt[huge] = 0
            i, j = candidate_pairs(lo[sel], hi[sel], huge)
            ii.append(sel[i])
            jj.append(sel[j])
        inside = np.zeros(len(fl), bool)
        inside[sel] = True
        link = inside[f1] & inside[f2]
        local = np.full(len(fl), -1, np.int64)
        local[sel] = np.arange(len(sel))
        i, j, bad = _sheet_pairs(a, span, cnt, nrm[sel], suspect[sel], local[f1[link]], local[f2[link]],
                                 level == REFINE, (org, cell, p0[sel]))
        ii.append(sel[i])
        jj.append(sel[j])
        if not len(bad):
            break
        sel, cell = sel[bad], cell / 2
    i, j = np.concatenate(ii), np.concatenate(jj)
    if len(i):
        keep = _boxes_overlap(lo, hi, i, j)
        i, j = i[keep], j[keep]
        fc = [np.ascontiguousarray(fl[:, k]) for k in range(3)]
        share = np.zeros(len(i), bool)
        for x in range(3):
            fi = fc[x][i]
            for y in range(3):
                share |= fi == fc[y][j]
        key = np.unique(np.minimum(i[~share], j[~share]) * len(fl) + np.maximum(i[~share], j[~share]))
        i, j = key // len(fl), key % len(fl)
        Pi, Pj = v[fl[i]], v[fl[j]]
        keep = ~(_separated(Pi, Pj) | _separated(Pj, Pi))
        i, j = i[keep], j[keep]
    return np.stack([idx[i], idx[j]], axis=1).astype(np.int64)


MAX_CELLS = 4096
"""A face whose bounding box touches more cells than this is paired by boxes instead of cells."""
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
                 f1: np.ndarray, f2: np.ndarray, last: bool, frame: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One level of :func:`intersection_candidates` on m faces: the pairs it looks at (face positions 0..m-1,
    repeats possible) and the faces of sheets that are not graphs, to be looked at in smaller cells (none when
    ``last``: their pairs are then among the pairs). ``a``: each face's first cell (integer coordinates),
    ``span``: its cells per axis, ``cnt``: its cells in all (0: the face takes no part), ``nrm``: normals (any
    length), ``suspect``: faces whose sheet is not a graph whatever their normals, ``f1``, ``f2``: the faces
    joined across an edge (:func:`_manifold_neighbours`), ``frame``: the grid's origin, the cell side and a corner
    of each face (a face spanning several cells is in those its plane passes through)."""
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
    return (*_cross_sheet_pairs(face, ckey, present, sheet, n_sheets, bad_sheet, last), bad)


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


def _cross_sheet_pairs(face, ckey, present, sheet, n_sheets, bad_sheet, last) -> tuple[np.ndarray, np.ndarray]:
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
