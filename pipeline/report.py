"""``scanreg-report``: MLflow runs -> comparison tables (Markdown, CSV) and plots (PNG).

    scanreg-report                                   # the newest sweep (of any experiment), grouped by what varies
    scanreg-report --experiment bunny_benchmark --group-by group.coarse --per data.pair
    scanreg-report --experiment sampling_density --group-by sampler.density --x sampler.density
    scanreg-report --experiment icp_comparison --compare-to icp_comparison_old

Runs are loaded with ``mlflow.search_runs``; ``--group-by`` takes config keys (``icp.tau``; ``group.coarse`` is
the chosen implementation of a stage group). Per group: runs, failed runs, success rate (rotation error < 2°
and translation error < 1 % of the diagonal, as configured in ``evaluate``; a failed run counts as a failure),
median and 90th-percentile errors, median time per stage. Plots: success rate per group, error and time against
``--x``, success per ``--per`` value (e.g. per scan pair). An experiment file turns the report on with
``report.enabled=true`` so that ``scanreg experiment=NAME`` writes it when its sweep ends.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Optional

import numpy as np
import pandas as pd

STAGES = ("load", "repair", "sample", "coarse", "icp", "evaluate", "total")
AGG_METRICS = [
    ("rotation_error_deg", "median"), ("rotation_error_deg", "p90"),
    ("translation_error", "median"), ("translation_error", "p90"),
    ("translation_error_rel", "median"),
    ("coarse_rotation_error_deg", "median"),
    ("rms", "median"), ("fitness", "median"), ("icp_iterations", "median"),
    *[(f"time_{s}_s", "median") for s in STAGES[1:]],
]
IGNORED_VARYING = {"seed"}
MD_COLUMNS = ["runs", "failed", "success_rate", "rotation_error_deg_median", "rotation_error_deg_p90",
              "translation_error_median", "translation_error_p90", "coarse_rotation_error_deg_median",
              "time_coarse_s_median", "time_icp_s_median", "time_total_s_median"]
"""Columns of the Markdown table (report.csv has them all)."""
COMPARE_COLUMNS = ["runs", "success_rate", "rotation_error_deg_median", "translation_error_median",
                   "time_coarse_s_median", "time_total_s_median"]

CI_LEVEL = 0.95
"""Confidence level of every interval in the reports."""
BOOTSTRAP_RESAMPLES = 2000
"""Resamples of the bootstrap percentile interval of a median (seeded: a report is reproducible)."""


def bootstrap_median_ci(x, level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
                        seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the median of ``x`` (NaNs dropped): the ``(1 - level) / 2`` and
    ``(1 + level) / 2`` quantiles of the medians of ``resamples`` resamples with replacement (seeded). One value:
    that value twice; none: NaN twice."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    if len(x) == 1 or np.all(x == x[0]):
        return float(x[0]), float(x[0])
    idx = np.random.default_rng(seed).integers(0, len(x), size=(resamples, len(x)))
    med = np.median(x[idx], axis=1)
    lo, hi = np.quantile(med, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def iqr_interval(x) -> tuple[float, float]:
    """The interquartile range of ``x`` (NaNs dropped): its 25th and 75th percentiles (linear interpolation)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    lo, hi = np.quantile(x, [0.25, 0.75])
    return float(lo), float(hi)


def wilson_interval(k: float, n: int, level: float = CI_LEVEL) -> tuple[float, float]:
    """Wilson score interval of a success rate ``k / n`` at ``level`` (z = 1.96 for 95 %): centre
    ``(p + z^2 / 2n) / (1 + z^2 / n)``, half-width ``z sqrt(p (1 - p) / n + z^2 / 4n^2) / (1 + z^2 / n)``.
    No runs: NaN twice."""
    from statistics import NormalDist

    if n <= 0:
        return float("nan"), float("nan")
    z = NormalDist().inv_cdf((1 + level) / 2)
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def interval(x, how: str = "bootstrap") -> tuple[float, float]:
    """The interval of the median of ``x`` named by ``how`` (``bootstrap`` or ``iqr``)."""
    if how == "bootstrap":
        return bootstrap_median_ci(x)
    if how == "iqr":
        return iqr_interval(x)
    raise ValueError(f"report.interval must be bootstrap or iqr, got '{how}'")


def interval_name(how: str) -> str:
    return "95 % bootstrap CI of the median" if how == "bootstrap" else "interquartile range"


@dataclass
class ReportParams:
    """What the report of an experiment's sweep shows (the ``report`` block of the config)."""

    enabled: bool = False
    """Write the report when a ``-m`` sweep (or an experiment run as one) ends."""
    out: Optional[str] = None
    """Folder for report.md, report.csv and the PNG plots; null: outputs/reports/<experiment>. Relative paths
    are taken from the current directory. The committed reports in experiments/ are rewritten only when asked
    (``report.out=experiments/NAME``)."""
    group_by: list[str] = field(default_factory=list)
    """Config keys whose values are the compared methods (e.g. ``[group.salience]``); empty: the parameters
    that vary between the runs."""
    x: Optional[str] = None
    """A numeric swept key to plot errors and times against (e.g. ``sampler.density``); null: no such plot."""
    per: Optional[str] = None
    """A key to show success per value of (e.g. ``data.pair``): a table and a heat map; null: none."""
    title: Optional[str] = None
    """Heading of the report; null: the experiment name."""
    notes: Optional[str] = None
    """A paragraph put under the heading (what the experiment asks, how to read it)."""
    metrics: list[str] = field(default_factory=list)
    """Further metrics whose median per group the table shows (e.g. ``dev_rms_um``, ``landmark_coarse_rms``)."""
    interval: str = "bootstrap"
    """The interval shown beside every median: ``bootstrap`` (percentile 95 % confidence interval of the median,
    2000 seeded resamples of the group's runs) or ``iqr`` (interquartile range, 25th to 75th percentile). Success
    rates always get the Wilson 95 % score interval."""
    bin_by: Optional[str] = None
    """A per-run metric (e.g. ``gt_overlap``, a share 0..1) whose bins get their own success table and plot; null:
    none."""
    bin_edges: list[float] = field(default_factory=lambda: [0.0, 0.1, 0.2, 0.4, 0.6, 0.8, 1.0])
    """Edges of the ``bin_by`` bins (left-closed, the last also right-closed), in that metric's unit."""
    bin_metrics: list[str] = field(default_factory=list)
    """Metrics whose median (with its interval) per bin and group the report also tabulates."""
    curves: list[str] = field(default_factory=list)
    """Metrics plotted against ``x`` (robustness curves), one panel each: ``success`` as a rate with its Wilson
    band, any other as the median with its interval band (e.g. ``[success, keypoint_repeatability]``)."""
    showcase: Optional[dict[str, Any]] = None
    """Config values selecting one run to show in detail (e.g. ``{data.noise: 0.02, data.pick_error: 0.3}``):
    its key metrics, its per-part table and its PNG pictures are copied into the report; null: none."""


