"""Benchmark (issue #13, item 4): ICP alone (coarse=none) from 10 degrees and 2 % of the diagonal off.

    ./run python experiments/benchmarks/icp_basin.py [N] [variants] [overrides]
    ./run python experiments/benchmarks/icp_basin.py 100000 horn,anderson "schedule='fixed'"

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


def main():
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
