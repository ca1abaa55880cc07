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
- ``deviation_<parts>.csv`` (``deviation_teeth.csv`` for the dental case): the statistics per part, with the
  pose uncertainty of each part's mean (``mean_sigma_<unit>``) and the shares beyond ``deviation_tolerance``.

Pictures write µm for ``um``; tooth numbers (FDI) and the patient's sides are marked on the dental map.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanreg.geometry import Cloud, Mesh, face_normals, vertex_normals


def signed_deviation(points: np.ndarray, normals: np.ndarray | None, cp):
    """``(signed distance, compared-normal cosine or None, part index of the closest face or None)`` against
    the target behind ``cp`` (a :class:`scanreg.geometry.ClosestPoints`, built once per target)."""
    return _signed(points, normals, cp)[:3]


def _signed(points: np.ndarray, normals: np.ndarray | None, cp):
    """:func:`signed_deviation` and the target normals at the closest points (or None)."""
    q, d, qn, ids = cp.query(points)
    if qn is not None:
        sign = np.where(np.einsum("ij,ij->i", points - q, qn) < 0, -1.0, 1.0)
        cos = None if normals is None else np.einsum("ij,ij->i", normals, qn)
    else:
        sign, cos = np.ones(len(d)), None
    return sign * d, cos, ids, qn


def display_unit(unit: str) -> str:
    """The unit as written for people (``um`` in metric names, ``µm`` in pictures)."""
    return "µm" if unit == "um" else unit


def fdi_side(n: int) -> str | None:
    """The patient's side of an FDI tooth number (quadrants 1, 4 and 5, 8: right; 2, 3 and 6, 7: left)."""
    q = n // 10
    return {1: "right", 4: "right", 5: "right", 8: "right", 2: "left", 3: "left", 6: "left", 7: "left"}.get(q)


def tolerance_shares(dev: np.ndarray, sigma: np.ndarray | None, p, prefix: str = "dev_") -> dict[str, float]:
    """Share of points with |deviation| beyond ``deviation_tolerance`` and, given per-point pose sigmas, the
    share beyond it with ``deviation_confidence`` (|deviation| - z sigma > tolerance)."""
    from scipy.stats import norm

    if not len(dev):
        return {}
    p = p.shown()
    tag = f"{prefix}over_{p.deviation_tolerance * p.deviation_scale:g}{p.deviation_unit}"
    out = {f"{tag}_share": float(np.mean(np.abs(dev) > p.deviation_tolerance))}
    if sigma is not None:
        z = float(norm.ppf(p.deviation_confidence))
        out[f"{tag}_sure_share"] = float(np.mean(np.abs(dev) - z * sigma > p.deviation_tolerance))
    return out


def compared_mask(dev: np.ndarray, cos: np.ndarray | None, max_distance: float | None,
                  max_angle_deg: float | None) -> np.ndarray:
    ok = np.isfinite(dev)
    if max_distance is not None:
        ok &= np.abs(dev) <= max_distance
    if max_angle_deg is not None and cos is not None:
        ok &= cos >= np.cos(np.radians(max_angle_deg))
    return ok


def stats(dev: np.ndarray, scale: float, unit: str, bands: list[float], prefix: str = "dev_") -> dict[str, float]:
    """Mean, RMS, median, 5th/95th percentile, 95th percentile and max of |.| in display units, and the share within each ±band."""
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
        f"{prefix}p95_abs_{unit}": float(np.percentile(np.abs(v), 95)),
        f"{prefix}max_abs_{unit}": float(np.abs(v).max()),
    }
    for b in bands:
        out[f"{prefix}within_{b * scale:g}{unit}"] = float(np.mean(np.abs(dev) <= b))
    return out


def plural(word: str) -> str:
    """``tooth`` -> ``teeth``, ``part`` -> ``parts``."""
    return {"tooth": "teeth"}.get(word, word + "s")


READABLE_STEPS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
"""The colour range's steps within a power of ten (in the display unit)."""


def colour_range(dev: np.ndarray, p) -> float:
    """The colour map's range ±r (input units) for the signed deviations ``dev`` of the compared points:
    ``p.deviation_range`` when set; else the 95th percentile of |dev| in the display unit (``deviation_scale``),
    rounded up to the next of :data:`READABLE_STEPS` times a power of ten (0.27 mm shown in µm: 300 µm); one
    display unit when nothing was compared or every deviation is zero."""
    if p.deviation_range is not None:
        return float(p.deviation_range)
    p = p.shown()
    a = np.abs(dev[np.isfinite(dev)]) * p.deviation_scale
    q = float(np.percentile(a, 95)) if len(a) else 0.0
    if not q > 0:
        return 1.0 / p.deviation_scale
    decade = 10.0 ** np.floor(np.log10(q))
    step = next(s for s in READABLE_STEPS if s * decade >= q * (1 - 1e-9))
    return float(step * decade / p.deviation_scale)


