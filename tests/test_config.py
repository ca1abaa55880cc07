"""Level 1: every config option composes and builds; registries and YAML files match one to one."""

import dataclasses
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from scanreg.app import CONF_DIR, STAGE_GROUPS, check_group_overrides, precheck
from scanreg.errors import ConfigError
from scanreg.stages.registry import REGISTRIES, field_docs, load_all, make_params
from scanreg.app import validate_config as build_stages

load_all()


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


ALL_OPTIONS = [(g, o) for g in STAGE_GROUPS for o in options(g)]


def test_every_group_has_options_and_a_registry():
    assert set(STAGE_GROUPS) == set(REGISTRIES)
    for g in STAGE_GROUPS:
        assert options(g), f"conf/{g}/ is empty"


@pytest.mark.parametrize("group,option", ALL_OPTIONS)
def test_option_composes_and_builds(group, option):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[f"{group}={option}"])
    assert cfg[group].name == option, f"conf/{group}/{option}.yaml must have name: {option}"
    inst = REGISTRIES[group].build(cfg[group])
    assert type(inst).name == option
    build_stages(cfg)  # the whole pipeline builds with this choice


@pytest.mark.parametrize("family", list(REGISTRIES))
def test_every_registered_stage_has_a_yaml_and_docs(family):
    reg = REGISTRIES[family]
    assert reg.names() == options(family), f"registry {family} and conf/{family}/ differ"
    for name in reg.names():
        cls = reg.get(name)
        assert cls.__doc__, f"{family}={name} has no docstring"
        docs = field_docs(cls.Params)
        for f in dataclasses.fields(cls.Params):
            assert docs.get(f.name), f"{family}={name}: parameter '{f.name}' has no docstring"
        yaml_keys = set(OmegaConf.load(CONF_DIR / family / f"{name}.yaml")) - {"name"}
        assert yaml_keys == {f.name for f in dataclasses.fields(cls.Params)}, \
            f"conf/{family}/{name}.yaml should list every parameter of {cls.__name__}.Params"


def test_unknown_name_lists_valid_ones():
    with pytest.raises(ConfigError, match=r"unknown icp 'nope'; valid icp names: anderson, gicp, horn, open3d, point_to_plane"):
        REGISTRIES["icp"].build({"name": "nope"})


def test_wrong_type_and_unknown_parameter():
    from scanreg.stages.icp import Horn

    with pytest.raises(ConfigError, match=r"icp=horn: parameter 'max_iterations' expects int, got 'abc'"):
        make_params(Horn.Params, {"max_iterations": "abc"}, "icp=horn")
    with pytest.raises(ConfigError, match=r"unknown parameter 'bogus'; valid parameters: max_iterations"):
        make_params(Horn.Params, {"bogus": 1}, "icp=horn")
    with pytest.raises(ConfigError, match=r"distances"):
        make_params(Horn.Params, {"distances": "furlongs"}, "icp=horn")
    p = make_params(Horn.Params, {"max_iterations": "7"}, "icp=horn")  # numeric strings from the CLI are fine
    assert p.max_iterations == 7


def test_check_hook_runs():
    from scanreg.stages.sampler import Barycentric

    with pytest.raises(ConfigError, match="exactly one of n_points and density"):
        make_params(Barycentric.Params, {"n_points": None, "density": None}, "sampler=barycentric")


def test_precheck_messages():
    assert check_group_overrides(["repair=foo"]) == "unknown repair 'foo'; valid repair choices: meshfix, meshlab, none"
    assert check_group_overrides(["-m", "repair=none,meshfix"]) is None
    msg, cfg = precheck(["icp.bogus=1"])
    assert msg.startswith("icp=point_to_plane: unknown parameter 'bogus'; valid parameters:")
    assert cfg is not None and cfg.icp.name == "point_to_plane"
    assert precheck(["icp.tau=0.5", "-m", "sampler.n_points=100,200"]) is None
    msg, _ = precheck(["nosuchkey=3"])
    assert "nosuchkey" in msg


def test_experiment_files_are_global_overrides():
    for p in (CONF_DIR / "experiment").glob("*.yaml"):
        lines = p.read_text().splitlines()
        assert lines[0] == "# @package _global_", f"{p.name}: must start as a '# @package _global_' override"
        assert lines[1].startswith("# run: scanreg"), f"{p.name}: second line must be the command that runs it"
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", overrides=[f"experiment={p.stem}"])
        build_stages(cfg)


def test_user_config_dir_plugs_in(tmp_path):
    """A user's own config folder (their presets and experiments) on Hydra's search path: --config-dir on the
    command line, config_dirs in the Python API."""
    from scanreg.app import precheck
    from scanreg.app.config import compose

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "my_density.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /icp: horn\nsampler:\n  n_points: 3000\n")
    assert precheck(["--config-dir", str(tmp_path), "experiment=my_density"]) is None
    assert precheck([f"hydra.searchpath=[file://{tmp_path}]", "experiment=my_density"]) is None
    msg, _ = precheck(["experiment=my_density"])
    assert "unknown experiment 'my_density'" in msg
    cfg = compose(["experiment=my_density"], config_dirs=[tmp_path])
    assert cfg.sampler.n_points == 3000 and cfg.icp.name == "horn"


def _yaml_text(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, list):
        return "[" + ", ".join(_yaml_text(x) for x in v) + "]"
    return str(v)


