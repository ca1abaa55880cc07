"""Level 1: every config option composes and builds; registries and YAML files match one to one; every
default lives in its stage's Params dataclass; composition errors are one clear line."""

import dataclasses
import enum

import numpy as np
import pytest
from omegaconf import OmegaConf

from scanreg.app.config import STAGE_GROUPS, compose, group_choices
from scanreg.app.tracking import TRACKING
from scanreg.errors import ConfigError
from scanreg.runner import build_stages
from scanreg.stages.registry import REGISTRIES, conf_dir, field_docs, load_all, make_params

load_all()
CONF_DIR = conf_dir()
GROUP_REGISTRIES = {**REGISTRIES, "tracking": TRACKING}
"""The registry behind each stage group (the tracking backends are the app's, not a stage family)."""


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


ALL_OPTIONS = [(g, o) for g in STAGE_GROUPS for o in options(g)]


def defaults_of(params_cls) -> dict:
    """A Params dataclass's defaults, field by field."""
    out = {}
    for f in dataclasses.fields(params_cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def test_every_group_has_options_and_a_registry():
    assert set(STAGE_GROUPS) == set(REGISTRIES) | {"tracking"}
    for g in STAGE_GROUPS:
        assert options(g), f"conf/{g}/ is empty"


@pytest.mark.parametrize("group,option", ALL_OPTIONS)
def test_option_composes_and_builds(group, option):
    cfg = compose([f"{group}={option}"])
    assert cfg[group].name == option, f"{group}={option} must compose to name: {option}"
    stages = build_stages(cfg)  # the whole pipeline builds with this choice
    if group == "tracking":
        inst = TRACKING.build(cfg.tracking)
    else:  # a coarse stage takes the helper stages it uses: built with the pipeline
        inst = stages.helpers[group] if group in stages.helpers else getattr(stages, group)
    assert type(inst).name == option


@pytest.mark.parametrize("family", list(GROUP_REGISTRIES))
def test_every_registered_stage_has_a_yaml_and_docs(family):
    """Each registered stage has its YAML, which holds only the defaults line and its links to the run's seed:
    composed, every parameter has its Params default (the linked ones the run's seed)."""
    reg = GROUP_REGISTRIES[family]
    assert reg.names() == options(family), f"registry {family} and conf/{family}/ differ"
    for name in reg.names():
        cls = reg.get(name)
        assert cls.__doc__, f"{family}={name} has no docstring"
        docs = field_docs(cls.Params)
        fields = {f.name for f in dataclasses.fields(cls.Params)}
        for f in fields:
            assert docs.get(f), f"{family}={name}: parameter '{f}' has no docstring"
        yaml = OmegaConf.to_container(OmegaConf.load(CONF_DIR / family / f"{name}.yaml"), resolve=False)
        assert yaml.pop("defaults") == [f"_{name}", "_self_"], f"conf/{family}/{name}.yaml: defaults"
        assert set(yaml) <= fields and set(yaml.values()) <= {"${seed}"}, \
            f"conf/{family}/{name}.yaml should hold only links to the run's seed; defaults belong in Params"
        cfg = compose([f"{family}={name}", "seed=7"])
        composed = OmegaConf.to_container(cfg[family], resolve=True)
        assert composed.pop("name") == name and set(composed) == fields, (family, name)
        want = {**defaults_of(cls.Params), **{k: 7 for k in yaml}}
        assert composed == want, (family, name)


def test_unknown_name_lists_valid_ones():
    with pytest.raises(ConfigError, match=r"unknown icp 'nope'; valid icp names: anderson, gicp, horn, open3d, point_to_plane"):
        REGISTRIES["icp"].build({"name": "nope"})


def test_wrong_type_and_unknown_parameter():
    from scanreg.stages.icp.point import Horn

    with pytest.raises(ConfigError, match=r"icp=horn: parameter 'max_iterations' expects int, got 'abc'"):
        make_params(Horn.Params, {"max_iterations": "abc"}, "icp=horn")
    with pytest.raises(ConfigError, match=r"unknown parameter 'bogus'; valid parameters: max_iterations"):
        make_params(Horn.Params, {"bogus": 1}, "icp=horn")
    with pytest.raises(ConfigError, match=r"parameter 'distances' expects spacing \| absolute, got 'furlongs'"):
        make_params(Horn.Params, {"distances": "furlongs"}, "icp=horn")
    # the type as scanreg-stages lists it, not Python's annotation text ('expects Optional[float]', a user's trial)
    with pytest.raises(ConfigError, match=r"parameter 'max_correspondence_distance' expects float \| null, got 'x'$"):
        make_params(Horn.Params, {"max_correspondence_distance": "x"}, "icp=horn")
    p = make_params(Horn.Params, {"max_iterations": "7"}, "icp=horn")  # numeric strings from the CLI are fine
    assert p.max_iterations == 7


def test_a_misspelt_key_is_named_with_the_one_meant():
    """An unknown top-level key near a config group or block (``smapler.n_points``): one line that names the one
    meant; one near nothing says only that it is unknown."""
    with pytest.raises(ConfigError, match=r"^unknown config key 'smapler': did you mean 'sampler'\? \(add it"):
        compose(["smapler.n_points=5"])
    with pytest.raises(ConfigError, match=r"^unknown config key 'evalute': did you mean 'evaluate'\?"):
        compose(["evalute.units=mm"])
    with pytest.raises(ConfigError, match=r"^unknown config key 'zzz' \(add it with \+zzz=VALUE"):
        compose(["zzz=1"])
    # a stage's parameter without its stage (a user's trial: told to add +max_iterations, which is then ignored)
    with pytest.raises(ConfigError, match=r"^unknown config key 'max_iterations': did you mean "
                                          r"'coarse.max_iterations' or 'icp.max_iterations'\?"):
        compose(["max_iterations=5"])
    with pytest.raises(ConfigError, match=r"did you mean 'evaluate.success_rotation_deg'\?"):
        compose(["success_rotation_deg=1"])


def test_check_hook_runs():
    from scanreg.stages.sampler import Barycentric

    with pytest.raises(ConfigError, match="exactly one of n_points and density"):
        make_params(Barycentric.Params, {"n_points": None, "density": None}, "sampler=barycentric")


def _compose_error(overrides) -> str:
    with pytest.raises(ConfigError) as e:
        compose(overrides)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_composition_error_lines():
    """Hydra's composition errors as the CLI says them (scanreg.app.config.config_error_line): an unknown group
    choice with the valid ones, an unknown or mistyped parameter as the stage's registry says it, an unknown
    key with how to add it; overrides that compose raise nothing (a sweep's values are Hydra's to expand)."""
    assert _compose_error(["repair=foo"]) == "unknown repair 'foo'; valid repair choices: meshfix, meshlab, none"
    assert _compose_error(["method=nope"]) == "unknown method 'nope'; valid method choices: open3d, open3d_multiway, scanreg"
    assert _compose_error(["icp.bogus=1"]).startswith(
        "icp=point_to_plane: unknown parameter 'bogus'; valid parameters:")
    assert _compose_error(["icp=horn", "icp.max_iterations=abc"]) == \
        "icp=horn: parameter 'max_iterations' expects int, got 'abc'"
    assert _compose_error(["evaluate.bogus=1"]).startswith("evaluate: unknown parameter 'bogus'; valid parameters:")
    assert _compose_error(["report.enabled=maybe"]) == "report: parameter 'enabled' expects bool, got 'maybe'"
    msg = _compose_error(["nosuchkey=3"])
    assert "nosuchkey" in msg and "+nosuchkey=" in msg
    assert _compose_error(["icp.tau=[1"]).startswith("bad override:")
    assert compose(["icp.tau=0.5", "sampler.n_points=100"]).icp.tau == 0.5


def test_unknown_tracking_parameter_is_one_line():
    assert _compose_error(["tracking.bogus=1"]) == \
        "tracking=mlflow: unknown parameter 'bogus'; valid parameters: uri, experiment"


def test_wrong_enum_value_names_the_value():
    assert _compose_error(["icp.distances=furlongs"]) == \
        "icp=point_to_plane: parameter 'distances' expects spacing | absolute, got 'furlongs'"


def test_unknown_hydra_group_choice_lists_the_valid_ones():
    msg = _compose_error(["hydra/launcher=nope"])
    assert msg.startswith("unknown hydra/launcher 'nope'; valid hydra/launcher choices: ") and "joblib" in msg


def test_experiment_files_are_global_overrides():
    for p in (CONF_DIR / "experiment").glob("*.yaml"):
        lines = p.read_text().splitlines()
        assert lines[0] == "# @package _global_", f"{p.name}: must start as a '# @package _global_' override"
        assert lines[1].startswith("# run: scanreg"), f"{p.name}: second line must be the command that runs it"
        build_stages(compose([f"experiment={p.stem}"]))


def test_user_config_dir_plugs_in(tmp_path):
    """A user's own config folder (their presets and experiments) on Hydra's search path: --config-dir or
    hydra.searchpath on the command line, config_dirs in the Python API."""
    from conftest import run_cli

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "my_density.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /icp: horn\nsampler:\n  n_points: 3000\n")
    cfg = compose(["experiment=my_density"], config_dirs=[tmp_path])
    assert cfg.sampler.n_points == 3000 and cfg.icp.name == "horn"
    assert "unknown experiment 'my_density'" in _compose_error(["experiment=my_density"])
    assert "my_density" in group_choices("experiment", [tmp_path])
    assert "my_density" in group_choices("experiment", [f"file://{tmp_path}"])
    assert "my_density" not in group_choices("experiment")
    work = tmp_path / "work"
    work.mkdir()
    for args in (["--config-dir", str(tmp_path)], [f"hydra.searchpath=[file://{tmp_path}]"]):
        r = run_cli([*args, "experiment=my_density", "--cfg", "job"], work)
        assert r.returncode == 0, r.stderr
        shown = OmegaConf.create(r.stdout)
        assert shown.sampler.n_points == 3000 and shown.icp.name == "horn", args
    assert not list(work.iterdir())  # showing the config runs nothing


