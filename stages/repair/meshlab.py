"""``repair=meshlab``: a switchable pymeshlab filter chain covering MeshFix's steps, audited."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.errors import StageError
from scanreg.geometry import Mesh, locality_ordered, submesh
from scanreg.mesh.topology import (_meshset, boundary_edges, boundary_loop_sizes, dilate_faces, large_components,
                                   mesh_stats, self_intersecting_faces)
from scanreg.stages.registry import REPAIR
from scanreg.stages.repair.audit import AuditedRepair, GuardParams
from scanreg.types import RunContext


@REPAIR.register("meshlab")
class MeshLab(AuditedRepair):
    """A MeshLab (pymeshlab) filter chain covering MeshFix's steps, each switchable. It merges duplicate or
    close vertices, removes duplicate and null faces, repairs non-manifold edges and vertices, removes small
    components (below ``min_component_share`` of the largest part's area) and orients coherently. It then loops, up to ``max_rounds`` times: delete the self-intersecting
    faces and a ring around them, repair again, and close the holes, until the mesh is clean."""

    @dataclass
    class Params(GuardParams):
        merge_close_vertices: float = 0.0
        """Merge vertices closer than this share of the bounding-box diagonal (0: exact duplicates only)."""
        remove_duplicate_faces: bool = True
        """Remove faces that repeat another face's vertices."""
        remove_null_faces: bool = True
        """Remove faces of zero area."""
        repair_non_manifold: bool = True
        """Remove faces on non-manifold edges, split non-manifold vertices."""
        orient: bool = True
        """Orient all faces coherently."""
        remove_self_intersections: bool = True
        """Delete self-intersecting faces (with ``self_intersection_ring`` rings of neighbours) and refill."""
        self_intersection_ring: int = 2
        """Rings of neighbouring faces deleted with each self-intersecting face, so that the refilled holes are
        simple."""
        close_holes: bool = True
        """Close holes; first without creating self-intersections, then the rest unconditionally."""
        max_hole_edges: int = 0
        """Close only holes with at most this many boundary edges (0: every hole; see meshfix's note on an
        open scan's outer border)."""
        refine_holes: bool = True
        """Refine the patches that close holes to the surrounding edge length. Better patches, fewer rounds,
        but MeshLab's refinement visits every face of the mesh it is given, which is slow on large meshes."""
        max_rounds: int = 6
        """Most rounds of intersection removal and hole closing."""

    def fills_holes(self, p: MeshLab.Params) -> bool:
        return p.close_holes

    def run(self, mesh: Mesh, p: MeshLab.Params, ctx: RunContext) -> Mesh:
        """The filter chain on ``mesh`` with the planned parameters ``p``."""
        return _FilterChain(p).run(mesh)


class _FilterChain:
    """One run of MeshLab's filter chain with the parameters ``p``."""

    def __init__(self, p: MeshLab.Params):
        self.p = p

    def _clean_topology(self, ms) -> None:
        import pymeshlab

        p = self.p
        if ms.current_mesh().face_number() == 0:
            return
        if p.remove_null_faces:
            ms.meshing_remove_null_faces()
        ms.meshing_remove_unreferenced_vertices()
        if p.repair_non_manifold:
            ms.meshing_repair_non_manifold_edges(method=0)
            ms.meshing_repair_non_manifold_vertices()
        ms.meshing_remove_unreferenced_vertices()
        if p.min_component_share > 0:  # relative to the largest part, not to the bounding box
            mesh = _current(ms)
            keep = large_components(mesh, p.min_component_share)
            if not keep.all():
                small = submesh(mesh, keep)
                ms.clear()
                ms.add_mesh(pymeshlab.Mesh(small.vertices, small.faces.astype(np.int32)))

    def _close(self, ms, prevent: bool) -> None:
        """Close the holes within ``max_hole_edges`` (MeshLab's hole closing, ``selfintersection=prevent``), on
        the neighbourhood of those holes only: MeshLab's refinement visits every face of the mesh it is given
        (whatever the holes: seconds on a 100k-face mesh), so the holes are closed in the submesh of
        the faces whose bounding boxes overlap a hole's (grown by its size and three of its faces' longest
        edges: every face a patch can touch, which the intersection check needs), with only the holes' own
        faces selected (so that the submesh's cut is not closed), the refinement's edge length taken from the
        whole mesh; the patched submesh then replaces those faces."""
        import pymeshlab

        cm = ms.current_mesh()
        if cm.face_number() == 0:
            return
        mesh = Mesh(cm.vertex_matrix(), cm.face_matrix().astype(np.int64))
        loop, bf = _hole_loops(mesh)
        if not len(loop):
            return
        sizes = np.bincount(loop)
        chosen = np.flatnonzero(sizes <= (self.p.max_hole_edges or 10**9))
        if not len(chosen):
            return  # nothing within the limit: MeshLab's pass would cost seconds for nothing
        region = _hole_region(mesh, loop, bf, chosen)
        sub_idx = np.flatnonzero(region)
        sub = submesh(mesh, region)
        # the faces on the chosen holes, in the submesh's face order
        on_hole = np.zeros(len(mesh.faces), bool)
        on_hole[bf[np.isin(loop, chosen)]] = True
        sel = on_hole[sub_idx]
        m = pymeshlab.Mesh(sub.vertices, sub.faces.astype(np.int32), f_scalar_array=sel.astype(np.float64))
        local = pymeshlab.MeshSet()
        local.add_mesh(m)
        local.compute_selection_by_condition_per_face(condselect="fq > 0.5")
        diag = float(np.linalg.norm(mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)))
        try:
            local.meshing_close_holes(maxholesize=self.p.max_hole_edges or 10**9, selected=True,
                                      selfintersection=prevent, refinehole=self.p.refine_holes,
                                      refineholeedgelen=pymeshlab.PureValue(0.03 * diag))
        except pymeshlab.PyMeshLabException:
            return  # MeshLab refuses some holes; what stays open is reported by the audit
        lm = local.current_mesh()
        lv, lf = lm.vertex_matrix(), lm.face_matrix().astype(np.int64)
        n_sub = len(sub.vertices)
        if len(lv) < n_sub or not np.array_equal(lv[:n_sub], sub.vertices):
            raise StageError("repair=meshlab: MeshLab's hole closing reordered the vertices")  # never seen
        # the submesh's vertices back to the whole mesh's, new ones appended
        used = np.unique(mesh.faces[region])
        vmap = np.concatenate([used, len(mesh.vertices) + np.arange(len(lv) - n_sub)])
        v = np.vstack([mesh.vertices, lv[n_sub:]])
        f = np.vstack([mesh.faces[~region], vmap[lf]])
        ms.clear()
        ms.add_mesh(pymeshlab.Mesh(v, f.astype(np.int32)))

    def _cut_out(self, ms, now: Mesh, sel: np.ndarray) -> None:
        """The faces ``sel`` of ``now`` (the MeshSet's current mesh) and ``self_intersection_ring`` rings of
        neighbours removed, then the topology cleaned up; nothing when ``sel`` is empty. The vertices stay until
        the clean-up, as with MeshLab's own face removal."""
        import pymeshlab

        if not sel.any():
            return
        ms.clear()
        kept = now.faces[~dilate_faces(now.faces, sel, self.p.self_intersection_ring)]
        ms.add_mesh(pymeshlab.Mesh(now.vertices, kept))
        self._clean_topology(ms)

    def run(self, mesh: Mesh) -> Mesh:
        import pymeshlab

        p = self.p
        # renumbered for memory locality when the order is scattered (locality_ordered): MeshLab's filters and the
        # self-intersection tests below walk neighbours (MeshLab's cuts and fills may then differ in detail)
        ms = _meshset(Mesh(*locality_ordered(mesh.vertices, mesh.faces), mesh.source))
        if p.merge_close_vertices > 0:
            ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(100 * p.merge_close_vertices))
        else:
            ms.meshing_remove_duplicate_vertices()
        if p.remove_duplicate_faces:
            ms.meshing_remove_duplicate_faces()
        self._clean_topology(ms)
        if p.orient:
            ms.meshing_re_orient_faces_coherently()
        stuck = False
        last = mesh  # the last mesh tested for self-intersections: each test starts from its outcome
        for _ in range(p.max_rounds):
            if ms.current_mesh().face_number() == 0:
                break
            if p.close_holes and p.max_hole_edges and stuck:
                # holes under the limit that the last round's closing left or the clean-up opened again
                # (a patch MeshLab cannot make manifold): widened by the same rings, then refilled
                now = _current(ms)
                loop, on = _hole_loops(now)
                sel = np.zeros(len(now.faces), bool)
                sel[on[np.bincount(loop)[loop] <= p.max_hole_edges]] = True
                self._cut_out(ms, now, sel)
            if p.remove_self_intersections:
                now = _current(ms)
                sel = self_intersecting_faces(now, previous=last)
                last = now
                self._cut_out(ms, now, sel)
            if p.close_holes:
                self._close(ms, prevent=True)
                self._clean_topology(ms)
                self._close(ms, prevent=False)
                self._clean_topology(ms)
            cm = ms.current_mesh()
            if cm.face_number() == 0:
                break
            if p.orient:
                ms.meshing_re_orient_faces_coherently()
            now = _current(ms)
            intersecting = 0
            if p.remove_self_intersections:
                intersecting = int(self_intersecting_faces(now, previous=last).sum())
                last = now
            if not p.close_holes:
                open_holes = 0
            elif p.max_hole_edges:  # holes under the limit left (or opened again by the clean-up)
                open_holes = int((boundary_loop_sizes(now) <= p.max_hole_edges).sum())
            else:
                open_holes = mesh_stats(now)["boundary_loops"]
            if not intersecting and not open_holes:
                break
            stuck = open_holes > 0
        cm = ms.current_mesh()
        if cm.face_number() == 0:
            raise StageError(f"repair=meshlab: {mesh.source or 'mesh'}: the filter chain removed every face")
        out = Mesh(cm.vertex_matrix().astype(np.float64), cm.face_matrix().astype(np.int64), mesh.source)
        if p.orient and "volume" in (s := mesh_stats(out)) and s["volume"] < 0:
            out = Mesh(out.vertices, out.faces[:, ::-1].copy(), out.source)  # outward normals
        return out


