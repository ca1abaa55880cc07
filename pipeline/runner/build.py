"""The stages of a run, built from its config: every name and parameter validated before any work."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

from scanreg.eval.metrics import EvalParams
from scanreg.runner.settings import MultiviewParams
from scanreg.stages.registry import COARSE, DATA, GRAPH, ICP, REGISTRIES, REPAIR, SAMPLER, SURFACE, load_all, make_params

HELPER_FAMILIES = ("salience", "descriptor", "matcher")
"""Families whose stages a coarse stage may use (its ``uses``); built and validated whatever the coarse stage."""


@dataclass
class Stages:
    """One built stage per family (the helpers inside the coarse stage that uses them) and the evaluation's
    parameters."""

    data: Any
    repair: Any
    sampler: Any
    coarse: Any
    icp: Any
    evaluate: EvalParams
    helpers: dict[str, Any] = field(default_factory=dict)
    """The built salience, descriptor and matcher stages (the coarse stage holds those it uses)."""
    graph: Any = None
    """A scan set's pose graph."""
    surface: Any = None
    """A scan set's surface reconstruction."""
    multiview: MultiviewParams = field(default_factory=MultiviewParams)
    """How a scan set is registered and merged."""


def build_stages(cfg: DictConfig) -> Stages:
    """Every configured stage, built (names and parameters validated) without running anything."""
    load_all()
    data, repair, sampler = DATA.build(cfg.data), REPAIR.build(cfg.repair), SAMPLER.build(cfg.sampler)
    helpers = {fam: REGISTRIES[fam].build(cfg[fam]) for fam in HELPER_FAMILIES}
    cls, params = COARSE.params(cfg.coarse)
    coarse = cls(params, **{fam: helpers[fam] for fam in cls.uses})
    icp = ICP.build(cfg.icp)
    evaluate = make_params(EvalParams, OmegaConf.to_container(cfg.evaluate, resolve=True), "evaluate")
    multiview = make_params(MultiviewParams, OmegaConf.to_container(cfg.multiview, resolve=True), "multiview")
    return Stages(data, repair, sampler, coarse, icp, evaluate, helpers, GRAPH.build(cfg.graph),
                  SURFACE.build(cfg.surface), multiview)
