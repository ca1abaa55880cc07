"""``data=views``: a scan set rendered from a closed model, as a range scanner would see it from many sides."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scanreg.geometry import Mesh, bbox_diagonal
from scanreg.io import expand_path, read_mesh, resolve_path
from scanreg.stages.data.base import Provider
from scanreg.stages.registry import DATA
from scanreg.types import RunContext, ScanSet


@DATA.register("views")
class Views(Provider):
    """Range scans of a mesh from ``n_views`` cameras spread over a sphere around it (a Fibonacci lattice turned
    by a seeded rotation): each view a pinhole camera's depth image, ray-cast on the mesh, with noise along the
    rays, without the surfaces seen at grazing angles, and triangulated over its pixel grid where neighbouring
    depths are continuous, as a range scanner's mesh. Each scan is in its camera's frame (x right, y down, z
    along the view); the cameras' poses are the ground truth and the mesh the reference surface. The default
    mesh is pymeshlab's closed Stanford bunny (about 0.6 across)."""

    @dataclass
    class Params:
        mesh: str = "pkg:pymeshlab/tests/sample_meshes/bunny.obj"
        """The model to scan (path, ``pkg:`` or ``shared:`` name); closed, so that every side can be seen."""
        n_views: int = 20
        """Number of scans."""
        pixels: int = 160
        """Width and height of each depth image, pixels."""
        fov_deg: float = 40.0
        """The cameras' field of view, degrees; each camera stands where the model fills it."""
        noise: float = 0.2
        """Standard deviation of the depth noise, in pixel footprints at the hit (the spacing of the scan)."""
        max_incidence_deg: float = 75.0
        """Surface seen at a larger angle between its normal and the ray is not scanned (grazing views)."""
        max_edge: float = 4.0
        """Neighbouring pixels are joined by a triangle when their points lie within this many footprints
        (a jump in depth is an occluding edge, not surface)."""
        seed: int = 0
        """Seed of the cameras' turn and the noise (the YAML links it to the run's seed)."""

        def check(self):
            if self.n_views < 2:
                raise ValueError(f"n_views must be >= 2, got {self.n_views}")
            if self.pixels < 8:
                raise ValueError(f"pixels must be >= 8, got {self.pixels}")
            if not 1 < self.fov_deg < 170:
                raise ValueError(f"fov_deg must be in (1, 170), got {self.fov_deg}")
            if not 0 < self.max_incidence_deg < 90:
                raise ValueError(f"max_incidence_deg must be in (0, 90), got {self.max_incidence_deg}")

    def preflight(self) -> None:
        """The mesh file is there."""
        resolve_path(expand_path(self.p.mesh), "data.mesh")

    def load(self, ctx: RunContext) -> ScanSet:
        mesh = read_mesh(expand_path(self.p.mesh), "data.mesh")
        scans, poses = render_views(mesh, self.p)
        names = [f"view{k:02d}.ply" for k in range(len(scans))]
        for s, n in zip(scans, names):
            s.source = n
        info = {"n_scans": len(scans), "view_points_mean": float(np.mean([len(s.vertices) for s in scans]))}
        return ScanSet(scans, names, poses, "unordered", info, mesh)


def view_directions(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice), turned by a random rotation."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + np.sqrt(5)) * k
    d = np.column_stack([np.sqrt(1 - z ** 2) * np.cos(phi), np.sqrt(1 - z ** 2) * np.sin(phi), z])
    q = rng.normal(size=4)
    w, x, y, zq = q / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + zq * zq), 2 * (x * y - zq * w), 2 * (x * zq + y * w)],
                  [2 * (x * y + zq * w), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - x * w)],
                  [2 * (x * zq - y * w), 2 * (y * zq + x * w), 1 - 2 * (x * x + y * y)]])
    return d @ R.T


def camera_pose(eye: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``T_world_camera`` of a camera at ``eye`` looking at ``centre`` (z along the view, x and y across it)."""
    z = (centre - eye) / np.linalg.norm(centre - eye)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def render_views(mesh: Mesh, p: Views.Params, directions: np.ndarray | None = None,
                 ) -> tuple[list[Mesh], list[np.ndarray]]:
    """The range scans of ``mesh`` (each in its camera's frame) and the cameras' poses ``T_world_scan``; the
    cameras look from ``directions`` (unit vectors from the model's centre; default: :func:`view_directions`)."""
    import open3d as o3d

    rng = np.random.default_rng([p.seed, 303])
    centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    radius = 0.5 * bbox_diagonal(mesh.vertices)
    half = np.radians(p.fov_deg) / 2
    distance = radius / np.sin(half)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((mesh.vertices - centre).astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    # the pixel grid's rays in a camera frame: through the centres of the pixels, unit length
    u = (np.arange(p.pixels) + 0.5) / p.pixels * 2 - 1
    gx, gy = np.meshgrid(u * np.tan(half), u * np.tan(half))
    rays = np.dstack([gx, gy, np.ones_like(gx)]).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    footprint = 2 * np.tan(half) / p.pixels  # a pixel's width per unit of depth
    scans, poses = [], []
    if directions is None:
        directions = view_directions(p.n_views, rng)
    for direction in directions:
        T = camera_pose(centre + distance * direction, centre)
        world_rays = rays @ T[:3, :3].T
        origin = np.broadcast_to(T[:3, 3] - centre, world_rays.shape)
        hit = scene.cast_rays(o3d.core.Tensor(np.hstack([origin, world_rays]).astype(np.float32)))
        t = hit["t_hit"].numpy().astype(np.float64)
        normal = hit["primitive_normals"].numpy().astype(np.float64)
        seen = np.isfinite(t) & (np.abs(np.einsum("ij,ij->i", normal, world_rays)) > np.cos(np.radians(p.max_incidence_deg)))
        depth = np.where(seen, t, np.nan) + rng.normal(scale=p.noise * footprint * np.nan_to_num(t), size=t.shape)
        scans.append(grid_mesh(rays * depth[:, None], p.pixels, p.max_edge * footprint * np.nan_to_num(depth)))
        poses.append(T)
    return scans, poses


def grid_mesh(points: np.ndarray, size: int, max_edge: np.ndarray) -> Mesh:
    """A ``size`` x ``size`` grid of points (NaN where no surface) triangulated as a range scan: two triangles per
    square of pixels, each kept when its three points exist and its edges are at most ``max_edge`` (of its first
    point) long; oriented to face the camera at the origin; points in no triangle dropped."""
    idx = np.arange(size * size).reshape(size, size)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.vstack([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    ok = np.isfinite(points[faces]).all(axis=(1, 2))
    faces = faces[ok]
    tri = points[faces]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    faces = faces[edges <= max_edge[faces[:, 0]]]
    tri = points[faces]
    facing = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri[:, 0]) > 0
    faces[facing] = faces[facing][:, [0, 2, 1]]
    used, faces = np.unique(faces, return_inverse=True)
    return Mesh(points[used], faces.reshape(-1, 3).astype(np.int64), "view")