def test_scanreg_stages_shows_the_yaml_defaults_at_100_columns(capsys):
    """scanreg-stages: every stage, every parameter, with the value its YAML sets (point_to_plane's
    initial_share is 0.25 there, 1.0 in the shared Params), in at most 100 columns and without markup."""
    import re

    from scanreg.app.stages_cli import main as stages_main

    assert stages_main([]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert max(len(ln) for ln in lines) <= 100
    assert "``" not in text and "<Distances" not in text
    shown: dict[tuple[str, str], dict[str, str]] = {}
    stage = None
    for ln in lines:
        if re.fullmatch(r"[a-z_]+=[a-z0-9_]+", ln):
            stage = tuple(ln.split("="))
            shown[stage] = {}
        m = re.fullmatch(r"  (\w+) = (.*)   \((.*)\)", ln)
        if m and stage:
            shown[stage][m.group(1)] = m.group(2)
    assert set(shown) == set(ALL_OPTIONS)
    for group, option in ALL_OPTIONS:
        yaml = OmegaConf.to_container(OmegaConf.load(CONF_DIR / group / f"{option}.yaml"), resolve=False)
        fields = {f.name for f in dataclasses.fields(REGISTRIES[group].get(option).Params)}
        assert set(shown[group, option]) == fields, (group, option)
        for k, v in yaml.items():
            if k != "name":
                assert shown[group, option][k] == _yaml_text(v), (group, option, k)
    assert shown["icp", "point_to_plane"]["initial_share"] == "0.25"
    assert shown["icp", "point_to_plane"]["distances"] == "spacing"


def test_scanreg_stages_help_and_filter(capsys):
    from scanreg.app.stages_cli import main as stages_main

    with pytest.raises(SystemExit) as e:
        stages_main(["--help"])
    assert e.value.code == 0 and "FAMILY[=NAME]" in capsys.readouterr().out
    assert stages_main(["icp=horn", "matcher"]) == 0
    heads = [ln for ln in capsys.readouterr().out.splitlines() if ln and not ln.startswith(" ")]
    assert heads == ["icp=horn", "matcher=mutual_knn"]
    assert stages_main(["icp=bogus"]) == 2
    assert capsys.readouterr().err.startswith("error: unknown icp 'bogus'")


def test_scanreg_help_is_the_projects_own(tmp_path):
    from conftest import run_cli

    r = run_cli(["--help"], tmp_path)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "powered by Hydra" not in out and "scanreg: repair, sample and rigidly register" in out
    assert "scanreg data=synthetic" in out and "Exit codes:" in out and str(CONF_DIR) in out
    assert "icp: anderson, gicp, horn, open3d, point_to_plane" in out
    assert len(out.splitlines()) < 60 and max(len(ln) for ln in out.splitlines()) <= 100
    assert not list(tmp_path.iterdir())  # help runs nothing


def test_quick_help_is_hydras_text(tmp_path):
    """`scanreg --help` writes the template itself (scanreg.app.quick_help) instead of Hydra's help machinery;
    the text must be exactly what Hydra writes, with and without an override."""
    import subprocess
    import sys

    for extra in ([], ["experiment=demo_density"]):
        code = ("import sys; sys.argv = ['scanreg', '--help', *sys.argv[1:]]\n"
                "from scanreg.app import _hydra_main; _hydra_main()")
        hydra = subprocess.run([sys.executable, "-c", code, *extra], cwd=tmp_path, capture_output=True, text=True,
                               timeout=300)
        ours = subprocess.run([sys.executable, "-m", "scanreg.app.cli", "--help", *extra], cwd=tmp_path,
                              capture_output=True, text=True, timeout=300)
        assert hydra.returncode == 0 and ours.returncode == 0, hydra.stderr + ours.stderr
        assert ours.stdout == hydra.stdout and "Config groups" in ours.stdout


def test_run_mode_read_off_the_precheck(tmp_path):
    """Hydra's first composition (``Hydra.get_mode``) is answered from the config the precheck composed: the
    same mode as Hydra finds itself, from a config file too; unknown when the command line overrides Hydra's
    own mode or groups; Hydra's method back in place afterwards."""
    from hydra._internal.hydra import Hydra
    from hydra.types import RunMode

    from scanreg.app import _UNKNOWN, _hydra_mode_known, _mode_of, compose_checked

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "swept.yaml").write_text(
        "# @package _global_\nhydra:\n  mode: MULTIRUN\n  sweeper:\n    params:\n      sampler.n_points: 100,200\n")
    argv = ["--config-dir", str(tmp_path), "experiment=swept"]
    problem, cfg = compose_checked(argv)
    assert problem is None and _mode_of(argv, cfg) == RunMode.MULTIRUN
    problem, cfg = compose_checked(["icp.tau=0.5"])
    assert problem is None and _mode_of(["icp.tau=0.5"], cfg) is None  # Hydra's default: run
    for args in (["hydra.mode=MULTIRUN"], ["hydra/launcher=basic"], ["+hydra.mode=RUN"], ["icp.tau=0.1,0.2"],
                 ["experiment=swept,other"], ["-cp", str(tmp_path)], ["--config-path=x"]):
        assert _mode_of(args, cfg) is _UNKNOWN, args  # Hydra may read another mode than the precheck's config
    assert _mode_of(["--config-dir", str(tmp_path), "icp.tau=0.5"], cfg) is None  # a flag's value is no override
    original = Hydra.get_mode
    with _hydra_mode_known(RunMode.MULTIRUN):
        assert Hydra.get_mode(None, "config", []) == RunMode.MULTIRUN
    assert Hydra.get_mode is original
    with _hydra_mode_known(_UNKNOWN):
        assert Hydra.get_mode is original
