"""``repair=meshfix``: MeshFix (Attene 2010) through pymeshfix, audited.

Every pymeshfix session runs in a child process of its own (:func:`scanreg.process.run_isolated`): MeshFix keeps
state between calls, and a crash in it is then one error line."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.errors import StageError
from scanreg.geometry import Mesh, locality_ordered, submesh, triangle_areas_normals
from scanreg.mesh.intersect import intersecting_across
from scanreg.mesh.topology import (_face_components, _meshset, dilate_faces, known, large_components, mesh_stats,
                                   remember, self_intersecting_faces)
from scanreg.process import run_isolated
from scanreg.stages.registry import REPAIR
from scanreg.stages.repair.audit import AuditedRepair, GuardParams
from scanreg.types import RunContext


@REPAIR.register("meshfix")
class MeshFix(AuditedRepair):
    """MeshFix (Attene 2010) through pymeshfix. It removes the parts below ``min_component_share`` of the
    largest part's area and repairs every other part on its own (MeshFix itself keeps one component, and its
    intersection removal between touching parts, a head and its eyes, can eat them whole): it fixes
    connectivity and orientation, removes degenerate and self-intersecting triangles, and fills holes. When
    MeshFix's cleaning reports success (its own exact intersection test), or the loop that keeps the border open
    ended on the exact test (:mod:`scanreg.mesh.intersect`) finding none, the audit takes that count instead of
    testing again; for parts repaired one by one, every one of them so certified, it counts the pairs across
    parts only (:func:`~scanreg.mesh.intersect.intersecting_across`). (MeshFix's verdict and the exact test agree on
    the bunny and the cow: tests/test_repair.py.)"""

    @dataclass
    class Params(GuardParams):
        keep_largest: bool = False
        """Keep the largest part only (as ``min_component_share=1``; MeshFix's own behaviour)."""
        join_components: bool = False
        """Try to join nearby open components (MeshFix's ``join_closest_components``; all parts are then
        repaired as one mesh, and MeshFix keeps the largest)."""
        fill_holes: bool = True
        """Fill boundary loops (holes)."""
        max_hole_edges: int = 0
        """Fill only holes with at most this many boundary edges (0: every hole). An open scan's outer
        border is a hole too: capping it usually cuts through the scan, and the guard then fails the run; set
        a limit below the border's edge count to keep it open."""
        refine: bool = True
        """Refine the patches that fill holes so that their triangles match the surrounding size. (The holes
        the loop of ``clean_iterations`` cuts around self-intersections are refilled unrefined, as MeshFix's
        own intersection removal does: a refined patch bulges through the surface nearby and is cut again. On
        the raw Stanford scans the loop then ends after at most 3 refills with no self-intersection left;
        refined, bun090 still had 15 after 10.)"""
        clean_iterations: int = 10
        """Maximum iterations of MeshFix's degeneracy and self-intersection removal (0: skip it). With
        ``max_hole_edges`` > 0, MeshFix's own cleaning (which caps every border) is replaced by: delete the
        self-intersecting faces (the exact test, :mod:`scanreg.mesh.intersect`) and a ring around them, refill holes
        under the limit (unrefined), until none is left."""

    def fills_holes(self, p: MeshFix.Params) -> bool:
        return p.fill_holes

    def changes(self, mesh: Mesh, p: MeshFix.Params) -> bool:
        """MeshFix changes a mesh only where it finds a defect: by the census of its topology and face shapes
        (:func:`~scanreg.mesh.census.mesh_census`), a part to remove (or to join, or any but the largest with
        ``keep_largest``), a hole (with ``open_border=cap`` any border), a non-manifold edge or vertex, an
        inconsistent orientation, an unreferenced or duplicate vertex, a degenerate, sliver or duplicate face."""
        from scanreg.mesh.census import mesh_census

        c = mesh_census(mesh, sliver_angle_deg=p.sliver_angle_deg, min_component_share=p.min_component_share,
                        open_border_ratio=p.open_border_ratio, broad_phase=False).counts()
        holes = c["boundary_loops"] if p.open_border == "cap" else c["holes"]
        parts = (p.keep_largest or p.join_components) and c["components"] > 1
        return bool(holes or parts or any(c[k] for k in (
            "small_components", "non_manifold_edges", "non_manifold_vertices", "inconsistent_orientation_edges",
            "unreferenced_vertices", "duplicate_vertices", "degenerate_faces", "sliver_faces", "duplicate_faces")))

    def run(self, mesh: Mesh, p: MeshFix.Params, ctx: RunContext) -> Mesh:
        """MeshFix on ``mesh`` with the planned parameters ``p``."""
        out = self._repaired(mesh, p, ctx)
        if len(out.faces) == 0:
            raise StageError(f"repair=meshfix: {mesh.source or 'mesh'}: MeshFix removed every face")
        return out

    def _repaired(self, mesh: Mesh, p: MeshFix.Params, ctx: RunContext) -> Mesh:
        """``scope: defects``: the defective regions (:meth:`_regional`) when they can be cut out. Else the whole
        mesh at once when it is one part (or ``join_components``); else the parts below ``min_component_share``
        removed and every other part repaired on its own, the results side by side."""
        if p.scope == "defects" and not p.join_components:
            out = self._regional(mesh, p, ctx)
            if out is not None:
                return out
        if not p.join_components and not _face_components(mesh).any():
            return self._run_one(mesh, p, ctx, previous=mesh)
        keep = large_components(mesh, 1.0 if p.keep_largest else p.min_component_share)
        kept = mesh if keep.all() else submesh(mesh, keep)
        lab = _face_components(kept)
        if p.join_components or not lab.max() > 0:
            return self._run_one(kept, p, ctx, previous=mesh)
        parts = [self._run_one(submesh(kept, lab == k), p, ctx, previous=mesh) for k in range(lab.max() + 1)]
        parts = [q for q in parts if len(q.faces)] or parts[:1]
        off = np.cumsum([0] + [len(q.vertices) for q in parts])
        out = Mesh(np.vstack([q.vertices for q in parts]), np.vstack([q.faces + o for q, o in zip(parts, off)]),
                   kept.source)
        if all(known(q, "self_intersecting_faces") == 0 for q in parts):
            # each part certified free of self-intersections: only pairs across parts can intersect (the audit's
            # one self-intersection pass is this one, on the faces near another part's box)
            across = intersecting_across(out.vertices, out.faces,
                                         np.repeat(np.arange(len(parts)), [len(q.faces) for q in parts]))
            remember(out, "self_intersecting_faces", int(across.sum()))
        return out

    def _regional(self, mesh: Mesh, p: MeshFix.Params, ctx: RunContext) -> Mesh | None:
        """MeshFix on the defective regions only (:func:`_fill_regions`), after the parts below
        ``min_component_share`` are removed. The result is tested for self-intersections where it changed (from
        the input's outcome); those found are cut out with a ring of faces around them and the holes refilled
        in their regions (unrefined), as :func:`_clean_keeping_borders` does on the whole mesh, up to
        ``clean_iterations`` times. None (repair the whole mesh) when the regions cannot be cut out, or when
        cutting out intersections split a part in pieces."""
        keep = large_components(mesh, 1.0 if p.keep_largest else p.min_component_share)
        quiet = not ctx.verbose
        kept = mesh if keep.all() else submesh(mesh, keep)
        out = _fill_regions(kept, p, p.refine, quiet)
        clean, previous = False, mesh
        for _ in range(p.clean_iterations):
            if out is None:
                return None
            sel = self_intersecting_faces(out, previous=previous)
            if not sel.any():
                clean = True
                break
            previous = out
            out = _fill_regions(submesh(out, ~dilate_faces(out.faces, sel)), p, False, quiet)
        if out is None or _face_components(out).max() > _face_components(kept).max():
            return None  # cutting out intersections split a part: MeshFix on the whole mesh keeps one piece of it
        if clean:
            remember(out, "self_intersecting_faces", 0)
        return out

    def _run_one(self, mesh: Mesh, p: MeshFix.Params, ctx: RunContext, previous: Mesh) -> Mesh:
        """MeshFix on one part (or on every part with ``join_components``); may return no face. ``previous``:
        the repair's input, whose self-intersection test the loop that keeps borders open starts from."""
        import pymeshfix  # noqa: F401  (loaded here, before the fork: no library loading in a child)

        quiet = not ctx.verbose
        v, f, clean = run_isolated(_meshfix_session, mesh.vertices, mesh.faces, p, quiet)
        if _keeps_borders(p):
            # MeshFix's clean() fills every boundary while it removes intersections, capping the outer border
            # that max_hole_edges keeps open; remove intersections here and refill only holes under the limit.
            v, f, clean = _clean_keeping_borders(v, f, p, quiet, previous)
        out = Mesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), mesh.source)
        if clean:  # the audit need not test it again (its one self-intersection pass is this one)
            remember(out, "self_intersecting_faces", 0)
        return out


