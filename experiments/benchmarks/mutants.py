"""Mutation testing of the core maths (issue #38): cosmic-ray over the pure maths functions, each module against
the fast tests that exercise it.

    ./run mutants                      every module of mutants.toml, then the report (experiments/benchmarks/mutants.md)
    ./run mutants --module ransac ...  only these modules (the others' last results stay in the report)
    ./run mutants --survivors [--module ...]  only the last run's survivors again, with the current tests
    ./run mutants --list               count the mutants per module, run nothing
    ./run mutants --report-only        rewrite the report from the last results (after editing explanations)

A mutant is a copy of the code with one small change (``+`` for ``-``, ``<`` for ``<=``, a number plus or minus
one, a condition negated, ...); it is *killed* when the module's tests fail on it, and *survives* when they pass.
What is mutated, with which tests and which operators, is in ``mutants.toml`` beside this file, and so are the
explanations of the mutants that survive (equivalent mutants, or why a survivor is acceptable): the report lists
every survivor with its explanation and marks those without one.

The mutants are made in a copy of the working tree (``outputs/mutants/tree``; the files git tracks, and new ones it
does not ignore), never in the project's own files: the tests there import ``scanreg`` from the copy (a
``PYTHONPATH`` entry ahead of the editable install), so the project can be edited while a run goes on. cosmic-ray
(pinned in constraints.txt, the ``mutants`` extra, which ``./run mutants`` installs) writes each mutant into the
copy, runs the module's tests in a subprocess and puts the file back. One test process at a time, on one thread
(OpenMP and BLAS): the run shares the machine. Not part of ``./run test`` or CI.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import time
import tomllib
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
CONFIG = HERE / "mutants.toml"
REPORT = HERE / "mutants.md"
WORK = ROOT / "outputs" / "mutants"
TREE = WORK / "tree"

# pytest in each mutant's subprocess: stop at the first failure (the mutant is killed), no cache written into the
# copy, and without the third-party plugins the environment brings (Hypothesis, Hydra, Dash, AnyIO, platformdirs),
# which the selected tests do not use and which cost about 2 s of start-up per mutant
PYTEST = ["-m", "pytest", "-x", "-q", "-m", "not slow", "-p", "no:cacheprovider", "-p", "no:hypothesispytest",
          "-p", "no:hydra_pytest", "-p", "no:dash", "-p", "no:anyio", "-p", "no:platformdirs"]


def load_config() -> dict:
    cfg = tomllib.loads(CONFIG.read_text())
    names = [m["name"] for m in cfg["module"]]
    if len(set(names)) != len(names):
        raise SystemExit(f"mutants.toml: module names repeat: {names}")
    return cfg


# ------------------------------------------------------------------------------------------------- the copy


def copy_tree() -> None:
    """The working tree's files (tracked, and untracked but not ignored) into TREE, and the links that let
    ``import scanreg`` find the copy as the installed package maps it (pipeline/ -> scanreg, stages/ ->
    scanreg.stages, conf/ -> scanreg.conf)."""
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, check=True).stdout.decode().split("\0")
    if TREE.exists():
        shutil.rmtree(TREE)
    for rel in filter(None, files):
        src = ROOT / rel
        if src.is_file():  # a tracked file deleted in the working tree is left out
            (TREE / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, TREE / rel)
    (TREE / "pipeline" / "stages").symlink_to("../stages")
    (TREE / "pipeline" / "conf").symlink_to("../conf")
    (TREE / "_import").mkdir()
    (TREE / "_import" / "scanreg").symlink_to("../pipeline")


def env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join(filter(None, [str(TREE / "_import"), e.get("PYTHONPATH")]))
    e["SCANREG_SHARED_DATA"] = e.get("SCANREG_SHARED_DATA", str(ROOT.parent / "shared" / "data"))
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        e[v] = "1"
    return e


def check_imports_from_copy() -> None:
    code = "import scanreg, scanreg.stages, scanreg.conf; print(scanreg.__path__[0]); print(scanreg.stages.__path__[0])"
    out = subprocess.run([sys.executable, "-c", code], cwd=TREE, env=env(), capture_output=True, text=True,
                         check=True).stdout.split()
    if not all(Path(p).resolve().is_relative_to(TREE.resolve()) for p in out):
        raise SystemExit(f"the copy's scanreg is not the one imported ({out}): mutants would not be tested")


# ----------------------------------------------------------------------------------------- scope and sessions


def definitions(path: Path) -> list[tuple[str, int, int]]:
    """Every function and class of a module: ``(qualified name, first line, last line)``."""
    out = []

    def walk(node, prefix):
        for ch in ast.iter_child_nodes(node):
            if isinstance(ch, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                out.append((prefix + ch.name, ch.lineno, ch.end_lineno))
                walk(ch, prefix + ch.name + ".")
            else:
                walk(ch, prefix)

    walk(ast.parse(path.read_text()), "")
    return out


def unexecuted_spans(path: Path) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """The source spans where a mutant changes no computation: annotations (never evaluated: the modules use
    ``from __future__ import annotations``), f-strings (message text), the exception of a ``raise`` (its
    message; the condition that raises stays mutated) and ``print`` calls (logging). ``((line, column), (end
    line, end column))``, columns from 0 as cosmic-ray's positions."""
    spans = []

    def add(node):
        if node is not None:
            spans.append(((node.lineno, node.col_offset), (node.end_lineno, node.end_col_offset)))

    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            add(node.returns)
        elif isinstance(node, ast.arg):
            add(node.annotation)
        elif isinstance(node, ast.AnnAssign):
            add(node.annotation)
        elif isinstance(node, ast.JoinedStr):
            add(node)
        elif isinstance(node, ast.Raise):
            add(node.exc)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
            add(node)
    return spans


