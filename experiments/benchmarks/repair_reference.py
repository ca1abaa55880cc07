"""Reference values of the default repair's audit (issue #34): what ``repair=meshfix`` with no override reports
before and after on every mesh we have, recorded so that a change to how the repair works can be checked against
them (``tests/test_repair_reference.py``).

    nice -n 10 .venv/bin/python experiments/benchmarks/repair_reference.py [--out tests/data/repair_reference.json]

Meshes: pymeshfix's ``StanfordBunny.ply`` (``pkg:pymeshfix/examples/StanfordBunny.ply``, always available); every
mesh under ``../shared/data`` (``$SCANREG_SHARED_DATA``): the 10 raw Stanford range scans
(``stanford_bunny/*.ply``, read with the project's reader: pymeshlab triangulates the range grid), the 3 meshes
of ``meshlab_defects``, and the 31 teeth of the dental case one by one (``open_full_jaw_p26/{maxilla,
mandible}/tooth_*.ply``). Meshes under ``../shared/data`` are skipped with a note when the folder is absent (a
recording made so covers less: record on a machine that has the data).

The repair is the CLI's default: ``scanreg.build_stage("repair", "meshfix")``, checked to be the stage that
``scanreg.compose([])`` builds (same class, same parameters), run through its audited entry point
``stage.repair(mesh, RunContext(seed=0))`` on a freshly read mesh (``cache: auto`` outside a sweep: no cache).

Per mesh, keyed by the name the test reads it by (``pkg:...``, or ``shared:REL`` under ``../shared/data``): every
``before_*`` and ``after_*`` metric of the audit; ``untouched``, ``open_border_open``, ``removed_area_share``,
``hausdorff_max_rel``, ``displacement_q_edges``, ``guard_ok``; the repaired mesh's vertex and face counts; the
StageError's message when the repair fails (the guard: its metrics are still recorded, the repaired mesh's counts
are then null); and the repair's wall time (for information only: the test never reads it). The file also holds
the commit the values were recorded at (and whether the package's sources differed from it), the versions of the
libraries the repair uses, and the default parameters.

Re-record only on purpose (a change meant to alter the repair's counts), and say so in the commit.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.metadata
import io
import json
import os
import re
import subprocess
import time
from pathlib import Path

import scanreg
from scanreg.errors import StageError
from scanreg.io import expand_path, read_mesh, resolve_path, shared_data_dir
from scanreg.types import RunContext

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
OUT = ROOT / "tests" / "data" / "repair_reference.json"
BUNNY = "pkg:pymeshfix/examples/StanfordBunny.ply"
SHARED_GLOBS = ("stanford_bunny/*.ply", "meshlab_defects/*.ply", "open_full_jaw_p26/maxilla/tooth_*.ply",
                "open_full_jaw_p26/mandible/tooth_*.ply")
RECORDED = ("untouched", "open_border_open", "removed_area_share", "hausdorff_max_rel", "displacement_q_edges",
            "guard_ok")
"""The audit's metrics recorded beside every ``before_*`` and ``after_*``."""
LIBRARIES = ("numpy", "scipy", "pymeshfix", "pymeshlab", "open3d", "libigl")


def _natural(name: str) -> list:
    """A sort key that puts tooth_2 before tooth_10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def mesh_names() -> list[str]:
    """pymeshfix's bunny, then every mesh under ``../shared/data`` as ``shared:REL`` (a note for each folder that
    is absent)."""
    names, data = [BUNNY], shared_data_dir()
    for pattern in SHARED_GLOBS:
        folder = data / pattern.rpartition("/")[0]
        if not folder.is_dir():
            print(f"note: {folder} absent: skipped")
            continue
        found = sorted((p.relative_to(data).as_posix() for p in data.glob(pattern)), key=_natural)
        names += [f"shared:{rel}" for rel in found]
    return names


def default_repair():
    """The CLI's default repair stage, checked to be the one the API builds."""
    from scanreg.app.config import compose
    from scanreg.runner import build_stages

    stage = scanreg.build_stage("repair", "meshfix")
    cfg = compose([])
    cli = build_stages(cfg).repair
    if cfg.repair.name != "meshfix" or type(cli) is not type(stage) or \
            dataclasses.asdict(cli.p) != dataclasses.asdict(stage.p):
        raise SystemExit(f"the CLI's default repair ({cfg.repair.name}: {dataclasses.asdict(cli.p)}) is not "
                         f"build_stage('repair', 'meshfix') ({dataclasses.asdict(stage.p)})")
    return stage