def load_runs(experiment: str, uri: str | None = None, parent: str | None = None) -> pd.DataFrame:
    """Child runs of ``parent`` (``latest``: the newest sweep), or every non-parent run of the experiment."""
    from scanreg.tracking import MlflowTracking, _quiet_mlflow

    _quiet_mlflow()
    import mlflow

    tr = MlflowTracking(MlflowTracking.Params(uri=uri, experiment=experiment))
    mlflow.set_tracking_uri(tr.uri)
    exp = mlflow.get_experiment_by_name(experiment)
    if exp is None:
        raise SystemExit(f"error: no experiment '{experiment}' in {tr.uri}")
    parent_row = None
    if parent:
        flt = "tags.`scanreg.sweep` = 'parent'" + ("" if parent == "latest" else f" and attributes.run_id = '{parent}'")
        parents = mlflow.search_runs([exp.experiment_id], filter_string=flt, order_by=["start_time DESC"],
                                     max_results=1)
        if parents.empty:
            raise SystemExit(f"error: experiment '{experiment}' has no sweep"
                             + ("" if parent == "latest" else f" with parent run {parent}")
                             + " (run 'scanreg -m ...' first, pass --parent all for its single runs, or name "
                             "another with --experiment NAME; without --experiment: the newest sweep of any)")
        parent_row = parents.iloc[0]
        parent = parent_row["run_id"]
    flt = f"tags.mlflow.parentRunId = '{parent}'" if parent else ""
    df = mlflow.search_runs([exp.experiment_id], filter_string=flt, max_results=100000)
    if "tags.scanreg.sweep" in df:
        df = df[df["tags.scanreg.sweep"] != "parent"]
    if df.empty:
        raise SystemExit(f"error: no runs found in experiment '{experiment}'" + (f" under parent {parent}" if parent else ""))
    df = df.sort_values("start_time").reset_index(drop=True)
    df.attrs.update(parent=parent, uri=tr.uri, experiment=experiment,
                    parent_tags={k[5:]: v for k, v in parent_row.items() if k.startswith("tags.")}
                    if parent_row is not None else {})
    return df


def latest_sweep_experiment(uri: str | None = None) -> str:
    """The MLflow experiment holding the newest sweep (parent run) of the store, for a bare ``scanreg-report``."""
    from scanreg.tracking import MlflowTracking, _quiet_mlflow

    _quiet_mlflow()
    import mlflow

    tr = MlflowTracking(MlflowTracking.Params(uri=uri))
    mlflow.set_tracking_uri(tr.uri)
    client = mlflow.MlflowClient(tr.uri)
    exps = client.search_experiments()
    runs = client.search_runs([e.experiment_id for e in exps], filter_string="tags.`scanreg.sweep` = 'parent'",
                              order_by=["attributes.start_time DESC"], max_results=1) if exps else []
    if not runs:
        names = ", ".join(sorted(e.name for e in exps if e.name != "Default")) or "none"
        raise SystemExit(f"error: no sweep in {tr.uri} (run 'scanreg -m ...' first, or name an experiment with "
                         f"--experiment NAME --parent all; experiments: {names})")
    return next(e.name for e in exps if e.experiment_id == runs[0].info.experiment_id)


def find_column(key: str, df: pd.DataFrame, bare: bool = True) -> str | None:
    """The column holding a config key, tag or metric (``params.``, ``tags.``, ``metrics.`` prefixed, then the
    key itself when ``bare``), or None."""
    for c in (f"params.{key}", f"tags.{key}", f"metrics.{key}", *([key] if bare else [])):
        if c in df.columns:
            return c
    return None


def column_for(key: str, df: pd.DataFrame) -> str:
    c = find_column(key, df)
    if c is not None:
        return c
    raise SystemExit(f"error: unknown group-by key '{key}'; e.g. {', '.join(varying_keys(df)) or 'sampler.n_points'}")


def varying_keys(df: pd.DataFrame) -> list[str]:
    """Config keys whose values differ between runs; a stage group whose implementation varies is shown by its
    choice (``group.X``) instead of every parameter of it."""
    switched = {c[len("tags.group."):] for c in df.columns
                if c.startswith("tags.group.") and df[c].nunique(dropna=False) > 1}
    keys = [f"group.{g}" for g in sorted(switched)]
    for c in df.columns:
        if c.startswith("params.") and df[c].nunique(dropna=False) > 1:
            k = c[len("params."):]
            if k.split(".")[0] in switched:
                continue
            if k.split(".")[-1] not in IGNORED_VARYING and not k.endswith(("_seed", ".seed")):
                keys.append(k)
    return keys


def _typed(s: pd.Series) -> pd.Series:
    num = pd.to_numeric(s, errors="coerce")
    return num if num.notna().all() else s.astype(str)


def canonical(v) -> str:
    """One exact text per group value, for tables, plot labels and matching alike: the run values are MLflow
    strings ("1.0", "20000"), the typed ones numbers; both give "1" and "20000" here (never a rounded "2e+04",
    which could also merge two groups)."""
    if isinstance(v, (bool, np.bool_)):
        return str(v)
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if np.isnan(v):
            return "nan"
        if float(v).is_integer() and abs(v) < 1e15:
            return str(int(v))
        return repr(float(v))
    return str(v)


