"""Benchmark: the audited repair's speed against pymeshfix alone, and the repair cache (issue #16), in one run.

    .venv/bin/python experiments/benchmarks/repair_speed.py [--repeat 5] [--fresh-repeat 21]
        [--out experiments/benchmarks/repair_speed.md]

Rows, each round interleaved (every method once per round, so that a slow spell of the shared machine hits all of
them); the table gives the median with the min-max range over the rounds, ratios taken within each round:

- pymeshfix's StanfordBunny.ply (100k faces, a closed model with holes): pymeshfix's stock
  ``MeshFix(v, f).repair()`` with its result read back (``points``, ``faces``; the anchor) against
  ``repair=meshfix`` with its audit and guard (defaults), and ``repair=meshlab``; and the anchor,
  ``repair=meshfix``, the anchor on the renumbered copy that ``repair=meshfix`` hands to MeshFix (the bunny's
  vertices are scattered through its file; :func:`scanreg.geometry.locality_ordered` renumbers them in Morton
  order, and MeshFix walks its linked mesh about 25 % faster: this row tells that gain from the audit's cost) and
  ``repair=meshfix remove_slivers=false`` (the audit and guard on pymeshfix's own work: pymeshfix does not remove
  slivers) once each in a fresh process (after the same warm-up), as a run makes them, in ``--fresh-repeat``
  rounds of their own after the others;
- the raw Stanford scan bun000 (80k faces, an open range scan; ../shared/data): ``repair=meshfix`` (the default
  repair, no override) and ``repair=meshlab``;
- a cache hit (``repair.cache=on``, the entry made before the rounds): the time to hash the input and read the
  repaired mesh and its metrics back;
- bun000's default repair in a fresh process (one per round, after the same warm-up), as a run makes it.

pymeshfix gets slower with each use in one process (it leaks about 13 MB per repair of the bunny, and its
mesh's many small blocks land scattered in a heap that other work has used: 1.09, 1.43, 1.64, 1.87, 1.84, 1.95 s
for six repairs in a row), so the anchor's row from this long process drifts over the rounds (the row "first
and last round" shows by how much). ``repair=meshfix`` runs MeshFix in a child process per session, in a thread
of its own there (:func:`scanreg.process.run_isolated`: a fresh malloc arena, the memory given back at exit),
and keeps its speed. The fresh-process rows are the ones a single run sees.

Every repair gets its own copy of the input mesh, as a run reads it: the audit remembers its measurements of a
mesh (edge table, components, self-intersections) on the mesh object, and a mesh repaired again would reuse the
input's. (There is no process-wide memo of recent meshes any more, #32: nothing else to empty between repairs.)
Since #32 the input's audit (its self-intersection test, statistics and samples) runs in this process before the
backend (the output's after it), no longer in a forked child beside it: the wall time of ``repair=meshfix`` is now
the backend's plus the audit's, and its CPU time (which counts the MeshFix children's, each reaped when its session
ends) no longer includes work that the wall time overlaps. Every row of the table before #32 still measures
something the code does, so none is dropped; the audit's share of the backend's time is now the audit's
sequential cost. The anchor and ``repair=meshfix`` on the bunny swap places every other round.

Every repair runs in this process after one warm-up (imports of open3d, pymeshlab and pymeshfix excluded: a run
of the pipeline pays them once, for every stage). ``backend`` is the backend itself (with the sliver collapse),
``audit`` the before/after audit and the guard (``repair_backend_time_s``, ``repair_audit_time_s``).
Each row gives the wall time and the CPU time (user + system, ``resource.getrusage`` of the process and its
children) of the same calls:
on the shared machine the CPU time is the steadier of the two.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scanreg.geometry import Mesh
from scanreg.io import read_mesh, shared_data_dir
from scanreg.stages.registry import REPAIR, load_all, make_params
from scanreg.types import RunContext


def spread(values, fmt: str) -> str:
    v = np.asarray(values, float)
    return f"{np.median(v):{fmt}} ({v.min():{fmt}}-{v.max():{fmt}})"


def stage(name: str, **kw):
    cls = REPAIR.get(name)
    return cls(make_params(cls.Params, kw, name))


def cpu_s() -> float:
    """This process's CPU time so far (user + system, s), with its finished child processes' (MeshFix's sessions
    run in forked children, :func:`scanreg.process.run_isolated`)."""
    r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime


CPU: dict[str, list] = {}
"""The CPU time of each timed call, by row (filled by :func:`timed`)."""


def timed(key: str, fn):
    """``fn()``'s wall time (s), its CPU time recorded in ``CPU[key]``, and its result."""
    c0, t0 = cpu_s(), time.perf_counter_ns()
    out = fn()
    wall = (time.perf_counter_ns() - t0) / 1e9
    CPU.setdefault(key, []).append(cpu_s() - c0)
    return wall, out


