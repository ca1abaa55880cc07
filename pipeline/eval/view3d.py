"""``view3d.html``: one self-contained interactive 3D view of a run (plotly; its JavaScript is embedded, so the
file opens without network).

Shown: the target (grey), the source before alignment (as loaded, light orange, hidden at first: click its
legend entry), the source after alignment coloured by its signed deviation to the target with a colour bar in
display units (grey where not compared), and, when the target has parts (teeth), their numbers in 3D and the
per-part table. Every surface is a seeded subsample of at most ``view_max_points`` points, which keeps the file
a few MB (about 4.6 MB of it is plotly's JavaScript).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanreg.eval.deviation import colour_range, display_unit
from scanreg.geometry import Mesh


def _points(g) -> np.ndarray:
    return g.vertices if isinstance(g, Mesh) else g.points


def _subsample(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    return np.sort(rng.choice(n, size=k, replace=False)) if n > k else np.arange(n)


def _scatter(go, pts: np.ndarray, name: str, **marker):
    pts = pts.astype(np.float32)  # half the bytes; far below the display's resolution
    return go.Scatter3d(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], mode="markers", name=name,
                        marker=dict(size=1.6, **marker), hoverinfo="skip")


def write_view(path: Path, target, source, T: np.ndarray, aligned: np.ndarray, on_surface, dev_view: dict | None,
               p, seed: int = 0) -> Path:
    """Write the view to ``path`` and return it. ``target``/``source`` are the input geometries (source in its
    input pose), ``aligned`` the sampled source points moved by ``T``; ``on_surface`` what
    :class:`scanreg.geometry.ClosestPoints` returned for them; ``dev_view`` what
    :func:`scanreg.eval.deviation.evaluate_deviation` returned for the 3D view (None without a deviation map: the
    colours are then the signed distances of ``aligned``, all shown)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    rng = np.random.default_rng([seed, 77])
    k = int(p.view_max_points)
    scale, du = p.deviation_scale, display_unit(p.deviation_unit)
    if dev_view is not None:
        pts, dev, ok, table = dev_view["points"], dev_view["dev"], dev_view["ok"], dev_view["table"]
        label_name, r = dev_view["label_name"], dev_view["range"]
    else:
        q, d, qn = on_surface
        sign = np.ones(len(d)) if qn is None else np.where(np.einsum("ij,ij->i", aligned - q, qn) < 0, -1.0, 1.0)
        pts, dev, ok, table, label_name = aligned, sign * d, np.isfinite(d), None, "part"
        r = colour_range(dev[ok], p)

    tp = _points(target)
    tp = tp[_subsample(len(tp), k, rng)]
    sp = _points(source)
    sp = sp[_subsample(len(sp), k, rng)]
    j = _subsample(len(pts), k, rng)
    pts, dev, ok = pts[j].astype(np.float32), dev[j], ok[j]

    rows = 2 if table else 1
    fig = make_subplots(rows=rows, cols=1, specs=[[{"type": "scene"}]] + ([[{"type": "table"}]] if table else []),
                        row_heights=[0.72, 0.28] if table else [1.0], vertical_spacing=0.02)
    fig.add_trace(_scatter(go, tp, "target", color="rgb(150,150,150)", opacity=0.35), row=1, col=1)
    before = _scatter(go, sp, "source before alignment", color="rgb(240,170,80)", opacity=0.5)
    before.visible = "legendonly"
    fig.add_trace(before, row=1, col=1)
    if (~ok).any():
        fig.add_trace(_scatter(go, pts[~ok], "source after alignment, not compared", color="rgb(200,200,200)"),
                      row=1, col=1)
    v = dev[ok] * scale
    fig.add_trace(go.Scatter3d(
        x=pts[ok, 0], y=pts[ok, 1], z=pts[ok, 2], mode="markers", name=f"source after alignment: deviation [{du}]",
        marker=dict(size=2.2, color=v.astype(np.float32), colorscale="RdBu_r", cmin=-r * scale, cmax=r * scale,
                    colorbar=dict(title=f"signed deviation [{du}]", len=0.6, y=0.7 if table else 0.5)),
        hovertemplate=f"%{{marker.color:.1f}} {du}<extra></extra>"), row=1, col=1)
    if dev_view is not None and dev_view.get("part") is not None:
        part = dev_view["part"][j]
        nums = [n for n in np.unique(part[ok])]
        at = np.array([pts[ok & (part == n)].mean(axis=0) for n in nums])
        fig.add_trace(go.Scatter3d(x=at[:, 0], y=at[:, 1], z=at[:, 2], mode="text", text=[str(int(n)) for n in nums],
                                   name=f"{label_name} numbers" + (" (FDI)" if label_name == "tooth" else ""),
                                   textfont=dict(size=13, color="black")), row=1, col=1)
    if table:
        u = p.deviation_unit
        if f"mean_sigma_{u}" in table[0]:  # mean ± its pose uncertainty, as a dentist reads it
            lead = [k for k in table[0] if k in (dev_view["label_name"], "side", "points")]
            table = [{**{k: row[k] for k in lead},
                      f"mean ± pose sigma [{du}]": f"{row[f'mean_{u}']:.1f} ± {row[f'mean_sigma_{u}']:.1f}",
                      **{k: v for k, v in row.items() if k not in lead and k not in (f"mean_{u}", f"mean_sigma_{u}")}}
                     for row in table]
        cols = list(table[0].keys())
        fmt = [[(f"{row.get(c):.3g}" if isinstance(row.get(c), float) else str(row.get(c, ""))) for row in table]
               for c in cols]
        fig.add_trace(go.Table(header=dict(values=[c.replace("_um", f" [{du}]") for c in cols], font=dict(size=10)),
                               cells=dict(values=fmt, font=dict(size=10))), row=2, col=1)
    title = f"deviation of the aligned source from the target (colour range ±{r * scale:g} {du})"
    if table:
        title += f"; table: statistics per {label_name}" + (" (FDI numbers)" if label_name == "tooth" else "")
    fig.update_layout(title=dict(text=title, font=dict(size=13)), height=1000 if table else 800,
                      scene=dict(aspectmode="data", xaxis_title="x", yaxis_title="y", zaxis_title="z"),
                      legend=dict(x=0, y=1), margin=dict(l=0, r=0, t=40, b=0))
    path.write_text(fig.to_html(include_plotlyjs=True, full_html=True), encoding="utf-8")
    return path


