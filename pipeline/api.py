"""The Python API: register two scans in one call, compose configs, build single stages.

    import scanreg
    res = scanreg.register("scan.ply", "ct.stl")                  # paths, as on the command line
    res = scanreg.register(src_xyz, tgt_xyz, overrides=["icp=gicp"])  # (N, 3) or (N, 6) NumPy arrays
    res.T_target_source, res.metrics["rms"], res.histories["icp_rms"]

    rec = scanreg.reconstruct("scans/")                           # many scans of one object into one model
    rec.poses["bun045.ply"], rec.mesh, rec.merged, rec.unplaced

    cfg = scanreg.compose(["icp=horn", "icp.tau=1e-6"])            # the run config, as scanreg composes it
    icp = scanreg.build_stage("icp", "horn", tau=1e-6)            # one stage, from the registry by name

Inputs may be paths (any format scanreg reads, ``pkg:`` and ``shared:`` included), NumPy arrays of points
(``(N, 3)``, or ``(N, 6)`` with normals), or Open3D ``PointCloud`` / ``TriangleMesh`` objects. In-memory inputs
are written into the run directory (``inputs/``) and read back through the same validating readers as files, so
that the API and the CLI run exactly the same pipeline and give the same transform for the same config.
"""

from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from scanreg.app.arguments import quote_value as _quote
from scanreg.app.config import compose
from scanreg.errors import ConfigError, InputError, ScanregError
from scanreg.types import Reconstruction, Result

__all__ = ["Reconstruction", "Result", "build_stage", "compose", "reconstruct", "register", "run_config"]


def build_stage(family: str, name: str, **params: Any):
    """One stage from its family's registry by name, its ``Params`` validated (``ConfigError`` on a bad name or
    value), e.g. ``build_stage("sampler", "barycentric", n_points=5000)``: the same stage, with the same
    defaults, as the CLI builds from ``sampler=barycentric sampler.n_points=5000``. A coarse stage that uses
    helper stages gets the default ones of the config (``salience``, ``descriptor``, ``matcher``). Stages run with a
    :class:`scanreg.types.RunContext`."""
    from scanreg.stages.registry import REGISTRIES, load_all

    load_all()
    if family not in REGISTRIES:
        raise ConfigError(f"unknown stage family '{family}'; valid: {', '.join(REGISTRIES)}")
    cls, p = REGISTRIES[family].params({"name": name, **params})
    helpers = {}
    if getattr(cls, "uses", ()):
        from scanreg.runner import build_stages

        built = build_stages(compose(["data.source=_", "data.target=_"])).helpers
        helpers = {fam: built[fam] for fam in cls.uses}
    return cls(p, **helpers)


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


@contextmanager
def _run_folder(run_dir: str | Path | None):
    """The run's folder: ``run_dir``, or a new temporary one (``scanreg-*`` in the system's temporary folder,
    kept after the call: it holds the run's artifacts), which is removed again when the call fails (it would
    hold only the inputs and the config of a run that gave nothing)."""
    temp = run_dir is None
    path = Path(tempfile.mkdtemp(prefix="scanreg-")) if temp else Path(run_dir)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=path, prefix=".scanreg-write-test-")  # writable, not just there
        probe.close()
    except OSError as e:
        raise InputError(f"run_dir {path}: cannot write there ({e.strerror or e}); give a writable folder") from None
    try:
        yield path
    except BaseException:
        if temp:
            shutil.rmtree(path, ignore_errors=True)
        raise


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
    with _run_folder(run_dir) as run_dir:
        folder = run_dir / "inputs"
        given = {"source": source, "target": target}
        paths = {role: _as_input(obj, role, folder) for role, obj in given.items()}
        ovs = [f"data.{role}={_quote(path)}" for role, path in paths.items()]
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
        in_memory = {paths[role]: (role, type(obj).__name__) for role, obj in given.items()
                     if not isinstance(obj, (str, Path))}
        with _named_as_given(in_memory):
            return run_config(cfg, run_dir, tracking, user)


@contextmanager
def _named_as_given(written: dict[str, tuple[str, str]]):
    """An error about an input the caller gave in memory names it as such ("source (the ndarray given)"), not by
    the file it was written to for the run (which goes with the failed run's folder); ``written``: each such
    file's path -> (its role, the type given)."""
    try:
        yield
    except ScanregError as e:
        text = str(e)
        for path, (role, kind) in written.items():
            text = text.replace(f"{role} {path}", f"{role} (the {kind} given)")
            text = text.replace(path, f"the {role} (the {kind} given)")
        if text != str(e):
            e.args = (text, *e.args[1:])
        raise


