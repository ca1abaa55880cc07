"""Experiment tracking with MLflow.

One MLflow run per job, logged when the job ends: its config as params, its stage choices as tags, its metrics,
per-iteration series and artifacts, and its status (FINISHED, FAILED with its one-line reason in the tag
``error``, KILLED when interrupted). The store and the experiment are created once, before any job starts (in the
single run itself, or by :class:`scanreg.app.sweep.SweepCallback` in the launching process of a ``-m`` sweep), and
every run is created with an explicit ``experiment_id``. A sweep has one parent run; each job's run is its child
(``mlflow.parentRunId``); a failing job ends FAILED and the sweep goes on, and the parent ends FAILED if any child
failed.

A single ``scanreg`` run logs through a worker process started with the command (``python -m
scanreg.app.tracking``, see :mod:`scanreg.app.startup`), which imports MLflow while the run works.

Default store: ``sqlite:///<cwd>/outputs/mlflow.db`` (absolute path), artifacts beside it in
``outputs/mlartifacts``; ``$MLFLOW_TRACKING_URI`` or ``tracking.uri`` override it.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from scanreg.stages.registry import Registry

if TYPE_CHECKING:
    from omegaconf import DictConfig

# No Hydra or OmegaConf at import: the worker process (``python -m scanreg.app.tracking``) imports this module.

TRACKING = Registry("tracking")
"""The tracking backends (``tracking=mlflow|none``)."""

SWEEP_ENV = "SCANREG_SWEEP"
"""Environment variable through which a sweep's jobs learn the store, experiment and parent run."""
SWEEP_FILE = ".scanreg_sweep.json"
"""The same, as a file in the sweep directory: for launchers whose workers do not inherit the launching
process's environment (a Ray cluster, Slurm), given a shared file system."""


def sweep_info() -> dict | None:
    """What the launching process said about the running sweep: from the environment, else from the sweep
    directory of the current Hydra job (multirun only)."""
    if os.environ.get(SWEEP_ENV):
        return json.loads(os.environ[SWEEP_ENV])
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
        if hc.mode == RunMode.MULTIRUN:
            f = Path(hc.sweep.dir) / SWEEP_FILE
            if f.exists():
                return json.loads(f.read_text())
    except Exception:  # noqa: BLE001  # not inside a Hydra job
        pass
    return None


_sweep_outcome: dict[str, Any] = {}
"""Set by SweepCallback.on_multirun_end in the launching process: ``{"failed": n, "total": n}``."""


def _quiet_mlflow() -> None:
    for name in ("alembic", "mlflow", "mlflow.store", "mlflow.tracking"):
        logging.getLogger(name).setLevel(logging.WARNING)


