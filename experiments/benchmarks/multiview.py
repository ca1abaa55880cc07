"""Many scans into one model: scanreg's scan-set registration beside Open3D's multiway registration, on the same
files, in the same run (interleaved), with the same error measure.

    python experiments/benchmarks/multiview.py                  # bunny scans + 20 and 30 rendered views, seeds 0 1 2
    python experiments/benchmarks/multiview.py --seeds 0 --views    # one seed, the bunny scans only
    python experiments/benchmarks/multiview.py --no-bunny --views 15 --seeds 0   # 15 rendered views only

For every seed each of the 10 Stanford bunny scans is moved by a random pose (any rotation, up to half the
diagonal) and written as a PLY mesh with its true pose beside it; likewise each set of views rendered from
pymeshlab's closed bunny (``data=views``: range scans from cameras spread over a sphere, each in its camera's
frame, the seed turning the cameras). Then, on the same files,

- scanreg: ``scanreg data=scanset data.scans=DIR data.poses=POSES`` and nothing else (a new user's command,
  MLflow tracking into a new store in the run's folder included), timed from outside the process (wall clock,
  start-up and logging included) and by its own ``time_total_s``;
- Open3D: the multiway registration of Open3D's tutorials, as a new user builds it from them: every scan read as
  a point cloud, voxel-downsampled to 1 % of the diagonal, normals, FPFH; for every pair, RANSAC on the FPFH
  matches (mutual filter, edge-length and distance checkers, 100 000 iterations, confidence 0.999) and
  point-to-plane ICP; consecutive pairs as odometry edges, every other pair with fitness above 0.3 as a loop
  closure; Levenberg-Marquardt with the line process (edge prune threshold 0.25), the first scan the reference.
  Run in a fresh process, timed the same way.

Both are scored alike (scanreg.eval.scanset.pose_errors): each scan's rotation error and the shift of its points'
centroid against the truth, the frames aligned at the first scan, the shift as a share of the bunny's diagonal;
a scan is within tolerance below 0.5 degrees and 0.25 %. Prints a Markdown table; ``--out`` writes it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"

OPEN3D_MULTIWAY = r'''
import json, sys, time
import numpy as np
import open3d as o3d
t0 = time.perf_counter()
files = json.loads(sys.argv[1])
reg = o3d.pipelines.registration
pcds = [o3d.io.read_point_cloud(f) for f in files]
pts = np.asarray(pcds[0].points)
voxel = 0.01 * float(np.linalg.norm(pts.max(0) - pts.min(0)))
downs, feats = [], []
for p in pcds:
    d = p.voxel_down_sample(voxel)
    d.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    feats.append(reg.compute_fpfh_feature(d, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)))
    downs.append(d)
graph = reg.PoseGraph()
odometry = np.eye(4)
graph.nodes.append(reg.PoseGraphNode(odometry))
for s in range(len(downs)):
    for t in range(s + 1, len(downs)):
        r = reg.registration_ransac_based_on_feature_matching(
            downs[s], downs[t], feats[s], feats[t], True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False),
            3, [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        icp = reg.registration_icp(downs[s], downs[t], 1.5 * voxel, r.transformation,
                                   reg.TransformationEstimationPointToPlane())
        info = reg.get_information_matrix_from_point_clouds(downs[s], downs[t], 1.5 * voxel, icp.transformation)
        if t == s + 1:
            odometry = icp.transformation @ odometry
            graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry)))
            graph.edges.append(reg.PoseGraphEdge(s, t, icp.transformation, info, uncertain=False))
        elif icp.fitness > 0.3:
            graph.edges.append(reg.PoseGraphEdge(s, t, icp.transformation, info, uncertain=True))
option = reg.GlobalOptimizationOption(max_correspondence_distance=1.5 * voxel, edge_prune_threshold=0.25,
                                      reference_node=0)
reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                        reg.GlobalOptimizationConvergenceCriteria(), option)
print(json.dumps({"poses": [np.asarray(n.pose).tolist() for n in graph.nodes], "time": time.perf_counter() - t0}))
'''


def moved_set(folder: Path, seed: int) -> tuple[list[Path], list[np.ndarray], list[np.ndarray]]:
    """The bunny's scans, each moved by a seeded random pose, written into ``folder`` (with a 4x4 pose file per
    scan under ``folder/poses``): the paths, the true poses ``T_world_scan`` and each scan's centroid."""
    from scanreg.geometry import bbox_diagonal, invert_T, points_of, random_pose, transform_geometry
    from scanreg.io import read_geometry, read_stanford_conf, write_ply, write_transform

    conf = read_stanford_conf(SHARED / "stanford_bunny" / "bun.conf")
    names = sorted(conf)
    scans = [read_geometry(SHARED / "stanford_bunny" / n) for n in names]
    diagonal = bbox_diagonal(np.vstack([points_of(g) for g in scans]))
    (folder / "poses").mkdir(parents=True)
    paths, truth, centres = [], [], []
    for k, (n, g) in enumerate(zip(names, scans)):
        P = random_pose(np.random.default_rng([seed, 900 + k]), 180.0, 0.5 * diagonal)
        moved = transform_geometry(P, g)
        paths.append(folder / n)
        write_ply(paths[-1], moved)
        truth.append(conf[n] @ invert_T(P))
        write_transform(folder / "poses" / f"{Path(n).stem}.txt", truth[-1])
        centres.append(points_of(moved).mean(axis=0))
    return paths, truth, centres