def _fill_regions(mesh: Mesh, p: MeshFix.Params, refine: bool, quiet: bool) -> Mesh | None:
    """``mesh`` with the regions around its holes to fill (at most ``max_hole_edges`` edges) and its non-manifold
    vertices and edges, with a margin (:func:`~scanreg.mesh.regions.defect_regions`), repaired by MeshFix in one
    child process (:func:`_region_sessions`; ``refine``: refine the patches) and stitched back
    (:func:`~scanreg.mesh.regions.stitch`), without the parts below ``min_component_share`` and the vertices no
    face uses; the regions also take in inconsistently oriented edges. None (repair the whole mesh) for defects
    that are not local to a region (duplicate faces, degenerate faces) or regions whose cut MeshFix
    did not leave as it was (a flipped patch larger than its region comes back turned at the cut)."""
    from scanreg.mesh.census import mesh_census
    from scanreg.mesh.regions import defect_regions, stitch

    c = mesh_census(mesh, sliver_angle_deg=p.sliver_angle_deg, min_component_share=p.min_component_share,
                    open_border_ratio=p.open_border_ratio, broad_phase=False)
    if len(c.duplicate_faces) or len(c.degenerate_faces):
        return None
    if len(c.small_components):  # bits a cut split off
        mesh = submesh(mesh, ~np.isin(c.component, c.small_components))
        return _fill_regions(mesh, p, refine, quiet)
    f = mesh.faces
    loops = c.loop_edges
    holes = (loops <= p.max_hole_edges if p.max_hole_edges else np.ones(len(loops), bool)) & p.fill_holes
    seeds = np.zeros(len(f), bool)
    seeds[c.boundary_faces[holes[c.boundary_loop]]] = True
    seeds[c.non_manifold_edge_faces] = True
    seeds[c.inconsistent_edge_faces] = True  # (a flipped patch larger than its region: its cut comes back turned)
    hot = np.zeros(len(mesh.vertices), bool)
    hot[c.non_manifold_vertices] = True
    seeds |= hot[f].any(axis=1)
    regions = defect_regions(mesh, seeds, holes)
    if regions is None:
        return None
    parts = [submesh(mesh, r.faces) for r in regions]
    repaired = run_isolated(_region_sessions, [(q.vertices, q.faces, r.hole_edges) for q, r in zip(parts, regions)],
                            refine, quiet) if regions else []
    return stitch(mesh, regions, repaired)


