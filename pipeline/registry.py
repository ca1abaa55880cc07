"""Name registries, one per stage family.

A stage is a small class with a typed ``Params`` dataclass (one docstring per field, units included)::

    @SAMPLER.register("barycentric")
    class Barycentric:
        @dataclass
        class Params:
            n_points: int = 20000
            \"\"\"Number of points to draw.\"\"\"

        def __init__(self, params: Params): ...

The YAML of a stage (``conf/<family>/<name>.yaml``) holds ``name`` plus values for ``Params``. ``build`` checks
the name against the registry and the values against ``Params`` with an OmegaConf structured config, turning
every problem into one :class:`ConfigError` line that lists the valid names or fields.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import sys
import textwrap
from typing import TYPE_CHECKING, Any, Callable

from scanreg.errors import ConfigError

if TYPE_CHECKING:
    from omegaconf import DictConfig
# OmegaConf is imported where it is used: registering a class needs none (the MLflow helper process imports
# scanreg.tracking, which registers its classes, on the critical path of a run's start-up)


class Registry:
    """Maps names to stage classes of one family (``repair``, ``sampler``, ...)."""

    def __init__(self, family: str):
        self.family = family
        self._classes: dict[str, type] = {}

    def register(self, name: str) -> Callable[[type], type]:
        def deco(cls: type) -> type:
            if name in self._classes:
                raise ValueError(f"{self.family} '{name}' registered twice")
            params = getattr(cls, "Params", None)
            if params is None or not dataclasses.is_dataclass(params):
                raise TypeError(f"{cls.__name__} must define a dataclass 'Params'")
            cls.name = name
            cls.family = self.family
            self._classes[name] = cls
            return cls

        return deco

    def names(self) -> list[str]:
        return sorted(self._classes)

    def get(self, name: Any) -> type:
        if name not in self._classes:
            raise ConfigError(
                f"unknown {self.family} '{name}'; valid {self.family} names: {', '.join(self.names())}"
            )
        return self._classes[name]

    def params(self, cfg: DictConfig | dict) -> tuple[type, Any]:
        """Validate ``cfg`` (``name`` plus parameters) and return ``(class, Params instance)``."""
        from omegaconf import OmegaConf

        if isinstance(cfg, dict):
            cfg = OmegaConf.create(cfg)
        if cfg is None or "name" not in cfg:
            raise ConfigError(f"{self.family}: no 'name' given; valid {self.family} names: {', '.join(self.names())}")
        cls = self.get(cfg.name)
        values = {k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k != "name"}
        return cls, make_params(cls.Params, values, f"{self.family}={cfg.name}")

    def build(self, cfg: DictConfig | dict) -> Any:
        cls, params = self.params(cfg)
        return cls(params)


def make_params(params_cls: type, values: dict, where: str) -> Any:
    """Validate ``values`` against the dataclass ``params_cls``; one-line :class:`ConfigError` on failure."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    fields = [f.name for f in dataclasses.fields(params_cls)]
    unknown = [k for k in values if k not in fields]
    if unknown:
        raise ConfigError(
            f"{where}: unknown parameter '{unknown[0]}'; valid parameters: {', '.join(fields) or '(none)'}"
        )
    try:
        merged = OmegaConf.merge(OmegaConf.structured(params_cls), values)
        obj = OmegaConf.to_object(merged)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or getattr(e, "key", None) or "?"
        ftype = {f.name: f.type for f in dataclasses.fields(params_cls)}.get(str(key).split(".")[0])
        tname = getattr(ftype, "__name__", str(ftype))
        raise ConfigError(
            f"{where}: parameter '{key}' expects {tname}, got {values.get(str(key).split('.')[0])!r}"
        ) from None
    check = getattr(obj, "check", None)
    if callable(check):
        try:
            check()
        except (ValueError, TypeError) as e:
            raise ConfigError(f"{where}: {e}") from None
    return obj