def record(stage, name: str, ctx: RunContext) -> dict:
    """The default repair of the mesh ``name`` (a fresh read): its audit's counts, the repaired mesh's size, the
    guard's message if it fails, the wall time."""
    mesh = read_mesh(expand_path(name))
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the repair's notes (border plan, untouched)
            r = stage.repair(mesh, ctx)
        metrics, out, error = r.metrics, r.mesh, None
    except StageError as e:  # the guard (its audit kept in the error) or the backend
        metrics, out, error = e.metrics, None, str(e)
    wall = time.perf_counter() - t0
    row = {k: v for k, v in sorted(metrics.items()) if k.startswith(("before_", "after_"))}
    row.update({k: metrics.get(k) for k in RECORDED})
    row["repaired_vertices"] = None if out is None else len(out.vertices)
    row["repaired_faces"] = None if out is None else len(out.faces)
    row["error"] = error
    row["wall_time_s"] = round(wall, 3)
    return row


def provenance() -> dict:
    """The commit, whether the package's sources (pipeline/, stages/, conf/) differ from it, the libraries'
    versions."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()

    versions = {}
    for lib in LIBRARIES:
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            versions[lib] = importlib.metadata.version(lib)
    return {"commit": git("rev-parse", "HEAD"),
            "package_modified": bool(git("status", "--porcelain", "--", "pipeline", "stages", "conf")),
            "versions": versions}


def table(meshes: dict) -> list[str]:
    """A compact table of the recording (markdown)."""
    lines = ["| mesh | faces | loops | nm e | nm v | SI faces | -> faces | loops | slivers | untouched | guard |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for name, r in meshes.items():
        guard = "ok" if r["guard_ok"] == 1 else "FAILS" if r["guard_ok"] == 0 else f"error: {r['error'][:60]}"
        lines.append(f"| {name.split(':', 1)[1]} | {r.get('before_faces')} | {r.get('before_boundary_loops')} | "
                     f"{r.get('before_non_manifold_edges')} | {r.get('before_non_manifold_vertices')} | "
                     f"{r.get('before_self_intersecting_faces')} | {r.get('after_faces')} | "
                     f"{r.get('after_boundary_loops')} | {r.get('after_sliver_faces')} | "
                     f"{r['untouched'] if r['untouched'] is None else int(r['untouched'])} | {guard} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(OUT), help="the JSON file to write (default: %(default)s)")
    args = ap.parse_args()
    assert resolve_path(BUNNY) == resolve_path(Path(__import__("pymeshfix").__file__).parent / "examples" /
                                               "StanfordBunny.ply")
    stage = default_repair()
    ctx = RunContext(seed=0)
    with contextlib.redirect_stdout(io.StringIO()):  # warm-up: imports and the first fork, out of the timings
        stage.repair(read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj"), ctx)
    meshes, t0, load0 = {}, time.perf_counter(), os.getloadavg()[0]
    for name in mesh_names():
        meshes[name] = record(stage, name, ctx)
        r = meshes[name]
        print(f"{name}: {r.get('before_faces')} -> {r['repaired_faces']} faces, guard_ok {r['guard_ok']}, "
              f"{r['wall_time_s']:.2f} s" + (f"; {r['error']}" if r["error"] else ""), flush=True)
    doc = {"about": "experiments/benchmarks/repair_reference.py: the default repair's audit per mesh (issue #34); "
                    "tests/test_repair_reference.py compares a new repair with it; wall_time_s for information",
           **provenance(),
           "seed": ctx.seed,
           "repair": {"name": "meshfix", **dataclasses.asdict(stage.p)},
           "total_wall_time_s": round(time.perf_counter() - t0, 1),
           "load_average": [round(load0, 2), round(os.getloadavg()[0], 2)],
           "meshes": meshes}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print("\n".join(table(meshes)))
    print(f"\n{len(meshes)} meshes, {doc['total_wall_time_s']} s; written to {out}")


if __name__ == "__main__":
    main()