def flatten(d: Any, prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
    else:
        out[prefix[:-1]] = "null" if d is None else str(d)
    return out


class RunLog:
    """Logging into one MLflow run."""

    def __init__(self, client, run_id: str):
        self.client, self.run_id = client, run_id

    def log_params(self, params: dict[str, str]) -> None:
        from mlflow.entities import Param

        items = [Param(k[:250], v[:6000]) for k, v in sorted(params.items())]
        for i in range(0, len(items), 100):
            self.client.log_batch(self.run_id, params=items[i : i + 100])

    def set_tags(self, tags: dict[str, str]) -> None:
        from mlflow.entities import RunTag

        self.client.log_batch(self.run_id, tags=[RunTag(k, str(v)[:5000]) for k, v in tags.items()])

    def log_metrics(self, metrics: dict[str, float], step_metrics: dict[str, list[float]] | None = None) -> None:
        import math

        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        items = [Metric(k, float(v), ts, 0) for k, v in sorted(metrics.items())
                 if isinstance(v, (int, float)) and math.isfinite(float(v))]
        for k, seq in (step_metrics or {}).items():
            items += [Metric(f"{k}_step", float(v), ts, i) for i, v in enumerate(seq)]
        for i in range(0, len(items), 500):
            self.client.log_batch(self.run_id, metrics=items[i : i + 500])

    def log_artifacts(self, paths: list[Path]) -> None:
        for p in paths:
            if Path(p).exists():
                self.client.log_artifact(self.run_id, str(p))

    def end(self, status: str, reason: str | None = None) -> None:
        if reason:
            self.set_tags({"error": reason})
        self.client.set_terminated(self.run_id, status)


@dataclass
class RunRecord:
    """Everything one run logs (plain values, so that it travels to the worker process as JSON)."""

    run_name: str
    params: dict[str, str]
    tags: dict[str, str]
    start_time: int = field(default_factory=lambda: int(time.time() * 1000))
    """Milliseconds since the epoch."""
    status: str = "FINISHED"
    reason: Optional[str] = None
    """Why the run failed or was stopped (the tag ``error``)."""
    metrics: dict[str, float] = field(default_factory=dict)
    step_metrics: dict[str, list[float]] = field(default_factory=dict)
    """Per-iteration series, logged as ``<name>_step`` with steps 0, 1, ..."""
    artifacts: list[str] = field(default_factory=list)

    def ended(self, status: str, reason: str | None = None, metrics=None, step_metrics=None,
              artifacts=()) -> "RunRecord":
        """This record with how the run ended."""
        return RunRecord(self.run_name, self.params, self.tags, self.start_time, status, reason,
                         {k: float(v) for k, v in (metrics or {}).items() if isinstance(v, (int, float))},
                         {k: [float(x) for x in v] for k, v in (step_metrics or {}).items()},
                         [str(Path(p).resolve()) for p in artifacts])


SQLITE_SUFFIXES = (".db", ".sqlite", ".sqlite3")
"""A tracking store given as a plain path with one of these endings is a SQLite file."""


def store_uri(uri: str, where: str) -> str:
    """The tracking URI ``uri`` as MLflow takes it: a URI (``scheme://...``) as it is; a plain path to a SQLite
    file (``outputs/mlflow.db``, as the default is written) as ``sqlite:///<absolute path>``. Any other plain path
    (a folder: MLflow's file store, which MLflow 3 no longer writes) is a :class:`~scanreg.errors.ConfigError`
    naming ``where`` (the parameter or variable that gave it); so is a ``file:`` URI, unless
    ``MLFLOW_ALLOW_FILE_STORE`` is true (MLflow's own opt-in: without it MLflow refuses the store only once a run
    is logged, after the run's work, and in a sweep after every job's)."""
    from scanreg.errors import ConfigError

    if uri.lower().startswith("file:") and os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").lower() not in ("true",
                                                                                                           "1"):
        raise ConfigError(f"{where}={uri}: a file store (a folder), which MLflow 3 no longer writes; give a SQLite "
                          "file (e.g. outputs/mlflow.db; `mlflow migrate-filestore` moves a folder's runs into one) or "
                          "set MLFLOW_ALLOW_FILE_STORE=true to use the folder anyway")
    if "://" in uri:
        return uri
    if uri.lower().endswith(SQLITE_SUFFIXES):
        return f"sqlite:///{Path(uri).expanduser().resolve()}"
    raise ConfigError(f"{where}={uri}: not a tracking store scanreg can use; give a SQLite file (a path ending in "
                      f"{', '.join(SQLITE_SUFFIXES)}, e.g. outputs/mlflow.db) or a URI (sqlite:///..., http://...)")


