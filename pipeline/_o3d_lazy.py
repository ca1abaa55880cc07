"""Defer Open3D's plotly/dash viewer, which ``import open3d`` loads eagerly and scanreg never uses.

``open3d/visualization/__init__.py`` runs ``from .draw_plotly import get_plotly_fig, draw_plotly,
draw_plotly_server``, and ``draw_plotly`` imports plotly and dash at module level: about 0.25-0.45 s of every
``scanreg`` process's start-up (measured with ``python -X importtime``; half of Open3D's import). :func:`install`,
called when the ``scanreg`` package is imported and only if Open3D is not imported yet, puts a stand-in module
under that name whose three functions import the real module when first called and then forward to it, so that
Open3D behaves as before for anyone who uses its plotly viewer (``tests/test_o3d_lazy.py``); any other name looked
up on the stand-in loads the real module too. If Open3D's layout changes (the module is renamed or gains names
that ``visualization/__init__`` imports from it), the stand-in loads the real module at once: slower, never wrong.
"""

from __future__ import annotations

import sys
import types

_NAME = "open3d.visualization.draw_plotly"
_FUNCS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _load() -> types.ModuleType:
    import importlib

    stub = sys.modules.get(_NAME)
    if stub is not None and not getattr(stub, "_scanreg_stub", False):
        return stub  # loaded already
    sys.modules.pop(_NAME, None)
    real = importlib.import_module(_NAME)
    parent = sys.modules.get("open3d.visualization")
    if parent is not None:  # importing the submodule rebinds the parent's name 'draw_plotly' to the module
        for f in _FUNCS:
            if hasattr(real, f):
                setattr(parent, f, getattr(real, f))
    return real


def _forwarder(name: str):
    def forward(*args, **kwargs):
        return getattr(_load(), name)(*args, **kwargs)

    forward.__name__ = forward.__qualname__ = name
    forward.__doc__ = f"Open3D's ``{name}`` (its module imported on first use by scanreg's start-up shim)."
    return forward


def _getattr(name: str):
    if name.startswith("__"):
        raise AttributeError(name)
    return getattr(_load(), name)


def install() -> bool:
    """Put the stand-in in place unless Open3D (or the module) is imported already; True if it did."""
    if "open3d" in sys.modules or _NAME in sys.modules:
        return False
    stub = types.ModuleType(_NAME, "scanreg's stand-in for Open3D's plotly viewer; see scanreg._o3d_lazy.")
    stub._scanreg_stub = True
    for f in _FUNCS:
        setattr(stub, f, _forwarder(f))
    stub.__getattr__ = _getattr
    sys.modules[_NAME] = stub
    return True
