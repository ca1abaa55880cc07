"""``view3d.html``: one self-contained interactive 3D view of a run, drawn by plotly.js (its JavaScript, shipped
in the plotly package, is embedded, gzip-compressed, so the file opens without network).

Shown: the target (grey), the source before alignment (as loaded, light orange, hidden at first: click its
legend entry), the source after alignment coloured by its signed deviation to the target with a colour bar in
display units (grey where not compared), and, when the target has parts (teeth), their numbers in 3D and the
per-part table. Every surface is a seeded subsample of at most ``view_max_points`` points, which keeps the file
a few MB (2.0 MB of it is plotly's JavaScript, packed).

The figure is written as plotly.js's own JSON (traces and layout as plain dicts, coordinates as base64 typed
arrays) into a fixed page: plotly's Python figure objects (importing them, validating every property, serialising)
were most of a small run's evaluation time (``experiments/benchmarks/end_to_end.md``), for a file the page builds
anyway.
"""

from __future__ import annotations

import base64
import contextlib
import importlib.util
import json
from pathlib import Path

import numpy as np

from scanreg.errors import ConfigError
from scanreg.eval.deviation import colour_range, display_unit
from scanreg.geometry import Mesh, random_subset
from scanreg.io import write_atomic

RDBU_R = [[0.0, "rgb(5,48,97)"], [0.1, "rgb(33,102,172)"], [0.2, "rgb(67,147,195)"], [0.3, "rgb(146,197,222)"],
          [0.4, "rgb(209,229,240)"], [0.5, "rgb(247,247,247)"], [0.6, "rgb(253,219,199)"], [0.7, "rgb(244,165,130)"],
          [0.8, "rgb(214,96,77)"], [0.9, "rgb(178,24,43)"], [1.0, "rgb(103,0,31)"]]
"""ColorBrewer's diverging RdBu, reversed: blue below the target, red above (plotly's ``RdBu_r``)."""


def _points(g) -> np.ndarray:
    return g.vertices if isinstance(g, Mesh) else g.points


def _typed(a: np.ndarray) -> dict:
    """A float array as plotly.js's typed-array JSON (4-byte floats: half the bytes, far below the display's
    resolution)."""
    return {"dtype": "f4", "bdata": base64.b64encode(np.ascontiguousarray(a, dtype="<f4").tobytes()).decode("ascii")}


def _scatter(pts: np.ndarray, name: str, **marker) -> dict:
    return {"type": "scatter3d", "mode": "markers", "name": name, "hoverinfo": "skip",
            "x": _typed(pts[:, 0]), "y": _typed(pts[:, 1]), "z": _typed(pts[:, 2]),
            "marker": {"size": 1.6, **marker}}


def _plotly_js_path() -> Path:
    """plotly.js as the installed plotly package ships it (found without importing the package)."""
    spec = importlib.util.find_spec("plotly")
    js = Path(spec.origin).parent / "package_data" / "plotly.min.js" if spec and spec.origin else None
    if js is None or not js.exists():
        raise ConfigError("evaluate.view_html: plotly's JavaScript (plotly/package_data/plotly.min.js) is not "
                          "installed; reinstall plotly or set evaluate.view_html=false")
    return js


def _plotly_js_packed() -> str:
    """plotly.js gzip-compressed and base64-encoded, as the page unpacks it: 2.0 MB in each view instead of 4.8 MB
    (a sweep's runs each write one, and MLflow keeps a copy). Compressing takes 0.25 s, so it is done once per
    plotly file and kept in the user's cache folder (:func:`_cache_file`); where that folder cannot be written
    it is done for each page."""
    import gzip

    js = _plotly_js_path()
    st = js.stat()
    cached = _cache_file(st)
    if cached is not None:
        try:
            text = cached.read_text(encoding="ascii")
            if _whole_gzip(text, st.st_size):  # (else damaged: made again)
                return text
        except (OSError, UnicodeDecodeError, ValueError):
            pass
    packed = base64.b64encode(gzip.compress(js.read_bytes(), compresslevel=9, mtime=0)).decode("ascii")
    if cached is not None:
        with contextlib.suppress(OSError):  # (a folder that cannot be written: packed again for the next page)
            write_atomic(cached, packed.encode("ascii"))
    return packed


