"""Geometry containers and rigid-transform helpers.

Conventions: points are ``(N, 3)`` float64 arrays in the input's units; a transform ``T_a_b`` is a 4x4
matrix mapping points given in frame ``b`` into frame ``a`` (``p_a = R p_b + t``). Functions that relate two
point sets take ``(target, source)`` in that order and return ``T_target_source``.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.errors import InputError


@dataclass
class Mesh:
    """Triangle mesh: ``vertices`` (N, 3) float64, ``faces`` (M, 3) int64 (counter-clockwise = outward)."""

    vertices: np.ndarray
    faces: np.ndarray
    source: str = ""
    """Where it came from (path or description), for messages."""
    closure_faces: int = 0
    """The last this-many faces were added to close an open scan into a thin shell (``repair.open_border=shell``):
    they are not scanned surface, and :meth:`scanned` leaves them out."""

    @property
    def n_points(self) -> int:
        return len(self.vertices)

    def scanned(self) -> "Mesh":
        """The mesh without its closure faces (and the vertices only they use): what samplers and the
        evaluation see."""
        if not self.closure_faces:
            return self
        keep = np.arange(len(self.faces)) < len(self.faces) - self.closure_faces
        return submesh(self, keep)


def submesh(mesh: Mesh, face_mask: np.ndarray | None = None) -> Mesh:
    """The faces where ``face_mask`` holds (every face when None), without the vertices no kept face uses."""
    f = mesh.faces if face_mask is None else mesh.faces[face_mask]
    used, inv = np.unique(f, return_inverse=True)
    return Mesh(mesh.vertices[used], inv.reshape(-1, 3).astype(np.int64), mesh.source)


@dataclass
class Cloud:
    """Point cloud with optional unit normals (N, 3)."""

    points: np.ndarray
    normals: np.ndarray | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def subset(self, idx) -> "Cloud":
        """The points (and normals, and per-point ``extra`` arrays such as colours) at ``idx`` (indices, a mask or
        a slice), in that order."""
        n = len(self.points)
        extra = {k: v[idx] for k, v in self.extra.items() if isinstance(v, np.ndarray) and len(v) == n}
        return Cloud(self.points[idx], None if self.normals is None else self.normals[idx], self.source, extra)


Geometry = Mesh | Cloud


def points_of(g: Geometry) -> np.ndarray:
    return g.vertices if isinstance(g, Mesh) else g.points


def validate_points(pts: np.ndarray, what: str) -> np.ndarray:
    """Check a coordinate array: (N, 3), non-empty, finite. Returns it as contiguous float64."""
    pts = np.asarray(pts)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{what}: expected N x 3 coordinates, got an array of shape {pts.shape}")
    if len(pts) == 0:
        raise InputError(f"{what}: contains no points")
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    bad = ~rows_all(np.isfinite(pts))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{what}: {int(bad.sum())} point(s) with NaN or infinite coordinates (first: index {i})")
    return pts


def validate_mesh(mesh: Mesh) -> Mesh:
    what = mesh.source or "mesh"
    v = validate_points(mesh.vertices, what)
    f = np.asarray(mesh.faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"{what}: expected M x 3 triangle indices, got an array of shape {f.shape}")
    if len(f) == 0:
        raise InputError(f"{what}: mesh has no faces")
    f = f.astype(np.int64, copy=False)
    if f.min() < 0 or f.max() >= len(v):
        bad = int(rows_any((f < 0) | (f >= len(v))).sum())
        raise InputError(
            f"{what}: {bad} face(s) index missing vertices (indices must be in 0..{len(v) - 1}, found {f.min()}..{f.max()})"
        )
    return Mesh(v, np.ascontiguousarray(f), mesh.source)


def bbox_diagonal(pts: np.ndarray) -> float:
    return float(np.linalg.norm(col_max(pts) - col_min(pts)))


# ----------------------------------------------------------------------------------------------- transforms


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


@contextlib.contextmanager
def blas_single_thread():
    """Run the block with OpenBLAS on one thread. The numpy products of an ICP or RANSAC loop are small (N x 3);
    between them OpenBLAS's idle threads spin and take the cores from the k-d tree's and Open3D's OpenMP
    threads (measured: an ICP iteration at 100k points 66 ms with threaded BLAS, 35 ms without)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays; same values as ``np.cross``, about 5x faster."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def row_norms(a: np.ndarray) -> np.ndarray:
    """Euclidean norms along the last axis, of length 3, of any array: 4x faster than
    ``np.linalg.norm(a, axis=-1)``, whose reduction over 3 elements is slow."""
    return np.sqrt(a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2])


