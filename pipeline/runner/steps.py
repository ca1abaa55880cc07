"""The steps of a registration, each a call that takes values and returns a value:

- :func:`load_problem`: the data provider's problem, checked before any expensive work;
- :func:`prepare_scan`: one scan repaired, sampled and measured (:class:`~scanreg.types.PreparedScan`);
- :func:`register_pair`: coarse then fine registration of two prepared scans (:class:`~scanreg.types.PairResult`);
- :func:`evaluate_pair`: every number the run reports about a registered pair (:class:`Evaluation`).

``scanreg.runner.pipeline.run_pipeline`` chains them for one pair; many scans of one object reuse
:func:`prepare_scan` for every scan and :func:`register_pair` for every pair.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np

from scanreg.errors import InputError, ScanregError, note, one_line, warn
from scanreg.eval.checks import check_geometry, check_inputs
from scanreg.eval.metrics import (EvalParams, alignment_metrics, field_metrics, gt_metrics, inverted_gt_warning,
                                  low_fitness_warning, sparse_pair_warning, surface_deviation, unit_metrics)
from scanreg.eval.uncertainty import (PoseCovariance, bootstrap_spread, degeneracy_warning, pairs_covariance,
                                      relative_motion)
from scanreg.geometry import (ClosestPoints, Geometry, Mesh, apply_T, bbox_centre, bbox_diagonal, estimate_spacing,
                              principal_box_diagonal, transform_geometry)
from scanreg.process import blas_single_thread, cores, start_isolated
from scanreg.runner.build import Stages
from scanreg.runner.outputs import write_keypoints
from scanreg.types import (CoarseResult, Correspondences, IcpResult, PairResult, PreparedScan, Problem, Repaired,
                           RunContext, ScanSet, to_abs)

MIN_POINTS = 10
"""Fewest points a cloud may have after sampling (the coarse and fine stages need neighbourhoods)."""
GT_SAMPLE_SALT = 8100
"""Salt of the run's generator (:meth:`~scanreg.types.RunContext.rng`) that draws the source points the
ground-truth metrics are measured on (``evaluate.max_points``)."""


def _seconds_since(t0: int) -> float:
    return (time.perf_counter_ns() - t0) / 1e9


def load_problem(stages: Stages, ctx: RunContext) -> Problem | ScanSet:
    """The data provider's problem (a pair, or a scan set); too few points, coincident, collinear or planar
    inputs stop here."""
    problem = stages.data.load(ctx)
    sampleable = getattr(stages.sampler, "check", None)  # (the Sampler protocol asks only for sample)
    named = list(zip(problem.scans, problem.names)) if isinstance(problem, ScanSet) else \
        [(g, g.source or role) for role, g in (("source", problem.source), ("target", problem.target))]
    if isinstance(problem, ScanSet):
        for g, name in named:
            check_geometry(g, name, MIN_POINTS)
    else:
        check_inputs(problem, MIN_POINTS)
    if sampleable is not None:  # a mesh the sampler could take no point of, before the repair
        for g, name in named:
            sampleable(g, name)
    return problem


def repairs_needed(geometries: dict[str, Geometry], stages: Stages) -> list[str]:
    """The roles (keys of ``geometries``) whose scan the repair works on: meshes, when it applies to the role."""
    return [role for role, g in geometries.items() if isinstance(g, Mesh) and stages.repair.applies_to(role)]


def repair_scans(geometries: dict[str, Geometry], stages: Stages, ctx: RunContext) -> dict[str, Repaired]:
    """The repair of every scan in ``geometries`` (by role) that it applies to (:func:`repairs_needed`), the
    scans at once: each but the first in a process of its own (:func:`scanreg.process.start_isolated`) while
    this one repairs the first, so that two scans take one repair's time on two cores. The same results as
    one after the other (each repair is a function of its scan, the seed and its parameters). When one fails,
    the others still finish; the first failure is raised, with ``role`` (whose) and ``repaired`` (the repairs
    that finished)."""
    roles = repairs_needed(geometries, stages)
    if len(roles) > 1:  # the cores shared among the scans (a repair then forks no test beside itself on 2 cores)
        ctx = replace(ctx, cores=max(1, (ctx.cores or cores()) // len(roles)))
    started = {role: start_isolated(_repaired_alone, stages.repair, geometries[role], ctx) for role in roles[1:]}
    out, failed = {}, None
    try:
        for role in roles:
            try:
                out[role] = started[role].result() if role in started else stages.repair.repair(geometries[role],
                                                                                                 ctx)
            except ScanregError as e:  # the others finish (one cut short would leave its cache entry locked)
                e.role = role  # whose repair failed, for the metrics that go with the failed run
                failed = failed or e
    except BaseException:  # a crash or an interrupt: the others are ended (a no-op for those already taken)
        for pending in started.values():
            pending.cancel()
        raise
    if failed is not None:
        failed.repaired = out  # the repairs that finished, whose audits go with the failed run too
        raise failed
    return out


def _repaired_alone(repair, mesh: Mesh, ctx: RunContext) -> Repaired:
    """``repair.repair(mesh, ctx)`` with its mesh's arrays only (the measurements remembered on it stay here)."""
    r = repair.repair(mesh, ctx)
    m = r.mesh
    return Repaired(Mesh(m.vertices, m.faces, m.source, m.closure_faces), r.metrics)