def group_labels(df: pd.DataFrame, group_by: list[str]) -> pd.Series:
    """Each run's group as one canonical label (``canonical`` of the typed value of every key, joined by
    " / "); the same function labels the summary rows, the plots and the per-value table."""
    if not group_by:
        return pd.Series(["all"] * len(df), index=df.index)
    typed = [_typed(df[column_for(k, df)]) for k in group_by]
    return pd.Series([" / ".join(canonical(t.loc[i]) for t in typed) for i in df.index], index=df.index,
                     dtype=object)


def save_figure(fig, path: Path) -> Path:
    """Lay out, write (110 dpi) and close a report figure; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def success_stats(d: pd.DataFrame) -> dict:
    """A group of runs' successes: ``successes``, ``success_rate`` and its Wilson interval (``success_lo``,
    ``success_hi``); a run that failed (not FINISHED) counts as a failure."""
    ok = d[d["status"] == "FINISHED"]
    k = int((ok.get("metrics.success", pd.Series(dtype=float)).fillna(0) > 0.5).sum())
    lo, hi = wilson_interval(k, len(d))
    return {"successes": k, "success_rate": k / len(d), "success_lo": lo, "success_hi": hi}


def median_stats(ok: pd.DataFrame, metrics, how: str) -> dict:
    """The median ``M_median`` of each metric ``M`` logged by the finished runs ``ok``, with its interval
    ``M_lo``, ``M_hi`` (``how``: see :func:`interval`); a metric no run logged is left out."""
    row = {}
    for m in metrics:
        c = f"metrics.{m}"
        if c in ok and ok[c].notna().any():
            v = ok[c].dropna().values
            row[f"{m}_median"] = float(np.median(v))
            row[f"{m}_lo"], row[f"{m}_hi"] = interval(v, how)
    return row


def summarize(df: pd.DataFrame, group_by: list[str], extra: list[str] = (), how: str = "bootstrap") -> pd.DataFrame:
    """One row per group: runs, failed, success rate with its Wilson interval (``success_lo``, ``success_hi``),
    error quantiles, median stage times (and the median of each ``extra`` metric); every median ``M_median``
    with its interval ``M_lo``, ``M_hi`` (``how``: see :func:`interval`)."""
    cols = [column_for(k, df) for k in group_by]
    work = df.copy()
    for c in cols:
        work[c] = _typed(work[c])
    rows = []
    groups = work.groupby(cols, dropna=False, sort=True) if cols else [((), work)]
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        ok = g[g["status"] == "FINISHED"]
        row = dict(zip(group_by, key))
        row["runs"] = len(g)
        row["failed"] = int((g["status"] != "FINISHED").sum())
        if "metrics.success" in g:  # runs with ground truth; a group whose runs all failed has 0 successes
            row.update(success_stats(g))
        for m, agg in [*AGG_METRICS, *[(e, "median") for e in extra if (e, "median") not in AGG_METRICS]]:
            c = f"metrics.{m}"
            if c in ok and ok[c].notna().any():
                s = ok[c].dropna()
                row[f"{m}_{agg}"] = float(s.median() if agg == "median" else s.quantile(0.9))
                if agg == "median":
                    row[f"{m}_lo"], row[f"{m}_hi"] = interval(s.values, how)
        row["_label"] = " / ".join(canonical(v) for v in key) if group_by else "all"
        rows.append(row)
    return pd.DataFrame(rows)


def per_table(df: pd.DataFrame, group_by: list[str], per: str) -> pd.DataFrame:
    """Success rate for each value of ``per`` (rows) and each group (columns)."""
    work = df.copy()
    work["_per"] = _typed(work[column_for(per, df)])
    work["_grp"] = group_labels(work, group_by)
    work["_ok"] = (work["status"] == "FINISHED") & (work.get("metrics.success", 0).fillna(0) > 0.5)
    t = work.pivot_table(index="_per", columns="_grp", values="_ok", aggfunc="mean")
    t.index.name, t.columns.name = per, None
    return t


def fmt_interval(v, lo, hi) -> str:
    """``median [lo, hi]`` (``–`` when missing)."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "–"
    if lo is None or (isinstance(lo, float) and np.isnan(lo)):
        return fmt_value(v)
    return f"{fmt_value(v)} [{fmt_value(lo)}, {fmt_value(hi)}]"


def fmt_success(k, n, lo, hi) -> str:
    """``k/n = rate % [lo, hi]`` with the Wilson interval in percent."""
    if n is None or not n or k is None or (isinstance(k, float) and np.isnan(k)):
        return "–"
    return f"{int(k)}/{int(n)} = {100 * k / n:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


TABLE_MEDIANS = ["rotation_error_deg", "translation_error", "coarse_rotation_error_deg"]
TABLE_TIMES = ["time_coarse_s", "time_icp_s", "time_total_s"]


def display_table(table: pd.DataFrame, group_by: list[str], metrics: list[str]) -> pd.DataFrame:
    """The Markdown table: the group keys, runs, failed, success with its Wilson interval, then every median with
    its interval (errors, ``metrics``, stage times)."""
    out = pd.DataFrame({k: table[k] for k in group_by})
    out["runs"] = table["runs"]
    out["failed"] = table["failed"]
    if "success_rate" in table:
        out["success [Wilson 95 %]"] = [fmt_success(r.get("successes"), r["runs"], r.get("success_lo"),
                                                    r.get("success_hi")) for _, r in table.iterrows()]
    for m in [*TABLE_MEDIANS, *[m for m in metrics if m not in TABLE_MEDIANS], *TABLE_TIMES]:
        if f"{m}_median" in table:
            out[m] = [fmt_interval(r[f"{m}_median"], r.get(f"{m}_lo"), r.get(f"{m}_hi")) for _, r in table.iterrows()]
    return out


def bin_labels(edges: list[float]) -> list[str]:
    return [f"[{canonical(a)}, {canonical(b)}{']' if i == len(edges) - 2 else ')'}"
            for i, (a, b) in enumerate(zip(edges[:-1], edges[1:]))]