def _whole_gzip(text: str, size: int) -> bool:
    """Whether ``text`` is base64 of a whole gzip stream of ``size`` bytes: its magic bytes first, and last the
    uncompressed size (mod 2^32) that gzip ends with."""
    if not text.startswith("H4sI") or len(text) % 4 or len(text) < 12:  # "H4sI": base64 of 1f 8b 08
        return False
    return int.from_bytes(base64.b64decode(text[-12:])[-4:], "little") == size % (1 << 32)


def _cache_file(st) -> Path | None:
    """Where packed plotly.js is kept: ``$XDG_CACHE_HOME/scanreg``, else ``~/.cache/scanreg``, named by the
    file's size and time (``st``: its ``os.stat``); None without a home folder."""
    import os

    try:
        root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "scanreg"
    except RuntimeError:
        return None
    return root / f"plotly-{st.st_size}-{st.st_mtime_ns}.min.js.gz.b64"


# The page unpacks plotly.js (DecompressionStream: every browser since 2023) and runs it, then draws the figure;
# drawn, it says so in <html data-drawn="true"> (for scripts that capture the view: the tests' headless browser),
# and on a failure, there and in the page, why.
_PAGE_SCRIPT = """<script>
(async function () {
  var packed = atob(document.getElementById("plotly-js-gz").textContent);
  var bytes = new Uint8Array(packed.length);
  for (var i = 0; i < packed.length; i++) bytes[i] = packed.charCodeAt(i);
  var stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
  var code = document.createElement("script");
  code.textContent = await new Response(stream).text();
  document.head.appendChild(code);
  var fig = JSON.parse(document.getElementById("figure").textContent);
  document.getElementById("view").textContent = "";
  await Plotly.newPlot("view", fig.data, fig.layout, {"responsive": true});
  document.documentElement.dataset.drawn = "true";
})().catch(function (e) {
  document.getElementById("view").textContent = "The 3D view could not be drawn: " + e;
  document.documentElement.dataset.drawn = "error: " + e;
});
</script>"""


def _write_page(path: Path, traces: list[dict], layout: dict, title: str = "scanreg") -> Path:
    """One HTML page drawing ``traces`` with ``layout`` (plotly.js JSON), its JavaScript embedded (packed,
    :func:`_plotly_js_packed`); ``title`` names it in the browser's tab."""
    import html

    # (in a script element of a data type, "</" would end it: JSON may hold it only escaped)
    fig = json.dumps({"data": traces, "layout": layout}, separators=(",", ":")).replace("</", "<\\/")
    height = int(layout.get("height", 800))
    page = (f'<!doctype html>\n<html>\n<head>\n<meta charset="utf-8" />\n<title>{html.escape(title)}</title>\n'
            f"<style>html, body {{height: 100%; margin: 0;}}</style>\n</head>\n<body>\n"
            f'<div id="view" style="height:{height}px; width:100%;">This 3D view needs JavaScript and a browser '
            "from 2023 or later (it unpacks plotly.js with DecompressionStream).</div>\n"
            f'<script id="plotly-js-gz" type="application/octet-stream">{_plotly_js_packed()}</script>\n'
            f'<script id="figure" type="application/json">{fig}</script>\n'
            f"{_PAGE_SCRIPT}\n</body>\n</html>\n")
    path.write_text(page, encoding="utf-8")
    return path


def _scene(domain_y: list[float]) -> dict:
    return {"domain": {"x": [0.0, 1.0], "y": domain_y}, "aspectmode": "data",
            **{f"{a}axis": {"title": {"text": a}} for a in "xyz"}}


