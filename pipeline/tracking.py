"""Experiment tracking with MLflow.

One MLflow run per job. The store and the experiment are created once, before any job starts (in the single
run itself, or by :class:`SweepCallback` in the launching process of a ``-m`` sweep), and every run is created
with an explicit ``experiment_id``. A sweep has one parent run; each job's run is its child
(``mlflow.parentRunId``). A failing job ends FAILED with its one-line reason in the tag ``error``; the sweep goes
on, and the parent ends FAILED if any child failed.

Default store: ``sqlite:///<cwd>/outputs/mlflow.db`` (absolute path), artifacts beside it in
``outputs/mlartifacts``; ``$MLFLOW_TRACKING_URI`` or ``tracking.uri`` override it.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional


from scanreg.errors import ConfigError
from scanreg.registry import TRACKING

if TYPE_CHECKING:
    from omegaconf import DictConfig

# No Hydra or OmegaConf at import: the MLflow helper process (``python -m scanreg.tracking``) imports this module
# on the critical path of a run's start-up. The Hydra callback lives in :mod:`scanreg.sweep`.

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
    except Exception:  # noqa: BLE001: not inside a Hydra job
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


class BackgroundRunLog:
    """A :class:`RunLog` kept by a helper process (``python -m scanreg.tracking``), so that importing MLflow (2-5 s:
    it imports pandas, pyarrow, FastAPI...) and opening its store overlap the pipeline instead of preceding it. A
    process, not a thread: two threads importing overlapping module trees can see each other's half-imported
    modules. The helper creates the run at once (its start time the time of the request) and then does what it
    is sent, in order, answering each request; every method here waits for the answer, and raises the helper's
    error (a bad store) as a ``RuntimeError``. The helper ignores Ctrl-C, so that an interrupted run can still
    be ended KILLED, and exits when this process closes its input."""

    def __init__(self, start: dict):
        global _prestarted
        self._proc, _prestarted = (_prestarted or spawn_helper()), None
        self._run_id: str | None = None
        self._send({"op": "start", **start})

    def _send(self, msg: dict) -> None:
        try:
            self._proc.stdin.write(json.dumps(msg) + "\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            pass  # the helper is gone: _reply says so

    def _reply(self) -> dict:
        while True:
            line = self._proc.stdout.readline()
            if not line:
                raise RuntimeError(f"the MLflow logging process ended (exit {self._proc.wait()})")
            if line.startswith(_REPLY):  # anything else a library printed is not an answer
                r = json.loads(line[len(_REPLY):])
                if "error" in r:
                    raise RuntimeError(r["error"])
                return r

    def _call(self, op: str, **kw) -> dict:
        self.run_id  # noqa: B018 (the start's answer comes first)
        self._send({"op": op, **kw})
        return self._reply()

    @property
    def run_id(self) -> str:
        if self._run_id is None:
            self._run_id = self._reply()["run_id"]
        return self._run_id

    def log_metrics(self, metrics: dict[str, float], step_metrics: dict[str, list[float]] | None = None) -> None:
        self._call("metrics", metrics={k: float(v) for k, v in metrics.items() if isinstance(v, (int, float))},
                   step_metrics={k: [float(x) for x in v] for k, v in (step_metrics or {}).items()})

    def log_artifacts(self, paths: list[Path]) -> None:
        self._call("artifacts", paths=[str(Path(p).resolve()) for p in paths])

    def set_tags(self, tags: dict[str, str]) -> None:
        self._call("tags", tags={k: str(v) for k, v in tags.items()})

    def end(self, status: str, reason: str | None = None) -> None:
        try:
            self._call("end", status=status, reason=reason)
        finally:
            try:
                self._proc.stdin.close()
            except OSError:
                pass
            self._proc.wait(timeout=60)


_REPLY = "@scanreg-tracking "
"""Prefix of the helper process's answers on its standard output."""

_prestarted = None
"""A helper process started by :func:`prestart_helper`, taken by the next :class:`BackgroundRunLog`."""


def spawn_helper():
    """Start ``python -m scanreg.tracking`` (it imports MLflow at once, then waits for requests)."""
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-m", "scanreg.tracking"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)


