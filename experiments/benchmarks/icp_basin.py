"""Benchmark (issue #13, item 4): ICP alone (coarse=none) from 10 degrees and 2 % of the diagonal off; with
``far``, issue #35's cases from 30 degrees, as a user runs them (results in icp_basin.md).

    ./run python experiments/benchmarks/icp_basin.py [N] [variants] [overrides]
    ./run python experiments/benchmarks/icp_basin.py 100000 horn,anderson "schedule='fixed'"
    ./run python experiments/benchmarks/icp_basin.py far [N]

Case: pymeshlab's closed bunny.obj sampled twice independently (N points each, default 100 000); the target is
the first sampling moved 10 degrees about a random axis through its centre plus 2 % of the diagonal; ICP starts
at the identity with each variant's defaults (plus the overrides, Python keyword syntax). Prints the rotation
error, the translation error as a share of the diagonal, iterations, time and the ICP metrics.

Each variant's defaults are its Params dataclass's, which since #32 are also the CLI's: point_to_plane now
iterates on a quarter of the points first (``initial_share`` 0.25; this script ran it at 1 before); pass
``"initial_share=1"`` for the earlier point_to_plane row (the same numbers, bit for bit).
"""

import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation

from scanreg.geometry import (Cloud, apply_T, barycentric_sample, bbox_diagonal, estimate_spacing, make_T,
                              transform_errors)
from scanreg.io import read_mesh
from scanreg.stages.registry import ICP, load_all, make_params
from scanreg.types import RunContext


def far_cases(n: int):
    """Issue #35's cases: (name, source points, target points, T_target_source). The elongated blob: 4,000
    Gaussian points with axes 3:2:1 against themselves moved by rotation vector (0.2, -0.1, 0.3) (21 deg) and
    (0.5, -0.3, 0.2), or 30 deg about (1, 1, 0) and 5 % of the diagonal; the bunny: two independent samplings of n
    points of pymeshlab's bunny.obj, 30 deg about (1, 1, 0) through the origin and 5 % of the diagonal along x."""
    blob = np.random.default_rng(0).normal(size=(4000, 3)) * np.array([3.0, 2.0, 1.0])
    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    a, b = (barycentric_sample(m, n, np.random.default_rng(s))[0] for s in (1, 2))
    R30 = Rotation.from_rotvec(np.radians(30.0) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)).as_matrix()
    T21 = make_T(Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([0.5, -0.3, 0.2]))
    T_blob, T_bunny = (make_T(R30, 0.05 * bbox_diagonal(x) * np.array([1.0, 0.0, 0.0])) for x in (blob, a))
    return [("blob 21 deg", blob, apply_T(T21, blob), T21),
            ("blob 30 deg, 5 %", blob, apply_T(T_blob, blob), T_blob),
            (f"bunny {n} pts 30 deg, 5 %", b, apply_T(T_bunny, a), T_bunny)]


def far(n: int):
    """Each case through ``scanreg.register(source, target, overrides=["coarse=none", "icp=V"])`` with
    ``icp.basin`` local (the schedule alone, as before #35) and auto (the default), interleaved; and Open3D's
    registration_icp from the same start (point-to-point and point-to-plane, limit 5 % of the diagonal, 100
    iterations) as the anchor."""
    import open3d as o3d

    import scanreg

    reg = o3d.pipelines.registration
    print("| case | variant | basin=local | basin=auto (default) | wide end point kept | time local | time auto |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    anchors = []
    for name, src, tgt, T in far_cases(n):
        for v in ("horn", "point_to_plane", "gicp", "anderson"):
            row = {}
            for basin in ("local", "auto"):
                t0 = time.perf_counter()
                res = scanreg.register(src, tgt, overrides=["coarse=none", f"icp={v}", f"icp.basin={basin}",
                                                            "tracking=none"])
                row[basin] = (transform_errors(res.T_target_source, T)[0], time.perf_counter() - t0,
                              res.metrics.get("icp_basin_wide"))
            print(f"| {name} | {v} | {row['local'][0]:.4f} deg | {row['auto'][0]:.4f} deg | "
                  f"{row['auto'][2]:.0f} | {row['local'][1]:.1f} s | {row['auto'][1]:.1f} s |", flush=True)
        s, t = (o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x)) for x in (src, tgt))
        t.estimate_normals()
        for est in ("point_to_point", "point_to_plane"):
            e = reg.TransformationEstimationPointToPoint() if est == "point_to_point" else \
                reg.TransformationEstimationPointToPlane()
            t0 = time.perf_counter()
            r = reg.registration_icp(s, t, 0.05 * bbox_diagonal(tgt), np.eye(4), e,
                                     reg.ICPConvergenceCriteria(max_iteration=100))
            anchors.append((name, est, transform_errors(np.asarray(r.transformation), T)[0],
                            time.perf_counter() - t0))
    print("\n| case | Open3D registration_icp | rotation error | time |\n| --- | --- | --- | --- |")
    for name, est, err, dt in anchors:
        print(f"| {name} | {est} | {err:.4f} deg | {dt:.1f} s |")


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "far":
        return far(int(sys.argv[2]) if len(sys.argv) > 2 else 100_000)
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100_000
    variants = (sys.argv[2] if len(sys.argv) > 2 else "horn,point_to_plane,anderson,gicp,open3d").split(",")
    kw = eval(f"dict({sys.argv[3]})") if len(sys.argv) > 3 else {}  # noqa: S307 - a benchmark's own command line
    load_all()
    m = read_mesh("pkg:pymeshlab/tests/sample_meshes/bunny.obj")
    a, b = (Cloud(*barycentric_sample(m, n, np.random.default_rng(s))[:2]) for s in (1, 2))
    diag = bbox_diagonal(a.points)
    rng = np.random.default_rng(0)
    axis = rng.normal(size=3)
    t = rng.normal(size=3)
    t *= 0.02 * diag / np.linalg.norm(t)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(10)).as_matrix()
    c0 = a.points.mean(0)
    T = make_T(R, c0 + t - R @ c0)
    tgt = Cloud(apply_T(T, a.points), a.normals @ T[:3, :3].T)
    ctx = RunContext(seed=0, run_dir=None)
    spacing = estimate_spacing(tgt.points, np.random.default_rng(0))
    rot0, tr0 = transform_errors(np.eye(4), T)
    print(f"N {n}: start {rot0:.2f} deg, {tr0 / diag * 100:.2f} % of the diagonal; spacing {spacing:.4g}")
    for v in variants:
        cls = ICP.get(v)
        stage = cls(make_params(cls.Params, kw, f"icp={v}"))
        t0 = time.perf_counter()
        r = stage.refine(tgt, b, np.eye(4), spacing, ctx)
        dt = time.perf_counter() - t0
        rot, tr = transform_errors(r.T_target_source, T)
        print(f"{v:15s} rotation {rot:.4f} deg  translation {tr / diag * 100:.4f} % diag  iterations {r.iterations}"
              f"  {dt:.1f} s  " + " ".join(f"{k}={x:.4g}" for k, x in r.metrics.items()))


if __name__ == "__main__":
    main()
