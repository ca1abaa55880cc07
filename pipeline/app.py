"""``scanreg``: the Hydra application that runs the pipeline and tracks it."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from pipeline.config import PROJECT_ROOT
from pipeline.errors import ScanregError

CONF_DIR = PROJECT_ROOT / "conf"
STAGE_GROUPS = ("data", "repair", "sampler", "salience", "descriptor", "matcher", "coarse", "icp", "tracking")


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr, flush=True)


def run_job(cfg: DictConfig) -> dict | None:
    from pipeline.registry import TRACKING, load_all
    from pipeline.runner import run_pipeline, summary_lines
    from pipeline.tracking import flatten

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
        choices = {f"group.{g}": str(hc.runtime.choices.get(g)) for g in STAGE_GROUPS if g in hc.runtime.choices}
        overrides = " ".join(hc.overrides.task)
        run = tracker.start_run(
            run_name=(overrides or "defaults")[:250],
            params=flatten(resolved),
            tags={**choices, "scanreg.run_dir": str(run_dir), "scanreg.overrides": overrides},
        )
    except ScanregError as e:
        _err(str(e))
        if multirun:
            return None
        raise SystemExit(1)

    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(resolved))
    try:
        if resolve_error:
            raise ScanregError(resolve_error)
        res = run_pipeline(cfg, run_dir)
    except KeyboardInterrupt:
        if run:
            run.end("KILLED", "interrupted")
        raise
    except BaseException as e:  # noqa: BLE001: every failure ends the run FAILED with its reason
        if isinstance(e, ScanregError):
            reason = str(e)
        elif isinstance(e, SystemExit):
            reason = f"exit {e.code}"
        else:
            reason = f"internal error: {type(e).__name__}: {e}".splitlines()[0]
            if verbose:
                traceback.print_exc()
            else:
                reason += " (run with verbose=true for the traceback)"
        if run:
            run.log_artifacts([run_dir / "config.yaml"])
            run.end("FAILED", reason)
        _err(reason)
        if multirun:
            return None
        raise SystemExit(1)

    if run:
        run.log_metrics(res.metrics, res.step_metrics)
        run.log_artifacts([run_dir / "config.yaml", *res.artifacts])
        run.end("FINISHED")
    print("\n".join(summary_lines(res)))
    print(f"results: {run_dir}" + (f"  (MLflow run {run.run_id})" if run else ""))
    return res.to_json()


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> dict | None:
    return run_job(cfg)


def check_group_overrides(argv: list[str]) -> str | None:
    """Unknown choices of a stage group (``repair=foo``) as one line, before Hydra prints its longer error."""
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        key, _, value = arg.partition("=")
        key = key.lstrip("+")
        if key not in STAGE_GROUPS and key != "experiment":
            continue
        valid = sorted(p.stem for p in (CONF_DIR / key).glob("*.yaml"))
        for v in value.split(","):
            v = v.strip()
            if v.startswith(("choice(", "range(", "glob(")) or v in ("null", ""):
                break
            if v not in valid:
                return f"unknown {key} '{v}'; valid {key} choices: {', '.join(valid)}"
    return None


def main() -> None:
    msg = check_group_overrides(sys.argv[1:])
    if msg:
        _err(msg)
        raise SystemExit(2)
    from pipeline.tracking import _sweep_outcome

    _hydra_main()
    if _sweep_outcome.get("failed"):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
