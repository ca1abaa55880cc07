"""``scanreg-stages``: every registered stage with its parameters, their types, defaults and documentation."""

from __future__ import annotations

import dataclasses
import inspect
import sys
import textwrap
from typing import Any

from scanreg.stages.registry import REGISTRIES, conf_dir, field_docs, field_types, load_all, type_text


def plain(text: str) -> str:
    """Docstring markup as plain text: ``x`` and :class:`x` become 'x'; whitespace runs become one space."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"'\1'", text)
    text = re.sub(r"``([^`]+)``", r"'\1'", text)
    return " ".join(text.split())


def value_text(v: Any) -> str:
    """A value as YAML writes it (``null``, ``true``, ``[a, b]``, ``${seed}``)."""
    import enum

    if isinstance(v, enum.Enum):
        v = v.value
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(value_text(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {value_text(x)}" for k, x in v.items()) + "}"
    return str(v)


def params_defaults(params: type) -> dict[str, Any]:
    """The defaults of the dataclass ``params`` by field (``???`` for a field without one)."""
    values: dict[str, Any] = {}
    for f in dataclasses.fields(params):
        if f.default is not dataclasses.MISSING:
            values[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            values[f.name] = f.default_factory()
        else:
            values[f.name] = "???"
    return values


def yaml_defaults(family: str, name: str) -> dict[str, Any]:
    """The parameter values ``conf/<family>/<name>.yaml`` sets (interpolations such as ``${seed}`` as
    written); every field missing there keeps the Params default."""
    values = params_defaults(REGISTRIES[family].get(name).Params)
    path = conf_dir() / family / f"{name}.yaml"
    if path.exists():
        from omegaconf import OmegaConf

        yaml = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        values.update({k: v for k, v in yaml.items() if k in values and k != "name"})
    return values


def _wrap(text: str, indent: str, width: int) -> list[str]:
    return textwrap.wrap(text, width, initial_indent=indent, subsequent_indent=indent) or [indent]


def param_lines(params: type, values: dict[str, Any], width: int = 100) -> list[str]:
    """Each parameter of the dataclass ``params``: its value in ``values``, its type, then its docstring,
    wrapped at ``width`` columns."""
    docs = field_docs(params)
    hints = field_types(params)
    lines = []
    for f in dataclasses.fields(params):
        tp = type_text(hints.get(f.name, f.type))
        lines += _wrap(f"{f.name} = {value_text(values[f.name])}   ({tp})", "  ", width)
        lines += _wrap(plain(docs.get(f.name, "(undocumented)")), "      ", width)
    return lines


def describe(family: str, name: str, width: int = 100) -> list[str]:
    """One stage for ``scanreg-stages``: its summary, then each parameter with its type, its default as the
    YAML sets it and its docstring, wrapped at ``width`` columns."""
    cls = REGISTRIES[family].get(name)
    summary = plain((inspect.getdoc(cls) or "").split("\n\n")[0])
    return [f"{family}={name}", *_wrap(summary, "  ", width),
            *param_lines(cls.Params, yaml_defaults(family, name), width)]


def blocks() -> dict[str, type]:
    """The config blocks that are not stage families, by their key in the config: each a Params dataclass whose
    defaults hold as they are (``conf/config.yaml`` sets none of them)."""
    from scanreg.app.report.params import ReportParams
    from scanreg.eval.metrics import EvalParams
    from scanreg.runner.settings import MultiviewParams

    return {"evaluate": EvalParams, "report": ReportParams, "multiview": MultiviewParams}


def describe_block(key: str, params: type, width: int = 100) -> list[str]:
    """One config block (:func:`blocks`) as :func:`describe` shows a stage: each parameter with its type, its
    default and its docstring."""
    return [key, *_wrap(f"set with {key}.PARAM=VALUE", "  ", width),
            *param_lines(params, params_defaults(params), width)]


def _one_line_parser():
    import argparse

    class OneLineErrorParser(argparse.ArgumentParser):
        """Usage errors as one line, ``error: ...``, and exit 2 (as every scanreg command)."""

        def error(self, message):
            self.exit(2, f"error: {message} (see {self.prog} --help)\n")

    return OneLineErrorParser


STAGES_HELP = """\
List the pipeline's stages: every implementation of every stage family, with its parameters, their
types, their defaults as conf/<family>/<name>.yaml sets them, and their documentation (units included).
Choose a stage with FAMILY=NAME on the scanreg command line and set a parameter with FAMILY.PARAM=VALUE,
e.g. 'scanreg icp=horn icp.max_iterations=50'.

examples:
  scanreg-stages                  every family, every stage
  scanreg-stages icp              the ICP variants only
  scanreg-stages icp=horn data    one stage, and the data providers
  scanreg-stages evaluate         what is measured after registration (also: report, multiview)
  scanreg-stages --list           names and one-line summaries only
"""


def main(argv: list[str] | None = None) -> int:
    """``scanreg-stages [FAMILY[=NAME] ...]``: list registered stages with their parameters and docs."""
    import argparse

    settings = blocks()
    OneLineErrorParser = _one_line_parser()
    ap = OneLineErrorParser(prog="scanreg-stages", description=STAGES_HELP,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("filter", nargs="*", metavar="FAMILY[=NAME]",
                    help=f"show only these families or stages; families: {', '.join(REGISTRIES)}; or the "
                         f"settings of {', '.join(settings)}")
    ap.add_argument("--list", action="store_true", help="names and one-line summaries only")
    a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    load_all()
    wanted: list[tuple[str, str]] = []
    for item in a.filter or list(REGISTRIES):
        fam, _, name = item.partition("=")
        if fam in settings and not name:
            wanted.append((fam, ""))
            continue
        if fam in settings:
            print(f"error: {fam} is a block of settings, not a stage family: 'scanreg-stages {fam}' lists them",
                  file=sys.stderr)
            return 2
        if fam not in REGISTRIES:
            print(f"error: unknown stage family '{fam}'; valid: {', '.join(REGISTRIES)} (and the settings "
                  f"{', '.join(settings)})", file=sys.stderr)
            return 2
        if name and name not in REGISTRIES[fam].names():
            print(f"error: unknown {fam} '{name}'; valid {fam} names: {', '.join(REGISTRIES[fam].names())}",
                  file=sys.stderr)
            return 2
        wanted += [(fam, n) for n in ([name] if name else REGISTRIES[fam].names())]
    out: list[str] = []
    for fam, name in wanted:
        if not name:  # a config block
            out += [fam] if a.list else [*describe_block(fam, settings[fam]), ""]
        elif a.list:
            summary = plain((inspect.getdoc(REGISTRIES[fam].get(name)) or "").split("\n\n")[0])
            head = f"{fam}={name}"
            out += textwrap.wrap(f"{head:<26} {summary}", 100, subsequent_indent=" " * 27,
                                 max_lines=2, placeholder=" …")
        else:
            out += [*describe(fam, name), ""]
    try:
        print("\n".join(out))
    except BrokenPipeError:  # e.g. piped into head
        sys.stdout = None
    return 0


if __name__ == "__main__":
    sys.exit(main())