def field_docs(params_cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass (the string literal right after each field)."""
    docs: dict[str, str] = {}
    for klass in reversed([k for k in params_cls.__mro__ if dataclasses.is_dataclass(k)]):
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        for node, nxt in zip(body, body[1:] + [None]):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str):
                    docs[node.target.id] = inspect.cleandoc(nxt.value.value)
    return docs


# One registry per stage family; the order is the order of the pipeline.
DATA = Registry("data")
REPAIR = Registry("repair")
SAMPLER = Registry("sampler")
SALIENCE = Registry("salience")
DESCRIPTOR = Registry("descriptor")
MATCHER = Registry("matcher")
COARSE = Registry("coarse")
ICP = Registry("icp")
TRACKING = Registry("tracking")

REGISTRIES: dict[str, Registry] = {
    r.family: r for r in (DATA, REPAIR, SAMPLER, SALIENCE, DESCRIPTOR, MATCHER, COARSE, ICP, TRACKING)
}


STAGE_ENTRY_POINTS = "scanreg.stages"
"""Entry-point group whose modules register stages (``scanreg``'s own in pyproject.toml; a plugin package adds
its stage modules to the same group)."""


def load_all() -> None:
    """Import every stage module named in the ``scanreg.stages`` entry-point group so that their ``register``
    decorators run. The framework thus reaches stages only through the registries, never by importing them."""
    import importlib
    from importlib.metadata import entry_points

    eps = sorted(entry_points(group=STAGE_ENTRY_POINTS), key=lambda e: e.name)
    if not eps:
        raise ConfigError("no stage modules found (entry points 'scanreg.stages'): is scanreg installed "
                          "(pip install -e . or a wheel)?")
    for ep in eps:
        importlib.import_module(ep.value)


def plain(text: str) -> str:
    """Docstring markup as plain text: ``x`` and :class:`x` become 'x'; whitespace runs become one space."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"'\1'", text)
    text = re.sub(r"``([^`]+)``", r"'\1'", text)
    return " ".join(text.split())


def type_text(tp: Any) -> str:
    """A parameter type as a user writes it: ``float | null``, ``spacing | absolute`` for an enum."""
    import enum
    import typing

    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if typing.get_origin(tp) is typing.Union:
        return " | ".join(type_text(a) for a in args) + (" | null" if type(None) in typing.get_args(tp) else "")
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return " | ".join(str(m.value) for m in tp)
    if typing.get_origin(tp) in (list, dict, tuple):
        return f"{typing.get_origin(tp).__name__}[{', '.join(type_text(a) for a in args)}]"
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


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


def yaml_defaults(family: str, name: str) -> dict[str, Any]:
    """The parameter values ``conf/<family>/<name>.yaml`` sets (interpolations such as ``${seed}`` as
    written); every field missing there keeps the Params default."""
    from scanreg.config import conf_dir

    cls = REGISTRIES[family].get(name)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls.Params):
        if f.default is not dataclasses.MISSING:
            values[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            values[f.name] = f.default_factory()
        else:
            values[f.name] = "???"
    path = conf_dir() / family / f"{name}.yaml"
    if path.exists():
        from omegaconf import OmegaConf

        yaml = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        values.update({k: v for k, v in yaml.items() if k in values})
    return values


def describe(family: str, name: str, width: int = 100) -> list[str]:
    """One stage for ``scanreg-stages``: its summary, then each parameter with its type, its default as the
    YAML sets it and its docstring, wrapped at ``width`` columns."""
    import typing

    cls = REGISTRIES[family].get(name)
    wrap = lambda text, indent: textwrap.wrap(text, width, initial_indent=indent, subsequent_indent=indent) or [indent]
    summary = plain((inspect.getdoc(cls) or "").split("\n\n")[0])
    lines = [f"{family}={name}", *wrap(summary, "  ")]
    docs = field_docs(cls.Params)
    try:
        hints = typing.get_type_hints(cls.Params)
    except Exception:  # noqa: BLE001: fall back to the annotation text
        hints = {}
    defaults = yaml_defaults(family, name)
    for f in dataclasses.fields(cls.Params):
        tp = type_text(hints.get(f.name, f.type))
        lines += wrap(f"{f.name} = {value_text(defaults[f.name])}   ({tp})", "  ")
        lines += wrap(plain(docs.get(f.name, "(undocumented)")), "      ")
    return lines


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
  scanreg-stages --list           names and one-line summaries only
"""


def main(argv: list[str] | None = None) -> int:
    """``scanreg-stages [FAMILY[=NAME] ...]``: list registered stages with their parameters and docs."""
    import argparse

    OneLineErrorParser = _one_line_parser()
    ap = OneLineErrorParser(prog="scanreg-stages", description=STAGES_HELP,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("filter", nargs="*", metavar="FAMILY[=NAME]",
                    help=f"show only these families or stages; families: {', '.join(REGISTRIES)}")
    ap.add_argument("--list", action="store_true", help="names and one-line summaries only")
    a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    load_all()
    wanted: list[tuple[str, str]] = []
    for item in a.filter or list(REGISTRIES):
        fam, _, name = item.partition("=")
        if fam not in REGISTRIES:
            print(f"error: unknown stage family '{fam}'; valid: {', '.join(REGISTRIES)}", file=sys.stderr)
            return 2
        if name and name not in REGISTRIES[fam].names():
            print(f"error: unknown {fam} '{name}'; valid {fam} names: {', '.join(REGISTRIES[fam].names())}",
                  file=sys.stderr)
            return 2
        wanted += [(fam, n) for n in ([name] if name else REGISTRIES[fam].names())]
    out: list[str] = []
    for fam, name in wanted:
        if a.list:
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
