"""The ``scanreg`` command line before Hydra reads it: scan files given by position, and overrides whose path
values Hydra's grammar cannot read.

- :func:`with_files`: ``scanreg SOURCE TARGET [overrides]`` and ``scanreg SCAN SCAN SCAN ... [overrides]`` or
  ``scanreg FOLDER [overrides]`` become ``data.source=`` / ``data.target=`` (``data=scanset data.scans=``)
  overrides, each path quoted as the Python API quotes it (:func:`quote_value`), so names with spaces, brackets,
  ``=``, commas, ``#``, quotes or non-ASCII letters reach the readers verbatim.
- :func:`path_override_error`: an override whose value looks like a path and does not parse (or, outside a
  sweep, parses as a list of choices) is said in one line with the command that works.
"""

from __future__ import annotations

import os
import re
import shlex

from scanreg.errors import ConfigError

VALUE_FLAGS = ("-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir", "-c", "--cfg", "-p",
               "--package", "-i", "--info", "-sc", "--shell-completion", "--experimental-rerun")
"""Hydra's flags that take the next argument as their value (``--cfg job``, ``--config-dir DIR``)."""

SWITCH_FLAGS = ("-h", "--help", "--hydra-help", "--version", "--resolve", "-r", "--run", "-m", "--multirun")
"""Hydra's flags that take no value."""


def unknown_flag_error(argv: list[str]) -> str | None:
    """One line for the first argument of ``argv`` that looks like a flag and is none of Hydra's (argparse printed
    its 8-line usage block), or None."""
    known = (*VALUE_FLAGS, *SWITCH_FLAGS)
    for i, a in enumerate(argv):
        if a.startswith("-") and len(a) > 1 and not (i > 0 and argv[i - 1] in VALUE_FLAGS) \
                and a.partition("=")[0] not in known and not os.path.lexists(a):
            return (f"unknown option {a}: scanreg takes scan files, overrides (key=value) and Hydra's options "
                    "(-m, --cfg job, --config-dir DIR, ...; scanreg --help)")
    return None


PATH_KEYS = ("data.source", "data.target", "data.gt", "data.landmarks", "data.scans", "data.poses",
             "data.folder", "hydra.run.dir", "hydra.sweep.dir", "tracking.uri")
"""Keys whose values are paths whatever they look like."""

_EXTENSION = re.compile(r"\.[A-Za-z][A-Za-z0-9]{0,4}$")


def quote_value(path: str) -> str:
    """``path`` as a quoted Hydra override value: spaces, ``=``, commas, brackets, ``#``, quotes and non-ASCII
    letters stay literal."""
    # Hydra's quoted strings take a backslash as an escape only before a quote (and before the backslashes
    # that precede a quote): those runs are doubled, and every quote escaped
    escaped = re.sub(r"(\\*)('|$)", lambda m: m.group(1) * 2 + ("\\'" if m.group(2) else ""), path)
    return "'" + escaped + "'"


def _is_override(arg: str) -> bool:
    return arg.startswith("~") or "=" in arg


def _is_flag(argv: list[str], i: int) -> bool:
    """Whether ``argv[i]`` is a Hydra flag or the value of the flag before it."""
    return argv[i].startswith("-") or (i > 0 and argv[i - 1] in VALUE_FLAGS)


def split_files(argv: list[str]) -> tuple[list[str], list[str]]:
    """``(files, rest)``: the positional scan files of ``argv`` in their order, and everything else (flags, their
    values, overrides) in its order. An argument is a file when it names an existing file or folder, or when it
    is neither a flag nor an override (no ``=``; a missing file is then reported by the reader, by name)."""
    files, rest = [], []
    for i, a in enumerate(argv):
        is_file = not _is_flag(argv, i) and (os.path.lexists(a) or not _is_override(a))
        (files if is_file else rest).append(a)
    return files, rest


def _data_choice(overrides: list[str]) -> str | None:
    choice = None
    for o in overrides:
        key, _, value = o.partition("=")
        if key.lstrip("+") == "data":
            choice = value
    return choice


def _preset_data_choice(overrides: list[str], config_dirs: list[str]) -> tuple[str, str] | None:
    """``(preset override, data choice)`` when an ``experiment=`` or ``method=`` override (one name, not a sweep)
    picks a data provider: the configuration composed as the run will compose it (a preset sets ``data`` in its
    defaults list, which the command line does not show)."""
    from scanreg.app.config import PRESET_GROUPS, compose

    presets = [o for o in overrides if o.partition("=")[0].lstrip("+") in PRESET_GROUPS]
    if not presets or any(re.search(r"[,\[\]()]", o.partition("=")[2]) for o in presets):
        return None
    try:  # the presets alone (another override may be a sweep, which one composition cannot take)
        cfg = compose(presets, config_dirs=config_dirs, return_hydra_config=True)
    except ConfigError:  # the run says what is wrong with it
        return None
    choice = cfg.hydra.runtime.choices.get("data")
    return (presets[-1], choice) if choice not in (None, "files") else None


