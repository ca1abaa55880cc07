"""Errors that end a run with one clear line (no traceback unless ``verbose=true``)."""


class ScanregError(Exception):
    """Base of all expected failures; the message is shown to the user as one line."""


class ConfigError(ScanregError):
    """Unknown stage name, unknown or mistyped parameter, inconsistent options."""


class InputError(ScanregError):
    """Missing, unreadable, corrupt, empty or degenerate input data."""


class StageError(ScanregError):
    """A stage could not do its work on valid input (too few points, no solution...)."""
