"""Name registries, one per stage family, and the one place where a stage's parameters get their defaults.

A stage is a small class with a typed ``Params`` dataclass (one docstring per field, units included)::

    @SAMPLER.register("barycentric")
    class Barycentric:
        @dataclass
        class Params:
            n_points: int = 20000
            \"\"\"Number of points to draw.\"\"\"

        def __init__(self, params: Params): ...

Registering a class also stores its ``Params`` as a Hydra structured config (``_<name>`` in the family's config
group), so that the dataclass is the only source of every default: the stage's YAML
(``conf/<family>/<name>.yaml``) starts from it (``defaults: [_<name>, _self_]``) and holds only what differs
(the link to the run's seed). :meth:`Registry.build` checks a name against the registry and values against
``Params``, turning every problem into one :class:`ConfigError` line that lists the valid names or fields.

Stage modules are found through the entry-point group ``scanreg.stages`` (:func:`load_all`); a separate package
adds stages by declaring its modules there, and its YAML files in a ``conf/<family>/`` folder beside the
module (or none: a stage without a YAML gets one that holds its defaults).
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from scanreg.errors import ConfigError
from scanreg.stages.protocols import PROTOCOLS

if TYPE_CHECKING:
    from omegaconf import DictConfig


class Registry:
    """Maps names to the stage classes of one family (``repair``, ``sampler``, ...)."""

    def __init__(self, family: str, protocol: type | None = None):
        self.family = family
        self.protocol = protocol
        self._classes: dict[str, type] = {}

    def register(self, name: str) -> Callable[[type], type]:
        """Class decorator: register the stage under ``name`` (its defaults become a structured config when
        configs are composed: :meth:`store_schemas`)."""
        def deco(cls: type) -> type:
            if name in self._classes:
                raise ValueError(f"{self.family} '{name}' registered twice")
            params = getattr(cls, "Params", None)
            if params is None or not dataclasses.is_dataclass(params):
                raise TypeError(f"{cls.__name__} must define a dataclass 'Params'")
            missing = [m for m in _protocol_methods(self.protocol) if not callable(getattr(cls, m, None))]
            if missing:
                raise TypeError(f"{self.family} '{name}' ({cls.__name__}) lacks {', '.join(missing)} "
                                f"(see scanreg.stages.protocols.{self.protocol.__name__})")
            short = [m for m in _protocol_methods(self.protocol) if _takes_fewer(getattr(cls, m),
                                                                                  getattr(self.protocol, m))]
            if short:  # the pipeline calls them with every parameter of the protocol, by position
                m = short[0]
                raise TypeError(f"{self.family} '{name}' ({cls.__name__}): {m}{_signature(getattr(cls, m))} takes "
                                f"fewer parameters than {m}{_signature(getattr(self.protocol, m))} of "
                                f"scanreg.stages.protocols.{self.protocol.__name__}")
            cls.name = name
            cls.family = self.family
            self._classes[name] = cls
            return cls

        return deco

    def names(self) -> list[str]:
        return sorted(self._classes)

    def store_schemas(self) -> None:
        """Store every registered stage's defaults as the structured config ``<family>/_<name>``, which its YAML's
        defaults line names (see :func:`store_schema`). Done before composing, not at registration, so that
        importing a stage module needs no Hydra (the MLflow worker imports the tracking backends)."""
        for name, cls in self._classes.items():
            store_schema(self.family, name, cls.Params)

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
        values = {k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k not in ("name", "defaults")}
        return cls, make_params(cls.Params, values, f"{self.family}={cfg.name}")

    def build(self, cfg: DictConfig | dict, **helpers: Any) -> Any:
        """The stage ``cfg`` names, built with its validated ``Params`` (and ``helpers``: built stages it uses)."""
        cls, params = self.params(cfg)
        return cls(params, **helpers)


def _signature(fn) -> str:
    import inspect

    try:
        return str(inspect.signature(fn)).replace("self, ", "").replace("(self)", "()")
    except (TypeError, ValueError):
        return "(...)"


def _takes_fewer(fn, proto) -> bool:
    """Whether ``fn`` cannot take every positional parameter of the protocol's method ``proto`` (no
    ``*args``)."""
    import inspect

    def positional(f):
        try:
            ps = inspect.signature(f).parameters.values()
        except (TypeError, ValueError):
            return None
        if any(p.kind == p.VAR_POSITIONAL for p in ps):
            return None
        return sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in ps)

    have, need = positional(fn), positional(proto)
    return have is not None and need is not None and have < need


def _protocol_methods(protocol: type | None) -> list[str]:
    if protocol is None:
        return []
    return [n for n, v in vars(protocol).items() if callable(v) and not n.startswith("_")]


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
        raise ConfigError(type_error(params_cls, str(key), values.get(str(key).split(".")[0]), where)) from None
    check = getattr(obj, "check", None)
    if callable(check):
        try:
            check()
        except (ValueError, TypeError) as e:
            raise ConfigError(f"{where}: {e}") from None
    return obj


def type_error(params_cls: type, key: str, value: Any, where: str) -> str:
    """The one-line message for a value of the wrong type, the type as ``scanreg-stages`` lists it."""
    name = key.split(".")[0]
    ftype = field_types(params_cls).get(name, {f.name: f.type for f in dataclasses.fields(params_cls)}.get(name))
    return f"{where}: parameter '{key}' expects {type_text(ftype)}, got {value!r}"


def field_types(params_cls: type) -> dict[str, Any]:
    """The dataclass's field types, resolved (its annotations are text under ``from __future__ import
    annotations``); empty when they cannot be."""
    import typing

    try:
        return typing.get_type_hints(params_cls)
    except Exception:  # noqa: BLE001  # (the annotation text then stands)
        return {}


def type_text(tp: Any) -> str:
    """A parameter type as a user writes it: ``float | null``, ``spacing | absolute`` for an enum."""
    import enum
    import typing

    if isinstance(tp, str):
        return tp
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if typing.get_origin(tp) is typing.Union:
        return " | ".join(type_text(a) for a in args) + (" | null" if type(None) in typing.get_args(tp) else "")
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return " | ".join(str(m.value) for m in tp)
    if typing.get_origin(tp) in (list, dict, tuple):
        return f"{typing.get_origin(tp).__name__}[{', '.join(type_text(a) for a in args)}]"
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


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


# ------------------------------------------------------------------------------------- structured configs

def schema_name(name: str) -> str:
    """The config-group entry that holds a stage's defaults (its YAML's first default)."""
    return f"_{name}"


def store_schema(group: str, name: str, params_cls: type) -> None:
    """Store ``params_cls`` plus ``name`` as the structured config ``<group>/_<name>`` (Hydra's ConfigStore)."""
    from hydra.core.config_store import ConfigStore

    node = dataclasses.make_dataclass(f"{group}_{name}", [("name", str, dataclasses.field(default=name))],
                                      bases=(params_cls,))
    node.__scanreg_stage__ = (group, name)  # names the stage in a composition error (scanreg.app.config)
    ConfigStore.instance().store(group=group, name=schema_name(name), node=node)


def store_config(group: str, name: str, node: Any) -> None:
    """Store ``node`` (a YAML's content, or a defaults list) as the config-group entry ``<group>/<name>``."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(group=group, name=name, node=node)


# ---------------------------------------------------------------------------------------------- families

DATA = Registry("data", PROTOCOLS["data"])
REPAIR = Registry("repair", PROTOCOLS["repair"])
SAMPLER = Registry("sampler", PROTOCOLS["sampler"])
SALIENCE = Registry("salience", PROTOCOLS["salience"])
DESCRIPTOR = Registry("descriptor", PROTOCOLS["descriptor"])
MATCHER = Registry("matcher", PROTOCOLS["matcher"])
COARSE = Registry("coarse", PROTOCOLS["coarse"])
ICP = Registry("icp", PROTOCOLS["icp"])
GRAPH = Registry("graph", PROTOCOLS["graph"])
SURFACE = Registry("surface", PROTOCOLS["surface"])

REGISTRIES: dict[str, Registry] = {
    r.family: r for r in (DATA, REPAIR, SAMPLER, SALIENCE, DESCRIPTOR, MATCHER, COARSE, ICP, GRAPH, SURFACE)
}
"""The stage families in the order of the pipeline."""

CONF_PACKAGE = "scanreg.conf"
"""The package holding the YAML configs, Hydra's primary config source ``pkg://scanreg.conf``."""


def conf_dir() -> Path:
    """The folder of the shipped configs (``conf/`` of the checkout, or the installed package's copy)."""
    from importlib.resources import files

    return Path(str(files(CONF_PACKAGE)))


STAGE_ENTRY_POINTS = "scanreg.stages"
"""Entry-point group whose modules register stages (scanreg's own in pyproject.toml; a plugin package adds its
stage modules to the same group)."""

_loaded = False


def load_all() -> None:
    """Import every stage module named in the ``scanreg.stages`` entry-point group so that their ``register``
    decorators run, then give every registered stage a config-group entry: its YAML (scanreg's own in
    ``conf/``, a plugin's in ``conf/<family>/`` beside its module) or, without one, a node of its defaults. The
    framework thus reaches stages only through the registries, never by importing them."""
    global _loaded
    if _loaded:
        return
    import importlib
    from importlib.metadata import entry_points

    eps = sorted(entry_points(group=STAGE_ENTRY_POINTS), key=lambda e: e.name)
    if not eps:
        raise ConfigError("no stage modules found (entry points 'scanreg.stages'): is scanreg installed "
                          "(pip install -e . or a wheel)?")
    plugin_dirs = []
    for ep in eps:
        if ep.value.startswith("scanreg."):
            importlib.import_module(ep.value)
            continue
        try:  # a plugin that fails to load (a stage that does not meet its protocol) costs its own stages only
            module = importlib.import_module(ep.value)
        except Exception as e:  # noqa: BLE001
            from scanreg.errors import one_line, warn

            warn(f"stage plugin {ep.value} (entry point '{ep.name}') not loaded, its stages unavailable: "
                 f"{one_line(e, 300)}")
            continue
        plugin_dirs.append(Path(module.__file__).parent / "conf")
    _store_group_entries(plugin_dirs)
    _loaded = True


def _store_group_entries(plugin_dirs: list[Path]) -> None:
    from omegaconf import OmegaConf

    for family, reg in REGISTRIES.items():
        reg.store_schemas()
        for name in reg.names():
            if (conf_dir() / family / f"{name}.yaml").is_file():
                continue  # Hydra finds it in the primary config folder
            yaml = next((d / family / f"{name}.yaml" for d in plugin_dirs if (d / family / f"{name}.yaml").is_file()),
                        None)
            node = OmegaConf.load(yaml) if yaml else OmegaConf.create({"defaults": [schema_name(name), "_self_"]})
            store_config(family, name, node)
