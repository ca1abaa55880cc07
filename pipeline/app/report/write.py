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

import re
import shlex
import sys
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from scanreg.app.report.params import ReportParams
from scanreg.app.report.paired import paired_section
from scanreg.app.report.plots import _slug, make_plots, plot_bins, plot_curves
from scanreg.app.report.runs import latest_sweep_experiment, load_runs
from scanreg.app.report.stats import interval, interval_name
from scanreg.app.report.tables import (bin_markdown, bin_table, column_for, compare, concurrency_note, console_table,
                                       curve_display, curve_table, display_table, find_column, fmt_value, per_table,
                                       default_grouping, group_labels, per_errors, summarize, to_markdown)

def run_time_line(df: pd.DataFrame) -> str:
    """Wall-clock time of the sweep (first start to last end) and the sum of the runs' pipeline times."""
    t0 = pd.to_datetime(df["start_time"]).min()
    t1 = pd.to_datetime(df["end_time"]).max() if "end_time" in df else pd.NaT
    wall = (t1 - t0).total_seconds() if pd.notna(t1) and pd.notna(t0) else float("nan")
    busy = float(df["metrics.time_total_s"].sum()) if "metrics.time_total_s" in df else float("nan")
    return (f"- run time: {wall / 60:.1f} min wall clock for {len(df)} runs (first start to last end); the runs' "
            f"own pipeline times sum to {busy / 60:.1f} min")


SET_ONLY_GROUPS = ("graph", "surface")
"""Stage groups that only a scan set's runs use: left out of a pair sweep's stages line."""


def configuration_line(df: pd.DataFrame) -> str:
    """The stage choices of the runs (``tags.group.*``): one value, or the values compared."""
    parts = []
    sets = "metrics.scans_within_tolerance" in df.columns
    for c in sorted(c for c in df.columns if c.startswith("tags.group.")):
        if not sets and c[len("tags.group."):] in SET_ONLY_GROUPS:
            continue  # a pair's runs: the scan-set stages took no part
        vals = sorted(set(df[c].dropna().astype(str)) - {"None", "null"})
        if vals:
            parts.append(f"{c[len('tags.group.'):]}={'|'.join(vals)}")
    return "- stages: " + (", ".join(parts) or "unknown") + " (the defaults of that commit unless overridden above)"


def _check_asked(df: pd.DataFrame, p: ReportParams) -> None:
    """What the report settings ``p`` ask of the runs, checked before anything is written: the metrics
    (:func:`_check_metrics`, warnings) and the key to plot against (:func:`_check_x`, a config error)."""
    _check_metrics(df, {"metrics": p.metrics, "bin_metrics": p.bin_metrics, "curves": p.curves})
    _check_x(df, p.x)


def _check_x(df: pd.DataFrame, x: str | None) -> None:
    """``x`` (``--x``, ``report.x``) names a key with numbers (its plot and curves were left out without a
    word for a key such as icp.name), else a config error."""
    from scanreg.errors import ConfigError

    if x is None:
        return
    values = df[column_for(x, df)].dropna()
    if len(values) and pd.to_numeric(values, errors="coerce").isna().all():
        shown = ", ".join(map(str, list(dict.fromkeys(values))[:3]))
        raise ConfigError(f"report x '{x}' has no numbers ({shown}): errors and times are plotted against a numeric "
                          "key, e.g. sampler.n_points; group by it instead (--group-by)")


def _check_metrics(df: pd.DataFrame, asked: dict) -> None:
    """A warning line for each metric asked for that no run has (a typo showed no column, silently; a sweep whose
    runs all failed has none, and still gets its report)."""
    import difflib

    from scanreg.errors import warn

    have = sorted(c[len("metrics."):] for c in df.columns if c.startswith("metrics."))
    for option, names in asked.items():
        for name in names or ():
            if name not in have and name != "success":
                close = difflib.get_close_matches(name, have, n=3)
                warn(f"report.{option}{' (--metrics)' if option == 'metrics' else ''}: no run has the metric "
                     f"'{name}'" + (f"; did you mean {', '.join(close)}?" if close else ""))