def _yaml_text(v) -> str:
    if isinstance(v, enum.Enum):
        v = v.value
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_yaml_text(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_yaml_text(x)}" for k, x in v.items()) + "}"
    return str(v)


def test_scanreg_stages_shows_the_defaults_at_100_columns(capsys):
    """scanreg-stages: every stage, every parameter, with its Params default (or the YAML's link to the run's
    seed), in at most 100 columns and without markup. point_to_plane's initial_share is 0.25 in its own Params
    (the shared IcpParams say 1.0)."""
    import re

    from scanreg.app.stages_cli import main as stages_main
    from scanreg.stages.icp.base import IcpParams

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
    stage_options = [(g, o) for g, o in ALL_OPTIONS if g in REGISTRIES]
    assert set(shown) == set(stage_options)
    for group, option in stage_options:
        params = REGISTRIES[group].get(option).Params
        yaml = OmegaConf.to_container(OmegaConf.load(CONF_DIR / group / f"{option}.yaml"), resolve=False)
        assert set(shown[group, option]) == {f.name for f in dataclasses.fields(params)}, (group, option)
        for k, v in defaults_of(params).items():
            want = yaml[k] if k in yaml else _yaml_text(v)  # the YAML holds only '${seed}' links
            assert shown[group, option][k] == want, (group, option, k)
    assert shown["icp", "point_to_plane"]["initial_share"] == "0.25" and IcpParams().initial_share == 1.0
    assert shown["icp", "point_to_plane"]["distances"] == "spacing"
    assert shown["sampler", "barycentric"]["seed"] == "${seed}"


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
    # the settings that are not stages: each parameter with its default and its documentation
    from scanreg.eval.metrics import EvalParams

    assert stages_main(["evaluate"]) == 0
    shown = capsys.readouterr().out
    assert shown.startswith("evaluate\n  set with evaluate.PARAM=VALUE\n")
    assert "  units = auto   (str)" in shown and "  deviation_scale = null   (float | null)" in shown
    assert shown.count(" = ") >= len(dataclasses.fields(EvalParams))
    assert stages_main(["evaluate=x"]) == 2
    assert capsys.readouterr().err.startswith("error: evaluate is a block of settings, not a stage family")
    assert stages_main(["bogus"]) == 2 and "valid: data, repair" in capsys.readouterr().err


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
    """`scanreg --help` writes the template itself (scanreg.app.startup.quick_help) instead of Hydra's help
    machinery; the text must be exactly what Hydra writes, with and without an override."""
    import subprocess
    import sys

    for extra in ([], ["experiment=demo_density"]):
        code = ("import sys; sys.argv = ['scanreg', '--help', *sys.argv[1:]]\n"
                "from scanreg.app.config import register_schemas; register_schemas()\n"
                "from scanreg.app.main import _hydra_main; _hydra_main()")
        hydra = subprocess.run([sys.executable, "-c", code, *extra], cwd=tmp_path, capture_output=True, text=True,
                               timeout=300)
        ours = subprocess.run([sys.executable, "-m", "scanreg.app.cli", "--help", *extra], cwd=tmp_path,
                              capture_output=True, text=True, timeout=300)
        assert hydra.returncode == 0 and ours.returncode == 0, hydra.stderr + ours.stderr
        assert ours.stdout == hydra.stdout and "Config groups" in ours.stdout