def prepare_scan(geometry: Geometry, stages: Stages, ctx: RunContext, name: str, salt: int,
                 role: str | None = None, repair: bool = True, repaired: Repaired | None = None) -> PreparedScan:
    """One scan ready to register: a mesh repaired (``repair``, and when the repair applies to its ``role``:
    ``source``, ``target``, or ``scan`` for a scan of a set; ``name`` by default; or ``repaired``, its repair
    made already, :func:`repair_scans`) and then its scanned side sampled; a cloud sampled (thinned) as the
    sampler says; the sampling spacing estimated with ``ctx.rng(salt)``."""
    t0 = time.perf_counter_ns()
    surface, audit = geometry, {}
    if repaired is None and repair and isinstance(geometry, Mesh) and stages.repair.applies_to(role or name):
        repaired = stages.repair.repair(geometry, ctx)
    if repaired is not None:
        surface, audit = repaired.mesh, repaired.metrics
    # a scan closed as a shell by the repair (repair.open_border=shell) is sampled and compared on its scanned side
    surface = surface.scanned() if isinstance(surface, Mesh) else surface
    t1 = time.perf_counter_ns()
    cloud = stages.sampler.sample(surface, ctx)
    if cloud.n_points < MIN_POINTS:
        raise InputError(f"{surface.source}: {cloud.n_points} point(s) after sampling; at least {MIN_POINTS} are needed")
    timings = {"repair": (t1 - t0) / 1e9, "sample": _seconds_since(t1)}
    return PreparedScan(name, geometry, surface, cloud, estimate_spacing(cloud.points, ctx.rng(salt)), audit, timings)


def register_pair(target: PreparedScan, source: PreparedScan, stages: Stages, ctx: RunContext,
                  landmarks: Optional[tuple[np.ndarray, np.ndarray]] = None) -> PairResult:
    """``source`` registered to ``target``: the coarse stage from any pose, then the fine stage from its result,
    at the pair's spacing (the larger of the two scans')."""
    spacing = max(target.spacing, source.spacing)
    if not spacing > 0:
        raise InputError(f"{source.cloud.source} / {target.cloud.source}: all points coincide; cannot estimate a "
                         "sampling spacing")
    diagonal = bbox_diagonal(target.cloud.points)
    if not diagonal > 0:
        raise InputError(f"{target.cloud.source}: degenerate geometry (zero extent)")
    t0 = time.perf_counter_ns()
    coarse = stages.coarse.align(target.cloud, source.cloud, spacing, ctx, landmarks)
    t1 = time.perf_counter_ns()
    icp = stages.icp.refine(target.cloud, source.cloud, coarse.T_target_source, spacing, ctx, target.mesh,
                            coarse.estimated)
    timings = {"coarse": (t1 - t0) / 1e9, "icp": _seconds_since(t1)}
    coarse, icp = second_look(target, source, stages, ctx, spacing, coarse, icp, timings)
    return PairResult(coarse, icp, spacing, diagonal, timings)


