"""What a run writes and prints: ``result.json``, the transform, the aligned source, the keypoints and matches
the coarse stage compared, and the summary table."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scanreg.eval.metrics import input_unit_name
from scanreg.geometry import Cloud, apply_T
from scanreg.io import write_ply, write_transform
from scanreg.types import CoarseTrace, Result


def write_outputs(run_dir: Path, res: Result, aligned: Cloud, generated_target: Cloud | None) -> list[Path]:
    """``result.json``, ``T_target_source.txt``, ``aligned_source.ply`` (and ``target.ply`` for a target the
    data provider made)."""
    paths = [run_dir / "result.json", run_dir / "T_target_source.txt", run_dir / "aligned_source.ply"]
    paths[0].write_text(json.dumps(res.to_json(), indent=2, allow_nan=True) + "\n")
    write_transform(paths[1], res.T_target_source)
    write_ply(paths[2], aligned)
    if generated_target is not None:
        paths.append(run_dir / "target.ply")
        write_ply(paths[-1], generated_target)
    return paths


GOOD, BAD, OUTSIDE = (0, 170, 0), (220, 0, 0), (150, 150, 150)
"""Colours of the keypoint and match PLYs: repeatable / correct, not, outside the overlap (RGB)."""


def write_keypoints(run_dir: Path, trace: CoarseTrace, masks: dict | None, T_frame: np.ndarray) -> list[Path]:
    """``keypoints_target.ply``, ``keypoints_source.ply`` and ``matches.ply`` from the coarse stage's trace, all
    in the target frame: the source keypoints moved by ``T_frame`` (the true transform when known, else the
    estimate). With ground truth (``masks`` from :func:`scanreg.eval.metrics.field_metrics`) keypoints are green
    when repeatable, red when not, grey outside the overlap (source) or unmatched by any overlap keypoint
    (target), and matches green when correct under the true transform, red when not; without it all grey,
    matches green when RANSAC accepted them. ``matches.ply`` holds each match's target point (vertex 2i) and
    moved source point (2i + 1) joined by a coloured edge, with the scalar ``ransac_inlier`` (0/1)."""
    paths = []
    kt, ks = trace.keypoints_target, trace.keypoints_source
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
    P0, P1 = trace.matches_target, trace.matches_source
    if P0 is not None and P1 is not None and len(P0):
        acc = trace.ransac_inliers
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
    """The table a run prints: its stage times and its main numbers (a scan set's: per scan)."""
    if res.scanset is not None:
        return set_summary_lines(res)
    m = res.metrics
    rows = [(s, f"{m[f'time_{s}_s']:.3f}") for s in ("load", "repair", "sample", "coarse", "icp", "evaluate", "total")
            if f"time_{s}_s" in m]
    lines = ["stage     time [s]"] + [f"{s:<9} {t:>8}" for s, t in rows]
    keys = ["n_source_points", "n_target_points", "source_spacing", "target_spacing", "spacing", "icp_iterations",
            "icp_rms", "icp_fitness", "icp_inlier_rms", "rms", "fitness", "p2s_mean", "p2s_median", "p2s_rms",
            "p2s_p95_abs", "p2s_max_abs", "coarse_rotation_error_deg", "rotation_error_deg", "translation_error", "translation_error_rel", "success",
            "registration_recall"]
    keys += ["gt_overlap", "coarse_translation_error", "landmark_coarse_rms", "landmark_final_rms"]
    keys += ["pose_sigma_rot_deg", "pose_sigma_trans", "pose_condition", "pose_gt_centre_shift", "pose_bootstrap_rot_deg",
             "pose_bootstrap_trans"]
    keys += [k for k in m if k.startswith("dev_") and "_tooth_" not in k and "_part_" not in k]
    lines += ["", *unit_line(m, "the target's size")]
    for k in keys:
        if k in m:
            lines.append(f"{k:<26} {_shown(m[k])}")
        if k == "p2s_rms" and k in m and m.get("rms", 0) > 2 * m[k]:
            lines.append("  (rms: to the closest target points, so it holds their spacing; p2s_*: to the target's "
                         "surface)")
        if k == "registration_recall" and m.get("success") == 0 and m.get(k) == 1:
            lines.append("  (success: the strict test, evaluate.success_rotation_deg and success_translation; "
                         "registration_recall: 3DMatch's looser one, evaluate.recall_*)")
    for prefix, role in (("repair_", "source"), ("target_repair_", "target")):
        lines += repair_table(m, prefix, role)
    return lines


def _shown(v: float, digits: int = 6) -> str:
    """A number as the summary prints it: ``digits`` significant digits, whole numbers of a million and more in
    full (a point count of 3 007 275, not 3.00728e+06), ``-`` for a number not measured (NaN)."""
    v = float(v)
    if v != v:
        return "-"
    return f"{int(v)}" if v.is_integer() and 1e6 <= abs(v) < 1e15 else f"{v:.{digits}g}"


def repair_table(m: dict, prefix: str = "repair_", role: str = "source") -> list[str]:
    """The before/after table of a repair audit (empty when there was none)."""
    rep = [k[len(prefix + "before_"):] for k in m if k.startswith(prefix + "before_")]
    if not rep:
        return []
    lines = ["", f"{'repair (' + role + ')':<32} {'before':>12} {'after':>12}"]
    lines += [f"{k:<32} {_shown(m[prefix + 'before_' + k]):>12} "
              f"{_shown(m.get(prefix + 'after_' + k, float('nan'))):>12}" for k in rep]
    extra = ["hausdorff_max", "hausdorff_max_rel", "hausdorff_mean_rel", "hausdorff_added_max_rel",
             "removed_area_share", "guard_ok"]
    lines += [f"{k:<32} {m[prefix + k]:>25.6g}" for k in extra if prefix + k in m]
    return lines


SET_STEPS = ("load", "prepare", "pairs", "graph", "refine", "surface", "evaluate", "total")
SET_KEYS = ("scans", "scans_placed", "edges_registered", "edges_skipped", "edges_predicted", "edges_retried", "edges_accepted", "edges_false", "graph_edges_pruned",
            "spacing", "model_diagonal", "multiview_rms", "scan_rotation_error_max_deg", "scan_translation_error_max_rel",
            "scans_within_tolerance", "success", "surface_faces", "surface_closed_manifold",
            "surface_self_intersecting_faces", "surface_reference_rms")


def unit_line(m: dict[str, float], guessed_from: str) -> list[str]:
    """The line that says what unit the lengths of a run's table are in (none when the run did not say):
    ``input_unit_m``, and whether it was guessed (from ``guessed_from``)."""
    unit = input_unit_name(m.get("input_unit_m"))
    if not unit:
        return []
    how = f"guessed from {guessed_from}; set evaluate.units" if m.get("input_unit_guessed") else "evaluate.units"
    return [f"lengths in {unit}, the input's unit ({how})"]


def set_summary_lines(res: Result) -> list[str]:
    """A scan set's table: step times, the set's numbers, and one row per scan (its errors with ground truth, its
    residual to the scans it overlaps)."""
    m, reg = res.metrics, res.scanset
    lines = ["step      time [s]"] + [f"{s:<9} {m[f'time_{s}_s']:>8.3f}" for s in SET_STEPS if f"time_{s}_s" in m]
    lines += ["", *unit_line(m, "the model's size")] + [f"{k:<32} {_shown(m[k])}" for k in SET_KEYS if k in m]
    cols = [c for c in ("rotation_error_deg", "translation_error_rel", "residual_rms", "residual_overlap")
            if f"scan_{c}" in res.histories]
    width = max(text_columns(n) for n in [*reg.names, "scan"])
    lines += ["", padded("scan", width) + "  placed  " + "  ".join(f"{c:>22}" for c in cols)]
    for k, name in enumerate(reg.names):
        vals = "  ".join(f"{_shown(res.histories[f'scan_{c}'][k], 4):>22}" for c in cols)
        lines.append(f"{padded(name, width)}  {'yes' if reg.poses[k] is not None else 'no':>6}  {vals}")
    return lines


def text_columns(text: str) -> int:
    """How many columns ``text`` takes in a terminal: East Asian wide and full-width characters (a file named
    in Chinese or Japanese) take two, combining marks none."""
    import unicodedata

    return sum(0 if unicodedata.combining(c) else 2 if unicodedata.east_asian_width(c) in "WF" else 1 for c in text)


def padded(text: str, width: int, right: bool = False) -> str:
    """``text`` padded with spaces to ``width`` terminal columns (:func:`text_columns`), on the right (left-aligned
    text) or, with ``right``, on the left."""
    pad = " " * max(0, width - text_columns(text))
    return pad + text if right else text + pad


def clipped(text: str, width: int) -> str:
    """``text`` cut to at most ``width`` terminal columns, its last one an ellipsis when cut."""
    from itertools import accumulate

    if text_columns(text) <= width:
        return text
    # the first character that would leave no column for the ellipsis
    cut = next(k for k, used in enumerate(accumulate(map(text_columns, text))) if used > width - 1)
    return text[:cut] + "…"
