"""``data=synthetic``: the demo case made from one mesh."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scanreg.geometry import Cloud, barycentric_sample, bbox_diagonal, transform_geometry, triangle_areas_normals
from scanreg.io import expand_path, read_mesh, resolve_path
from scanreg.stages.data.perturb import PoseParams
from scanreg.stages.data.base import Provider
from scanreg.stages.registry import DATA
from scanreg.types import Problem, RunContext


@DATA.register("synthetic")
class Synthetic(Provider):
    """A second "scan" made from one mesh: the source is the mesh itself (repaired and sampled by the run);
    the target an independent resampling of the same surface with part cut away, Gaussian noise and outliers,
    placed under a random pose that is the ground truth. The default mesh is pymeshfix's defective Stanford
    bunny (units: mm-like, about 50 across)."""

    @dataclass
    class Params(PoseParams):
        mesh: str = "pkg:pymeshfix/examples/StanfordBunny.ply"
        """Mesh to make the case from (path, ``pkg:`` or ``shared:`` name)."""
        n_points: int = 20000
        """Points sampled on the surface for the target (before cropping)."""
        keep: float = 0.8
        """Share of the target's points kept; the rest, beyond a random plane, is cut away (partial overlap)."""
        noise: float = 0.1
        """Standard deviation of Gaussian noise per coordinate, in multiples of the target's sampling
        spacing sqrt(area / n_points)."""
        outliers: float = 0.0
        """Share of outlier points added uniformly in the target's bounding box."""
        seed: int = 0
        """Seed of the target's sampling, cropping, noise and outliers (the YAML links it to the run's seed)."""

        def check(self):
            super().check()
            if not 0.05 <= self.keep <= 1.0:
                raise ValueError(f"keep must be in [0.05, 1], got {self.keep}")
            if self.n_points < 3:
                raise ValueError(f"n_points must be >= 3, got {self.n_points}")


    def preflight(self) -> None:
        """The mesh file is there."""
        resolve_path(expand_path(self.p.mesh), "data.mesh")

    def load(self, ctx: RunContext) -> Problem:
        p = self.p
        mesh = read_mesh(expand_path(p.mesh), "data.mesh")
        rng = np.random.default_rng([p.seed, 101])
        pts, normals, _ = barycentric_sample(mesh, p.n_points, rng)
        spacing = float(np.sqrt(triangle_areas_normals(mesh)[0].sum() / p.n_points))
        if p.keep < 1.0:
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            h = pts @ d
            keep = h <= np.quantile(h, p.keep)
            pts, normals = pts[keep], normals[keep]
        pts = pts + rng.normal(scale=p.noise * spacing, size=pts.shape)
        n_out = int(round(p.outliers * len(pts)))
        if n_out:
            lo, hi = pts.min(0), pts.max(0)
            out = rng.uniform(lo, hi, size=(n_out, 3))
            on = rng.normal(size=(n_out, 3))
            pts = np.vstack([pts, out])
            normals = np.vstack([normals, on / np.linalg.norm(on, axis=1, keepdims=True)])
        T = p.pose(202, pts, bbox_diagonal(mesh.vertices))
        target = transform_geometry(T, Cloud(pts, normals, f"synthetic scan of {p.mesh}"))
        return Problem(mesh, target, T, None, {"synthetic_spacing": spacing}, target_generated=True)
