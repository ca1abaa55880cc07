"""The dental case (``data=dental``): a cast-scan-like surface of one dental arch against its CT dentition.

Built reproducibly from ../shared/data/open_full_jaw_p26 (CBCT-segmented tooth surfaces, mm, one CT frame):

- **target**: every tooth surface of the arch merged into one mesh (crowns and roots, as the CT shows them);
  each face keeps its tooth number, so deviations can be reported per tooth. The data numbers teeth in the
  Universal scheme (1-32); they are converted to FDI (ISO 3950: 11-48, quadrant then position) for reporting.
- **source**: what a 3D scanner sees of a plaster cast of that arch, seen from the occlusal side: the crowns of
  the erupted teeth (teeth with an axis in the JSON) above a cut at ``crown_height`` below each tooth's
  occlusal-most point along its axis, and a gum surface around and between them that the CT does not have.
  The cast is a height field over the occlusal plane (rays cast onto the crowns, the gum where they miss),
  triangulated on a grid of ``grid`` mm: one connected open surface like a real scan, with steep walls
  where a scanner looking from above cannot see under the crowns' bulge. Then scanner noise along the normals,
  holes on the crowns and a few self-intersecting flaps are added, and the whole is moved by a random pose
  (the ground truth).
- **landmarks**: cusp tips (the occlusal-most point of ``landmarks`` teeth spread along the arch), picked on
  both surfaces with a random error of ``pick_error`` (RMS distance, in the surface's tangent plane), snapped to
  the nearest vertex, as a user would click them.

All lengths are in mm (the data's units).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from scanreg.errors import InputError
from scanreg.geometry import (Mesh, apply_T, bbox_diagonal, invert_T, submesh, transform_geometry,
                               vertex_normals)
from scanreg.io import expand_path, read_mesh
from scanreg.stages.data.perturb import PerturbParams, perturb_inputs
from scanreg.stages.data.base import Provider
from scanreg.stages.registry import DATA
from scanreg.types import Problem, RunContext


@dataclass
class Tooth:
    number: int
    mesh: Mesh
    centre: np.ndarray | None
    axis: np.ndarray | None
    """Unit long axis pointing to the crown (from the JSON), None when the JSON has none."""


def arch_folder(folder: Path, arch: str) -> Path:
    """The folder of ``arch``'s teeth, or one line naming it."""
    d = folder / arch
    if not d.is_dir():
        raise InputError(f"data=dental: no folder {d} (arch '{arch}'); the Open-Full-Jaw data lives in "
                         "../shared/data/open_full_jaw_p26")
    return d


def load_arch(folder: Path, arch: str) -> list[Tooth]:
    d = arch_folder(folder, arch)
    axes_file = next(iter(sorted(d.glob("teeth_axes_*.json"))), None)
    axes = json.loads(axes_file.read_text()) if axes_file else {}
    teeth = []
    for f in sorted(d.glob("tooth_*.ply"), key=lambda p: int(re.findall(r"\d+", p.stem)[0])):
        n = int(re.findall(r"\d+", f.stem)[0])
        a = axes.get(str(n))
        c = np.array(a["c"], float) if a else None
        z = (np.array(a["z"], float) - c) if a else None
        teeth.append(Tooth(n, read_mesh(f, f"tooth {n}"), c, None if z is None else z / np.linalg.norm(z)))
    if not teeth:
        raise InputError(f"data=dental: no tooth_*.ply files in {d}")
    return teeth


def universal_to_fdi(n: int) -> int:
    """FDI (ISO 3950) number of a permanent tooth in the Universal scheme: 1-8 (upper right, third molar to
    central incisor) -> 18-11, 9-16 (upper left) -> 21-28, 17-24 (lower left, third molar to central incisor)
    -> 38-31, 25-32 (lower right) -> 41-48."""
    if not 1 <= n <= 32:
        raise InputError(f"data=dental: tooth number {n} is not a Universal number (1-32)")
    if n <= 8:
        return 19 - n
    if n <= 16:
        return 12 + n
    if n <= 24:
        return 55 - n
    return 16 + n


def merge(meshes: list[Mesh], labels: list[int]) -> tuple[Mesh, np.ndarray]:
    v, f, lab, off = [], [], [], 0
    for m, n in zip(meshes, labels):
        v.append(m.vertices)
        f.append(m.faces + off)
        lab.append(np.full(len(m.faces), n, np.int64))
        off += len(m.vertices)
    return Mesh(np.vstack(v), np.vstack(f)), np.concatenate(lab)


