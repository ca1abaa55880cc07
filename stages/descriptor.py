"""Local shape descriptors computed at keypoints. Issue 4 adds the paper's ``histogram3p``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.config import Context, Distances, to_abs
from scanreg.geometry import Cloud
from scanreg.registry import DESCRIPTOR


def to_o3d(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pc


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
        distances: Distances = Distances.spacing
        """Unit of the distances above: multiples of the sampling spacing, or absolute input units."""

    def __init__(self, params: Params):
        self.p = params

    def compute(self, cloud: Cloud, keypoints: np.ndarray, ctx: Context) -> np.ndarray:
        """(K, 33) descriptors of ``cloud.points[keypoints]``."""
        import open3d as o3d

        u, s = self.p.distances, ctx.spacing
        support = to_o3d(cloud.points, cloud.normals)
        voxel = to_abs(self.p.support_voxel, u, s)
        if voxel > 0:
            support = support.voxel_down_sample(voxel)
        kp = cloud.points[keypoints]
        both = to_o3d(np.vstack([np.asarray(support.points), kp]))
        if cloud.normals is not None:  # orient estimated normals like the given ones
            both.normals = o3d.utility.Vector3dVector(
                np.vstack([np.asarray(support.normals), cloud.normals[keypoints]])
            )
        both.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(self.p.normal_radius, u, s), max_nn=30))
        # histograms at the keypoints only (Open3D >= 0.19 computes the SPFH of their neighbourhoods alone):
        # the same values as over the whole support cloud, in about a third of the time
        n_support = len(support.points)
        feat = o3d.pipelines.registration.compute_fpfh_feature(
            both, o3d.geometry.KDTreeSearchParamHybrid(radius=to_abs(self.p.radius, u, s), max_nn=self.p.max_nn),
            o3d.utility.IntVector(np.arange(n_support, n_support + len(kp)).tolist()),
        )
        return np.asarray(feat.data).T[-len(kp):].copy()


def local_frames(points: np.ndarray, normals: np.ndarray | None, keypoints: np.ndarray, radius: float,
                 max_neighbors: int = 128) -> np.ndarray:
    """Local reference frames (K, 3, 3), rows x, y, z, from the eigenvectors of the point covariance of each
    keypoint's neighbours within ``radius``, weighted by (radius - distance) as in SHOT.

    - z is the eigenvector of the smallest eigenvalue (the surface normal), x that of the largest.
    - Signs are fixed so that the frame repeats across scans: z points along the point's normal when the cloud
      has (oriented) normals, else along the weighted mean neighbour offset; x points along the weighted mean
      neighbour offset (a continuous variant of SHOT's majority rule, which flips on ties); y = z x x. Where
      l2 ~ l3 the x axis itself is ill-defined, and the frame cannot repeat exactly.
    """
    from scanreg.stages.salience import neighbourhoods

    kp = points[keypoints]
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
        distances: Distances = Distances.spacing
        """Unit of the radii: multiples of the sampling spacing, or input units."""

    def __init__(self, params: Params):
        self.p = params

    def compute(self, cloud: Cloud, keypoints: np.ndarray, ctx: Context) -> np.ndarray:
        from scanreg.closest import estimate_normals
        from scanreg.stages.salience import neighbourhoods

        p, u, s = self.p, self.p.distances, ctx.spacing
        R = to_abs(p.radius, u, s)
        pts = cloud.points
        nrm = cloud.normals if cloud.normals is not None else estimate_normals(pts)
        frames = local_frames(pts, cloud.normals, keypoints, to_abs(p.frame_radius, u, s))
        j, d, valid = neighbourhoods(pts, R, p.max_neighbors, pts[keypoints])
        # inverse local density of every neighbour that votes
        used = np.unique(j[valid])
        _, _, vd = neighbourhoods(pts, to_abs(p.density_radius, u, s), 64, pts[used])
        dens = np.zeros(len(pts))
        dens[used] = vd.sum(axis=1)
        w = np.where(valid, (1.0 - np.minimum(d, R) / R) / np.maximum(dens[j], 1.0), 0.0)
        L = np.einsum("nkj,nij->nki", pts[j] - pts[keypoints][:, None, :], frames)   # local coordinates
        Ln = np.einsum("nkj,nij->nki", nrm[j], frames)                               # local normals
        n = len(keypoints)
        hist = np.zeros(n * 216)
        rows = np.repeat(np.arange(n), j.shape[1]).reshape(j.shape)
        for plane, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
            ua = (L[:, :, a] + R) / (2 * R / 3) - 0.5
            ub = (L[:, :, b] + R) / (2 * R / 3) - 0.5
            ang = np.arctan2(Ln[:, :, b], Ln[:, :, a])
            uo = (ang + np.pi) / (2 * np.pi / 8) - 0.5
            ia, ib, io = np.floor(ua).astype(int), np.floor(ub).astype(int), np.floor(uo).astype(int)
            fa, fb, fo = ua - ia, ub - ib, uo - io
            for da, wa in ((0, 1 - fa), (1, fa)):
                for db, wb in ((0, 1 - fb), (1, fb)):
                    ca, cb = ia + da, ib + db
                    inside = valid & (ca >= 0) & (ca < 3) & (cb >= 0) & (cb < 3)
                    for do, wo in ((0, 1 - fo), (1, fo)):
                        co = (io + do) % 8
                        wt = w * wa * wb * wo
                        m = inside & (wt > 0)
                        flat = (((rows[m] * 3 + plane) * 3 + ca[m]) * 3 + cb[m]) * 8 + co[m]
                        hist += np.bincount(flat, weights=wt[m], minlength=n * 216)
        out = hist.reshape(n, 216)
        norm = np.linalg.norm(out, axis=1, keepdims=True)
        return out / np.where(norm > 0, norm, 1.0)
