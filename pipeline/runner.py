"""The pipeline: load -> repair -> sample -> coarse -> fine -> evaluate, every stage timed.

``run_pipeline`` builds every stage from the composed config first (so a bad name or parameter fails before
any work), then runs them, writes ``result.json``, ``T_target_source.txt`` and ``aligned_source.ply`` into the
run directory, and returns the result. Tracking is the caller's business (``scanreg.app``).
"""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from scanreg.checks import check_inputs
from scanreg.config import Context
from scanreg.errors import InputError, ScanregError
from scanreg.geometry import Cloud, Mesh, apply_T, bbox_diagonal, transform_geometry
from scanreg.io import write_ply, write_transform
from scanreg.metrics import (EvalParams, alignment_metrics, estimate_spacing, field_metrics, gt_metrics,
                             surface_deviation)
from scanreg.registry import COARSE, DATA, ICP, REPAIR, SAMPLER, load_all, make_params, REGISTRIES
from scanreg.closest import ClosestPoints
from scanreg.config import to_abs
from scanreg.uncertainty import (PoseCovariance, bootstrap_spread, degeneracy_warning, pose_covariance,
                                 relative_motion)

MIN_POINTS = 10
"""Fewest points a cloud may have after sampling (the coarse and fine stages need neighbourhoods)."""


@dataclass
class Result:
    metrics: dict[str, float] = field(default_factory=dict)
    T_target_source: np.ndarray | None = None
    step_metrics: dict[str, list[float]] = field(default_factory=dict)
    artifacts: list[Path] = field(default_factory=list)
    stage_lines: list[tuple[str, str]] = field(default_factory=list)

    def to_json(self) -> dict:
        out = {"T_target_source": self.T_target_source.tolist() if self.T_target_source is not None else None}
        out.update(self.metrics)
        return out


class Timer:
    def __init__(self, metrics: dict):
        self.metrics = metrics

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter_ns()
        try:
            yield
        finally:
            self.metrics[f"time_{stage}_s"] = (time.perf_counter_ns() - t0) / 1e9


def build_stages(cfg: DictConfig) -> dict:
    """Instantiate every configured stage (validating names and parameters) without running anything."""
    load_all()
    stages = {
        "data": DATA.build(cfg.data),
        "repair": REPAIR.build(cfg.repair),
        "sampler": SAMPLER.build(cfg.sampler),
        "coarse": COARSE.build(cfg.coarse),
        "icp": ICP.build(cfg.icp),
    }
    # helper families are built when the coarse stage uses them, but validated always
    for fam in ("salience", "descriptor", "matcher"):
        inst = REGISTRIES[fam].build(cfg[fam])
        if fam in getattr(stages["coarse"], "uses", ()):
            stages[fam] = inst
    stages["evaluate"] = make_params(EvalParams, OmegaConf.to_container(cfg.evaluate, resolve=True), "evaluate")
    return stages


