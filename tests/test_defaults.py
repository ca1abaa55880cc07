"""Every default in one place: a stage's ``Params`` dataclass. The Python API and the CLI's composition build
every stage identically, and the stage YAMLs hold nothing but the defaults line and links to the run's seed."""

from __future__ import annotations

import dataclasses

import pytest
from omegaconf import OmegaConf

from scanreg.api import build_stage
from scanreg.app.config import compose
from scanreg.app.tracking import TRACKING
from scanreg.runner import build_stages
from scanreg.stages.registry import REGISTRIES, conf_dir, load_all

load_all()
STAGES = [(fam, name) for fam, reg in REGISTRIES.items() for name in reg.names()]


def params_of(stage) -> dict:
    return dataclasses.asdict(stage.p)


@pytest.mark.parametrize("family,name", STAGES, ids=[f"{f}={n}" for f, n in STAGES])
def test_the_api_and_the_cli_build_the_same_stage(family, name):
    built = build_stages(compose([f"{family}={name}"]))
    cli = built.helpers[family] if family in built.helpers else getattr(built, family)
    assert type(cli) is type(build_stage(family, name))
    assert params_of(cli) == params_of(build_stage(family, name))


def test_the_api_and_the_cli_build_the_same_tracking_and_evaluation():
    cfg = compose([])
    assert dataclasses.asdict(TRACKING.build(cfg.tracking).p) == dataclasses.asdict(
        TRACKING.build({"name": "mlflow"}).p)
    from scanreg.eval.metrics import EvalParams

    assert build_stages(cfg).evaluate == EvalParams()


@pytest.mark.parametrize("family,name", STAGES, ids=[f"{f}={n}" for f, n in STAGES])
def test_a_stage_yaml_holds_only_its_defaults_line_and_seed_links(family, name):
    yaml = OmegaConf.to_container(OmegaConf.load(conf_dir() / family / f"{name}.yaml"), resolve=False)
    assert yaml.pop("defaults") == [f"_{name}", "_self_"]
    assert all(isinstance(v, str) and v == "${seed}" for v in yaml.values()), yaml


def test_a_changed_default_reaches_the_cli(monkeypatch):
    """The CLI's value comes from the dataclass: change the default and the composed config follows (the test
    above would otherwise pass by two copies agreeing)."""
    from scanreg.stages.icp.point import Horn

    field = {f.name: f for f in dataclasses.fields(Horn.Params)}["max_iterations"]
    monkeypatch.setattr(field, "default", 77)
    from scanreg.stages.registry import store_schema

    store_schema("icp", "horn", Horn.Params)
    try:
        assert compose(["icp=horn"]).icp.max_iterations == 77
    finally:
        monkeypatch.undo()
        store_schema("icp", "horn", Horn.Params)