def fresh(mesh: Mesh) -> Mesh:
    """A copy of ``mesh`` with new arrays: nothing the audit remembered about ``mesh`` applies to it."""
    return Mesh(mesh.vertices.copy(), mesh.faces.copy(), mesh.source)


def timed_repair(st, mesh, ctx, key: str = "warm-up") -> tuple[float, dict]:
    """``st``'s audited repair of a fresh copy of ``mesh`` (the copy made before the clock starts)."""
    mesh = fresh(mesh)

    def run():
        with contextlib.redirect_stdout(io.StringIO()):
            return st.repair(mesh, ctx).metrics
    return timed(key, run)


FRESH = """
import contextlib, io, resource, sys, time
import numpy as np
import pymeshfix
from scanreg.types import RunContext
from scanreg.geometry import locality_ordered
from scanreg.io import read_mesh
from scanreg.stages.registry import REPAIR, load_all, make_params
def cpu():
    r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime
load_all()
cls = REPAIR.get("meshfix")
extra = {"remove_slivers": False} if sys.argv[2] == "noslivers" else {}
st = cls(make_params(cls.Params, {"cache": "off", **extra}, "meshfix"))
ctx = RunContext(seed=0, run_dir=None)
mesh = read_mesh(sys.argv[1])
with contextlib.redirect_stdout(io.StringIO()):
    st.repair(read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj"), ctx)  # warm-up: imports
    c0, t0 = cpu(), time.perf_counter_ns()
    if sys.argv[2] in ("anchor", "ordered"):
        v, f = mesh.vertices.copy(), mesh.faces
        if sys.argv[2] == "ordered":
            v, f = locality_ordered(v, f)
        fix = pymeshfix.MeshFix(v, f.astype(np.int32))
        fix.repair()
        fix.points, fix.faces
    else:
        st.repair(mesh, ctx)
    t = (time.perf_counter_ns() - t0) / 1e9
print(t, cpu() - c0)
"""
"""One repair (``anchor``: pymeshfix alone; ``ordered``: pymeshfix alone on the mesh renumbered as repair=meshfix
hands it to MeshFix, the renumbering timed; ``noslivers``: the default repair without the sliver collapse; else
the default repair) as the first after the warm-up in a fresh process: prints wall and CPU (s)."""


