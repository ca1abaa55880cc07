"""The Python API: register two scans in one call, compose configs, build single stages.

    import scanreg
    res = scanreg.register("scan.ply", "ct.stl")                  # paths, as on the command line
    res = scanreg.register(src_xyz, tgt_xyz, overrides=["icp=gicp"])  # (N, 3) or (N, 6) NumPy arrays
    res.T_target_source, res.metrics["rms"], res.histories["icp_rms"]

    cfg = scanreg.compose(["icp=horn", "icp.tau=1e-6"])            # the run config, as scanreg composes it
    icp = scanreg.build_stage("icp", "horn", tau=1e-6)            # one stage, from the registry by name

Inputs may be paths (any format scanreg reads, ``pkg:`` and ``shared:`` included), NumPy arrays of points
(``(N, 3)``, or ``(N, 6)`` with normals), or Open3D ``PointCloud`` / ``TriangleMesh`` objects. In-memory inputs
are written into the run directory (``inputs/``) and read back through the same validating readers as files, so
that the API and the CLI run exactly the same pipeline and give the same transform for the same config.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from scanreg.config import compose
from scanreg.errors import ConfigError, InputError, ScanregError

__all__ = ["Result", "build_stage", "compose", "register"]


@dataclass
class Result:
    """What one registration produced."""

    T_target_source: np.ndarray
    """4x4 transform mapping source points into the target frame (input units)."""
    metrics: dict[str, float]
    """Every metric the run logs (the names of ``result.json`` and MLflow: ``rms``, ``rotation_error_deg``, ...)."""
    histories: dict[str, list[float]] = field(default_factory=dict)
    """Per-iteration metrics, e.g. ``icp_rms`` (the ICP RMS at each iterate; MLflow step metric ``icp_rms_step``)."""
    run_dir: Path | None = None
    """The folder holding the artifacts."""
    artifacts: list[Path] = field(default_factory=list)
    """Files written: ``result.json``, ``T_target_source.txt``, ``aligned_source.ply``, deviation maps, ..."""
    run_id: str | None = None
    """The MLflow run id when ``tracking=True``."""

    @property
    def success(self) -> bool | None:
        """With ground truth: rotation and translation errors under the ``evaluate.success_*`` limits."""
        s = self.metrics.get("success")
        return None if s is None else bool(s)


def build_stage(family: str, name: str, **params: Any):
    """One stage from its family's registry by name, its ``Params`` validated (``ConfigError`` on a bad name or
    value), e.g. ``build_stage("sampler", "barycentric", n_points=5000)``. Stages run with a
    :class:`scanreg.config.Context` (``Context(seed=0, run_dir=Path("."))``; distances in spacings need its
    ``spacing`` set)."""
    from scanreg.registry import REGISTRIES, load_all

    load_all()
    if family not in REGISTRIES:
        raise ConfigError(f"unknown stage family '{family}'; valid: {', '.join(REGISTRIES)}")
    return REGISTRIES[family].build({"name": name, **params})


def _quote(path: str) -> str:
    """A path as a quoted Hydra override value (spaces, ``=``, commas and brackets stay literal)."""
    return "'" + path.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _as_input(obj: Any, role: str, folder: Path) -> str:
    """A path scanreg's readers take for ``obj`` (written into ``folder`` when it is in memory)."""
    if isinstance(obj, (str, Path)):
        return str(obj)
    folder.mkdir(parents=True, exist_ok=True)
    if isinstance(obj, np.ndarray):
        a = np.asarray(obj, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] not in (3, 6):
            raise InputError(f"{role}: a NumPy array must be (N, 3) points or (N, 6) points + normals, "
                             f"got shape {a.shape}")
        path = folder / f"{role}.npy"
        np.save(path, a)
        return str(path)
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover: open3d is a dependency
        o3d = None
    if o3d is not None and isinstance(obj, o3d.geometry.TriangleMesh):
        from scanreg.geometry import Mesh
        from scanreg.io import write_ply

        path = folder / f"{role}.ply"
        write_ply(path, Mesh(np.asarray(obj.vertices, dtype=np.float64), np.asarray(obj.triangles, dtype=np.int64)))
        return str(path)
    if o3d is not None and isinstance(obj, o3d.geometry.PointCloud):
        pts = np.asarray(obj.points, dtype=np.float64)
        if obj.has_normals():
            pts = np.hstack([pts, np.asarray(obj.normals, dtype=np.float64)])
        return _as_input(pts, role, folder)
    raise InputError(f"{role}: expected a path, an (N, 3)/(N, 6) NumPy array or an Open3D PointCloud/TriangleMesh, "
                     f"got {type(obj).__name__}")


