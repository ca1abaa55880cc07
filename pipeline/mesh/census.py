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
a broad phase cannot prove apart (:func:`~scanreg.mesh.broad_phase.intersection_candidates`), and the *fold vertices*, where two faces
sharing the vertex may meet beyond it (:func:`~scanreg.mesh.broad_phase.fold_vertices`). The exact self-intersection test (:mod:`scanreg.mesh.intersect`) decides among those
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

from scanreg.geometry import Mesh, rows_any
from scanreg.mesh.broad_phase import face_geometry, fold_vertices, intersection_candidates
from scanreg.mesh.topology import (SLIVER_ANGLE_DEG, _cached, _face_areas, _mesh_edges_sorted,
                                   border_loops, boundary_edges, component_areas, dilate_faces, known,
                                   loop_labels, min_angles_deg, non_manifold_vertex_mask, open_scan_borders)

MIN_COMPONENT_SHARE = 0.01
"""The repair's default ``min_component_share`` (:class:`scanreg.stages.repair.audit.GuardParams`): parts with
less than this share of the largest part's area are removed."""
OPEN_BORDER_RATIO = 1.5
"""The repair's default ``open_border_ratio``: a boundary loop at least this many times as long as the square
root of its part's area is an open scan's outer border (:func:`~scanreg.mesh.topology.open_scan_borders`)."""


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