def prestart_helper() -> None:
    """Start the MLflow helper process now, so that its import of MLflow (1-2 s) overlaps this process's own
    imports and Hydra's composition instead of following them: for a single CLI run that may track with MLflow
    (:func:`scanreg.cli.may_track_single_run`, before the config is composed). The next :class:`BackgroundRunLog`
    takes it; if none does, :func:`drop_prestarted` stops it (``scanreg.cli``, and ``scanreg.app.main`` once the
    composed config does not use MLflow). Does nothing if already started."""
    global _prestarted
    if _prestarted is None:
        _prestarted = spawn_helper()


def drop_prestarted() -> None:
    """Stop the helper process of :func:`prestart_helper` if no run took it (the run does not use MLflow)."""
    global _prestarted
    if _prestarted is not None:
        _prestarted.kill()
        _prestarted.wait()
        _prestarted = None


def _warm_mlflow() -> None:
    """Import what opening a SQL store and logging into it will import (MLflow, its SQLAlchemy store, the
    store's ORM mappers configured), about 1.5-2 s, so that the helper is ready when the run starts."""
    import mlflow.tracking  # noqa: F401

    try:
        import mlflow.store.tracking.sqlalchemy_store  # noqa: F401
        import sqlalchemy.orm

        sqlalchemy.orm.configure_mappers()
    except Exception:  # noqa: BLE001: only a head start; opening the store reports any real problem
        pass


def _helper() -> None:
    """The loop of ``python -m scanreg.tracking`` (see :class:`BackgroundRunLog`): JSON requests on standard input,
    one answer each on standard output."""
    import signal
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _quiet_mlflow()
    _warm_mlflow()  # at once: the caller starts this process before it knows the run

    log = None
    for line in sys.stdin:
        msg = json.loads(line)
        try:
            op = msg["op"]
            if op == "start":
                if msg.get("sweep"):
                    os.environ[SWEEP_ENV] = json.dumps(msg["sweep"])
                tr = MlflowTracking(MlflowTracking.Params(uri=msg["uri"], experiment=msg["experiment"]))
                tr.uri = msg["resolved_uri"]
                log = tr._start_run(msg["run_name"], msg["params"], msg["tags"], start_time=msg["start_time"])
                reply = {"run_id": log.run_id}
            elif op == "metrics":
                log.log_metrics(msg["metrics"], msg["step_metrics"])
                reply = {}
            elif op == "artifacts":
                log.log_artifacts([Path(p) for p in msg["paths"]])
                reply = {}
            elif op == "tags":
                log.set_tags(msg["tags"])
                reply = {}
            elif op == "end":
                log.end(msg["status"], msg.get("reason"))
                reply = {}
            else:
                reply = {"error": f"unknown request {op!r}"}
        except Exception as e:  # noqa: BLE001: the caller reports it
            reply = {"error": f"{type(e).__name__}: {e}".splitlines()[0] if str(e) else type(e).__name__}
        print(_REPLY + json.dumps(reply), flush=True)
        if msg.get("op") == "end" and "error" not in reply:
            # the run is ended and its store committed: exit without tearing down MLflow's module graph and
            # SQLAlchemy's pools, which takes about 0.5 s that the caller would wait for
            sys.stderr.flush()
            os._exit(0)


@TRACKING.register("none")
class NoTracking:
    """Track nothing (results stay in the run directory)."""

    @dataclass
    class Params:
        uri: Optional[str] = None
        """Ignored; accepted so that configs written for ``tracking=mlflow`` also run untracked."""
        experiment: str = "scanreg"
        """Ignored; accepted so that experiment files that name their MLflow experiment also run untracked."""

    def __init__(self, params: Params):
        self.p = params

    def prepare(self) -> None:
        return None

    def start_run(self, *a, **k) -> None:
        return None


