"""Closest points on a target cloud or mesh, and normal estimation: the correspondence search that ICP, the
evaluation and the deviation map share (geometry core: imports no stage)."""

from __future__ import annotations

import numpy as np

from scanreg.geometry import Cloud, Mesh, morton_order, row_norms


class ClosestPoints:
    """Closest target points of query points: nearest target *points* (k-d tree, pykdtree), or exact closest
    points on the target's *triangles* (Open3D raycasting scene; coordinates centred before the float32
    conversion). Returns ``(closest points, distances, target normals at them or None)``."""

    last_primitive_ids: np.ndarray | None = None
    """Mesh targets: the face of each closest point of the last query."""

    def __init__(self, target: Cloud, mesh: Mesh | None = None):
        self.mesh = mesh
        self.normals = target.normals
        if mesh is not None:
            import open3d as o3d

            self.centre = mesh.vertices.mean(axis=0)
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.core.Tensor((mesh.vertices - self.centre).astype(np.float32)),
                                     o3d.core.Tensor(mesh.faces.astype(np.uint32)))
        else:
            from pykdtree.kdtree import KDTree

            # stored in Morton order: a leaf's points sit together in memory (25 % faster queries at 100k)
            order = morton_order(target.points)
            self.points = np.ascontiguousarray(target.points[order])
            self.normals = None if target.normals is None else target.normals[order]
            self.tree = KDTree(self.points, leafsize=16)

    def __call__(self, q: np.ndarray, max_distance: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Closest points; with ``max_distance`` the search is bounded (farther points get distance inf and an
        arbitrary closest point), which is what makes a k-d tree fast far from the surface."""
        if self.mesh is not None:
            import open3d as o3d

            r = self.scene.compute_closest_points(o3d.core.Tensor((q - self.centre).astype(np.float32)))
            cp = r["points"].numpy().astype(np.float64) + self.centre
            self.last_primitive_ids = r["primitive_ids"].numpy().astype(np.int64)
            return cp, row_norms(q - cp), r["primitive_normals"].numpy().astype(np.float64)
        if max_distance is None:
            d, j = self.tree.query(np.ascontiguousarray(q), k=1)
        else:
            d, j = self.tree.query(np.ascontiguousarray(q), k=1, distance_upper_bound=max_distance)
            j = np.minimum(j, len(self.points) - 1)
        return self.points.take(j, axis=0), d, None if self.normals is None else self.normals.take(j, axis=0)


def estimate_normals(points: np.ndarray, k: int = 20) -> np.ndarray:
    """Unit normals from the ``k`` nearest neighbours (Open3D), unoriented."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    return np.asarray(pc.normals).copy()
