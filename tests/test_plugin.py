"""A salience measure added from a separate package: one class and one YAML, found through the ``scanreg.stages``
entry point (tests/plugin_example/, the documentation's "Extending scanreg" example), used by the CLI and
listed by ``scanreg-stages``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PLUGIN = Path(__file__).resolve().parent / "plugin_example"


def run(args: list[str], cwd: Path, module: str = "scanreg.app") -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(PLUGIN))
    env.pop("SCANREG_SWEEP", None)
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.slow
def test_a_plugin_salience_measure_registers_and_runs(tmp_path):
    stages = run(["salience=surface_variation"], tmp_path, module="scanreg.app.stages_cli")
    assert stages.returncode == 0, stages.stderr
    assert "salience=surface_variation" in stages.stdout and "Surface variation" in stages.stdout
    r = run(["data=synthetic", "salience=surface_variation", "coarse.fallback_voxel=null", "tracking=none",
             "evaluate.view_html=false", "hydra.run.dir=out"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "out" / "result.json").read_text())
    assert res["coarse_fallback"] == 0  # the plugin's keypoints served, no fallback
    assert res["rotation_error_deg"] < 0.05  # the demo reaches 0.008 deg with the default detector
    assert "name: surface_variation" in (tmp_path / "out" / "config.yaml").read_text()


def test_without_the_plugin_the_name_is_unknown(tmp_path):
    """The stage comes from the plugin alone: without it on the path, the CLI names the valid choices."""
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    r = subprocess.run([sys.executable, "-m", "scanreg.app", "data=synthetic", "salience=surface_variation"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [r.stderr.strip().splitlines()[-1]]
    assert "unknown salience 'surface_variation'; valid salience choices:" in r.stderr and "cn_l3" in r.stderr