def test_a_value_an_interpolation_passes_on_is_named_by_its_key():
    """``seed=abc`` reaches the stages through ``${seed}``: one line naming the key and the type (it was
    OmegaConf's 'While dereferencing interpolation ...')."""
    from scanreg.app.config import interpolation_error_line

    cfg = compose(["seed=abc"])
    with pytest.raises(Exception) as e:
        OmegaConf.to_container(cfg, resolve=True)
    assert interpolation_error_line(e.value) == "seed=abc: expects an integer"


def test_a_sweep_jobs_line_says_its_result():
    """A sweep prints one line per job: a pair's errors or fit, a scan set's scans placed and its worst scan's
    rotation error (it said only the time), and the time."""
    from scanreg.app.main import job_line

    assert job_line({"rotation_error_deg": 0.0512, "translation_error_rel": 0.0003, "time_total_s": 1.23}) == \
        "rot 0.0512°, transl 0.03 %, 1.2 s"
    assert job_line({"rms": 0.00123, "time_total_s": 2.0}) == "rms 0.00123, 2.0 s"
    assert job_line({"n_scans": 10.0, "scans_placed": 9.0, "scan_rotation_error_max_deg": 0.353,
                     "time_total_s": 14.1}) == "9/10 scans placed, worst rot 0.353°, 14.1 s"


