"""The ``run`` entry point: the caller's working directory is kept, and the libusb check is not flaky."""

import shutil
import subprocess
import sys
from pathlib import Path

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


def _stamp(root: Path) -> str:
    """The install stamp ``run`` wants for the checkout at ``root`` (its own ``install_stamp``)."""
    r = subprocess.run(["bash", "-c", f"source {root / 'run'} && install_stamp"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def _venv_ready(root=ROOT) -> bool:
    """``./run`` would (re)install first unless its stamp matches: the tests must not run pip."""
    stamp = root / ".venv" / ".scanreg-installed"
    return stamp.exists() and stamp.read_text().strip() == _stamp(root)


def _run_script(tmp_path) -> Path:
    """The ``run`` to call: the project's own when its .venv is set up for this checkout, else a copy of it in a
    folder whose .venv is already 'installed' (its stamp matches; its bin/scanreg is this environment's), so that
    the script itself runs as written without pip."""
    if _venv_ready():
        return RUN
    root = tmp_path / "project"
    (root / ".venv" / "bin").mkdir(parents=True)
    (root / "pipeline" / "mesh").mkdir(parents=True)
    for f in ("pyproject.toml", "constraints.txt", "run", *(str(c.relative_to(ROOT))
                                                           for c in (ROOT / "pipeline" / "mesh").glob("*.c"))):
        shutil.copy2(ROOT / f, root / f)
    (root / ".venv" / "bin" / "scanreg").symlink_to(Path(sys.executable).parent / "scanreg")
    (root / ".venv" / ".scanreg-installed").write_text(_stamp(root) + "\n")
    assert _venv_ready(root)
    return root / "run"


def test_run_keeps_the_callers_directory(tmp_path):
    import ctypes.util

    if ctypes.util.find_library("usb-1.0") is None:
        pytest.skip("libusb-1.0 is not installed here: ./run would install it first")
    run = _run_script(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    (work / "bad.ply").write_bytes(b"this is not a mesh\n")
    common = ["data.target=bad.ply", "tracking=none", f"hydra.run.dir={work / 'out'}"]
    r = subprocess.run([str(run), "scanreg", "data.source=bad.ply", *common], cwd=work, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1 and "error: source bad.ply: not a PLY file" in r.stderr, r.stderr  # read here
    r = subprocess.run([str(run), "scanreg", "data.source=nope.ply", *common], cwd=work, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1] == f"error: source nope.ply: no such file ({work / 'nope.ply'})"