def assign_bins(values: pd.Series, edges: list[float]) -> pd.Series:
    """The bin label of each value: left-closed bins, the last right-closed too; outside or NaN: None."""
    labels = bin_labels(edges)
    v = pd.to_numeric(values, errors="coerce").to_numpy(float)
    i = np.searchsorted(np.asarray(edges, float), v, side="right") - 1
    i = np.where(v == edges[-1], len(edges) - 2, i)
    ok = np.isfinite(v) & (i >= 0) & (i < len(labels))
    return pd.Series([labels[j] if o else None for j, o in zip(i, ok)], index=values.index, dtype=object)


def bin_table(df: pd.DataFrame, group_by: list[str], bin_by: str, edges: list[float], metrics: list[str] = (),
              per: str | None = None, how: str = "bootstrap") -> pd.DataFrame:
    """One row per (bin of the metric ``bin_by``, group): runs, successes, success rate with its Wilson interval,
    and the median with its interval of each of ``metrics``. A run that lacks ``bin_by`` (a failed run) takes the
    value of another run of the same ``per`` value (the same scan pair has the same overlap)."""
    col = f"metrics.{bin_by}"
    if col not in df:
        raise SystemExit(f"error: report.bin_by: no metric '{bin_by}' in the runs")
    work = df.copy()
    v = pd.to_numeric(work[col], errors="coerce")
    if per and v.isna().any():
        key = work[column_for(per, work)].astype(str)
        v = v.fillna(v.groupby(key).transform("first"))
    work["_bin"] = assign_bins(v, edges)
    work["_grp"] = group_labels(work, group_by)
    rows = []
    for b in bin_labels(edges):
        for g in sorted(set(work["_grp"])):
            d = work[(work["_bin"] == b) & (work["_grp"] == g)]
            if d.empty:
                continue
            rows.append({bin_by: b, "group": g, "runs": len(d), **success_stats(d),
                         **median_stats(d[d["status"] == "FINISHED"], metrics, how)})
    return pd.DataFrame(rows)


def bin_markdown(bt: pd.DataFrame, bin_by: str, metrics: list[str]) -> list[str]:
    """Success (and each metric's median) per bin (rows) and group (columns)."""
    groups = list(dict.fromkeys(bt["group"]))
    lines = []
    for what in ["success", *[m for m in metrics if f"{m}_median" in bt]]:
        head = f"{bin_by} | " + " | ".join(groups)
        body = []
        for b, d in bt.groupby(bin_by, sort=False):
            cells = []
            for g in groups:
                r = d[d["group"] == g]
                if r.empty:
                    cells.append("–")
                    continue
                r = r.iloc[0]
                cells.append(fmt_success(r["successes"], r["runs"], r["success_lo"], r["success_hi"])
                             if what == "success" else fmt_interval(r.get(f"{what}_median"), r.get(f"{what}_lo"),
                                                                    r.get(f"{what}_hi")))
            body.append(f"| {b} | " + " | ".join(cells) + " |")
        lines += [f"### {what} per {bin_by} bin", "", f"| {head} |", "|" + "---|" * (len(groups) + 1), *body, ""]
    return lines


def fmt_value(v) -> str:
    if isinstance(v, (float, np.floating)):
        if np.isnan(v):
            return "–"
        return f"{v:.4g}"
    return str(v)


def to_markdown(df: pd.DataFrame, index: bool = False) -> str:
    if index:
        df = df.reset_index()
    head = "| " + " | ".join(str(c) for c in df.columns) + " |"
    sep = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(fmt_value(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body])


def compare(a: pd.DataFrame, b: pd.DataFrame, group_by: list[str], name_a: str, name_b: str) -> pd.DataFrame:
    """Two summaries side by side on the group keys (outer join), the main columns of each."""
    cols = [c for c in COMPARE_COLUMNS if c in a.columns or c in b.columns]
    pick = lambda s, n: s[[*group_by, *[c for c in cols if c in s.columns]]].rename(
        columns={c: f"{c} [{n}]" for c in cols})
    if group_by:
        for s in (a, b):
            for k in group_by:
                s[k] = s[k].astype(str)
        return pick(a, name_a).merge(pick(b, name_b), on=group_by, how="outer")
    return pd.concat([pick(a, name_a), pick(b, name_b)], axis=1)


def max_concurrent(df: pd.DataFrame) -> int:
    """The largest number of runs that were running at the same moment (from their start and end times)."""
    if "start_time" not in df or "end_time" not in df:
        return 1
    t = df[["start_time", "end_time"]].dropna()
    events = sorted([(s, 1) for s in t["start_time"]] + [(e, -1) for e in t["end_time"]],
                    key=lambda ev: (ev[0], ev[1]))  # an end before a start at the same instant
    n = best = 0
    for _, d in events:
        n += d
        best = max(best, n)
    return max(best, 1)


def concurrency_note(df: pd.DataFrame) -> tuple[str, str | None]:
    """(how the jobs were launched, a warning when stage times come from jobs that ran concurrently)."""
    ptags = df.attrs.get("parent_tags", {})
    launcher = ptags.get("scanreg.launcher")
    par = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in ptags.items() if k.startswith("scanreg.launcher."))
    n = max_concurrent(df)
    how = (f"launcher {launcher}" + (f" ({par})" if par else "") + "; " if launcher else "") + \
        f"at most {n} run(s) at the same time"
    warn = None
    if n > 1:
        warn = (f"up to {n} jobs ran at once: their stage times include the contention for the cores "
                "(for timings: launch=serial)")
    return how, warn


# ---------------------------------------------------------------------------------------------------- plots
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", s)