@TRACKING.register("mlflow")
class MlflowTracking:
    """Log every run to MLflow: config as params, stage choices as tags, metrics, artifacts."""

    @dataclass
    class Params:
        uri: Optional[str] = None
        """Tracking URI; null: $MLFLOW_TRACKING_URI, else sqlite:///<cwd>/outputs/mlflow.db (absolute path). A plain
        path to a SQLite file (``other/mlflow.db``) is taken as ``sqlite:///`` and its absolute path."""
        experiment: str = "scanreg"
        """MLflow experiment name the runs are filed under."""

    def __init__(self, params: Params):
        self.p = params
        given = params.uri or os.environ.get("MLFLOW_TRACKING_URI")
        where = "tracking.uri" if params.uri else "MLFLOW_TRACKING_URI"
        self.uri = store_uri(given, where) if given else f"sqlite:///{(Path.cwd() / 'outputs' / 'mlflow.db').resolve()}"

    def _client(self):
        _quiet_mlflow()
        from mlflow.tracking import MlflowClient

        if self.uri.startswith("sqlite:///"):
            Path(self.uri[len("sqlite:///"):]).parent.mkdir(parents=True, exist_ok=True)
        return MlflowClient(tracking_uri=self.uri)

    def prepare(self) -> tuple[Any, str]:
        """Create the store and the experiment if needed; returns ``(client, experiment_id)``."""
        client = self._client()
        exp = client.get_experiment_by_name(self.p.experiment)
        if exp is not None:
            return client, exp.experiment_id
        artifact_location = None
        if self.uri.startswith("sqlite:///"):
            root = Path(self.uri[len("sqlite:///"):]).parent / "mlartifacts" / self.p.experiment
            artifact_location = root.resolve().as_uri()
        try:
            return client, client.create_experiment(self.p.experiment, artifact_location=artifact_location)
        except Exception:  # created meanwhile by another process
            exp = client.get_experiment_by_name(self.p.experiment)
            if exp is None:
                raise
            return client, exp.experiment_id

    def request(self, record: RunRecord, children: list[RunRecord] = ()) -> dict:
        """What logging ``record`` (and ``children``) takes, as plain values (:func:`_log_request` logs it): sent
        to the worker process, and kept in a sweep job's folder while it is logged (:data:`PENDING_RECORD`)."""
        return {"uri": self.p.uri, "resolved_uri": self.uri, "experiment": self.p.experiment,
                "sweep": sweep_info(), "record": asdict(record), "children": [asdict(c) for c in children]}

    def log_run(self, record: RunRecord, children: list[RunRecord] = ()) -> str:
        """Log a finished run (and ``children``, runs nested in it: a scan set's pairs); its run id. Through the
        worker process when the command started one (and MLflow is not imported here), else here."""
        import sys

        from scanreg.app import startup

        request = self.request(record, children)
        worker = None if "mlflow" in sys.modules else startup.take_tracking_worker()
        if worker is not None:
            return worker.log(request)
        return _log_request(request)


@TRACKING.register("none")
class NoTracking:
    """Track nothing (results stay in the run directory). Its parameters are ``tracking=mlflow``'s, accepted and
    ignored, so that configs and experiment files written for MLflow also run untracked."""

    Params = MlflowTracking.Params

    def __init__(self, params: MlflowTracking.Params):
        self.p = params

    def log_run(self, record: RunRecord, children: list[RunRecord] = ()) -> None:
        return None


def _log_request(request: dict) -> str:
    """Log ``request``'s record (see :meth:`MlflowTracking.log_run`) into its store; the new run's id. A sweep's
    jobs log where the launching process created the parent run, unless a job names another store explicitly
    (workers of a cluster may not share the launching process's environment or cwd)."""
    tr = MlflowTracking(MlflowTracking.Params(uri=request["uri"], experiment=request["experiment"]))
    tr.uri = request["resolved_uri"]
    rec = RunRecord(**request["record"])
    sweep = request.get("sweep")
    tags = dict(rec.tags)
    if sweep and sweep.get("parent_run_id") and (tr.p.uri is None or sweep["uri"] == tr.uri) and \
            sweep["experiment"] == tr.p.experiment:  # (an untracked sweep's info has no parent run)
        tr.uri = sweep["uri"]
        client, eid = tr._client(), sweep["experiment_id"]
        tags["mlflow.parentRunId"] = sweep["parent_run_id"]
    else:
        client, eid = tr.prepare()
    run_id = _log_record(client, eid, rec, tags)
    for child in request.get("children", ()):
        c = RunRecord(**child)
        _log_record(client, eid, c, {**c.tags, "mlflow.parentRunId": run_id})
    return run_id


def _log_record(client, eid: str, rec: RunRecord, tags: dict[str, str]) -> str:
    """One run created with ``tags``, its params, metrics and artifacts logged and its status set."""
    run = client.create_run(eid, run_name=rec.run_name, tags=tags, start_time=rec.start_time)
    log = RunLog(client, run.info.run_id)
    log.log_params(rec.params)
    log.log_metrics(rec.metrics, rec.step_metrics)
    log.log_artifacts([Path(p) for p in rec.artifacts])
    log.end(rec.status, rec.reason)
    return run.info.run_id


