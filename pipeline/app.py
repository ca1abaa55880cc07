"""``scanreg``: the Hydra application that runs the pipeline and tracks it."""

from __future__ import annotations

import contextlib
import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from scanreg.config import CONF_PACKAGE, conf_dir
from scanreg.errors import ConfigError, ScanregError

EXIT_FAILED, EXIT_USAGE, EXIT_INTERNAL, EXIT_INTERRUPTED = 1, 2, 3, 130
"""The exit codes (README, Errors): 0 done; 1 the input or a stage failed (the MLflow run ends FAILED), or a
job of a sweep failed; 2 a usage or config error (unknown stage or parameter, wrong type, a required setting
missing), found before any MLflow run is created; 3 an internal error (a bug: verbose=true for the traceback);
130 interrupted."""

CONF_DIR = conf_dir()
STAGE_GROUPS = ("data", "repair", "sampler", "salience", "descriptor", "matcher", "coarse", "icp", "tracking")
PRESET_GROUPS = ("method", "experiment", "launch")
"""Groups of ``# @package _global_`` files that set several stage groups (or the sweep launcher) at once."""


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr, flush=True)


def validate_config(cfg: DictConfig, stages: bool = True) -> dict | None:
    """Build every stage of ``cfg`` (unless ``stages`` is false: :func:`check_config` did) and check the
    ``report`` block, without running anything: a bad name, parameter or value fails here, before any work.
    Returns the built stages."""
    from scanreg.registry import make_params
    from scanreg.runner import build_stages

    stages = build_stages(cfg) if stages else None
    if cfg.get("report") is not None and cfg.report.get("enabled"):
        # only when a report will be written: scanreg.report imports pandas (about 1 s), which a run never uses
        from scanreg.report import ReportParams

        make_params(ReportParams, OmegaConf.to_container(cfg.report, resolve=True), "report")
    return stages


