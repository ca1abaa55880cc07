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
from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from scanreg.errors import ConfigError


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


def main(argv: list[str] | None = None) -> int:
    """``scanreg-stages [FAMILY]``: list registered stages with their parameters and docs."""
    load_all()
    argv = sys.argv[1:] if argv is None else argv
    families = argv or list(REGISTRIES)
    for fam in families:
        if fam not in REGISTRIES:
            print(f"error: unknown stage family '{fam}'; valid: {', '.join(REGISTRIES)}", file=sys.stderr)
            return 2
        reg = REGISTRIES[fam]
        for name in reg.names():
            cls = reg.get(name)
            summary = (inspect.getdoc(cls) or "").split("\n\n")[0].replace("\n", " ")
            print(f"{fam}={name}: {summary}")
            docs = field_docs(cls.Params)
            for f in dataclasses.fields(cls.Params):
                default = f.default if f.default is not dataclasses.MISSING else (
                    f.default_factory() if f.default_factory is not dataclasses.MISSING else "???")
                tname = getattr(f.type, "__name__", str(f.type))
                print(f"    {f.name}: {tname} = {default!r}  -- {docs.get(f.name, '(undocumented)')}".replace("\n", " "))
        print()
    return 0
