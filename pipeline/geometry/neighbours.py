"""Neighbour searches: closest points on a target cloud or mesh (the correspondence search that ICP, the
evaluation and the deviation map share), fixed-radius neighbourhoods, the sampling spacing, normal estimation,
and the conversion to Open3D's point cloud."""

from __future__ import annotations

import numpy as np

from scanreg.geometry.arrays import row_norms
from scanreg.geometry.containers import Cloud, Mesh
from scanreg.geometry.voxels import morton_order


class ClosestPoints:
    """Closest target points of query points: nearest target *points* (k-d tree, pykdtree), or exact closest
    points on the target's *triangles* (Open3D raycasting scene; coordinates centred before the float32
    conversion). A call returns ``(closest points, distances, target normals at them or None)``."""

    def __init__(self, target: Cloud, mesh: Mesh | None = None):
        self.mesh = mesh
        self.normals = target.normals
        self._coherence: float | None = None  # (normal_coherence, computed on first use)
        if mesh is not None:
            import open3d as o3d

            self.centre = mesh.vertices.mean(axis=0)
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.core.Tensor((mesh.vertices - self.centre).astype(np.float32)),
                                     o3d.core.Tensor(mesh.faces.astype(np.uint32)))
        else:
            from pykdtree.kdtree import KDTree

            # the tree's points stored in Morton order: a leaf's points lie together in memory
            order = morton_order(target.points)
            self.points = np.ascontiguousarray(target.points[order])
            self.normals = None if target.normals is None else target.normals[order]
            self.tree = KDTree(self.points, leafsize=16)

    def normal_coherence(self) -> float:
        """The share of the target cloud's points whose normal agrees (cosine above 0.5) with that of their
        nearest other point (the nearest at a distance above 0, among the 3 nearest): how far its normals can
        agree with another scan's at all (clean normals 0.93-0.98 on the Stanford scans, 0.75-0.78 with noise of
        0.37 spacings); 1 without normals or points to compare. Computed once."""
        if self._coherence is None:
            if self.mesh is not None or self.normals is None or len(self.points) < 2:
                self._coherence = 1.0
            else:
                # the nearest point at a distance (a duplicated point's twin would agree with it trivially)
                k = min(4, len(self.points))
                d, j = self.tree.query(self.points, k=k)
                first = np.argmax(d > 0, axis=1)
                has = d[np.arange(len(d)), first] > 0
                other = j[np.arange(len(j)), first][has]
                cos = np.einsum("ij,ij->i", self.normals[has], self.normals.take(other, axis=0))
                self._coherence = float((cos > 0.5).mean()) if len(cos) else 1.0
        return self._coherence

    def __call__(self, q: np.ndarray, max_distance: float | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Closest points; with ``max_distance`` the search is bounded (farther points get distance inf and an
        arbitrary closest point), which is what makes a k-d tree fast far from the surface."""
        return self.query(q, max_distance)[:3]

    def query(self, q: np.ndarray, max_distance: float | None = None,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """As a call, plus the face of each closest point on a mesh target (None on a cloud)."""
        if self.mesh is not None:
            import open3d as o3d

            r = self.scene.compute_closest_points(o3d.core.Tensor((q - self.centre).astype(np.float32)))
            cp = r["points"].numpy().astype(np.float64) + self.centre
            faces = r["primitive_ids"].numpy().astype(np.int64)
            return cp, row_norms(q - cp), r["primitive_normals"].numpy().astype(np.float64), faces
        if max_distance is None:
            d, j = self.tree.query(np.ascontiguousarray(q), k=1)
        else:
            d, j = self.tree.query(np.ascontiguousarray(q), k=1, distance_upper_bound=max_distance)
            j = np.minimum(j, len(self.points) - 1)
        return self.points.take(j, axis=0), d, None if self.normals is None else self.normals.take(j, axis=0), None


def estimate_normals(points: np.ndarray, k: int = 20) -> np.ndarray:
    """Unit normals from the ``k`` nearest neighbours (Open3D), unoriented."""
    pc = to_o3d(points - far_offset(points))
    import open3d as o3d

    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    return np.asarray(pc.normals).copy()


def orient_normals(points: np.ndarray, normals: np.ndarray, k: int = 10) -> np.ndarray:
    """``normals`` (unit, signs arbitrary, as :func:`estimate_normals` gives them) with consistent signs: each
    sign propagated from one seed along the minimum spanning tree of the ``k``-nearest-neighbour graph weighted
    by ``1 - |n_i . n_j|`` (Hoppe et al. 1992: the flattest paths first, so that a sign crosses a sharp fold
    last; parts of the cloud the graph leaves apart, such as an ear beside a head, joined across their gaps,
    :func:`_joined`), then all of them turned so that they point away from the cloud's centroid on balance (the
    sum of ``n . (p - centroid)`` positive), as the outer surface of an object seen from outside does. A
    function of the points' positions (not of their pose), so that two scans of one object get normals on the
    same side of its surface, which sign-sensitive descriptors (FPFH) need. An open surface has no outside: two
    crops of it may come out on opposite sides (the coarse stage then matches both ways, ``FPFH.flipped``)."""
    from pykdtree.kdtree import KDTree
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    n = len(points)
    points = np.ascontiguousarray(points, dtype=np.float64)
    normals = np.array(normals, dtype=np.float64)
    if n < 2:
        return normals
    kk = min(k + 1, n)
    _, j = KDTree(points).query(points, k=kk)
    rows, cols = np.repeat(np.arange(n), kk - 1), j.reshape(n, kk)[:, 1:].astype(np.int64).ravel()
    rows, cols = _joined(points, normals, rows[cols != rows], cols[cols != rows])
    # weights > 0 (a zero weight is no edge to scipy): parallel normals cost a tiny constant
    w = 1.0 - np.abs(np.einsum("ij,ij->i", normals[rows], normals[cols])) + 1e-9
    g = coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(g.maximum(g.T))
    parent = breadth_first_order(tree + tree.T, 0, directed=False)[1]
    parent[0] = 0
    # a point's sign flips against its parent's where their normals disagree; its flip against the seed is the
    # parity of the flips on its path, summed by pointer jumping (about log2 of the tree's depth steps)
    flip = np.einsum("ij,ij->i", normals, normals[parent]) < 0
    for _ in range(int(np.ceil(np.log2(n))) + 1):
        flip = flip ^ flip[parent]
        parent = parent[parent]
    out = np.where(flip[:, None], -normals, normals)
    return -out if float(np.einsum("ij,ij->", out, points - points.mean(axis=0))) < 0 else out


def _joined(points: np.ndarray, normals: np.ndarray, rows: np.ndarray,
            cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The graph's edges ``rows -> cols`` and, while it falls apart in several parts, one edge from each part to
    another (Boruvka's step: the parts at least halve each round): of the part's points at most twice the
    shortest gap from another part, the one whose edge to its nearest point there carries a sign the surest,
    its two normals the most nearly parallel and the edge the most nearly in both tangent planes (the surface
    continued across the gap; not two sheets stacked, such as an ear's two sides, whose normals are parallel
    too but whose sides are opposite)."""
    from pykdtree.kdtree import KDTree
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(points)
    while True:
        n_parts, part = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                             directed=False)
        if n_parts == 1:
            return rows, cols
        if n_parts > JOIN_EXACT_PARTS:  # scattered clumps: each part's shortest edge out, from one search
            e = _shortest_edges_out(points, part)
            rows, cols = np.concatenate([rows, e[:, 0]]), np.concatenate([cols, e[:, 1]])
            continue
        extra = []
        for c in range(n_parts):
            inside = np.flatnonzero(part == c)
            outside = np.flatnonzero(part != c)
            d, j = KDTree(points[outside]).query(points[inside], k=1)
            near = np.flatnonzero(d <= 2 * d.min())
            a, b = inside[near], outside[j[near]]
            gap = points[b] - points[a]
            gap /= np.maximum(np.linalg.norm(gap, axis=1, keepdims=True), np.finfo(float).tiny)
            parallel = np.abs(np.einsum("ij,ij->i", normals[a], normals[b]))
            across = np.maximum(np.abs(np.einsum("ij,ij->i", normals[a], gap)),
                                np.abs(np.einsum("ij,ij->i", normals[b], gap)))
            best = near[np.argmax(parallel * (1.0 - across))]
            extra.append((inside[best], outside[int(j[best])]))
        e = np.array(extra, dtype=np.int64)
        rows, cols = np.concatenate([rows, e[:, 0]]), np.concatenate([cols, e[:, 1]])


