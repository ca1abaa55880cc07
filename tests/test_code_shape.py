"""The shape of the code (issue #32's rules): few modules at the top of the package, no oversized module or
function, process machinery in one module, comments that say what and why rather than how fast."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for d in ("pipeline", "stages") for p in (ROOT / d).rglob("*.py"))

MAX_TOP_MODULES = 6
MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 100
PROCESS_MODULE = ROOT / "pipeline" / "process.py"
MAX_TIMING_NARRATIONS = 5


def test_few_modules_directly_under_the_package():
    top = sorted(p.name for p in (ROOT / "pipeline").glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, f"{len(top)} modules directly under pipeline/: {top}"


def test_no_module_is_too_long():
    long = {str(p.relative_to(ROOT)): n for p in SOURCES if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def long_functions(text: str) -> dict[str, int]:
    """The functions and methods of a module's source that span more than the limit (docstring included)."""
    out = {}
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = node.end_lineno - node.lineno + 1
            if n > MAX_FUNCTION_LINES:
                out[node.name] = n
    return out


def test_no_function_is_too_long():
    long = {f"{p.relative_to(ROOT)}:{name}": n for p in SOURCES for name, n in long_functions(p.read_text()).items()}
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def test_the_function_rule_is_not_vacuous():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES + 1))
    assert long_functions(f"def f():\n{body}\n") == {"f": MAX_FUNCTION_LINES + 2}


PROCESS_CALLS = re.compile(r"\bos\.fork\b|register_at_fork|\bimport ctypes\b|\bctypes\.|mallopt|malloc_trim|os\.pipe\(")


def test_process_machinery_lives_in_one_module():
    """Forks, pipes, at-fork hooks, ctypes and malloc calls only in scanreg.process: the geometry, mesh and stage
    code call it as plain functions."""
    found = {str(p.relative_to(ROOT)) for p in SOURCES if p != PROCESS_MODULE and PROCESS_CALLS.search(p.read_text())}
    assert not found, f"process machinery outside pipeline/process.py: {sorted(found)}"
    assert PROCESS_CALLS.search(PROCESS_MODULE.read_text())


TIMING = re.compile(r"\b\d+(\.\d+)?\s*(ms|s)\b(?![\w/])|\b\d+(\.\d+)?x (faster|slower)|faster than|-> \d+(\.\d+)? ?m?s\b")


def comments_and_docstrings(text: str) -> list[str]:
    """A module's comments and docstrings."""
    out = [m.group(0) for m in re.finditer(r"#.*", text)]
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                out.append(doc)
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            out.append(node.value.value)  # attribute docstrings
    return out


def test_comments_say_what_and_why_not_how_fast():
    """Timings and history belong in experiments/benchmarks/*.md and commit messages; a few comments may still
    give the measurement behind a design decision."""
    hits = [f"{p.relative_to(ROOT)}: {TIMING.search(c).group(0)!r}" for p in SOURCES
            for c in set(comments_and_docstrings(p.read_text())) if TIMING.search(c)]
    assert len(hits) <= MAX_TIMING_NARRATIONS, "comments or docstrings narrating timings:\n" + "\n".join(hits)


def test_the_timing_rule_is_not_vacuous():
    assert TIMING.search("the bunny: 0.91 -> 0.68 s") and TIMING.search("about 5x faster")
    assert not TIMING.search("distances in input units (mm for dental scans)")
