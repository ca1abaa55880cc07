"""The ``run`` entry point: the caller's working directory is kept, and the libusb check is not flaky."""

import hashlib
import subprocess

import pytest

from conftest import ROOT

RUN = ROOT / "run"


def test_libusb_check_200_times_under_pipefail():
    """``ldconfig -p | grep -q`` failed about 1 time in 10 under pipefail (SIGPIPE); the check reads the whole
    cache instead."""
    import ctypes.util

    if ctypes.util.find_library("usb-1.0") is None:
        pytest.skip("libusb-1.0 is not installed here: nothing to find")
    script = f"""set -euo pipefail
source {RUN}
fails=0
for i in $(seq 200); do have_libusb || fails=$((fails + 1)); done
echo "$fails"
"""
    r = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "0", f"{r.stdout.strip()} of 200 checks failed"


def _venv_ready() -> bool:
    """``./run`` would (re)install first unless its stamp matches: the tests must not run pip."""
    stamp = ROOT / ".venv" / ".scanreg-installed"
    want = hashlib.sha256(b"".join((ROOT / f).read_bytes() for f in ("pyproject.toml", "constraints.txt", "run")))
    return stamp.exists() and stamp.read_text().strip() == want.hexdigest()[:16]


def test_run_keeps_the_callers_directory(tmp_path):
    if not _venv_ready():
        pytest.skip("the .venv of ./run is not set up for this checkout (run ./run once)")
    (tmp_path / "bad.ply").write_bytes(b"this is not a mesh\n")
    common = ["data.target=bad.ply", "tracking=none", f"hydra.run.dir={tmp_path / 'out'}"]
    r = subprocess.run([str(RUN), "scanreg", "data.source=bad.ply", *common], cwd=tmp_path, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1 and "error: source bad.ply: not a PLY file" in r.stderr, r.stderr  # read here
    r = subprocess.run([str(RUN), "scanreg", "data.source=nope.ply", *common], cwd=tmp_path, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1] == f"error: source nope.ply: no such file ({tmp_path / 'nope.ply'})"
