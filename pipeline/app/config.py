"""The run configuration: composing it as ``scanreg`` does, its config groups, and Hydra's composition errors as
one line each."""

from __future__ import annotations

import subprocess
from pathlib import Path

from scanreg.errors import ConfigError
from scanreg.io.paths import PROJECT_ROOT
from scanreg.stages.registry import CONF_PACKAGE, REGISTRIES, conf_dir, load_all, make_params, type_error

STAGE_GROUPS = ("data", "repair", "sampler", "salience", "descriptor", "matcher", "coarse", "icp", "graph", "surface",
                "tracking")
"""The config groups that pick one implementation each."""
PRESET_GROUPS = ("method", "experiment", "launch")
"""Groups of ``# @package _global_`` files that set several groups (or the sweep launcher) at once."""


def search_path_override(config_dirs) -> list[str]:
    """``hydra.searchpath=[...]`` for extra config folders (a user's experiments and presets), or nothing."""
    dirs = [d if "://" in str(d) else f"file://{Path(d).expanduser().resolve()}" for d in config_dirs]
    return [f"hydra.searchpath=[{','.join(dirs)}]"] if dirs else []


def compose(overrides=(), config_name: str = "config", config_dirs=(), return_hydra_config: bool = False):
    """The run configuration as ``scanreg`` composes it: the shipped configs (``pkg://scanreg.conf``), plus
    ``config_dirs`` on Hydra's search path, with command-line style ``overrides``. Returns a ``DictConfig``
    (with its ``hydra`` node when ``return_hydra_config``); a bad override raises one :class:`ConfigError` line."""
    from hydra import compose as hydra_compose, initialize_config_module

    for d in map(str, config_dirs):  # (Hydra's search path passes over a folder that is not there)
        if not d.startswith("pkg://") and not Path(d.removeprefix("file://")).expanduser().is_dir():
            raise ConfigError(f"config_dirs: additional config directory '{d}' not found")
    register_schemas()
    try:
        with initialize_config_module(CONF_PACKAGE, version_base="1.3"):
            return hydra_compose(config_name, overrides=[*overrides, *search_path_override(config_dirs)],
                                 return_hydra_config=return_hydra_config)
    except Exception as e:  # noqa: BLE001  # Hydra's composition errors, as the CLI says them
        raise ConfigError(config_error_line(e)) from None


def group_choices(group: str, config_dirs=()) -> list[str]:
    """The choices of a config group: the YAML names in the shipped configs and in extra config folders
    (``--config-dir``, ``hydra.searchpath``: ``file://`` or plain paths, ``pkg://`` packages), and the stages
    registered without a YAML."""
    from importlib.resources import files

    roots = [conf_dir()]
    for d in config_dirs:
        d = str(d)
        if d.startswith("pkg://"):
            try:
                roots.append(Path(str(files(d[len("pkg://"):].replace("/", ".")))))
            except (ModuleNotFoundError, TypeError):
                continue
        else:
            roots.append(Path(d.removeprefix("file://")).expanduser())
    names = {p.stem for r in roots for p in (r / group).glob("*.yaml")}
    if group in REGISTRIES:
        load_all()
        names |= set(REGISTRIES[group].names())
    return sorted(names)


def help_groups() -> str:
    """The config groups and their choices, wrapped at 100 columns, for ``scanreg --help``."""
    import textwrap

    lines = []
    for g in sorted(p.name for p in conf_dir().iterdir() if p.is_dir() and any(p.glob("*.yaml"))):
        lines += textwrap.wrap(f"{g}: {', '.join(group_choices(g))}", 100, subsequent_indent="    ")
    return "\n".join(lines)


def register_schemas() -> None:
    """Every default as a structured config, before a config is composed: the stages' (:func:`load_all`), the
    tracking backends', and the ``evaluate`` and ``report`` blocks' (``_evaluate``, ``_report`` in
    ``conf/config.yaml``'s defaults list); and the resolvers ``conf/config.yaml``'s help text uses. Once per
    process (every compose calls it)."""
    global _schemas_registered
    if _schemas_registered:
        return
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    from scanreg.app.report.params import ReportParams
    from scanreg.app.tracking import TRACKING
    from scanreg.eval.metrics import EvalParams
    from scanreg.runner.settings import MultiviewParams

    load_all()
    TRACKING.store_schemas()
    ConfigStore.instance().store(name="_evaluate", node=EvalParams)
    ConfigStore.instance().store(name="_report", node=ReportParams)
    ConfigStore.instance().store(name="_multiview", node=MultiviewParams)
    if not OmegaConf.has_resolver("scanreg_conf_dir"):
        OmegaConf.register_new_resolver("scanreg_conf_dir", lambda: str(conf_dir()))
        OmegaConf.register_new_resolver("scanreg_groups", help_groups)
    _schemas_registered = True


_schemas_registered = False