@pytest.mark.parametrize("override, message", [
    ("evaluate.inlier_distance=0", "evaluate: inlier_distance must be > 0, got 0.0"),
    ("evaluate.success_rotation_deg=-2", "evaluate: success_rotation_deg must be > 0, got -2.0"),
    ("evaluate.success_translation=0", "evaluate: success_translation must be > 0, got 0.0"),
    ("evaluate.deviation_max_distance=-1", "evaluate: deviation_max_distance must be > 0 or null, got -1.0"),
    ("evaluate.deviation_bands=[0.05,-1]", "evaluate: deviation_bands must all be > 0, got [0.05, -1.0]"),
    ("seed=-1", "seed must be an integer >= 0, got -1"),
])
def test_settings_that_cannot_mean_anything_stop_before_the_run(override, message):
    """A user's trial: ``evaluate.inlier_distance=-3`` ran, reported fitness 0 and 'the registration failed' on a
    pose 0.04 deg off, with exit 0; ``seed=-1`` failed after the run had started, as an internal error. Each is a
    config error now, one line, before anything runs (the CLI's exit 2; the API's ConfigError)."""
    from scanreg.app.main import check_config

    with pytest.raises(ConfigError) as e:
        check_config(compose([override, "data.source=a.ply", "data.target=b.ply", "tracking=none"]))
    assert str(e.value) == message


def test_a_seed_given_as_digits_is_a_seed():
    """``seed='7'`` (quoted, or from an environment variable) ran before the seed check and still does; the API's
    RunContext holds it as an int."""
    from scanreg.app.main import check_config
    from scanreg.types import RunContext, checked_seed

    check_config(compose(["seed='7'", "data.source=a.ply", "data.target=b.ply", "tracking=none"]))
    assert checked_seed("7") == 7 and checked_seed(np.int64(3)) == 3 and RunContext(seed="3").seed == 3
    for bad in (-1, "x", "-2", 1.5, True):
        with pytest.raises(ConfigError, match="seed must be an integer >= 0"):
            checked_seed(bad)


def test_a_config_folder_that_is_not_there_is_named():
    """scanreg.compose(config_dirs=[missing]) passed over the folder and said 'unknown experiment' (a researcher's
    trial); the CLI names it (Hydra's --config-dir check), and so does the API now."""
    import pytest

    import scanreg
    from scanreg.errors import ConfigError

    with pytest.raises(ConfigError, match=r"config_dirs: additional config directory '~/no-such-conf-dir' not found"):
        scanreg.compose(["experiment=my_icp"], config_dirs=["~/no-such-conf-dir"])
