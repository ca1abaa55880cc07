"""Surface reconstruction (``surface=NAME``): one mesh from the merged points of a registered scan set."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.geometry import Cloud, Mesh, estimate_normals, orient_normals, principal_axes, to_o3d
from scanreg.stages.registry import SURFACE
from scanreg.types import RunContext


@SURFACE.register("poisson")
class Poisson:
    """Screened Poisson reconstruction (Kazhdan & Hoppe 2013, Open3D's) of the merged points and their normals:
    a closed surface through the scans, where the scans saw nothing a smooth continuation. The scan set's run
    then repairs it with the configured repair backend (MeshFix: one closed, manifold mesh without
    self-intersections) and measures it."""

    @dataclass
    class Params:
        resolution: float = 3.0
        """The finest octree cell, in sampling spacings: the octree's depth is the one whose cells come nearest
        this (within a factor of 1.41), measured over the points' largest extent along their principal axes (so
        the same in any pose; between ``min_depth`` and ``max_depth``). Finer cells add faces, not shape."""
        min_depth: int = 5
        """The shallowest octree (2^depth cells across the reconstruction's cube)."""
        max_depth: int = 10
        """The deepest octree: bounds the time and memory of a large model scanned finely."""
        trim_quantile: float = 0.0
        """Remove the vertices whose point density is below this quantile of all vertices' (0..1): surface
        extrapolated far from any scan. The holes this opens are closed by the repair; 0: no trimming."""
        scale: float = 1.1
        """The reconstruction's cube over the points' bounding box (Open3D's ``scale``)."""
        when: str = "meshes"
        """``meshes``: only when the scans were meshes (a cloud set gives merged points only); ``always`` (clouds
        without normals: from normals estimated on the merged points, turned outward)."""

        def check(self):
            if self.when not in ("meshes", "always"):
                raise ValueError(f"when must be meshes or always, got '{self.when}'")
            if not 0 <= self.trim_quantile < 1:
                raise ValueError(f"trim_quantile must be in [0, 1), got {self.trim_quantile}")
            if not 1 <= self.min_depth <= self.max_depth <= 14:
                raise ValueError(f"need 1 <= min_depth <= max_depth <= 14, got {self.min_depth}, {self.max_depth}")
            if not self.resolution > 0 or not self.scale >= 1:
                raise ValueError(f"resolution must be > 0 and scale >= 1, got {self.resolution}, {self.scale}")

    def __init__(self, params: Params):
        self.p = params

    def depth(self, points: np.ndarray, spacing: float) -> int:
        """The octree depth for ``points`` sampled ``spacing`` apart (see ``resolution``)."""
        centre, axes = principal_axes(points)
        return self._depth((points - centre) @ axes, spacing)

    def _depth(self, local: np.ndarray, spacing: float) -> int:
        """:meth:`depth` of points given in their principal frame (``local``)."""
        extent = self.p.scale * float(np.ptp(local, axis=0).max())
        cells = extent / (self.p.resolution * spacing) if spacing > 0 else 2.0 ** self.p.max_depth
        return int(np.clip(np.round(np.log2(max(cells, 1.0))), self.p.min_depth, self.p.max_depth))

    def reconstruct(self, points: Cloud, from_meshes: bool, spacing: float, ctx: RunContext) -> Optional[Mesh]:
        """The Poisson surface of ``points`` (None for clouds with ``when: meshes``; points without normals get
        estimated ones, turned outward, :func:`scanreg.geometry.orient_normals`): its largest connected part (the
        solver leaves small closed bubbles where the points are sparse)."""
        import open3d as o3d

        if self.p.when == "meshes" and not from_meshes:
            return None
        if points.n_points < 10:
            return None
        normals = points.normals
        if normals is None:  # clouds without normals (when: always): estimated, outward (the merged model's outside)
            normals = orient_normals(points.points, estimate_normals(points.points))
        # the octree laid in the points' principal frame, so that the surface does not depend on the pose of the
        # world scan (in the world frame its cube would span whatever bounding box that pose gives)
        centre, axes = principal_axes(points.points)
        local = (points.points - centre) @ axes
        pc = to_o3d(local, normals @ axes)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pc, depth=self._depth(local, spacing), scale=self.p.scale, linear_fit=False, n_threads=1)
        if self.p.trim_quantile > 0:
            density = np.asarray(density)
            mesh.remove_vertices_by_mask(density < np.quantile(density, self.p.trim_quantile))
        if not len(mesh.triangles):
            return None
        part, sizes, _ = mesh.cluster_connected_triangles()
        mesh.remove_triangles_by_mask(np.asarray(part) != int(np.argmax(np.asarray(sizes))))
        mesh.remove_unreferenced_vertices()
        return Mesh(np.asarray(mesh.vertices, dtype=np.float64) @ axes.T + centre,
                    np.asarray(mesh.triangles, dtype=np.int64).copy(), "reconstruction")


@SURFACE.register("none")
class NoSurface:
    """No surface: the merged points are the model."""

    @dataclass
    class Params:
        pass

    def __init__(self, params: Params):
        self.p = params

    def reconstruct(self, points: Cloud, from_meshes: bool, spacing: float, ctx: RunContext) -> Optional[Mesh]:
        return None