# --------------------------------------------------------------------------------------------------- report
def write_report(df: pd.DataFrame, p: ReportParams, out: Path, compare_to: pd.DataFrame | None = None,
                 plots: bool = True, again: str | None = None) -> dict:
    """Write report.md, report.csv (and per.csv, compare.csv) and PNG plots into ``out``. ``again``: the
    ``scanreg-report`` command that writes this report again, as report.md records it (default: one from the
    experiment and ``p``'s options)."""
    _check_asked(df, p)
    out.mkdir(parents=True, exist_ok=True)
    since = _clear_previous(out)
    if not p.group_by:  # the methods, the cases apart (default_grouping)
        group_by, per = default_grouping(df, p.per)
        p = replace(p, group_by=group_by, per=per)
    group_by = list(p.group_by)
    how = p.interval
    interval(np.array([0.0, 1.0]), how)  # a bad name fails before any table is written
    table = summarize(df, group_by, list(p.metrics), how)
    table.drop(columns="_label").to_csv(out / "report.csv", index=False)
    run_columns(df).to_csv(out / "runs.csv", index=False)  # every run, for one's own statistics
    per_t = per_table(df, group_by, p.per) if p.per else None
    per_e = per_errors(df, group_by, p.per) if p.per else None
    if per_t is not None:
        per_t.to_csv(out / "per.csv")
    if per_e is not None:
        per_e.to_csv(out / "per_rotation_error.csv")
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
        f"- report: `{again or _options_command(df, p, group_by)}`, {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC",
        "",
        success_line(df),
        "",
        *([f"**Warning: {warn}.**", ""] if warn else []),
        f"## Results by {', '.join(group_by) or 'run'}", "",
        f"Each cell: the median over the group's runs (seeds, poses, pairs) [{interval_name(how)}]; success: "
        "successes/runs = rate [Wilson 95 % score interval] (a failed run counts as a failure; a finished run without "
        "ground truth is not counted). Two groups differ only where their intervals do not "
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
    if per_e is not None:
        lines += [f"## Median rotation error per {p.per} [deg, finished runs]", "",
                  to_markdown(per_e.map(lambda v: fmt_value(v) if pd.notna(v) else "–"), index=True), ""]
    lines += paired_section(df, group_labels(df, group_by), group_by, list(p.paired), out)
    if compare_to is not None:
        lines += _compare_section(table, compare_to, group_by, exp, out)
    if p.showcase:
        lines += showcase_section(df, dict(p.showcase), out)
    if "metrics.scans_within_tolerance" in df.columns:
        lines += scanset_section(df, group_by, out)
    if figs:
        lines += ["## Plots", ""] + [f"![{f.stem}]({f.name})" for f in figs] + [""]
    lines += failed_section(df, group_by, n_fail)
    (out / "report.md").write_text("\n".join(lines))
    _list_written(out, since)
    return {"table": table, "per": per_t, "group_by": group_by, "warning": warn,
            "paths": [out / "report.md", out / "report.csv", out / "runs.csv", *figs]}


def _compare_section(table: pd.DataFrame, compare_to: pd.DataFrame, group_by: list[str], exp: str,
                     out: Path) -> list[str]:
    """The table beside another experiment's runs (``compare.csv``), naming the sweep compared with."""
    keys = [k for k in group_by if _has_key(compare_to, k)]
    cmp = compare(table.copy(), summarize(compare_to, keys), keys, exp, compare_to.attrs.get("experiment", "other"))
    cmp.to_csv(out / "compare.csv", index=False)
    which = f" (its sweep `{compare_to.attrs['parent']}`, then the latest)" if compare_to.attrs.get("parent") else ""
    return [f"## Compared with experiment `{compare_to.attrs.get('experiment')}`{which}", "", to_markdown(cmp), ""]


WRITTEN = ".scanreg-report-files"
"""The list of the files a report wrote into its folder, kept there: the next report into the folder removes
them first (a report of another sweep left its per-case tables and plots beside the new ones)."""


def _clear_previous(out: Path) -> float:
    """Remove the files the previous report into ``out`` wrote (:data:`WRITTEN`); the time this report starts."""
    listed = out / WRITTEN
    if listed.is_file():
        for name in listed.read_text().splitlines():
            if name and "/" not in name and name != WRITTEN:
                (out / name).unlink(missing_ok=True)
    return time.time()


def _list_written(out: Path, since: float) -> None:
    """Keep the list of the files written into ``out`` since ``since`` (:data:`WRITTEN`)."""
    names = sorted(f.name for f in out.iterdir()
                   if f.is_file() and f.name != WRITTEN and f.stat().st_mtime >= since - 1)
    (out / WRITTEN).write_text("\n".join(names) + "\n")


