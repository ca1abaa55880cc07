"""Benchmark: point clouds without normals (raw scanner points), with and without the orientation of the
estimated normals, beside Open3D's standard pipeline, in one run.

    .venv/bin/python experiments/benchmarks/unoriented_clouds.py              # ~6-8 min on the 2-core box
    .venv/bin/python experiments/benchmarks/unoriented_clouds.py --pairs 10   # the first 10 bunny pairs only

A cloud without normals (an ``.xyz`` file, an RGB-D fragment) reaches the coarse stage with normals it
estimates, whose signs the estimation leaves arbitrary; FPFH reads them as given, so two scans whose normals lie on
opposite sides of the surface in the regions they share do not match. ``descriptor.orient_normals`` (default on)
gives them consistent signs on the outer side of the surface first (:func:`scanreg.geometry.orient_normals`).

Cases (every one with ground truth, the source under a seeded random pose of any angle):
- bunny_xyz: the 40 ordered pairs of the raw Stanford range scans with ground-truth overlap >= 40 %
  (``end_to_end.PAIRS``), each scan's vertices that a face uses written as an ``.xyz`` file (no normals), truth
  from ``bun.conf``; pair k under pose seed k: ``scanreg data.source=A.xyz data.target=B.xyz data.gt=T.txt
  data.max_angle_deg=180 data.max_translation=0.1 data.pose_seed=k``;
- 3dmatch: the shared 3DMatch fragment pair (``.npy`` points, no normals), 6 poses (``data=pairs_3dmatch``).

Methods, on the same loaded inputs, interleaved per case (the order turns every case):
- scanreg: the default pipeline (``tracking=none``);
- scanreg unoriented: the same with ``descriptor.orient_normals=false`` (the signs as estimated, the pipeline
  before the orientation);
- open3d: Open3D's standard pipeline (``end_to_end.o3d_standard``: voxel 1 % of the diagonal, FPFH, RANSAC,
  point-to-plane ICP), whose normals are unoriented too;
- histogram3p, histogram3p unoriented: the default pipeline with the paper's descriptor
  (``descriptor=histogram3p``), with and without the orientation.

Success: rotation < 2 deg and translation < 1 % of the diagonal (3DMatch: 15 deg and 0.3 m). Times: the coarse
stage (Open3D: its FPFH and RANSAC), in seconds, median [inter-quartile range]. Written to
``unoriented_clouds.md`` beside this file.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from end_to_end import PAIRS, load_inputs, med_iqr, o3d_standard, tolerances  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BUNNY = ROOT.parent / "shared" / "data" / "stanford_bunny"
TDM = ROOT.parent / "shared" / "data" / "3dmatch_pair"
METHODS = ("scanreg", "scanreg unoriented", "open3d", "histogram3p", "histogram3p unoriented")
EXTRA = {"scanreg": [], "scanreg unoriented": ["descriptor.orient_normals=false"],
         "histogram3p": ["descriptor=histogram3p"],
         "histogram3p unoriented": ["descriptor=histogram3p", "descriptor.orient_normals=false"]}


def write_clouds(folder: Path) -> None:
    """Each bunny scan's used vertices as ``NAME.xyz`` and each pair's truth as ``A_B.txt``."""
    from scanreg.io import read_geometry
    from scanreg.io.readers import read_stanford_conf

    poses = read_stanford_conf(BUNNY / "bun.conf")
    for name in {n for p in PAIRS for n in p.split(":")}:
        m = read_geometry(BUNNY / f"{name}.ply")
        np.savetxt(folder / f"{name}.xyz", m.vertices[np.unique(m.faces)], fmt="%.9g")
    for p in PAIRS:
        s, t = p.split(":")
        np.savetxt(folder / f"{s}_{t}.txt", np.linalg.inv(poses[f"{t}.ply"]) @ poses[f"{s}.ply"])


def overrides(case: dict, folder: Path) -> list[str]:
    if case["group"] == "3dmatch":
        return ["data=pairs_3dmatch", f"data.pose_seed={case['seed']}", "tracking=none"]
    s, t = case["pair"].split(":")
    return [f"data.source={folder / (s + '.xyz')}", f"data.target={folder / (t + '.xyz')}",
            f"data.gt={folder / f'{s}_{t}.txt'}", "data.max_angle_deg=180", "data.max_translation=0.1",
            f"data.pose_seed={case['seed']}", "tracking=none"]


def run_method(method: str, case: dict, folder: Path) -> dict:
    from omegaconf import OmegaConf

    import scanreg
    from scanreg.geometry import bbox_diagonal, points_of, transform_errors
    from scanreg.runner import run_pipeline
    from scanreg.types import RunContext

    cfg = scanreg.compose(overrides(case, folder) + EXTRA.get(method, []))
    OmegaConf.resolve(cfg)
    with tempfile.TemporaryDirectory() as d:
        inputs = load_inputs(cfg, RunContext(seed=0, run_dir=Path(d)))
        if method == "open3d":
            tgt, src = points_of(inputs.target), points_of(inputs.source)
            diagonal, times = bbox_diagonal(tgt), {}
            T = o3d_standard(src, tgt, diagonal, times)
            coarse = times["time_coarse_s"]
        else:
            res = run_pipeline(cfg, Path(d))
            T, diagonal, coarse = res.T_target_source, res.metrics["diagonal"], res.metrics["time_coarse_s"]
    rot, trans = transform_errors(T, inputs.T_gt)
    lim_r, lim_t = tolerances({"group": "3dmatch" if case["group"] == "3dmatch" else "bunny"}, diagonal)
    return {"rot": rot, "trans": trans, "coarse": coarse, "success": bool(rot < lim_r and trans < lim_t)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=len(PAIRS), help="the first N bunny pairs (default: all 40)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("unoriented_clouds.md")))
    a = ap.parse_args()
    if not BUNNY.is_dir() or not TDM.is_dir():
        sys.exit(f"skipped: the shared data ({BUNNY}, {TDM}) is not there")
    import open3d  # noqa: F401  (imported before any timing)

    t_start = time.perf_counter()
    cases = [{"group": "bunny_xyz", "pair": p, "seed": k} for k, p in enumerate(PAIRS[:a.pairs])]
    cases += [{"group": "3dmatch", "seed": s} for s in range(6)]
    rows = []
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        write_clouds(folder)
        for i, case in enumerate(cases):
            k = i % len(METHODS)
            for method in METHODS[k:] + METHODS[:k]:
                r = run_method(method, case, folder)
                rows.append({**case, "method": method, **r})
                print(f"{i + 1:>3}/{len(cases)} {case.get('pair', case['group']):<16} seed {case['seed']} "
                      f"{method:<19} {'ok  ' if r['success'] else 'FAIL'} rot {r['rot']:8.3f} "
                      f"coarse {r['coarse']:5.2f} s", flush=True)
    wall = time.perf_counter() - t_start
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                           text=True, cwd=ROOT).stdout.strip()
    commit += " with changes in the working tree" if dirty else ""
    lines = ["# Point clouds without normals: oriented estimated normals (`descriptor.orient_normals`)", "",
             f"`experiments/benchmarks/unoriented_clouds.py` (cases and methods: its module doc), commit {commit}, "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, 2 cores, wall time "
             f"{wall:.0f} s.", "",
             "| case | method | success | rotation error [deg] | coarse [s] |", "|---|---|---|---|---|"]
    for group in ("bunny_xyz", "3dmatch"):
        for method in METHODS:
            sel = [r for r in rows if r["group"] == group and r["method"] == method]
            if sel:
                lines.append(f"| {group} | {method} | {sum(r['success'] for r in sel)}/{len(sel)} | "
                             f"{med_iqr([r['rot'] for r in sel], '{:.3f}')} | "
                             f"{med_iqr([r['coarse'] for r in sel])} |")
    lines += ["", "Cases where scanreg, scanreg unoriented and open3d disagree (rotation error in degrees):", "",
              "| case | seed | " + " | ".join(METHODS) + " |", "|---|---|" + "---|" * len(METHODS)]
    for case in cases:
        sel = {r["method"]: r for r in rows if r["group"] == case["group"] and r.get("pair") == case.get("pair")
               and r["seed"] == case["seed"]}
        if len({sel[m]["success"] for m in METHODS[:3]}) > 1:
            lines.append(f"| {case.get('pair', case['group'])} | {case['seed']} | "
                         + " | ".join(f"{sel[m]['rot']:.2f}" + ("" if sel[m]["success"] else " (fail)")
                                      for m in METHODS) + " |")
    Path(a.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