def run_job(cfg: DictConfig) -> dict | None:
    from scanreg.registry import TRACKING, load_all
    from scanreg.runner import run_pipeline, summary_lines
    from scanreg.config import git_revision
    from scanreg.tracking import flatten, report_progress

    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    verbose = bool(cfg.get("verbose", False))
    try:
        load_all()
        tracker = TRACKING.build(cfg.tracking)
        try:
            resolved = OmegaConf.to_container(cfg, resolve=True)
        except Exception as e:  # noqa: BLE001 (bad interpolation): still log what we have
            resolved = OmegaConf.to_container(cfg, resolve=False)
            resolve_error = f"config: {e}".splitlines()[0]
        else:
            resolve_error = None
        if not multirun:  # config errors stop here, before an MLflow run is created (a sweep files them)
            if resolve_error:
                raise ConfigError(resolve_error)
            check_config(cfg)
        choices = {f"group.{g}": str(hc.runtime.choices.get(g)) for g in STAGE_GROUPS + PRESET_GROUPS
                   if g in hc.runtime.choices}
        overrides = " ".join(hc.overrides.task)
        run = tracker.start_run(
            run_name=(overrides or "defaults")[:250],
            params=flatten(resolved),
            tags={**choices, "scanreg.run_dir": str(run_dir), "scanreg.overrides": overrides,
                  "scanreg.git_commit": git_revision()},
            # a single run: MLflow's import and store open while the pipeline runs (tracking.BackgroundRunLog); a
            # sweep's jobs log in their own process, which imports MLflow once for all its jobs
            background=not multirun,
        )
    except Exception as e:  # noqa: BLE001: a bad tracking setup is reported like any other error
        _err(str(e) if isinstance(e, ScanregError) else f"tracking: {type(e).__name__}: {e}".splitlines()[0])
        if multirun:
            report_progress("FAILED", str(e).splitlines()[0] if str(e) else type(e).__name__)
            return _failed_objective(cfg)
        raise SystemExit(EXIT_USAGE if isinstance(e, ConfigError) else EXIT_FAILED)

    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(resolved))
    try:
        if resolve_error:
            raise ScanregError(resolve_error)
        validate_config(cfg, stages=multirun)  # a single run's stages were built by check_config above
        res = run_pipeline(cfg, run_dir, in_sweep=multirun)
    except KeyboardInterrupt:
        if run:
            run.end("KILLED", "interrupted")
        raise
    except BaseException as e:  # noqa: BLE001: every failure ends the run FAILED with its reason
        code = EXIT_USAGE if isinstance(e, ConfigError) else EXIT_FAILED
        if isinstance(e, ScanregError):
            reason = str(e)
        elif isinstance(e, SystemExit):
            reason = f"exit {e.code}"
            code = e.code if isinstance(e.code, int) else EXIT_FAILED
        else:
            code = EXIT_INTERNAL
            reason = f"internal error: {type(e).__name__}: {e}".splitlines()[0]
            if verbose:
                traceback.print_exc()
            else:
                reason += " (run with verbose=true for the traceback)"
        if run:
            try:
                run.log_metrics(getattr(e, "metrics", {}) or {})
                run.log_artifacts([run_dir / "config.yaml"])
                run.end("FAILED", reason)
            except Exception as te:  # noqa: BLE001: the tracking failed too; the job's own error is the one
                _err(_tracking_error(te))
        if getattr(e, "metrics", None):
            from scanreg.runner import repair_table

            table = [ln for prefix, role in (("repair_", "source"), ("target_repair_", "target"))
                     for ln in repair_table(e.metrics, prefix, role)[1:]]
            if multirun:  # a sweep's console gets one line per job; the table stays in the job's folder
                (run_dir / "summary.txt").write_text("\n".join([f"error: {reason}", *table]) + "\n")
            elif table:
                print("\n".join(table))
        _err(reason)
        if multirun:
            report_progress("FAILED", reason)
            return _failed_objective(cfg)
        raise SystemExit(code)

    if run:
        try:
            run.log_metrics(res.metrics, res.step_metrics)
            run.log_artifacts([run_dir / "config.yaml", *res.artifacts])
            run.end("FINISHED")
        except Exception as e:  # noqa: BLE001: a bad store, found by the background thread
            _err(_tracking_error(e))
            if multirun:
                report_progress("FAILED", _tracking_error(e))
                return _failed_objective(cfg)
            raise SystemExit(EXIT_FAILED)
    where = f"results: {run_dir}" + (f"  (MLflow run {run.run_id})" if run else "")
    if multirun:  # one line per job on the console; the full table in the job's folder
        (run_dir / "summary.txt").write_text("\n".join([*summary_lines(res), "", where]) + "\n")
        report_progress("FINISHED", job_line(res.metrics))
    else:
        print("\n".join(summary_lines(res)))
        print(where)
    objective = cfg.get("objective")
    if objective:  # what a tuning sweeper (Optuna) minimises
        if objective not in res.metrics:
            _err(f"objective '{objective}' is not a metric of this run; e.g. rotation_error_deg, rms, time_total_s")
            return float("inf")
        return float(res.metrics[objective])
    return res.to_json()


def _tracking_error(e: BaseException) -> str:
    return (str(e) if isinstance(e, ScanregError) else f"tracking: {type(e).__name__}: {e}").splitlines()[0]


def check_config(cfg: DictConfig) -> None:
    """Every stage's name and parameters, and what a stage needs set (``data.source``): a ConfigError before
    anything runs or is tracked."""
    from scanreg.runner import build_stages

    stages = build_stages(cfg)
    require = getattr(stages["data"], "require", None)
    if callable(require):
        require()


def job_line(m: dict) -> str:
    """A sweep job's result in a few words: its errors (with ground truth), RMS and time."""
    parts = []
    if "rotation_error_deg" in m:
        parts.append(f"rot {m['rotation_error_deg']:.3g}°")
    if "translation_error_rel" in m:
        parts.append(f"transl {100 * m['translation_error_rel']:.2g} %")
    elif "rms" in m:
        parts.append(f"rms {m['rms']:.3g}")
    if "time_total_s" in m:
        parts.append(f"{m['time_total_s']:.1f} s")
    return ", ".join(parts)


