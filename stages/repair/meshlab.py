"""``repair=meshlab``: a switchable pymeshlab filter chain covering MeshFix's steps, audited."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.config import Context
from scanreg.errors import StageError
from scanreg.geometry import Mesh, submesh
from scanreg.registry import REPAIR
from scanreg.stages.repair.audit import AuditedRepair, GuardParams
from scanreg.topology import _meshset, boundary_loop_sizes, large_components, mesh_stats


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
        but MeshLab's refinement costs about 9 s per pass on a 100k-face mesh (false: 0.1 s)."""
        max_rounds: int = 6
        """Most rounds of intersection removal and hole closing."""

    def __init__(self, params: Params):
        self.p = params

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
            cm = ms.current_mesh()
            mesh = Mesh(cm.vertex_matrix(), cm.face_matrix())
            keep = large_components(mesh, p.min_component_share)
            if not keep.all():
                small = submesh(mesh, keep)
                ms.clear()
                ms.add_mesh(pymeshlab.Mesh(small.vertices, small.faces.astype(np.int32)))

    def _close(self, ms, prevent: bool) -> None:
        import pymeshlab

        cm = ms.current_mesh()
        if cm.face_number() == 0:
            return
        # MeshLab's hole closing costs seconds on a large mesh even with nothing to close (its refinement
        # visits the whole mesh): skip it when no boundary loop is within the limit
        loops = boundary_loop_sizes(Mesh(cm.vertex_matrix(), cm.face_matrix()))
        if not (loops <= (self.p.max_hole_edges or 10**9)).any():
            return
        try:
            ms.meshing_close_holes(maxholesize=self.p.max_hole_edges or 10**9, selfintersection=prevent,
                                   refinehole=self.p.refine_holes)
        except pymeshlab.PyMeshLabException:
            pass  # MeshLab refuses some holes; what stays open is reported by the audit

    def run(self, mesh: Mesh, ctx: Context) -> Mesh:
        import pymeshlab

        p = self.p
        ms = _meshset(mesh)
        if p.merge_close_vertices > 0:
            ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(100 * p.merge_close_vertices))
        else:
            ms.meshing_remove_duplicate_vertices()
        if p.remove_duplicate_faces:
            ms.meshing_remove_duplicate_faces()
        self._clean_topology(ms)
        if p.orient:
            ms.meshing_re_orient_faces_coherently()
        for _ in range(p.max_rounds):
            if ms.current_mesh().face_number() == 0:
                break
            if p.remove_self_intersections:
                ms.compute_selection_by_self_intersections_per_face()
                if ms.current_mesh().selected_face_number():
                    for _ in range(p.self_intersection_ring):
                        ms.apply_selection_dilatation()
                    ms.meshing_remove_selected_faces()
                    self._clean_topology(ms)
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
            ms.compute_selection_by_self_intersections_per_face()
            intersecting = cm.selected_face_number() if p.remove_self_intersections else 0
            stats = mesh_stats(Mesh(cm.vertex_matrix(), cm.face_matrix()))
            open_holes = stats["boundary_loops"] if (p.close_holes and not p.max_hole_edges) else 0
            if not intersecting and not open_holes:
                break
        cm = ms.current_mesh()
        if cm.face_number() == 0:
            raise StageError(f"repair=meshlab: {mesh.source or 'mesh'}: the filter chain removed every face")
        out = Mesh(cm.vertex_matrix().astype(np.float64), cm.face_matrix().astype(np.int64), mesh.source)
        if p.orient and "volume" in (s := mesh_stats(out)) and s["volume"] < 0:
            out = Mesh(out.vertices, out.faces[:, ::-1].copy(), out.source)  # outward normals
        return out