def second_look(target: PreparedScan, source: PreparedScan, stages: Stages, ctx: RunContext, spacing: float,
                coarse: CoarseResult, icp: IcpResult, timings: dict[str, float]) -> tuple[CoarseResult, IcpResult]:
    """The coarse stage's second estimate of the pair, when it has a ``second_look`` (optional in the
    :class:`~scanreg.stages.protocols.CoarseStage` protocol) and makes one for the pose ``icp`` refined (e.g. a
    pose that keeps little of the source on the target), refined by the fine stage too; of the two, the results
    whose refined pose keeps the larger share of the source (``icp_fitness``; ties, or a second refinement that
    fails: the first). The share, not the acceptance test's truncated cost, because at these overlaps it
    separated right from wrong poses more clearly (``experiments/benchmarks/low_overlap.md``). The kept coarse
    result's metrics say whether a second look was made (``coarse_second_look``) and kept
    (``coarse_second_look_kept``), and the share each look's refined pose keeps (``coarse_first_look_fitness``,
    ``coarse_second_look_fitness``; NaN when the second refinement failed); a look made prints one note line;
    its time goes to ``timings``."""
    look = getattr(stages.coarse, "second_look", None)
    fitness = icp.metrics.get("icp_fitness")
    if look is None or fitness is None:
        return coarse, icp
    t0 = time.perf_counter_ns()
    again = look(target.cloud, source.cloud, spacing, ctx, coarse, fitness)
    timings["coarse"] += _seconds_since(t0)
    if again is None:
        coarse.metrics["coarse_second_look"] = 0.0
        return coarse, icp
    t1 = time.perf_counter_ns()
    try:
        icp_again = stages.icp.refine(target.cloud, source.cloud, again.T_target_source, spacing, ctx,
                                      target.mesh, again.estimated)
        second = icp_again.metrics.get("icp_fitness", float("nan"))
        outcome = f"that pose keeps {second:.1%}"
    except ScanregError as e:  # (e.g. too few pairs from the second estimate: the first stands)
        icp_again, second, outcome = None, float("nan"), f"its refinement failed ({one_line(e)})"
    timings["icp"] += _seconds_since(t1)
    kept = second > fitness
    note(f"second look: the refined pose keeps {fitness:.1%} of the source on the target, so the coarse stage "
         f"registered the pair again with wider matching; {outcome}: {'kept' if kept else 'the first pose kept'}")
    if kept:
        coarse, icp = again, icp_again
    coarse.metrics.update({"coarse_second_look": 1.0, "coarse_second_look_kept": float(kept),
                           "coarse_first_look_fitness": fitness, "coarse_second_look_fitness": second})
    return coarse, icp


@dataclass
class Evaluation:
    """What :func:`evaluate_pair` measured."""

    metrics: dict[str, float] = field(default_factory=dict)
    histories: dict[str, list[float]] = field(default_factory=dict)
    artifacts: list[Path] = field(default_factory=list)
    """Files written: keypoints and matches, deviation maps, the 3D view."""