def unexecuted(spans, pos: tuple[int, int]) -> bool:
    return any(a <= tuple(pos) < b for a, b in spans)


def owner(defs, line: int) -> str | None:
    """The innermost function or class holding ``line``."""
    inside = [d for d in defs if d[1] <= line <= d[2]]
    return max(inside, key=lambda d: d[1])[0] if inside else None


def in_scope(qualname: str | None, functions: list[str]) -> bool:
    """Whether a mutant in ``qualname`` is mutated: a listed function, a method of a listed class, or a function
    nested in either."""
    return qualname is not None and any(qualname == f or qualname.startswith(f + ".") for f in functions)


def test_command(module: dict) -> str:
    return shlex.join([sys.executable, *PYTEST, *module["tests"]])


def cosmic_config(module: dict, timeout: float) -> str:
    q = json.dumps  # TOML basic strings are JSON strings
    return (f"[cosmic-ray]\nmodule-path = {q(module['path'])}\ntimeout = {timeout}\nexcluded-modules = []\n"
            f"test-command = {q(test_command(module))}\n\n[cosmic-ray.distributor]\nname = \"local\"\n")


def cosmic_ray(*args: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("cosmic-ray")
    return subprocess.run([str(exe), *args], cwd=TREE, env=env(), capture_output=True, text=True)


def init_session(module: dict, cfg: dict, db: Path, cfg_file: Path) -> int:
    """cosmic-ray's work items for the module, every one outside the listed functions or of an operator not kept
    marked as skipped (as cosmic-ray's own filters do), and so is every one in an annotation or a message
    (:func:`unexecuted_spans`). Returns the number of mutants left to run."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    r = cosmic_ray("init", str(cfg_file), str(db), "--force")
    if r.returncode:
        raise SystemExit(f"cosmic-ray init failed for {module['name']}:\n{r.stderr}")
    keep = re.compile("|".join(f"(?:{o})" for o in cfg["run"]["operators"]))
    defs = definitions(TREE / module["path"])
    missing = [f for f in module["functions"] if not any(d[0] == f for d in defs)]
    if missing:
        raise SystemExit(f"mutants.toml: {module['path']} has no {', '.join(missing)}")
    spans = unexecuted_spans(TREE / module["path"])
    left = 0
    with use_db(str(db), WorkDB.Mode.open) as work_db:
        skip = []
        for item in work_db.pending_work_items:
            (m,) = item.mutations
            if (keep.fullmatch(m.operator_name) and in_scope(owner(defs, m.start_pos[0]), module["functions"])
                    and not unexecuted(spans, m.start_pos)):
                left += 1
            else:
                skip.append(item.job_id)
        work_db.set_multiple_results(skip, WorkResult(output="outside the scope of mutants.toml",
                                                      worker_outcome=WorkerOutcome.SKIPPED))
    return left


def baseline(module: dict, cfg: dict) -> tuple[float, float]:
    """The module's tests on the unmutated copy: they must pass (else every mutant would count as killed). Returns
    their time and the timeout it sets (a mutant that loops forever is killed by it)."""
    t0 = time.monotonic()
    base = subprocess.run(shlex.split(test_command(module)), cwd=TREE, env=env(), capture_output=True, text=True)
    base_s = time.monotonic() - t0
    if base.returncode:
        raise SystemExit(f"{module['name']}: the tests fail without any mutant:\n{base.stdout[-3000:]}{base.stderr[-2000:]}")
    return base_s, round(max(30.0, cfg["run"]["timeout_factor"] * base_s), 1)


def source_sha(module: dict) -> str:
    return hashlib.sha256((TREE / module["path"]).read_bytes()).hexdigest()[:16]


def run_module(module: dict, cfg: dict, commit: str) -> None:
    name = module["name"]
    db, cfg_file = WORK / f"{name}.sqlite", WORK / f"{name}.cosmic-ray.toml"
    base_s, timeout = baseline(module, cfg)
    cfg_file.write_text(cosmic_config(module, timeout))
    n = init_session(module, cfg, db, cfg_file)
    print(f"mutants: {name}: {n} mutants of {module['path']} (unmutated tests {base_s:.1f} s)", flush=True)
    t0 = time.monotonic()
    r = cosmic_ray("exec", str(cfg_file), str(db))
    if r.returncode:
        raise SystemExit(f"cosmic-ray exec failed for {name}:\n{r.stderr[-3000:]}")
    meta = {"commit": commit, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "seconds": round(time.monotonic() - t0), "baseline_seconds": round(base_s, 1), "timeout": timeout,
            "tests": module["tests"], "path": module["path"], "source_sha": source_sha(module),
            "mutants": results(module, db)}
    (WORK / f"{name}.json").write_text(json.dumps(meta, indent=1) + "\n")


def rerun_survivors(module: dict, cfg: dict, commit: str) -> None:
    """The module's surviving mutants of its last run tested again with the current tests (after tests were
    added to kill them); its killed mutants stay killed (tests are only added). Refused when the module's source
    changed since that run: the mutants are numbered by their place in the file."""
    import sqlite3

    name = module["name"]
    db, meta_file = WORK / f"{name}.sqlite", WORK / f"{name}.json"
    if not (db.exists() and meta_file.exists()):
        raise SystemExit(f"{name}: no run to take the survivors of; run ./run mutants --module {name}")
    meta = json.loads(meta_file.read_text())
    was = meta.get("source_sha") or hashlib.sha256(subprocess.run(
        ["git", "show", f"{meta['commit'].split()[0]}:{module['path']}"], cwd=ROOT, capture_output=True,
        check=True).stdout).hexdigest()[:16]
    if was != source_sha(module):
        raise SystemExit(f"{name}: {module['path']} changed since its last run; run the module again in full")
    base_s, timeout = baseline(module, cfg)
    cfg_file = WORK / f"{name}.cosmic-ray.toml"
    cfg_file.write_text(cosmic_config(module, timeout))
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome

    with use_db(str(db), WorkDB.Mode.open) as work_db:
        again = [item.job_id for item, res in work_db.completed_work_items if res.test_outcome == TestOutcome.SURVIVED]
    with sqlite3.connect(db) as con:  # cosmic-ray runs the work items without a result
        con.executemany("DELETE FROM work_results WHERE job_id = ?", [(j,) for j in again])
    print(f"mutants: {name}: {len(again)} survivors of {module['path']} again (unmutated tests {base_s:.1f} s)",
          flush=True)
    t0 = time.monotonic()
    r = cosmic_ray("exec", str(cfg_file), str(db))
    if r.returncode:
        raise SystemExit(f"cosmic-ray exec failed for {name}:\n{r.stderr[-3000:]}")
    meta.update({"source_sha": was, "mutants": results(module, db), "tests": module["tests"],
                 "seconds": meta["seconds"] + round(time.monotonic() - t0),
                 "survivors_rerun": {"commit": commit, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                                     "mutants": len(again)}})
    meta_file.write_text(json.dumps(meta, indent=1) + "\n")


# ---------------------------------------------------------------------------------------------------- results


def changed_line(diff: str) -> tuple[int, str, str]:
    """``(line number, original, mutated)`` of a one-line mutant's unified diff (lines stripped)."""
    at = line = old = new = None
    for ln in diff.splitlines():
        if ln.startswith("@@"):
            at = int(re.match(r"@@ -(\d+)", ln).group(1))
        elif at is None or ln.startswith(("---", "+++")):
            continue
        elif ln.startswith("-"):
            if old is None:
                old, line = ln[1:].strip(), at
            at += 1
        elif ln.startswith("+"):
            new = ln[1:].strip() if new is None else new
        else:
            at += 1
    return line, old, new


