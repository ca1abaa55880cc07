"""Benchmark: a sweep's start with scanreg's check of every job against Hydra's own validation.

    .venv/bin/python experiments/benchmarks/sweep_check.py [--rounds 2] [--out experiments/benchmarks/sweep_check.md]

A sweep (``scanreg -m``) checks every job before launching any (``scanreg.app.sweep.check_jobs``), and when it
checked them all, Hydra's basic sweeper does not compose each job once more to validate it. The anchor is the
same command without the check (``SCANREG_SWEEP_CHECK=0``): Hydra's own start, its validation included. For each of three shipped experiment sweeps the time from the command's start to Hydra's
"Launching jobs" line is measured, the sweep then stopped (no job is waited for); the two sides alternate
within each round (a slow spell of the shared machine hits both). ``tracking=none``; the experiments read
``../shared/data`` (skipped with a message when absent). The table gives the median over the rounds.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EXPERIMENTS = ("bunny_benchmark", "salience_comparison", "icp_comparison")


def time_to_launch(experiment: str, check: bool, folder: Path) -> float:
    """Seconds from the command's start to Hydra's 'Launching jobs' line (the sweep is stopped there)."""
    env = dict(os.environ, SCANREG_SWEEP_CHECK="1" if check else "0")
    log = folder / "log.txt"
    start = time.perf_counter_ns()
    with open(log, "w") as out:
        proc = subprocess.Popen([str(ROOT / ".venv/bin/scanreg"), "-m", f"experiment={experiment}", "tracking=none",
                                 f"hydra.sweep.dir={folder / 'sweep'}"], stdout=out, stderr=subprocess.STDOUT,
                                env=env, cwd=folder, start_new_session=True)
        while "Launching jobs" not in log.read_text() and proc.poll() is None:
            time.sleep(0.05)
        seconds = (time.perf_counter_ns() - start) / 1e9
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    if "Launching jobs" not in log.read_text():
        raise SystemExit(f"{experiment}: the sweep did not launch:\n{log.read_text()[-2000:]}")
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default=None, help="write the table (markdown) here")
    a = ap.parse_args()
    if not (ROOT.parent / "shared" / "data" / "stanford_bunny").is_dir():
        print("skipped: ../shared/data/stanford_bunny is absent (the experiments read it)")
        return
    times: dict[tuple[str, bool], list[float]] = {}
    for r in range(a.rounds):
        for experiment in EXPERIMENTS:
            for check in ((True, False) if r % 2 == 0 else (False, True)):
                with tempfile.TemporaryDirectory() as tmp:
                    t = time_to_launch(experiment, check, Path(tmp))
                times.setdefault((experiment, check), []).append(t)
                print(f"round {r}: {experiment} check={check}: {t:.1f} s", flush=True)
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    lines = [f"`experiments/benchmarks/sweep_check.py --rounds {a.rounds}`, commit {commit}, "
             f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC; medians of the rounds.", "",
             "| experiment | jobs | to launch, checked [s] | to launch, SCANREG_SWEEP_CHECK=0 (Hydra's validation) [s] | difference [s] |",
             "|---|---|---|---|---|"]
    from omegaconf import OmegaConf

    sys.path.insert(0, str(ROOT))
    from scanreg.app.config import compose
    from scanreg.app.tracking import sweep_size

    for experiment in EXPERIMENTS:
        on, off = (statistics.median(times[(experiment, c)]) for c in (True, False))
        cfg = compose([f"experiment={experiment}"], return_hydra_config=True)
        OmegaConf.set_struct(cfg, False)
        lines.append(f"| {experiment} | {sweep_size(cfg)} | {on:.1f} | {off:.1f} | {on - off:+.1f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