def _clean_keeping_borders(v: np.ndarray, f: np.ndarray, p: MeshFix.Params, quiet: bool,
                           previous: Mesh) -> tuple[np.ndarray, np.ndarray, bool]:
    """Intersections removed, holes under the limit refilled (unrefined); and whether the exact test found the
    result free of self-intersections. Each round's test starts from the previous round's mesh (the first from
    ``previous``)."""
    clean = False
    for _ in range(p.clean_iterations):
        current = Mesh(v, f)
        sel = self_intersecting_faces(current, previous=previous)
        previous = current
        if not sel.any():
            clean = True
            break
        import pymeshlab  # only when there is something to cut

        ms = _meshset(Mesh(v, f[~dilate_faces(f, sel)]))
        ms.meshing_remove_unreferenced_vertices()
        ms.meshing_repair_non_manifold_edges(method=0)
        ms.meshing_repair_non_manifold_vertices()
        ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=pymeshlab.PercentageValue(50))
        ms.meshing_remove_unreferenced_vertices()
        cm = ms.current_mesh()
        vm, fm = cm.vertex_matrix(), cm.face_matrix()  # here: MeshLab is not called in the child
        v, f = run_isolated(_fill_session, vm, fm, p.max_hole_edges, False, quiet)  # unrefined
    if _degenerate(v, f).any():
        v2, f2 = run_isolated(_degeneracy_session, v, f)
        if mesh_stats(Mesh(v2, f2))["boundary_loops"] <= mesh_stats(Mesh(v, f))["boundary_loops"]:
            v, f, clean = v2, f2, False  # changed after the test
    return v, f, clean


