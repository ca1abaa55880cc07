"""Surface reconstruction (``surface=NAME``): one mesh from the merged points of a registered scan set."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from scanreg.geometry import Cloud, Mesh, to_o3d
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
        depth: int = 8
        """Octree depth: the reconstruction's resolution is the bounding box over 2^depth (8: 1/256 of it)."""
        trim_quantile: float = 0.0
        """Remove the vertices whose point density is below this quantile of all vertices' (0..1): surface
        extrapolated far from any scan. The holes this opens are closed by the repair; 0: no trimming."""
        scale: float = 1.1
        """The reconstruction's cube over the points' bounding box (Open3D's ``scale``)."""
        when: str = "meshes"
        """``meshes``: only when the scans were meshes (a cloud set gives merged points only); ``always``."""

        def check(self):
            if self.when not in ("meshes", "always"):
                raise ValueError(f"when must be meshes or always, got '{self.when}'")
            if not 0 <= self.trim_quantile < 1:
                raise ValueError(f"trim_quantile must be in [0, 1), got {self.trim_quantile}")
            if not 1 <= self.depth <= 14:
                raise ValueError(f"depth must be in 1..14, got {self.depth}")

    def __init__(self, params: Params):
        self.p = params

    def reconstruct(self, points: Cloud, from_meshes: bool, spacing: float, ctx: RunContext) -> Optional[Mesh]:
        import open3d as o3d

        if self.p.when == "meshes" and not from_meshes:
            return None
        if points.normals is None:
            return None
        pc = to_o3d(points.points, points.normals)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pc, depth=self.p.depth, scale=self.p.scale, linear_fit=False, n_threads=1)
        if self.p.trim_quantile > 0:
            density = np.asarray(density)
            mesh.remove_vertices_by_mask(density < np.quantile(density, self.p.trim_quantile))
        return Mesh(np.asarray(mesh.vertices, dtype=np.float64).copy(), np.asarray(mesh.triangles, dtype=np.int64).copy(),
                    "reconstruction")


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
