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


def _plugin(root: Path, name: str, code: str) -> Path:
    """A one-module plugin package ``name`` with its entry point, under ``root`` (as tests/plugin_example)."""
    (root / name).mkdir(parents=True)
    (root / name / "__init__.py").write_text(code)
    info = root / f"{name}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[scanreg.stages]\n{name} = {name}\n")
    return root


def test_a_plugin_that_does_not_meet_its_protocol_costs_its_own_stages_only(tmp_path):
    """A coarse stage with ``align`` alone (no ``describe_set``), and an ICP stage whose ``refine`` takes fewer
    parameters than the protocol's (the pipeline passes them all by position): each plugin is named in one
    warning line, with what it lacks, and every other command works (a plugin that failed to load made every
    ``scanreg`` command a traceback; the short signature failed at run time as an internal error)."""
    root = _plugin(tmp_path / "plugins", "my_coarse", (
        "from dataclasses import dataclass\nfrom scanreg.stages.registry import COARSE\n\n"
        "@COARSE.register('centroid')\nclass Centroid:\n    uses = ()\n\n    @dataclass\n    class Params:\n"
        "        pass\n\n    def __init__(self, p):\n        self.p = p\n\n"
        "    def align(self, target, source, spacing, ctx, landmarks=None):\n        raise NotImplementedError\n"))
    _plugin(root, "my_icp", (
        "from scanreg.stages.icp.point import Horn\nfrom scanreg.stages.registry import ICP\n\n"
        "@ICP.register('my_icp')\nclass MyIcp(Horn):\n"
        "    def refine(self, target, source, T_init, spacing, ctx, target_mesh=None):\n"
        "        return super().refine(target, source, T_init, spacing, ctx, target_mesh)\n"))
    env = dict(os.environ, PYTHONPATH=str(root))
    env.pop("SCANREG_SWEEP", None)
    r = subprocess.run([sys.executable, "-m", "scanreg.app", "data=synthetic", "sampler.n_points=3000", "tracking=none",
                        "evaluate.view_html=false", "hydra.run.dir=out"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0 and "Traceback" not in r.stderr + r.stdout, r.stderr
    warned = [ln for ln in r.stdout.splitlines() if ln.startswith("warning: stage plugin")]
    assert len(warned) == 2, r.stdout
    assert "my_coarse" in warned[0] and "lacks describe_set, align_described" in warned[0]
    assert "my_icp" in warned[1] and "refine(target, source, T_init, spacing, ctx, target_mesh=None) takes fewer " \
        "parameters than refine(" in warned[1] and "start_is_estimate" in warned[1]
    r = subprocess.run([sys.executable, "-m", "scanreg.app", "data=synthetic", "icp=my_icp"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "unknown icp 'my_icp'" in r.stderr and len(r.stderr.strip().splitlines()) == 1
