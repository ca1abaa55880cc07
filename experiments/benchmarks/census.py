"""Benchmark: the defect census (issue #34) against the default repair of the same mesh, in one run, and what the
repair changes on each mesh beside what the census finds there.

    .venv/bin/python experiments/benchmarks/census.py [--repeat 5] [--repair-repeat 3]
        [--out experiments/benchmarks/census.md]

Meshes: pymeshfix's ``StanfordBunny.ply`` (a closed model with 70 holes, non-manifold edges, folds); the 10 raw
Stanford range scans (``../shared/data/stanford_bunny``, read as meshes: pymeshlab triangulates the range grid);
``../shared/data/meshlab_defects``; the dental case's two meshes (``data=dental``: the CT dentition of the
maxilla, 15 separate teeth, and the synthetic cast scan with its defects). Meshes under ``../shared/data`` are
skipped with a message when the folder is absent.

Per mesh, in rounds (each round: every mesh's census, then every mesh's repair, so that a slow spell of the
shared machine hits both): the census (:func:`scanreg.mesh.census.census`) ``--repeat`` times, its median wall
time and CPU time; the default repair (``scanreg.build_stage("repair", "meshfix", cache="off")``: MeshFix in a
child process, the audit and the guard, no override but the cache) ``--repair-repeat`` times on a fresh copy,
its median wall time; the census without its broad phase as often, CPU time. The census's counts per mesh; the
repair's audit before and after. The exact self-intersection test on the census's pairs only
(:meth:`~scanreg.mesh.census.Census.pairs_to_test`) against the full test of the mesh, once per round each, CPU
time.

Where the repair works: the input faces that are not in the output (their corners matched to the output's
vertices within 1e-6 of the diagonal, :func:`where`) are the faces it changed; the table gives their share of the mesh
and how many of them lie within the census's defect faces grown by 0, 1, 2 and 4 rings
(:meth:`~scanreg.mesh.census.Census.defect_faces`), and the share of the mesh those rings cover: what a repair
of the defective regions only would have to work on.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import scanreg
from scanreg.geometry import Mesh, bbox_diagonal
from scanreg.io import read_mesh, shared_data_dir
from scanreg.mesh.census import census
from scanreg.mesh.intersect import _pair_hits, _welded, self_intersections
from scanreg.types import RunContext

RINGS = (0, 1, 2, 4)
ANALYSIS = "## Analysis"
"""The heading of the part of the report written by hand; a new run keeps it (its numbers are the run's it
names)."""
TOL = 1e-6
"""A vertex of the input counts as kept when the repair's output has one this close (share of the diagonal)."""
COUNTS = ("components", "small_components", "boundary_loops", "holes", "outer_borders", "non_manifold_edges",
          "non_manifold_vertices", "inconsistent_orientation_edges", "unreferenced_vertices", "duplicate_vertices",
          "duplicate_faces", "degenerate_faces", "sliver_faces", "intersection_candidate_pairs",
          "intersection_candidate_faces", "fold_vertices")
SHORT = {"components": "parts", "small_components": "small", "boundary_loops": "loops", "holes": "holes",
         "outer_borders": "outer", "non_manifold_edges": "nm e", "non_manifold_vertices": "nm v",
         "inconsistent_orientation_edges": "flip e", "unreferenced_vertices": "unref v",
         "duplicate_vertices": "dup v", "duplicate_faces": "dup f", "degenerate_faces": "degen",
         "sliver_faces": "sliver", "intersection_candidate_pairs": "SI pairs", "intersection_candidate_faces":
         "SI faces", "fold_vertices": "fold v"}
AUDIT = ("components", "boundary_loops", "non_manifold_edges", "non_manifold_vertices",
         "inconsistent_orientation_edges", "degenerate_faces", "sliver_faces", "self_intersecting_faces",
         "unreferenced_vertices")