def reconstruct(scans: Any, *, poses: Any = None, overrides: Sequence[str] = (), tracking: bool = False,
                run_dir: str | Path | None = None, config_dirs: Sequence[str] = ()) -> Reconstruction:
    """Register many scans of one object into one model, as ``scanreg data=scanset data.scans=...`` does, and
    return the :class:`Reconstruction` (each scan's ``T_world_scan``, the world its first scan's frame in sorted
    order; the merged points; the surface; the metrics).

    - ``scans``: a folder, a glob, or a list whose items are paths, (N, 3)/(N, 6) NumPy arrays or Open3D
      geometries (in-memory scans are named ``scan000`` ... in their order);
    - ``poses``: ground truth for the evaluation: a Stanford ``.conf``, a folder of 4x4 files, or a list of 4x4
      arrays (one per scan, ``T_world_scan`` in any common frame; None for a scan without one: it is registered,
      not evaluated, as ``data.poses`` with a file missing; at least two need one);
    - ``overrides``, ``tracking``, ``run_dir``, ``config_dirs``: as for :func:`register`.
    """
    with _run_folder(run_dir) as run_dir:
        folder = run_dir / "inputs"
        items = [scans] if isinstance(scans, (str, Path)) else list(scans)
        if len(items) < 2 and not any(isinstance(obj, (str, Path)) for obj in items):
            raise InputError(f"reconstruct: {len(items)} scan(s) given; a scan set needs at least 2 (a folder, a "
                             "glob, or a list of paths, arrays or Open3D geometries)")
        paths = [_as_input(obj, f"scan{k:03d}", folder) for k, obj in enumerate(items)]
        ovs = ["data=scanset", "data.scans=[" + ",".join(_quote(p) for p in paths) + "]"]
        if poses is not None:
            if isinstance(poses, (str, Path)):
                ovs.append(f"data.poses={_quote(str(poses))}")
            else:
                Ts = [None if T is None else np.asarray(T, dtype=np.float64) for T in poses]
                if len(Ts) != len(paths) or any(T is not None and T.shape != (4, 4) for T in Ts):
                    raise InputError(f"poses: expected one 4x4 transform (or None) per scan ({len(paths)}), got "
                                     f"{[None if T is None else T.shape for T in Ts]}")
                posed = sum(T is not None for T in Ts)
                if posed < 2:
                    raise InputError(f"poses: {posed} of the {len(Ts)} scans have a pose; at least two need one to "
                                     "evaluate the set (or poses=None: not evaluated)")
                (folder / "poses").mkdir(parents=True, exist_ok=True)
                for path, T in zip(paths, Ts):
                    if T is not None:  # a scan without a pose: registered, not evaluated (as a missing file)
                        np.savetxt(folder / "poses" / f"{Path(path).stem}.txt", T)
                ovs.append(f"data.poses={_quote(str(folder / 'poses'))}")
        user = list(overrides)
        if not tracking and not any(o.split("=")[0].lstrip("+") == "tracking" for o in user):
            user.append("tracking=none")
        cfg = compose([*user, *ovs], config_dirs=config_dirs)
        res = run_config(cfg, run_dir, tracking, user)
        reg = res.scanset
        if reg is None:
            raise InputError("reconstruct: the run registered no scan set")
        return Reconstruction({n: T for n, T in zip(reg.names, reg.poses) if T is not None}, reg.merged, reg.surface,
                          res.metrics, reg.unplaced(), [[reg.names[k] for k in g] for g in reg.groups if g],
                          run_dir, res.artifacts, res.run_id)


def run_config(cfg, run_dir: str | Path, tracking: bool = False, overrides: Sequence[str] = ()) -> Result:
    """Run a composed config (:func:`compose`) into ``run_dir``, as the CLI runs one; ``tracking``: log it with
    the config's tracking backend."""
    import time

    from omegaconf import OmegaConf

    from scanreg.app.tracking import TRACKING, RunRecord, flatten
    from scanreg.runner import run_pipeline

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    resolved = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    tracker = TRACKING.build(cfg.tracking) if tracking else None
    record = RunRecord(run_name="api " + " ".join(overrides)[:240], params=flatten(resolved),
                       tags={"scanreg.run_dir": str(run_dir), "scanreg.overrides": " ".join(overrides),
                             "scanreg.api": "1"}, start_time=int(time.time() * 1000))
    config_file = run_dir / "config.yaml"
    config_file.write_text(OmegaConf.to_yaml(resolved))
    try:
        res = run_pipeline(cfg, run_dir)
    except BaseException as e:
        if tracker is not None:
            reason = str(e) if isinstance(e, ScanregError) else f"internal error: {type(e).__name__}: {e}"
            status = "KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED"
            tracker.log_run(record.ended(status, reason.splitlines()[0], getattr(e, "metrics", None),
                                         artifacts=[config_file]))
        raise
    if tracker is not None:
        res.run_id = tracker.log_run(record.ended("FINISHED", None, res.metrics, res.histories,
                                                  [config_file, *res.artifacts]))
    return res
