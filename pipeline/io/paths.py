"""Where files are: ``pkg:`` names (a file shipped inside an installed package), ``shared:`` names (the shared
scan data beside the checkout), and the checks that a path names a readable, non-empty regular file."""

from __future__ import annotations

import errno
import importlib.util
import os
import stat
from pathlib import Path

from scanreg.errors import InputError

PROJECT_ROOT = Path(__file__).resolve().parents[2]
"""The source checkout (``pipeline/`` is the package ``scanreg``) in an editable install; in a wheel install the
folder holding the package, which is no checkout: :func:`shared_data_dir` and ``git_revision`` check."""


def shared_data_dir() -> Path:
    """``$SCANREG_SHARED_DATA``, else ``../shared/data`` beside the project root."""
    env = os.environ.get("SCANREG_SHARED_DATA")
    return Path(env) if env else (PROJECT_ROOT.parent / "shared" / "data")  # beside a checkout


def expand_path(s: str) -> str:
    """``shared:REL`` -> a path under :func:`shared_data_dir`; other strings unchanged (``pkg:`` is resolved by
    :func:`resolve_path`)."""
    if s.startswith("shared:"):
        return str(shared_data_dir() / s[len("shared:") :])
    return s


def resolve_path(path: str | os.PathLike, what: str = "file") -> Path:
    """Resolve ``pkg:`` names and check that ``path`` is an existing, non-empty regular file."""
    s = str(path)
    if s.startswith("pkg:"):
        pkg, _, rel = s[4:].partition("/")
        spec = importlib.util.find_spec(pkg)
        if spec is None or not spec.submodule_search_locations:
            raise InputError(f"{what} {s}: Python package '{pkg}' is not installed")
        p = Path(list(spec.submodule_search_locations)[0]) / rel
    else:
        p = Path(os.path.expanduser(s))
    try:
        st = p.stat()
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise InputError(f"{what} {s}: symbolic link loop (too many levels of symbolic links)") from None
        if e.errno == errno.ENOENT and p.is_symlink():
            raise InputError(f"{what} {s}: broken symbolic link (to '{os.readlink(p)}', which does not exist)") \
                from None
        if e.errno == errno.ENOENT:
            full = p.absolute()
            raise InputError(f"{what} {s}: no such file" + ("" if str(full) == s else f" ({full})")) from None
        raise InputError(f"{what} {s}: cannot read ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{what} {s}: is a directory, expected a file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{what} {s}: not a regular file (a device, pipe or socket)")
    if st.st_size == 0:
        raise InputError(f"{what} {s}: file is empty (0 bytes)")
    if not os.access(p, os.R_OK):
        raise InputError(f"{what} {s}: permission denied")
    return p