@DATA.register("dental")
class Dental(Provider):
    """A cast scan of one dental arch (crowns, gum, noise, holes, self-intersections) against the CT surface of
    the same teeth, with ground truth and picked cusp-tip landmarks. See :mod:`scanreg.stages.data.dental`."""

    @dataclass
    class Params(PerturbParams):
        folder: str = "shared:open_full_jaw_p26"
        """Folder of the Open-Full-Jaw patient (``shared:NAME`` = ../shared/data/NAME)."""
        arch: str = "mandible"
        """``mandible`` or ``maxilla``."""
        crown_height: float = 7.0
        """Height of the crown the cast shows, mm, from each tooth's occlusal-most point down its axis; the
        gum starts there."""
        gum_width: float = 4.0
        """Width of the gum band around the crowns, mm."""
        gum_slope: float = 0.5
        """Drop of the gum per mm away from the crowns."""
        grid: float = 0.15
        """Grid step of the cast's height field, mm (the scan's resolution)."""
        noise: float = 0.02
        """Scanner noise: standard deviation of the displacement of each vertex along its normal, mm (0.02 = 20
        µm)."""
        holes: int = 6
        """Holes cut into the crowns (missing scan data)."""
        hole_radius: float = 0.5
        """Radius of each hole, mm."""
        flaps: int = 3
        """Small patches of the surface duplicated and tilted through it (self-intersections, as overlapping
        scan patches produce)."""
        flap_radius: float = 0.4
        """Radius of each flap, mm."""
        landmarks: int = 4
        """Cusp-tip landmark pairs picked on both surfaces (3 to 6; 0: none)."""
        pick_error: float = 0.3
        """RMS distance of each pick from the true cusp tip, mm (in the tangent plane, then snapped to the
        nearest vertex)."""
        seed: int = 0
        """Seed of the noise, holes, flaps and picks."""

        def check(self):
            super().check()
            if self.arch not in ("mandible", "maxilla"):
                raise ValueError(f"arch must be mandible or maxilla, got '{self.arch}'")
            if self.landmarks and not 3 <= self.landmarks <= 6:
                raise ValueError(f"landmarks must be 0 or 3 to 6, got {self.landmarks}")
            for k in ("crown_height", "gum_width", "grid"):
                if not getattr(self, k) > 0:
                    raise ValueError(f"{k} must be > 0 mm, got {getattr(self, k)}")
            for k in ("noise", "hole_radius", "flap_radius", "pick_error", "gum_slope"):
                if not getattr(self, k) >= 0:
                    raise ValueError(f"{k} must be >= 0, got {getattr(self, k)}")


    def preflight(self) -> None:
        """The data folder and the arch's folder in it."""
        arch_folder(self._folder(), self.p.arch)

    def _folder(self) -> Path:
        folder = Path(expand_path(self.p.folder))
        if not folder.is_dir():
            raise InputError(f"data.folder {self.p.folder}: no such folder ({folder}); the Open-Full-Jaw data lives "
                             "in ../shared/data/open_full_jaw_p26")
        return folder

    def load(self, ctx: RunContext) -> Problem:
        p = self.p
        folder = self._folder()
        teeth = load_arch(folder, p.arch)
        # Open-Full-Jaw numbers teeth in the Universal scheme (1-32); parts are reported in FDI (ISO 3950)
        target, labels = merge([t.mesh for t in teeth], [universal_to_fdi(t.number) for t in teeth])
        target.source = f"CT dentition ({p.arch}, {len(teeth)} teeth)"
        erupted = [t for t in teeth if t.axis is not None]
        if len(erupted) < 3:
            raise InputError(f"data=dental: {p.arch}: fewer than 3 teeth with an axis in the JSON")
        rng = np.random.default_rng([p.seed, 505])
        cast, cast_labels, tips = self.cast(erupted, rng)
        n_before = len(cast.faces)
        cast = self.add_defects(cast, cast_labels, rng)
        P = p.pose(606, cast.vertices, bbox_diagonal(target.vertices))
        source = transform_geometry(P, cast)
        source.source = f"cast scan of the {p.arch} (synthetic, seed {p.seed})"
        lm = self.pick_landmarks(erupted, tips, target, source, P, rng) if p.landmarks else None
        info = {"dental_teeth": len(teeth), "dental_crowns": len(erupted), "dental_cast_faces": n_before,
                "dental_gum_share": float(np.mean(cast_labels == 0))}
        return perturb_inputs(Problem(source, target, invert_T(P), lm, info, target_labels=labels,
                                      label_name="tooth", target_generated=True), p)

    # ------------------------------------------------------------------------------------------------ cast
    def cast(self, teeth: list[Tooth], rng) -> tuple[Mesh, np.ndarray, dict[int, np.ndarray]]:
        """The noise-free cast surface in the CT frame, a tooth number per vertex (0: gum), and each tooth's
        cusp tip (its occlusal-most vertex along its axis)."""
        import open3d as o3d

        p = self.p
        a = np.mean([t.axis for t in teeth], axis=0)
        a /= np.linalg.norm(a)
        e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        crowns, levels, tips, crown_labels = [], [], {}, []
        for t in teeth:
            s = (t.mesh.vertices - t.centre) @ t.axis
            cut = s.max() - p.crown_height
            tips[t.number] = t.mesh.vertices[int(np.argmax(s))]
            crown = submesh(t.mesh, (s[t.mesh.faces] >= cut).all(axis=1))
            crowns.append(crown)
            crown_labels.append(t.number)
            levels.append(float((t.centre + cut * t.axis) @ a))
        cm, _ = merge(crowns, crown_labels)
        owner = np.concatenate([np.full(len(c.vertices), i) for i, c in enumerate(crowns)])
        uv = np.stack([cm.vertices @ e1, cm.vertices @ e2], axis=1)
        lo, hi = uv.min(0) - p.gum_width, uv.max(0) + p.gum_width
        gu = np.arange(lo[0], hi[0] + p.grid, p.grid)
        gw = np.arange(lo[1], hi[1] + p.grid, p.grid)
        U, W = np.meshgrid(gu, gw, indexing="ij")
        nodes = np.stack([U.ravel(), W.ravel()], axis=1)
        d, j = cKDTree(uv).query(nodes, k=1, workers=-1)
        gum = np.asarray(levels)[owner[j]] - p.gum_slope * d
        top = float((cm.vertices @ a).max()) + 1.0
        scene = o3d.t.geometry.RaycastingScene()
        centre = cm.vertices.mean(axis=0)
        scene.add_triangles(o3d.core.Tensor((cm.vertices - centre).astype(np.float32)),
                            o3d.core.Tensor(cm.faces.astype(np.uint32)))
        origins = nodes[:, :1] * e1 + nodes[:, 1:] * e2 + top * a - centre
        rays = np.hstack([origins, np.tile(-a, (len(nodes), 1))]).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        crown_h = np.where(np.isfinite(t_hit), top - t_hit, -np.inf)
        h = np.maximum(crown_h, gum)
        lab = np.where(crown_h >= gum, np.asarray(crown_labels)[owner[j]], 0)
        valid = (d <= p.gum_width).reshape(U.shape)
        idx = np.arange(U.size).reshape(U.shape)
        v00, v10, v01, v11 = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
        vm = valid.ravel()
        tris = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3),
                               np.stack([v00, v11, v01], -1).reshape(-1, 3)])
        tris = tris[vm[tris].all(axis=1)]
        verts = nodes[:, :1] * e1 + nodes[:, 1:] * e2 + h[:, None] * a
        # orient outward (towards the occlusal side, +a)
        fn = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
        if (fn @ a).sum() < 0:
            tris = tris[:, [0, 2, 1]]
        used, inv = np.unique(tris, return_inverse=True)
        mesh = Mesh(verts[used], inv.reshape(-1, 3).astype(np.int64), "cast")
        return mesh, lab[used], tips

    def add_defects(self, mesh: Mesh, labels: np.ndarray, rng) -> Mesh:
        p = self.p
        v, f = mesh.vertices.copy(), mesh.faces
        if p.noise > 0:
            v = v + vertex_normals(Mesh(v, f)) * rng.normal(scale=p.noise, size=(len(v), 1))
        crown_idx = np.flatnonzero(labels > 0)
        keep = np.ones(len(f), bool)
        tree = cKDTree(v)
        for c in rng.choice(crown_idx, size=min(p.holes, len(crown_idx)), replace=False) if p.holes else []:
            gone = np.zeros(len(v), bool)
            gone[tree.query_ball_point(v[c], p.hole_radius)] = True
            keep &= ~gone[f].any(axis=1)
        f = f[keep]
        extra_v, extra_f, off = [], [], len(v)
        normals = vertex_normals(Mesh(v, f)) if p.flaps else None
        for c in rng.choice(crown_idx, size=min(p.flaps, len(crown_idx)), replace=False) if p.flaps else []:
            near = np.zeros(len(v), bool)
            near[tree.query_ball_point(v[c], p.flap_radius)] = True
            patch = f[near[f].all(axis=1)]
            if not len(patch):
                continue
            used, inv = np.unique(patch, return_inverse=True)
            axis = np.cross(normals[c], rng.normal(size=3))
            axis /= np.linalg.norm(axis)
            from scipy.spatial.transform import Rotation

            R = Rotation.from_rotvec(np.radians(35.0) * axis).as_matrix()
            extra_v.append((v[used] - v[c]) @ R.T + v[c])
            extra_f.append(inv.reshape(-1, 3) + off)
            off += len(used)
        if extra_v:
            v = np.vstack([v, *extra_v])
            f = np.vstack([f, *extra_f])
        return submesh(Mesh(v, f, mesh.source))

    def pick_landmarks(self, teeth, tips, target: Mesh, source: Mesh, P, rng):
        """Cusp tips of ``landmarks`` teeth spread along the arch, each picked with an error on both surfaces."""
        p = self.p
        chosen = [teeth[int(round(i))] for i in np.linspace(0, len(teeth) - 1, p.landmarks)]
        tt, ts = cKDTree(target.vertices), cKDTree(source.vertices)
        nt = vertex_normals(target)
        out_t, out_s = [], []
        for t in chosen:
            tip = tips[t.number]
            n = nt[tt.query(tip)[1]]
            for tree, verts, T, out in ((tt, target.vertices, np.eye(4), out_t), (ts, source.vertices, P, out_s)):
                e = rng.normal(scale=p.pick_error / np.sqrt(2.0), size=3)
                e -= (e @ n) * n  # in the tangent plane
                q = apply_T(T, (tip + e)[None])[0]
                out.append(verts[tree.query(q)[1]])
        return np.asarray(out_t), np.asarray(out_s)
