"""The import layers: every module imports only modules of its own layer or lower ones (statically, including
imports inside functions), so the framework reaches stages only through the registries."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# highest first; a module may import its own layer and the layers after it. A layer is a set of packages (every
# module in them) and modules, as the folders show them (README, Architecture).
LAYERS = [
    ("app", {"scanreg", "scanreg.api", "scanreg.app"}),
    ("runner", {"scanreg.runner"}),
    ("stages", {"scanreg.stages"}),
    ("kernel", {"scanreg.eval", "scanreg.io", "scanreg.mesh"}),
    ("types", {"scanreg.types"}),
    ("base", {"scanreg.geometry", "scanreg.errors", "scanreg.process", "scanreg.conf"}),
]
FRAMEWORK_MAY_IMPORT = {"scanreg.stages", "scanreg.stages.registry", "scanreg.stages.protocols"}
"""The stage modules the framework (pipeline/) may import: the registries and the contracts, never a stage."""


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT)
    parts = {"pipeline": ["scanreg"], "stages": ["scanreg", "stages"], "conf": ["scanreg", "conf"]}[rel.parts[0]]
    parts = parts + list(rel.parts[1:])
    parts[-1] = parts[-1].removesuffix(".py")
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer_of(mod: str) -> int:
    for i, (_, mods) in enumerate(LAYERS):
        if mod in mods or any(mod.startswith(m + ".") for m in mods if m != "scanreg"):
            return i
    raise AssertionError(f"module {mod} is in no layer: add it to LAYERS in tests/test_layers.py")


def scanreg_imports(path: Path, text: str | None = None) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text() if text is None else text)):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        assert not any(n.split(".")[0] in ("pipeline", "stages") for n in names), \
            f"{path}: imports the folder name, not the package scanreg: {names}"
        # the longest name that is a module (``from scanreg.geometry import Mesh`` imports scanreg.geometry)
        for n in names:
            if n.startswith("scanreg") and _is_module(n):
                out.append(n)
    return out


def _is_module(name: str) -> bool:
    try:
        layer_of(name)
        return True
    except AssertionError:
        return False


def source_files() -> list[Path]:
    return sorted(p for d in ("pipeline", "stages", "conf") for p in (ROOT / d).rglob("*.py"))


def test_every_module_has_a_layer():
    for p in source_files():
        layer_of(module_name(p))


def test_imports_go_downwards_only():
    bad = []
    for p in source_files():
        mod = module_name(p)
        for imp in scanreg_imports(p):
            if imp == "scanreg" and mod != "scanreg":
                continue  # the package itself (its lazy API attributes are not imported by core modules)
            if layer_of(imp) < layer_of(mod):
                bad.append(f"{mod} ({LAYERS[layer_of(mod)][0]}) imports {imp} ({LAYERS[layer_of(imp)][0]})")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_framework_never_imports_a_stage_module():
    for p in (ROOT / "pipeline").rglob("*.py"):
        stages = [i for i in scanreg_imports(p) if i.startswith("scanreg.stages") and i not in FRAMEWORK_MAY_IMPORT
                  and not any(i.startswith(m + ".") and i.count(".") == m.count(".") + 1 and m != "scanreg.stages"
                              for m in FRAMEWORK_MAY_IMPORT)]
        assert not stages, f"{p.relative_to(ROOT)} imports {stages}: use the registries"


def test_the_checker_catches_an_upward_import():
    """The rule above is not vacuous: a core module importing the runner inside a function is caught."""
    core = ROOT / "pipeline" / "geometry" / "voxels.py"
    text = core.read_text() + "\n\ndef _x():\n    from scanreg.runner import run_pipeline\n"
    imports = scanreg_imports(core, text)
    assert "scanreg.runner" in imports
    assert layer_of("scanreg.runner") < layer_of(module_name(core))