JOIN_EXACT_PARTS = 64
"""Up to this many parts, each is joined by the surest of its nearly shortest edges out (one search per part);
beyond it (a cloud of scattered clumps: thousands of searches), by its shortest edge, all from one search."""


def _shortest_edges_out(points: np.ndarray, part: np.ndarray) -> np.ndarray:
    """For each part, its shortest edge (point inside, point outside) to another part, as rows (k, 2): from the
    32 nearest neighbours of every point, and for a part none of whose points has another part among them, from
    a search of the points outside it."""
    from pykdtree.kdtree import KDTree

    n = len(points)
    k = min(n, 33)
    d, j = KDTree(points).query(points, k=k)
    d, j = d.reshape(n, k), j.reshape(n, k).astype(np.int64)
    other = part[j] != part[:, None]
    first = other.argmax(axis=1)
    dist = np.where(other.any(axis=1), d[np.arange(n), first], np.inf)
    order = np.lexsort((dist, part))  # by part, shortest first
    lead = order[np.r_[True, part[order][1:] != part[order][:-1]]]
    edges = []
    for i in lead:
        if np.isfinite(dist[i]):
            edges.append((i, j[i, first[i]]))
        else:  # a part larger than the neighbourhoods: searched on its own
            inside, outside = np.flatnonzero(part == part[i]), np.flatnonzero(part != part[i])
            dd, jj = KDTree(points[outside]).query(points[inside], k=1)
            best = int(np.argmin(dd))
            edges.append((inside[best], outside[int(jj[best])]))
    return np.array(edges, dtype=np.int64).reshape(-1, 2)