def make_plots(df: pd.DataFrame, table: pd.DataFrame, group_by: list[str], out: Path, x: str | None,
               per_t: pd.DataFrame | None) -> list[Path]:
    """Success per group, then errors and times against ``x`` (or per group), then success per ``per`` value.
    Every group of ``table`` appears in every plot: the runs are matched to the rows by the same canonical
    label (:func:`group_labels`)."""
    plt = _plt()
    from matplotlib.ticker import NullLocator

    paths: list[Path] = []
    labels = list(table["_label"]) if "_label" in table else ["all"] * len(table)
    keys = " / ".join(group_by) or "runs"
    ok = df[df["status"] == "FINISHED"].copy()
    ok["_g"] = group_labels(ok, group_by)
    missing = sorted(set(ok["_g"]) - set(labels))
    if missing:  # cannot happen with one labelling function; never drop data without a word
        raise ValueError(f"runs of group(s) {', '.join(missing)} have no row in the table")

    def ticks(ax, names):
        many = len(names) > 4 or max((len(n) for n in names), default=0) > 12
        ax.set_xticks(range(len(names)), names, rotation=45 if many else 0, ha="right" if many else "center",
                      fontsize=7)
        ax.set_xlabel(keys)

    if "success_rate" in table:  # success per method
        fig, ax = plt.subplots(figsize=(max(4.5, 0.6 * len(table) + 2), 3.4))
        ax.bar(range(len(table)), table["success_rate"].fillna(0) * 100, color="tab:blue")
        ticks(ax, labels)
        ax.set_ylabel("success [%]")
        ax.set_ylim(0, 100)
        ax.set_title("success rate (rotation and translation\nerror within the thresholds)", fontsize=9)
        paths.append(save_figure(fig, out / "success.png"))

    if x and "metrics.rotation_error_deg" in ok:
        xc = column_for(x, ok)
        ok["_x"] = pd.to_numeric(ok[xc], errors="coerce")
        others = [k for k in group_by if k != x]
        ok["_g2"] = group_labels(ok, others)
        if ok["_x"].notna().any():
            fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
            for g, d in ok.groupby("_g2", sort=True):
                pre = f"{g} " if others else ""
                s = d.groupby("_x")
                med = s["metrics.rotation_error_deg"].median()
                p90 = s["metrics.rotation_error_deg"].quantile(0.9)
                line = axes[0].plot(med.index, med.values, "o-", label=f"{pre}median")[0]
                axes[0].plot(p90.index, p90.values, "--", color=line.get_color(), label=f"{pre}p90")
                if "metrics.time_total_s" in d:
                    t = s["metrics.time_total_s"].median()
                    axes[1].plot(t.index, t.values, "o-", color=line.get_color(), label=f"{pre}total")
                    if "metrics.time_coarse_s" in d:
                        tc = s["metrics.time_coarse_s"].median()
                        axes[1].plot(tc.index, tc.values, ":", color=line.get_color(), label=f"{pre}coarse")
            axes[0].set_yscale("log")
            axes[0].set_ylabel("rotation error [deg]")
            axes[1].set_ylabel("median time [s]")
            xs = np.sort(ok["_x"].dropna().unique())
            for ax in axes:
                ax.set_xlabel(x)
                if (xs > 0).all() and xs.max() / xs.min() >= 10:
                    ax.set_xscale("log")
                ax.set_xticks(xs, [canonical(v) for v in xs], fontsize=7)
                ax.xaxis.set_minor_locator(NullLocator())  # x only: a log y axis within a decade needs its minor labels
                ax.legend(fontsize=7, title=" / ".join(others) or None, title_fontsize=7)
            paths.append(save_figure(fig, out / f"error_time_vs_{_slug(x)}.png"))
    elif "metrics.rotation_error_deg" in ok and len(ok):  # error distribution and stage times per method
        names = list(dict.fromkeys(labels))
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
        data = [ok.loc[ok["_g"] == n, "metrics.rotation_error_deg"].dropna().clip(lower=1e-3).values for n in names]
        axes[0].boxplot([d if len(d) else [np.nan] for d in data], positions=range(len(names)))
        ticks(axes[0], names)
        axes[0].set_yscale("log")
        axes[0].set_ylabel("rotation error [deg]")
        bottom = np.zeros(len(names))
        for s in STAGES[1:-1]:
            c = f"metrics.time_{s}_s"
            if c not in ok:
                continue
            v = np.array([ok.loc[ok["_g"] == n, c].median() for n in names])
            v = np.nan_to_num(v)
            axes[1].bar(range(len(names)), v, bottom=bottom, label=s)
            bottom += v
        ticks(axes[1], names)
        axes[1].set_ylabel("median time per stage [s]")
        if bottom.any():  # no stage times logged: no legend to draw
            axes[1].legend(fontsize=7)
        paths.append(save_figure(fig, out / "errors_times.png"))

    if per_t is not None and not per_t.empty:
        fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * per_t.shape[1] + 3), max(3.0, 0.22 * len(per_t) + 1.2)))
        im = ax.imshow(per_t.values * 100, aspect="auto", cmap="RdYlGn", vmin=0, vmax=100)
        ax.set_yticks(range(len(per_t)), [str(i) for i in per_t.index], fontsize=7)
        ax.set_xticks(range(per_t.shape[1]), list(per_t.columns), rotation=45 if per_t.shape[1] > 3 else 0,
                      ha="right" if per_t.shape[1] > 3 else "center", fontsize=7)
        ax.set_ylabel(per_t.index.name)
        fig.colorbar(im, ax=ax, label="success [%]")
        paths.append(save_figure(fig, out / f"success_per_{_slug(per_t.index.name)}.png"))
    return paths


def plot_bins(bt: pd.DataFrame, bin_by: str, out: Path) -> Path:
    """Success per bin, one bar per group, with the Wilson interval as error bars."""
    plt = _plt()
    bins = list(dict.fromkeys(bt[bin_by]))
    groups = list(dict.fromkeys(bt["group"]))
    w = 0.8 / max(1, len(groups))
    fig, ax = plt.subplots(figsize=(max(5.0, 0.35 * len(bins) * len(groups) + 2.5), 3.6))
    for j, g in enumerate(groups):
        d = bt[bt["group"] == g].set_index(bin_by).reindex(bins)
        xs = np.arange(len(bins)) + (j - (len(groups) - 1) / 2) * w
        r = d["success_rate"].to_numpy(float) * 100
        err = np.vstack([r - d["success_lo"].to_numpy(float) * 100, d["success_hi"].to_numpy(float) * 100 - r])
        ax.bar(xs, np.nan_to_num(r), w, yerr=np.nan_to_num(err), capsize=2, label=g)
    ax.set_xticks(range(len(bins)), [f"{b}\n(n={int(bt[bt[bin_by] == b]['runs'].iloc[0])})" for b in bins],
                  fontsize=7)
    ax.set_xlabel(bin_by)
    ax.set_ylabel("success [%] (Wilson 95 %)")
    ax.set_ylim(0, 105)
    ax.legend(fontsize=7)
    return save_figure(fig, out / f"success_by_{_slug(bin_by)}.png")