def _current(ms) -> Mesh:
    """The MeshSet's current mesh as arrays."""
    cm = ms.current_mesh()
    return Mesh(cm.vertex_matrix(), cm.face_matrix())


def _hole_loops(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The boundary loop of each boundary edge (labels from 0) and the face on that edge."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    bnd, bf = boundary_edges(mesh, with_faces=True)
    if not len(bnd):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    bv, binv = np.unique(bnd, return_inverse=True)
    binv = binv.reshape(-1, 2)
    g = coo_matrix((np.ones(len(bnd)), (binv[:, 0], binv[:, 1])), shape=(len(bv), len(bv)))
    return connected_components(g, directed=False)[1][binv[:, 0]], bf


def _hole_region(mesh: Mesh, loop: np.ndarray, bf: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """Mask of the faces whose bounding boxes overlap the box of a chosen hole's faces grown by two median edge
    lengths: a hole's patch lies within its loop's box (MeshLab's ear cutting joins the loop's vertices, its
    refinement splits the new edges), so these are the faces it can touch, the hole's neighbours with them."""
    P = mesh.vertices[mesh.faces]
    lo, hi = P.min(axis=1), P.max(axis=1)
    grow = 2 * float(np.median(np.sqrt(((P[:, 1] - P[:, 0]) ** 2).sum(-1))))
    region = np.zeros(len(P), bool)
    for k in chosen:
        faces = bf[loop == k]
        blo, bhi = lo[faces].min(axis=0) - grow, hi[faces].max(axis=0) + grow
        region |= ((lo <= bhi) & (hi >= blo)).all(axis=1)
    return region