def meshes() -> list[tuple[str, Mesh]]:
    out = [("pymeshfix StanfordBunny", read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply"))]
    data = shared_data_dir()
    for folder, label in (("stanford_bunny", "raw"), ("meshlab_defects", "meshlab")):
        if not (data / folder).is_dir():
            print(f"note: {data / folder} absent: skipped")
        for p in sorted((data / folder).glob("*.ply")):
            out.append((f"{label} {p.stem}", read_mesh(str(p))))
    if (data / "open_full_jaw_p26").is_dir():
        with contextlib.redirect_stdout(io.StringIO()):
            prob = scanreg.build_stage("data", "dental").load(RunContext(seed=0, run_dir=None))
        out += [("dental CT dentition", prob.target), ("dental cast scan", prob.source)]
    else:
        print(f"note: {data / 'open_full_jaw_p26'} absent: the dental case skipped")
    return out


def fresh(mesh: Mesh) -> Mesh:
    """A copy with new arrays: nothing the audit remembered about ``mesh`` applies to it."""
    return Mesh(mesh.vertices.copy(), mesh.faces.copy(), mesh.source)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="census runs per mesh and round")
    ap.add_argument("--repair-repeat", type=int, default=3, help="rounds (one repair per mesh each)")
    ap.add_argument("--out", default=None, help="also write the report to this markdown file")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    todo = meshes()
    repair = scanreg.build_stage("repair", "meshfix", cache="off")
    ctx = RunContext(seed=0, run_dir=None)
    with contextlib.redirect_stdout(io.StringIO()):  # warm-up: imports, the first fork
        repair.repair(read_mesh("pkg:pymeshlab/tests/sample_meshes/cow.obj"), ctx)
    census(*(lambda m: (m.vertices, m.faces))(todo[0][1]))
    rows = {name: {"census_wall": [], "census_cpu": [], "repair_wall": [], "exact_pairs_cpu": [],
                   "exact_full_cpu": [], "topology_cpu": []} for name, _ in todo}
    for _ in range(args.repair_repeat):
        for name, m in todo:
            measure(m, rows[name], args.repeat)
        for name, m in todo:
            inp = fresh(m)
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                out = repair.repair(inp, ctx)
            rows[name]["repair_wall"].append(time.perf_counter() - t0)
            rows[name]["repaired"] = out
    load1 = os.getloadavg()[0]
    lines = report(todo, rows, args, load0, load1)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        old = Path(args.out).read_text() if Path(args.out).exists() else ""
        if ANALYSIS in old:  # the analysis written from an earlier run's tables stays, after the new tables
            text += "\n" + old[old.index(ANALYSIS):]
        Path(args.out).write_text(text)
        Path(args.out).with_suffix(".json").write_text(json.dumps(
            {name: {"census_wall_s": r["census_wall"], "census_cpu_s": r["census_cpu"],
                    "exact_pairs_cpu_s": r["exact_pairs_cpu"], "exact_full_cpu_s": r["exact_full_cpu"],
                    "topology_cpu_s": r["topology_cpu"],
                    "exact": list(r["exact"]),
                    "repair_wall_s": r["repair_wall"], "counts": r["census"].counts(),
                    "repair": {k: v for k, v in r["repaired"].metrics.items() if isinstance(v, (int, float))},
                    "where": r["where"]} for name, r in rows.items()}, indent=1) + "\n")


def measure(m: Mesh, r: dict, repeat: int) -> None:
    """One round's census of ``m`` (``repeat`` times) and exact tests (on the census's pairs, in full), into
    ``r``."""
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        c = census(m.vertices, m.faces)
        r["census_wall"].append(time.perf_counter() - t0)
        r["census_cpu"].append(time.process_time() - c0)
    r["census"] = c
    for _ in range(repeat):
        c0 = time.process_time()
        census(m.vertices, m.faces, broad_phase=False)
        r["topology_cpu"].append(time.process_time() - c0)
    t0 = time.process_time()
    pairs, hits = exact_on(m, c)
    r["exact_pairs_cpu"].append(time.process_time() - t0)
    t0 = time.process_time()
    full = np.flatnonzero(self_intersections(m.vertices, m.faces).mask)
    r["exact_full_cpu"].append(time.process_time() - t0)
    r["exact"] = (len(pairs), len(hits), len(full), set(hits.tolist()) == set(full.tolist()))


def exact_on(m: Mesh, c) -> tuple[np.ndarray, np.ndarray]:
    """The exact self-intersection test (:mod:`scanreg.mesh.intersect`'s pair test, on the welded mesh) of the
    census's pairs only (:meth:`~scanreg.mesh.census.Census.pairs_to_test`): the pairs and the faces that
    intersect."""
    vw, fw, _ = _welded(m.vertices, m.faces)
    pairs = c.pairs_to_test(m.faces)
    hit = _pair_hits(vw[fw], fw, pairs[:, 0], pairs[:, 1]) if len(pairs) else np.zeros(0, bool)
    return pairs, np.unique(pairs[hit])


def where(m: Mesh, c, out: Mesh) -> dict:
    """The faces the repair changed (input faces not in its output) against the census's defect faces. A vertex
    is kept when the output has one within ``TOL`` of the input's bounding-box diagonal (MeshFix moves about
    two thirds of the pymeshfix bunny's vertices by one float32 rounding step, 2e-7 of 150 units, and nothing
    else there); a face is kept when its three kept vertices make an output face."""
    from scipy.spatial import cKDTree

    d, near = cKDTree(out.vertices).query(m.vertices)
    ok = d <= TOL * bbox_diagonal(m.vertices)
    n = len(out.vertices)

    def keys(f: np.ndarray) -> np.ndarray:
        s = np.sort(f, axis=1)
        return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]

    kept = ok[m.faces].all(axis=1) & np.isin(keys(near[m.faces]), keys(out.faces))
    gone = ~kept
    res = {"changed": int(gone.sum()), "moved_vertices": int((d > 0).sum())}
    # the defect faces without the broad phase's classes (what an exact test of those would leave at most)
    none = np.zeros(0, np.int64)
    topo = replace(c, intersection_candidates=none.reshape(0, 2), fold_vertices=none)
    res["topology_r2"] = len(topo.defect_faces(margin_rings=2, faces=m.faces))
    for k in RINGS:
        mask = np.zeros(len(m.faces), bool)
        mask[c.defect_faces(margin_rings=k, faces=m.faces)] = True
        res[f"defect_r{k}"] = int(mask.sum())
        res[f"covered_r{k}"] = int((gone & mask).sum())
    return res


