"""Before/after benchmark of the coarse stage's thinning: success and coarse time of the default pipeline with and
without a change, interleaved case by case, in one process and one run.

    .venv/bin/python experiments/robustness_outliers/thinning_benchmark.py                 # every group (~15 min)
    .venv/bin/python experiments/robustness_outliers/thinning_benchmark.py --groups clean,3dmatch

Variants (scanreg overrides on top of the defaults; ``--variants`` JSON replaces them):
- before: ``coarse.isolated_ratio=null``, the thinned coarse stage as it was (every point voxel-thinned);
- after: the defaults (isolated points dropped before thinning);
- every point: ``coarse.voxel=null`` (no thinning; only in the ``outliers`` and ``low_overlap`` groups, the
  reference whose robustness thinning should keep).

Groups (each case with ground truth, the source under pose seed 0 unless said):
- clean: the 40 ordered Stanford bunny pairs with >= 40 % overlap of ``experiment=first_contact`` (raw scans,
  ``repair=none`` as in the end-to-end benchmark), pose seed 0;
- 3dmatch: the real 3DMatch fragment pair, pose seeds 0-5 (success: 15 deg and 5 % of the diagonal, as
  ``conf/data/pairs_3dmatch.yaml`` suggests);
- outliers: ``experiment=robustness_outliers``'s cases (3 pairs, ISS / uniform / cn_l3, no fallback, min_inliers
  3, 10 000 points) at 30, 40 and 50 % outliers;
- low_overlap: ``experiment=bunny_benchmark``'s pairs with 10-20 % overlap (gt_overlap), 10 000 points.

Each case runs its variants back to back, the order alternating from case to case, so that a slow spell of the
shared machine hits both. Times are the pipeline's ``time_coarse_s`` (the coarse stage alone). Writes a
Markdown table (success k/n with Wilson 95 %, median and total coarse time) and a CSV of every run.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

CLEAN = ("bun000:bun045,bun045:bun000,bun000:bun315,bun315:bun000,bun045:bun090,bun090:bun045,bun090:bun180,"
         "bun180:bun090,bun180:bun270,bun270:bun180,bun270:bun315,bun315:bun270,top2:bun180,bun180:top2,top3:bun045,"
         "bun045:top3,bun000:top3,top3:bun000,top2:ear_back,ear_back:top2,bun180:ear_back,ear_back:bun180,"
         "bun090:ear_back,ear_back:bun090,bun315:bun045,bun045:bun315,chin:bun315,bun315:chin,top3:bun090,"
         "bun090:top3,chin:bun000,bun000:chin,top2:top3,top3:top2,bun315:top3,top3:bun315,top2:bun090,"
         "bun090:top2,bun270:chin,chin:bun270")
LOW = ("bun180:top3,ear_back:top3,bun045:top2,top3:ear_back,chin:bun090,bun045:bun270,top2:bun045,bun315:bun090,"
       "bun270:bun045,top3:bun180,bun090:chin,bun270:top3,top3:bun270,bun090:bun315,bun045:ear_back,chin:top3,"
       "bun180:bun315")
VARIANTS = {"before": ["coarse.isolated_ratio=null"], "after": [], "every point": ["coarse.voxel=null"]}


def cases(groups: list[str]) -> list[tuple[str, list[str], bool]]:
    """(group, overrides, with the every-point reference)."""
    out = []
    if "clean" in groups:
        out += [("clean", ["data=stanford", "repair=none", f"data.pair={p}", "data.pose_seed=0"], False)
                for p in CLEAN.split(",")]
    if "3dmatch" in groups:
        out += [("3dmatch", ["data=pairs_3dmatch", f"data.pose_seed={s}", "evaluate.success_rotation_deg=15",
                             "evaluate.success_translation=0.05"], False)
                for s in range(6)]
    if "outliers" in groups:
        out += [(f"outliers {o:.0%} {s}", ["data=stanford", "repair=none", f"data.pair={p}", f"salience={s}",
                                          f"data.add_outliers={o}", "data.cloud_points=10000", "sampler.n_points=10000",
                                          "coarse.fallback_voxel=null", "coarse.min_inliers=3"], True)
                for o in (0.3, 0.4, 0.5) for s in ("iss", "uniform", "cn_l3")
                for p in ("bun000:bun045", "top2:bun180", "top3:bun045")]
    if "low_overlap" in groups:
        out += [("low_overlap", ["data=stanford", "repair=none", f"data.pair={p}", "data.pose_seed=0",
                                 "sampler.n_points=10000"], True) for p in LOW.split(",")]
    return out


def run(overrides: list[str]) -> dict:
    from omegaconf import OmegaConf

    from scanreg.app.config import compose
    from scanreg.errors import ScanregError
    from scanreg.runner import run_pipeline

    cfg = compose([*overrides, "tracking=none"])
    OmegaConf.resolve(cfg)
    t0 = time.perf_counter_ns()
    try:
        m = dict(run_pipeline(cfg, Path(tempfile.mkdtemp(prefix="thinbench-"))).metrics)
    except ScanregError as e:
        m = {"success": 0.0, "error": str(e).splitlines()[0][:120]}
    m["wall_s"] = (time.perf_counter_ns() - t0) / 1e9
    return m


def wilson(k: int, n: int) -> str:
    if n == 0:
        return "-"
    z, p = 1.96, k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * ((p * (1 - p) / n + z * z / (4 * n * n)) ** 0.5) / d
    return f"{k}/{n} = {100 * p:.0f} % [{100 * max(0, c - h):.0f}, {100 * min(1, c + h):.0f}]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--groups", default="clean,3dmatch,outliers,low_overlap")
    ap.add_argument("--variants", default=None, help="JSON {name: [overrides]} replacing before/after/every point")
    ap.add_argument("--out", default=str(HERE / "thinning_benchmark"))
    a = ap.parse_args()
    warnings.filterwarnings("ignore")
    variants = json.loads(a.variants) if a.variants else VARIANTS
    import subprocess  # the commit the runs measure, read before they start

    git = ["git", "-C", str(ROOT)]
    commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run([*git, "status", "--porcelain", "--", ".", ":!experiments"], capture_output=True,
                           text=True).stdout.strip()
    commit += "+dirty" if dirty else ""
    rows, t_start = [], time.time()
    for i, (group, ovs, with_full) in enumerate(cases(a.groups.split(","))):
        names = [v for v in variants if with_full or v != "every point"]
        if i % 2:
            names = names[::-1]
        for name in names:
            m = run([*ovs, *variants[name]])
            row = {"group": group, "case": " ".join(ovs), "variant": name, "success": m.get("success", 0.0),
                   "time_coarse_s": m.get("time_coarse_s"), "rotation_error_deg": m.get("rotation_error_deg"),
                   "coarse_rotation_error_deg": m.get("coarse_rotation_error_deg"),
                   "gt_overlap": m.get("gt_overlap"), "coarse_points_source": m.get("coarse_points_source"),
                   "coarse_isolated_source": m.get("coarse_isolated_source"),
                   "coarse_isolated_target": m.get("coarse_isolated_target"),
                   "coarse_spacing": m.get("coarse_spacing"), "coarse_inliers": m.get("coarse_inliers"),
                   "coarse_inlier_ratio": m.get("coarse_inlier_ratio"), "coarse_fallback": m.get("coarse_fallback"),
                   "error": m.get("error", "")}
            rows.append(row)
            print(json.dumps(row), flush=True)
    minutes = (time.time() - t_start) / 60
    out = Path(a.out)
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    groups = list(dict.fromkeys(r["group"] for r in rows))
    names = list(variants)
    lines = [f"# Coarse-stage thinning: before/after ({sys.argv[0]} --groups {a.groups})", "",
             f"{len(rows)} runs, {minutes:.1f} min, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
             f"commit {commit}; "
             f"variants: " + "; ".join(f"{k}: `{' '.join(v) or 'the defaults'}`" for k, v in variants.items())
             + ". Cells: successes/runs = rate [Wilson 95 %]; coarse time: median [total] in s of `time_coarse_s`, "
             "the variants of a case run back to back (interleaved). How it is measured: this script's docstring.",
             "", "| group | " + " | ".join(f"{n} success | {n} coarse s" for n in names) + " |",
             "|---|" + "---|---|" * len(names)]
    for g in groups:
        cells = []
        for n in names:
            rr = [r for r in rows if r["group"] == g and r["variant"] == n]
            if not rr:
                cells += ["-", "-"]
                continue
            k = sum(int(r["success"] or 0) for r in rr)
            ts = [r["time_coarse_s"] for r in rr if r["time_coarse_s"] is not None]
            cells += [wilson(k, len(rr)),
                      f"{statistics.median(ts):.3f} [{sum(ts):.1f}]" if ts else "-"]
        lines.append(f"| {g} | " + " | ".join(cells) + " |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