def _warm_mlflow() -> None:
    """Do now what logging the run would otherwise do first when the run ends: import MLflow and its SQLAlchemy
    store (the store's ORM mappers configured), and open the default store (:class:`MlflowTracking`'s URI
    without ``tracking.uri``) when it exists already: MLflow keeps the opened store per URI, so the run finds it
    open when its config names the same one. A store is never created here: a run that fails before it logs
    leaves none behind."""
    import mlflow.tracking  # noqa: F401

    try:
        import mlflow.store.tracking.sqlalchemy_store  # noqa: F401
        import sqlalchemy.orm

        sqlalchemy.orm.configure_mappers()
        tr = MlflowTracking(MlflowTracking.Params())
        if tr.uri.startswith("sqlite:///") and Path(tr.uri[len("sqlite:///"):]).is_file():
            client = tr._client()
            client.get_experiment_by_name(tr.p.experiment)
    except Exception:  # noqa: BLE001  # only a head start; logging the run reports any real problem
        pass



def _worker() -> None:
    """``python -m scanreg.app.tracking``: import MLflow at once, then log the one run described on standard
    input (a JSON request, :meth:`MlflowTracking.log_run`) and answer its run id (or the error) on standard
    output. Ctrl-C is ignored, so that an interrupted run can still be logged KILLED."""
    import gc
    import signal
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _quiet_mlflow()
    _warm_mlflow()
    # What is imported now lives until the worker exits: keep it out of the garbage collector's full passes,
    # one of which would otherwise scan MLflow's whole module graph while the run waits for its answer.
    gc.freeze()
    line = sys.stdin.readline()
    if not line:  # the command did not need it
        return
    try:
        reply = {"run_id": _log_request(json.loads(line))}
    except Exception as e:  # noqa: BLE001  # the caller reports it
        reply = {"error": f"{type(e).__name__}: {e}".splitlines()[0] if str(e) else type(e).__name__}
    print(REPLY + json.dumps(reply), flush=True)
    # The run is logged and the store committed: skip the teardown of MLflow's and SQLAlchemy's module graph,
    # which a caller reading this process's standard error (a pipe, a test) would wait for.
    sys.stderr.flush()
    os._exit(0)


REPLY = "@scanreg-tracking "
"""Prefix of the worker's answer on its standard output (anything else a library prints is not an answer)."""


def launcher_tags(config: DictConfig) -> dict[str, str]:
    """The sweep's launcher and its parallelism (``n_jobs``, ``array_parallelism``...), for the report."""
    lc = config.hydra.get("launcher") or {}
    tags = {"scanreg.launcher": str(lc.get("_target_", "?")).rsplit(".", 1)[-1]}
    for k in ("n_jobs", "array_parallelism"):
        if lc.get(k) is not None:
            tags[f"scanreg.launcher.{k}"] = str(lc.get(k))
    return tags


def _children(client, info: dict) -> list:
    """The child runs of the sweep described by ``info`` (see :func:`sweep_info`)."""
    return client.search_runs([info["experiment_id"]],
                              filter_string=f"tags.mlflow.parentRunId = '{info['parent_run_id']}'",
                              max_results=50000)


PENDING_RECORD = "mlflow_pending.json"
"""A sweep job that has finished keeps what it logs in its folder under this name until its run is logged: an
interrupt that stops the job meanwhile (a parallel launcher ends its workers at once) leaves it there, and the
launching process logs it (:func:`end_interrupted_sweep`), so that no finished job's results are lost."""


def end_interrupted_sweep(reason: str = "interrupted", status: str = "KILLED") -> int:
    """After an interrupt of a sweep (in the launching process): the finished jobs whose logging the interrupt
    cut (:data:`PENDING_RECORD` left in their folders) logged from their folders, in place of what they had
    logged; then every child run still RUNNING, and the parent, end KILLED with the reason, so that no run is
    left RUNNING. Returns the number of runs ended."""
    info = json.loads(os.environ.pop(SWEEP_ENV, "null") or "null")
    if not info or not info.get("parent_run_id"):  # (an untracked sweep: no run to end)
        return 0
    tr = MlflowTracking(MlflowTracking.Params(uri=info["uri"], experiment=info["experiment"]))
    client = tr._client()
    _sweep_outcome["recovered"] = _log_pending(client, info)
    children = _children(client, info)
    n = 0
    for r in children:
        if r.info.status == "RUNNING":
            RunLog(client, r.info.run_id).end(status, reason)
            n += 1
    RunLog(client, info["parent_run_id"]).end(status, reason)
    return n + 1