# NumPy reduces a (N, k) array along a short axis (``a.min(axis=0)``, ``b.any(axis=1)``) 5-15x slower than it
# reduces its k columns one by one; these give the same values (min, max, any and all do not depend on order).

def col_min(a: np.ndarray) -> np.ndarray:
    """``a.min(axis=0)`` of a non-empty (N, k) array."""
    return np.array([a[:, k].min() for k in range(a.shape[1])], dtype=a.dtype)


def col_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=0)`` of a non-empty (N, k) array."""
    return np.array([a[:, k].max() for k in range(a.shape[1])], dtype=a.dtype)


def rows_any(a: np.ndarray) -> np.ndarray:
    """``a.any(axis=1)`` of a (N, k) array, k >= 1."""
    out = a[:, 0].astype(bool)
    for k in range(1, a.shape[1]):
        out |= a[:, k].astype(bool, copy=False)
    return out


def rows_all(a: np.ndarray) -> np.ndarray:
    """``a.all(axis=1)`` of a (N, k) array, k >= 1."""
    out = a[:, 0].astype(bool)
    for k in range(1, a.shape[1]):
        out &= a[:, k].astype(bool, copy=False)
    return out


def apply_T(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def rotate_normals(T: np.ndarray, normals: np.ndarray | None) -> np.ndarray | None:
    return None if normals is None else normals @ T[:3, :3].T


def transform_geometry(T: np.ndarray, g: Geometry) -> Geometry:
    if isinstance(g, Mesh):
        return Mesh(apply_T(T, g.vertices), g.faces, g.source)
    return Cloud(apply_T(T, g.points), rotate_normals(T, g.normals), g.source, dict(g.extra))


def invert_T(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (robust near 0 and 180)."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(s, np.clip(c, -1.0, 1.0))))


def transform_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in input units) of ``T_est`` against ``T_gt``."""
    dR = T_est[:3, :3] @ T_gt[:3, :3].T
    return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


def random_pose(rng: np.random.Generator, max_angle_deg: float, max_translation: float,
                min_angle_deg: float = 0.0) -> np.ndarray:
    """A random rigid transform: rotation about a uniformly random axis by an angle uniform in
    [min_angle_deg, max_angle_deg] (``max_angle_deg >= 180``: a rotation uniform over SO(3)), translation a
    uniformly random direction times a length uniform in [0, max_translation]."""
    if max_angle_deg >= 180.0:
        R = Rotation.from_quat(_unit(rng.normal(size=4))).as_matrix()
    else:
        axis = _unit(rng.normal(size=3))
        R = Rotation.from_rotvec(axis * np.radians(rng.uniform(min_angle_deg, max_angle_deg))).as_matrix()
    t = _unit(rng.normal(size=3)) * rng.uniform(0.0, max_translation)
    return make_T(R, t)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def horn_quaternion(target: np.ndarray, source: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform ``T_target_source`` by Horn's closed form (1987).

    With centred point sets and the cross-covariance ``S = sum w (s - s̄)(t - t̄)^T``, the rotation is the unit
    quaternion of the largest eigenvalue of the symmetric 4x4 matrix ``Q(S)``; then ``t = t̄ - R s̄``.
    """
    if len(target) != len(source) or len(source) < 3:
        raise ValueError("horn_quaternion needs at least 3 paired points")
    # means and sums as BLAS products: np.mean(axis=0) on (N, 3) arrays is 20x slower
    if weights is None:
        one = np.full(len(source), 1.0 / len(source))
        mu_s, mu_t = one @ source, one @ target
        S = (source - mu_s).T @ (target - mu_t)
    else:
        w = np.asarray(weights, dtype=np.float64)
        wsum = w.sum()
        mu_s = (w @ source) / wsum
        mu_t = (w @ target) / wsum
        S = ((source - mu_s) * w[:, None]).T @ (target - mu_t)
    R = rotation_from_cross_covariance(S)
    return make_T(R, mu_t - R @ mu_s)


def rotation_from_cross_covariance(S: np.ndarray) -> np.ndarray:
    """Horn's quaternion solution: the rotation R maximising trace(R S) for S = sum (s_i)(t_i)^T."""
    (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = S
    Q = np.array(
        [
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ]
    )
    evals, evecs = np.linalg.eigh(Q)
    q0, qx, qy, qz = evecs[:, np.argmax(evals)]
    return np.array(
        [
            [q0 * q0 + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - q0 * qz), 2 * (qx * qz + q0 * qy)],
            [2 * (qy * qx + q0 * qz), q0 * q0 - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - q0 * qx)],
            [2 * (qz * qx - q0 * qy), 2 * (qz * qy + q0 * qx), q0 * q0 - qx * qx - qy * qy + qz * qz],
        ]
    )