def write_view(path: Path, target, source, T: np.ndarray, aligned: np.ndarray, on_surface, dev_view: dict | None,
               p, seed: int = 0, units_note: str = "", max_distance: float | None = None) -> Path:
    """Write the view to ``path`` and return it. ``target``/``source`` are the input geometries (source in its
    input pose), ``aligned`` the sampled source points moved by ``T``; ``on_surface`` what
    :class:`scanreg.geometry.ClosestPoints` returned for them; ``dev_view`` what
    :func:`scanreg.eval.deviation.evaluate_deviation` returned for the 3D view (None without a deviation map: the
    colours are then the signed distances of ``aligned``, all shown). ``units_note`` follows the input unit in
    the title (how it was found). Without a deviation map, the points farther than ``max_distance`` from the
    target (input units; None: none) are grey, not compared: where the scans do not overlap, which would
    otherwise set the colour range."""
    rng = np.random.default_rng([seed, 77])
    k = int(p.view_max_points)
    p = p.shown()
    scale, du = p.deviation_scale, display_unit(p.deviation_unit)
    if dev_view is not None:
        pts, dev, ok, table = dev_view["points"], dev_view["dev"], dev_view["ok"], dev_view["table"]
        label_name, r = dev_view["label_name"], dev_view["range"]
    else:  # the distances to the target, signed by its normals when it has them; beyond the overlap: grey
        q, d, qn = on_surface
        sign = np.ones(len(d)) if qn is None else np.where(np.einsum("ij,ij->i", aligned - q, qn) < 0, -1.0, 1.0)
        ok = np.isfinite(d) & (d <= (np.inf if max_distance is None else max_distance))
        pts, dev, table, label_name = aligned, sign * d, None, "part"
        r = colour_range(dev[ok], p)
    signed = dev_view["signed"] if dev_view is not None else on_surface[2] is not None  # (target normals)
    what = "signed deviation" if signed else "distance"

    tp = _points(target)
    n_shown = {"target": len(tp), "source": len(pts)}
    tp = tp[random_subset(len(tp), k, rng)]
    sp = _points(source)
    sp = sp[random_subset(len(sp), k, rng)]
    j = random_subset(len(pts), k, rng)
    pts, dev, ok = pts[j].astype(np.float32), dev[j], ok[j]

    traces = [_scatter(tp, "target", color="rgb(150,150,150)", opacity=0.35),
              {**_scatter(sp, "source before alignment", color="rgb(240,170,80)", opacity=0.5),
               "visible": "legendonly"}]
    if (~ok).any():
        beyond = "" if dev_view is not None or max_distance is None else \
            f" (farther than {max_distance * scale:.3g} {du} from the target)"
        traces.append(_scatter(pts[~ok], f"source after alignment, not compared{beyond}", color="rgb(200,200,200)"))
    on = pts[ok]
    traces.append({
        "type": "scatter3d", "mode": "markers", "name": f"source after alignment: {what} [{du}]",
        "x": _typed(on[:, 0]), "y": _typed(on[:, 1]), "z": _typed(on[:, 2]),
        "marker": {"size": 2.2, "color": _typed(dev[ok] * scale), "colorscale": RDBU_R if signed else "Viridis",
                   "cmin": -float(r * scale) if signed else 0.0, "cmax": float(r * scale),
                   "colorbar": {"title": {"text": f"{what} [{du}]"}, "len": 0.6, "y": 0.7 if table else 0.5}},
        "hovertemplate": f"%{{marker.color:.1f}} {du}<extra></extra>"})
    if dev_view is not None and dev_view.get("part") is not None:
        part = dev_view["part"][j]
        nums = [n for n in np.unique(part[ok])]
        at = np.array([pts[ok & (part == n)].mean(axis=0) for n in nums], dtype=float)
        traces.append({"type": "scatter3d", "mode": "text", "text": [str(int(n)) for n in nums],
                       "x": at[:, 0].tolist(), "y": at[:, 1].tolist(), "z": at[:, 2].tolist(),
                       "name": f"{label_name} numbers" + (" (FDI)" if label_name == "tooth" else ""),
                       "textfont": {"size": 13, "color": "black"}})
    if table:
        traces.append(_table(table, p, dev_view["label_name"], du))
    title = f"{'deviation' if signed else 'distance'} of the aligned source from the target (colour range " \
            f"{'±' if signed else '0 to '}{r * scale:g} {du}"
    title += f"; input units: {display_unit(p.units)}" + (f", {units_note}" if units_note else "") + ")"
    if table:
        title += f"; table: statistics per {label_name}" + (" (FDI numbers)" if label_name == "tooth" else "")
    thinned = [f"{k:,} of the {n:,} {name} points" for name, n in n_shown.items() if n > k]
    if thinned:
        title += "; shown: a random " + " and ".join(thinned)
    layout = {"title": {"text": title, "font": {"size": 13}}, "height": 1000 if table else 800,
              "scene": _scene([0.3, 1.0] if table else [0.0, 1.0]), "legend": {"x": 0, "y": 1},
              "margin": {"l": 0, "r": 0, "t": 40, "b": 0}}
    names = [Path(g.source).name for g in (source, target) if getattr(g, "source", "")]
    return _write_page(path, traces, layout, "scanreg: " + (" onto ".join(names) if len(names) == 2 else "3D view"))


