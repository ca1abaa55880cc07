"""Mesh topology and the repair audit's measurements: counts of components, borders, holes, non-manifold and
degenerate elements, MeshLab's self-intersection and non-manifold-vertex counts, and surface-to-surface distances.
Shared by the repair stages, the shell closing and the dental case (the geometry core: it imports no stage)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from scanreg.geometry import Mesh, barycentric_sample, triangle_areas_normals


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



def _face_components(mesh: Mesh) -> np.ndarray:
    """The connected component of each face (faces sharing a vertex are connected), labelled from 0."""
    f = mesh.faces
    nf, nv = len(f), len(mesh.vertices)
    adj = coo_matrix((np.ones(3 * nf), (np.repeat(np.arange(nf), 3), f.ravel())), shape=(nf, nv)).tocsr()
    return connected_components(adj @ adj.T, directed=False)[1]