def rigid_points_normals(target, source, target_normals=None, source_normals=None, normal_weight: float = 1.0):
    """``T_target_source`` minimising sum |R s + t - t_i|^2 + w |R n_s - n_t|^2 (closed form: the normals
    only add ``w sum n_s n_t^T`` to the cross-covariance; t from the centroids)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    S = (source - mu_s).T @ (target - mu_t)
    if target_normals is not None and source_normals is not None and normal_weight > 0:
        S = S + normal_weight * source_normals.T @ target_normals
    R = rotation_from_cross_covariance(S)
    return make_T(R, mu_t - R @ mu_s)


def kabsch_batch(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Batched least-squares rigid transforms: ``target, source`` (B, k, 3) -> ``T_target_source`` (B, 4, 4)."""
    mu_s, mu_t = source.mean(axis=1, keepdims=True), target.mean(axis=1, keepdims=True)
    H = np.einsum("bki,bkj->bij", source - mu_s, target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", Vt, U)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    R = np.einsum("bji,bjk,blk->bil", Vt, D, U)
    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_t[:, 0] - np.einsum("bij,bj->bi", R, mu_s[:, 0])
    T[:, 3, 3] = 1.0
    return T


def kabsch_svd(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform ``T_target_source`` by SVD (Kabsch/Umeyama), for cross-checks."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    H = (source - mu_s).T @ (target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, mu_t - R @ mu_s)


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """Insert two zero bits after each of the low 21 bits of ``x`` (uint64), for 3-D Morton codes."""
    x = x & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation that sorts points along a Morton (Z-order) curve of a 2^bits grid over their bounding box
    (bits <= 21). Queries issued in this order, and a k-d tree built on points stored in this order, hit memory
    coherently (together about 40 % faster ICP iterations at 100k points)."""
    lo = col_min(points)
    q = ((points - lo) / ((col_max(points) - lo).max() + 1e-300) * (2**bits - 1)).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | (_spread_bits(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


LOCALITY_SPAN = 1024
""":func:`locality_ordered` renumbers a mesh whose faces' vertex indices lie further apart than this many
vertices (the median over the faces of the largest difference between a face's vertex indices)."""


def locality_ordered(vertices: np.ndarray, faces: np.ndarray,
                     span: int = LOCALITY_SPAN) -> tuple[np.ndarray, np.ndarray]:
    """The mesh renumbered for memory locality when its vertex order is scattered: the vertices in Morton order
    (:func:`morton_order`), the faces by their smallest new vertex index (stable); unchanged (the same arrays)
    when the faces' vertices are already near one another in the order (a median span of at most ``span``
    vertices, see :data:`LOCALITY_SPAN`: a range scan's rows, a mesh written face by face). The same surface
    either way, renumbered only.

    For a library that builds a linked mesh from the arrays in their order (MeshFix allocates its vertices,
    edges and triangles one by one), this puts neighbours near one another in memory. pymeshfix's
    StanfordBunny.ply (median span 22 640 of 50 000 vertices) repairs 25 % faster renumbered (0.91 -> 0.68 s,
    the same triangles out); the raw Stanford scans (span 160-250) are left as they are: renumbering them
    made MeshFix's hole filling slower, not faster (experiments/benchmarks/repair_speed.md)."""
    f = np.asarray(faces, dtype=np.int64)  # (differences of unsigned indices would wrap around)
    if not len(f):
        return vertices, faces
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    spread = np.maximum(np.maximum(np.abs(a - b), np.abs(b - c)), np.abs(c - a))
    if np.median(spread) <= span:
        return vertices, faces
    order = morton_order(vertices)
    new = np.empty_like(order)
    new[order] = np.arange(len(order))
    g = new[f]
    return vertices[order], g[np.argsort(g.min(axis=1), kind="stable")]


def face_normals(mesh: Mesh, unit: bool = True) -> np.ndarray:
    """Face normals (M, 3) by the right-hand rule (counter-clockwise = outward); area-weighted unless ``unit``."""
    v, f = mesh.vertices, mesh.faces
    n = cross3(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(row_norms(n)[:, None], 1e-300) if unit else n


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """Unit vertex normals: the area-weighted mean of the normals of the faces around each vertex."""
    fn = face_normals(mesh, unit=False)
    n = np.zeros_like(mesh.vertices)
    for k in range(3):
        np.add.at(n, mesh.faces[:, k], fn)
    return n / np.maximum(row_norms(n)[:, None], 1e-300)


def triangle_areas_normals(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per-face areas and unit normals (counter-clockwise winding = outward); degenerate faces get area 0."""
    v, f = mesh.vertices, mesh.faces
    cross = cross3(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
    return 0.5 * norm, normals


def barycentric_sample(
    mesh: Mesh, n_points: int, rng: np.random.Generator, min_area: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted random points on a mesh: ``(points, normals, face index)``.

    Each point falls on a triangle with probability proportional to its area (triangles with area <=
    ``min_area`` never): the per-triangle counts are drawn at once from the multinomial distribution, which is
    the same law as ``n_points`` independent area-weighted draws. On its triangle a point is
    ``a + u (b - a) + v (c - a)`` with ``u, v ~ U(0, 1)``, reflected to ``1 - u, 1 - v`` when ``u + v > 1``. The
    normal is the triangle's. Points come grouped by triangle (in face order).
    """
    v, f = mesh.vertices, mesh.faces
    a = v[f[:, 0]]
    e1, e2 = v[f[:, 1]] - a, v[f[:, 2]] - a
    cross = np.cross(e1, e2)
    norm = np.sqrt(np.einsum("ij,ij->i", cross, cross))
    drawn = area_weighted_draws(np.where(0.5 * norm > min_area, norm, 0.0), n_points, rng)
    if drawn is None:
        raise InputError(f"{mesh.source or 'mesh'}: no triangle has an area above {min_area:g}: nothing to sample")
    face, uv = drawn
    normals = cross / np.where(norm > 0, norm, 1.0)[:, None]
    return points_on_faces(mesh, face, uv, (a, e1, e2)), normals[face], face


def area_weighted_draws(weights: np.ndarray, n_points: int,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`barycentric_sample`'s random draws: each point's face, drawn with probability proportional to
    ``weights`` (per-face counts from the multinomial, faces in order), and its ``(u, v)`` (N, 2), uniform and
    reflected to ``(1 - u, 1 - v)`` when ``u + v > 1``. None when no weight is positive."""
    total = math.fsum(weights)
    if not total > 0:
        return None
    counts = rng.multinomial(n_points, weights / total)
    face = np.repeat(np.arange(len(weights)), counts)
    uv = rng.random((n_points, 2))
    flip = uv[:, 0] + uv[:, 1] > 1.0
    uv[flip] = 1.0 - uv[flip]
    return face, uv


def points_on_faces(mesh: Mesh, face: np.ndarray, uv: np.ndarray,
                    edges: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The points ``a + u (b - a) + v (c - a)`` on the faces ``face`` (corners a, b, c) at ``uv`` (N, 2).
    ``edges``: every face's ``(a, b - a, c - a)`` when already computed (then gathered per point, the same
    values: many points per face are cheaper so than subtracting per point)."""
    if edges is None:
        v, f = mesh.vertices, mesh.faces[face]
        a = v[f[:, 0]]
        e1, e2 = v[f[:, 1]] - a, v[f[:, 2]] - a
    else:
        a, e1, e2 = (x[face] for x in edges)
    pts = a  # a fresh array (gathered), added to in place
    pts += uv[:, :1] * e1
    pts += uv[:, 1:] * e2
    return pts


def voxel_cells(points: np.ndarray, voxel: float, margin: int = 0) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """The cell of each point on a grid of edge ``voxel`` (input units) anchored at the points' minimum corner,
    with ``margin`` empty cells on every side: ``(flat, keys, span)``, ``keys`` the (N, 3) integer cells,
    ``span`` the grid's size in cells, and ``flat`` one int64 per cell ordered as the (x, y, z) rows are
    lexicographically (the same groups in the same order as ``np.unique(keys, axis=0)``, about 50x faster on a
    million points), or None when the grid has too many cells for a 62-bit index."""
    if len(points) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.ones(3, np.int64)
    keys = np.floor((points - col_min(points)) / voxel).astype(np.int64) + margin
    span = col_max(keys) + 1 + margin
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0 ** 62:
        return None, keys, span
    return (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2], keys, span


def voxel_groups(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells of :func:`voxel_cells`' grid in key order: each point's cell number and each cell's
    point count, ``(inv (N,), counts (cells,))``."""
    flat, keys, _ = voxel_cells(points, voxel)
    if flat is not None:
        _, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    else:
        _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return inv.ravel(), counts


def voxel_occupancy(points: np.ndarray, voxel: float) -> np.ndarray:
    """For each point, how many points (itself included) fall in its cell of a grid of edge ``voxel`` (input units)
    anchored at the points' minimum corner: the grid :func:`scanreg.stages.salience.voxel_representatives` thins
    with."""
    inv, counts = voxel_groups(points, voxel)
    return counts[inv]


def sparse_voxel_mask(points: np.ndarray, voxel: float, ratio: float, near: float | None = None) -> np.ndarray:
    """Which points to keep, dropping isolated ones (outliers scattered through the volume), on a grid of edge
    ``voxel`` (input units). A full cell holds ``full`` points, the 90th percentile of the points' cell counts
    (:func:`voxel_occupancy`; counted per point, it is a surface cell's count while fewer than about 85 % of the
    points are outliers). A cell is sparse when it holds fewer than ``ratio * full`` points, and its points are
    dropped when its 3 x 3 x 3 block of cells (itself and its 26 neighbours) holds fewer than ``2 * full`` points
    too: a sampled surface fills its cells alike and a sparse cell at its border or where it grazes a cell's
    corner has full neighbours, while an outlier sits alone in an empty block. Voxel thinning would give each
    outlier a representative of its own. With ``near`` (input units), a point of a sparse cell whose block is
    full enough is dropped still when no other point lies within ``near`` of it: an outlier floating a few
    cells off the surface, where a point at the surface's border has neighbours one spacing away. A cloud
    whose full cells hold fewer than ``1 / ratio`` points (a sparse cloud) keeps every point, and so does one
    too large for a 62-bit cell index."""
    n = len(points)
    keep = np.ones(n, bool)
    if n == 0:
        return keep
    flat, _, span = voxel_cells(points, voxel, margin=1)  # a margin for the neighbours
    if flat is None:
        return keep
    cells, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    full = float(np.quantile(counts[inv], 0.9))  # voxel_occupancy's counts
    sparse = np.flatnonzero(counts < ratio * full)
    if not len(sparse):
        return keep
    c = cells[sparse]
    cx, rest = np.divmod(c, span[1] * span[2])
    cy, cz = np.divmod(rest, span[2])
    o = np.arange(-1, 2)
    ox, oy, oz = (a.ravel() for a in np.meshgrid(o, o, o, indexing="ij"))
    nb = ((cx[:, None] + ox) * span[1] + cy[:, None] + oy) * span[2] + cz[:, None] + oz  # (sparse, 27)
    pos = np.minimum(np.searchsorted(cells, nb), len(cells) - 1)
    block = np.where(cells[pos] == nb, counts[pos], 0).sum(axis=1)
    drop = np.zeros(len(cells), bool)
    drop[sparse[block < 2 * full]] = True
    keep = ~drop[inv]
    if near is not None:
        sparse_cell = np.zeros(len(cells), bool)
        sparse_cell[sparse] = True
        ask = np.flatnonzero(sparse_cell[inv] & keep)
        if len(ask):
            from scipy.spatial import cKDTree

            tree = cKDTree(points, leafsize=32, balanced_tree=False, compact_nodes=False)  # builds 2x faster
            d = tree.query(points[ask], k=2, distance_upper_bound=near)[0][:, 1]  # inf beyond near
            keep[ask[d > near]] = False
    return keep