def run_pipeline(cfg: DictConfig, run_dir: Path, in_sweep: bool = False) -> Result:
    """Run every stage of ``cfg`` into ``run_dir``; ``in_sweep``: the run is a job of a multirun sweep (the
    caller knows; ``repair.cache: auto`` caches repaired meshes only then)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    res = Result()
    m = res.metrics
    timer = Timer(m)
    t_start = time.perf_counter_ns()
    st = build_stages(cfg)
    ctx = Context(seed=int(cfg.seed), run_dir=run_dir, verbose=bool(cfg.get("verbose", False)))
    ctx.stages = {k: st[k] for k in ("salience", "descriptor", "matcher") if k in st}

    with timer("load"):
        inputs = st["data"].load(ctx)
    check_inputs(inputs, MIN_POINTS)  # too few points, coincident, collinear or planar: before any expensive stage
    m.update({k: float(v) for k, v in (inputs.info or {}).items() if isinstance(v, (int, float))})

    geoms = {"source": inputs.source, "target": inputs.target}
    with timer("repair"):
        if cfg.repair.name != "none":
            apply_to = getattr(st["repair"].p, "apply_to", "both")
            for role, g in geoms.items():
                if isinstance(g, Mesh) and apply_to in (role, "both"):
                    try:
                        geoms[role], rm = st["repair"].repair(g, ctx, "repair_" if role == "source"
                                                              else "target_repair_", sweep=in_sweep)
                    except ScanregError as e:
                        e.metrics = {**m, **e.metrics}
                        raise
                    m.update(rm)

    # a scan closed as a shell by the repair (repair.open_border=shell) is sampled and compared on its scanned side
    geoms = {role: g.scanned() if isinstance(g, Mesh) else g for role, g in geoms.items()}
    clouds: dict[str, Cloud] = {}
    with timer("sample"):
        for role, g in geoms.items():
            clouds[role] = st["sampler"].run(g, ctx) if isinstance(g, Mesh) else st["sampler"].run_cloud(g, ctx)
            if clouds[role].n_points < MIN_POINTS:
                raise InputError(
                    f"{g.source}: {clouds[role].n_points} point(s) after sampling; at least {MIN_POINTS} are needed"
                )
    src, tgt = clouds["source"], clouds["target"]
    target_labels_valid = inputs.target_labels is not None and geoms["target"] is inputs.target
    ctx.target_mesh = geoms["target"] if isinstance(geoms["target"], Mesh) else None
    m["n_source_points"], m["n_target_points"] = src.n_points, tgt.n_points
    m["target_spacing"] = estimate_spacing(tgt.points, ctx.rng(1))
    m["source_spacing"] = estimate_spacing(src.points, ctx.rng(2))
    spacing = max(m["target_spacing"], m["source_spacing"])
    if not spacing > 0:
        raise InputError(f"{src.source} / {tgt.source}: all points coincide; cannot estimate a sampling spacing")
    ctx.spacing, ctx.diagonal = spacing, bbox_diagonal(tgt.points)
    if not ctx.diagonal > 0:
        raise InputError(f"{tgt.source}: degenerate geometry (zero extent)")
    m["spacing"], m["diagonal"] = spacing, ctx.diagonal

    ctx.landmarks = inputs.landmarks
    with timer("coarse"):
        T0, cm = st["coarse"].run(tgt, src, ctx)
    m.update(cm)
    with timer("icp"):
        icp = st["icp"].run(tgt, src, T0, ctx)
    T = icp.T_target_source
    m["icp_iterations"] = icp.iterations
    m["icp_converged"] = float(icp.converged)
    m["icp_rms"] = icp.rms_history[-1]
    m.update(icp.metrics or {})

    with timer("evaluate"):
        ev: EvalParams = st["evaluate"]
        kp_paths: list[Path] = []
        aligned = apply_T(T, src.points)
        on_points = ClosestPoints(tgt)(aligned)
        m.update(alignment_metrics(on_points[1], ev, spacing))
        surface = None if ctx.target_mesh is None else ClosestPoints(tgt, ctx.target_mesh)
        on_surface = on_points if surface is None else surface(aligned)
        m.update(surface_deviation(aligned, on_surface, ev, spacing))
        if inputs.T_gt is not None:
            m.update(gt_metrics(T0, inputs.T_gt, ctx.diagonal, ev, prefix="coarse_"))
            m.update(gt_metrics(T, inputs.T_gt, ctx.diagonal, ev))
            fm, field_masks = field_metrics(ctx.coarse_trace, T0, T, inputs.T_gt, src.points, tgt.points, ev, spacing)
            m.update(fm)
        if ev.write_keypoints and ctx.coarse_trace:
            kp_paths = write_keypoints(run_dir, ctx.coarse_trace, field_masks if inputs.T_gt is not None else None,
                                       inputs.T_gt if inputs.T_gt is not None else T)
        if inputs.landmarks is not None:  # how well the picks agree before and after the fine stage
            lt, ls = inputs.landmarks
            for name, TT in (("coarse", T0), ("final", T)):
                r = np.linalg.norm(apply_T(TT, ls) - lt, axis=1)
                m[f"landmark_{name}_rms"] = float(np.sqrt(np.mean(r ** 2)))
            ctx.step_metrics["landmark_final_residual"] = r.tolist()
        pc = None
        if ev.pose_uncertainty:
            pc = pose_uncertainty(st["icp"], src, T, aligned, on_points, on_surface, surface is not None, spacing, ev, m)
            if pc is not None and inputs.T_gt is not None:  # the true error where pose_sigma_trans is measured
                m["pose_gt_centre_shift"] = relative_motion(T, inputs.T_gt, pc.centre)[1]
            if pc is not None and ev.pose_bootstrap > 0:
                m.update(bootstrap(st["icp"], tgt, src, T0, T, pc.centre, ev.pose_bootstrap, ctx))
        dev_view = None
        if ev.deviation_map:
            from scanreg.deviation import evaluate_deviation

            labels = inputs.target_labels if target_labels_valid else None
            dm, dev_paths, dev_view = evaluate_deviation(run_dir, transform_geometry(T, src),
                                                         transform_geometry(T, geoms["source"]),
                                                         surface or ClosestPoints(tgt), labels, ev, inputs.label_name,
                                                         pose=pc)
            m.update(dm)
        if ev.view_html:
            from scanreg.view3d import write_view

            dev_paths = (dev_paths if ev.deviation_map else []) + [
                write_view(run_dir / "view3d.html", geoms["target"], geoms["source"], T, aligned, on_surface,
                           dev_view, ev, seed=int(cfg.seed))]
    m["time_total_s"] = (time.perf_counter_ns() - t_start) / 1e9

    res.T_target_source = T
    res.step_metrics = dict(ctx.step_metrics)
    res.artifacts = (dev_paths if ev.deviation_map or ev.view_html else []) + kp_paths + write_outputs(run_dir, res, transform_geometry(T, src), tgt if inputs.T_gt is not None and
                                  cfg.data.name != "files" else None)
    return res


def pose_uncertainty(icp, src: Cloud, T: np.ndarray, aligned: np.ndarray, on_points, on_surface, mesh_target: bool,
                     spacing: float, ev: EvalParams, m: dict) -> PoseCovariance | None:
    """The pose covariance at the final pose from the pairs the fine stage keeps there (its distance, normal and
    trim rejections, on the target it searches); logs ``pose_*`` into ``m`` and warns when degenerate. None when
    the target has no normals or too few pairs remain."""
    p = icp.p
    use_mesh = mesh_target and getattr(p, "target", "auto") in ("mesh", "auto")
    q, d, qn = on_surface if use_mesh else on_points
    if qn is None:
        return None
    maxd = to_abs(getattr(p, "max_correspondence_distance", None), getattr(p, "distances", "spacing"), spacing)
    ok = np.isfinite(d) if maxd is None else d <= maxd
    angle = getattr(p, "max_normal_angle_deg", None)
    if angle is not None and src.normals is not None:
        ok &= np.einsum("ij,ij->i", src.normals @ T[:3, :3].T, qn) >= np.cos(np.radians(angle))
    trim = getattr(p, "trim", 1.0)
    if trim < 1.0 and ok.sum() > 3:
        keep = max(3, int(np.ceil(trim * ok.sum())))
        ok &= d <= np.partition(d[ok], keep - 1)[keep - 1]
    if ok.sum() < 7:
        return None
    pc = pose_covariance(aligned[ok], q[ok], qn[ok])
    m.update(pc.metrics())
    msg = degeneracy_warning(pc, ev.pose_condition_warn)
    if msg:
        print(f"warning: {msg}", flush=True)
    return pc


def bootstrap(icp, tgt: Cloud, src: Cloud, T0: np.ndarray, T: np.ndarray, centre: np.ndarray, runs: int,
              ctx: Context) -> dict[str, float]:
    """Re-register ``runs`` sources resampled with replacement (seeded) from the coarse pose with the same fine
    stage; their RMS spread about ``T`` (see :func:`scanreg.uncertainty.bootstrap_spread`)."""
    saved = dict(ctx.step_metrics)
    Ts = []
    for b in range(runs):
        idx = ctx.rng(1000 + b).integers(0, src.n_points, src.n_points)
        Ts.append(icp.run(tgt, src.subset(idx), T0, ctx).T_target_source)
    ctx.step_metrics.clear()
    ctx.step_metrics.update(saved)
    return bootstrap_spread(Ts, T, centre)


def write_outputs(run_dir: Path, res: Result, aligned: Cloud, generated_target: Cloud | None) -> list[Path]:
    paths = [run_dir / "result.json", run_dir / "T_target_source.txt", run_dir / "aligned_source.ply"]
    paths[0].write_text(json.dumps(res.to_json(), indent=2, allow_nan=True) + "\n")
    write_transform(paths[1], res.T_target_source)
    write_ply(paths[2], aligned)
    if generated_target is not None:  # a made-up target (synthetic/stanford) is kept beside the result
        paths.append(run_dir / "target.ply")
        write_ply(paths[-1], generated_target)
    return paths


GOOD, BAD, OUTSIDE = (0, 170, 0), (220, 0, 0), (150, 150, 150)
"""Colours of the keypoint and match PLYs: repeatable / correct, not, outside the overlap (RGB)."""


def write_keypoints(run_dir: Path, trace: dict, masks: dict | None, T_frame: np.ndarray) -> list[Path]:
    """``keypoints_target.ply``, ``keypoints_source.ply`` and ``matches.ply`` from the coarse stage's trace, all
    in the target frame: the source keypoints moved by ``T_frame`` (the true transform when known, else the
    estimate). With ground truth (``masks`` from :func:`scanreg.metrics.field_metrics`) keypoints are green
    when repeatable, red when not, grey outside the overlap (source) or unmatched by any overlap keypoint
    (target), and matches green when correct under the true transform, red when not; without it all grey,
    matches green when RANSAC accepted them. ``matches.ply`` holds each match's target point (vertex 2i) and
    moved source point (2i + 1) joined by a coloured edge, with the scalar ``ransac_inlier`` (0/1)."""
    paths = []
    kt, ks = trace.get("keypoints_target"), trace.get("keypoints_source")
    rep = (masks or {}).get("repeatability")
    if kt is not None and ks is not None:
        ct = np.tile(OUTSIDE, (len(kt), 1))
        cs = np.tile(OUTSIDE, (len(ks), 1))
        if rep is not None:
            ct[rep.target_repeatable] = GOOD
            cs[rep.source_in_overlap] = BAD
            cs[rep.source_repeatable] = GOOD
        for name, pts, col in (("target", kt, ct), ("source", apply_T(T_frame, ks) if len(ks) else ks, cs)):
            paths.append(run_dir / f"keypoints_{name}.ply")
            write_ply(paths[-1], Cloud(np.asarray(pts, float).reshape(-1, 3), None, f"keypoints_{name}"), colors=col)
    P0, P1 = trace.get("matches_target"), trace.get("matches_source")
    if P0 is not None and P1 is not None and len(P0):
        acc = trace.get("ransac_inliers")
        acc = np.zeros(len(P0), bool) if acc is None or len(acc) != len(P0) else np.asarray(acc, bool)
        good = (masks or {}).get("match_inliers", acc)
        col = np.where(good[:, None], GOOD, BAD).astype(np.uint8)
        pts = np.empty((2 * len(P0), 3))
        pts[0::2], pts[1::2] = P0, apply_T(T_frame, P1)
        paths.append(run_dir / "matches.ply")
        write_ply(paths[-1], Cloud(pts, None, "matches"), colors=np.repeat(col, 2, axis=0),
                  scalars={"ransac_inlier": np.repeat(acc.astype(np.float32), 2)},
                  edges=np.arange(2 * len(P0)).reshape(-1, 2), edge_colors=col)
    return paths


def summary_lines(res: Result) -> list[str]:
    m = res.metrics
    rows = [(s, f"{m[f'time_{s}_s']:.3f}") for s in ("load", "repair", "sample", "coarse", "icp", "evaluate", "total")
            if f"time_{s}_s" in m]
    lines = ["stage     time [s]"] + [f"{s:<9} {t:>8}" for s, t in rows]
    keys = ["n_source_points", "n_target_points", "source_spacing", "target_spacing", "spacing", "icp_iterations",
            "icp_rms", "icp_fitness", "icp_inlier_rms", "rms", "fitness", "p2s_mean", "p2s_median", "p2s_rms",
            "p2s_p95_abs", "p2s_max_abs", "coarse_rotation_error_deg", "rotation_error_deg", "translation_error", "translation_error_rel", "success"]
    keys += ["gt_overlap", "coarse_translation_error", "landmark_coarse_rms", "landmark_final_rms"]
    keys += ["pose_sigma_rot_deg", "pose_sigma_trans", "pose_condition", "pose_gt_centre_shift", "pose_bootstrap_rot_deg",
             "pose_bootstrap_trans"]
    keys += [k for k in m if k.startswith("dev_") and "_tooth_" not in k and "_part_" not in k]
    lines.append("")
    lines += [f"{k:<26} {m[k]:.6g}" for k in keys if k in m]
    for prefix, role in (("repair_", "source"), ("target_repair_", "target")):
        lines += repair_table(m, prefix, role)
    return lines


def repair_table(m: dict, prefix: str = "repair_", role: str = "source") -> list[str]:
    """The before/after table of a repair audit (empty when there was none)."""
    rep = [k[len(prefix + "before_"):] for k in m if k.startswith(prefix + "before_")]
    if not rep:
        return []
    lines = ["", f"{'repair (' + role + ')':<32} {'before':>12} {'after':>12}"]
    lines += [f"{k:<32} {m[prefix + 'before_' + k]:>12.6g} {m.get(prefix + 'after_' + k, float('nan')):>12.6g}"
              for k in rep]
    extra = ["hausdorff_max", "hausdorff_max_rel", "hausdorff_mean_rel", "hausdorff_added_max_rel",
             "removed_area_share", "guard_ok"]
    lines += [f"{k:<32} {m[prefix + k]:>25.6g}" for k in extra if prefix + k in m]
    return lines