def _table(table: list[dict], p, label_name: str, du: str) -> dict:
    """The per-part statistics as a plotly.js table below the scene."""
    u = p.deviation_unit
    if f"mean_sigma_{u}" in table[0]:  # mean ± its pose uncertainty, as a dentist reads it
        lead = [k for k in table[0] if k in (label_name, "side", "points")]
        table = [{**{k: row[k] for k in lead},
                  f"mean ± pose sigma [{du}]": f"{row[f'mean_{u}']:.1f} ± {row[f'mean_sigma_{u}']:.1f}",
                  **{k: v for k, v in row.items() if k not in lead and k not in (f"mean_{u}", f"mean_sigma_{u}")}}
                 for row in table]
    cols = list(table[0].keys())
    fmt = [[(f"{row.get(c):.3g}" if isinstance(row.get(c), float) else str(row.get(c, ""))) for row in table]
           for c in cols]
    return {"type": "table", "domain": {"x": [0.0, 1.0], "y": [0.0, 0.28]},
            "header": {"values": [c.replace(f"_{u}", f" [{du}]") for c in cols], "font": {"size": 10}},
            "cells": {"values": fmt, "font": {"size": 10}}}


def write_set_view(path: Path, merged, names: list[str], colours: np.ndarray, max_points: int = 200000,
                   seed: int = 0) -> Path:
    """The merged points of a scan set in one self-contained view, a colour and a legend entry per scan (click
    an entry to hide that scan); a seeded subsample of at most ``max_points`` points, named in the title."""
    rng = np.random.default_rng([seed, 78])
    j = random_subset(merged.n_points, max_points, rng)
    pts, scan = merged.points[j], merged.extra["scan"][j]
    traces = []
    for k in np.unique(scan):
        c = colours[int(k) % len(colours)]
        traces.append(_scatter(pts[scan == k], names[int(k)], color=f"rgb({c[0]},{c[1]},{c[2]})"))
    shown = f"{len(j)} of {merged.n_points} points" if len(j) < merged.n_points else f"{merged.n_points} points"
    layout = {"title": {"text": f"the registered scans, merged ({shown}), coloured by scan", "font": {"size": 13}},
              "height": 800, "scene": _scene([0.0, 1.0]), "legend": {"x": 0, "y": 1},
              "margin": {"l": 0, "r": 0, "t": 40, "b": 0}}
    return _write_page(path, traces, layout, f"scanreg: {len(names)} scans in one model")
