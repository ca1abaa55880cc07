"""One registration run from its config: build the stages, then load -> prepare both scans -> register ->
evaluate, every step timed, and the outputs written into the run folder. Tracking is the caller's business
(``scanreg.app``); the steps are :mod:`scanreg.runner.steps`."""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig

from scanreg.errors import ScanregError
from scanreg.geometry import transform_geometry
from scanreg.runner.build import Stages, build_stages
from scanreg.runner.outputs import write_outputs
from scanreg.runner.steps import evaluate_pair, load_problem, prepare_scan, register_pair, repair_scans
from scanreg.types import PreparedScan, Result, RunContext, ScanSet

REPAIR_PREFIX = {"source": "repair_", "target": "target_repair_"}
"""Prefix of each scan's repair audit in a run's metrics."""


def run_pipeline(cfg: DictConfig, run_dir: Path, in_sweep: bool = False) -> Result:
    """Run every stage of ``cfg`` into ``run_dir`` and return the :class:`~scanreg.types.Result`; ``in_sweep``:
    the run is a job of a multirun sweep (``repair.cache: auto`` caches repaired meshes only then)."""
    t_start = time.perf_counter_ns()
    run_dir.mkdir(parents=True, exist_ok=True)
    stages = build_stages(cfg)
    ctx = RunContext(seed=int(cfg.seed), run_dir=run_dir, verbose=bool(cfg.get("verbose", False)), in_sweep=in_sweep)
    return run_stages(stages, ctx, t_start)


def run_stages(stages: Stages, ctx: RunContext, t_start: int | None = None) -> Result:
    """:func:`run_pipeline` with the stages built: the steps, their timings (``time_<step>_s``) and the outputs."""
    t_start = time.perf_counter_ns() if t_start is None else t_start
    m: dict[str, float] = {}
    t0 = time.perf_counter_ns()
    problem = load_problem(stages, ctx)
    m["time_load_s"] = (time.perf_counter_ns() - t0) / 1e9
    if isinstance(problem, ScanSet):  # many scans of one object
        from scanreg.runner.scanset_run import run_scanset

        return run_scanset(problem, stages, ctx, m, t_start)
    m.update({k: float(v) for k, v in problem.info.items() if isinstance(v, (int, float))})
    scans: dict[str, PreparedScan] = {}
    t0 = time.perf_counter_ns()
    geometries = {"source": problem.source, "target": problem.target}
    try:
        repaired = repair_scans(geometries, stages, ctx)
    except ScanregError as e:  # the metrics measured so far go with the failed run
        done = {REPAIR_PREFIX[r] + k: v for r, rep in getattr(e, "repaired", {}).items()
                for k, v in rep.metrics.items()}
        role = getattr(e, "role", None) or "source"
        e.metrics = {**m, **done, **{REPAIR_PREFIX[role] + k: v for k, v in e.metrics.items()}}
        raise
    m["time_repair_s"] = (time.perf_counter_ns() - t0) / 1e9  # both scans, at once
    for role, salt in (("source", 2), ("target", 1)):
        try:
            scans[role] = scan = prepare_scan(geometries[role], stages, ctx, role, salt, repair=False,
                                              repaired=repaired.get(role))  # (repaired above, or not at all)
        except ScanregError as e:
            e.metrics = {**m, **e.metrics}
            raise
        m.update({REPAIR_PREFIX[role] + k: v for k, v in scan.repair.items()})
    source, target = scans["source"], scans["target"]
    m["time_sample_s"] = source.timings["sample"] + target.timings["sample"]
    m["n_source_points"], m["n_target_points"] = source.cloud.n_points, target.cloud.n_points
    m["target_spacing"], m["source_spacing"] = target.spacing, source.spacing
    pair = register_pair(target, source, stages, ctx, problem.landmarks)
    m["spacing"], m["diagonal"] = pair.spacing, pair.diagonal
    m["time_coarse_s"], m["time_icp_s"] = pair.timings["coarse"], pair.timings["icp"]
    m.update(pair.metrics)
    t0 = time.perf_counter_ns()
    ev = evaluate_pair(problem, target, source, pair, stages, ctx)
    m.update(ev.metrics)
    m["time_evaluate_s"] = (time.perf_counter_ns() - t0) / 1e9
    m["time_total_s"] = (time.perf_counter_ns() - t_start) / 1e9
    res = Result(pair.T_target_source, m, {**pair.histories, **ev.histories}, ctx.run_dir)
    generated = target.cloud if problem.T_gt is not None and problem.target_generated else None
    res.artifacts = ev.artifacts + write_outputs(ctx.run_dir, res, transform_geometry(pair.T_target_source,
                                                                                        source.cloud), generated)
    return res