def report(todo, rows, args, load0: float, load1: float) -> list[str]:
    lines = [
        "# The defect census against the default repair (issue #34)",
        "",
        "Made by `experiments/benchmarks/census.py` (its docstring says how); "
        f"census: median of {args.repeat * args.repair_repeat} runs in {args.repair_repeat} rounds, "
        f"repair (`repair=meshfix`, defaults, cache off): median of {args.repair_repeat}, interleaved with the "
        f"census by rounds. Load average when it started {load0:.1f}, when it ended {load1:.1f} (2 cores, shared).",
        "",
        "## Time",
        "",
        "Without broad phase: `census(..., broad_phase=False)`, the topology and the faces' shapes only (no "
        "self-intersection candidates or fold vertices), CPU.",
        "",
        "| mesh | faces | census wall (ms) | census CPU (ms) | CPU per 100k faces (ms) | without broad phase, CPU "
        "(ms) | repair wall (s) | census / repair |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, m in todo:
        r = rows[name]
        cw, cc, rw = (float(np.median(r[k])) for k in ("census_wall", "census_cpu", "repair_wall"))
        lines.append(f"| {name} | {len(m.faces)} | {1e3 * cw:.0f} | {1e3 * cc:.0f} | {1e8 * cc / len(m.faces):.0f} "
                     f"| {1e3 * np.median(r['topology_cpu']):.0f} | {rw:.2f} | {cw / rw:.1%} |")
    lines += ["", "## The exact self-intersection test on the census's pairs", "",
              "The exact test (`scanreg.mesh.intersect`) run on the census's pairs only (`Census.pairs_to_test`: "
              "the candidates and every pair of faces at a vertex whose fan is not a graph) beside the full test "
              "of the whole mesh (`self_intersections`, what the audit runs on the input), CPU time, median of the "
              "rounds; same: "
              "both find the same self-intersecting faces.", "",
              "| mesh | pairs tested | faces found | full test: faces | same | on the pairs (ms) | full test (ms) |",
              "| --- | ---: | ---: | ---: | --- | ---: | ---: |"]
    for name, _ in todo:
        r = rows[name]
        n_pairs, n_hit, n_full, same = r["exact"]
        lines.append(f"| {name} | {n_pairs} | {n_hit} | {n_full} | {'yes' if same else 'NO'} | "
                     f"{1e3 * np.median(r['exact_pairs_cpu']):.0f} | {1e3 * np.median(r['exact_full_cpu']):.0f} |")
    lines += ["", "## Census counts", "",
              "Columns: " + "; ".join(f"{v}: `{k}`" for k, v in SHORT.items()) + ". SI pairs/faces: the "
              "broad phase's self-intersection candidates (faces sharing no vertex; the exact test decides); fold v: "
              "vertices whose fan is not a graph (pairs sharing them go to the exact test).", "",
              "| mesh | " + " | ".join(SHORT[k] for k in COUNTS) + " |",
              "| --- | " + " | ".join("---:" for _ in COUNTS) + " |"]
    for name, _ in todo:
        c = rows[name]["census"].counts()
        lines.append(f"| {name} | " + " | ".join(str(c[k]) for k in COUNTS) + " |")
    lines += ["", "## What the repair changes, and where", "",
              "The repair's own audit, before -> after (`before_*`, `after_*`; SI: `self_intersecting_faces`, "
              "exact). changed: input faces not in the output (a face counts as changed when any corner moved by "
              "more than 1e-6 of the diagonal or it was removed); moved v: input vertices not found exactly (any "
              "distance) in the output; in r k: of those, how many lie within the census's defect faces grown by k "
              "rings; area r k: the share of the mesh's faces in the defect faces grown by k rings; topology r2: "
              "the same without the self-intersection candidates and fold vertices (the broad phase's classes, "
              "which an exact test of their pairs would settle).", "",
              "| mesh | " + " | ".join(a.replace("_", " ") for a in AUDIT) + " |",
              "| --- | " + " | ".join("---" for _ in AUDIT) + " |"]
    for name, m in todo:
        mt = rows[name]["repaired"].metrics
        cells = [f"{mt.get('before_' + k, float('nan')):g} -> {mt.get('after_' + k, float('nan')):g}" for k in AUDIT]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "| mesh | moved v | changed | " + " | ".join(f"in r{k}" for k in RINGS) + " | "
              + " | ".join(f"area r{k}" for k in RINGS) + " | topology r2 |",
              "| --- | ---: | ---: | " + " | ".join("---:" for _ in RINGS) + " | "
              + " | ".join("---:" for _ in RINGS) + " | ---: |"]
    for name, m in todo:
        r = rows[name]
        w = where(m, r["census"], r["repaired"].mesh)
        r["where"] = w
        n = len(m.faces)
        ch = w["changed"]
        lines.append(f"| {name} | {w['moved_vertices']} | {ch} ({ch / n:.2%}) | "
                     + " | ".join(f"{w[f'covered_r{k}'] / max(ch, 1):.1%}" for k in RINGS) + " | "
                     + " | ".join(f"{w[f'defect_r{k}'] / n:.2%}" for k in RINGS) + f" | {w['topology_r2'] / n:.2%} |")
    return lines


if __name__ == "__main__":
    main()
