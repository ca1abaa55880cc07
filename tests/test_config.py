"""Level 1: every config option composes and builds; registries and YAML files match one to one."""

import dataclasses
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from scanreg.app import CONF_DIR, STAGE_GROUPS, check_group_overrides, precheck
from scanreg.errors import ConfigError
from scanreg.registry import REGISTRIES, field_docs, load_all, make_params
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
    from scanreg.config import compose

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "my_density.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /icp: horn\nsampler:\n  n_points: 3000\n")
    assert precheck(["--config-dir", str(tmp_path), "experiment=my_density"]) is None
    assert precheck([f"hydra.searchpath=[file://{tmp_path}]", "experiment=my_density"]) is None
    msg, _ = precheck(["experiment=my_density"])
    assert "unknown experiment 'my_density'" in msg
    cfg = compose(["experiment=my_density"], config_dirs=[tmp_path])
    assert cfg.sampler.n_points == 3000 and cfg.icp.name == "horn"
