"""The report's tables: grouping runs by what varies, success and median statistics with their intervals, bins,
curves, and their Markdown and console forms."""

from __future__ import annotations

import numpy as np
import pandas as pd

from scanreg.app.report.stats import interval, wilson_interval
from scanreg.errors import ConfigError
from scanreg.runner.outputs import clipped, padded, text_columns

STAGES = ("load", "repair", "sample", "coarse", "icp", "evaluate", "total")


AGG_METRICS = [
    ("rotation_error_deg", "median"), ("rotation_error_deg", "p90"),
    ("translation_error", "median"), ("translation_error", "p90"),
    ("translation_error_rel", "median"),
    ("coarse_rotation_error_deg", "median"),
    ("rms", "median"), ("fitness", "median"), ("icp_iterations", "median"),
    *[(f"time_{s}_s", "median") for s in STAGES[1:]],
    ("scans_placed", "median"), ("scan_rotation_error_max_deg", "median"), ("scan_translation_error_max_rel", "median"),
]


IGNORED_VARYING = {"seed"}


MD_COLUMNS = ["runs", "failed", "success_rate", "rotation_error_deg_median", "rotation_error_deg_p90",
              "translation_error_median", "translation_error_p90", "coarse_rotation_error_deg_median",
              "time_coarse_s_median", "time_icp_s_median", "time_total_s_median"]
"""Columns of the Markdown table (report.csv has them all)."""


COMPARE_COLUMNS = ["runs", "success_rate", "rotation_error_deg_median", "translation_error_median",
                   "time_coarse_s_median", "time_total_s_median"]


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
    raise ConfigError(f"unknown group-by key '{key}'; e.g. {', '.join(varying_keys(df)) or 'sampler.n_points'}")


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
            if not is_seed_key(k):
                keys.append(k)
    return keys


def is_seed_key(key: str) -> bool:
    """Whether a config key is a seed (``seed``, ``data.pose_seed``, ``data.perturb_seed``): repeats of one method,
    not a method of its own (:func:`varying_keys`), and part of what names a case (the paired comparison)."""
    return key.split(".")[-1] in IGNORED_VARYING or key.endswith("_seed")


def default_grouping(df: pd.DataFrame, per: str | None = None) -> tuple[list[str], str | None]:
    """The groups a report shows when none are named: the varied keys (:func:`varying_keys`), but the data's
    (``data.*``: the cases, such as ``data.pair``) only when nothing else varies, so that a sweep of methods
    over cases compares the methods (each case was a group of one run); and ``per``, or the one data key dropped
    so, whose table shows each case."""
    keys = varying_keys(df)
    methods = [k for k in keys if not (k.startswith("data.") or k == "group.data")]
    if not methods:
        return keys, per
    cases = [k for k in keys if k not in methods]
    return methods, per if per is not None or len(cases) != 1 else cases[0]


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


def run_success(d: pd.DataFrame) -> pd.Series:
    """Each run's success: 1.0 or 0.0, a run that failed (not FINISHED) 0.0, and NaN for a finished run without
    ground truth (no ``success``: files without data.gt beside runs with it), which is not judged."""
    fin = d["status"] == "FINISHED"
    s = d["metrics.success"] if "metrics.success" in d else pd.Series(np.nan, index=d.index, dtype=float)
    return pd.Series(np.where(fin & s.isna(), np.nan, (fin & (s.fillna(0) > 0.5)).astype(float)), index=d.index)


def success_stats(d: pd.DataFrame) -> dict:
    """A group of runs' successes: ``successes`` of the ``judged`` runs (:func:`run_success`), ``success_rate``
    and its Wilson interval (``success_lo``, ``success_hi``)."""
    v = run_success(d)
    n, k = int(v.notna().sum()), int((v == 1.0).sum())
    lo, hi = wilson_interval(k, n)
    return {"successes": k, "judged": n, "success_rate": k / n if n else float("nan"), "success_lo": lo,
            "success_hi": hi}


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


SHARE_FLAGS = ("coarse_fallback", "coarse_second_look")
"""0/1 metrics shown beside every group as the share of its finished runs that had 1 (``M_share``), when any run
had: the coarse stage replaced the configured keypoints by uniform ones (a comparison of detectors, salience,
compares nothing where it did), and it looked at the pair a second time (wider matching at low overlap)."""


