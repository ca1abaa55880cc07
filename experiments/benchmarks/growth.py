"""Benchmark (issue #37, item 6): how time and memory grow with the points, scanreg beside Open3D's standard
pipeline, interleaved, in one run.

    ./run python experiments/benchmarks/growth.py                  # 30k, 100k, 300k, 1M points (~6 min)
    ./run python experiments/benchmarks/growth.py --sizes 30000,3000000

Case (issue #37): two independent barycentric samplings of pymeshlab's ``bunny.obj`` with N points each; the
source sees 80 % of the surface (the points with x below the 80th percentile of a sampling of N / 0.8) and is
moved by 60 deg about (0.3, 1, 0.2) and (0.05, -0.02, 0.03); both are given as ``.npy`` clouds, as a user with
clouds would give them. Each (size, method) runs in a fresh subprocess, the two methods alternating which goes
first:

- scanreg: ``scanreg.register(source.npy, target.npy, gt=...)`` with no overrides (tracking off): its
  ``time_*_s`` metrics, evaluation and output files included, as ``scanreg SOURCE TARGET`` runs it;
- open3d: the standard pipeline of ``end_to_end.py`` (voxel 1 % of the diagonal, FPFH, RANSAC, point-to-plane
  ICP on the full clouds), on the same arrays.

Peak memory: the subprocess's own peak resident set size (Linux's VmHWM) at the end, the arrays included.
Writes ``growth.md`` (the table) and ``growth.png`` (time against points, log-log) beside this file.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def make_case(n: int, folder: Path) -> tuple[Path, Path, np.ndarray]:
    """The two clouds of ``n`` points as .npy files and the true T_target_source (see the module doc)."""
    from scipy.spatial.transform import Rotation

    from scanreg.geometry import apply_T, barycentric_sample, make_T
    from scanreg.io import read_mesh

    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    tgt = barycentric_sample(m, n, np.random.default_rng(1))[0]
    b = barycentric_sample(m, int(n / 0.8), np.random.default_rng(2))[0]
    src_seen = b[b[:, 0] < np.quantile(b[:, 0], 0.8)][:n]
    axis = np.array([0.3, 1.0, 0.2])
    T = make_T(Rotation.from_rotvec(np.radians(60.0) * axis / np.linalg.norm(axis)).as_matrix(),
               np.array([0.05, -0.02, 0.03]))
    paths = folder / f"source_{n}.npy", folder / f"target_{n}.npy"
    np.save(paths[0], apply_T(np.linalg.inv(T), src_seen))
    np.save(paths[1], tgt)
    return paths[0], paths[1], T


def worker(method: str, source: str, target: str, gt: str) -> dict:
    import open3d  # noqa: F401  (imported before any timing, for both methods)

    from scanreg.geometry import bbox_diagonal, transform_errors

    T_gt = np.loadtxt(gt)
    if method == "scanreg":
        import scanreg

        t0 = time.perf_counter()
        r = scanreg.register(source, target, gt=T_gt)
        wall = time.perf_counter() - t0
        m = r.metrics
        out = {k: m[k] for k in ("time_coarse_s", "time_icp_s", "time_evaluate_s", "time_total_s")}
        T = r.T_target_source
    else:
        sys.path.insert(0, str(HERE))
        from end_to_end import o3d_standard

        src, tgt = np.load(source), np.load(target)
        out = {}
        t0 = time.perf_counter()
        T = o3d_standard(src, tgt, bbox_diagonal(tgt), out)
        wall = time.perf_counter() - t0
        out["time_total_s"] = wall
        out["time_evaluate_s"] = 0.0
    out["wall_s"] = wall
    out["rotation_error_deg"] = transform_errors(T, T_gt)[0]
    out["peak_mb"] = peak_mb()
    return out


def peak_mb() -> float:
    """This process's peak resident memory in MB: Linux's VmHWM (``ru_maxrss`` would include the memory of the
    process that forked it, this benchmark's driver with the clouds it made)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) for ln in f if ln.startswith("VmHWM:")) / 1024.0
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def spawn(method: str, case: tuple[Path, Path, Path]) -> dict:
    p = subprocess.run([sys.executable, __file__, "--worker", method, *map(str, case)], capture_output=True,
                       text=True, timeout=1800)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode or not lines:
        return {"error": (p.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(lines[-1])


def table(rows: dict) -> list[str]:
    out = ["| points per cloud | scanreg total [s] | coarse | ICP | evaluate | peak [MB] | rotation error [deg] | "
           "Open3D total [s] | Open3D coarse | Open3D ICP | Open3D peak [MB] | Open3D rotation error [deg] | "
           "time ratio |", "|---" * 13 + "|"]
    for n, r in rows.items():
        s, o = r["scanreg"], r["open3d"]
        if "error" in s or "error" in o:
            out.append(f"| {n:,} | {s.get('error', '')} | | | | | | {o.get('error', '')} | | | | | |")
            continue
        out.append(f"| {n:,} | {s['time_total_s']:.2f} | {s['time_coarse_s']:.2f} | {s['time_icp_s']:.2f} | "
                   f"{s['time_evaluate_s']:.2f} | {s['peak_mb']:.0f} | {s['rotation_error_deg']:.4f} | "
                   f"{o['time_total_s']:.2f} | {o['time_coarse_s']:.2f} | {o['time_icp_s']:.2f} | {o['peak_mb']:.0f} | "
                   f"{o['rotation_error_deg']:.4f} | {s['time_total_s'] / o['time_total_s']:.2f} |")
    return out


def plot(rows: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ns = [n for n, r in rows.items() if "error" not in r["scanreg"] and "error" not in r["open3d"]]
    for method, key, style in (("scanreg", "time_total_s", "o-"), ("scanreg coarse", "time_coarse_s", "o--"),
                               ("scanreg ICP", "time_icp_s", "o:"), ("open3d", "time_total_s", "s-"),
                               ("open3d coarse", "time_coarse_s", "s--"), ("open3d ICP", "time_icp_s", "s:")):
        who = method.split()[0]
        ax.loglog(ns, [rows[n][who][key] for n in ns], style, label=method)
    ax.set_xlabel("points per cloud")
    ax.set_ylabel("time [s]")
    ax.set_title("Time against points (bunny, 80 % overlap, 60 deg)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="30000,100000,300000,1000000")
    ap.add_argument("--out", default=str(HERE / "growth.md"))
    ap.add_argument("--worker", nargs=4, metavar=("METHOD", "SOURCE", "TARGET", "GT"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        print(json.dumps(worker(*a.worker)))
        return
    t0 = time.perf_counter()
    rows: dict = {}
    with tempfile.TemporaryDirectory(prefix="growth-") as d:
        for i, n in enumerate(int(x) for x in a.sizes.split(",")):
            src, tgt, T = make_case(n, Path(d))
            gt = Path(d) / f"gt_{n}.txt"
            np.savetxt(gt, T)
            order = ("scanreg", "open3d") if i % 2 == 0 else ("open3d", "scanreg")
            rows[n] = {m: spawn(m, (src, tgt, gt)) for m in order}
            print(n, {m: rows[n][m].get("time_total_s", rows[n][m].get("error")) for m in order}, flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=HERE).stdout.strip()
    md = ["# Growth: time and memory against points, scanreg beside Open3D (issue #37)", "",
          f"`./run python experiments/benchmarks/growth.py --sizes {a.sizes}`, commit {commit}, "
          f"{time.strftime('%Y-%m-%d', time.gmtime())}; the case and the methods are in the script's docstring. "
          "Each cell one run in a fresh process, the methods interleaved; this 2-core machine's speed drifts, "
          "so compare within a row. `time ratio`: scanreg's total over Open3D's.", "", *table(rows), "",
          "![time against points](growth.png)", "", f"Benchmark wall time {time.perf_counter() - t0:.0f} s."]
    Path(a.out).write_text("\n".join(md) + "\n")
    plot(rows, Path(a.out).with_suffix(".png"))
    print("\n".join(md))


if __name__ == "__main__":
    main()