def estimate_spacing(points: np.ndarray, rng: np.random.Generator, n: int = 5000) -> float:
    """Median distance from a point to its nearest other point (over a seeded subset of at most ``n``)."""
    from pykdtree.kdtree import KDTree  # the distances SciPy's tree gives, from a tree quicker to build

    idx = rng.choice(len(points), size=min(n, len(points)), replace=False) if len(points) > n else np.arange(len(points))
    d, _ = KDTree(np.ascontiguousarray(points, dtype=np.float64), leafsize=16).query(points[idx], k=2)
    d = d[:, 1]
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.0


def neighbourhoods(points: np.ndarray, radius: float, max_neighbors: int, queries: np.ndarray | None = None):
    """Neighbours within ``radius`` (at most ``max_neighbors``, the nearest): ``(indices (N, K), distances (N,
    K), valid mask (N, K))``; a point is its own neighbour."""
    from pykdtree.kdtree import KDTree

    q = points if queries is None else queries
    k = min(max_neighbors, len(points))
    d, j = KDTree(points).query(np.ascontiguousarray(q), k=k, distance_upper_bound=radius)
    d, j = d.reshape(len(q), k), j.reshape(len(q), k).astype(np.int64)
    valid = j < len(points)
    j = np.where(valid, j, 0)
    return j, np.where(valid, d, np.inf), valid


FAR_FROM_ORIGIN = 100.0
"""Points whose bounding box's centre lies more than this many of its diagonals from the origin are moved near
the origin before Open3D estimates normals, FPFH histograms or ISS keypoints of them (:func:`far_offset`)."""


def far_offset(points: np.ndarray) -> np.ndarray:
    """What to subtract from ``points`` before Open3D's normals, FPFH histograms or ISS keypoints are computed of
    them: their bounding box's centre when that lies more than :data:`FAR_FROM_ORIGIN` diagonals from the origin,
    else zero. Open3D sums coordinates and their products to form a neighbourhood's covariance, which loses
    the neighbourhood's shape to rounding far from the origin (survey or UTM coordinates: a bunny at 4.2e6 m
    registered 139 deg off); these results do not depend on where the points are, and points near the origin
    are handed over unchanged, bit for bit."""
    if not len(points):
        return np.zeros(3)
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    if float(np.linalg.norm(centre)) > FAR_FROM_ORIGIN * max(float(np.linalg.norm(hi - lo)), 1e-300):
        return centre
    return np.zeros(3)


def to_o3d(points: np.ndarray, normals: np.ndarray | None = None):
    """An Open3D ``PointCloud`` of ``points`` (and ``normals``)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pc


def to_o3d_mesh(mesh: Mesh):
    """An Open3D ``TriangleMesh`` of ``mesh``, with its triangle normals."""
    import open3d as o3d

    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    om.compute_triangle_normals()
    return om
