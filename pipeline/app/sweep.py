"""The Hydra callback of ``-m`` sweeps that files every job's MLflow run under one parent run (see
:mod:`scanreg.app.tracking`)."""

from __future__ import annotations

import json
import os
import re
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from scanreg.errors import ConfigError, InputError, ScanregError
from scanreg.app.tracking import (SWEEP_ENV, SWEEP_FILE, MlflowTracking, RunLog, _children, _sweep_outcome,
                              launcher_tags, progress_counts, sweep_jobs, sweep_size)


class SweepCallback(Callback):
    """Hydra callback for ``-m`` sweeps: creates store, experiment and parent run before the jobs start, and
    ends the parent run (FAILED if any child failed) when they are done. Holds no state but plain values."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        _sweep_outcome.clear()
        _sweep_outcome["started"] = True  # (the command exits normally after a sweep: scanreg.app.cli)
        os.environ.pop(SWEEP_ENV, None)
        try:
            if os.environ.get(CHECK_ENV, "1") != "0":
                _sweep_outcome["checked"] = check_jobs(config)
                validate = BasicSweeper.validate_batch_is_legal
                if not hasattr(validate, "wrapped"):
                    BasicSweeper.validate_batch_is_legal = _validate_unless_checked(validate)
        except ScanregError as e:  # (Hydra turns a callback's Exception into a warning and goes on: SystemExit)
            from scanreg.app.main import EXIT_FAILED, EXIT_USAGE, _err

            _err(str(e))
            raise SystemExit(EXIT_USAGE if isinstance(e, ConfigError) else EXIT_FAILED) from None
        except Exception:  # noqa: BLE001  # the check is an early warning: each job still checks itself
            pass
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
        overrides = " ".join(OmegaConf.to_container(config.hydra.overrides.task, resolve=False))  # (as written)
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


CHECK_ENV = "SCANREG_SWEEP_CHECK"
"""``SCANREG_SWEEP_CHECK=0`` launches a sweep without :func:`check_jobs` (e.g. on a launching machine that does
not see the data its jobs will read)."""


def check_jobs(config: DictConfig) -> bool:
    """Every job of a basic sweep composed and checked as its run would first check it (its stages built, the
    data's :meth:`~scanreg.stages.protocols.DataProvider.preflight`: settings, and files there) before any job
    starts or any run is tracked: a typo in one swept value (``data.pair=bun000:bun045,bun000:bun04``) stops the
    sweep at once, naming the job and its value, instead of failing when that job's turn comes. Raises the first
    problem's :class:`~scanreg.errors.ScanregError`; a job whose config cannot be resolved here (an
    interpolation of the job's own run) is left to the job. Returns whether every job was composed and checked
    (then Hydra's own composition of every job is left out: :func:`_validate_unless_checked`)."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    from scanreg.app.config import config_error_line

    jobs = sweep_jobs(config)
    if not jobs or not GlobalHydra.instance().is_initialized():
        return False
    configs = _job_configs(config, jobs, GlobalHydra.instance().config_loader())
    every = True
    bad: list[tuple[int, list[str], BaseException]] = []
    passed: set[str] = set()
    for i, (job, cfg) in enumerate(zip(jobs, configs)):
        try:
            _check_job(cfg, passed)
        except HydraException as e:
            bad.append((i, job, ConfigError(config_error_line(e))))
        except ScanregError as e:
            bad.append((i, job, e))
        except Exception:  # noqa: BLE001  # (e.g. ${hydra:runtime...}, set in the job): the job says what is wrong
            every = False
    if bad:
        i, job, e = bad[0]
        swept = [k for k, column in enumerate(zip(*jobs)) if len(set(column)) > 1]  # (the same keys in each job)
        named = re.sub(r"\\(.)", r"\1", " ".join(job[k] for k in swept) or " ".join(job))  # (Hydra's escapes)
        more = f" (and {len(bad) - 1} more of the {len(jobs)} jobs)" if len(bad) > 1 else ""
        unseen = f"; {CHECK_ENV}=0 launches it unchecked" if isinstance(e, InputError) else ""
        raise type(e)(f"sweep not started: job #{i} ({named}): {e}{more}{unseen}")
    return every


def _job_configs(config: DictConfig, jobs: list[list[str]], loader):
    """Each job's config, as the launcher composes it (``load_sweep_config``), made cheaply: composing is slow,
    so it is done once per distinct set of config-group choices, and each job's other overrides are applied to
    that composition the way Hydra applies them after composing (its ``_apply_overrides_to_config``, hydra-core
    1.3). Yields each job's config (``jobs``: each one's overrides, :func:`sweep_jobs`) or the exception making it
    raises."""
    import copy

    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser, composed = OverridesParser.create(config_loader=loader), {}
    for job in jobs:
        try:
            overrides = parser.parse_overrides(list(job))
            groups = tuple(o.input_line for o in overrides if loader.repository.group_exists(o.key_or_group))
            if groups not in composed:
                composed[groups] = loader.load_sweep_config(config, list(groups))
            values = [o for o in overrides if o.input_line not in groups]
            # every job of a basic sweep sets the same keys: they can be set over the last job's, unless a key is
            # added or deleted or a value is merged into (a dict): then on a copy
            cfg = composed[groups]
            if any(o.is_add() or o.is_delete() or o.is_force_add() or isinstance(o.value(), (dict, list))
                   for o in values):
                cfg = copy.deepcopy(cfg)
            ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
        except Exception as e:  # noqa: BLE001  # raised where the job is checked
            cfg = e
        yield cfg


def _check_job(cfg, passed: set[str]) -> None:
    """:func:`~scanreg.app.main.check_config` and the data's preflight for one job's config (or raise what
    making it raised). The data block is checked on its own (built, its preflight), and the rest of the config
    once per distinct rest (``passed`` keeps the keys of the blocks that passed): a sweep of pairs or seeds builds
    its stages once."""
    from scanreg.app.main import check_config
    from scanreg.stages.registry import DATA
    from scanreg.types import checked_seed

    if isinstance(cfg, BaseException):
        raise cfg
    checked_seed(cfg.get("seed"))

    def check_data() -> None:
        data = DATA.build(cfg.data)
        if not cfg.hydra.job.get("chdir"):  # (files relative to a job folder it changes into: the job's to find)
            _preflight(data)

    plain = OmegaConf.to_container(cfg, resolve=False)
    rest = {k: v for k, v in plain.items() if k not in ("seed", "hydra", "data")}
    # the data block keyed as this job resolves it, the rest as written (an interpolation such as ${seed} not
    # resolved): only a pass is taken from another job, a block that failed is checked again with this job's own
    # values (no valid job is refused)
    for block, check in ((["data", OmegaConf.to_container(cfg.data, resolve=True)], check_data),
                         (rest, lambda: check_config(cfg))):
        key = json.dumps(block, sort_keys=True, default=str)
        if key not in passed:
            with _job_environment(cfg):
                check()
            passed.add(key)


@contextmanager
def _job_environment(cfg):
    """The environment variables the job will have (``hydra.job.env_set``), set while it is checked."""
    env = {str(k): str(v) for k, v in (cfg.hydra.job.get("env_set") or {}).items()}
    before = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _preflight(data) -> None:
    """A data provider's preflight (:class:`~scanreg.stages.data.base.Provider`); a plugin's provider that has
    none: its ``require``."""
    getattr(data, "preflight", data.require)()


def _validate_unless_checked(validate):
    """Hydra's basic sweeper composes every job once more before launching, to validate it (its
    ``validate_batch_is_legal``, most of a sweep's start: ``experiments/benchmarks/sweep_check.md``); when
    :func:`check_jobs` has composed and checked every job of this sweep, that second composition is left out.
    (Hydra takes a sweeper class only from a ``hydra_plugins`` package, which this one-package project does not
    install: the basic sweeper's method is wrapped instead, in the launching process, hydra-core 1.3.)"""
    def validate_batch_is_legal(self, batch) -> None:
        if not _sweep_outcome.get("checked"):
            validate(self, batch)

    validate_batch_is_legal.wrapped = validate
    return validate_batch_is_legal


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
