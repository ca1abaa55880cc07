"""The installed package: a wheel holds one top-level package ``scanreg`` with its configs, and installed into a
fresh virtualenv (not editable) the CLI and the Python API work from any directory."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run(cmd, cwd, env=None, timeout=600):
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{cmd} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(ROOT)], ROOT)
    (whl,) = out.glob("scanreg-*.whl")
    return whl


SOURCE_FOLDERS = {"pipeline": "scanreg", "stages": "scanreg.stages", "conf": "scanreg.conf"}
"""The repository's folders and the packages they are (pyproject.toml's package-dir)."""


def _folders() -> dict[str, Path]:
    """Every package folder of the checkout by its package name: the folders under pipeline/ and stages/ with an
    __init__.py, and every folder of conf/ (config groups: packages without Python)."""
    out = {}
    for top, pkg in SOURCE_FOLDERS.items():
        for d in [ROOT / top, *sorted(p for p in (ROOT / top).rglob("*") if p.is_dir())]:
            if "__pycache__" in d.parts:
                continue
            if top == "conf" or (d / "__init__.py").is_file():
                rel = d.relative_to(ROOT / top).parts
                out[".".join((pkg, *rel))] = d
    return out


def _pyproject() -> dict:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_pyproject_lists_every_package_folder():
    """pyproject.toml's explicit package list: every folder under pipeline/ and stages/ with an __init__.py and
    every folder of conf/ is listed (a missing one would be absent from the wheel), and nothing else."""
    setup = _pyproject()["tool"]["setuptools"]
    assert setup["package-dir"] == {v: k for k, v in SOURCE_FOLDERS.items()}
    listed = setup["packages"]
    assert len(listed) == len(set(listed)), "a package listed twice"
    folders = _folders()
    assert set(folders) <= set(listed), f"not listed in pyproject.toml: {sorted(set(folders) - set(listed))}"
    assert set(listed) <= set(folders), f"listed but no such package folder: {sorted(set(listed) - set(folders))}"
    assert {"scanreg.app.report", "scanreg.runner", "scanreg.stages.icp", "scanreg.conf.tracking"} <= set(listed)
    # a folder with Python modules but no __init__.py would be skipped silently
    for top in ("pipeline", "stages"):
        for py in (ROOT / top).rglob("*.py"):
            assert (py.parent / "__init__.py").is_file(), f"{py.parent} has modules but no __init__.py"


def test_wheel_holds_one_package_and_the_configs(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"scanreg", "-".join(wheel.name.split("-")[:2]) + ".dist-info"}
    # the compiled kernels, built for this platform (pyproject.toml's ext-modules)
    assert any(n.startswith("scanreg/mesh/_native.") and n.endswith(".so") for n in names)
    assert "scanreg/conf/config.yaml" in names and "scanreg/conf/icp/point_to_plane.yaml" in names
    yamls = {n.removeprefix("scanreg/conf/") for n in names if n.endswith(".yaml")}
    assert yamls == {str(p.relative_to(ROOT / "conf")) for p in (ROOT / "conf").rglob("*.yaml")}
    assert "scanreg/stages/repair/meshfix.py" in names
    # every module of the checkout, at its package's place
    for top, pkg in SOURCE_FOLDERS.items():
        for py in (ROOT / top).rglob("*.py"):
            if "__pycache__" in py.parts:
                continue
            where = "/".join((*pkg.split("."), *py.relative_to(ROOT / top).parts))
            assert where in names, f"{py.relative_to(ROOT)} is not in the wheel (as {where})"


@pytest.mark.slow
def test_installed_wheel_runs_from_another_directory(wheel, tmp_path):
    """A fresh venv with the wheel installed (the dependencies are borrowed from this environment through a
    path entry, so that no network is needed): ``scanreg data=synthetic`` and ``scanreg.register`` on arrays."""
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path)
    py = venv / "bin" / "python"
    site = Path(run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path).stdout.strip())
    # this environment's packages as a plain path entry: its .pth files (our editable install) are not run
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", str(wheel)], tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MLFLOW_TRACKING_URI")}
    where = run([str(py), "-c", "import scanreg, scanreg.stages, scanreg.conf; print(scanreg.__file__); "
                 "print(scanreg.conf.__file__)"], elsewhere, env).stdout
    assert str(ROOT) not in where and str(site) in where, where
    r = run([str(venv / "bin" / "scanreg"), "data=synthetic", "tracking=none"], elsewhere, env)
    assert "rotation_error_deg" in r.stdout and "success                    1" in r.stdout, r.stdout[-2000:]
    script = (
        "import numpy as np, scanreg\n"
        "from scipy.spatial.transform import Rotation\n"
        "from scanreg.geometry import barycentric_sample, make_T, transform_errors\n"
        "from scanreg.io import read_mesh\n"
        "m = read_mesh('pkg:pymeshfix/examples/StanfordBunny.ply')\n"
        "tgt = barycentric_sample(m, 15000, np.random.default_rng(0))[0]\n"
        "T = make_T(Rotation.from_euler('xyz', [20, 50, -30], degrees=True).as_matrix(), np.array([5., 1, -2]))\n"
        "src = (tgt - T[:3, 3]) @ T[:3, :3]\n"
        "res = scanreg.register(src, tgt)\n"
        "print('ROT', transform_errors(res.T_target_source, T)[0])\n")
    out = run([str(py), "-c", script], elsewhere, env).stdout
    rot = float(out.split("ROT")[1])
    assert rot < 0.5, out


@pytest.mark.slow
def test_example_script_runs(tmp_path):
    r = run([sys.executable, str(ROOT / "examples" / "register_arrays.py")], tmp_path)
    assert "rotation error" in r.stdout


def test_the_api_lists_its_names_and_removes_the_folder_of_a_failed_call(tmp_path, monkeypatch):
    """dir(scanreg) shows the API though it loads lazily; a call that fails on bad input removes the temporary
    folder it made (a loop over many inputs filled /tmp), and keeps a run_dir it was given."""
    import numpy as np
    import pytest
    import scanreg
    from scanreg.errors import InputError

    assert {"register", "reconstruct", "compose", "build_stage", "run_config"} <= set(dir(scanreg))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # (TMPDIR read again)
    bad = np.full((100, 3), np.nan)
    with pytest.raises(InputError):
        scanreg.register(bad, bad)
    assert not list(tmp_path.glob("scanreg-*"))
    with pytest.raises(InputError):
        scanreg.register(bad, bad, run_dir=tmp_path / "mine")
    assert (tmp_path / "mine").is_dir()
    # an array is named as the array given, not by the file written for the run (deleted with the folder)
    with pytest.raises(InputError, match=r"^source \(the ndarray given\): 5 point\(s\); at least 10"):
        scanreg.register(np.zeros((5, 3)), np.random.default_rng(0).normal(size=(500, 3)))