def _log_pending(client, info: dict) -> int:
    """Log the finished jobs an interrupt stopped while they were being logged (:data:`PENDING_RECORD` in their
    folders under the sweep directory), each in place of the part of it the job had logged; how many."""
    sweep_dir = Path(info.get("sweep_dir") or "")
    if not info.get("sweep_dir") or not sweep_dir.is_dir():
        return 0
    pending = sorted(sweep_dir.glob(f"*/{PENDING_RECORD}"))
    children = _children(client, info) if pending else []
    logged = 0
    for f in pending:
        try:
            request = json.loads(f.read_text())
            where = request["record"]["tags"].get("scanreg.run_dir")
            for r in children:  # the run the job had begun to log (its params cut short)
                if where and r.data.tags.get("scanreg.run_dir") == where and r.info.status != "FINISHED":
                    client.delete_run(r.info.run_id)
            request["sweep"] = info
            _log_request(request)
            f.unlink()
            logged += 1
        except Exception:  # noqa: BLE001  # the job's folder keeps its results either way
            continue
    return logged


def sweep_jobs(config: DictConfig) -> list[list[str]] | None:
    """Each job's overrides in a basic-sweeper sweep (command-line sweeps and ``hydra.sweeper.params``), in
    launch order, as the sweeper makes them; None for another sweeper (e.g. Optuna's, which picks values as it
    goes)."""
    if "BasicSweeper" not in str(config.hydra.sweeper.get("_target_", "")):
        return None
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    # as written (an interpolation in a value, ${seed}, is the job's to resolve, as Hydra's sweeper reads them)
    params = OmegaConf.to_container(config.hydra.sweeper.params, resolve=False) if config.hydra.sweeper.get(
        "params") else {}
    lines = [f"{k}={v}" for k, v in params.items()]
    lines += OmegaConf.to_container(config.hydra.overrides.task, resolve=False)
    loader = GlobalHydra.instance().config_loader() if GlobalHydra.instance().is_initialized() else None
    parser = OverridesParser.create(config_loader=loader)  # (glob() needs the loader: it lists a group's choices)
    return BasicSweeper.split_arguments(parser.parse_overrides(lines), None)[0]


def sweep_size(config: DictConfig) -> int | None:
    """Number of jobs of a basic-sweeper sweep, else None."""
    try:
        jobs = sweep_jobs(config)
    except Exception:  # noqa: BLE001  # progress is a nicety
        return None
    return None if jobs is None else len(jobs)


def progress_counts(path: str) -> tuple[int, int]:
    """``(done, failed)`` jobs by a sweep's progress file: one line per job, ``FINISHED`` or its failure."""
    lines = Path(path).read_text().split()
    return len(lines), sum(s != "FINISHED" for s in lines)


def report_progress(status: str, what: str = "") -> None:
    """After a sweep job: append to the sweep's progress file and print one line, the job's outcome with a
    progress bar and the estimated time left (the job's full table is in its folder, ``summary.txt``)."""
    info = sweep_info()
    if not info or not info.get("progress"):
        return
    try:
        with open(info["progress"], "a") as f:
            f.write(status + "\n")
        done, failed = progress_counts(info["progress"])
    except OSError:
        return
    elapsed = time.time() - info["start"]
    total = info.get("total")
    try:
        from hydra.core.hydra_config import HydraConfig

        job = f"#{HydraConfig.get().job.num} "
    except Exception:  # noqa: BLE001  # not inside a Hydra job
        job = ""
    outcome = f"{job}{'done' if status == 'FINISHED' else status}" + (f": {what}" if what else "")
    if total:
        width = 10
        fill = int(round(width * min(done, total) / total))
        left = elapsed / done * max(total - done, 0)
        line = (f"sweep [{'#' * fill}{'.' * (width - fill)}] {done}/{total} jobs, {failed} failed, "
                f"~{_hms(left)} left | {outcome}")
    else:
        line = f"sweep: {done} jobs, {failed} failed, {_hms(elapsed)} | {outcome}"
    print(line if len(line) <= 100 else line[:99] + "…", flush=True)


def _hms(sec: float) -> str:
    sec = int(round(sec))
    return f"{sec // 3600}:{sec // 60 % 60:02d}:{sec % 60:02d}"


if __name__ == "__main__":
    _worker()
