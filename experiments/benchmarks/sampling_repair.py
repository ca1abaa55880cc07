"""Benchmark: sampling and repair, side by side with the anchors, measured in one run.

    ./run python experiments/benchmarks/sampling_repair.py [--points 1000000] [--repeat 3]

Sampling: scanreg's ``barycentric`` against Open3D's ``sample_points_uniformly`` (and the other samplers)
for N points on pymeshfix's bunny (100k faces), single process, same threads.
Repair: each backend on the defect meshes, against pymeshfix's stock ``MeshFix.repair()`` on the same mesh,
with the audit's verdict (default guard limits); open scans also with repair.open_border=cap and =shell. Real
scans from ../shared/data are included when present.

    ./run python experiments/benchmarks/sampling_repair.py --stanford [--borders auto,shell]

The 10 raw Stanford range scans with the default repair (meshfix, open_border=auto, no override) and the other
border modes given: time (backend and audit apart) and the guard's measurements; written to
``stanford_repair.md``.

Timings: ``--repeat`` rounds, each running the anchor and then every method once (interleaved, so that a slow
spell of the machine hits all of them); the tables give the median with the min-max range over the rounds, and
the ratio to the anchor is taken within each round.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time
from pathlib import Path

import numpy as np

from scanreg.errors import StageError
from scanreg.io import read_mesh, shared_data_dir
from scanreg.stages.registry import REPAIR, SAMPLER, make_params
from scanreg.types import RunContext


def timed(fn) -> float:
    t0 = time.perf_counter_ns()
    fn()
    return (time.perf_counter_ns() - t0) / 1e9


def spread(values: list[float], fmt: str) -> str:
    """``median (min-max)``."""
    v = np.asarray(values, float)
    return f"{np.median(v):{fmt}} ({v.min():{fmt}}-{v.max():{fmt}})"


def bench_sampling(n: int, repeat: int) -> list[str]:
    import open3d as o3d

    mesh = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    ctx = RunContext(seed=0, run_dir=None)
    methods = {}
    for name in ("barycentric", "open3d_uniform", "poisson_disk"):
        if name == "poisson_disk" and n > 200_000:
            continue  # sample elimination is far slower; not a like-for-like comparison at this size
        cls = SAMPLER.get(name)
        methods[name] = cls(make_params(cls.Params, {"n_points": n}, name))
    anchor, times = [], {name: [] for name in methods}
    for _ in range(repeat):  # interleaved: the anchor, then every method, in each round
        anchor.append(timed(lambda: om.sample_points_uniformly(n)))
        for name, s in methods.items():
            times[name].append(timed(lambda: s.sample_mesh(mesh, ctx)))
    rows = [f"| Open3D sample_points_uniformly (anchor) | {spread(anchor, '.3f')} | 1.00 |"]
    for name, t in times.items():
        rows.append(f"| scanreg {name} | {spread(t, '.3f')} | {spread([x / y for x, y in zip(t, anchor)], '.2f')} |")
    head = [f"Sampling {n:,} points on pymeshfix's StanfordBunny.ply ({len(mesh.faces):,} faces), median "
            f"(min-max) of {repeat} interleaved rounds", "", "| method | time [s] | ratio to anchor |", "|---|---|---|"]
    return head + rows


def bench_repair(repeat: int) -> list[str]:
    import pymeshfix

    from scanreg.stages.repair import repair_with_audit

    meshes = {"StanfordBunny.ply (pymeshfix)": "pkg:pymeshfix/examples/StanfordBunny.ply"}
    shared = shared_data_dir()
    for rel in ("meshlab_defects/many_small_holes.ply", "meshlab_defects/non_manif_hole.ply",
                "meshlab_defects/screwdriver.ply", "stanford_bunny/bun000.ply"):
        if (shared / rel).exists():
            meshes[rel] = str(shared / rel)
    rows = []
    ctx = RunContext(seed=0, run_dir=None)
    for label, path in meshes.items():
        m = read_mesh(path)
        m.source = label
        configs = [("meshfix", {}), ("meshlab", {})]
        if not label.startswith("StanfordBunny") and "screwdriver" not in label:
            # the default (auto: open for these) above; capping the outer border and closing a shell here
            configs += [(b, {"open_border": o}) for o in ("cap", "shell") for b in ("meshfix", "meshlab")]
        anchor, times, audits = [], [[] for _ in configs], [None] * len(configs)
        for _ in range(repeat):  # interleaved: the anchor, then every configuration, in each round
            def stock():
                pymeshfix.MeshFix(m.vertices, m.faces.astype(np.int32)).repair()

            anchor.append(timed(stock))
            for i, (name, kw) in enumerate(configs):
                cls = REPAIR.get(name)
                st = cls(make_params(cls.Params, {**kw, "check_only": True}, name))
                t0 = time.perf_counter_ns()
                with contextlib.redirect_stdout(io.StringIO()):
                    try:
                        mm = repair_with_audit(st, m, ctx).metrics
                    except StageError as e:  # the guard's failure carries the audit (unprefixed names)
                        mm = e.metrics
                times[i].append((time.perf_counter_ns() - t0) / 1e9)
                audits[i] = audits[i] or mm
        rows.append(f"| {label} | pymeshfix MeshFix.repair() (anchor) | {spread(anchor, '.2f')} | 1.00 | - |")
        for (name, kw), t, a in zip(configs, times, audits):
            verdict = (f"{'ok' if a['guard_ok'] else 'GUARD'}{', watertight' if a['after_watertight'] else ''}: "
                       f"loops {a['before_boundary_loops']}->"
                       f"{a['after_boundary_loops']}, self-int {a['before_self_intersecting_faces']}->"
                       f"{a['after_self_intersecting_faces']}, removed {a['removed_area_share']:.1%}, "
                       f"Hausdorff {a['hausdorff_max_rel']:.2%} of diag")
            opts = " ".join(f"{k}={v}" for k, v in kw.items())
            ratio = spread([x / y for x, y in zip(t, anchor)], ".2f")
            rows.append(f"| {label} | scanreg {name} {opts} (with audit) | {spread(t, '.2f')} | {ratio} | {verdict} |")
    head = ["Repair (time includes scanreg's audit: before/after statistics, self-intersections, Hausdorff); "
            f"median (min-max) of {repeat} interleaved rounds", "",
            "| mesh | method | time [s] | ratio to anchor | audit |", "|---|---|---|---|---|"]
    return head + rows


def bench_stanford(borders: list[str]) -> list[str]:
    from scanreg.stages.repair import repair_with_audit

    folder = shared_data_dir() / "stanford_bunny"
    names = ["bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "chin", "ear_back", "top2", "top3"]
    rows = []
    ctx = RunContext(seed=0, run_dir=None)
    import open3d  # noqa: F401  (its import, 2 s, is not the repair's)

    for border in borders:
        for name in names:
            m = read_mesh(str(folder / f"{name}.ply"))
            m.source = name
            cls = REPAIR.get("meshfix")
            st = cls(make_params(cls.Params, {"open_border": border, "check_only": True}, "meshfix"))
            t0 = time.perf_counter_ns()
            with contextlib.redirect_stdout(io.StringIO()):
                a = repair_with_audit(st, m, ctx).metrics
            t = (time.perf_counter_ns() - t0) / 1e9
            rows.append(f"| {name} | {border} | {t:.2f} | {a['backend_time_s']:.2f} | {a['audit_time_s']:.2f} | "
                        f"{'ok' if a['guard_ok'] else 'GUARD'} | {a['open_border_open']:.0f} | "
                        f"{a['before_boundary_loops']}->{a['after_boundary_loops']} | "
                        f"{a['after_self_intersecting_faces']} | {a['removed_area_share']:.2%} | "
                        f"{a['displacement_q_edges']:.2f} | {a['hausdorff_max_edges']:.1f} | "
                        f"{a['hausdorff_max_rel']:.2%} | {a['removed_components']:.0f} |")
    head = ["Raw Stanford range scans, repair=meshfix, default guard (time: total = backend + audit, 2 shared "
            "cores)", "",
            "| scan | open_border | time [s] | backend [s] | audit [s] | guard | border open | loops | "
            "self-int after | removed | q99 displacement [edges] | Hausdorff [edges] | Hausdorff [diag] | "
            "removed parts |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    return head + rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=str(Path(__file__).with_suffix(".md")))
    ap.add_argument("--stanford", action="store_true", help="only the 10 raw Stanford scans")
    ap.add_argument("--borders", default="auto,shell", help="--stanford: open_border modes, comma separated")
    a = ap.parse_args()
    from scanreg.stages.registry import load_all

    load_all()
    if a.repeat < 1:
        raise SystemExit("error: --repeat must be >= 1")
    if a.stanford:
        text = "\n".join(bench_stanford(a.borders.split(",")))
        print(text)
        import subprocess

        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        out = Path(__file__).with_name("stanford_repair.md")
        out.write_text(f"# Default repair on the raw Stanford scans\n\nProduced by `python experiments/benchmarks/"
                       f"sampling_repair.py --stanford` at commit {commit or '?'} on a 2-core machine shared "
                       f"with other jobs.\n\n{text}\n")
        return
    lines = bench_sampling(a.points, a.repeat) + [""] + bench_repair(a.repeat)
    text = "\n".join(lines)
    print(text)
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    Path(a.out).write_text(f"# Sampling and repair benchmark\n\nProduced by `python experiments/benchmarks/"
                           f"sampling_repair.py --points {a.points} --repeat {a.repeat}` at commit {commit or '?'} on a 2-core machine.\n\n{text}\n")


if __name__ == "__main__":
    main()
