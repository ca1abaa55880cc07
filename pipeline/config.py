"""Configuration helpers shared by stages: distance units, the run context, paths to shared data."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

PROJECT_ROOT = Path(__file__).resolve().parents[1]
"""The source checkout (``pipeline/`` is the package ``scanreg``) in an editable install; in a wheel install the
folder holding the package, which is no checkout: :func:`shared_data_dir` and :func:`git_revision` check."""

CONF_PACKAGE = "scanreg.conf"
"""The package holding the YAML configs, Hydra's primary config source ``pkg://scanreg.conf``."""


def conf_dir() -> Path:
    """The folder of the shipped configs (``conf/`` of the checkout, or the installed package's copy)."""
    from importlib.resources import files

    return Path(str(files(CONF_PACKAGE)))


def search_path_override(config_dirs) -> list[str]:
    """``hydra.searchpath=[...]`` for extra config folders (a user's experiments and presets), or nothing."""
    dirs = [d if "://" in str(d) else f"file://{Path(d).expanduser().resolve()}" for d in config_dirs]
    return [f"hydra.searchpath=[{','.join(dirs)}]"] if dirs else []


def compose(overrides=(), config_name: str = "config", config_dirs=(), return_hydra_config: bool = False):
    """The run configuration as ``scanreg`` composes it: the shipped configs (``pkg://scanreg.conf``), plus
    ``config_dirs`` on Hydra's search path, with command-line style ``overrides``. Returns a ``DictConfig``
    (with its ``hydra`` node when ``return_hydra_config``)."""
    from hydra import compose as hydra_compose, initialize_config_module

    with initialize_config_module(CONF_PACKAGE, version_base="1.3"):
        return hydra_compose(config_name, overrides=[*overrides, *search_path_override(config_dirs)],
                             return_hydra_config=return_hydra_config)


class Distances(str, Enum):
    """How a stage reads its distance parameters."""

    spacing = "spacing"
    """Multiples of the run's sampling spacing (median nearest-neighbour distance, see ``estimate_spacing``)."""
    absolute = "absolute"
    """Input units (the units of the mesh or cloud files: mm for dental scans, m for the Stanford bunny)."""


def to_abs(value: float | None, unit: Distances, spacing: float) -> float | None:
    """Turn a distance parameter into input units."""
    if value is None:
        return None
    return float(value) * spacing if unit == Distances.spacing else float(value)


def shared_data_dir() -> Path:
    """``$SCANREG_SHARED_DATA``, else ``../shared/data`` beside the project root."""
    env = os.environ.get("SCANREG_SHARED_DATA")
    return Path(env) if env else (PROJECT_ROOT.parent / "shared" / "data")  # beside a checkout


def expand_path(s: str) -> str:
    """``shared:REL`` -> a path under :func:`shared_data_dir`; other strings unchanged (``pkg:`` is io's)."""
    if s.startswith("shared:"):
        return str(shared_data_dir() / s[len("shared:") :])
    return s


@dataclass
class Context:
    """What a stage may use besides its own parameters; filled by the runner as the run proceeds."""

    seed: int
    run_dir: Path
    spacing: float = float("nan")
    """Sampling spacing of the run in input units (set after sampling)."""
    diagonal: float = float("nan")
    """Bounding-box diagonal of the target in input units."""
    landmarks: Any = None
    """Picked landmark pairs ``(target (K, 3), source (K, 3))`` when the data gives them."""
    target_mesh: Any = None
    """The (repaired) target mesh when the target is a mesh: ICP can pair with its triangles."""
    stages: dict[str, Any] = field(default_factory=dict)
    """Built helper stages a coarse stage may use: ``salience``, ``descriptor``, ``matcher``."""
    step_metrics: dict[str, list[float]] = field(default_factory=dict)
    """Per-iteration metrics (e.g. ``icp_rms``), logged as MLflow step metrics."""
    verbose: bool = False
    coarse_trace: Any = None
    """What the coarse stage compared, for the evaluation (``scanreg.metrics.field_metrics``): ``keypoints_target``,
    ``keypoints_source`` (positions, own frames), ``matches_target``, ``matches_source`` (descriptor matches'
    points, before RANSAC) and ``ransac_inliers`` (mask over the matches); each only when the stage has it."""

    def rng(self, salt: int = 0) -> np.random.Generator:
        return np.random.default_rng([self.seed, salt])


def git_revision() -> str:
    """The project's git commit (``+dirty`` when the work tree has changes), or ``unknown`` outside git."""
    import subprocess

    if not (PROJECT_ROOT / "pyproject.toml").is_file():  # an installed wheel: no checkout to ask
        return "unknown"
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=PROJECT_ROOT, capture_output=True,
                              text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=PROJECT_ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