def config_error_line(e: BaseException) -> str:
    """Hydra's composition error ``e`` as one line: an unknown choice of a group with the valid ones, an
    unknown or mistyped parameter of a stage as the registry says it, an unknown key, a bad override."""
    import re

    from hydra.errors import MissingConfigException, OverrideParseException

    text = " ".join(str(e).split())
    cause = e.__cause__ or e.__context__  # (Hydra chains some of OmegaConf's errors as the context)
    if isinstance(e, OverrideParseException):
        return f"bad override: {str(e).splitlines()[0]}"
    m = re.match(r"Ambiguous value for argument '([^=']+)=(.*?)' 1\. ", text)
    if m:  # (Hydra's own text shows its quotes escaped)
        key, value = m.groups()
        line = f"{key}={value}: several values for one run; to run each, sweep them with -m (scanreg -m {key}={value})"
        if group_choices(key.lstrip("+~")) or "'" in value or '"' in value:  # (a group's choice is one name)
            return line
        return f"{line}; for one value with commas quote it ({key}=\"'{value}'\"), for a list write {key}=[{value}]"
    if isinstance(e, MissingConfigException):
        m = re.search(r"Could not find '([^']+)/([^'/]+)'", text)
        if m:
            group, choice = m.groups()
            valid = group_choices(group) or re.findall(r"\t(\w+)", str(e))
            return f"unknown {group} '{choice}'; valid {group} choices: {', '.join(v for v in valid if v[:1] != '_')}"
        return text[:500]
    stage = getattr(getattr(cause, "object_type", None), "__scanreg_stage__", None)
    key = str(getattr(cause, "full_key", "") or "")
    m = re.search(r"(?:Could not override|Error merging override) '?([\w.]+)", text)
    key = key or (m.group(1) if m else "")
    param = key.split(".", 1)[1] if "." in key else key
    if stage is not None and param:
        family, name = stage
        params_cls = _registry(family).get(name).Params
        where = f"{family}={name}"
    elif key.split(".")[0] in ("evaluate", "report"):
        params_cls, where = _block_params(key.split(".")[0]), key.split(".")[0]
    else:
        params_cls = where = None
    if params_cls is not None:
        unknown = "Could not override" in text or "not in" in str(cause or "")
        if unknown:  # an unknown parameter: the registry's message
            try:
                make_params(params_cls, {param.split(".")[0]: None}, where)
            except ConfigError as ce:
                if "Could not override" not in text:  # set by a config file (an experiment), not the command line
                    return f"{ce} (set by a config file: an experiment or preset written for another choice?)"
                return str(ce)
        value = re.search(r"[Vv]alue '([^']*)'", str(cause or ""))
        return type_error(params_cls, param, value.group(1) if value else None, where)
    if "Could not override" in text and key:
        return f"unknown config key '{key}'{_did_you_mean(key)} (add it with +{key}=VALUE if it is meant to be new)"
    return (text + (f" ({' '.join(str(cause).split())})" if cause else ""))[:500]


def _top_level_keys() -> list[str]:
    """The keys at the top of a run's config, as ``conf/config.yaml`` makes them: its config groups (``data``,
    ..., ``experiment``), its blocks (``_evaluate@evaluate``) and its own keys (``seed``, ...)."""
    from omegaconf import OmegaConf

    conf = OmegaConf.load(conf_dir() / "config.yaml")
    keys = [str(k) for k in conf if k not in ("defaults", "hydra")]
    for entry in conf.get("defaults", []):
        if isinstance(entry, str):
            keys += entry.split("@")[1:]  # a block: its package
        else:
            keys += [str(k) for k in entry]  # a group: its name
    return keys


def _did_you_mean(key: str) -> str:
    """``: did you mean 'KEY'?`` when the first part of an unknown ``key`` is a near miss of a key at the top of
    the config (``smapler.n_points``: ``sampler.n_points``), else nothing."""
    import difflib

    head, dot, rest = key.partition(".")
    near = difflib.get_close_matches(head, _top_level_keys(), n=1, cutoff=0.75)
    if near and near[0] != head:
        return f": did you mean '{near[0]}{dot}{rest}'?"
    owners = [] if dot else _parameter_owners(head)  # a stage's parameter given without its stage
    return f": did you mean {' or '.join(repr(f'{o}.{head}') for o in owners)}?" if owners else ""


def _parameter_owners(name: str) -> list[str]:
    """The config blocks (stage families, ``evaluate``, ``report``) that have a parameter called ``name``."""
    from dataclasses import fields, is_dataclass

    from scanreg.stages.registry import REGISTRIES

    register_schemas()  # (the stages registered)
    out = []
    for family, reg in REGISTRIES.items():
        for stage in reg.names():
            params = getattr(reg.get(stage), "Params", None)
            if is_dataclass(params) and name in {f.name for f in fields(params)}:
                out.append(family)
                break
    return out + [b for b in ("evaluate", "report") if name in {f.name for f in fields(_block_params(b))}]


def interpolation_error_line(e: BaseException) -> str:
    """A config that does not resolve as one line: a value that an interpolation (``${seed}``) passes on and that
    is not of the type it goes to, by the key the user sets (``seed=abc: expects an integer``); else OmegaConf's
    first line."""
    import re

    text = " ".join(str(e).split())
    m = re.search(r"interpolation '\$\{([\w.]+)\}': Value '([^']*)' of type '\w+' could not be converted to (\w+)", text)
    if m:
        key, value, kind = m.groups()
        return f"{key}={value}: expects {'an' if kind[0] in 'AEIOU' else 'a'} {kind.lower()}"
    return f"config: {e}".splitlines()[0]


def _registry(family: str):
    """The registry of a config group's implementations (the stages', or the tracking backends')."""
    if family == "tracking":
        from scanreg.app.tracking import TRACKING

        return TRACKING
    return REGISTRIES[family]


def _block_params(block: str) -> type:
    if block == "evaluate":
        from scanreg.eval.metrics import EvalParams

        return EvalParams
    from scanreg.app.report.params import ReportParams

    return ReportParams


def git_revision() -> str:
    """The project's git commit (``+dirty`` when the work tree has changes), or ``unknown`` outside git."""
    if not (PROJECT_ROOT / "pyproject.toml").is_file():  # an installed wheel: no checkout to ask
        return "unknown"
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=PROJECT_ROOT, capture_output=True,
                              text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=PROJECT_ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