def register(source: Any, target: Any, *, gt: Any = None, landmarks: Any = None, overrides: Sequence[str] = (),
             tracking: bool = False, run_dir: str | Path | None = None, config_dirs: Sequence[str] = ()) -> Result:
    """Register ``source`` to ``target`` with the default pipeline (or as ``overrides`` say) and return the
    :class:`Result`; ``T_target_source`` maps source points into the target frame.

    - ``gt``: the true ``T_target_source`` (4x4 array or a file) for the error metrics;
    - ``landmarks``: picked pairs, a CSV path or an array of rows ``target x y z, source x y z`` (use with
      ``overrides=["coarse=landmarks"]``);
    - ``overrides``: command-line style, e.g. ``["icp=gicp", "sampler.n_points=50000"]``;
    - ``tracking``: log the run to MLflow (the store ``tracking.uri`` or ``$MLFLOW_TRACKING_URI`` names);
    - ``run_dir``: where the artifacts go (default: a new temporary folder);
    - ``config_dirs``: extra config folders (your presets and experiments), as ``--config-dir`` on the CLI.

    Raises :class:`scanreg.errors.ScanregError` (``InputError``, ``ConfigError``, ``StageError``) with the same
    one-line messages the CLI prints.
    """
    from omegaconf import OmegaConf

    from scanreg.runner import run_pipeline

    run_dir = Path(run_dir) if run_dir is not None else Path(tempfile.mkdtemp(prefix="scanreg-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    folder = run_dir / "inputs"
    ovs = [f"data.source={_quote(_as_input(source, 'source', folder))}",
           f"data.target={_quote(_as_input(target, 'target', folder))}"]
    if gt is not None:
        if isinstance(gt, (str, Path)):
            ovs.append(f"data.gt={_quote(str(gt))}")
        else:
            T = np.asarray(gt, dtype=np.float64)
            if T.shape != (4, 4):
                raise InputError(f"gt: expected a 4x4 transform, got shape {T.shape}")
            folder.mkdir(parents=True, exist_ok=True)
            np.savetxt(folder / "gt.txt", T)
            ovs.append(f"data.gt={_quote(str(folder / 'gt.txt'))}")
    if landmarks is not None:
        if isinstance(landmarks, (str, Path)):
            ovs.append(f"data.landmarks={_quote(str(landmarks))}")
        else:
            L = np.asarray(landmarks, dtype=np.float64)
            if L.ndim != 2 or L.shape[1] != 6:
                raise InputError(f"landmarks: expected rows of 6 numbers (target x y z, source x y z), got {L.shape}")
            folder.mkdir(parents=True, exist_ok=True)
            np.savetxt(folder / "landmarks.csv", L, delimiter=",")
            ovs.append(f"data.landmarks={_quote(str(folder / 'landmarks.csv'))}")
    user = list(overrides)
    if not tracking and not any(o.split("=")[0].lstrip("+") == "tracking" for o in user):
        user.append("tracking=none")
    # data=files unless the caller chose otherwise; the inputs go last so that they win
    cfg = compose(["data=files", *user, *ovs], config_dirs=config_dirs)
    OmegaConf.resolve(cfg)
    run = None
    if tracking:
        from scanreg.registry import TRACKING, load_all
        from scanreg.tracking import flatten

        load_all()
        run = TRACKING.build(cfg.tracking).start_run(
            run_name="api " + " ".join(user)[:240], params=flatten(OmegaConf.to_container(cfg)),
            tags={"scanreg.run_dir": str(run_dir), "scanreg.overrides": " ".join(user), "scanreg.api": "1"},
            background=True)  # MLflow's import and store open while the pipeline runs
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    try:
        res = run_pipeline(cfg, run_dir)
    except BaseException as e:
        if run:
            reason = str(e) if isinstance(e, ScanregError) else f"internal error: {type(e).__name__}: {e}"
            run.end("KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED", reason.splitlines()[0])
        raise
    if run:
        run.log_metrics(res.metrics, res.step_metrics)
        run.log_artifacts([run_dir / "config.yaml", *res.artifacts])
        run.end("FINISHED")
    return Result(T_target_source=res.T_target_source, metrics=dict(res.metrics), histories=dict(res.step_metrics),
                  run_dir=run_dir, artifacts=list(res.artifacts), run_id=getattr(run, "run_id", None))
