"""Benchmark: the default repair of every real scan, this working tree against an earlier commit, in one run.

    .venv/bin/python experiments/benchmarks/repair_ab.py BASE [--rounds 2] [--out experiments/benchmarks/repair_ab.md]

The anchor is the same code before a change: ``BASE`` (a commit) is checked out in a temporary git worktree and
imported in place of this tree (a folder of links that maps the package as ``pyproject.toml`` does:
``scanreg`` -> ``pipeline/``, ``scanreg.stages`` -> ``stages/``, ``scanreg.conf`` -> ``conf/``, put first on
``PYTHONPATH``), its compiled kernels built there as its install would build them (so that a base with kernels
does not run their NumPy versions). Each round runs one fresh process per side, the two sides alternating which goes first (a slow
spell of the shared machine hits both). A process imports Open3D, libigl and pymeshfix, repairs the first scan
once to warm up, then repairs each scan once with ``repair=meshfix`` defaults (``RunContext(seed=0)``), each from
its own freshly read mesh, and reports per scan the wall time and the CPU time of the process and its children
(MeshFix's sessions and the input's test beside the repair, each reaped before the repair returns), so that work
moved into a child process still counts.

Scans: the 10 raw Stanford range scans (``../shared/data/stanford_bunny``, skipped with a message when absent)
and pymeshfix's ``examples/StanfordBunny.ply`` (a closed model with 70 holes). The table gives the medians over
the rounds and the ratio of this tree's CPU time to the base's; the last row sums the scans.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE_DIRS = {"stages": "stages", "conf": "conf"}  # subpackages mapped elsewhere than pipeline/ (pyproject.toml)


def scan_paths() -> list[Path]:
    import pymeshfix

    shared = ROOT.parent / "shared" / "data" / "stanford_bunny"
    scans = sorted(shared.glob("*.ply")) if shared.is_dir() else []
    if not scans:
        print(f"note: {shared} not found: the raw Stanford scans are skipped", file=sys.stderr)
    return scans + [Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply"]


def worker() -> None:
    """Repair every scan once (after a warm-up) and print {scan: [wall s, CPU s]} as one JSON line."""
    import igl  # noqa: F401
    import open3d  # noqa: F401
    import pymeshfix  # noqa: F401

    import scanreg
    from scanreg.io import read_mesh
    from scanreg.types import RunContext

    def cpu() -> float:
        a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

    paths = scan_paths()
    stage = scanreg.build_stage("repair", "meshfix")
    stage.repair(read_mesh(str(paths[0])), RunContext(seed=0))
    out = {}
    for p in paths:
        mesh = read_mesh(str(p))
        c0, t0 = cpu(), time.perf_counter_ns()
        stage.repair(mesh, RunContext(seed=0))
        out[p.name] = [(time.perf_counter_ns() - t0) / 1e9, cpu() - c0]
    print(json.dumps(out))


def base_tree(commit: str, tmp: Path) -> Path:
    """A folder to put first on PYTHONPATH that imports ``scanreg`` from ``commit`` (a git worktree of it)."""
    tree = tmp / "tree"
    subprocess.run(["git", "worktree", "add", "--detach", str(tree), commit], cwd=ROOT, check=True,
                   capture_output=True)
    build_kernels(tree)
    pkg = tmp / "path" / "scanreg"
    pkg.mkdir(parents=True)
    for entry in (tree / "pipeline").iterdir():
        (pkg / entry.name).symlink_to(entry)
    for name, folder in PACKAGE_DIRS.items():
        (pkg / name).symlink_to(tree / folder)
    return tmp / "path"


def build_kernels(tree: Path) -> None:
    """The compiled kernels of the commit checked out at ``tree`` (its ``pyproject.toml``'s ext-modules, as its
    install would build them), built in place: without them the base would run their NumPy versions."""
    import tomllib

    from setuptools import Distribution, Extension

    config = tomllib.loads((tree / "pyproject.toml").read_text()).get("tool", {}).get("setuptools", {})
    mods = [Extension(**{k.replace("-", "_"): v for k, v in m.items() if k != "optional"})
            for m in config.get("ext-modules", [])]
    if not mods:
        return
    dist = Distribution({"ext_modules": mods, "package_dir": config.get("package-dir", {}),
                         "script_name": "setup.py"})
    cmd = dist.get_command_obj("build_ext")
    cmd.inplace = True
    cwd = os.getcwd()
    os.chdir(tree)  # the sources are relative to the project
    try:
        with contextlib.redirect_stdout(sys.stderr):
            dist.run_command("build_ext")
    finally:
        os.chdir(cwd)


def run_side(pythonpath: str | None) -> dict:
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    else:
        env.pop("PYTHONPATH", None)
    r = subprocess.run([sys.executable, __file__, "--worker"], capture_output=True, text=True, env=env, cwd=ROOT)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode != 0 or not lines:
        sys.exit(f"error: a worker failed: {(r.stderr.strip().splitlines() or ['?'])[-1]}")
    return json.loads(lines[-1])


def table(base: list[dict], head: list[dict], commit: str) -> list[str]:
    rows = ["| scan | wall, base [s] | wall, this tree [s] | CPU, base [s] | CPU, this tree [s] | CPU ratio |",
            "|---|---|---|---|---|---|"]
    tot = [0.0, 0.0, 0.0, 0.0]
    for name in base[0]:
        vals = [statistics.median(r[name][k] for r in runs) for k in (0, 1) for runs in (base, head)]
        wb, wh, cb, ch = vals
        tot = [t + x for t, x in zip(tot, (wb, wh, cb, ch))]
        rows.append(f"| {name} | {wb:.2f} | {wh:.2f} | {cb:.2f} | {ch:.2f} | {ch / cb:.2f} |")
    rows.append(f"| all (sum of medians) | {tot[0]:.2f} | {tot[1]:.2f} | {tot[2]:.2f} | {tot[3]:.2f} | "
                f"{tot[3] / tot[2]:.2f} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("base", nargs="?", help="the commit to compare with (the anchor)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default=str(Path(__file__).with_suffix(".md")))
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        worker()
        return
    if not a.base:
        ap.error("give the commit to compare with")
    commit = subprocess.run(["git", "rev-parse", "--short=12", a.base], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    if not commit:
        sys.exit(f"error: base: '{a.base}' is not a commit of this repository")
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip()
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        path = base_tree(commit, Path(tmp))
        try:
            runs: dict[str, list[dict]] = {"base": [], "head": []}
            for k in range(a.rounds):
                order = [("base", str(path)), ("head", None)]
                for side, pp in (order if k % 2 == 0 else order[::-1]):
                    runs[side].append(run_side(pp))
                    print(f"round {k + 1}/{a.rounds}: {side} done", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(Path(tmp) / "tree")], cwd=ROOT,
                           capture_output=True)
    rows = table(runs["base"], runs["head"], commit)
    intro = (f"# The default repair, this tree against {commit}\n\n`experiments/benchmarks/repair_ab.py {a.base}`, "
             f"this tree at {head} (with its uncommitted changes, if any), "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {a.rounds} rounds, "
             f"benchmark wall time {time.time() - t0:.0f} s. How it is measured: the module doc of `repair_ab.py`.")
    text = "\n".join([intro, "", *rows, ""])
    print(text)
    Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
