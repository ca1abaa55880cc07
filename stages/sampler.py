"""Samplers: turn a triangle mesh into a point cloud (point clouds pass through unchanged)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.errors import ConfigError, InputError
from scanreg.geometry import (Cloud, Geometry, Mesh, barycentric_sample, estimate_spacing, to_o3d_mesh,
                              triangle_areas_normals, voxel_representatives)
from scanreg.stages.registry import SAMPLER
from scanreg.types import Distances, RunContext, to_abs


@dataclass
class CloudParams:
    cloud_voxel: Optional[float] = None
    """Voxel downsampling of point-cloud inputs (which otherwise pass through unchanged): voxel size in
    multiples of the cloud's own spacing (median nearest-neighbour distance) or in input units, see
    ``cloud_distances``; null: no downsampling."""
    cloud_distances: Distances = Distances.spacing
    """Unit of ``cloud_voxel``: ``spacing`` (the cloud's own) or ``absolute`` (input units)."""


class SamplerBase:
    """Shared by all samplers: a mesh goes to the sampler's :meth:`sample_mesh`; point-cloud inputs pass through,
    optionally voxel-downsampled."""

    p: CloudParams
    samples_faces = True
    """Whether meshes are sampled on their triangles (then a mesh without a triangle of any area is refused)."""

    def __init__(self, params):
        self.p = params

    def check(self, geometry: Geometry, label: str) -> None:
        """Raise :class:`InputError` with one line, before any work, when this sampler could sample nothing of
        ``geometry`` (named ``label``): a mesh whose every triangle has zero area, for a sampler of triangles."""
        if isinstance(geometry, Mesh) and self.samples_faces and len(geometry.faces) and \
                not (triangle_areas_normals(geometry)[0] > 0).any():
            raise InputError(f"{label}: no triangle has an area above 0 (every face is degenerate): nothing to "
                             "sample; repair=none sampler=vertices registers its vertices as points")

    def sample(self, geometry: Geometry, ctx: RunContext) -> Cloud:
        return self.sample_mesh(geometry, ctx) if isinstance(geometry, Mesh) else self.thin_cloud(geometry, ctx)

    def sample_mesh(self, mesh: Mesh, ctx: RunContext) -> Cloud:  # pragma: no cover - per sampler
        raise NotImplementedError

    def thin_cloud(self, cloud: Cloud, ctx: RunContext) -> Cloud:
        if self.p.cloud_voxel is None:
            return cloud
        own = estimate_spacing(cloud.points, ctx.rng(3))
        voxel = to_abs(self.p.cloud_voxel, self.p.cloud_distances, own)
        if not voxel > 0:
            raise ConfigError(f"sampler={self.name}: cloud_voxel must be > 0, got {self.p.cloud_voxel}")
        out = cloud.subset(voxel_representatives(cloud.points, voxel))
        out.extra["voxel"] = voxel
        return out


@SAMPLER.register("barycentric")
class Barycentric(SamplerBase):
    """Area-weighted random barycentric sampling (the paper's method), vectorised with NumPy."""

    @dataclass
    class Params(CloudParams):
        n_points: Optional[int] = 20000
        """Number of points to draw; leave null to use ``density`` instead."""
        density: Optional[float] = None
        """Points per unit area (input units squared, e.g. points/mm^2); used when ``n_points`` is null."""
        min_triangle_area: float = 0.0
        """Triangles with an area at or below this are never sampled. Absolute area in input units squared,
        or, when ``min_area_quantile`` is true, a quantile in [0, 1) of the mesh's triangle areas."""
        min_area_quantile: bool = False
        """Read ``min_triangle_area`` as a quantile of the triangle areas instead of an absolute area."""
        seed: int = 0
        """Random seed; the same seed gives the same points bit for bit."""

        def check(self):
            _check_count(self)
            if self.min_area_quantile and not 0 <= self.min_triangle_area < 1:
                raise ValueError("min_triangle_area must be in [0, 1) when min_area_quantile is true")

    def sample_mesh(self, mesh: Mesh, ctx: RunContext) -> Cloud:
        areas, _ = triangle_areas_normals(mesh)
        min_area = self.p.min_triangle_area
        if self.p.min_area_quantile:
            min_area = float(np.quantile(areas, min_area))
        n = _count(self.p, float(areas[areas > min_area].sum()), self.name)
        pts, normals, face = barycentric_sample(mesh, n, np.random.default_rng(self.p.seed), min_area)
        return Cloud(pts, normals, mesh.source, {"face": face, "skipped_faces": int((areas <= min_area).sum())})


def _check_count(p) -> None:
    if (p.n_points is None) == (p.density is None):
        raise ValueError("give exactly one of n_points and density (set the other to null)")
    if p.n_points is not None and p.n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {p.n_points}")
    if p.density is not None and not p.density > 0:
        raise ValueError(f"density must be > 0, got {p.density}")


def _count(p, area: float, name: str) -> int:
    if p.n_points is not None:
        return p.n_points
    n = int(round(p.density * area))
    if n < 1:
        raise ConfigError(f"sampler={name}: density {p.density:g} gives no point on this mesh (area {area:g})")
    return n


@SAMPLER.register("open3d_uniform")
class Open3dUniform(SamplerBase):
    """Open3D's ``sample_points_uniformly`` (area-weighted random points), for comparison."""

    @dataclass
    class Params(CloudParams):
        n_points: Optional[int] = 20000
        """Number of points to draw; leave null to use ``density`` instead."""
        density: Optional[float] = None
        """Points per unit area (input units squared); used when ``n_points`` is null."""
        seed: int = 0
        """Seed of Open3D's random generator."""

        def check(self):
            _check_count(self)

    def sample_mesh(self, mesh: Mesh, ctx: RunContext) -> Cloud:
        import open3d as o3d

        o3d.utility.random.seed(self.p.seed)
        om = to_o3d_mesh(mesh)
        pc = om.sample_points_uniformly(_count(self.p, om.get_surface_area(), self.name), use_triangle_normal=True)
        return Cloud(np.asarray(pc.points).copy(), np.asarray(pc.normals).copy(), mesh.source)


@SAMPLER.register("poisson_disk")
class PoissonDisk(SamplerBase):
    """Open3D's Poisson-disk sampling (Yuksel 2015 sample elimination): evenly spaced points."""

    @dataclass
    class Params(CloudParams):
        n_points: Optional[int] = 20000
        """Number of points to keep; leave null to use ``density`` instead."""
        density: Optional[float] = None
        """Points per unit area (input units squared); used when ``n_points`` is null."""
        init_factor: int = 5
        """Candidates drawn uniformly before elimination, as a multiple of the points kept."""
        seed: int = 0
        """Seed of Open3D's random generator."""

        def check(self):
            _check_count(self)
            if self.init_factor < 1:
                raise ValueError(f"init_factor must be >= 1, got {self.init_factor}")

    def sample_mesh(self, mesh: Mesh, ctx: RunContext) -> Cloud:
        import open3d as o3d

        o3d.utility.random.seed(self.p.seed)
        om = to_o3d_mesh(mesh)
        pc = om.sample_points_poisson_disk(_count(self.p, om.get_surface_area(), self.name),
                                           init_factor=self.p.init_factor, use_triangle_normal=True)
        return Cloud(np.asarray(pc.points).copy(), np.asarray(pc.normals).copy(), mesh.source)


@SAMPLER.register("vertices")
class Vertices(SamplerBase):
    """The mesh's own vertices, with area-weighted vertex normals (unreferenced vertices dropped)."""

    samples_faces = False

    @dataclass
    class Params(CloudParams):
        pass

    def sample_mesh(self, mesh: Mesh, ctx: RunContext) -> Cloud:
        areas, fn = triangle_areas_normals(mesh)
        vn = np.zeros_like(mesh.vertices)
        for k in range(3):
            np.add.at(vn, mesh.faces[:, k], fn * areas[:, None])
        used = np.unique(mesh.faces)
        norm = np.linalg.norm(vn[used], axis=1, keepdims=True)
        return Cloud(mesh.vertices[used], vn[used] / np.where(norm > 0, norm, 1.0), mesh.source)
