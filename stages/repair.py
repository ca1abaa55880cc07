"""Mesh repair backends, and the audit that reports what a repair changed and guards against destroyed models.

Every backend's ``Params`` include the guard (:class:`GuardParams`). After a repair the audit compares the input
and the output:
- topology and size before and after (:func:`audit_mesh`);
- the one-sided Hausdorff distances input -> output (how far the input surface is from the repaired one, large
  where parts were removed) and output -> input (large where holes were filled);
- the share of the input surface that is no longer there.

The run fails with one clear line when the repair removed more than ``max_removed_area`` of the surface, or
moved it by more than ``max_hausdorff`` of the diagonal. This is MeshFix's known failure of reducing a dental
bridge to one tooth, or of eating an open scan whose outer border was capped. Open scans are made watertight
without that loss by ``open_border=shell`` (:func:`close_as_shell`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pipeline.config import Context
from pipeline.errors import StageError
from pipeline.geometry import Mesh, bbox_diagonal, face_normals, row_norms, submesh, vertex_normals
from pipeline.registry import REPAIR
from stages.sampler import barycentric_sample, triangle_areas_normals


def mesh_stats(mesh: Mesh) -> dict[str, float]:
    """Topology and size of a triangle mesh (NumPy only, fast).

    - ``components``: connected components of faces sharing a vertex;
    - ``boundary_edges``: edges with one face;
    - ``boundary_loops``: connected chains of boundary edges (holes and outer borders);
    - ``non_manifold_edges``: edges with more than two faces;
    - ``inconsistent_orientation_edges``: edges that two faces traverse in the same direction;
    - ``degenerate_faces``: faces with a repeated vertex or zero area;
    - ``area``: in input units squared;
    - ``watertight``: 1 when there are no boundary and no non-manifold edges;
    - ``volume``: signed, in input units cubed, positive when outward oriented; only when watertight.
    """
    f = mesh.faces
    nv, nf = len(mesh.vertices), len(f)
    areas, _ = triangle_areas_normals(mesh)
    directed, edge, counts = _edge_table(f)
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    bnd = directed[counts[edge] == 1]
    used = np.unique(f)
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
        "area": float(areas.sum()),
    }
    out["watertight"] = int(out["boundary_edges"] == 0 and out["non_manifold_edges"] == 0)
    if out["watertight"]:
        v = mesh.vertices
        out["volume"] = float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)
    return out


def _meshset(mesh: Mesh):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(mesh.vertices, mesh.faces.astype(np.int32)))
    return ms


def audit_mesh(mesh: Mesh) -> dict[str, float]:
    """:func:`mesh_stats` plus MeshLab's counts: ``non_manifold_vertices`` and ``self_intersecting_faces``
    (faces that intersect a face they do not share a vertex with)."""
    out = mesh_stats(mesh)
    ms = _meshset(mesh)
    out["non_manifold_vertices"] = int(ms.get_topological_measures()["non_two_manifold_vertices"])
    ms.compute_selection_by_self_intersections_per_face()
    out["self_intersecting_faces"] = int(ms.current_mesh().selected_face_number())
    return out


def surface_distances(a: Mesh, b: Mesh, n: int, seed: int) -> np.ndarray:
    """Distances from ``n`` area-weighted random points on ``a`` to the surface of ``b`` (exact point-to-
    triangle distances, Open3D's raycasting scene)."""
    import open3d as o3d

    pts, _, _ = barycentric_sample(a, n, np.random.default_rng([seed, 77]))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(b.vertices.astype(np.float32)), o3d.core.Tensor(b.faces.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy().astype(np.float64)


@dataclass
class GuardParams:
    apply_to: str = "both"
    """Which input meshes are repaired: ``source``, ``target`` or ``both`` (a CT surface made of separate
    teeth must not lose all but its largest component, so the dental case repairs the source only)."""
    check_only: bool = False
    """Audit what the repair would do (the before/after table and the guard) but go on with the unrepaired
    mesh; a guard violation is then reported, not fatal."""
    max_removed_area: float = 0.10
    """Fail when more than this share of the input surface is gone after the repair (see
    ``removed_tolerance``)."""
    max_hausdorff: float = 0.01
    """Fail when a point of the input surface lies farther than this share of the bounding-box diagonal
    from the repaired surface (one-sided Hausdorff distance, input -> output)."""
    max_hausdorff_edges: float = 2.0
    """The Hausdorff limit is at least this many median edge lengths of the input: on a coarse mesh one
    triangle can span more than ``max_hausdorff`` of the diagonal, and dropping a sliver at a ragged border
    must not fail the run (0: the diagonal share alone)."""
    removed_tolerance: float = 0.002
    """An input surface point counts as removed when it lies farther than this share of the bounding-box
    diagonal from the repaired surface."""
    audit_samples: int = 20000
    """Points sampled on each surface to measure the Hausdorff distances and the removed share."""
    open_border: str = "cap"
    """What becomes of an open scan's outer border, the longest boundary loop (with ``max_hole_edges`` set:
    every loop longer than that). ``cap``: filled like any hole (MeshFix's way; right for closed models with
    holes, but on an open scan the cap cuts through the surface and the guard fails the run). ``open``: left
    open. ``shell``: the scan is closed as a thin shell, its surface plus an offset copy ``shell_thickness``
    behind it, joined along the border: watertight without changing or removing any scanned surface; samplers
    and the evaluation use the scanned side only."""
    shell_thickness: float = 0.001
    """``open_border=shell``: distance of the back side behind the surface, as a share of the bounding-box
    diagonal (less where the space behind the surface is narrower, see :func:`close_as_shell`)."""

    def check(self):
        if self.apply_to not in ("source", "target", "both"):
            raise ValueError(f"apply_to must be source, target or both, got '{self.apply_to}'")
        if self.open_border not in ("cap", "open", "shell"):
            raise ValueError(f"open_border must be cap, open or shell, got '{self.open_border}'")
        if not self.shell_thickness > 0:
            raise ValueError(f"shell_thickness must be > 0, got {self.shell_thickness}")


def _edge_table(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces' directed edges (3M, 2; face k's at rows k, M + k, 2M + k), the undirected edge of each, and
    the number of faces on each undirected edge."""
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, edge, counts = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
    return directed, edge.ravel(), counts


def _loop_sizes(bnd: np.ndarray) -> np.ndarray:
    """Number of edges of each boundary loop (connected chain) of the boundary edges ``bnd`` (E, 2)."""
    if not len(bnd):
        return np.zeros(0, np.int64)
    bv, binv = np.unique(bnd, return_inverse=True)
    binv = binv.reshape(-1, 2)
    g = coo_matrix((np.ones(len(bnd)), (binv[:, 0], binv[:, 1])), shape=(len(bv), len(bv)))
    lab = connected_components(g, directed=False)[1]
    return np.bincount(lab[binv[:, 0]])


def boundary_edges(mesh: Mesh, with_faces: bool = False):
    """Directed boundary edges (a, b), as their one face traverses them (and that face's index)."""
    directed, edge, counts = _edge_table(mesh.faces)
    on = counts[edge] == 1
    return (directed[on], np.flatnonzero(on) % max(len(mesh.faces), 1)) if with_faces else directed[on]


def boundary_loop_sizes(mesh: Mesh) -> np.ndarray:
    """Number of edges of each boundary loop (connected chain of boundary edges)."""
    return _loop_sizes(boundary_edges(mesh))


def close_as_shell(mesh: Mesh, thickness: float, rounds: int = 6, attempts: int = 6) -> Mesh:
    """Close an oriented, edge-manifold open surface into a thin shell: the surface, a copy moved up to
    ``thickness`` behind it with its faces reversed (the back), and a strip of two triangles per boundary edge
    joining them. The result is watertight and consistently oriented (outward normals); the added faces come
    last and are counted in ``closure_faces``.

    The offset of each back vertex is at most a third of the free space behind it, and is halved (up to
    ``rounds`` times) where a back or strip face still intersects something. What no offset can fix, a spike
    (a vertex no direction lies behind), a fin, or a border that touches itself, is cut out: the few scanned
    faces involved are removed and the shell is built again (up to ``attempts`` times)."""
    front = mesh
    for _ in range(attempts):
        shell, sel, edge_faces = _shell(front, thickness, rounds)
        if not sel.any():
            break
        # the scanned faces involved: those selected, the originals of selected back faces, the border faces
        # of selected strip faces
        nf = len(front.faces)
        idx = np.flatnonzero(sel)
        bad = np.unique(np.concatenate([idx[idx < 2 * nf] % nf, edge_faces[(idx[idx >= 2 * nf] - 2 * nf)
                                                                             % len(edge_faces)]]))
        keep = np.ones(nf, bool)
        keep[bad] = False
        front = _manifold(Mesh(front.vertices, front.faces[keep], mesh.source))
    return shell


def _manifold(mesh: Mesh) -> Mesh:
    """Unreferenced vertices removed, non-manifold edges and vertices repaired, only the largest component."""
    ms = _meshset(mesh)
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_repair_non_manifold_edges(method=0)
    ms.meshing_repair_non_manifold_vertices()
    cm = ms.current_mesh()
    out = Mesh(cm.vertex_matrix().astype(np.float64), cm.face_matrix().astype(np.int64), mesh.source)
    lab = _face_components(out)
    return submesh(out, lab == np.argmax(np.bincount(lab)))


def _shell(mesh: Mesh, thickness: float, rounds: int) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """The shell of :func:`close_as_shell`, the mask of its faces that still intersect another, and the
    scanned face at each boundary edge."""
    import open3d as o3d

    bnd, edge_faces = boundary_edges(mesh, with_faces=True)
    v, f, nv = mesh.vertices, mesh.faces, len(mesh.vertices)
    if not len(bnd):
        return mesh, np.zeros(len(f), bool), edge_faces
    n = offset_directions(mesh)
    # where the surface comes back behind itself (a fold, a thin wall) the offset stops at a third of the gap
    c = v.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((v - c).astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    start = v - c - 1e-3 * thickness * n
    gap = scene.cast_rays(o3d.core.Tensor(np.hstack([start, -n]).astype(np.float32)))["t_hit"].numpy()
    offset = np.minimum(thickness, gap / 3.0)
    a, b = bnd[:, 0], bnd[:, 1]
    # the strip traverses each border edge b -> a (its face has a -> b) and the back's reversed edge a' -> b'
    strip = np.concatenate([np.stack([b, a, a + nv], axis=1), np.stack([b, a + nv, b + nv], axis=1)])
    added = np.concatenate([f[:, ::-1] + nv, strip])
    faces = np.concatenate([f, added]).astype(np.int64)
    for _ in range(rounds):
        shell = Mesh(np.vstack([v, v - offset[:, None] * n]), faces, mesh.source, closure_faces=len(added))
        ms = _meshset(shell)
        ms.compute_selection_by_self_intersections_per_face()
        sel = ms.current_mesh().face_selection_array().astype(bool)
        if not sel.any():
            break
        idx = np.unique(faces[sel])
        offset[idx[idx >= nv] - nv] *= 0.5
    return shell, sel, edge_faces


def offset_directions(mesh: Mesh, rounds: int = 20) -> np.ndarray:
    """Per vertex, a unit direction that lies on the front side of every face around it (positive dot product
    with each face normal) where one exists: the vertex normal, pulled towards the normals of the faces it
    fails. Offsetting a vertex against it keeps every copied face behind its original, also at sharp ridges
    where the plain vertex normal would flip a face through its neighbour."""
    fn = face_normals(mesh)
    d = vertex_normals(mesh)
    f = mesh.faces
    for _ in range(rounds):
        dots = np.einsum("fkj,fj->fk", d[f], fn)  # (M, 3): each face against the directions of its corners
        bad = dots < 0.3
        if not bad.any():
            break
        push = np.zeros_like(d)
        for k in range(3):
            np.add.at(push, f[bad[:, k], k], fn[bad[:, k]])
        d = d + 0.5 * push
        d /= np.maximum(row_norms(d), 1e-300)[:, None]
    return d


def repair_with_audit(stage, mesh: Mesh, ctx: Context, prefix: str) -> tuple[Mesh, dict[str, float]]:
    """Run ``stage`` on ``mesh``, audit before/after under ``prefix`` (``repair_``/``target_repair_``), apply
    the guard. Returns the mesh to go on with and the metrics."""
    p: GuardParams = stage.p
    before = audit_mesh(mesh)
    if p.open_border != "cap" and getattr(p, "fill_holes", getattr(p, "close_holes", False)):
        sizes = boundary_loop_sizes(mesh)
        if len(sizes) and not p.max_hole_edges:  # keep loops over half the longest (the outer border) open
            stage = copy.copy(stage)
            stage.p = replace(p, max_hole_edges=int(sizes.max()) // 2)
    out = stage.run(mesh, ctx)
    if p.open_border == "shell":
        out = close_as_shell(out, p.shell_thickness * bbox_diagonal(out.vertices))
    after = audit_mesh(out)
    m = {f"{prefix}before_{k}": v for k, v in before.items()}
    m.update({f"{prefix}after_{k}": v for k, v in after.items()})
    diag = bbox_diagonal(mesh.vertices)
    d_in = surface_distances(mesh, out, p.audit_samples, ctx.seed)
    d_out = surface_distances(out, mesh, p.audit_samples, ctx.seed + 1)
    removed = float((d_in > p.removed_tolerance * diag).mean())
    m.update({
        f"{prefix}hausdorff_max": float(d_in.max()),
        f"{prefix}hausdorff_mean": float(d_in.mean()),
        f"{prefix}hausdorff_max_rel": float(d_in.max() / diag),
        f"{prefix}hausdorff_mean_rel": float(d_in.mean() / diag),
        f"{prefix}hausdorff_added_max": float(d_out.max()),
        f"{prefix}hausdorff_added_max_rel": float(d_out.max() / diag),
        f"{prefix}removed_area_share": removed,
    })
    problems = []
    if removed > p.max_removed_area:
        problems.append(f"removed {removed:.1%} of the surface (limit repair.max_removed_area={p.max_removed_area:g})")
    v, f = mesh.vertices, mesh.faces
    edge = float(np.median(row_norms(v[f[:, [1, 2, 0]]] - v[f]))) if len(f) else 0.0
    limit = max(p.max_hausdorff * diag, p.max_hausdorff_edges * edge)
    m[f"{prefix}hausdorff_limit_rel"] = float(limit / diag)
    if d_in.max() > limit:
        problems.append(f"moved it by up to {d_in.max() / diag:.2%} of the diagonal (limit "
                        f"{limit / diag:.2%}: repair.max_hausdorff={p.max_hausdorff:g}, or "
                        f"repair.max_hausdorff_edges={p.max_hausdorff_edges:g} median edges if more)")
    m[f"{prefix}guard_ok"] = float(not problems)
    if problems:
        msg = (f"repair={stage.name}: {mesh.source}: the repair {' and '.join(problems)}; it would destroy part "
               "of the model. An open scan's outer border capped by hole filling does this: close the scan as a "
               "thin shell with repair.open_border=shell, keep the border open with repair.open_border=open, or "
               "inspect with repair.check_only=true")
        if not p.check_only:
            raise StageError(msg, metrics=m)
        print(f"warning: {msg}")
    return (mesh if p.check_only else out), m


@REPAIR.register("none")
class NoRepair:
    """Leave meshes as they are (no audit)."""

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def run(self, mesh: Mesh, ctx: Context) -> Mesh:
        return mesh


def _face_components(mesh: Mesh) -> np.ndarray:
    """The connected component of each face (faces sharing a vertex are connected), labelled from 0."""
    f = mesh.faces
    nf, nv = len(f), len(mesh.vertices)
    adj = coo_matrix((np.ones(3 * nf), (np.repeat(np.arange(nf), 3), f.ravel())), shape=(nf, nv)).tocsr()
    return connected_components(adj @ adj.T, directed=False)[1]


@REPAIR.register("meshfix")
class MeshFix:
    """MeshFix (Attene 2010) through pymeshfix. It keeps the largest component (or joins components), fixes
    connectivity and orientation, removes degenerate and self-intersecting triangles, and fills holes."""

    @dataclass
    class Params(GuardParams):
        keep_largest: bool = True
        """Remove all but the largest connected component before repairing."""
        join_components: bool = False
        """Try to join nearby open components (before keeping the largest)."""
        min_component_share: float = 0.0
        """With ``keep_largest`` false: remove components with fewer than this share of the faces."""
        fill_holes: bool = True
        """Fill boundary loops (holes)."""
        max_hole_edges: int = 0
        """Fill only holes with at most this many boundary edges (0: every hole). An open scan's outer
        border is a hole too: capping it usually cuts through the scan, and the guard then fails the run; set
        a limit below the border's edge count to keep it open."""
        refine: bool = True
        """Refine the patches that fill holes so that their triangles match the surrounding size."""
        clean_iterations: int = 10
        """Maximum iterations of MeshFix's degeneracy and self-intersection removal (0: skip it). With
        ``max_hole_edges`` > 0, MeshFix's own cleaning (which caps every border) is replaced by: delete the
        self-intersecting faces (found by MeshLab) and a ring around them, refill holes under the limit."""

    def __init__(self, params: Params):
        self.p = params

    def run(self, mesh: Mesh, ctx: Context) -> Mesh:
        import pymeshfix

        p = self.p
        if not p.keep_largest and p.min_component_share > 0:
            lab = _face_components(mesh)
            share = np.bincount(lab) / len(lab)
            mesh = Mesh(mesh.vertices, mesh.faces[share[lab] >= p.min_component_share], mesh.source)
        tin = pymeshfix.PyTMesh()
        tin.set_quiet(not (ctx.verbose if ctx else False))
        tin.load_array(mesh.vertices, mesh.faces.astype(np.int32))
        if p.join_components:
            tin.join_closest_components()
        if p.keep_largest:
            tin.remove_smallest_components()
        if p.fill_holes:
            tin.fill_small_boundaries(nbe=p.max_hole_edges, refine=p.refine)
        if p.clean_iterations > 0 and not (p.fill_holes and p.max_hole_edges > 0):
            tin.clean(max_iters=p.clean_iterations, inner_loops=3)
        v, f = tin.return_arrays()
        if p.clean_iterations > 0 and p.fill_holes and p.max_hole_edges > 0:
            # MeshFix's clean() fills every boundary while it removes intersections, capping the outer border
            # that max_hole_edges keeps open; remove intersections here and refill only holes under the limit.
            v, f = self._clean_keeping_borders(np.asarray(v), np.asarray(f), ctx)
        if len(f) == 0:
            raise StageError(f"repair=meshfix: {mesh.source or 'mesh'}: MeshFix removed every face")
        return Mesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), mesh.source)

    def _clean_keeping_borders(self, v: np.ndarray, f: np.ndarray, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        import pymeshfix
        import pymeshlab

        for _ in range(self.p.clean_iterations):
            ms = _meshset(Mesh(v, f))
            ms.compute_selection_by_self_intersections_per_face()
            if ms.current_mesh().selected_face_number() == 0:
                break
            ms.apply_selection_dilatation()
            ms.meshing_remove_selected_faces()
            ms.meshing_remove_unreferenced_vertices()
            ms.meshing_repair_non_manifold_edges(method=0)
            ms.meshing_repair_non_manifold_vertices()
            ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=pymeshlab.PercentageValue(50))
            ms.meshing_remove_unreferenced_vertices()
            cm = ms.current_mesh()
            tin = pymeshfix.PyTMesh()
            tin.set_quiet(not (ctx.verbose if ctx else False))
            tin.load_array(cm.vertex_matrix(), cm.face_matrix().astype(np.int32))
            tin.fill_small_boundaries(nbe=self.p.max_hole_edges, refine=self.p.refine)
            v, f = (np.asarray(a) for a in tin.return_arrays())
        if mesh_stats(Mesh(v, f))["degenerate_faces"]:
            tin = pymeshfix.PyTMesh()
            tin.set_quiet(True)
            tin.load_array(v, f.astype(np.int32))
            tin.strong_degeneracy_removal(3)
            v2, f2 = (np.asarray(a) for a in tin.return_arrays())
            if mesh_stats(Mesh(v2, f2))["boundary_loops"] <= mesh_stats(Mesh(v, f))["boundary_loops"]:
                v, f = v2, f2
        return v, f


@REPAIR.register("meshlab")
class MeshLab:
    """A MeshLab (pymeshlab) filter chain covering MeshFix's steps, each switchable. It merges duplicate or
    close vertices, removes duplicate and null faces, repairs non-manifold edges and vertices, removes small
    components and orients coherently. It then loops, up to ``max_rounds`` times: delete the self-intersecting
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
        min_component_diag: float = 0.5
        """Remove components whose bounding-box diagonal is below this share of the mesh's (0: keep all)."""
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
        if p.min_component_diag > 0:
            ms.meshing_remove_connected_component_by_diameter(
                mincomponentdiag=pymeshlab.PercentageValue(100 * p.min_component_diag))
        ms.meshing_remove_unreferenced_vertices()

    def _close(self, ms, prevent: bool) -> None:
        import pymeshlab

        if ms.current_mesh().face_number() == 0:
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
