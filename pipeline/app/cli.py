"""The ``scanreg`` command (the console script's entry point, :func:`main`): the start-up measures of
:mod:`scanreg.app.startup`, then the Hydra application :func:`scanreg.app.main.main`."""

from __future__ import annotations

import sys


def main() -> None:
    """The ``scanreg`` command. A single run exits without the interpreter's teardown once its outputs are
    written and its run is logged; a ``-m`` sweep exits normally, so that its launcher shuts its workers down."""
    from scanreg.app import startup

    startup.defer_open3d_viewer()
    argv = sys.argv[1:]
    if startup.may_track_single_run(argv):
        startup.prestart_tracking_worker()
    from scanreg.app.main import main as app_main

    code: int | str | None = 0
    try:
        app_main()
    except SystemExit as e:
        code = e.code
    startup.drop_tracking_worker()  # a run that did not log (untracked, or stopped early) leaves no worker behind
    from scanreg.app.tracking import _sweep_outcome

    if startup.is_multirun(argv) or _sweep_outcome.get("started"):  # (a sweep may be set by a config file)
        raise SystemExit(code)
    startup.exit_now(code)


if __name__ == "__main__":
    main()