def summarize(df: pd.DataFrame, group_by: list[str], extra: list[str] = (), how: str = "bootstrap") -> pd.DataFrame:
    """One row per group: runs, failed, success rate with its Wilson interval (``success_lo``, ``success_hi``),
    error quantiles, median stage times (and the median of each ``extra`` metric); every median ``M_median``
    with its interval ``M_lo``, ``M_hi`` (``how``: see :func:`interval`)."""
    cols = [column_for(k, df) for k in group_by]
    work = df.copy()
    for c in cols:
        work[c] = _typed(work[c])
    rows = []
    flags = [f for f in SHARE_FLAGS if f"metrics.{f}" in work and bool((work[f"metrics.{f}"] > 0).any())]
    groups = work.groupby(cols, dropna=False, sort=True) if cols else [((), work)]
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        ok = g[g["status"] == "FINISHED"]
        row = dict(zip(group_by, key))
        row["runs"] = len(g)
        row["failed"] = int((g["status"] != "FINISHED").sum())
        # runs with ground truth; a group whose runs all failed has 0 successes; a group whose finished runs had
        # none (files without data.gt in a table with runs that had) has no success rate ("-"), not 0
        if "metrics.success" in g and (ok.empty or ok["metrics.success"].notna().any()):
            row.update(success_stats(g))
        for m, agg in [*AGG_METRICS, *[(e, "median") for e in extra if (e, "median") not in AGG_METRICS]]:
            c = f"metrics.{m}"
            if c in ok and ok[c].notna().any():
                s = ok[c].dropna()
                row[f"{m}_{agg}"] = float(s.median() if agg == "median" else s.quantile(0.9))
                if agg == "median":
                    row[f"{m}_lo"], row[f"{m}_hi"] = interval(s.values, how)
        for f in flags:
            said = ok[f"metrics.{f}"].dropna()
            row[f"{f}_share"] = float(said.mean()) if len(said) else float("nan")
        row["_label"] = " / ".join(canonical(v) for v in key) if group_by else "all"
        rows.append(row)
    return pd.DataFrame(rows)


def per_table(df: pd.DataFrame, group_by: list[str], per: str) -> pd.DataFrame:
    """Success rate for each value of ``per`` (rows) and each group (columns)."""
    work = df.copy()
    work["_per"] = _typed(work[column_for(per, df)])
    work["_grp"] = group_labels(work, group_by)
    work["_ok"] = run_success(work)
    t = work.pivot_table(index="_per", columns="_grp", values="_ok", aggfunc="mean")
    t = t[[g for g in group_order(work, group_by) if g in t.columns]]
    t.index.name, t.columns.name = per, None
    return t


def group_order(df: pd.DataFrame, group_by: list[str]) -> list[str]:
    """The groups' labels (:func:`group_labels`) in the summary's order: by each key's typed value, so that
    densities 200000 and 1000000 come in that order (as text, 1000000 came first)."""
    if not group_by:
        return ["all"]
    typed = pd.DataFrame({f"_k{i}": _typed(df[column_for(k, df)]) for i, k in enumerate(group_by)}, index=df.index)
    typed["_label"] = group_labels(df, group_by)
    ordered = typed.sort_values([f"_k{i}" for i in range(len(group_by))], kind="stable")["_label"]
    return list(dict.fromkeys(ordered))


def per_errors(df: pd.DataFrame, group_by: list[str], per: str) -> pd.DataFrame | None:
    """Median rotation error (degrees, finished runs) for each value of ``per`` (rows) and each group (columns);
    None without ground truth."""
    if "metrics.rotation_error_deg" not in df.columns:
        return None
    work = df[df["status"] == "FINISHED"].copy()
    work["_per"] = _typed(work[column_for(per, df)])
    work["_grp"] = group_labels(work, group_by)
    t = work.pivot_table(index="_per", columns="_grp", values="metrics.rotation_error_deg", aggfunc="median")
    if t.empty:  # no run finished with an error to show
        return None
    t = t[[g for g in group_order(work, group_by) if g in t.columns]]
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


TABLE_SET = ["scans_placed", "scan_rotation_error_max_deg", "scan_translation_error_max_rel"]
"""A scan set's medians: its placed scans and, with ground truth, its worst scan's errors."""
TABLE_TIMES = ["time_coarse_s", "time_icp_s", "time_total_s"]
TABLE_FIT = ["rms", "fitness", "icp_iterations"]
"""The fit's medians, shown instead of the errors when the runs have no ground truth."""


def has_errors(table: pd.DataFrame) -> bool:
    """Whether the summary ``table`` holds errors against a ground truth (else the fit stands in for them)."""
    return f"{TABLE_MEDIANS[0]}_median" in table or f"{TABLE_SET[1]}_median" in table


