"""The Hydra callback of ``-m`` sweeps that files every job's MLflow run under one parent run (see
:mod:`scanreg.app.tracking`)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from scanreg.errors import ConfigError
from scanreg.app.tracking import (SWEEP_ENV, SWEEP_FILE, MlflowTracking, RunLog, _children, _sweep_outcome,
                              launcher_tags, progress_counts, sweep_size)


class SweepCallback(Callback):
    """Hydra callback for ``-m`` sweeps: creates store, experiment and parent run before the jobs start, and
    ends the parent run (FAILED if any child failed) when they are done. Holds no state but plain values."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        _sweep_outcome.clear()
        _sweep_outcome["started"] = True  # (the command exits normally after a sweep: scanreg.app.cli)
        os.environ.pop(SWEEP_ENV, None)
        # every job appends its outcome to the progress file, tracked or not: the command's exit code and the
        # closing line count the jobs from it (a store that fails later cannot hide a failed job)
        sweep_dir = Path(str(config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        progress = sweep_dir / ".progress"
        progress.write_text("")  # (a reused hydra.sweep.dir: the earlier sweep's jobs are not counted)
        info = {"total": sweep_size(config), "start": time.time(), "progress": str(progress.resolve()),
                "sweep_dir": str(sweep_dir)}
        _publish(sweep_dir, info)
        try:
            from scanreg.app.tracking import TRACKING as T

            cls, params = T.params(config.tracking)
        except ConfigError:
            return  # reported by each job
        if cls is not MlflowTracking:
            return
        import sys

        from scanreg.app.config import git_revision

        tr = MlflowTracking(params)
        client, eid = tr.prepare()
        overrides = " ".join(config.hydra.overrides.task)
        command = " ".join(["scanreg", *sys.argv[1:]]) if Path(sys.argv[0]).name == "scanreg" else \
            f"scanreg -m {overrides}"
        parent = client.create_run(eid, run_name=f"sweep: {overrides}"[:250],
                                   tags={"scanreg.sweep_dir": str(sweep_dir), "scanreg.overrides": overrides,
                                         "scanreg.sweep": "parent", "scanreg.command": command,
                                         "scanreg.git_commit": git_revision(), **launcher_tags(config)})
        info.update(uri=tr.uri, experiment=params.experiment, experiment_id=eid, parent_run_id=parent.info.run_id)
        _publish(sweep_dir, info)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        info = json.loads(os.environ.pop(SWEEP_ENV, "null") or "null")
        if not info:
            return
        failed, total = _progress_outcome(info)
        _sweep_outcome.update(failed=failed, total=total)
        if not info.get("parent_run_id"):  # untracked: the jobs' own outcomes
            print(f"sweep: {total} job(s), {failed} failed; results in {info['sweep_dir']}")
            return
        tr = MlflowTracking(MlflowTracking.Params(uri=info["uri"], experiment=info["experiment"]))
        client = tr._client()
        children = _children(client, info)
        failed = max(failed, sum(r.info.status != "FINISHED" for r in children))
        total = max(total, len(children))  # (a job that tracked nothing, or that the store lost, counts too)
        log = RunLog(client, info["parent_run_id"])
        log.log_metrics({"sweep_runs": total, "sweep_failed": failed})
        log.end("FAILED" if failed else "FINISHED", f"{failed} of {total} runs failed" if failed else None)
        _sweep_outcome.update(failed=failed, total=total)
        print(f"sweep: {total} run(s), {failed} failed; parent run {info['parent_run_id']} in experiment "
              f"'{info['experiment']}' at {info['uri']}")
        if config.get("report") is not None and config.report.get("enabled"):
            from scanreg.app.report.write import report_for_sweep

            try:
                report_for_sweep(config, info["parent_run_id"], info["uri"], info["experiment"])
            except Exception as e:  # noqa: BLE001  # the runs are safe; say why the report is missing
                msg = str(e) if isinstance(e, (ConfigError, SystemExit)) else f"{type(e).__name__}: {e}"
                print(f"error: report not written: {msg}".splitlines()[0])
                _sweep_outcome["failed"] = _sweep_outcome.get("failed", 0) or 1


def _publish(sweep_dir: Path, info: dict) -> None:
    """Tell the sweep's jobs ``info``: through the environment and, for workers that do not inherit it, the
    sweep folder's :data:`SWEEP_FILE`."""
    text = json.dumps(info)
    os.environ[SWEEP_ENV] = text
    (sweep_dir / SWEEP_FILE).write_text(text)


def _progress_outcome(info: dict) -> tuple[int, int]:
    """``(failed, total)`` jobs of the sweep by its progress file: a job that did not report (its worker died)
    counts as failed when the sweep's size is known."""
    try:
        done, failed = progress_counts(info["progress"])
    except OSError:
        done, failed = 0, 0
    total = max(done, info.get("total") or 0)
    return failed + total - done, total
