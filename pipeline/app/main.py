"""``scanreg``: the Hydra application that runs the pipeline and tracks it.

A job (one run, or one job of a ``-m`` sweep) builds its stages (a bad name or value fails before any work),
runs :func:`scanreg.runner.run_stages`, and logs the run with the configured tracking backend. Every expected
failure ends as one ``error:`` line and an exit code (:data:`EXIT_FAILED` ...); the run is logged FAILED with
its reason, and a sweep goes on with its other jobs.
"""

from __future__ import annotations

import json
import os
import sys
import time
import traceback
from contextlib import contextmanager
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from scanreg.app.config import (PRESET_GROUPS, STAGE_GROUPS, config_error_line, git_revision, interpolation_error_line,
                                register_schemas)
from scanreg.errors import ConfigError, ScanregError, log_line, warn
from scanreg.stages.registry import CONF_PACKAGE

# The exit codes (documentation: Getting started, Errors and exit codes); 0: done.
EXIT_FAILED = 1
"""The input or a stage failed (the MLflow run ends FAILED), or a job of a sweep failed."""
EXIT_USAGE = 2
"""A usage or config error (unknown stage or parameter, wrong type, a required setting missing), found before any
MLflow run is created."""
EXIT_INTERNAL = 3
"""An internal error (a bug: ``verbose=true`` for the traceback)."""
EXIT_INTERRUPTED = 130
"""Interrupted (Ctrl-C, SIGTERM)."""


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr, flush=True)
    log_line(f"error: {msg}")


def check_config(cfg: DictConfig):
    """Every stage built (names and parameters), what a stage needs set (``data.source``), the ``report`` block
    when a report will be written, and the tracking backend: a :class:`ConfigError` before anything runs or is
    tracked. Returns the built stages and the tracking backend."""
    from scanreg.app.tracking import TRACKING
    from scanreg.runner import build_stages
    from scanreg.stages.registry import make_params
    from scanreg.types import checked_seed

    checked_seed(cfg.get("seed"))
    stages = build_stages(cfg)
    stages.data.require()
    if cfg.get("report") is not None and cfg.report.get("enabled"):
        from scanreg.app.report.params import ReportParams

        make_params(ReportParams, OmegaConf.to_container(cfg.report, resolve=True), "report")
    return stages, TRACKING.build(cfg.tracking)