def curve_table(df: pd.DataFrame, group_by: list[str], x: str, curves: list[str], how: str) -> pd.DataFrame:
    """One row per (group without ``x``, value of ``x``): runs and, per curve metric, the success rate with its
    Wilson interval or the median with its interval."""
    xc = column_for(x, df)
    others = [k for k in group_by if k != x]
    work = df.copy()
    work["_x"] = pd.to_numeric(work[xc], errors="coerce")
    work["_g"] = group_labels(work, others)
    rows = []
    for (g, xv), d in work.dropna(subset=["_x"]).groupby(["_g", "_x"], sort=True):
        row = {"group": g, x: xv, "runs": len(d), **(success_stats(d) if "success" in curves else {}),
               **median_stats(d[d["status"] == "FINISHED"], [m for m in curves if m != "success"], how)}
        rows.append(row)
    return pd.DataFrame(rows)


def plot_curves(ct: pd.DataFrame, x: str, curves: list[str], out: Path, how: str) -> Path:
    """Robustness curves: each metric of ``curves`` against ``x``, one line per group, its interval as a band."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.6), squeeze=False)
    for ax, m in zip(axes[0], curves):
        col, lo, hi = ("success_rate", "success_lo", "success_hi") if m == "success" else \
            (f"{m}_median", f"{m}_lo", f"{m}_hi")
        if col not in ct:
            ax.set_title(f"{m}: not logged", fontsize=8)
            continue
        scale = 100 if m == "success" else 1
        for g, d in ct.groupby("group", sort=True):
            d = d.sort_values(x)
            line = ax.plot(d[x], d[col] * scale, "o-", label=g)[0]
            ax.fill_between(d[x], d[lo] * scale, d[hi] * scale, color=line.get_color(), alpha=0.15)
        if m == "success":
            ax.set_ylim(0, 105)
        ax.set_xlabel(x)
        ax.set_ylabel("success [%] (Wilson 95 %)" if m == "success" else f"{m}\n(median, {interval_name(how)})",
                      fontsize=8)
        ax.set_xticks(sorted(ct[x].unique()), [canonical(v) for v in sorted(ct[x].unique())], fontsize=7)
        ax.legend(fontsize=7)
    return save_figure(fig, out / f"robustness_vs_{_slug(x)}.png")


def curve_display(ct: pd.DataFrame, x: str, curves: list[str]) -> pd.DataFrame:
    out = pd.DataFrame({"group": ct["group"], x: ct[x], "runs": ct["runs"]})
    for m in curves:
        if m == "success" and "success_rate" in ct:
            out["success [Wilson 95 %]"] = [fmt_success(r["successes"], r["runs"], r["success_lo"],
                                                        r["success_hi"]) for _, r in ct.iterrows()]
        elif f"{m}_median" in ct:
            out[m] = [fmt_interval(r[f"{m}_median"], r[f"{m}_lo"], r[f"{m}_hi"]) for _, r in ct.iterrows()]
    return out


def run_time_line(df: pd.DataFrame) -> str:
    """Wall-clock time of the sweep (first start to last end) and the sum of the runs' pipeline times."""
    t0 = pd.to_datetime(df["start_time"]).min()
    t1 = pd.to_datetime(df["end_time"]).max() if "end_time" in df else pd.NaT
    wall = (t1 - t0).total_seconds() if pd.notna(t1) and pd.notna(t0) else float("nan")
    busy = float(df["metrics.time_total_s"].sum()) if "metrics.time_total_s" in df else float("nan")
    return (f"- run time: {wall / 60:.1f} min wall clock for {len(df)} runs (first start to last end); the runs' "
            f"own pipeline times sum to {busy / 60:.1f} min")


def configuration_line(df: pd.DataFrame) -> str:
    """The stage choices of the runs (``tags.group.*``): one value, or the values compared."""
    parts = []
    for c in sorted(c for c in df.columns if c.startswith("tags.group.")):
        vals = sorted(set(df[c].dropna().astype(str)))
        if vals:
            parts.append(f"{c[len('tags.group.'):]}={'|'.join(vals)}")
    return "- stages: " + (", ".join(parts) or "unknown") + " (the defaults of that commit unless overridden above)"