def results(module: dict, db: Path) -> list[dict]:
    """Every mutant run for the module (its session ``db``, the copy's source): operator, function, line,
    original and mutated text, outcome."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    out = []
    with use_db(str(db), WorkDB.Mode.open) as work_db:
        for item, res in work_db.completed_work_items:
            if res.worker_outcome == WorkerOutcome.SKIPPED:
                continue
            (m,) = item.mutations
            rec = {"operator": m.operator_name.removeprefix("core/"), "occurrence": m.occurrence}
            if res.worker_outcome == WorkerOutcome.NORMAL:
                rec["outcome"] = "survived" if res.test_outcome == TestOutcome.SURVIVED else "killed"
                if res.output == "timeout":
                    rec["outcome"] = "timeout"
                rec["line"], rec["original"], rec["mutated"] = changed_line(res.diff)
            else:  # the mutant could not be made or run (cosmic-ray's own failure): not counted
                rec["outcome"] = "incompetent"
                rec["line"], rec["original"], rec["mutated"] = m.start_pos[0], "", ""
            out.append(rec)
    defs = definitions(TREE / module["path"])
    for rec in out:
        rec["function"] = owner(defs, rec["line"]) or "?"
    return sorted(out, key=lambda r: (r["line"], r["operator"], r["occurrence"]))


def explanation(cfg: dict, module: dict, rec: dict) -> dict | None:
    for e in cfg.get("survivor", []):
        if (e["module"] == module["name"] and e["function"] == rec["function"] and e["original"] == rec["original"]
                and e["mutated"] == rec["mutated"]):
            return e
    return None


def write_report(cfg: dict, command: str) -> tuple[int, int]:
    from importlib.metadata import version

    rows, survivors = [], []
    tot = {"mutants": 0, "killed": 0, "survived": 0, "equivalent": 0, "seconds": 0}
    metas = {}
    for module in cfg["module"]:
        meta_file = WORK / f"{module['name']}.json"
        if not meta_file.exists():
            rows.append(f"| {module['name']} | `{module['path']}` | not run | | | | | | |")
            continue
        meta = metas[module["name"]] = json.loads(meta_file.read_text())
        recs = meta["mutants"]
        counted = [r for r in recs if r["outcome"] != "incompetent"]
        killed = sum(r["outcome"] in ("killed", "timeout") for r in counted)
        surv = [r for r in counted if r["outcome"] == "survived"]
        equiv = accepted = 0
        for r in surv:
            e = explanation(cfg, module, r)
            equiv += bool(e and e["kind"] == "equivalent")
            accepted += bool(e and e["kind"] == "accepted")
            survivors.append((module, r, e))
        n = len(counted)
        score = 100.0 * killed / n if n else float("nan")
        adj = 100.0 * killed / (n - equiv) if n - equiv else float("nan")
        timeouts = sum(r["outcome"] == "timeout" for r in counted)
        rows.append(f"| {module['name']} | `{module['path']}` | {n} | {killed}"
                    f"{f' ({timeouts} by timeout)' if timeouts else ''} | {len(surv)} | {equiv} | {accepted} | "
                    f"{score:.1f} % | {adj:.1f} % |")
        tot["accepted"] = tot.get("accepted", 0) + accepted
        tot["mutants"] += n
        tot["killed"] += killed
        tot["survived"] += len(surv)
        tot["equivalent"] += equiv
        tot["seconds"] += meta["seconds"]
    n, k, eq = tot["mutants"], tot["killed"], tot["equivalent"]
    rows.append(f"| **all** | | **{n}** | **{k}** | **{tot['survived']}** | **{eq}** | **{tot.get('accepted', 0)}** | "
                f"**{100.0 * k / max(n, 1):.1f} %** | **{100.0 * k / max(n - eq, 1):.1f} %** |")
    commits = sorted({m["commit"] for m in metas.values()})
    dates = sorted({m["date"] for m in metas.values()})
    ops = "\n".join(f"- `{o}`" for o in cfg["run"]["operators"])
    lines = [
        "# Mutation testing of the core maths",
        "",
        f"Produced by `{command}` (experiments/benchmarks/mutants.py; what is mutated, with which tests, and the "
        "survivors' explanations: mutants.toml beside it). Not part of `./run test` or CI.",
        "",
        f"- date: {', '.join(dates)}",
        f"- commit: {', '.join(commits)}",
        *([f"- survivors tested again (`--survivors`, after tests were added): "
           + "; ".join(f"{n} at {m['survivors_rerun']['commit']} ({m['survivors_rerun']['mutants']} mutants, "
                       f"{m['survivors_rerun']['date']})" for n, m in metas.items() if "survivors_rerun" in m)]
          if any("survivors_rerun" in m for m in metas.values()) else []),
        f"- tool: cosmic-ray {version('cosmic-ray')}, Python {platform.python_version()}, pytest {version('pytest')}",
        f"- machine: {os.cpu_count()} cores; one test process at a time, one thread (OMP/BLAS), `nice -n 19`",
        f"- time: {tot['seconds'] / 60:.0f} min of mutants in all (full runs and survivor reruns; each module's "
        "unmutated tests first), on a machine shared with other work",
        "",
        "A mutant is killed when its module's tests fail on it (or run past the timeout, 3x the unmutated tests' "
        "time and at least 30 s). Score = killed / mutants; the last column leaves out the survivors explained "
        "below as equivalent (no input can tell them from the code). The other survivors are *accepted* (an input "
        "could tell them apart, and the explanation says why no test needs to: mostly ties of floating-point "
        "values at a threshold, and efficiency-only changes that valid() masks) or a *gap* (a test should kill "
        "it and does not yet).",
        "",
        "| module | file | mutants | killed | survived | of which equivalent | accepted | score | score without equivalents |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "## What is mutated",
        "",
        "Only the listed functions (a class: its methods; nested functions included); I/O, logging and parameter "
        "checks are left out, and so are annotations, f-strings, the exception of a `raise` (its message; the "
        "condition that raises is mutated) and `print` calls. cosmic-ray's operators, those kept:",
        "",
        ops,
        "",
        "| module | functions | tests run on each mutant | unmutated tests [s] |",
        "|---|---|---|---|",
    ]
    for module in cfg["module"]:
        meta = metas.get(module["name"], {})
        lines.append(f"| {module['name']} | {', '.join(f'`{f}`' for f in module['functions'])} | "
                     f"{'<br>'.join(f'`{t}`' for t in module['tests'])} | {meta.get('baseline_seconds', '')} |")
    if cfg.get("finding"):
        lines += ["", "## Findings", "", "What the mutants showed beyond the tests (mutants.toml's `finding` entries):", ""]
        lines += [f"- {f['text']}" for f in cfg["finding"]]
    lines += ["", "## Surviving mutants", ""]
    if not survivors:
        lines.append("None.")
    unexplained = 0
    for module, r, e in survivors:
        head = (f"- **{module['name']}** `{r['function']}` line {r['line']} ({r['operator']}): "
                f"`{r['original']}` -> `{r['mutated']}`")
        if e is None:
            unexplained += 1
            lines.append(head + ". **Not explained.**")
        else:
            lines.append(head + f". *{e['kind']}*: {e['why']}")
    REPORT.write_text("\n".join(lines) + "\n")
    return unexplained, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--module", nargs="+", help="only these modules (names in mutants.toml), in this order")
    ap.add_argument("--list", action="store_true", help="count the mutants per module and stop")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the last results")
    ap.add_argument("--survivors", action="store_true",
                    help="test only the last run's survivors again, with the current tests (after adding tests)")
    args = ap.parse_args()
    cfg = load_config()
    known = {m["name"] for m in cfg["module"]}
    if args.module and not set(args.module) <= known:
        raise SystemExit(f"unknown module(s) {sorted(set(args.module) - known)}; mutants.toml has {sorted(known)}")
    by_name = {m["name"]: m for m in cfg["module"]}
    chosen = [by_name[n] for n in dict.fromkeys(args.module)] if args.module else cfg["module"]  # in the order given
    WORK.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
        commit += " (with uncommitted changes)" if dirty else ""
        copy_tree()
        check_imports_from_copy()
        if args.list:
            for module in chosen:
                cfg_file = WORK / f"{module['name']}.list.toml"
                cfg_file.write_text(cosmic_config(module, 30.0))
                n = init_session(module, cfg, WORK / f"{module['name']}.list.sqlite", cfg_file)
                print(f"{module['name']}: {n} mutants of {module['path']}")
            return
        for module in chosen:
            (rerun_survivors if args.survivors else run_module)(module, cfg, commit)
    unexplained, n = write_report(cfg, "./run mutants")
    print(f"mutants: report in {REPORT.relative_to(ROOT)} ({n} mutants, {unexplained} survivors not explained)")


if __name__ == "__main__":
    main()