def run_job(cfg: DictConfig) -> dict | float | None:
    """One job: check, run, log, report. Returns the job's result (its ``objective`` metric for a tuning
    sweeper); a single run's failure is a ``SystemExit`` with its code."""
    from scanreg.app.tracking import PENDING_RECORD, NoTracking, RunRecord, flatten, report_progress
    from scanreg.runner import run_stages, summary_lines
    from scanreg.types import RunContext

    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    t_start = time.perf_counter_ns()
    tracker, stages = NoTracking(NoTracking.Params()), None
    try:
        resolved = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    except Exception as e:  # noqa: BLE001 (a bad interpolation): still log what there is
        resolved, problem = OmegaConf.to_container(cfg, resolve=False), ConfigError(interpolation_error_line(e))
    else:
        problem = None
    try:
        if problem is None:
            stages, tracker = check_config(cfg)
    except ScanregError as e:
        problem = e
    if problem is not None and not multirun:  # no run is created for a single run's config error
        _err(str(problem))
        _unmake_run_dir(run_dir)
        raise SystemExit(EXIT_USAGE if isinstance(problem, ConfigError) else EXIT_FAILED)
    if problem is not None:  # a sweep files it as a failed job
        from scanreg.app.tracking import TRACKING

        try:
            tracker = TRACKING.build(cfg.tracking)
        except ScanregError:
            pass
    record = RunRecord(run_name=(" ".join(hc.overrides.task) or "defaults")[:250], params=flatten(resolved),
                       tags=_tags(hc, run_dir))
    if not multirun and (run_dir / "config.yaml").exists():  # (a reused hydra.run.dir: files are not deleted)
        warn(f"{run_dir} holds an earlier run's results: this run replaces the files it writes, and any other "
             "file of the earlier run stays beside them (give a new hydra.run.dir to keep runs apart)")
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(resolved))
    try:
        if problem is not None:
            raise problem
        ctx = RunContext(seed=int(cfg.seed), run_dir=run_dir, verbose=bool(cfg.get("verbose", False)),
                         in_sweep=multirun)
        res = run_stages(stages, ctx, t_start)
    except KeyboardInterrupt:
        _log(tracker, record.ended("KILLED", "interrupted", artifacts=[run_dir / "config.yaml"]), multirun)
        raise
    except BaseException as e:  # noqa: BLE001  # every failure ends the run FAILED with its reason
        return _failed(e, cfg, tracker, record, run_dir, multirun)
    children = [RunRecord(run_name=name, params={}, tags={"scanreg.part": "pair"}, start_time=record.start_time)
                .ended("FINISHED", None, metrics) for name, metrics in res.children]
    finished = record.ended("FINISHED", None, res.metrics, res.histories, [run_dir / "config.yaml", *res.artifacts])
    request = getattr(tracker, "request", None) if multirun else None
    pending = run_dir / PENDING_RECORD
    if request is not None:  # kept until logged: an interrupt that stops this job meanwhile loses nothing
        pending.write_text(json.dumps(request(finished, children)))
    run_id = _log(tracker, finished, multirun, children)
    pending.unlink(missing_ok=True)
    where = f"results: {run_dir}" + (f"  (MLflow run {run_id})" if run_id else "")
    lines = summary_lines(res)
    (run_dir / "summary.txt").write_text("\n".join([*lines, "", where]) + "\n")  # the table, kept with the run
    if multirun:  # one line per job on the console; the full table in the job's folder
        report_progress("FINISHED", job_line(res.metrics))
    else:
        print("\n".join(lines))
        print(where)
    objective = cfg.get("objective")
    if objective:  # what a tuning sweeper (Optuna) minimises
        if objective not in res.metrics:
            _err(f"objective '{objective}' is not a metric of this run; e.g. rotation_error_deg, rms, time_total_s")
            return float("inf")
        return float(res.metrics[objective])
    return res.to_json()


def _tags(hc, run_dir: Path) -> dict[str, str]:
    """The run's tags: the chosen implementation of every group, where it wrote, its overrides, the commit."""
    choices = {f"group.{g}": str(hc.runtime.choices.get(g)) for g in STAGE_GROUPS + PRESET_GROUPS
               if g in hc.runtime.choices}
    return {**choices, "scanreg.run_dir": str(run_dir), "scanreg.overrides": " ".join(hc.overrides.task),
            "scanreg.git_commit": git_revision()}


def _log(tracker, record, multirun: bool, children=()) -> str | None:
    """Log the run (and its ``children``); a failure of the store itself is one error line (the job fails, its
    results stay)."""
    try:
        return tracker.log_run(record, children)
    except Exception as e:  # noqa: BLE001  # a bad store
        msg = (str(e) if isinstance(e, ScanregError) else f"tracking: {type(e).__name__}: {e}").splitlines()[0]
        _err(msg)
        if multirun:
            from scanreg.app.tracking import report_progress

            report_progress("FAILED", msg)
            return None
        raise SystemExit(EXIT_FAILED)


def _unmake_run_dir(run_dir: Path) -> None:
    """Remove what Hydra made for a run that a configuration error stopped before it began (``.hydra/`` and
    ``main.log``, which holds only the lines the console showed), and the folder when nothing else is in it, with
    the folders above it that it leaves empty, up to the working directory (``outputs/runs/DATE/``): a run that
    never ran leaves no folder."""
    import shutil

    shutil.rmtree(run_dir / ".hydra", ignore_errors=True)
    try:
        if not (run_dir / "config.yaml").exists():  # (the folder of an earlier run, reused, keeps its log)
            (run_dir / "main.log").unlink(missing_ok=True)
        run_dir.rmdir()  # only when empty
        here = Path.cwd().resolve()
        for parent in run_dir.resolve().parents:
            if parent == here or here not in parent.parents:
                break
            parent.rmdir()  # only when empty (else OSError: stop)
    except OSError:
        pass