@TRACKING.register("mlflow")
class MlflowTracking:
    """Log every run to MLflow: config as params, stage choices as tags, metrics, artifacts."""

    @dataclass
    class Params:
        uri: Optional[str] = None
        """Tracking URI; null: $MLFLOW_TRACKING_URI, else sqlite:///<cwd>/outputs/mlflow.db (absolute path)."""
        experiment: str = "scanreg"
        """MLflow experiment name the runs are filed under."""

    def __init__(self, params: Params):
        self.p = params
        self.uri = params.uri or os.environ.get("MLFLOW_TRACKING_URI") or \
            f"sqlite:///{(Path.cwd() / 'outputs' / 'mlflow.db').resolve()}"

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

    def start_run(self, run_name: str, params: dict[str, str], tags: dict[str, str],
                  background: bool = False) -> RunLog | BackgroundRunLog:
        """Create the run (with its params and tags) and return its log; ``background``: by a helper process (see
        :class:`BackgroundRunLog`) unless MLflow is imported in this process already."""
        import sys

        if background and "mlflow" not in sys.modules:  # once imported here (a sweep's process), log here
            return BackgroundRunLog({"uri": self.p.uri, "resolved_uri": self.uri, "experiment": self.p.experiment,
                                     "sweep": sweep_info(), "run_name": run_name, "params": params, "tags": tags,
                                     "start_time": int(time.time() * 1000)})
        return self._start_run(run_name, params, tags)

    def _start_run(self, run_name: str, params: dict[str, str], tags: dict[str, str],
                   start_time: int | None = None) -> RunLog:
        sweep = sweep_info()
        # a sweep's jobs log where the launching process created the parent run, unless a job names another
        # store explicitly (workers of a cluster may not share the launching process's environment or cwd)
        if sweep and (self.p.uri is None or sweep["uri"] == self.uri) and sweep["experiment"] == self.p.experiment:
            self.uri = sweep["uri"]
            client, eid = self._client(), sweep["experiment_id"]
            tags = {**tags, "mlflow.parentRunId": sweep["parent_run_id"]}
        else:
            client, eid = self.prepare()
        run = client.create_run(eid, run_name=run_name, tags=tags, start_time=start_time)
        log = RunLog(client, run.info.run_id)
        log.log_params(params)
        return log


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


def end_interrupted_sweep(reason: str = "interrupted", status: str = "KILLED") -> int:
    """After an interrupt of a sweep (in the launching process): every child run still RUNNING, and the parent,
    end KILLED with the reason, so that no run is left RUNNING. Returns the number of runs ended."""
    info = json.loads(os.environ.pop(SWEEP_ENV, "null") or "null")
    if not info:
        return 0
    tr = MlflowTracking(MlflowTracking.Params(uri=info["uri"], experiment=info["experiment"]))
    client = tr._client()
    children = _children(client, info)
    n = 0
    for r in children:
        if r.info.status == "RUNNING":
            RunLog(client, r.info.run_id).end(status, reason)
            n += 1
    RunLog(client, info["parent_run_id"]).end(status, reason)
    return n + 1


def sweep_size(config: DictConfig) -> int | None:
    """Number of jobs of a basic-sweeper sweep (command-line sweeps and ``hydra.sweeper.params``), else None."""
    try:
        if "BasicSweeper" not in str(config.hydra.sweeper.get("_target_", "")):
            return None
        from hydra.core.override_parser.overrides_parser import OverridesParser

        lines = [f"{k}={v}" for k, v in (config.hydra.sweeper.get("params") or {}).items()]
        lines += list(config.hydra.overrides.task)
        sizes: dict[str, int] = {}
        for o in OverridesParser.create().parse_overrides(lines):
            sizes[o.get_key_element()] = len(list(o.sweep_string_iterator())) if o.is_sweep_override() else 1
        n = 1
        for v in sizes.values():
            n *= v
        return n
    except Exception:  # noqa: BLE001: progress is a nicety
        return None


def report_progress(status: str, what: str = "") -> None:
    """After a sweep job: append to the sweep's progress file and print one line, the job's outcome with a
    progress bar and the estimated time left (the job's full table is in its folder, ``summary.txt``)."""
    info = sweep_info()
    if not info or not info.get("progress"):
        return
    try:
        with open(info["progress"], "a") as f:
            f.write(status + "\n")
        done_lines = Path(info["progress"]).read_text().split()
    except OSError:
        return
    done, failed = len(done_lines), sum(s != "FINISHED" for s in done_lines)
    elapsed = time.time() - info["start"]
    total = info.get("total")
    try:
        from hydra.core.hydra_config import HydraConfig

        job = f"#{HydraConfig.get().job.num} "
    except Exception:  # noqa: BLE001: not inside a Hydra job
        job = ""
    outcome = f"{job}{'ok' if status == 'FINISHED' else status}" + (f": {what}" if what else "")
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
    _helper()


def __getattr__(name: str):
    if name == "SweepCallback":  # configs written before it moved name scanreg.tracking.SweepCallback
        from scanreg.sweep import SweepCallback

        return SweepCallback
    raise AttributeError(f"module 'scanreg.tracking' has no attribute {name!r}")
