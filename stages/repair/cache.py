"""Repaired meshes cached by content (``repair.cache``): a sweep over registration parameters repairs each scan
once.

The key is a SHA-256 of the input mesh's arrays (vertices, faces, closure faces), the backend's name and every
repair parameter except the cache's own, the seed (the audit samples with it), the versions of scanreg,
pymeshfix and pymeshlab, and a hash of the repair code's source files. An entry holds the repaired mesh and the repair's metrics (unprefixed), in one ``.npz``
written to a temporary file and renamed into place, so concurrent jobs of a sweep never read a half-written entry
While a job repairs a mesh it holds a lock file beside the entry (created exclusively); a parallel job that
needs the same entry waits for it (up to ``WAIT_S``) instead of repairing the same scan again, and repairs it
itself when none appears (the other job's repair failed, or a lock left by a killed job, older than ``STALE_S``).

Only repairs that pass the guard (or run with ``check_only``) are stored; a failing repair fails again in every
job. The metrics of a hit are those of the repair that made the entry (``repair_backend_time_s`` and
``repair_audit_time_s`` included); ``repair_cache_hit`` says 1, and the runner's ``time_repair_s`` is the time
the hit took.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import time
from pathlib import Path

import numpy as np

from scanreg.errors import note
from scanreg.geometry import Mesh
from scanreg.io import write_atomic
from scanreg.types import Repaired, RunContext

CACHE_FORMAT = 1
"""Bumped when the entry layout or the meaning of a stored metric changes."""

WAIT_S = 900.0
"""Longest wait, in seconds, for an entry that another job is making."""

STALE_S = 3600.0
"""A lock file older than this many seconds is left over from a killed job and ignored."""

DEFAULT_DIR = "outputs/cache/repair"
"""Where entries go when ``repair.cache_dir`` is null: under the working directory's ``outputs/``, beside the
runs and the MLflow store."""


def _versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    out = []
    for pkg in ("scanreg", "pymeshfix", "pymeshlab"):
        try:
            out.append(f"{pkg}={version(pkg)}")
        except PackageNotFoundError:
            out.append(f"{pkg}=none")
    return ",".join(out)


def _code_fingerprint() -> str:
    """A hash of the repair code itself (the backends, the audit, the topology, self-intersection, shell and
    geometry helpers), so that an edited repair never reuses entries made by the old one even at the same
    version number."""
    import scanreg.geometry
    import scanreg.mesh

    here = Path(__file__).parent
    h = hashlib.sha256()
    kernel = [Path(m.__file__).parent for m in (scanreg.mesh, scanreg.geometry)]
    for f in sorted(here.glob("*.py")) + [f for d in kernel for f in sorted(d.glob("*.py"))]:
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def cache_key(stage, mesh: Mesh, seed: int) -> str:
    """The hex SHA-256 naming ``stage``'s repair of ``mesh`` with ``seed`` (see the module docstring)."""
    h = hashlib.sha256()
    params = {k: v for k, v in dataclasses.asdict(stage.p).items() if k not in ("cache", "cache_dir", "apply_to")}
    h.update(json.dumps({"format": CACHE_FORMAT, "backend": stage.name, "params": params, "seed": int(seed),
                         "versions": _versions(), "code": _code_fingerprint(), "closure_faces": int(mesh.closure_faces),
                         "shapes": [list(mesh.vertices.shape), list(mesh.faces.shape)],
                         "dtypes": [str(mesh.vertices.dtype), str(mesh.faces.dtype)]},
                        sort_keys=True, default=str).encode())
    h.update(np.ascontiguousarray(mesh.vertices).tobytes())
    h.update(np.ascontiguousarray(mesh.faces).tobytes())
    return h.hexdigest()


class RepairCache:
    """A directory of repaired meshes keyed by :func:`cache_key`."""

    def __init__(self, directory: str | Path):
        self.dir = Path(directory)

    def path(self, key: str) -> Path:
        return self.dir / f"{key}.npz"

    def load(self, key: str, source: str) -> tuple[Mesh, dict[str, float]] | None:
        """The entry's mesh (named ``source``) and metrics, or None when there is none or it cannot be read."""
        p = self.path(key)
        try:
            with np.load(p, allow_pickle=False) as z:
                mesh = Mesh(z["vertices"], z["faces"], source, int(z["closure_faces"]))
                metrics = json.loads(str(z["metrics"]))
        except (OSError, KeyError, ValueError):
            return None
        return mesh, {k: float(v) for k, v in metrics.items()}

    def store(self, key: str, mesh: Mesh, metrics: dict[str, float]) -> Path:
        """Write the entry atomically (:func:`scanreg.io.write_atomic`)."""
        buf = io.BytesIO()
        np.savez(buf, vertices=mesh.vertices, faces=mesh.faces, closure_faces=np.int64(mesh.closure_faces),
                 metrics=np.str_(json.dumps(metrics, allow_nan=True)))
        return write_atomic(self.path(key), buf.getvalue())

    def lock(self, key: str) -> Path | None:
        """Take the lock on ``key`` (the path to release), or None when another job holds it."""
        self.dir.mkdir(parents=True, exist_ok=True)
        path = self.dir / f".{key}.lock"
        try:
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            return path
        except FileExistsError:
            try:
                if time.time() - path.stat().st_mtime > STALE_S:  # left by a killed job: take it over
                    path.touch()
                    return path
            except FileNotFoundError:
                return self.lock(key)
            return None

    def wait(self, key: str, source: str, timeout: float = WAIT_S) -> tuple[Mesh, dict[str, float]] | None:
        """The entry for ``key`` once the job holding its lock is done with it (None: it made none)."""
        lock = self.dir / f".{key}.lock"
        end = time.monotonic() + timeout
        while lock.exists() and time.monotonic() < end:
            time.sleep(0.1)
        return self.load(key, source)


def cache_enabled(mode: str, in_sweep: bool) -> bool:
    """``repair.cache``: ``on`` always, ``off`` never, ``auto`` in Hydra multirun sweeps only."""
    return mode == "on" or (mode == "auto" and in_sweep)


def cached_repair(stage, mesh: Mesh, ctx: RunContext, cache: RepairCache | None) -> Repaired:
    """:func:`~scanreg.stages.repair.audit.repair_with_audit` through ``cache`` (None: no cache). The metrics
    gain ``cache_hit`` 0/1 when a cache is used."""
    from scanreg.stages.repair.audit import repair_with_audit

    if cache is None:
        return repair_with_audit(stage, mesh, ctx)
    key = cache_key(stage, mesh, ctx.seed)
    hit = cache.load(key, mesh.source)
    lock = None
    if hit is None:
        lock = cache.lock(key)
        if lock is None:  # another job of the sweep is repairing the same mesh: wait for its entry
            hit = cache.wait(key, mesh.source)
    if hit is not None:
        out, m = hit
        note(f"repair={stage.name}: {mesh.source or 'mesh'}: the repaired mesh from the cache ({cache.path(key)})")
        return Repaired(mesh if stage.p.check_only else out, {**m, "cache_hit": 1.0})
    try:
        res = repair_with_audit(stage, mesh, ctx)
        stored = mesh if stage.p.check_only else res.mesh  # (with check_only the audit ran on what it would make)
        cache.store(key, stored, res.metrics)
    finally:
        if lock is not None:
            lock.unlink(missing_ok=True)
    return Repaired(res.mesh, {**res.metrics, "cache_hit": 0.0})
