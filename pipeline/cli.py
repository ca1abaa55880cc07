"""The ``scanreg`` command (the console script's entry point, :func:`main`).

Kept free of heavy imports: it starts the MLflow helper process of a single run (:class:`scanreg.tracking.
BackgroundRunLog`) before Hydra, Open3D or SciPy are imported, then hands over to :func:`scanreg.app.main`.
"""

from __future__ import annotations

import sys


NO_RUN_FLAGS = ("-h", "--help", "--hydra-help", "-c", "--cfg", "--info", "-i")
"""Hydra's flags that show something instead of running."""


def is_multirun(argv: list[str]) -> bool:
    return any(a in ("-m", "--multirun") or a.startswith("hydra.mode=") for a in argv)


def may_track_single_run(argv: list[str]) -> bool:
    """Whether ``scanreg ARGV`` may be a single run that logs to MLflow (the default): not a ``-m`` sweep, not
    ``tracking=`` something else. A config may still choose otherwise; :func:`scanreg.app.main` then stops the
    helper process once the config is composed."""
    if is_multirun(argv) or any(a in NO_RUN_FLAGS for a in argv):
        return False
    return not any(a.replace(" ", "").startswith("tracking=") and a.replace(" ", "") != "tracking=mlflow"
                   for a in argv)


def main() -> None:
    """The ``scanreg`` command: :func:`scanreg.app.main`; after a single run, exit without the interpreter's
    teardown.

    Once a single run has written its outputs and ended its MLflow run, tearing down the imported module graph
    (Open3D, SciPy, Hydra) and joining idle worker threads only delays the prompt, by 0.2-0.3 s of a run's
    start-up budget (``experiments/benchmarks/end_to_end.py``). Standard output and error and the log handlers
    are flushed and closed first; every file a run writes is closed when written. A ``-m`` sweep exits
    normally, so that its launcher shuts its workers down. Library callers use :func:`scanreg.app.main`, which
    returns or raises as usual."""
    import logging
    import os

    argv = sys.argv[1:]
    if may_track_single_run(argv):
        from scanreg import tracking

        tracking.prestart_helper()
    from scanreg.app import main as app_main

    code: int | str | None = 0
    try:
        app_main()
    except SystemExit as e:
        code = e.code
    tracking = sys.modules.get("scanreg.tracking")
    if tracking is not None:
        tracking.drop_prestarted()  # a run that stopped before it opened its MLflow run leaves no helper behind
    if is_multirun(argv):
        raise SystemExit(code)
    if isinstance(code, str):  # SystemExit("message") prints the message and exits 1
        print(code, file=sys.stderr)
        code = 1
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        logging.shutdown()
        os._exit(code or 0)


if __name__ == "__main__":
    main()
