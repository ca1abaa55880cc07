"""One scan-set run: :func:`~scanreg.runner.scanset.register_scanset`, its evaluation and its outputs
(``poses.json``, ``merged.ply``, ``reconstruction.ply`` and its picture, ``view3d.html``, ``result.json``)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from scanreg.errors import StageError, note, warn
from scanreg.eval.metrics import unit_metrics
from scanreg.eval.scanset import scan_residuals, set_metrics, surface_metrics
from scanreg.geometry import Mesh, invert_T, principal_box_diagonal, transform_geometry
from scanreg.io import write_ply
from scanreg.runner.build import Stages
from scanreg.runner.scanset import SetRegistration, register_scanset
from scanreg.types import Result, RunContext, ScanSet

SCAN_COLOURS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                         [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)
"""One colour per scan in ``merged.ply`` and the 3D view (repeating after ten)."""


def run_scanset(problem: ScanSet, stages: Stages, ctx: RunContext, m: dict[str, float], t_start: int) -> Result:
    """Register, evaluate and write a scan set; ``m`` holds the metrics measured so far (loading)."""
    p = stages.multiview
    timings: dict[str, float] = {}
    reg = register_scanset(problem, stages, p, ctx, timings)
    m.update({f"time_{k}_s": v for k, v in timings.items()})
    if len(reg.groups[0]) < 2:  # no two scans placed together: the set was not registered
        if ctx.run_dir is not None:  # poses.json: every pair and why
            write_set_outputs(ctx.run_dir, reg, Result(None, m, {}, ctx.run_dir), {})
        raise StageError(nothing_placed(reg), metrics=m)
    m.update({k: float(v) for k, v in problem.info.items() if isinstance(v, (int, float))})
    t0 = time.perf_counter_ns()
    anchor = reg.groups[0][0]
    # the model's size, the same in any pose of the set (its box along its principal axes)
    diagonal = principal_box_diagonal(reg.merged.points) if reg.merged is not None and reg.merged.n_points else 0.0
    sm, per_scan = set_metrics(reg.poses, reg.edges, anchor, diagonal, problem.poses_gt, p.success_rotation_deg,
                               p.success_translation, p.false_edge_rotation_deg, p.false_edge_translation,
                               [s.cloud.points.mean(axis=0) for s in reg.scans])
    m.update(reg.metrics)
    m.update(sm)
    m.update(unit_metrics(stages.evaluate, diagonal or None))  # what the lengths are in
    links = [(e.i, e.j) for e in reg.edges if e.accepted and reg.poses[e.i] is not None and reg.poses[e.j] is not None]
    coarsest = max([reg.levels[k] for k, T in enumerate(reg.poses) if T is not None] or [reg.spacing])
    rms, share = scan_residuals([s.cloud for s in reg.scans], reg.poses, links, p.inlier_distance * coarsest)
    per_scan.update({"residual_rms": rms.tolist(), "residual_overlap": share.tolist()})
    if np.isfinite(rms).any():
        m["scan_residual_rms_max"] = float(np.nanmax(rms))
    m["groups"] = float(len([g for g in reg.groups if g]))
    if reg.surface is not None:
        reference = None
        if problem.reference is not None and problem.poses_gt is not None and problem.poses_gt[anchor] is not None:
            reference = transform_geometry(invert_T(problem.poses_gt[anchor]), problem.reference)
        elif problem.reference is not None:
            note("data.reference: not measured against: the world scan has no true pose (data.poses) to place it")
        m.update(surface_metrics(reg.surface, reference, seed=ctx.seed))
    m["time_evaluate_s"] = (time.perf_counter_ns() - t0) / 1e9
    m["time_total_s"] = (time.perf_counter_ns() - t_start) / 1e9
    _say_groups(reg)
    if anchor != 0:
        note(f"scan set: the world frame is {reg.names[anchor]}'s (the first scan, {reg.names[0]}, is not in the "
             "model's group)")
    res = Result(None, m, {f"scan_{k}": v for k, v in per_scan.items()}, ctx.run_dir)
    res.children = [(f"{reg.names[e.j]} -> {reg.names[e.i]}", edge_metrics(e)) for e in reg.edges]
    res.scanset = reg
    if ctx.run_dir is not None:
        res.artifacts = write_set_outputs(ctx.run_dir, reg, res, per_scan)
    return res


def nothing_placed(reg: SetRegistration) -> str:
    """Why no pair of the set was verified, in one line: the pairs registered and the reason of the one that
    overlapped most (its verification's limits name the parameters)."""
    tried = [e for e in reg.edges if e.reason]
    best = max(tried, key=lambda e: e.fitness, default=None)
    why = f"; the best, {reg.names[best.j]} -> {reg.names[best.i]}: {best.reason}" if best is not None else ""
    return (f"scan set: no pair of the {len(reg.names)} scans was verified ({len(tried)} registered and rejected"
            f"{why}), so no scan is placed beside another; poses.json lists every pair and why")


def edge_metrics(e) -> dict[str, float]:
    """A pair's numbers, as its child run logs them."""
    return {**e.metrics, "edge_accepted": float(e.accepted), "edge_fitness": e.fitness,
            "edge_inlier_rms_spacings": e.inlier_rms, "edge_normal_agreement": e.normal_agreement}


def _say_groups(reg: SetRegistration) -> None:
    """One line each for scans left out and for groups that share no verified pair."""
    groups = [g for g in reg.groups if len(g) > 1 or g is reg.groups[0]]  # a lone scan is unplaced, not a group
    if len(groups) > 1:
        names = "; ".join("{" + ", ".join(reg.names[k] for k in g) + "}" for g in groups)
        warn(f"the scans fall into {len(groups)} groups that share no verified pair: {names}; the model holds the "
             "first (poses.json gives each group's poses)")
    for name, why in reg.unplaced().items():
        if not any(name in [reg.names[k] for k in g] for g in groups[1:] if len(g) > 1):
            warn(f"scan {name} is not placed: {why}")


def write_set_outputs(run_dir: Path, reg: SetRegistration, res: Result, per_scan: dict) -> list[Path]:
    """``poses.json`` (every placed scan's ``T_world_scan``, the world its first scan's frame; the other groups;
    the unplaced scans and why), ``merged.ply`` (points with normals, the scan index as a scalar, a colour per
    scan), ``reconstruction.ply`` and ``reconstruction.png`` (three sides), ``view3d.html`` and ``result.json``."""
    paths = [run_dir / "poses.json", run_dir / "result.json"]
    anchor = reg.groups[0][0]
    poses = {"world": reg.names[anchor], "poses": {n: T.tolist() for n, T in zip(reg.names, reg.poses) if T is not None},
             "groups": [[reg.names[k] for k in g] for g in reg.groups if g],
             "group_poses": [{reg.names[k]: T.tolist() for k, T in gp.items()} for gp in reg.group_poses],
             "unplaced": reg.unplaced(), "per_scan": {k: dict(zip(reg.names, v)) for k, v in per_scan.items()},
             "edges": [{"target": reg.names[e.i], "source": reg.names[e.j], "accepted": e.accepted,
                        "reason": e.reason, "fitness": e.fitness, "inlier_rms_spacings": e.inlier_rms,
                        "T_target_source": e.T_i_j.tolist()} for e in reg.edges]}
    paths[0].write_text(json.dumps(poses, indent=1, allow_nan=True) + "\n")
    paths[1].write_text(json.dumps({"T_world_scan": poses["poses"], **res.metrics}, indent=2, allow_nan=True) + "\n")
    if reg.merged is not None and reg.merged.n_points:
        scan = reg.merged.extra["scan"]
        paths.append(run_dir / "merged.ply")
        write_ply(paths[-1], reg.merged, colors=SCAN_COLOURS[scan % len(SCAN_COLOURS)],
                  scalars={"scan": scan.astype(np.float32)})
    if isinstance(reg.surface, Mesh):
        from scanreg.eval.picture import write_mesh_picture

        paths.append(run_dir / "reconstruction.ply")
        write_ply(paths[-1], reg.surface)
        placed = sum(T is not None for T in reg.poses)
        paths.append(write_mesh_picture(run_dir / "reconstruction.png", reg.surface,
                                        f"reconstruction of {placed} scans: {len(reg.surface.faces)} faces"))
    if reg.merged is not None and reg.merged.n_points:
        from scanreg.eval.view3d import write_set_view

        paths.append(write_set_view(run_dir / "view3d.html", reg.merged, reg.names, SCAN_COLOURS, seed=0))
    return paths