def _failed(e: BaseException, cfg: DictConfig, tracker, record, run_dir: Path, multirun: bool):
    """A failed job: its reason and exit code, the run logged FAILED with the metrics measured before the
    failure, the repair's table when there is one; a sweep goes on."""
    from scanreg.app.tracking import report_progress
    from scanreg.runner import REPAIR_PREFIX, repair_table

    code = EXIT_USAGE if isinstance(e, ConfigError) else EXIT_FAILED
    if isinstance(e, ScanregError):
        reason = str(e)
    elif isinstance(e, SystemExit):
        reason = f"exit {e.code}"
        code = e.code if isinstance(e.code, int) else EXIT_FAILED
    else:
        code = EXIT_INTERNAL
        reason = f"internal error: {type(e).__name__}: {e}".splitlines()[0]
        if cfg.get("verbose", False):
            traceback.print_exc()
        else:
            reason += " (run with verbose=true for the traceback)"
    metrics = getattr(e, "metrics", None) or {}
    _log(tracker, record.ended("FAILED", reason, metrics, artifacts=[run_dir / "config.yaml"]), multirun)
    table = [ln for role, prefix in REPAIR_PREFIX.items() for ln in repair_table(metrics, prefix, role)[1:]]
    if multirun:  # a sweep's console gets one line per job; the table stays in the job's folder
        if metrics:
            (run_dir / "summary.txt").write_text("\n".join([f"error: {reason}", *table]) + "\n")
    elif table:
        print("\n".join(table))
    _err(reason)
    if multirun:
        report_progress("FAILED", reason)
        return float("inf") if cfg.get("objective") else None  # the worst value: a tuning sweep goes on
    raise SystemExit(code)


def job_line(m: dict) -> str:
    """A sweep job's result in a few words: with ground truth whether it is a success, a scan set's scans placed
    and its worst scan's errors, a pair's errors (with ground truth) or RMS; and the time."""
    parts = []
    if m.get("success") in (0.0, 1.0):  # (the job ran either way: "ok" said nothing of a 162-degree result)
        parts.append("success" if m["success"] == 1.0 else "NO success")
    if "scans_placed" in m and "n_scans" in m:
        parts.append(f"{int(m['scans_placed'])}/{int(m['n_scans'])} scans placed")
    if "scan_rotation_error_max_deg" in m:
        parts.append(f"worst rot {m['scan_rotation_error_max_deg']:.3g}°")
    if "rotation_error_deg" in m:
        parts.append(f"rot {m['rotation_error_deg']:.3g}°")
    if "translation_error_rel" in m:
        parts.append(f"transl {100 * m['translation_error_rel']:.2g} %")
    elif "rms" in m:
        parts.append(f"rms {m['rms']:.3g}")
    if "time_total_s" in m:
        parts.append(f"{m['time_total_s']:.1f} s")
    return ", ".join(parts)