def write_set_view(path: Path, merged, names: list[str], colours: np.ndarray, max_points: int = 200000,
                   seed: int = 0) -> Path:
    """The merged points of a scan set in one self-contained view, a colour and a legend entry per scan (click
    an entry to hide that scan); a seeded subsample of at most ``max_points`` points, named in the title."""
    import plotly.graph_objects as go

    rng = np.random.default_rng([seed, 78])
    j = _subsample(merged.n_points, max_points, rng)
    pts, scan = merged.points[j], merged.extra["scan"][j]
    fig = go.Figure()
    for k in np.unique(scan):
        c = colours[int(k) % len(colours)]
        fig.add_trace(_scatter(go, pts[scan == k], names[int(k)], color=f"rgb({c[0]},{c[1]},{c[2]})"))
    shown = f"{len(j)} of {merged.n_points} points" if len(j) < merged.n_points else f"{merged.n_points} points"
    fig.update_layout(title=dict(text=f"the registered scans, merged ({shown}), coloured by scan", font=dict(size=13)),
                      height=800, scene=dict(aspectmode="data", xaxis_title="x", yaxis_title="y", zaxis_title="z"),
                      legend=dict(x=0, y=1), margin=dict(l=0, r=0, t=40, b=0))
    path.write_text(fig.to_html(include_plotlyjs=True, full_html=True), encoding="utf-8")
    return path