def display_table(table: pd.DataFrame, group_by: list[str], metrics: list[str]) -> pd.DataFrame:
    """The Markdown table: the group keys, runs, failed, success with its Wilson interval, then every median with
    its interval (errors, ``metrics``, stage times)."""
    out = pd.DataFrame({k: table[k] for k in group_by})
    out["runs"] = table["runs"]
    out["failed"] = table["failed"]
    if "success_rate" in table:
        out["success [Wilson 95 %]"] = [fmt_success(r.get("successes"), r.get("judged", r["runs"]), r.get("success_lo"),
                                                    r.get("success_hi")) for _, r in table.iterrows()]
    for f in SHARE_FLAGS:
        if f"{f}_share" in table:
            out[f"{f} (share of runs)"] = [fmt_value(v) for v in table[f"{f}_share"]]
    fit = [] if has_errors(table) else TABLE_FIT
    shown = TABLE_MEDIANS + TABLE_SET + fit
    for m in [*shown, *[m for m in metrics if m not in shown], *TABLE_TIMES]:
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
        key = work[column_for(per, work)].map(str)
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
                cells.append(fmt_success(r["successes"], r["judged"], r["success_lo"], r["success_hi"])
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
                s[k] = s[k].map(str)
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


def curve_display(ct: pd.DataFrame, x: str, curves: list[str]) -> pd.DataFrame:
    out = pd.DataFrame({"group": ct["group"], x: ct[x], "runs": ct["runs"]})
    for m in curves:
        if m == "success" and "success_rate" in ct:
            out["success [Wilson 95 %]"] = [fmt_success(r["successes"], r["judged"], r["success_lo"],
                                                        r["success_hi"]) for _, r in ct.iterrows()]
        elif f"{m}_median" in ct:
            out[m] = [fmt_interval(r[f"{m}_median"], r[f"{m}_lo"], r[f"{m}_hi"]) for _, r in ct.iterrows()]
    return out


CONSOLE_COUNTS = [("runs", "runs"), ("failed", "failed"), ("success_rate", "success")]
CONSOLE_ERRORS = [("rotation_error_deg_median", "rot_deg"), ("translation_error_median", "transl"),
                  ("scan_rotation_error_max_deg_median", "worst_rot_deg"),
                  ("scan_translation_error_max_rel_median", "worst_transl_rel")]
CONSOLE_FIT = [("rms_median", "rms"), ("fitness_median", "fitness")]
CONSOLE_SET = [("scans_placed_median", "placed"), ("coarse_fallback_share", "fallback"),
               ("coarse_second_look_share", "second_look")]
CONSOLE_TIMES = [("time_coarse_s_median", "coarse_s"), ("time_total_s_median", "total_s")]
"""The console's short table: (report.csv column, heading); the errors, or without ground truth the fit (a scan
set's placed scans, and the share of runs whose coarse stage fell back to uniform keypoints, or looked again,
when any did, beside either)."""


CONSOLE_LENGTHS = {"transl", "rms"}
"""The console's headings of lengths in input units: they name the unit when the runs logged one."""


def console_table(table: pd.DataFrame, group_by: list[str], width: int = 100, unit: str | None = None) -> str:
    """The summary as a table of at most ``width`` columns: the group (its canonical label), runs, success,
    median errors and times; the rest is in report.csv. ``unit``: the runs' input unit, named in the headings of
    lengths (``transl_mm``)."""
    columns = CONSOLE_COUNTS + (CONSOLE_ERRORS if has_errors(table) else CONSOLE_FIT) + CONSOLE_SET + CONSOLE_TIMES
    cols = [(c, f"{h}_{unit}" if unit and h in CONSOLE_LENGTHS else h) for c, h in columns if c in table]
    head = " / ".join(group_by) or "group"
    def cell(r, c):  # success as a count of the runs (as report.md has it), the rest as values
        if c == "success_rate" and "successes" in r and pd.notna(r["successes"]) and pd.notna(r.get("judged")):
            return f"{int(r['successes'])}/{int(r['judged'])}"
        return fmt_value(r[c])

    rows = [[str(r["_label"]) if "_label" in table else "all", *[cell(r, c) for c, _ in cols]]
            for _, r in table.iterrows()]
    # widths in terminal columns (a group named by a file in Chinese or Japanese takes two per character)
    widths = [max(text_columns(h), *(text_columns(x[i]) for x in rows)) if rows else text_columns(h)
              for i, h in enumerate([head, *[h for _, h in cols]])]
    room = width - sum(widths[1:]) - 2 * len(cols)
    widths[0] = max(8, min(widths[0], room))
    lines = ["  ".join([padded(clipped(head, widths[0]), widths[0]),
                        *[padded(h, w, right=True) for (_, h), w in zip(cols, widths[1:])]])]
    for x in rows:
        lines.append("  ".join([padded(clipped(x[0], widths[0]), widths[0]),
                                *[padded(v, w, right=True) for v, w in zip(x[1:], widths[1:])]]))
    return "\n".join(lines)