# --------------------------------------------------------------------------------------------------- report
def write_report(df: pd.DataFrame, p: ReportParams, out: Path, compare_to: pd.DataFrame | None = None,
                 plots: bool = True) -> dict:
    """Write report.md, report.csv (and per.csv, compare.csv) and PNG plots into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    group_by = list(p.group_by) or varying_keys(df)
    how = p.interval
    interval(np.array([0.0, 1.0]), how)  # a bad name fails before any table is written
    table = summarize(df, group_by, list(p.metrics), how)
    table.drop(columns="_label").to_csv(out / "report.csv", index=False)
    per_t = per_table(df, group_by, p.per) if p.per else None
    if per_t is not None:
        per_t.to_csv(out / "per.csv")
    figs = make_plots(df, table, group_by, out, p.x, per_t) if plots else []
    bt = bin_table(df, group_by, p.bin_by, list(p.bin_edges), list(p.bin_metrics), p.per, how) if p.bin_by else None
    if bt is not None:
        bt.to_csv(out / f"by_{_slug(p.bin_by)}.csv", index=False)
        if plots:
            figs.append(plot_bins(bt, p.bin_by, out))
    ct = curve_table(df, group_by, p.x, list(p.curves), how) if p.x and p.curves else None
    if ct is not None:
        ct.to_csv(out / f"curves_vs_{_slug(p.x)}.csv", index=False)
        if plots:
            figs.append(plot_curves(ct, p.x, list(p.curves), out, how))

    exp = df.attrs.get("experiment", "?")
    ptags = df.attrs.get("parent_tags", {})
    commits = sorted(set(df.get("tags.scanreg.git_commit", pd.Series(dtype=str)).dropna()))
    command = ptags.get("scanreg.command") or (f"scanreg -m {ptags['scanreg.overrides']}" if "scanreg.overrides" in ptags else None)
    when = pd.to_datetime(df["start_time"]).min()
    n_fail = int((df["status"] != "FINISHED").sum())
    jobs, warn = concurrency_note(df)
    lines = [f"# {p.title or 'Experiment ' + exp}", ""]
    if p.notes:
        lines += [" ".join(p.notes.split()), ""]
    lines += [
        "## How this was produced", "",
        f"- command: `{command}`" if command else f"- runs of MLflow experiment `{exp}`",
        f"- commit: {', '.join(commits) or 'unknown'}",
        f"- runs: {len(df)} ({n_fail} failed), started {when:%Y-%m-%d %H:%M} UTC"
        + (f", sweep parent run `{df.attrs['parent']}`" if df.attrs.get("parent") else ""),
        run_time_line(df),
        configuration_line(df),
        f"- jobs: {jobs}",
        f"- tracking store: `{df.attrs.get('uri')}` (experiment `{exp}`)",
        f"- report: `scanreg-report --experiment {exp}" + (f" --group-by {','.join(group_by)}" if group_by else "")
        + (f" --x {p.x}" if p.x else "") + (f" --per {p.per}" if p.per else "") + "`, "
        + f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC",
        "",
        "Success: rotation error < `evaluate.success_rotation_deg` (2°) and translation error < "
        "`evaluate.success_translation` (1 %) of the target's bounding-box diagonal; a failed run counts as a "
        "failure. Errors are against the ground truth, in degrees and input units; times are medians in seconds.",
        "",
        *([f"**Warning: {warn}.**", ""] if warn else []),
        f"## Results by {', '.join(group_by) or 'run'}", "",
        f"Each cell: the median over the group's runs (seeds, poses, pairs) [{interval_name(how)}]; success: "
        "successes/runs = rate [Wilson 95 % score interval]. Two groups differ only where their intervals do not "
        "overlap. Every column (p90 errors, fitness, each stage's time) is in report.csv.", "",
        to_markdown(display_table(table, group_by, list(p.metrics))), "",
    ]
    if bt is not None:
        lines += [f"## Success by {p.bin_by}", "",
                  f"Runs binned by `{p.bin_by}`; cells: successes/runs = rate [Wilson 95 %]"
                  + (f", and medians [{interval_name(how)}]" if p.bin_metrics else "") + f". by_{_slug(p.bin_by)}.csv "
                  "has the numbers.", "", *bin_markdown(bt, p.bin_by, list(p.bin_metrics))]
    if ct is not None:
        lines += [f"## Robustness against {p.x}", "",
                  f"Per value of `{p.x}`: success [Wilson 95 %] and medians [{interval_name(how)}]; "
                  f"curves_vs_{_slug(p.x)}.csv has the numbers.", "",
                  to_markdown(curve_display(ct, p.x, list(p.curves))), ""]
    if per_t is not None:
        lines += [f"## Success per {p.per}", "", to_markdown((per_t * 100).round(0), index=True), ""]
    if compare_to is not None:
        other = summarize(compare_to, [k for k in group_by if _has_key(compare_to, k)])
        cmp = compare(table.copy(), other, [k for k in group_by if _has_key(compare_to, k)], exp,
                      compare_to.attrs.get("experiment", "other"))
        cmp.to_csv(out / "compare.csv", index=False)
        lines += [f"## Compared with experiment `{compare_to.attrs.get('experiment')}`", "", to_markdown(cmp), ""]
    if p.showcase:
        lines += showcase_section(df, dict(p.showcase), out)
    if figs:
        lines += ["## Plots", ""] + [f"![{f.stem}]({f.name})" for f in figs] + [""]
    if n_fail:
        reasons = df.loc[df["status"] != "FINISHED", "tags.error"] if "tags.error" in df else pd.Series(dtype=str)
        lines += ["## Failed runs", ""] + [f"- {r}" for r in reasons.fillna("(no reason recorded)").value_counts().index] + [""]
    (out / "report.md").write_text("\n".join(lines))
    return {"table": table, "per": per_t, "paths": [out / "report.md", out / "report.csv", *figs], "warning": warn}


def showcase_section(df: pd.DataFrame, sel: dict, out: Path) -> list[str]:
    """One run in detail: the first finished run matching ``sel``, its metrics, part table and pictures."""
    import shutil

    ok = df["status"] == "FINISHED"
    for k, v in sel.items():
        col = column_for(k, df)
        ok &= df[col].astype(str) == str(v)
    if not ok.any():
        return ["## Showcase run", "", f"No finished run matches {sel}.", ""]
    row = df[ok].iloc[0]
    run_dir = Path(str(row.get("tags.scanreg.run_dir", "")))
    title = ", ".join(f"{k}={v}" for k, v in sel.items())
    lines = [f"## Showcase run: {title}", "", f"MLflow run `{row['run_id']}`, run directory `{run_dir}`.", ""]
    metrics = {c[len("metrics."):]: row[c] for c in df.columns if c.startswith("metrics.") and pd.notna(row[c])
               and not re.search(r"_\d+$", c)}
    keys = [k for k in ("coarse_rotation_error_deg", "rotation_error_deg", "coarse_translation_error",
                        "translation_error", "landmark_coarse_rms", "landmark_final_rms") if k in metrics]
    keys += [k for k in metrics if k.startswith("dev_")]
    if keys:
        lines += ["| metric | value |", "|---|---|"] + [f"| {k} | {fmt_value(float(metrics[k]))} |" for k in keys] + [""]
    for csv in sorted(run_dir.glob("deviation_*.csv")) if run_dir.is_dir() else []:
        part = pd.read_csv(csv)
        plural = csv.stem[len("deviation_"):]
        lines += [f"### Per {'tooth' if plural == 'teeth' else plural.removesuffix('s')}", "", to_markdown(part), ""]
        shutil.copy(csv, out / f"showcase_{csv.name}")
    view = run_dir / "view3d.html"
    if view.is_file():  # the interactive 3D view (self-contained HTML: opens without a network)
        shutil.copy(view, out / "showcase_view3d.html")
        lines += ["Interactive 3D view (source before and after alignment over the target, deviation colours, "
                  "per-part table): [showcase_view3d.html](showcase_view3d.html)", ""]
    for png in sorted(run_dir.glob("*.png")) if run_dir.is_dir() else []:
        shutil.copy(png, out / f"showcase_{png.name}")
        lines += [f"![{png.stem}](showcase_{png.name})", ""]
    return lines


def _has_key(df: pd.DataFrame, key: str) -> bool:
    return find_column(key, df, bare=False) is not None


def report_for_sweep(cfg, parent_run_id: str, uri: str, experiment: str) -> None:
    """Called when an experiment's sweep ends (``report.enabled``): write its report."""
    from omegaconf import OmegaConf

    from scanreg.registry import make_params

    p = make_params(ReportParams, OmegaConf.to_container(cfg.report, resolve=True), "report")
    out = Path(p.out or Path("outputs") / "reports" / experiment)
    df = load_runs(experiment, uri, parent_run_id)
    res = write_report(df, p, out)
    if res["warning"]:
        print(f"warning: {res['warning']}")
    print(f"report: {res['paths'][0]}")