def fresh_repair(path: Path | str, what: str = "scanreg") -> tuple[float, float]:
    out = subprocess.run([sys.executable, "-c", FRESH, str(path), what], capture_output=True, text=True,
                         check=True)
    wall, cpu = (float(x) for x in out.stdout.split()[-2:])
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--fresh-repeat", type=int, default=21,
                    help="rounds of the bunny's fresh-process rows (anchor, repair=meshfix, the "
                         "anchor on the renumbered copy, remove_slivers=false)")
    ap.add_argument("--out", default=None, help="also write the table to this markdown file")
    args = ap.parse_args()
    import pymeshfix

    load_all()
    ctx = RunContext(seed=0, run_dir=None)
    bunny = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    bun000_path = shared_data_dir() / "stanford_bunny" / "bun000.ply"
    bun000 = read_mesh(str(bun000_path)) if bun000_path.exists() else None
    meshfix, meshlab = stage("meshfix", cache="off"), stage("meshlab", cache="off")
    timed_repair(meshfix, read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj"), ctx)  # warm-up: imports
    cache_dir = tempfile.mkdtemp(prefix="scanreg-repair-cache-")
    cached = stage("meshfix", cache="on", cache_dir=cache_dir)
    if bun000 is not None:
        timed_repair(cached, bun000, ctx)  # makes the entry

    t = {k: [] for k in ("anchor", "bunny_meshfix", "bunny_meshlab", "bun000_meshfix", "bun000_meshlab", "hit",
                         "fresh", "fresh_bunny_anchor", "fresh_bunny_ordered", "fresh_bunny_scanreg",
                         "fresh_bunny_noslivers")}
    parts = {k: [] for k in ("bunny_backend", "bunny_audit", "bun000_backend", "bun000_audit")}
    for r in range(args.repeat):
        def anchor():
            v, f = bunny.vertices.copy(), bunny.faces.astype(np.int32)

            def alone():  # repair and read the result back, as a user of pymeshfix does
                fix = pymeshfix.MeshFix(v, f)
                fix.repair()
                return fix.points, fix.faces
            t["anchor"].append(timed("anchor", alone)[0])

        def scanreg():
            s, m = timed_repair(meshfix, bunny, ctx, "bunny_meshfix")
            t["bunny_meshfix"].append(s)
            parts["bunny_backend"].append(m["backend_time_s"])
            parts["bunny_audit"].append(m["audit_time_s"])

        for run in ((anchor, scanreg) if r % 2 == 0 else (scanreg, anchor)):
            run()
        t["bunny_meshlab"].append(timed_repair(meshlab, bunny, ctx, "bunny_meshlab")[0])
        if bun000 is not None:
            s, m = timed_repair(meshfix, bun000, ctx, "bun000_meshfix")
            t["bun000_meshfix"].append(s)
            parts["bun000_backend"].append(m["backend_time_s"])
            parts["bun000_audit"].append(m["audit_time_s"])
            t["bun000_meshlab"].append(timed_repair(meshlab, bun000, ctx, "bun000_meshlab")[0])
            s, m = timed_repair(cached, bun000, ctx, "hit")
            assert m["cache_hit"] == 1.0
            t["hit"].append(s)
            wall, c = fresh_repair(bun000_path)
            t["fresh"].append(wall)
            CPU.setdefault("fresh", []).append(c)

    # the bunny's fresh-process rows (the done-when's ratio): rounds of their own, more of them, as the
    # per-round spread of a fresh process (0.1-0.2 s) is about the size of the overhead measured
    for r in range(args.fresh_repeat):
        kinds = ("anchor", "scanreg", "ordered", "noslivers")
        for what in (kinds if r % 2 == 0 else kinds[::-1]):
            wall, c = fresh_repair("pkg:pymeshfix/examples/StanfordBunny.ply", what)
            t[f"fresh_bunny_{what}"].append(wall)
            CPU.setdefault(f"fresh_bunny_{what}", []).append(c)

    def ratio(a, b):
        return spread([x / y for x, y in zip(t[a], t[b])], ".2f")

    def cpu(a, fmt=".2f"):
        return spread(CPU[a], fmt)

    def cpu_ratio(a, b):
        return spread([x / y for x, y in zip(CPU[a], CPU[b])], ".2f")

    def share(a, b):
        return spread([x / y for x, y in zip(parts[a], parts[b])], ".2f")

    rows = [
        "| mesh | method | wall time [s] | CPU time [s] | wall ratio | CPU ratio | ratio to |",
        "|---|---|---|---|---|---|---|",
        f"| StanfordBunny.ply (100k faces) | pymeshfix MeshFix.repair() alone (anchor) | {spread(t['anchor'], '.2f')} "
        f"| {cpu('anchor')} | 1.00 | 1.00 | anchor |",
        f"| StanfordBunny.ply | scanreg repair=meshfix with audit and guard | {spread(t['bunny_meshfix'], '.2f')} | "
        f"{cpu('bunny_meshfix')} | {ratio('bunny_meshfix', 'anchor')} | {cpu_ratio('bunny_meshfix', 'anchor')} "
        "| anchor (target <= 1.2) |",
        f"| StanfordBunny.ply | ... the first and the last round in this process (pymeshfix alone drifts in a long "
        f"process; repair=meshfix runs it in a child process per session) | anchor {t['anchor'][0]:.2f} -> "
        f"{t['anchor'][-1]:.2f}; repair=meshfix {t['bunny_meshfix'][0]:.2f} -> {t['bunny_meshfix'][-1]:.2f} | - | - "
        "| - | - |",
        f"| StanfordBunny.ply | ... of which the audit and guard | {spread(parts['bunny_audit'], '.2f')} | - | "
        f"{share('bunny_audit', 'bunny_backend')} | - | its backend (target <= 0.2) |",
        f"| StanfordBunny.ply | pymeshfix alone, in a fresh process (as a run) | {spread(t['fresh_bunny_anchor'], '.2f')} "
        f"| {cpu('fresh_bunny_anchor')} | 1.00 | 1.00 | anchor in a fresh process |",
        f"| StanfordBunny.ply | repair=meshfix, in a fresh process (as a run) | "
        f"{spread(t['fresh_bunny_scanreg'], '.2f')} | {cpu('fresh_bunny_scanreg')} | "
        f"{ratio('fresh_bunny_scanreg', 'fresh_bunny_anchor')} | {cpu_ratio('fresh_bunny_scanreg', 'fresh_bunny_anchor')} "
        "| anchor in a fresh process (target <= 1.2) |",
        f"| StanfordBunny.ply | ... repair=meshfix minus the anchor, the same round (the overhead in seconds: steadier "
        f"than the ratio across the machine's spells, in which pymeshfix's own time swings more) | "
        f"{spread([a - b for a, b in zip(t['fresh_bunny_scanreg'], t['fresh_bunny_anchor'])], '.2f')} | "
        f"{spread([a - b for a, b in zip(CPU['fresh_bunny_scanreg'], CPU['fresh_bunny_anchor'])], '.2f')} | - | - "
        "| anchor in a fresh process |",
        f"| StanfordBunny.ply | pymeshfix alone on the renumbered copy that repair=meshfix hands to MeshFix "
        f"(geometry.locality_ordered: the bunny's vertices are scattered through its file; the renumbering timed), "
        f"in a fresh process | {spread(t['fresh_bunny_ordered'], '.2f')} | {cpu('fresh_bunny_ordered')} | "
        f"{ratio('fresh_bunny_ordered', 'fresh_bunny_anchor')} | "
        f"{cpu_ratio('fresh_bunny_ordered', 'fresh_bunny_anchor')} | anchor in a fresh process |",
        f"| StanfordBunny.ply | ... repair=meshfix on it | - | - | "
        f"{ratio('fresh_bunny_scanreg', 'fresh_bunny_ordered')} "
        f"| {cpu_ratio('fresh_bunny_scanreg', 'fresh_bunny_ordered')} | pymeshfix alone on the renumbered copy |",
        f"| StanfordBunny.ply | repair=meshfix remove_slivers=false (the audit and guard on pymeshfix's work alone, "
        f"without the paper's sliver collapse, which pymeshfix does not do), in a fresh process | "
        f"{spread(t['fresh_bunny_noslivers'], '.2f')} | {cpu('fresh_bunny_noslivers')} | "
        f"{ratio('fresh_bunny_noslivers', 'fresh_bunny_anchor')} | "
        f"{cpu_ratio('fresh_bunny_noslivers', 'fresh_bunny_anchor')} | anchor in a fresh process |",
        f"| StanfordBunny.ply | scanreg repair=meshlab with audit and guard | {spread(t['bunny_meshlab'], '.2f')} | "
        f"{cpu('bunny_meshlab')} | {ratio('bunny_meshlab', 'bunny_meshfix')} | "
        f"{cpu_ratio('bunny_meshlab', 'bunny_meshfix')} | repair=meshfix (target <= 3) |",
    ]
    if bun000 is not None:
        rows += [
            f"| bun000.ply (80k faces, raw scan) | scanreg default repair (meshfix, open_border=auto) | "
            f"{spread(t['bun000_meshfix'], '.2f')} | {cpu('bun000_meshfix')} | - | - | target < 2 s |",
            f"| bun000.ply | ... of which the audit and guard | {spread(parts['bun000_audit'], '.2f')} | - | "
            f"{share('bun000_audit', 'bun000_backend')} | - | its backend |",
            f"| bun000.ply | scanreg repair=meshlab | {spread(t['bun000_meshlab'], '.2f')} | {cpu('bun000_meshlab')} | "
            f"{ratio('bun000_meshlab', 'bun000_meshfix')} | {cpu_ratio('bun000_meshlab', 'bun000_meshfix')} "
            "| repair=meshfix (target <= 3) |",
            f"| bun000.ply | cache hit (repair.cache=on) | {spread(t['hit'], '.3f')} | {cpu('hit', '.3f')} | "
            f"{ratio('hit', 'bun000_meshfix')} | {cpu_ratio('hit', 'bun000_meshfix')} | the default repair |",
            f"| bun000.ply | default repair in a fresh process (as a run) | {spread(t['fresh'], '.2f')} | "
            f"{cpu('fresh')} | - | - | target < 2 s |",
        ]
    else:
        rows.append("| bun000.ply | (not run: ../shared/data absent) | - | - | - | - | - |")
    head = [f"Repair speed: median (min-max) of {args.repeat} interleaved rounds, one process after a warm-up "
            "(imports excluded), 2 shared cores; each repair on a fresh copy of its input; the anchor and "
            "repair=meshfix swap places every other round; wall and process CPU time (user + system) of the same "
            "calls; the audit's share from the stage's own wall-time metrics; the bunny's fresh-process rows: "
            f"{args.fresh_repeat} rounds of their own (a new process each), after the others", ""]
    text = "\n".join(head + rows)
    print(text)
    if args.out:
        Path(args.out).write_text("# Repair speed (`experiments/benchmarks/repair_speed.py --repeat "
                                  f"{args.repeat} --fresh-repeat {args.fresh_repeat}`)\n\n{text}\n")


if __name__ == "__main__":
    main()
