"""The runs of a sweep, from MLflow, as a table (one row per run)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd


def existing_store(tr):
    """``tr`` (a :class:`~scanreg.app.tracking.MlflowTracking`) when its store exists: a report reads runs, and a
    SQLite store that is not there would be created empty."""
    if tr.uri.startswith("sqlite:///") and not Path(tr.uri[len("sqlite:///"):]).is_file():
        raise SystemExit(f"error: no tracking store at {tr.uri[len('sqlite:///'):]} (run scanreg there first, or "
                         "give the store with --uri or $MLFLOW_TRACKING_URI)")
    return tr


def load_runs(experiment: str, uri: str | None = None, parent: str | None = None) -> pd.DataFrame:
    """Child runs of ``parent`` (``latest``: the newest sweep), or every run of the experiment that is neither a
    sweep's parent nor a part of a scan set's run (its pairs)."""
    from scanreg.app.tracking import MlflowTracking, _quiet_mlflow

    _quiet_mlflow()
    import mlflow

    tr = existing_store(MlflowTracking(MlflowTracking.Params(uri=uri, experiment=experiment)))
    mlflow.set_tracking_uri(tr.uri)
    exp = mlflow.get_experiment_by_name(experiment)
    if exp is None:
        raise SystemExit(f"error: no experiment '{experiment}' in {tr.uri}")
    parent_row = None
    if parent:
        flt = "tags.`scanreg.sweep` = 'parent'" + ("" if parent == "latest" else f" and attributes.run_id = '{parent}'")
        parents = mlflow.search_runs([exp.experiment_id], filter_string=flt, order_by=["start_time DESC"],
                                     max_results=1 if parent != "latest" else LATEST_SEARCHED)
        if parent == "latest":  # the newest sweep with runs (a sweep that a typo stopped has none)
            parents = parents[[_has_runs(mlflow.MlflowClient(tr.uri), exp.experiment_id, r)
                               for r in parents["run_id"]]].head(1)
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
    if "tags.scanreg.part" in df:  # a scan set's pairs: parts of its run, not runs (their parent is the set's run)
        df = df[df["tags.scanreg.part"].isna()]
    if df.empty:
        raise SystemExit(f"error: no runs found in experiment '{experiment}'" + (f" under parent {parent}" if parent else ""))
    # runs an interrupt ended (KILLED, or left RUNNING: a job stopped while it was being logged) before they had
    # logged their whole config: no group to put them in, and their missing keys would seem to vary
    params = [c for c in df.columns if c.startswith("params.")]
    n = df[params].notna().sum(axis=1) if params else pd.Series(0, index=df.index)
    finished = df["status"] == "FINISHED"
    whole = int(n[finished].min()) if finished.any() else int(n.max())
    bare = (df["status"] != "FINISHED") & ((n == 0) | (df["status"].isin(["KILLED", "RUNNING"]) & (n < whole)))
    unlogged = int(bare.sum()) if not bare.all() else 0
    df = df[~bare] if unlogged else df
    df = df.sort_values("start_time").reset_index(drop=True)
    df.attrs.update(unlogged=unlogged, parent=parent, uri=tr.uri, experiment=experiment,
                    parent_tags={k[5:]: v for k, v in parent_row.items() if k.startswith("tags.")}
                    if parent_row is not None else {})
    return df


LATEST_SEARCHED = 50
"""The newest sweep is looked for among this many newest parent runs: the first with a run under it."""


def _has_runs(client, experiment_id: str, parent_id: str) -> bool:
    """Whether the sweep ``parent_id`` has a run under it (one whose job started)."""
    return bool(client.search_runs([experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent_id}'",
                                   max_results=1))


def latest_sweep_experiment(uri: str | None = None) -> str:
    """The MLflow experiment holding the newest sweep (parent run) of the store, for a bare ``scanreg-report``."""
    from scanreg.app.tracking import MlflowTracking, _quiet_mlflow

    _quiet_mlflow()
    import mlflow

    tr = existing_store(MlflowTracking(MlflowTracking.Params(uri=uri)))
    mlflow.set_tracking_uri(tr.uri)
    client = mlflow.MlflowClient(tr.uri)
    exps = client.search_experiments()
    runs = client.search_runs([e.experiment_id for e in exps], filter_string="tags.`scanreg.sweep` = 'parent'",
                              order_by=["attributes.start_time DESC"], max_results=LATEST_SEARCHED) if exps else []
    runs = [r for r in runs if _has_runs(client, r.info.experiment_id, r.info.run_id)][:1]
    if not runs:
        names = ", ".join(sorted(e.name for e in exps if e.name != "Default")) or "none"
        raise SystemExit(f"error: no sweep in {tr.uri} (run 'scanreg -m ...' first, or name an experiment with "
                         f"--experiment NAME --parent all; experiments: {names})")
    return next(e.name for e in exps if e.experiment_id == runs[0].info.experiment_id)
