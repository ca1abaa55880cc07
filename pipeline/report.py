"""``scanreg-report``: MLflow runs -> a comparison table (pandas).

    scanreg-report                                   # latest sweep of experiment 'scanreg', grouped by what varies
    scanreg-report --experiment scanreg --parent latest --group-by sampler.n_points --out reports/density

Runs are loaded with ``mlflow.search_runs``; ``--group-by`` takes config keys (``icp.tau``, ``group.coarse`` for
a group's choice). Per group: runs, failed runs, success rate (rotation error < 2 deg and translation error < 1 %
of the diagonal, as configured in ``evaluate``), median and 90th-percentile errors, median stage times.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import pandas as pd

AGG_METRICS = [
    ("rotation_error_deg", "median"), ("rotation_error_deg", "p90"),
    ("translation_error", "median"), ("translation_error", "p90"),
    ("rms", "median"), ("fitness", "median"), ("icp_iterations", "median"),
    ("time_repair_s", "median"), ("time_sample_s", "median"), ("time_coarse_s", "median"),
    ("time_icp_s", "median"), ("time_total_s", "median"),
]
IGNORED_VARYING = {"seed"}


def load_runs(experiment: str, uri: str | None = None, parent: str | None = None) -> pd.DataFrame:
    """Child runs of ``parent`` (``latest``: the newest sweep), or every non-parent run of the experiment."""
    from pipeline.tracking import MlflowTracking, _quiet_mlflow

    _quiet_mlflow()
    import mlflow

    tr = MlflowTracking(MlflowTracking.Params(uri=uri, experiment=experiment))
    mlflow.set_tracking_uri(tr.uri)
    exp = mlflow.get_experiment_by_name(experiment)
    if exp is None:
        raise SystemExit(f"error: no experiment '{experiment}' in {tr.uri}")
    if parent == "latest":
        parents = mlflow.search_runs([exp.experiment_id], filter_string="tags.`scanreg.sweep` = 'parent'",
                                     order_by=["start_time DESC"], max_results=1)
        if parents.empty:
            raise SystemExit(f"error: experiment '{experiment}' has no sweep (run 'scanreg -m ...' first)")
        parent = parents.iloc[0]["run_id"]
    flt = f"tags.mlflow.parentRunId = '{parent}'" if parent else ""
    df = mlflow.search_runs([exp.experiment_id], filter_string=flt, max_results=100000)
    if "tags.scanreg.sweep" in df:
        df = df[df["tags.scanreg.sweep"] != "parent"]
    if df.empty:
        raise SystemExit(f"error: no runs found in experiment '{experiment}'" + (f" under parent {parent}" if parent else ""))
    df.attrs["parent"] = parent
    df.attrs["uri"] = tr.uri
    return df.reset_index(drop=True)


def column_for(key: str, df: pd.DataFrame) -> str:
    for c in (f"params.{key}", f"tags.{key}", f"metrics.{key}", key):
        if c in df.columns:
            return c
    raise SystemExit(f"error: unknown group-by key '{key}'; e.g. {', '.join(varying_keys(df)) or 'sampler.n_points'}")


def varying_keys(df: pd.DataFrame) -> list[str]:
    keys = []
    for c in df.columns:
        if c.startswith("params.") and df[c].nunique(dropna=False) > 1:
            k = c[len("params."):]
            if k.split(".")[-1] not in IGNORED_VARYING and not k.endswith(("_seed", ".seed")):
                keys.append(k)
    return keys


def summarize(df: pd.DataFrame, group_by: list[str]) -> pd.DataFrame:
    cols = [column_for(k, df) for k in group_by]
    work = df.copy()
    for c in cols:
        num = pd.to_numeric(work[c], errors="coerce")
        work[c] = num if num.notna().all() else work[c].astype(str)
    rows = []
    groups = work.groupby(cols, dropna=False, sort=True) if cols else [((), work)]
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        ok = g[g["status"] == "FINISHED"]
        row = dict(zip(group_by, key))
        row["runs"] = len(g)
        row["failed"] = int((g["status"] != "FINISHED").sum())
        if "metrics.success" in g and ok["metrics.success"].notna().any():
            row["success_rate"] = float(ok["metrics.success"].fillna(0).sum() / len(g))
        for m, how in AGG_METRICS:
            c = f"metrics.{m}"
            if c in ok and ok[c].notna().any():
                s = ok[c].dropna()
                row[f"{m}_{how}"] = float(s.median() if how == "median" else s.quantile(0.9))
        rows.append(row)
    return pd.DataFrame(rows)


def to_markdown(df: pd.DataFrame) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    head = "| " + " | ".join(df.columns) + " |"
    sep = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scanreg-report", description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiment", default="scanreg", help="MLflow experiment name (default: scanreg)")
    ap.add_argument("--parent", default="latest",
                    help="parent run id of a sweep; 'latest' (default): the newest sweep; 'all': every run")
    ap.add_argument("--group-by", default=None,
                    help="comma-separated config keys (default: the parameters that vary between the runs)")
    ap.add_argument("--uri", default=None, help="tracking URI (default: $MLFLOW_TRACKING_URI or outputs/mlflow.db)")
    ap.add_argument("--out", default=None, help="folder for report.md and report.csv (default: outputs/reports/<experiment>)")
    a = ap.parse_args(argv)
    df = load_runs(a.experiment, a.uri, None if a.parent == "all" else a.parent)
    group_by = [k.strip() for k in a.group_by.split(",") if k.strip()] if a.group_by else varying_keys(df)
    table = summarize(df, group_by)
    out = Path(a.out or Path("outputs") / "reports" / a.experiment)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "report.csv", index=False)
    title = f"# scanreg report: experiment '{a.experiment}'"
    src = f"{len(df)} run(s)" + (f" of sweep {df.attrs['parent']}" if df.attrs.get("parent") else "") + \
        f", store {df.attrs['uri']}; grouped by {', '.join(group_by) or '(nothing)'}"
    (out / "report.md").write_text(f"{title}\n\n{src}\n\n{to_markdown(table)}\n")
    with pd.option_context("display.width", 200, "display.max_columns", 50):
        print(src)
        print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"written: {out / 'report.md'}, {out / 'report.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