def file_overrides(files: list[str], overrides: list[str], config_dirs: list[str] = ()) -> list[str]:
    """The overrides that say ``files`` (positional scan files) to the data provider: two files are the
    source and the target of ``data=files`` (the default); one folder, three or more files, or any number with
    ``data=scanset`` are a scan set (a ``shared:`` folder too). One file alone is a usage error, and so is a name
    that is no file or folder, and so are files with a ``data=`` (or an
    ``experiment=`` or ``method=`` preset whose ``data``) that picks its own scans (``config_dirs``: where
    presets are looked for besides the shipped configs)."""
    if not files:
        return []
    choice = _data_choice(overrides)
    if choice not in (None, "files", "scanset"):
        raise ConfigError(f"scan files given ({', '.join(files)}) with data={choice}, which picks its own scans: "
                          "leave data= out to register the files, or give data=scanset for a scan set")
    preset = _preset_data_choice(overrides, config_dirs) if choice is None else None
    if preset is not None and preset[1] != "scanset":
        raise ConfigError(f"scan files given ({', '.join(files)}) with {preset[0]}, whose data={preset[1]} picks "
                          "its own scans: give the files without it, or the preset without files")
    choice = choice or (preset[1] if preset else None)
    scanset = choice == "scanset"
    if not scanset and len(files) == 2 and not any(os.path.isdir(f) for f in files):
        return _no_clash([f"data.source={quote_value(files[0])}", f"data.target={quote_value(files[1])}"], overrides)
    if scanset or len(files) >= 3 or (len(files) == 1 and os.path.isdir(_expanded(files[0]))):
        scans = quote_value(files[0]) if len(files) == 1 else "[" + ",".join(quote_value(f) for f in files) + "]"
        return _no_clash(([] if scanset else ["data=scanset"]) + [f"data.scans={scans}"], overrides)
    if len(files) == 1:
        given = {o.partition("=")[0].lstrip("+") for o in overrides} & {"data.source", "data.target"}
        if not scanset and len(given) == 1:  # the other one named as an override (quoted for its characters)
            role = "target" if "data.source" in given else "source"
            return [f"data.{role}={quote_value(files[0])}"]
        path = _expanded(files[0])
        if not os.path.exists(path) and not files[0].startswith("pkg:"):  # a mistyped folder or file
            raise ConfigError(f"{files[0]}: no such file or folder ({os.path.abspath(path)})")
        raise ConfigError(f"one scan given ({files[0]}): give the source and the target (scanreg SOURCE TARGET), "
                          "or a folder or three or more scans to register into one model")
    raise ConfigError(f"a folder among two scans ({', '.join(files)}): give two files (SOURCE TARGET), or one "
                      "folder, or three or more scans")


def _expanded(name: str) -> str:
    """``name`` with a ``shared:`` prefix resolved (:func:`scanreg.io.paths.expand_path`)."""
    from scanreg.io.paths import expand_path  # here: the package's readers are not needed before a run

    return expand_path(name) if name.startswith("shared:") else name


def _no_clash(made: list[str], overrides: list[str]) -> list[str]:
    """``made`` (the positional files' overrides), unless the user's ``overrides`` set one of its keys too."""
    keys = {o.partition("=")[0] for o in made if o.startswith("data.")}
    for o in overrides:
        key = o.partition("=")[0].lstrip("+~")
        if key in keys:
            raise ConfigError(f"{key} is given twice: by the scan files on the command line and by {o}; give one")
    return made


def with_files(argv: list[str]) -> list[str]:
    """``argv`` with its positional scan files turned into quoted overrides, placed after the user's own. With
    files, Hydra's flags (and their values) go first: its command line takes the overrides as one run of
    arguments, which a flag between them would split (``scanreg a.ply b.ply --cfg job``)."""
    files, rest = split_files(argv)
    if not files:
        return rest
    flags = [a for i, a in enumerate(rest) if _is_flag(rest, i)]
    overrides = [a for i, a in enumerate(rest) if not _is_flag(rest, i)]
    return flags + overrides + file_overrides(files, overrides, _config_dirs(rest))


