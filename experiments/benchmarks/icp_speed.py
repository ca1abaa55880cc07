"""Benchmark: ICP variants against Open3D, side by side, measured in one run.

    ./run python experiments/benchmarks/icp_speed.py [--sizes 10000,100000,1000000]

Case: pymeshfix's bunny sampled twice independently (N points each, normals from the triangles); the source
moved by 10 degrees about a random axis through its centre plus 2 % of the diagonal. Every measurement runs in a
fresh subprocess, ``--repeat`` rounds, each round running every method once in turn (interleaved with the
anchor, Open3D, so that a slow spell of the machine hits all of them); the tables give the median over the rounds
with the min-max range. Per iteration: in one subprocess, 1 iteration then 30 with the same pair limit, after a
warm-up; per iteration = (t30 - t1) / 29, and its ratio to Open3D point-to-point is taken within each round.
Both on all cores (Open3D's OpenMP, pykdtree's OpenMP). "To convergence" runs each method with its own stopping
rule and its defaults (its Params dataclass, which conf/icp/<name>.yaml takes its defaults from since #32;
point_to_plane: coarse-to-fine from a quarter of the points).
Peak memory is the subprocess's maximum resident set size minus that of a process that only loaded the data
(first round).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

MAXD = 10.0  # pair limit in sampling spacings (10 degrees moves the far side by ~10 spacings at 100k points)


def make_case(n: int):
    from scipy.spatial.transform import Rotation

    from scanreg.geometry import Cloud, apply_T, barycentric_sample, estimate_spacing, make_T
    from scanreg.io import read_mesh

    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    a, an, _ = barycentric_sample(m, n, np.random.default_rng(1))
    b, bn, _ = barycentric_sample(m, n, np.random.default_rng(2))
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(10)).as_matrix()
    c = b.mean(0)
    diag = np.linalg.norm(np.ptp(m.vertices, axis=0))
    d = rng.normal(size=3)
    P = make_T(R, c - R @ c + 0.02 * diag * d / np.linalg.norm(d))  # source moved by P; truth is inv(P)
    src = Cloud(apply_T(P, b), bn @ R.T)
    tgt = Cloud(a, an)
    T_gt = np.linalg.inv(P)
    spacing = estimate_spacing(a, np.random.default_rng(0))
    return tgt, src, T_gt, spacing


def run_case(method: str, n: int, iters: int | None, case=None) -> dict:
    """One measurement in this process. iters=None: to convergence."""
    from scanreg.geometry import transform_errors
    from scanreg.types import RunContext

    import open3d  # noqa: F401  (imports and registries outside the measured region, for every method)

    from scanreg.stages.registry import load_all

    load_all()
    tgt, src, T_gt, spacing = case or make_case(n)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter_ns()
    if method.startswith("open3d"):
        import open3d as o3d

        reg = o3d.pipelines.registration
        ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.points))
        pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt.points))
        pt.normals = o3d.utility.Vector3dVector(tgt.normals)
        est = reg.TransformationEstimationPointToPlane() if method == "open3d_point_to_plane" \
            else reg.TransformationEstimationPointToPoint()
        crit = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=iters) if iters \
            else reg.ICPConvergenceCriteria(max_iteration=100)
        r = reg.registration_icp(ps, pt, MAXD * spacing, np.eye(4), est, crit)
        T, its = np.asarray(r.transformation), None
    else:
        from scanreg.stages.registry import ICP, make_params

        cls = ICP.get(method)
        # each variant with its defaults (its Params dataclass: the same as conf/icp's since #32), one pair limit
        # every point (max_points=0): the loop at N points against Open3D's (the default works on at most 200k)
        kw = {"max_correspondence_distance": MAXD, "max_points": 0}
        if iters:
            kw.update(tau=0.0, max_iterations=iters)
        res = cls(make_params(cls.Params, kw, method)).refine(tgt, src, np.eye(4), spacing, RunContext(seed=0))
        T, its = res.T_target_source, res.iterations
    secs = (time.perf_counter_ns() - t0) / 1e9
    rot, trans = transform_errors(T, T_gt)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"time_s": secs, "rotation_error_deg": rot, "translation_error": trans, "iterations": its,
            "peak_extra_mb": max(rss - rss0, 0) / 1024}


def per_iteration_case(method: str, n: int) -> dict:
    """In this process: a warm-up, then 1 iteration and 30 iterations; per iteration = (t30 - t1) / 29."""
    case = make_case(n)
    run_case(method, n, 1, case)  # warm-up: first-call costs (allocations, thread pools) outside the timing
    t1 = run_case(method, n, 1, case)["time_s"]
    t30 = run_case(method, n, 30, case)["time_s"]
    return {"per_iteration_s": (t30 - t1) / 29, "t1_s": t1, "t30_s": t30}


def measure(method: str, n: int, iters: int | None, per_iteration: bool = False) -> dict:
    mode = "per" if per_iteration else str(iters or 0)
    out = subprocess.run([sys.executable, __file__, "--child", method, str(n), mode],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
    if out.returncode:
        raise SystemExit(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def spread(values: list[float], fmt: str, scale: float = 1.0) -> str:
    """``median (min-max)`` of ``values`` times ``scale``."""
    v = np.asarray(values, float) * scale
    return f"{np.median(v):{fmt}} ({v.min():{fmt}}-{v.max():{fmt}})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--repeat", type=int, default=5, help="rounds of every measurement (default 5)")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(Path(__file__).with_suffix(".md")))
    a = ap.parse_args()
    if a.child:
        method, n, mode = a.child
        print(json.dumps(per_iteration_case(method, int(n)) if mode == "per"
                         else run_case(method, int(n), int(mode) or None)))
        return
    if a.repeat < 1:
        raise SystemExit("error: --repeat must be >= 1")
    R = a.repeat
    lines = [f"Threads: {os.cpu_count()} cores, Open3D OpenMP and pykdtree OpenMP on all of them. Pair limit "
             f"{MAXD:g} spacings for every method. {R} rounds, each running every method once in turn; median "
             "(min-max) over the rounds.", ""]
    lines += ["Per iteration ((30 iterations - 1) / 29, in one process after a warm-up)", "",
              "| points | method | per iteration [ms] | ratio to Open3D point-to-point |", "|---|---|---|---|"]
    conv = ["", "To convergence (each method's own stopping rule)", "",
            "| points | method | total [s] | iterations | rotation error [deg] | translation error | peak extra memory [MB] |",
            "|---|---|---|---|---|---|---|"]
    anchor, per_methods = "open3d_point_to_point", ("open3d_point_to_point", "horn")
    conv_methods = ("open3d_point_to_plane", "open3d_point_to_point", "horn", "anderson", "point_to_plane", "gicp")
    for n in [int(x) for x in a.sizes.split(",")]:
        per: dict[str, list[float]] = {m: [] for m in per_methods}
        runs: dict[str, list[dict]] = {m: [] for m in conv_methods}
        for _ in range(R):  # interleaved: every method once per round
            for m in per_methods:
                per[m].append(measure(m, n, None, per_iteration=True)["per_iteration_s"])
            for m in conv_methods:
                runs[m].append(measure(m, n, None))
        for m in per_methods:
            ratio = [x / y for x, y in zip(per[m], per[anchor])]
            lines.append(f"| {n:,} | {m} | {spread(per[m], '.2f', 1e3)} | {spread(ratio, '.2f')} |")
        for m in conv_methods:
            r = runs[m][0]
            its = "-" if r["iterations"] is None else r["iterations"]
            conv.append(f"| {n:,} | {m} | {spread([x['time_s'] for x in runs[m]], '.3f')} | {its} | "
                        f"{r['rotation_error_deg']:.4f} | {r['translation_error']:.4f} | {r['peak_extra_mb']:.0f} |")
        print("\n".join(lines + conv), flush=True)
    text = "\n".join(lines + conv)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    Path(a.out).write_text(f"# ICP benchmark\n\nProduced by `python experiments/benchmarks/icp_speed.py "
                           f"--sizes {a.sizes} --repeat {R}` at commit {commit or '?'} on a 2-core machine "
                           f"(shared with other work: hence the ranges).\n\n{text}\n")


if __name__ == "__main__":
    main()
