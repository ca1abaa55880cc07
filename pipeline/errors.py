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


def log_line(text: str) -> None:
    """``text`` into the log of the run (Hydra's ``main.log`` in the run folder, which the command line's
    config writes at INFO and shows on the console only from WARNING: the console has the line already). Outside
    a command-line run no handler takes it."""
    import logging

    logging.getLogger("scanreg").info(text)
