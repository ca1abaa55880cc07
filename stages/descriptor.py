"""Local shape descriptors computed at keypoints: FPFH (Open3D) and the paper's 3-plane histogram."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.geometry import Cloud, estimate_normals, far_offset, neighbourhoods, orient_normals, to_o3d
from scanreg.stages.registry import DESCRIPTOR
from scanreg.types import Distances, to_abs


FLIP_ORDER = np.r_[np.arange(10, -1, -1), np.arange(11, 22), np.arange(32, 21, -1)]
"""FPFH's 33 bins as the same point's histogram with its normals turned over has them (:meth:`FPFH.flipped`)."""


@DESCRIPTOR.register("fpfh")
class FPFH:
    """Fast Point Feature Histograms (Rusu 2009, Open3D), 33 bins, over a voxel-downsampled support cloud."""

    @dataclass
    class Params:
        radius: float = 15.0
        """Support radius of the histogram (see ``distances``)."""
        max_nn: int = 100
        """At most this many neighbours within the radius."""
        normal_radius: float = 6.0
        """Radius for normal estimation on the support cloud (see ``distances``)."""
        support_voxel: float = 3.0
        """Voxel size of the support cloud the histograms are built from (see ``distances``); 0 uses every
        point of the cloud."""
        orient_normals: bool = True
        """For a cloud without normals: give the estimated normals consistent signs, on the outer side of the
        surface (:func:`scanreg.geometry.orient_normals`), as FPFH needs the same side in both scans; false:
        the signs the estimation leaves (arbitrary, as in Open3D's recipe). A cloud with normals has its
        estimated normals turned to them either way."""
        distances: Distances = Distances.spacing
        """Unit of the distances above: multiples of the sampling spacing, or absolute input units."""

    def __init__(self, params: Params):
        self.p = params

    def compute(self, cloud: Cloud, keypoints: np.ndarray, spacing: float) -> np.ndarray:
        """(K, 33) descriptors of ``cloud.points[keypoints]``."""
        import open3d as o3d

        u, s = self.p.distances, spacing
        off = far_offset(cloud.points)  # (zero near the origin)
        support = to_o3d(cloud.points - off, cloud.normals)
        voxel = to_abs(self.p.support_voxel, u, s)
        if voxel > 0:
            support = support.voxel_down_sample(voxel)
        kp = cloud.points[keypoints] - off
        both = to_o3d(np.vstack([np.asarray(support.points), kp]))
        if cloud.normals is not None:  # orient estimated normals like the given ones
            both.normals = o3d.utility.Vector3dVector(
                np.vstack([np.asarray(support.normals), cloud.normals[keypoints]])
            )
        both.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(self.p.normal_radius, u, s), max_nn=30))
        if cloud.normals is None and self.p.orient_normals:  # no sign to follow (see orient_normals)
            oriented = orient_normals(np.asarray(both.points), np.asarray(both.normals))
            both.normals = o3d.utility.Vector3dVector(oriented)
        # histograms at the keypoints only (Open3D >= 0.19 computes the SPFH of their neighbourhoods alone):
        # the same values as over the whole support cloud, in about a third of the time
        n_support = len(support.points)
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            both, o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(self.p.radius, u, s), max_nn=self.p.max_nn),
            o3d.utility.IntVector(np.arange(n_support, n_support + len(kp)).tolist()),
        )
        return np.asarray(feat.data).T[-len(kp):].copy()

    def flipped(self, descriptors: np.ndarray) -> np.ndarray | None:
        """The histograms the same keypoints have with every normal turned over: FPFH's first and third 11-bin
        features change sign with the normals (the second does not), so their bins come in reverse order
        (exact; ``tests/test_orient_normals.py``). Two clouds whose normals were estimated and oriented each on
        its own may lie on opposite sides of the surface (an open surface has no outside to agree on): the
        coarse stage matches both ways (``lo_ransac``). None when the signs are the estimation's own
        (``orient_normals`` false): no one turn relates the two clouds then."""
        if not self.p.orient_normals:
            return None
        return descriptors[:, FLIP_ORDER]


def local_frames(points: np.ndarray, normals: np.ndarray | None, keypoints: np.ndarray, radius: float,
                 max_neighbors: int = 128, neighbours: tuple | None = None) -> np.ndarray:
    """Local reference frames (K, 3, 3), rows x, y, z, from the eigenvectors of the point covariance of each
    keypoint's neighbours within ``radius``, weighted by (radius - distance) as in SHOT.

    - z is the eigenvector of the smallest eigenvalue (the surface normal), x that of the largest.
    - Signs are fixed so that the frame repeats across scans: z points along the point's normal when the cloud
      has (oriented) normals, else along the weighted mean neighbour offset; x points along the weighted mean
      neighbour offset (a continuous variant of SHOT's majority rule, which flips on ties); y = z x x. Where
      l2 ~ l3 the x axis itself is ill-defined, and the frame cannot repeat exactly.

    ``neighbours``: the keypoints' ``(indices, distances, valid)`` from
    :func:`scanreg.geometry.neighbourhoods` with a radius of at least ``radius`` and at least
    ``max_neighbors`` columns (nearest first), reused instead of a new search: its first ``max_neighbors``
    columns closer than ``radius`` are the same neighbours.
    """
    kp = points[keypoints]
    k = min(max_neighbors, len(points))
    if neighbours is not None and neighbours[0].shape[1] >= k:
        j, d, valid = (a[:, :k] for a in neighbours)
        valid = valid & (d < radius)  # neighbourhoods' bound is strict too
        j, d = np.where(valid, j, 0), np.where(valid, d, np.inf)
    else:
        j, d, valid = neighbourhoods(points, radius, max_neighbors, kp)
    w = np.where(valid, radius - np.minimum(d, radius), 0.0)
    X = points[j] - kp[:, None, :]
    C = np.einsum("nk,nki,nkj->nij", w, X, X) / np.maximum(w.sum(axis=1), 1e-300)[:, None, None]
    _, vec = np.linalg.eigh(C)
    x, z = vec[:, :, 2], vec[:, :, 0]
    sx = np.where(np.einsum("nk,nki,ni->n", w, X, x) >= 0, 1.0, -1.0)
    x = x * sx[:, None]
    if normals is not None:
        sz = np.where(np.einsum("ni,ni->n", z, normals[keypoints]) >= 0, 1.0, -1.0)
    else:
        sz = np.where(np.einsum("nk,nki,ni->n", w, X, z) >= 0, 1.0, -1.0)
    z = z * sz[:, None]
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


@DESCRIPTOR.register("histogram3p")
class Histogram3P:
    """The paper's descriptor. Each keypoint's neighbours within the support radius are expressed in its local
    reference frame (:func:`local_frames`) and projected on the frame's three coordinate planes. In each plane:
    a 3x3 grid of spatial bins x 8 orientation bins of the projected normal's angle. Each neighbour votes
    bilinearly into its 4 nearest spatial bins and its 2 nearest orientation bins, weighted by proximity
    (1 - d / radius) and by the inverse of the local sampling density. The result is 3 x 9 x 8 = 216 values,
    L2-normalised.

    Conventions (pinned by ``tests/test_paper_equations.py``): on each axis of a plane the spatial bins are 2R/3
    wide, centred at -2R/3, 0, 2R/3, and the shares are (1 - f, f) of the two nearest centres; a share that falls
    outside the 3x3 grid is dropped, not moved inside. The planes are (x, y), (y, z), (z, x) and the angle is
    atan2(second, first) of the projected normal, bins 45 degrees wide centred at -180 + 22.5 + 45 k degrees,
    wrapping around; a normal perpendicular to the plane (zero projection) gets the angle atan2(0, 0) = 0. The
    density is the count of points within ``density_radius`` (itself included, at most 64)."""

    @dataclass
    class Params:
        radius: float = 15.0
        """Support radius (see ``distances``)."""
        frame_radius: float = 10.0
        """Radius of the neighbourhood that defines the local reference frame (see ``distances``)."""
        density_radius: float = 2.0
        """Radius within which a neighbour's local density is counted (see ``distances``)."""
        max_neighbors: int = 256
        """At most this many (nearest) neighbours vote."""
        orient_normals: bool = True
        """For a cloud without normals: give the estimated normals consistent signs, on the outer side of the
        surface (:func:`scanreg.geometry.orient_normals`), and describe the cloud as one with those normals (the
        frames' z along them); false: the signs the estimation leaves, and the frames' z by the neighbours'
        offsets."""
        distances: Distances = Distances.spacing
        """Unit of the radii: multiples of the sampling spacing, or input units."""

    def __init__(self, params: Params):
        self.p = params

    def compute(self, cloud: Cloud, keypoints: np.ndarray, spacing: float) -> np.ndarray:
        from scipy.spatial import cKDTree

        p, u, s = self.p, self.p.distances, spacing
        R = to_abs(p.radius, u, s)
        pts = cloud.points
        nrm = cloud.normals if cloud.normals is not None else estimate_normals(pts)
        if cloud.normals is None and p.orient_normals:
            cloud = Cloud(pts, orient_normals(pts, nrm), cloud.source)
            nrm = cloud.normals
        # One k-d tree for both searches. scipy's cKDTree returns the same neighbours, distances and order as
        # :func:`scanreg.geometry.neighbourhoods` (pykdtree), and faster at 256 neighbours; only where
        # neighbours lie at exactly equal distances (grids, not scans) may their order, and which of them the
        # cap keeps, differ (tests/test_histogram3p_speed_equal.py).
        tree = cKDTree(pts)
        j, d, valid = _knn(tree, pts[keypoints], R, p.max_neighbors)
        fr = to_abs(p.frame_radius, u, s)
        frames = local_frames(pts, cloud.normals, keypoints, fr, neighbours=(j, d, valid) if fr <= R else None)
        # inverse local density of every neighbour that votes: its points within density_radius (strict, itself
        # included), at most 64
        used = np.zeros(len(pts), bool)
        used[j[valid]] = True
        used = np.flatnonzero(used)
        dens = np.zeros(len(pts))
        dens[used] = _count_within(tree, pts[used], to_abs(p.density_radius, u, s), 64)
        w = np.where(valid, (1.0 - np.minimum(d, R) / R) / np.maximum(dens[j], 1.0), 0.0)
        n = len(keypoints)
        count = valid.sum(axis=1)  # the valid neighbours are each row's first columns (nearest first)
        out = np.empty((n, 3, 9, 8))
        pn = np.hstack([pts, nrm])

        # Every neighbour votes w * share_a * share_b * share_o into its 2 x 2 spatial x 2 orientation bins per
        # plane. With the shares dense, (3, K) per axis and (8, K) per plane's angle (0 away from the two nearest
        # bins), a plane's 9 x 8 histogram is one matrix product over the K neighbours: (w s_a s_b) s_o^T. In
        # blocks of a few keypoints, whose temporaries stay in the cache, neighbours along the last axis.
        def block(r0):
            rs = slice(r0, r0 + step)
            K = max(int(count[rs].max()), 1)
            m = len(j[rs])
            G = pn[j[rs, :K]]                                  # (m, K, 6): neighbour points and normals
            G[:, :, :3] -= pts[keypoints[rs]][:, None, :]
            LN = np.matmul(frames[rs], G.reshape(m, 2 * K, 3).transpose(0, 2, 1))  # (m, 3, 2K) in the frame
            Lt, Nt = LN[:, :, 0::2], LN[:, :, 1::2]            # local coordinates, local normals (m, 3, K)
            S = _hat_shares((Lt + R) / (2 * R / 3) - 0.5)      # (m, 3 axes, 3 bins, K)
            wr = w[rs, None, :K]
            # orientation shares (m, 3 planes, 8 bins, K): 1 - f and f into the two nearest bins, circularly
            uo = (np.arctan2(Nt[:, [1, 2, 0]], Nt) + np.pi) / (2 * np.pi / 8) - 0.5
            lo = np.floor(uo)
            f = (uo - lo).reshape(m * 3, K)
            lo = lo.astype(np.intp).reshape(m * 3, K)
            so = np.zeros((m, 3, 8, K))
            at = (np.arange(m * 3) * (8 * K))[:, None] + np.arange(K)
            so.reshape(-1)[at + (lo & 7) * K] = 1 - f
            so.reshape(-1)[at + ((lo + 1) & 7) * K] = f
            for plane, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
                ab = ((wr * S[:, a])[:, :, None, :] * S[:, b, None, :, :]).reshape(m, 9, K)
                np.matmul(ab, so[:, plane].transpose(0, 2, 1), out=out[rs, plane])

        step = 16
        for r0 in range(0, n, step):  # one thread: on 2 shared cores, a thread pool over the blocks was slower
            block(r0)
        out = out.reshape(n, 216)
        norm = np.linalg.norm(out, axis=1, keepdims=True)
        return out / np.where(norm > 0, norm, 1.0)


def _knn(tree, queries: np.ndarray, radius: float, max_neighbors: int):
    """:func:`scanreg.geometry.neighbourhoods` on a prebuilt scipy k-d tree: the (at most
    ``max_neighbors``) nearest points closer than ``radius``, ``(indices, distances, valid)``, nearest first."""
    k = min(max_neighbors, tree.n)
    d, j = tree.query(np.ascontiguousarray(queries), k=k, distance_upper_bound=radius)
    d, j = d.reshape(len(queries), k), j.reshape(len(queries), k)
    valid = j < tree.n
    return np.where(valid, j, 0), np.where(valid, d, np.inf), valid


def _count_within(tree, queries: np.ndarray, radius: float, cap: int, first: int = 16) -> np.ndarray:
    """Points of the tree closer than ``radius`` to each query, at most ``cap``: the valid count of
    :func:`_knn` with ``cap`` neighbours. Searched for ``first`` neighbours, then for ``cap`` only where all
    ``first`` are within the radius (few: a density radius holds about a dozen points)."""
    def count(q, k):
        return (tree.query(q, k=k, distance_upper_bound=radius)[1].reshape(len(q), k) < tree.n).sum(axis=1)

    k0, k = min(first, cap, tree.n), min(cap, tree.n)
    counts = count(queries, k0)
    full = np.flatnonzero(counts == k0)
    if len(full) and k > k0:
        counts[full] = count(queries[full], k)
    return counts


_CENTRES = np.arange(3.0)[:, None]


def _hat_shares(u: np.ndarray) -> np.ndarray:
    """Bilinear shares (..., 3, K) of spatial bin coordinates ``u`` (..., K) (bin i centred at u = i): max(0,
    1 - |u - i|), i.e. the (1 - f, f) of the two nearest bins, 0 elsewhere; shares of bins outside 0..2 are
    dropped."""
    t = np.abs(u[..., None, :] - _CENTRES)
    np.subtract(1.0, t, out=t)
    return np.maximum(t, 0.0, out=t)