def colours(dev: np.ndarray, ok: np.ndarray, rng: float) -> np.ndarray:
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"]
    c = (cmap(np.clip(dev / rng, -1, 1) * 0.5 + 0.5)[:, :3] * 255).astype(np.uint8)
    c[~ok] = 170
    return c


def write_outputs(run_dir: Path, geom, dev_v: np.ndarray, ok_v: np.ndarray, dev_pts: np.ndarray,
                  p, part_table: list[dict] | None, label_name: str, rng: float, marks=None) -> list[Path]:
    """The coloured PLY (``geom`` with per-vertex ``dev_v``), histogram and picture, and the part table; the
    colours saturate at ±``rng`` (input units, :func:`colour_range`); ``p`` with its display unit settled
    (:meth:`~scanreg.eval.metrics.EvalParams.shown`, as :func:`evaluate_deviation` passes it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scanreg.io import write_ply

    scale, unit = p.deviation_scale, p.deviation_unit
    paths = [run_dir / "deviation_map.ply", run_dir / "deviation_histogram.png", run_dir / "deviation_map.png"]
    write_ply(paths[0], geom, colors=colours(dev_v, ok_v, rng),
              scalars={"quality": np.where(ok_v, dev_v * scale, np.nan).astype(np.float32)})

    du = display_unit(unit)
    fig, ax = plt.subplots(figsize=(6, 3.6))
    lim = 2 * rng * scale
    v = dev_pts * scale
    ax.hist(np.clip(v, -lim, lim), bins=80, range=(-lim, lim), color="tab:blue")
    for b in p.deviation_bands:
        for sgn in (-1, 1):
            ax.axvline(sgn * b * scale, color="k", lw=0.7, ls="--")
    lo, hi = int(np.sum(v < -lim)), int(np.sum(v > lim))
    for x, n, ha in ((-lim, lo, "left"), (lim, hi, "right")):  # the clipped tails, in the outermost bins
        if n:
            ax.annotate(f"{n} beyond {'-' if x < 0 else '+'}{lim:g} {du}", xy=(x, 0), xytext=(x, 0.9),
                        textcoords=("data", "axes fraction"), ha=ha, fontsize=8, color="tab:red",
                        arrowprops=dict(arrowstyle="->", color="tab:red", lw=0.8))
    ax.set_xlabel(f"signed deviation [{du}] (+: source outside the target; clipped at ±{lim:g})")
    ax.set_ylabel("points")
    ax.set_title(f"{len(v)} compared points: median {np.median(v):.1f} {du}, 95th percentile of |dev| "
                 f"{np.percentile(np.abs(v), 95):.1f} {du}, RMS {np.sqrt(np.mean(v ** 2)):.1f} {du}"
                 if len(v) else "no compared points", fontsize=8)
    fig.tight_layout()
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)

    pts = geom.vertices if isinstance(geom, Mesh) else geom.points
    centre = pts.mean(axis=0)
    c = pts - centre
    _, _, vt = np.linalg.svd(c[:: max(1, len(c) // 20000)], full_matrices=False)
    view = vt[2]
    if isinstance(geom, Mesh):
        if (face_normals(geom, unit=False).sum(axis=0) @ view) < 0:
            view = -view
    elif geom.normals is not None and geom.normals.sum(axis=0) @ view < 0:
        view = -view
    ex, ey = vt[0], np.cross(view, vt[0])
    teeth = label_name == "tooth" and marks
    if teeth:  # the patient's right on the viewer's left, as a dentist looks at an occlusal view
        right = [m[1] for m in marks if fdi_side(m[0]) == "right"]
        left = [m[1] for m in marks if fdi_side(m[0]) == "left"]
        if right and left and (np.mean(right, axis=0) - np.mean(left, axis=0)) @ ex > 0:
            ex, ey = -ex, -ey
    x, y = c @ ex, c @ ey
    depth = c @ view
    order = np.argsort(depth)
    fig, ax = plt.subplots(figsize=(7, 6))
    col = colours(dev_v, ok_v, rng)[order] / 255.0
    ax.scatter(x[order], y[order], c=col, s=0.6, linewidths=0)
    for n, at in marks or []:
        ax.text((at - centre) @ ex, (at - centre) @ ey, str(n), fontsize=8, ha="center", va="center",
                fontweight="bold", bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.7))
    if teeth:
        ax.set_title("occlusal view (from the crowns), tooth numbers FDI; looking onto the surface", fontsize=9)
        ax.text(0.0, 0.5, "patient's\nright", transform=ax.transAxes, ha="left", va="center", fontsize=9)
        ax.text(1.0, 0.5, "patient's\nleft", transform=ax.transAxes, ha="right", va="center", fontsize=9)
    else:
        ax.set_title("view along the surface's thinnest direction, onto its outer side", fontsize=9)
    ax.set_aspect("equal")
    ax.set_axis_off()
    sm = plt.cm.ScalarMappable(cmap="RdBu_r", norm=matplotlib.colors.Normalize(-rng * scale, rng * scale))
    fig.colorbar(sm, ax=ax, shrink=0.7, label=f"signed deviation [{du}] (grey: not compared)")
    fig.tight_layout()
    fig.savefig(paths[2], dpi=120)
    plt.close(fig)

    if part_table:
        import pandas as pd

        paths.append(run_dir / f"deviation_{plural(label_name)}.csv")
        pd.DataFrame(part_table).to_csv(paths[-1], index=False)
    return paths


def evaluate_deviation(run_dir: Path, aligned: Cloud, aligned_geom, cp, labels: np.ndarray | None, p,
                       label_name: str = "part", pose=None) -> tuple[dict, list[Path], dict]:
    """Metrics ``dev_*`` (overall and ``dev_rms_<unit>_<label_name>_<n>`` per part), the output files, and what
    the 3D view needs (``points``, ``dev``, ``ok``, ``table``, ``part``); ``cp`` finds closest points on the
    target (its triangles when it is a mesh). With ``pose`` (a :class:`scanreg.eval.uncertainty.PoseCovariance`),
    each compared point's deviation gets its standard deviation due to the pose: ``dev_pose_sigma_median_<unit>``
    overall, and per part the uncertainty of the mean (``mean_sigma_<unit>``) and of the points. The display
    unit is ``p``'s (:meth:`EvalParams.shown`: settled by the caller, who knows the target's size)."""
    p = p.shown()
    dev, cos, ids, qn = _signed(aligned.points, aligned.normals, cp)
    ok = compared_mask(dev, cos, p.deviation_max_distance, p.deviation_max_angle_deg)
    m = stats(dev[ok], p.deviation_scale, p.deviation_unit, p.deviation_bands)
    m["dev_compared_share"] = float(ok.mean())
    sigma = None
    if pose is not None and qn is not None and ok.any():
        sigma = np.full(len(dev), np.nan)
        sigma[ok] = pose.point_sigma(aligned.points[ok], qn[ok])
        m[f"dev_pose_sigma_median_{p.deviation_unit}"] = float(np.median(sigma[ok]) * p.deviation_scale)
        m[f"dev_pose_sigma_max_{p.deviation_unit}"] = float(np.max(sigma[ok]) * p.deviation_scale)
        m[f"dev_mean_sigma_{p.deviation_unit}"] = pose.mean_sigma(aligned.points[ok], qn[ok]) * p.deviation_scale
    m.update(tolerance_shares(dev[ok], None if sigma is None else sigma[ok], p))
    table, part = None, None
    if labels is not None and ids is not None:
        part = labels[ids]
        table = []
        u = p.deviation_unit
        for n in np.unique(part[ok]):
            sel = ok & (part == n)
            s = stats(dev[sel], p.deviation_scale, u, p.deviation_bands, prefix="")
            row = {label_name: int(n)}
            if label_name == "tooth":
                row["side"] = fdi_side(int(n)) or ""
            row.update(s)
            if sigma is not None:
                row[f"mean_sigma_{u}"] = pose.mean_sigma(aligned.points[sel], qn[sel]) * p.deviation_scale
                row[f"pose_sigma_median_{u}"] = float(np.median(sigma[sel]) * p.deviation_scale)
            row.update(tolerance_shares(dev[sel], None if sigma is None else sigma[sel], p, prefix=""))
            table.append(row)
            m[f"dev_rms_{u}_{label_name}_{int(n)}"] = s[f"rms_{u}"]
    if isinstance(aligned_geom, Mesh):
        dev_v, cos_v, _ = signed_deviation(aligned_geom.vertices, vertex_normals(aligned_geom), cp)
    else:
        dev_v, cos_v = dev, cos
    ok_v = compared_mask(dev_v, cos_v, p.deviation_max_distance, p.deviation_max_angle_deg)
    marks = None
    if part is not None:  # part numbers at the centroid of their compared points, for the map
        marks = [(int(n), aligned.points[ok & (part == n)].mean(axis=0)) for n in np.unique(part[ok])]
    rng = colour_range(dev[ok], p)
    paths = write_outputs(run_dir, aligned_geom, dev_v, ok_v, dev[ok], p, table, label_name, rng, marks)
    view = {"points": aligned.points, "dev": dev, "ok": ok, "sigma": sigma, "table": table, "part": part,
            "label_name": label_name, "range": rng, "signed": qn is not None}
    return m, paths, view
