"""The README's command blocks: each is marked, and those that need no private data run as written."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from conftest import ROOT

MARK = re.compile(r"<!-- readme-test: (run|skip \(.+\)) -->")


def bash_blocks() -> list[tuple[str, list[str]]]:
    """(the mark before each ```bash block, its command lines without comments)."""
    lines = (ROOT / "README.md").read_text().splitlines()
    out = []
    for i, ln in enumerate(lines):
        if ln.strip() != "```bash":
            continue
        prev = next((p for p in reversed(lines[:i]) if p.strip()), "")
        m = MARK.fullmatch(prev.strip())
        body = []
        for b in lines[i + 1:]:
            if b.strip() == "```":
                break
            cmd = b.split(" #")[0].strip() if not b.lstrip().startswith("#") else ""
            if cmd:
                body.append(cmd)
        out.append((m.group(1) if m else "", body))
    return out


def test_every_command_block_is_run_or_says_why_not():
    blocks = bash_blocks()
    assert blocks and all(mark for mark, _ in blocks), [b for m, b in blocks if not m]
    assert sum(mark == "run" for mark, _ in blocks) >= 1


# the one change to the commands as written: demo_density runs one seed of its three (3 jobs, not 9)
SHORTER = {"scanreg -m experiment=demo_density": ["hydra.sweeper.params.seed=0"]}


@pytest.mark.slow
def test_runnable_readme_blocks_run_as_written(tmp_path):
    bindir = Path(sys.executable).parent
    env = {k: v for k, v in os.environ.items() if k not in ("SCANREG_SWEEP", "MLFLOW_TRACKING_URI")}
    def status() -> list[str]:
        """The project's changed and new files, tests/ aside (edited by hand while the suite may run)."""
        out = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=ROOT, capture_output=True,
                             text=True).stdout
        return [ln for ln in out.splitlines() if not ln[3:].lstrip('"').startswith("tests/")]

    before = status()
    commands = [c for mark, body in bash_blocks() if mark == "run" for c in body]
    assert commands
    for cmd in commands:
        argv = shlex.split(cmd) + SHORTER.get(cmd, [])
        assert argv[0] in ("scanreg", "scanreg-report", "scanreg-stages"), cmd
        r = subprocess.run([str(bindir / argv[0]), *argv[1:]], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=900)
        assert r.returncode == 0, f"{cmd}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
        assert "Traceback" not in r.stderr, cmd
        rep = tmp_path / "outputs" / "reports" / "demo_density"
        if "experiment=demo_density" in cmd:  # its report went to the working directory, with its plot
            assert (rep / "error_time_vs_sampler.density.png").exists()
    # every density in the table (the bare scanreg-report after it wrote its own report into the same folder, and
    # removed the files the experiment's report wrote there first)
    assert list(pd.read_csv(rep / "report.csv")["sampler.density"]) == [0.5, 1.0, 2.0]
    assert list(pd.read_csv(tmp_path / "reports" / "density" / "report.csv")["runs"]) == [1, 1, 1]
    assert status() == before  # nothing written into the project (experiments/ untouched)
