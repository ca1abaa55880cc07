"""Deviation maps: signed distances of the aligned source to the target surface, as numbers and pictures.

For every aligned source point, the closest point on the target (its triangles when the target is a mesh) gives
a signed distance: positive where the source lies outside the target (along the target's outward normal). Points
farther than ``deviation_max_distance``, or whose normal differs from the target's by more than
``deviation_max_angle_deg``, are not compared (surface the target does not have, such as the gum of a cast that
a CT of the teeth lacks); their share is reported. Statistics are given in a display unit (µm for mm input),
overall and per part of the target (per tooth) when the target's faces carry part numbers.

Outputs in the run directory:
- ``deviation_map.ply``: the aligned source (mesh when it is one) coloured by a diverging colour map clipped
  at ±``deviation_range`` (blue inside, red outside, grey not compared), with the signed deviation as the
  per-vertex scalar ``quality`` (in display units) for MeshLab/CloudCompare;
- ``deviation_histogram.png``, ``deviation_map.png`` (the colour map seen along the surface's thinnest
  direction, with a legend in display units);
- ``deviation_parts.csv``: the statistics per part.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanreg.geometry import Cloud, Mesh, face_normals, vertex_normals


def signed_deviation(points: np.ndarray, normals: np.ndarray | None, cp):
    """``(signed distance, compared-normal cosine or None, part index of the closest face or None)`` against
    the target behind ``cp`` (a :class:`scanreg.closest.ClosestPoints`, built once per target)."""
    q, d, qn = cp(points)
    ids = getattr(cp, "last_primitive_ids", None)
    if qn is not None:
        sign = np.where(np.einsum("ij,ij->i", points - q, qn) < 0, -1.0, 1.0)
        cos = None if normals is None else np.einsum("ij,ij->i", normals, qn)
    else:
        sign, cos = np.ones(len(d)), None
    return sign * d, cos, ids


def compared_mask(dev: np.ndarray, cos: np.ndarray | None, max_distance: float | None,
                  max_angle_deg: float | None) -> np.ndarray:
    ok = np.isfinite(dev)
    if max_distance is not None:
        ok &= np.abs(dev) <= max_distance
    if max_angle_deg is not None and cos is not None:
        ok &= cos >= np.cos(np.radians(max_angle_deg))
    return ok


def stats(dev: np.ndarray, scale: float, unit: str, bands: list[float], prefix: str = "dev_") -> dict[str, float]:
    """Mean, RMS, median, 5th/95th percentile, max |.| in display units, and the share within each ±band."""
    if not len(dev):
        return {f"{prefix}points": 0.0}
    v = dev * scale
    out = {
        f"{prefix}points": float(len(v)),
        f"{prefix}mean_{unit}": float(v.mean()),
        f"{prefix}rms_{unit}": float(np.sqrt(np.mean(v ** 2))),
        f"{prefix}median_{unit}": float(np.median(v)),
        f"{prefix}p05_{unit}": float(np.percentile(v, 5)),
        f"{prefix}p95_{unit}": float(np.percentile(v, 95)),
        f"{prefix}max_abs_{unit}": float(np.abs(v).max()),
    }
    for b in bands:
        out[f"{prefix}within_{b * scale:g}{unit}"] = float(np.mean(np.abs(dev) <= b))
    return out


def colours(dev: np.ndarray, ok: np.ndarray, rng: float) -> np.ndarray:
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"]
    c = (cmap(np.clip(dev / rng, -1, 1) * 0.5 + 0.5)[:, :3] * 255).astype(np.uint8)
    c[~ok] = 170
    return c


def write_outputs(run_dir: Path, geom, dev_v: np.ndarray, ok_v: np.ndarray, dev_pts: np.ndarray,
                  p, part_table: list[dict] | None, label_name: str) -> list[Path]:
    """The coloured PLY (``geom`` with per-vertex ``dev_v``), histogram and picture, and the part table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scanreg.io import write_ply

    scale, unit, rng = p.deviation_scale, p.deviation_unit, p.deviation_range
    paths = [run_dir / "deviation_map.ply", run_dir / "deviation_histogram.png", run_dir / "deviation_map.png"]
    write_ply(paths[0], geom, colors=colours(dev_v, ok_v, rng),
              scalars={"quality": np.where(ok_v, dev_v * scale, np.nan).astype(np.float32)})

    fig, ax = plt.subplots(figsize=(6, 3.4))
    lim = 2 * rng * scale
    ax.hist(np.clip(dev_pts * scale, -lim, lim), bins=80, range=(-lim, lim), color="tab:blue")
    for b in p.deviation_bands:
        for sgn in (-1, 1):
            ax.axvline(sgn * b * scale, color="k", lw=0.7, ls="--")
    ax.set_xlabel(f"signed deviation [{unit}] (clipped at ±{lim:g})")
    ax.set_ylabel("points")
    ax.set_title(f"{len(dev_pts)} compared points: mean {dev_pts.mean() * scale:.1f}, RMS "
                 f"{np.sqrt(np.mean(dev_pts ** 2)) * scale:.1f} {unit}" if len(dev_pts) else "no compared points",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)

    pts = geom.vertices if isinstance(geom, Mesh) else geom.points
    c = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(c[:: max(1, len(c) // 20000)], full_matrices=False)
    view = vt[2]
    if isinstance(geom, Mesh):
        if (face_normals(geom, unit=False).sum(axis=0) @ view) < 0:
            view = -view
    elif geom.normals is not None and geom.normals.sum(axis=0) @ view < 0:
        view = -view
    x, y = c @ vt[0], c @ np.cross(view, vt[0])
    depth = c @ view
    order = np.argsort(depth)
    fig, ax = plt.subplots(figsize=(7, 6))
    col = colours(dev_v, ok_v, rng)[order] / 255.0
    ax.scatter(x[order], y[order], c=col, s=0.6, linewidths=0)
    ax.set_aspect("equal")
    ax.set_axis_off()
    sm = plt.cm.ScalarMappable(cmap="RdBu_r", norm=matplotlib.colors.Normalize(-rng * scale, rng * scale))
    fig.colorbar(sm, ax=ax, shrink=0.7, label=f"signed deviation [{unit}] (grey: not compared)")
    fig.tight_layout()
    fig.savefig(paths[2], dpi=120)
    plt.close(fig)

    if part_table:
        import pandas as pd

        paths.append(run_dir / f"deviation_{label_name}s.csv")
        pd.DataFrame(part_table).to_csv(paths[-1], index=False)
    return paths


def evaluate_deviation(run_dir: Path, aligned: Cloud, aligned_geom, cp, labels: np.ndarray | None, p,
                       label_name: str = "part") -> tuple[dict, list[Path]]:
    """Metrics ``dev_*`` (overall and ``dev_rms_<unit>_<label_name>_<n>`` per part) and the output files;
    ``cp`` finds closest points on the target (its triangles when it is a mesh)."""
    dev, cos, ids = signed_deviation(aligned.points, aligned.normals, cp)
    ok = compared_mask(dev, cos, p.deviation_max_distance, p.deviation_max_angle_deg)
    m = stats(dev[ok], p.deviation_scale, p.deviation_unit, p.deviation_bands)
    m["dev_compared_share"] = float(ok.mean())
    table = None
    if labels is not None and ids is not None:
        part = labels[ids]
        table = []
        for n in np.unique(part[ok]):
            sel = ok & (part == n)
            s = stats(dev[sel], p.deviation_scale, p.deviation_unit, p.deviation_bands, prefix="")
            table.append({label_name: int(n), **s})
            m[f"dev_rms_{p.deviation_unit}_{label_name}_{int(n)}"] = s[f"rms_{p.deviation_unit}"]
    if isinstance(aligned_geom, Mesh):
        dev_v, cos_v, _ = signed_deviation(aligned_geom.vertices, vertex_normals(aligned_geom), cp)
    else:
        dev_v, cos_v = dev, cos
    ok_v = compared_mask(dev_v, cos_v, p.deviation_max_distance, p.deviation_max_angle_deg)
    paths = write_outputs(run_dir, aligned_geom, dev_v, ok_v, dev[ok], p, table, label_name)
    return m, paths