def main(argv: list[str] | None = None) -> int:
    from scanreg.registry import _one_line_parser

    ap = _one_line_parser()(prog="scanreg-report", description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiment", default=None,
                    help="MLflow experiment name (default: the experiment of the newest sweep in the store)")
    ap.add_argument("--parent", default="latest",
                    help="parent run id of a sweep; 'latest' (default): the newest sweep; 'all': every run")
    ap.add_argument("--group-by", default=None,
                    help="comma-separated config keys (default: the parameters that vary between the runs)")
    ap.add_argument("--x", default=None, help="numeric key to plot errors and times against")
    ap.add_argument("--per", default=None, help="key to show success per value of (e.g. data.pair)")
    ap.add_argument("--compare-to", default=None, metavar="EXPERIMENT",
                    help="another experiment (its latest sweep) to put side by side")
    ap.add_argument("--metrics", default=None, help="comma-separated further metrics to show the median of")
    ap.add_argument("--title", default=None, help="heading of report.md")
    ap.add_argument("--no-plots", action="store_true", help="tables only")
    ap.add_argument("--config", default=None, metavar="EXPERIMENT",
                    help="take the experiment name and the report settings (group-by, x, per, metrics, showcase, "
                         "title, notes, out) from conf/experiment/EXPERIMENT.yaml; other options override them")
    ap.add_argument("--uri", default=None, help="tracking URI (default: $MLFLOW_TRACKING_URI or outputs/mlflow.db)")
    ap.add_argument("--out", default=None, help="folder for the report (default: outputs/reports/<experiment>)")
    a = ap.parse_args(argv)
    base = ReportParams(enabled=True)
    if a.config:
        from omegaconf import OmegaConf

        from scanreg.config import compose
        from scanreg.registry import make_params

        cfg = compose([f"experiment={a.config}"])
        base = make_params(ReportParams, OmegaConf.to_container(cfg.report, resolve=True), "report")
        if a.experiment is None:
            a.experiment = cfg.tracking.experiment
    if a.experiment is None:
        if a.parent not in ("latest",):
            raise SystemExit("error: --parent needs --experiment NAME")
        a.experiment = latest_sweep_experiment(a.uri)
    df = load_runs(a.experiment, a.uri, None if a.parent == "all" else a.parent)
    other = load_runs(a.compare_to, a.uri, "latest" if a.parent != "all" else None) if a.compare_to else None
    from dataclasses import replace

    split = lambda v: [k.strip() for k in v.split(",") if k.strip()]
    p = replace(base, **{k: v for k, v in dict(
        out=a.out, group_by=split(a.group_by) if a.group_by else None, x=a.x, per=a.per, title=a.title,
        metrics=split(a.metrics) if a.metrics else None).items() if v is not None})
    out = Path(p.out or Path("outputs") / "reports" / a.experiment)
    res = write_report(df, p, out, other, plots=not a.no_plots)
    print(f"{len(df)} run(s) of experiment '{a.experiment}'"
          + (f", sweep {df.attrs['parent']}" if df.attrs.get("parent") else ""))
    print(console_table(res["table"], p.group_by or varying_keys(df)))
    if res["warning"]:
        print(f"warning: {res['warning']}")
    print(f"every column: {out / 'report.csv'}; report: {out / 'report.md'}")
    return 0


CONSOLE_COLUMNS = [("runs", "runs"), ("failed", "failed"), ("success_rate", "success"),
                   ("rotation_error_deg_median", "rot_deg"), ("translation_error_median", "transl"),
                   ("time_coarse_s_median", "coarse_s"), ("time_total_s_median", "total_s")]
"""The console's short table: (report.csv column, heading)."""


def console_table(table: pd.DataFrame, group_by: list[str], width: int = 100) -> str:
    """The summary as a table of at most ``width`` columns: the group (its canonical label), runs, success,
    median errors and times; the rest is in report.csv."""
    cols = [(c, h) for c, h in CONSOLE_COLUMNS if c in table]
    head = " / ".join(group_by) or "group"
    rows = [[str(r["_label"]) if "_label" in table else "all", *[fmt_value(r[c]) for c, _ in cols]]
            for _, r in table.iterrows()]
    widths = [max(len(h), *(len(x[i]) for x in rows)) if rows else len(h)
              for i, h in enumerate([head, *[h for _, h in cols]])]
    room = width - sum(widths[1:]) - 2 * len(cols)
    widths[0] = max(8, min(widths[0], room))
    clip = lambda t, w: t if len(t) <= w else t[: w - 1] + "…"
    lines = ["  ".join([clip(head, widths[0]).ljust(widths[0]),
                        *[h.rjust(w) for (_, h), w in zip(cols, widths[1:])]])]
    for x in rows:
        lines.append("  ".join([clip(x[0], widths[0]).ljust(widths[0]),
                                *[v.rjust(w) for v, w in zip(x[1:], widths[1:])]]))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