def rendered_set(folder: Path, seed: int, n_views: int) -> tuple[list[Path], list[np.ndarray], list[np.ndarray]]:
    """``n_views`` range scans rendered from pymeshlab's closed bunny (``data=views``, seeded), each in its camera's
    frame, written into ``folder`` with its camera's pose under ``folder/poses``."""
    from scanreg.io import read_mesh, write_ply, write_transform
    from scanreg.stages.data.views import Views, render_views

    scans, poses = render_views(read_mesh(Views.Params.mesh), Views.Params(n_views=n_views, seed=seed))
    (folder / "poses").mkdir(parents=True)
    paths = []
    for k, (scan, T) in enumerate(zip(scans, poses)):
        paths.append(folder / f"view{k:02d}.ply")
        write_ply(paths[-1], scan)
        write_transform(folder / "poses" / f"view{k:02d}.txt", T)
    return paths, poses, [s.vertices.mean(axis=0) for s in scans]


def score(poses: list[np.ndarray | None], truth: list[np.ndarray], centres: list[np.ndarray],
          diagonal: float) -> dict[str, float]:
    from scanreg.eval.scanset import pose_errors

    rot, trans = pose_errors(poses, truth, 0, diagonal, centres)
    ok = np.nan_to_num(rot, nan=np.inf) < 0.5
    ok &= np.nan_to_num(trans, nan=np.inf) < 0.0025
    return {"within": int(ok.sum()), "rot_max": float(np.nanmax(rot)), "trans_max": float(np.nanmax(trans)),
            "placed": int(np.isfinite(rot).sum())}


def run_scanreg(folder: Path, work: Path) -> tuple[list[np.ndarray | None], float, float]:
    out = work / "scanreg"
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "scanreg.app", "data=scanset", f"data.scans={folder}",
                        f"data.poses={folder / 'poses'}", f"hydra.run.dir={out}"],
                       cwd=work, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"scanreg failed: {r.stderr.strip().splitlines()[-1]}")
    poses = json.loads((out / "poses.json").read_text())
    names = sorted(p.name for p in folder.glob("*.ply"))  # the files' order, as both methods read them
    res = json.loads((out / "result.json").read_text())
    return [np.array(poses["poses"][n]) if n in poses["poses"] else None for n in names], wall, res["time_total_s"]


def run_open3d(paths: list[Path]) -> tuple[list[np.ndarray], float, float]:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", OPEN3D_MULTIWAY, json.dumps([str(p) for p in paths])],
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"Open3D failed: {r.stderr.strip()[-300:]}")
    out = json.loads(r.stdout.strip().splitlines()[-1])
    return [np.array(T) for T in out["poses"]], wall, out["time"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--views", type=int, nargs="*", default=[20, 30],
                    help="also sets of this many views rendered from a closed bunny (data=views), per seed")
    ap.add_argument("--no-bunny", action="store_true", help="only the rendered sets")
    ap.add_argument("--out", type=Path, default=None, help="write the table (Markdown) here")
    a = ap.parse_args()
    sets = [] if a.no_bunny else ["bunny"]
    if sets and not (SHARED / "stanford_bunny").is_dir():
        print(f"the 10 bunny scans are skipped: {SHARED / 'stanford_bunny'} is absent")
        sets = []
    sets += [f"views{n}" for n in a.views]
    from scanreg.geometry import apply_T, points_of, principal_box_diagonal
    from scanreg.io import read_geometry

    rows = ["| set | seed | method | scans within 0.5° and 0.25 % | placed | worst rotation [°] | worst shift [% diag] "
            "| wall [s] | own time [s] |", "|---|---|---|---|---|---|---|---|---|"]
    for name in sets:
        for seed in a.seeds:
            with tempfile.TemporaryDirectory(prefix="scanreg-mv-") as tmp:
                folder = Path(tmp) / "scans"
                paths, truth, centres = moved_set(folder, seed) if name == "bunny" else \
                    rendered_set(folder, seed, int(name[len("views"):]))
                # the model's diagonal: every scan at its true pose, the box along its principal axes (as a
                # scan set's model_diagonal)
                diagonal = principal_box_diagonal(np.vstack([apply_T(T, points_of(read_geometry(p)))
                                                             for p, T in zip(paths, truth)]))
                for method in ("open3d", "scanreg") if seed % 2 else ("scanreg", "open3d"):  # interleaved
                    poses, wall, own = run_open3d(paths) if method == "open3d" else run_scanreg(folder, Path(tmp))
                    s = score(poses, truth, centres, diagonal)
                    rows.append(f"| {name} | {seed} | {method} | {s['within']}/{len(paths)} | {s['placed']} | "
                                f"{s['rot_max']:.3f} | {100 * s['trans_max']:.3f} | {wall:.1f} | {own:.1f} |")
                    print(rows[-1], flush=True)
    table = "\n".join(rows)
    print("\n" + table)
    if a.out:
        a.out.write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
