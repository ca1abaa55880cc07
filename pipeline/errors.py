"""Errors that end a run with one clear line (no traceback unless ``verbose=true``)."""


class ScanregError(Exception):
    """Base of all expected failures; the message is shown to the user as one line. ``metrics`` measured
    before the failure (e.g. a repair audit) are still logged with the failed run."""

    def __init__(self, message: str, metrics: dict | None = None):
        super().__init__(message)
        self.metrics = metrics or {}


class ConfigError(ScanregError):
    """Unknown stage name, unknown or mistyped parameter, inconsistent options."""


class InputError(ScanregError):
    """Missing, unreadable, corrupt, empty or degenerate input data."""


class StageError(ScanregError):
    """A stage could not do its work on valid input (too few points, no solution...)."""


def one_line(e: BaseException, limit: int = 160) -> str:
    """A library's exception as ``Type: message`` on one line (at most ``limit`` characters of the message)."""
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:limit]}" if text else type(e).__name__


def warn(msg: str) -> None:
    """A ``warning:`` line on standard output (the run goes on)."""
    _line(f"warning: {msg}")


def note(msg: str) -> None:
    """A ``note:`` line on standard output: what a default chose, or that a step was skipped."""
    _line(f"note: {msg}")


def _line(text: str) -> None:
    """``text`` and its newline in one write (``print`` makes two when standard output is unbuffered, and the
    lines of two processes, such as a pair's two repairs, would interleave); and the same line in the run
    folder's log (:func:`log_line`)."""
    import sys

    sys.stdout.write(text + "\n")
    sys.stdout.flush()
    log_line(text)


RUN_LOG = "scanreg.run"
"""The logger of the lines a run prints (notes, warnings, errors). Only a command-line run gives it a handler
(``main.log`` in the run folder, :func:`scanreg.app.main.run_log`), which passes nothing on to the root logger's
handlers (Hydra's or an application's console would print the lines again)."""


def log_line(text: str) -> None:
    """``text`` into the run's log when it has one (:data:`RUN_LOG`); else nothing (the console has the line)."""
    import logging

    log = logging.getLogger(RUN_LOG)
    if log.handlers:
        log.info(text)