def _keeps_borders(p: MeshFix.Params) -> bool:
    """Whether MeshFix's cleaning is replaced by the loop that keeps borders over the hole limit open
    (:func:`_clean_keeping_borders`)."""
    return p.clean_iterations > 0 and p.fill_holes and p.max_hole_edges > 0


# pymeshfix's sessions, each run in a child process of its own (run_isolated): arrays in, arrays out

def _loaded(vertices: np.ndarray, faces: np.ndarray, quiet: bool):
    """A pymeshfix mesh (``PyTMesh``) holding ``vertices`` and ``faces``, renumbered for memory locality when
    their order is scattered (:func:`~scanreg.geometry.locality_ordered`: MeshFix builds its linked mesh in the
    arrays' order, and walks it faster when neighbours lie near one another)."""
    import pymeshfix

    vertices, faces = locality_ordered(vertices, faces)
    tin = pymeshfix.PyTMesh()
    tin.set_quiet(quiet)
    tin.load_array(vertices, faces.astype(np.int32))
    return tin


def _meshfix_session(vertices: np.ndarray, faces: np.ndarray, p, quiet: bool):
    """MeshFix on one mesh: loaded, parts joined (``join_components``), the smaller parts MeshFix splits off
    removed, then holes filled and, unless a hole limit keeps borders open, MeshFix's cleaning. Returns the
    vertices, the faces and whether the cleaning reported success."""
    tin = _loaded(vertices, faces, quiet)
    if p.join_components:
        tin.join_closest_components()
    tin.remove_smallest_components()  # one part here (or the joined ones): bits MeshFix splits off
    if p.fill_holes:
        tin.fill_small_boundaries(nbe=p.max_hole_edges, refine=p.refine)
    clean = False  # True: the result is known to be free of self-intersections
    if p.clean_iterations > 0 and not _keeps_borders(p):
        clean = bool(tin.clean(max_iters=p.clean_iterations, inner_loops=3))
    v, f = tin.return_arrays()
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), clean


def _region_sessions(regions: list, refine: bool, quiet: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    """MeshFix on each region (vertices, faces, the edges of its largest hole): loaded, its holes of at most
    that many edges filled (none when 0), and when the filling made degenerate faces, MeshFix's strong
    degeneracy removal (kept unless it opens a border, as :func:`_clean_keeping_borders` does on the whole
    mesh). No part is removed: a region's cut border ties it to the rest."""
    out = []
    for vertices, faces, hole_edges in regions:
        tin = _loaded(vertices, faces, quiet)
        if hole_edges:
            tin.fill_small_boundaries(nbe=hole_edges, refine=refine)
        v, f = (np.asarray(a) for a in tin.return_arrays())
        if _degenerate(v, f).any():
            loops = tin.n_boundaries
            tin.strong_degeneracy_removal(3)
            if tin.n_boundaries <= loops:
                v, f = (np.asarray(a) for a in tin.return_arrays())
        out.append((np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)))
    return out


def _degenerate(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Faces with a repeated vertex index or zero area (:func:`~scanreg.mesh.topology.mesh_stats`' degenerate
    faces)."""
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    return repeated | (triangle_areas_normals(Mesh(np.asarray(v, dtype=np.float64), f))[0] <= 0)


def _fill_session(vertices: np.ndarray, faces: np.ndarray, max_hole_edges: int, refine: bool,
                  quiet: bool) -> tuple[np.ndarray, np.ndarray]:
    """MeshFix's hole filling alone (holes with at most ``max_hole_edges`` edges)."""
    tin = _loaded(vertices, faces, quiet)
    tin.fill_small_boundaries(nbe=max_hole_edges, refine=refine)
    return tuple(np.asarray(a) for a in tin.return_arrays())


def _degeneracy_session(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MeshFix's strong degeneracy removal (3 iterations)."""
    tin = _loaded(vertices, faces, True)
    tin.strong_degeneracy_removal(3)
    return tuple(np.asarray(a) for a in tin.return_arrays())