def _failed_objective(cfg: DictConfig):
    """A failed job's value for a tuning sweeper: the worst possible, so the sweep goes on."""
    return float("inf") if cfg.get("objective") else None


def _help_groups() -> str:
    """The config groups and their choices, wrapped at 100 columns, for ``scanreg --help``."""
    import textwrap

    lines = []
    for g in sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and any(p.glob("*.yaml"))):
        choices = ", ".join(sorted(q.stem for q in (CONF_DIR / g).glob("*.yaml")))
        lines += textwrap.wrap(f"{g}: {choices}", 100, subsequent_indent="    ")
    return "\n".join(lines)


if not OmegaConf.has_resolver("scanreg_conf_dir"):  # where the configs are, and the groups, for the help text
    OmegaConf.register_new_resolver("scanreg_conf_dir", lambda: str(CONF_DIR))
    OmegaConf.register_new_resolver("scanreg_groups", _help_groups)


def quick_help(overrides: list[str]) -> str | None:
    """``scanreg --help``'s text without Hydra's help machinery, or None to let Hydra write it.

    Hydra formats every config group's options for its ``$APP_CONFIG_GROUPS`` and ``$HYDRA_CONFIG_GROUPS``
    whether or not the template uses them (about 1 s of deep copies for our 17 groups); scanreg's template
    (``hydra.help.template`` in ``conf/config.yaml``) lists the groups itself and uses none of Hydra's
    variables, so substituting nothing gives Hydra's text (``tests/test_cli.py`` compares the two)."""
    import string

    from scanreg.config import compose

    try:
        return string.Template(str(compose(overrides, return_hydra_config=True).hydra.help.template)).substitute({})
    except Exception:  # noqa: BLE001: Hydra's own path reports it, or the template uses Hydra's variables
        return None