def run_columns(df: pd.DataFrame) -> pd.DataFrame:
    """One row per run: its id, status and error, its stage choices (``group.*``), parameters and metrics, named
    without MLflow's prefixes (a paired comparison of methods on the same cases starts from it)."""
    keep = [c for c in ("run_id", "status", "tags.error") if c in df.columns]
    keep += sorted(c for c in df.columns if c.startswith("tags.group."))
    keep += sorted(c for c in df.columns if c.startswith("params."))
    keep += sorted(c for c in df.columns if c.startswith("metrics."))
    out = df[keep].copy()
    out.columns = [c.removeprefix("tags.").removeprefix("params.").removeprefix("metrics.") for c in keep]
    return out.loc[:, ~out.columns.duplicated()]


def failed_section(df: pd.DataFrame, group_by: list[str], n_fail: int) -> list[str]:
    """The report's 'Failed runs' section (none when every run finished): each reason (:func:`failed_lines`),
    and the runs that ended before logging their config (an interrupted sweep's jobs that had not started: in
    no group, so in no table; :func:`~scanreg.app.report.runs.load_runs` counts them)."""
    unlogged = df.attrs.get("unlogged", 0)
    if not (n_fail or unlogged):
        return []
    lines = ["## Failed runs", ""] + failed_lines(df, group_by)
    if unlogged:
        lines.append(f"- {unlogged} run(s) ended before logging their config (an interrupted sweep's jobs): in no "
                     "table")
    return lines + [""]


def failed_lines(df: pd.DataFrame, group_by: list[str]) -> list[str]:
    """Each reason a run failed for, with how many runs and which groups (a list of distinct reasons lost both)."""
    bad = df[df["status"] != "FINISHED"]
    reasons = (bad["tags.error"] if "tags.error" in bad else pd.Series(index=bad.index, dtype=object))
    reasons = reasons.fillna("(no reason recorded)")
    cols = [find_column(k, df) for k in group_by]
    out = []
    for reason, n in reasons.value_counts().items():
        rows = bad[reasons == reason]
        groups = sorted({", ".join(str(r[c]) for c in cols if c) for _, r in rows.iterrows()} - {""})
        out.append(f"- {reason} ({n} run{'s' if n > 1 else ''}" + (f"; {'; '.join(groups)}" if groups else "") + ")")
    return out


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


def _runs_options(df: pd.DataFrame) -> list[str]:
    """The ``scanreg-report`` options that name the runs ``df`` holds for good: their experiment and their
    sweep's parent run id (``latest`` would read a later sweep)."""
    return ["--experiment", df.attrs.get("experiment", "?"), *(["--parent", df.attrs["parent"]]
                                                               if df.attrs.get("parent") else [])]


def _options_command(df: pd.DataFrame, p: ReportParams, group_by: list[str]) -> str:
    """A ``scanreg-report`` command for these runs with ``p``'s settings that have an option."""
    parts = ["scanreg-report", *_runs_options(df)]
    for option, value in (("--group-by", ",".join(group_by)), ("--x", p.x), ("--per", p.per),
                          ("--metrics", ",".join(p.metrics or ())), ("--title", p.title), ("--out", p.out)):
        if value:
            parts += [option, str(value)]
    return shlex.join(parts)


def given_command(argv: list[str], df: pd.DataFrame) -> str:
    """The ``scanreg-report`` command as given (``argv``), with the runs it read named for good: the experiment,
    and the sweep's parent run id in place of ``latest`` (a later sweep would be the latest)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        key = a.split("=", 1)[0]
        if key in ("--experiment", "--parent"):
            skip = "=" not in a
            continue
        out.append(a)
    pinned = _runs_options(df)
    if not df.attrs.get("parent") and ("--parent" in argv or any(a.startswith("--parent=") for a in argv)):
        pinned += ["--parent", "all"]
    return shlex.join(["scanreg-report", *pinned, *out])


def report_for_sweep(cfg, parent_run_id: str, uri: str, experiment: str) -> None:
    """Called when an experiment's sweep ends (``report.enabled``): write its report."""
    from omegaconf import OmegaConf

    from scanreg.stages.registry import make_params

    p = make_params(ReportParams, OmegaConf.to_container(cfg.report, resolve=True), "report")
    out = Path(p.out or Path("outputs") / "reports" / experiment)
    changed = _changed_runs(cfg)
    if changed and not p.out:  # a part or a variant of the experiment: its own folder, the experiment's kept
        out = out / _slug(" ".join(changed))
    df = load_runs(experiment, uri, parent_run_id)
    res = write_report(df, p, out, again=_sweep_report_command(cfg, df, out if changed and not p.out else None))
    if res["warning"]:
        print(f"warning: {res['warning']}")
    print(f"report: {res['paths'][0]}" + (f" (the sweep changed the experiment: {' '.join(changed)})"
                                          if changed and not p.out else ""))