def _config_dirs(argv: list[str]) -> list[str]:
    """The folders of Hydra's ``--config-dir DIR`` / ``-cd DIR`` / ``--config-dir=DIR`` flags in ``argv``."""
    dirs = []
    for i, a in enumerate(argv):
        if a.startswith("--config-dir="):
            dirs.append(a.partition("=")[2])
        elif a in ("-cd", "--config-dir") and i + 1 < len(argv):
            dirs.append(argv[i + 1])
    return dirs


def _parse(override: str):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create().parse_override(override)


def _looks_like_path(key: str, value: str) -> bool:
    return (key.lstrip("+") in PATH_KEYS or "/" in value or "\\" in value or os.path.lexists(value)
            or bool(_EXTENSION.search(value.strip())))


def _needs_quoting(value: str) -> list[str]:
    """The characters of ``value`` that Hydra's grammar does not take literally in an unquoted value."""
    bad = []
    for c in dict.fromkeys(value):
        try:
            ok = _parse(f"k=a{c}b").value() == f"a{c}b"
        except Exception:  # noqa: BLE001  # Hydra's parse error: the character needs quoting
            ok = False
        if not ok:
            bad.append(c)
    return bad


def shell_arg(arg: str) -> str:
    """``arg`` as a POSIX shell would need it typed: bare when safe, else in double quotes when that suffices
    (no ``"``, ``$``, backquote or ``!``, and no backslash that the shell would read as an escape), else as
    :func:`shlex.quote` writes it."""
    if re.fullmatch(r"[\w@%+=:,./~-]+", arg, flags=re.ASCII):
        return arg
    if not re.search(r'["$`!]|\\(?=[$`"\\]|$)', arg):
        return f'"{arg}"'
    return shlex.quote(arg)


def _unparsable_path(arg: str, multirun: bool) -> tuple[str, str] | None:
    """``(key, value)`` when ``arg`` is an override whose value looks like a path and that Hydra would not read
    as that path (a parse error; outside a sweep, a list of choices)."""
    key, _, value = arg.partition("=")
    if not _looks_like_path(key, value) or value[:1] in ("'", '"'):
        return None
    try:
        parsed = _parse(arg)
        if not parsed.is_sweep_override() or multirun:
            return None  # read as written (null, a list, a quoted path), or a sweep over files: as meant
    except Exception:  # noqa: BLE001  # Hydra's parse error: said by the caller
        pass
    return key, value


def path_override_error(argv: list[str], multirun: bool) -> str | None:
    """One line for the overrides of ``argv`` whose values look like paths and that Hydra would not read as
    those paths: the characters that need quoting and the whole command with the values quoted (and, when the
    source and the target are given so, the positional form). None when every path parses."""
    bad = {}
    for i, a in enumerate(argv):
        if _is_flag(argv, i) or "=" not in a:
            continue
        found = _unparsable_path(a, multirun)
        if found:
            bad[i] = found
    if not bad:
        return None
    swept = multirun and any("," in value for _, value in bad.values())  # (a sweep over several paths)
    chars = dict.fromkeys(c for _, value in bad.values() for c in _needs_quoting(value) if not (swept and c == ","))
    def quoted(value: str) -> str:  # in a sweep, commas separate the values: each is quoted alone
        return ",".join(map(quote_value, value.split(","))) if multirun else quote_value(value)

    fixed = [f"{bad[i][0]}={quoted(bad[i][1])}" if i in bad else a for i, a in enumerate(argv)]
    keys = ", ".join(key for key, _ in bad.values())
    line = (f"{keys}: {'a path holds' if len(bad) == 1 else 'paths hold'} "
            f"{', '.join(repr(c) for c in chars) or 'characters'}, which Hydra's override grammar reads as syntax; "
            f"quote {'the value' if len(bad) == 1 and not swept else 'the values'}: "
            f"scanreg {' '.join(shell_arg(x) for x in fixed)}")
    positional = None if swept else _positional_form(argv)
    if positional:
        line += f"  (or give the files by position: scanreg {' '.join(shell_arg(x) for x in positional)})"
    return line


def override_value(arg: str) -> str:
    """The value of ``key=value`` as Hydra reads it when it is quoted, else as written."""
    value = arg.partition("=")[2]
    if value[:1] in ("'", '"'):
        try:
            return str(_parse(arg).value())
        except Exception:  # noqa: BLE001  # as written
            pass
    return value


def _positional_form(argv: list[str]) -> list[str] | None:
    """``argv`` with ``data.source=S data.target=T`` as ``S T`` in front, when both are given."""
    values = {}
    for a in argv:
        key, eq, _ = a.partition("=")
        if eq and key in ("data.source", "data.target"):
            values[key] = override_value(a)
    if len(values) < 2:
        return None
    rest = [a for a in argv if a.partition("=")[0] not in ("data.source", "data.target")]
    return [values["data.source"], values["data.target"], *rest]