@hydra.main(config_path=f"pkg://{CONF_PACKAGE}", config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> dict | None:
    return run_job(cfg)


def group_choices(group: str, config_dirs=()) -> list[str]:
    """The YAML names of a config group in the shipped configs and in extra config folders (``--config-dir``,
    ``hydra.searchpath``: ``file://`` or plain paths, ``pkg://`` packages)."""
    from importlib.resources import files

    roots = [CONF_DIR]
    for d in config_dirs:
        d = str(d)
        if d.startswith("pkg://"):
            try:
                roots.append(Path(str(files(d[len("pkg://"):].replace("/", ".")))))
            except (ModuleNotFoundError, TypeError):
                continue
        else:
            roots.append(Path(d.removeprefix("file://")).expanduser())
    return sorted({p.stem for r in roots for p in (r / group).glob("*.yaml")})


def check_group_overrides(argv: list[str], config_dirs=()) -> str | None:
    """Unknown choices of a stage group (``repair=foo``) as one line, before Hydra prints its longer error."""
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        key, _, value = arg.partition("=")
        key = key.lstrip("+")
        if key not in STAGE_GROUPS + PRESET_GROUPS:
            continue
        valid = group_choices(key, config_dirs)
        for v in value.split(","):
            v = v.strip()
            if v.startswith(("choice(", "range(", "glob(")) or v in ("null", ""):
                break
            if v not in valid:
                return f"unknown {key} '{v}'; valid {key} choices: {', '.join(valid)}"
    return None


_FLAGS_WITH_VALUE = {"-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir", "--info", "-i",
                     "--experimental-rerun"}


def _parse_argv(argv: list[str]) -> tuple[str, list, list[str], bool]:
    """The command line as Hydra reads it: (config name, the parsed overrides, extra config folders from
    ``--config-dir``, whether ``--config-path`` names another primary config folder)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    name, raw, dirs, skip, config_path = "config", [], [], False, False
    for i, a in enumerate(argv):
        if skip:
            skip = False
            continue
        flag, eq, val = a.partition("=")
        config_path |= flag in ("-cp", "--config-path")
        if flag in ("-cd", "--config-dir") and eq:
            dirs.append(val)
            continue
        if a in _FLAGS_WITH_VALUE:
            skip = True
            if a in ("-cn", "--config-name") and i + 1 < len(argv):
                name = argv[i + 1]
            if a in ("-cd", "--config-dir") and i + 1 < len(argv):
                dirs.append(argv[i + 1])
            continue
        if a.startswith("-"):
            continue
        raw.append(a)
    return name, OverridesParser.create().parse_overrides(raw), dirs, config_path


def _task_overrides(argv: list[str]) -> tuple[str, list[str], list[str]]:
    """(config name, the command line's overrides with every sweep reduced to its first value, extra config
    folders from ``--config-dir`` and ``hydra.searchpath``)."""
    name, parsed, dirs, _ = _parse_argv(argv)
    out = []
    for o in parsed:
        if o.key_or_group == "hydra.searchpath":
            v = o.value()
            dirs += [str(x) for x in (v if isinstance(v, list) else [v])]
            continue
        if o.key_or_group.startswith("hydra"):
            continue
        if o.is_sweep_override():
            try:
                first = next(iter(o.sweep_string_iterator()))
            except Exception:  # noqa: BLE001 (glob sweeps etc.): leave it to Hydra
                continue
            out.append(f"{o.get_key_element()}={first}")
        else:
            out.append(o.input_line)
    return name, out, dirs


def precheck(argv: list[str]) -> tuple[str, DictConfig | None] | None:
    """Compose the config as Hydra will and turn a composition error into one line.

    Returns ``(message, config composed without the offending override or None)``, or None when all is well.
    """
    problem, _ = compose_checked(argv)
    return problem


def compose_checked(argv: list[str]) -> tuple[tuple[str, DictConfig | None] | None, DictConfig | None]:
    """:func:`precheck`'s work: ``(problem, config)``, the config as composed when there is no problem."""
    import re

    from hydra.errors import HydraException

    from scanreg.config import compose

    try:
        name, overrides, dirs = _task_overrides(argv)
    except HydraException as e:
        return (f"bad override: {str(e).splitlines()[0]}", None), None
    msg = check_group_overrides(argv, dirs)

    def try_compose(ovs):
        try:
            return compose(ovs, name, dirs, return_hydra_config=True), None
        except Exception as e:  # noqa: BLE001
            return None, e

    if msg:
        bad = [o for o in overrides if o.lstrip("+").split("=")[0] not in STAGE_GROUPS + PRESET_GROUPS]
        return (msg, try_compose(bad)[0]), None
    cfg, err = try_compose(overrides)
    if err is None:
        return None, cfg
    text = " ".join(str(err).split())
    m = re.search(r"Could not override '([^']+)'", text)
    if not m:
        cause = " ".join(str(err.__cause__ or "").split())
        return ((text + (f" ({cause})" if cause else ""))[:500], None), None
    key = m.group(1)
    rest = [o for o in overrides if o.lstrip("+~").split("=")[0] != key]
    good, _ = try_compose(rest)
    group, _, param = key.partition(".")
    if good is not None and group in STAGE_GROUPS and param:
        from scanreg.errors import ConfigError
        from scanreg.registry import REGISTRIES, load_all, make_params

        load_all()
        try:  # the registry's own message for an unknown parameter
            cls = REGISTRIES[group].get(good[group].name)
            make_params(cls.Params, {param.split(".")[0]: None}, f"{group}={good[group].name}")
        except ConfigError as e:
            return (str(e), good), None
    return (f"unknown config key '{key}' (add it with +{key}=VALUE if it is meant to be new)", good), None


def _stdout_gone() -> None:
    """The reader of our output went away (``scanreg --help | head``): nothing to report, and no error from the
    interpreter's own flush at exit."""
    import os

    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def verbose_requested(argv: list[str]) -> bool:
    return any(a.replace(" ", "") in ("verbose=true", "verbose=True") for a in argv)


_UNKNOWN = object()


def _mode_of(argv: list[str], cfg: DictConfig) -> object:
    """``hydra.mode`` as Hydra's ``get_mode`` would find it, read off the config the precheck composed, or
    ``_UNKNOWN`` when the precheck may have composed something else: an override of ``hydra.mode`` or of a
    ``hydra/`` group (the precheck leaves Hydra's own overrides out), a sweep (the precheck takes its first
    value, Hydra's ``get_mode`` none for a config group), another primary config folder (``--config-path``)."""
    try:
        _, parsed, _, config_path = _parse_argv(argv)
    except Exception:  # noqa: BLE001: Hydra reports it
        return _UNKNOWN
    if config_path:
        return _UNKNOWN
    for o in parsed:
        key = o.key_or_group
        if key == "hydra" or key.startswith(("hydra.mode", "hydra/")) or o.is_sweep_override():
            return _UNKNOWN
    try:
        return cfg.hydra.mode
    except Exception:  # noqa: BLE001: no hydra node: let Hydra find it
        return _UNKNOWN


@contextlib.contextmanager
def _hydra_mode_known(mode: object):
    """Hydra 1.3 composes the whole config once only to read ``hydra.mode`` (``Hydra.get_mode``) before it
    composes it again to run; the precheck has composed it already, so that first pass (0.07-0.14 s of every
    run's start-up) answers with what the precheck read. Nothing changes when the mode is ``_UNKNOWN``."""
    if mode is _UNKNOWN:
        yield
        return
    from hydra._internal.hydra import Hydra

    original = Hydra.__dict__.get("get_mode")
    if original is None:  # another Hydra: leave it alone
        yield
        return
    Hydra.get_mode = lambda self, *args, **kwargs: mode
    try:
        yield
    finally:
        Hydra.get_mode = original


def main() -> None:
    from scanreg.cli import NO_RUN_FLAGS

    argv = sys.argv[1:]
    helps = [a for a in argv if a in ("-h", "--help")]
    if helps and all(a in helps or ("=" in a and not a.startswith("-")) for a in argv):
        text = quick_help([a for a in argv if a not in helps])
        if text is not None:
            try:
                print(text, flush=True)
            except BrokenPipeError:
                _stdout_gone()
            return
    if not any(a in NO_RUN_FLAGS for a in argv):
        from scanreg import tracking

        # the ``scanreg`` command (scanreg.cli) started the MLflow helper process of a single run before Hydra
        # was imported; it is stopped at once if the composed config turns out not to track with MLflow
        problem, cfg = compose_checked(argv)
        if problem or cfg.get("tracking", {}).get("name") != "mlflow":
            tracking.drop_prestarted()
        if problem:  # a usage or config error: one line, exit 2, and no MLflow run
            _err(problem[0])
            raise SystemExit(EXIT_USAGE)
        mode = _mode_of(argv, cfg)
    else:
        mode = _UNKNOWN
    import signal

    from scanreg.tracking import _sweep_outcome, end_interrupted_sweep

    def _terminate(signum, frame):  # SIGTERM (a scheduler's preemption, kill) ends runs like Ctrl-C does
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminate)
    try:
        with _hydra_mode_known(mode):
            _hydra_main()
    except KeyboardInterrupt:
        try:
            n = end_interrupted_sweep()
        except Exception:  # noqa: BLE001: the message below is what matters
            n = 0
        _err("interrupted" + (f"; {n} unfinished MLflow run(s) of the sweep marked KILLED" if n else ""))
        raise SystemExit(EXIT_INTERRUPTED)
    except BrokenPipeError:
        _stdout_gone()
        raise SystemExit(0)
    except Exception as e:  # noqa: BLE001: e.g. a launcher that cannot start; no run is left RUNNING
        reason = f"sweep failed: {type(e).__name__}: {e}".splitlines()[0]
        try:
            end_interrupted_sweep(reason, status="FAILED")
        except Exception:  # noqa: BLE001
            pass
        if verbose_requested(sys.argv[1:]):
            traceback.print_exc()
        _err(reason + " (verbose=true for the traceback)")
        raise SystemExit(EXIT_INTERNAL)
    if _sweep_outcome.get("failed"):
        raise SystemExit(EXIT_FAILED)


if __name__ == "__main__":
    from scanreg.cli import main as _cli

    _cli()