def _sweep_report_command(cfg, df: pd.DataFrame, out: Path | None) -> str:
    """The command that writes a sweep's report again: ``--config`` with the sweep's experiment (its report
    settings), the runs pinned, ``out`` when the report went elsewhere; the sweep's own ``report.*``
    overrides, which have no option, are named after it."""
    try:
        name = cfg.hydra.runtime.choices.get("experiment")
    except Exception:  # noqa: BLE001  # (a config without Hydra's node)
        name = None
    parts = ["scanreg-report", *(["--config", name] if name else []), *_runs_options(df)]
    if df.attrs.get("uri"):
        parts += ["--uri", str(df.attrs["uri"])]
    try:  # the user's config folders (--config-dir) where --config finds the experiment
        for source in cfg.hydra.runtime.config_sources:
            if name and source.get("provider") == "command-line" and source.get("schema") == "file":
                parts += ["--config-dir", str(source.get("path"))]
    except Exception:  # noqa: BLE001  # (a config without Hydra's node)
        pass
    if out is not None:
        parts += ["--out", str(out)]
    task = list(cfg.hydra.overrides.task) if "hydra" in cfg else []
    report_overrides = [o for o in task if o.lstrip("+~").startswith("report.")]
    return shlex.join(parts) + (f" (with the sweep's {' '.join(report_overrides)})" if report_overrides else "")


PROCESS_KEYS = ("experiment", "hydra", "launch", "tracking", "verbose", "report")
"""Overrides that change how a sweep runs or is filed, not its runs: the experiment's report is theirs."""


def _changed_runs(cfg) -> list[str]:
    """The command-line overrides of an experiment's sweep that change its runs (re-running one job of it, a
    variant): its report then goes into a folder of its own instead of replacing the experiment's."""
    task = list(cfg.hydra.overrides.task) if "hydra" in cfg else []
    return [o for o in task if o.lstrip("+~").split("=")[0].split(".")[0].split("/")[0] not in PROCESS_KEYS]


def main(argv: list[str] | None = None) -> int:
    """``scanreg-report``: what goes wrong is one ``error:`` line (exit 2 for the options, 1 otherwise)."""
    from scanreg.errors import ConfigError, ScanregError, one_line

    try:
        return _main(argv)
    except ScanregError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2 if isinstance(e, ConfigError) else 1
    except (OSError, ValueError, KeyError, RuntimeError) as e:  # a library's or the file system's: one line
        print(f"error: report: {one_line(e)}", file=sys.stderr)
        return 1


def _main(argv: list[str] | None) -> int:
    from scanreg.app.stages_cli import _one_line_parser

    ap = _one_line_parser()(prog="scanreg-report", description=__doc__.split("\n\n")[0],
                            allow_abbrev=False)  # (report.md records the options as given: in full)
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
    ap.add_argument("--config-dir", default=None, action="append", metavar="DIR",
                    help="a folder of your own configs (with experiment/EXPERIMENT.yaml) for --config, as "
                         "scanreg's --config-dir; may be given more than once")
    ap.add_argument("--uri", default=None, help="tracking URI (default: $MLFLOW_TRACKING_URI or outputs/mlflow.db)")
    ap.add_argument("--out", default=None, help="folder for the report (default: outputs/reports/<experiment>)")
    a = ap.parse_args(argv)
    if a.uri:
        from scanreg.app.tracking import store_uri

        a.uri = store_uri(a.uri, "--uri")
    base = ReportParams(enabled=True)
    if a.config:
        from omegaconf import OmegaConf

        from scanreg.app.config import compose
        from scanreg.stages.registry import make_params

        cfg = compose([f"experiment={a.config}"], config_dirs=[str(Path(d).resolve()) for d in a.config_dir or ()])
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
    res = write_report(df, p, out, other, plots=not a.no_plots,
                       again=given_command(sys.argv[1:] if argv is None else list(argv), df))
    print(f"{len(df)} run(s) of experiment '{a.experiment}'"
          + (f", sweep {df.attrs['parent']}" if df.attrs.get("parent") else ""))
    print(console_table(res["table"], res["group_by"], unit=runs_unit(df)))
    if res["warning"]:
        print(f"warning: {res['warning']}")
    print(f"every column: {out / 'report.csv'}; every run: {out / 'runs.csv'}; report: {out / 'report.md'}")
    return 0


