"""Griffe extension for scanreg's documentation (mkdocs.yml, mkdocstrings' python handler).

1. The layout: the package ``scanreg`` is the folder ``pipeline/``, but its subpackage ``scanreg.stages`` is the
   folder ``stages/`` (``package-dir`` in pyproject.toml). Griffe reads a package from one folder, so this
   extension attaches ``stages/`` as ``scanreg.stages`` when ``scanreg`` is visited.
2. The docstrings are written with Sphinx roles (``:func:`prepare_scan```, ``:class:`~scanreg.types.Result```).
   Each role whose target is an object of the loaded tree becomes a cross-reference (an optional autoref: a link
   where the target is rendered on some page, plain code elsewhere); ``::`` before a literal block becomes ``:``.
   A role whose target names no object of scanreg is rendered as code and logged (``info`` level;
   ``SCANREG_DOCS_STALE_REFS=error`` makes it a warning, which fails ``mkdocs build --strict``).
"""

from __future__ import annotations

import html
import importlib.util
import logging
import os
import re
from pathlib import Path

from griffe import Extension, GriffeLoader, Module, Object

_log = logging.getLogger("mkdocs.plugins.scanreg_docs")

ROLE = re.compile(r":(?:py:)?(?P<role>mod|func|class|meth|attr|data|exc|obj|const):`(?P<target>[^`]+)`")


class ScanregLayout(Extension):
    # ---------------------------------------------------------------------------------------- 1. the layout

    def on_module_members(self, *, mod: Module, agent, **kwargs) -> None:
        if mod.path != "scanreg" or "stages" in mod.members:
            return
        spec = importlib.util.find_spec("scanreg.stages")
        if spec is None or spec.origin is None:
            return
        loader = GriffeLoader(docstring_parser=agent.docstring_parser, docstring_options=agent.docstring_options,
                              lines_collection=mod.lines_collection, modules_collection=mod.modules_collection)
        stages = loader._load_module("stages", Path(spec.origin), parent=mod)  # a private method: griffe has no public one
        mod.set_member("stages", stages)

    # ------------------------------------------------------------------------------------ 2. the docstrings

    def on_package(self, *, pkg: Module, **kwargs) -> None:
        if pkg.path != "scanreg":
            return
        for obj in _walk(pkg):
            if obj.docstring is not None:
                obj.docstring.value = self._markdown(obj, obj.docstring.value)

    def _markdown(self, obj: Object, text: str) -> str:
        def role(m: re.Match) -> str:
            target = m["target"].strip()
            short = target.startswith("~")
            target = target.lstrip("~.")
            shown = target.rsplit(".", 1)[-1] if short else target
            if m["role"] in ("func", "meth"):
                shown += "()"
            path = _resolve(obj, target)
            code = f"<code>{html.escape(shown)}</code>"
            if path == "":  # another package's object (numpy, omegaconf...): code, no link
                return code
            if path is None:
                level = logging.WARNING if os.environ.get("SCANREG_DOCS_STALE_REFS") == "error" else logging.INFO
                _log.log(level, "%s: %s names no object of scanreg", obj.path, m.group(0))
                return code
            return f'<autoref identifier="{html.escape(path)}" optional>{code}</autoref>'

        text = ROLE.sub(role, text)
        return re.sub(r"(?<=\S)::\n", ":\n", text)  # reST's literal-block marker


def _walk(obj: Object):
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)


def _resolve(obj: Object, target: str) -> str | None:
    """The full path of ``target`` as seen from ``obj``'s scope (its class, its module, their imports), or from
    the package root; ``""`` when it names another package's object; None when it names nothing."""
    head, _, rest = target.partition(".")
    scope = obj if obj.is_module or obj.is_class else obj.parent
    ours = target.startswith("scanreg")  # a name of scanreg's (by its path, or found in scope)
    while scope is not None:
        try:
            base = scope.resolve(head)
        except Exception:  # noqa: BLE001 (griffe's NameResolutionError)
            base = None
        if base is not None:
            full = f"{base}.{rest}" if rest else base
            if _exists(obj, full):
                return full
            ours = ours or full.startswith("scanreg")
        scope = scope.parent
    if _exists(obj, target):
        return target
    return None if ours or "." not in target else ""


def _exists(obj: Object, path: str) -> bool:
    try:
        obj.modules_collection.get_member(path)
        return True
    except Exception:  # noqa: BLE001
        return False
