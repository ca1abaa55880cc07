"""Mesh repair backends and the mesh statistics that report what a repair changed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pipeline.config import Context
from pipeline.errors import StageError
from pipeline.geometry import Mesh
from pipeline.registry import REPAIR
from stages.sampler import triangle_areas_normals


def mesh_stats(mesh: Mesh) -> dict[str, float]:
    """Topology and size of a triangle mesh.

    ``components``: connected components of faces sharing a vertex; ``boundary_edges``: edges with one face;
    ``boundary_loops``: connected chains of boundary edges (holes and outer borders);
    ``non_manifold_edges``: edges with more than two faces; ``degenerate_faces``: faces with a repeated vertex
    or zero area; ``area`` in input units squared.
    """
    f = mesh.faces
    nv, nf = len(mesh.vertices), len(f)
    areas, _ = triangle_areas_normals(mesh)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    bnd = uniq[counts == 1]
    used = np.unique(f)
    # faces connected through shared vertices
    rows = np.repeat(np.arange(nf), 3)
    adj = coo_matrix((np.ones(3 * nf), (rows, f.ravel())), shape=(nf, nv)).tocsr()
    n_comp = connected_components(adj @ adj.T, directed=False)[0] if nf else 0
    if len(bnd):
        bv, binv = np.unique(bnd, return_inverse=True)
        g = coo_matrix((np.ones(len(bnd)), (binv.reshape(-1, 2)[:, 0], binv.reshape(-1, 2)[:, 1])),
                       shape=(len(bv), len(bv)))
        loops = connected_components(g, directed=False)[0]
    else:
        loops = 0
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    return {
        "vertices": nv,
        "faces": nf,
        "unreferenced_vertices": nv - len(used),
        "components": int(n_comp),
        "boundary_edges": int(len(bnd)),
        "boundary_loops": int(loops),
        "non_manifold_edges": int((counts > 2).sum()),
        "degenerate_faces": int((repeated | (areas <= 0)).sum()),
        "area": float(areas.sum()),
    }


@REPAIR.register("none")
class NoRepair:
    """Leave meshes as they are (their statistics are still reported)."""

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def run(self, mesh: Mesh, ctx: Context) -> Mesh:
        return mesh


@REPAIR.register("meshfix")
class MeshFix:
    """MeshFix (Attene 2010) through pymeshfix: keep the largest component (or join components), fix
    connectivity and orientation, remove degenerate and self-intersecting triangles, fill holes."""

    @dataclass
    class Params:
        keep_largest: bool = True
        """Remove all but the largest connected component before repairing."""
        join_components: bool = False
        """Try to join nearby open components instead of dropping them."""
        fill_holes: bool = True
        """Fill boundary loops (holes)."""
        max_hole_edges: int = 0
        """Fill only holes with at most this many boundary edges (0: every hole). The outer border of an open
        scan is a hole too: set a limit to keep it open."""
        refine: bool = True
        """Refine the patches that fill holes so that their triangles match the surrounding size."""
        clean_iterations: int = 10
        """Maximum iterations of MeshFix's degeneracy and self-intersection removal."""

    def __init__(self, params: Params):
        self.p = params

    def run(self, mesh: Mesh, ctx: Context) -> Mesh:
        import pymeshfix

        tin = pymeshfix.PyTMesh()
        tin.set_quiet(not ctx.verbose if ctx else True)
        tin.load_array(mesh.vertices, mesh.faces.astype(np.int32))
        if self.p.join_components:
            tin.join_closest_components()
        if self.p.keep_largest:
            tin.remove_smallest_components()
        if self.p.fill_holes:
            tin.fill_small_boundaries(nbe=self.p.max_hole_edges, refine=self.p.refine)
        tin.clean(max_iters=self.p.clean_iterations, inner_loops=3)
        v, f = tin.return_arrays()
        if len(f) == 0:
            raise StageError(f"repair=meshfix: {mesh.source or 'mesh'}: MeshFix removed every face")
        return Mesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), mesh.source)
