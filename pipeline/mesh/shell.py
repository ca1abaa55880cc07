"""Closing an open scan as a thin shell (``repair.open_border=shell``): the scanned surface plus an offset copy
behind it, joined along the border; watertight, manifold and free of self-intersections, with the added faces
marked (``Mesh.closure_faces``) so that samplers and evaluation use the scanned side only."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Mesh, face_normals, row_norms, submesh, vertex_normals
from scanreg.mesh.topology import _face_components, _meshset, boundary_edges, self_intersecting_faces


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
        sel = self_intersecting_faces(shell)
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


