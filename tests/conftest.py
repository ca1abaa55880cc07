import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("SCANREG_SHARED_DATA", ROOT.parent / "shared" / "data"))


def shared(rel: str) -> Path:
    """A file under ../shared/data, or skip the test with a clear message when the folder is absent."""
    p = SHARED / rel
    if not p.exists():
        pytest.skip(f"real scan data not available: {p} (../shared/data beside the project root)")
    return p


def children() -> set[int]:
    """This process's child processes, zombies included (Linux's /proc)."""
    me, found = str(os.getpid()), set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[1] == me:
            found.add(int(stat.parent.name))
    return found


def settled(before: set[int], seconds: float = 5.0) -> bool:
    """Whether every child process started since ``before`` (:func:`children`) is gone, reaped (threads reap
    some), waiting up to ``seconds``."""
    import time

    end = time.monotonic() + seconds
    while not children() <= before:
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


def pkg_file(spec: str) -> Path:
    from scanreg.io import resolve_path

    return resolve_path(spec)


@pytest.fixture(scope="session")
def mlflow_uri(tmp_path_factory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"


def run_cli(args: list[str], cwd: Path, uri: str | None = None, timeout: int = 300, module: str = "scanreg.app"):
    env = dict(os.environ)
    env.pop("SCANREG_SWEEP", None)
    if uri:
        env["MLFLOW_TRACKING_URI"] = uri
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def rng(seed=0):
    return np.random.default_rng(seed)


def runs(uri: str, experiment: str):
    """Every run of an MLflow experiment as a pandas frame (the experiment must exist)."""
    import mlflow

    mlflow.set_tracking_uri(uri)
    exp = mlflow.get_experiment_by_name(experiment)
    assert exp is not None, f"experiment {experiment} was not created"
    return mlflow.search_runs([exp.experiment_id])


def stage_ctx(seed=0):
    """A run context for stages called directly (no run directory)."""
    from scanreg.types import RunContext

    return RunContext(seed=seed)


def build(reg, name, **kw):
    """A stage of registry ``reg`` by name, its Params validated."""
    from scanreg.stages.registry import make_params

    cls = reg.get(name)
    return cls(make_params(cls.Params, kw, name))


def oriented_triangles(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """A mesh's triangles as rows of 9 coordinates, each the lexicographically smallest of its three rotations
    (orientation kept), the rows sorted: equal for the same surface in any numbering."""
    t = v[f]
    rows = np.stack([t, t[:, [1, 2, 0]], t[:, [2, 0, 1]]], 1).reshape(3 * len(f), 9)
    face = np.repeat(np.arange(len(f)), 3)
    order = np.lexsort(tuple(rows[:, k] for k in range(8, -1, -1)) + (face,))  # by face, then by the row
    rows = rows[order[::3]]
    return rows[np.lexsort(rows.T[::-1])]


def build_coarse(name, helpers=None, **kw):
    """A coarse stage of ``COARSE`` by name, its Params validated, built with the helper stages it ``uses``
    (``helpers``: family -> built stage; a family not given gets None, for tests that use only its Params)."""
    from scanreg.stages.registry import COARSE, make_params

    cls = COARSE.get(name)
    helpers = helpers or {}
    return cls(make_params(cls.Params, kw, name), **{fam: helpers.get(fam) for fam in cls.uses})
