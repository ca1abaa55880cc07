"""Start-up measures of the ``scanreg`` command. Each is kept because it saves a user 0.3 s or more of every
run (``experiments/benchmarks/end_to_end.md`` measures them) and each has a test:

1. :func:`defer_open3d_viewer`: ``import open3d`` loads its plotly/dash viewer eagerly, which scanreg never uses;
   a stand-in module defers it to its first use (``tests/test_startup.py``).
2. :func:`prestart_tracking_worker`: MLflow's import (it imports pandas, pyarrow, SQLAlchemy...) runs in a
   worker process started with the command, while the run works; the run's record is handed to it at the end
   (:meth:`scanreg.app.tracking.MlflowTracking.log_run`).
3. :func:`exit_now`: after a single run has written its outputs and logged its run, the interpreter's teardown
   of the imported module graph (Open3D, SciPy, Hydra) only delays the prompt.
4. :func:`quick_help`: ``scanreg --help`` without Hydra's help machinery, which formats every config group's
   options whether or not the template uses them.

Library callers use :func:`scanreg.app.main.main` and the Python API, which need none of these.
"""

from __future__ import annotations

import json
import sys
import types

# ------------------------------------------------------------------------------- 1. Open3D's plotly viewer


_NAME = "open3d.visualization.draw_plotly"
_FUNCS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _load() -> types.ModuleType:
    import importlib

    stub = sys.modules.get(_NAME)
    if stub is not None and not getattr(stub, "_scanreg_stub", False):
        return stub  # loaded already
    sys.modules.pop(_NAME, None)
    real = importlib.import_module(_NAME)
    parent = sys.modules.get("open3d.visualization")
    if parent is not None:  # importing the submodule rebinds the parent's name 'draw_plotly' to the module
        for f in _FUNCS:
            if hasattr(real, f):
                setattr(parent, f, getattr(real, f))
    return real


def _forwarder(name: str):
    def forward(*args, **kwargs):
        return getattr(_load(), name)(*args, **kwargs)

    forward.__name__ = forward.__qualname__ = name
    forward.__doc__ = f"Open3D's ``{name}`` (its module imported on first use by scanreg's start-up shim)."
    return forward


def _getattr(name: str):
    if name.startswith("__"):
        raise AttributeError(name)
    return getattr(_load(), name)


def defer_open3d_viewer() -> bool:
    """Put the stand-in in place unless Open3D (or the module) is imported already; True if it did."""
    if "open3d" in sys.modules or _NAME in sys.modules:
        return False
    stub = types.ModuleType(_NAME, "scanreg's stand-in for Open3D's plotly viewer; see scanreg.app.startup.")
    stub._scanreg_stub = True
    for f in _FUNCS:
        setattr(stub, f, _forwarder(f))
    stub.__getattr__ = _getattr
    sys.modules[_NAME] = stub
    return True


# ------------------------------------------------------------------------------------ 2. the MLflow worker

NO_RUN_FLAGS = ("-h", "--help", "--hydra-help", "-c", "--cfg", "--info", "-i")
"""Hydra's flags that show something instead of running."""


def is_multirun(argv: list[str]) -> bool:
    return any(a in ("-m", "--multirun") or a.startswith("hydra.mode=") for a in argv)


def may_track_single_run(argv: list[str]) -> bool:
    """Whether ``scanreg ARGV`` may be a single run that logs to MLflow (the default): not a ``-m`` sweep, not
    ``tracking=`` something else. A config may still choose otherwise: the worker is then dropped."""
    if is_multirun(argv) or any(a in NO_RUN_FLAGS for a in argv):
        return False
    return not any(a.replace(" ", "").startswith("tracking=") and a.replace(" ", "") != "tracking=mlflow"
                   for a in argv)


class TrackingWorker:
    """``python -m scanreg.app.tracking``, started early; :meth:`log` hands it one run to log."""

    def __init__(self):
        import subprocess

        self.proc = subprocess.Popen([sys.executable, "-m", "scanreg.app.tracking"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)

    def log(self, request: dict) -> str:
        """Send the request, wait for the answer: the run id (a ``RuntimeError`` with the worker's error)."""
        from scanreg.app.tracking import REPLY

        try:
            self.proc.stdin.write(json.dumps(request) + "\n")
            self.proc.stdin.close()
        except (BrokenPipeError, OSError):
            pass  # the worker is gone: the reply says so
        for line in self.proc.stdout:
            if line.startswith(REPLY):
                reply = json.loads(line[len(REPLY):])
                if "error" in reply:
                    raise RuntimeError(reply["error"])
                return reply["run_id"]
        raise RuntimeError(f"the MLflow logging process ended (exit {self.proc.wait()})")

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()


_worker: TrackingWorker | None = None


def prestart_tracking_worker() -> None:
    """Start the MLflow worker now (once), so that its import of MLflow overlaps this process's own imports and
    the run; the run's tracking takes it (:func:`take_tracking_worker`), or :func:`drop_tracking_worker`
    stops it."""
    global _worker
    if _worker is None:
        _worker = TrackingWorker()


def take_tracking_worker() -> TrackingWorker | None:
    """The prestarted worker, once (None when there is none)."""
    global _worker
    worker, _worker = _worker, None
    return worker


def drop_tracking_worker() -> None:
    """Stop the prestarted worker if no run took it."""
    worker = take_tracking_worker()
    if worker is not None:
        worker.stop()


# -------------------------------------------------------------------------------------- 3. exit at once

def exit_now(code: int | str | None) -> None:
    """Exit with ``code`` without the interpreter's teardown: standard output and error and the log handlers
    flushed and closed first (every file a run writes is closed when written)."""
    import logging
    import os

    if isinstance(code, str):  # SystemExit("message") prints the message and exits 1
        print(code, file=sys.stderr)
        code = 1
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        logging.shutdown()
        os._exit(code or 0)


# --------------------------------------------------------------------------------------- 4. quick --help

def quick_help(overrides: list[str]) -> str | None:
    """``scanreg --help``'s text without Hydra's help machinery, or None to let Hydra write it. scanreg's
    template (``hydra.help.template`` in ``conf/config.yaml``) lists the groups itself and uses none of Hydra's
    variables, so substituting nothing gives Hydra's text (``tests/test_cli.py`` compares the two)."""
    import string

    from scanreg.app.config import compose

    try:
        return string.Template(str(compose(overrides, return_hydra_config=True).hydra.help.template)).substitute({})
    except Exception:  # noqa: BLE001  # Hydra's own path reports it, or the template uses Hydra's variables
        return None