def success_line(df) -> str:
    """What counts as a success: a pair's errors within ``evaluate.success_*``; a scan set's every scan within
    ``multiview.success_*``."""
    if "metrics.scans_within_tolerance" in df.columns:
        return ("Success (scan sets): every scan's rotation error < `multiview.success_rotation_deg` (0.5°) and "
                "the shift of its centroid < `multiview.success_translation` (0.25 %) of the model's diagonal (its "
                "box along its principal axes), the frames aligned at the first scan (scans without a true pose in "
                "`data.poses` are not evaluated); a failed run counts as a failure. Errors are against the ground "
                "truth, in degrees and as shares of the diagonal; times are medians in seconds.")
    if "metrics.rotation_error_deg" not in df.columns and "metrics.rms" in df.columns:
        return ("No ground truth (`data.gt`): no errors and no success; the table gives the fit instead, `rms` (the "
                "RMS distance of the source points within `evaluate.inlier_distance` of the target, input units) and "
                "`fitness` (their share), and the stage times (medians, seconds).")
    return ("Success: rotation error < `evaluate.success_rotation_deg` (2°) and translation error < "
            "`evaluate.success_translation` (1 %) of the target's bounding-box diagonal; a failed run counts as a "
            f"failure. Errors are against the ground truth, in degrees and input units{_unit_note(df)}, their "
            "medians and quantiles over the runs that finished; times are medians in seconds.")


def runs_unit(df: pd.DataFrame) -> str | None:
    """The input unit the runs logged (``input_unit_m``) as written for people (``mm``), when they agree."""
    from scanreg.eval.metrics import input_unit_name

    vals = set(df["metrics.input_unit_m"].dropna()) if "metrics.input_unit_m" in df.columns else set()
    return input_unit_name(next(iter(vals))) if len(vals) == 1 else None


def _unit_note(df: pd.DataFrame) -> str:
    """`` (m)``: the input unit the runs logged (``input_unit_m``), when they agree; else nothing."""
    unit = runs_unit(df)
    if unit is None:
        return ""
    guessed = "metrics.input_unit_guessed" in df.columns and bool(df["metrics.input_unit_guessed"].fillna(0).max())
    return f" ({unit}{', guessed from the sizes' if guessed else ''})"


def scanset_section(df: pd.DataFrame, group_by: list[str], out: Path) -> list[str]:
    """Scan sets: every scan's errors in every run (``per_scan.csv``, from each run's ``poses.json``) and the
    reconstruction of each group's first run (its ``reconstruction.png``, copied beside the report)."""
    import json
    import shutil

    cols, pictures = {}, []
    ordered = df.sort_values([*(column_for(k, df) for k in group_by), "params.seed"] if "params.seed" in df
                             else [column_for(k, df) for k in group_by])
    for _, row in ordered.iterrows():
        run_dir = Path(str(row.get("tags.scanreg.run_dir", "")))
        if not (run_dir / "poses.json").is_file():
            continue
        groups = " ".join(str(row[column_for(k, df)]) for k in group_by) or str(row.get("tags.mlflow.runName", ""))
        label = groups + (f" seed {row['params.seed']}" if "params.seed" in row else "")
        per = json.loads((run_dir / "poses.json").read_text()).get("per_scan", {})
        if "rotation_error_deg" in per:
            cols[f"{label}: rotation [°]"] = pd.Series(per["rotation_error_deg"])
            cols[f"{label}: shift [% diag]"] = 100 * pd.Series(per["translation_error_rel"])
        png = run_dir / "reconstruction.png"
        if png.is_file() and groups not in {g for g, _ in pictures}:
            name = f"reconstruction_{_slug(groups)}.png"
            shutil.copyfile(png, out / name)
            pictures.append((groups, name))
    lines = []
    if cols:
        table = pd.DataFrame(cols)
        table.index.name = "scan"
        table.to_csv(out / "per_scan.csv")
        lines += ["## Every scan's error", "", "Rotation error (degrees) and shift of the scan's centroid (% of the "
                  "model's diagonal) against the truth, per run; empty where a scan was not placed. per_scan.csv has "
                  "the numbers.", "", to_markdown(table.T.round(3).rename_axis("run"), index=True), ""]
    for groups, name in pictures:
        lines += [f"## The reconstruction: {groups}", "", f"![reconstruction {groups}]({name})", ""]
    return lines


if __name__ == "__main__":
    sys.exit(main())