@contextmanager
def run_log(run_dir: Path):
    """While a job runs, its note, warning and error lines (:data:`scanreg.errors.RUN_LOG`) are appended to
    ``run_dir/main.log``, time-stamped, and not passed on to the console's handlers (the console has them)."""
    import logging

    from scanreg.errors import RUN_LOG

    log = logging.getLogger(RUN_LOG)
    handler = logging.FileHandler(run_dir / "main.log", delay=True)
    handler.setFormatter(logging.Formatter("[%(asctime)s] %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False
    try:
        yield
    finally:
        log.removeHandler(handler)
        handler.close()


@hydra.main(config_path=f"pkg://{CONF_PACKAGE}", config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> dict | None:
    with run_log(Path(HydraConfig.get().runtime.output_dir)):
        return run_job(cfg)


def _stdout_gone() -> None:
    """The reader of our output went away (``scanreg --help | head``): nothing to report, and no error from the
    interpreter's own flush at exit."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def main() -> None:
    """The Hydra application: scan files given by position (:mod:`scanreg.app.arguments`); a composition error (a
    bad override, an unknown group choice or parameter) is one ``error:`` line and exit 2; Ctrl-C or SIGTERM
    ends every run of a sweep that is still open."""
    import signal

    from hydra.errors import HydraException

    from scanreg.app.arguments import path_override_error, unknown_flag_error, with_files
    from scanreg.app.startup import is_multirun, quick_help
    from scanreg.app.tracking import _sweep_outcome, end_interrupted_sweep

    try:  # scan files given by position become quoted overrides; a path Hydra cannot read says the fix
        argv = with_files(sys.argv[1:])
        fix = unknown_flag_error(argv) or path_override_error(argv, multirun=is_multirun(argv))
    except ConfigError as e:
        fix = str(e)
    if fix:
        _err(fix)
        raise SystemExit(EXIT_USAGE)
    sys.argv[1:] = argv
    helps = [a for a in argv if a in ("-h", "--help")]
    if helps and all(a in helps or ("=" in a and not a.startswith("-")) for a in argv):
        text = quick_help([a for a in argv if a not in helps])
        if text is not None:
            try:
                print(text, flush=True)
            except BrokenPipeError:
                _stdout_gone()
            return
    register_schemas()
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises its composition errors here, to be said in one line

    def _terminate(signum, frame):  # SIGTERM (a scheduler's preemption, kill) ends runs like Ctrl-C does
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminate)
    try:
        _hydra_main()
    except KeyboardInterrupt:
        try:
            n = end_interrupted_sweep()
        except Exception:  # noqa: BLE001  # the message below is what matters
            n = 0
        saved = _sweep_outcome.get("recovered", 0)
        _err("interrupted" + (f"; {n} unfinished MLflow run(s) of the sweep marked KILLED" if n else "")
             + (f"; {saved} finished job(s) cut short while being logged, logged from their folders" if saved else ""))
        raise SystemExit(EXIT_INTERRUPTED)
    except BrokenPipeError:
        _stdout_gone()
        raise SystemExit(0)
    except HydraException as e:  # the config did not compose: no run was made (a sweep's parent ends FAILED)
        reason = config_error_line(e)
        _end_sweep_quietly(end_interrupted_sweep, reason)
        _err(reason)
        raise SystemExit(EXIT_USAGE)
    except Exception as e:  # noqa: BLE001  # e.g. a launcher that cannot start; no run is left RUNNING
        unwritable = _unwritable_output(e, argv)
        if unwritable:  # Hydra could not make the run's folder or its log file there: the user's to fix
            _end_sweep_quietly(end_interrupted_sweep, unwritable)
            _err(unwritable)
            raise SystemExit(EXIT_FAILED)
        reason = f"sweep failed: {type(e).__name__}: {e}".splitlines()[0]
        _end_sweep_quietly(end_interrupted_sweep, reason)
        if any(a.replace(" ", "") in ("verbose=true", "verbose=True") for a in argv):
            traceback.print_exc()
        _err(reason + " (verbose=true for the traceback)")
        raise SystemExit(EXIT_INTERNAL)
    if _sweep_outcome.get("failed"):
        raise SystemExit(EXIT_FAILED)


def _unwritable_output(e: BaseException, argv: list[str] = ()) -> str | None:
    """The error line for an exception that says an output folder or file cannot be written (a permission, a
    read-only file system, a file where a folder should be, or a folder the command names in ``argv``
    (``hydra.run.dir``, ``hydra.sweep.dir``) that cannot be made, e.g. under /proc; anywhere in its chain of
    causes: Hydra wraps its log file's in a ValueError), else None."""
    import errno

    cannot = (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EEXIST)
    from scanreg.app.arguments import override_value

    named = {override_value(a) for a in argv
             if "=" in a and a.partition("=")[0].lstrip("+") in ("hydra.run.dir", "hydra.sweep.dir")}
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        at = Path(os.path.abspath(e.filename)) if isinstance(e, OSError) and e.filename else None
        made = at is not None and e.errno == errno.ENOENT and any(
            Path(n) == at or at in Path(n).parents for n in map(os.path.abspath, named))
        if isinstance(e, OSError) and (e.errno in cannot or made) and e.filename:
            return (f"output folder: cannot write {e.filename} ({e.strerror}); run from a writable folder or set "
                    "hydra.run.dir=FOLDER (hydra.sweep.dir=FOLDER for -m) to one")
        e = e.__cause__ or e.__context__
    return None


def _end_sweep_quietly(end, reason: str) -> None:
    try:
        end(reason, status="FAILED")
    except Exception:  # noqa: BLE001  # the error line is what matters
        pass