def evaluate_pair(problem: Problem, target: PreparedScan, source: PreparedScan, pair: PairResult, stages: Stages,
                  ctx: RunContext) -> Evaluation:
    """Every number the run reports about a registered pair: the fit (``rms``, ``fitness``), the distances to
    the target's surface, with ground truth the errors and the field's metrics, the landmarks' residuals, the
    pose covariance; and, into ``ctx.run_dir``, the keypoints and matches, the deviation map and the 3D view as
    ``evaluate`` asks."""
    size = principal_box_diagonal(target.cloud.points)  # the target's size in any pose, for the unit's guess
    ev: EvalParams = stages.evaluate.shown(size)  # (the deviations' display unit follows the input's)
    T, T0, T_gt = pair.T_target_source, pair.coarse.T_target_source, problem.T_gt
    src, tgt, spacing = source.cloud, target.cloud, pair.spacing
    out = Evaluation()
    m = out.metrics
    m.update(unit_metrics(stages.evaluate, size))  # (what every length below is in: set, or guessed)
    with blas_single_thread():
        aligned = apply_T(T, src.points)
    on_target = ClosestPoints(tgt)  # the target points' search, for the fit and the field's overlap tests
    on_points = on_target(aligned)
    m.update(alignment_metrics(on_points[1], ev, spacing))
    for line in (sparse_pair_warning(source.spacing, target.spacing, src.n_points, tgt.n_points,
                                     ev.spacing_ratio_warn, principal_box_diagonal(src.points), size),
                 low_fitness_warning(m["fitness"], ev.fitness_warn)):
        if line:
            warn(line)
    surface = None if target.mesh is None else ClosestPoints(tgt, target.mesh)
    on_surface = on_points if surface is None else surface(aligned)
    m.update(surface_deviation(aligned, on_surface, ev, spacing))
    masks = None
    if T_gt is not None:
        at = bbox_centre(src.points)  # the translation error where the source is, not at its frame's origin
        m.update(gt_metrics(T0, T_gt, pair.diagonal, ev, prefix="coarse_", at=at))
        m.update(gt_metrics(T, T_gt, pair.diagonal, ev, at=at))
        line = inverted_gt_warning(T, T_gt, m, pair.diagonal, ev, at)
        if line:
            warn(line)
        gt_points = src.thinned(ev.max_points, ctx.rng(GT_SAMPLE_SALT)).points  # (every point up to max_points)
        with blas_single_thread():  # its products of (N, 3) arrays by 3 x 3: rows apart, no gain from threads
            fm, masks = field_metrics(pair.coarse.trace, T0, T, T_gt, gt_points, tgt.points, ev, spacing, on_target)
        m.update(fm)
    write = ctx.run_dir is not None
    keypoint_files, view_files = [], []
    if write and ev.write_keypoints and pair.coarse.trace is not None:
        keypoint_files = write_keypoints(ctx.run_dir, pair.coarse.trace, masks, T_gt if T_gt is not None else T)
    if problem.landmarks is not None:  # how well the picks agree before and after the fine stage
        lt, ls = problem.landmarks
        for name, TT in (("coarse", T0), ("final", T)):
            r = np.linalg.norm(apply_T(TT, ls) - lt, axis=1)
            m[f"landmark_{name}_rms"] = float(np.sqrt(np.mean(r ** 2)))
        out.histories["landmark_final_residual"] = r.tolist()
    pc = None
    if ev.pose_uncertainty:
        pc = pose_from_pairs(pair.icp.final_pairs, ev)
        if pc is not None:
            m.update(pc.metrics())
            if T_gt is not None:  # the true error where pose_sigma_trans is measured
                m["pose_gt_centre_shift"] = relative_motion(T, T_gt, pc.centre)[1]
            if ev.pose_bootstrap > 0:
                m.update(bootstrap(stages, target, source, pair, pc.centre, ev.pose_bootstrap, ctx))
    dev_view = None
    if write and ev.deviation_map:
        from scanreg.eval.deviation import evaluate_deviation

        labels = problem.target_labels if target.surface is problem.target else None
        dm, paths, dev_view = evaluate_deviation(ctx.run_dir, transform_geometry(T, src),
                                                 transform_geometry(T, source.surface), surface or ClosestPoints(tgt),
                                                 labels, ev, problem.label_name, pose=pc)
        m.update(dm)
        view_files += paths
    if write and ev.view_html:
        from scanreg.eval.view3d import write_view

        view_files.append(write_view(ctx.run_dir / "view3d.html", target.surface, source.surface, T, aligned,
                                     on_surface, dev_view, ev, seed=ctx.seed,
                                     units_note=units_note(stages.evaluate, size),
                                     max_distance=to_abs(ev.inlier_distance, ev.distances, spacing)))
    out.artifacts = view_files + keypoint_files
    return out


def units_note(ev: EvalParams, diagonal: float) -> str:
    """How the input unit was found, for the 3D view's title: guessed from the target's size, or set."""
    if ev.units != "auto":
        return "evaluate.units"
    return f"guessed from the target's size, {diagonal:.3g} across; set evaluate.units if wrong"


def pose_from_pairs(pairs: Correspondences | None, ev: EvalParams) -> PoseCovariance | None:
    """The pose covariance at the final pose from the pairs the fine stage kept there (None when the target has
    no normals or fewer than 7 pairs remain); prints one warning line when the pose is poorly constrained."""
    pc = pairs_covariance(pairs)
    if pc is None:
        return None
    msg = degeneracy_warning(pc, ev.pose_condition_warn)
    if msg:
        warn(msg)
    return pc


def bootstrap(stages: Stages, target: PreparedScan, source: PreparedScan, pair: PairResult, centre: np.ndarray,
              runs: int, ctx: RunContext) -> dict[str, float]:
    """Re-register ``runs`` sources resampled with replacement (seeded) from the coarse pose with the same fine
    stage; their RMS spread about the final pose (see :func:`scanreg.eval.uncertainty.bootstrap_spread`)."""
    src, T0 = source.cloud, pair.coarse.T_target_source
    Ts = []
    for b in range(runs):
        idx = ctx.rng(1000 + b).integers(0, src.n_points, src.n_points)
        Ts.append(stages.icp.refine(target.cloud, src.subset(idx), T0, pair.spacing, ctx, target.mesh,
                                    pair.coarse.estimated).T_target_source)
    return bootstrap_spread(Ts, pair.T_target_source, centre)
