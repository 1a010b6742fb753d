"""The import rules of the layering hold: imports point downward only.

``acquire -> planner -> pipeline``, ``acquire -> mock_camera``; ``experiments`` (the paper's Sec. 7
and Fig. 8 on the simulator) sits above ``pipeline`` and ``mock_camera``; ``pipeline`` imports
nothing of ours above it, ``mock_camera`` only pipeline's shared types; no library module imports
a command module. Every import statement counts, also those inside functions (lazy imports).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import hdrcap

PKG = Path(hdrcap.__file__).resolve().parent
#: Folder of each sub-package (the root folders are mapped into ``hdrcap`` by package-dir).
SUBPACKAGES = {
    name: Path(__import__(f"hdrcap.{name}", fromlist=["_"]).__file__).resolve().parent
    for name in ("pipeline", "planner", "mock_camera", "acquire")
}

#: What each layer may not import (prefixes of absolute module names).
FORBIDDEN = {
    "pipeline": ("hdrcap.planner", "hdrcap.acquire", "hdrcap.mock_camera", "hdrcap.experiments", "hdrcap.api"),
    "planner": ("hdrcap.acquire", "hdrcap.mock_camera", "hdrcap.experiments", "hdrcap.api"),
    "mock_camera": ("hdrcap.planner", "hdrcap.acquire", "hdrcap.experiments", "hdrcap.api"),
}
#: The only modules of pipeline the simulator may read: shared parameter and error types.
MOCK_CAMERA_MAY_READ = (
    "hdrcap.pipeline.params",
    "hdrcap.pipeline.errors",
    "hdrcap.pipeline.camera_types",
    "hdrcap.pipeline.times",
)


def _modules():
    """(layer, absolute module name, path) of every module of the project."""
    for layer, folder in SUBPACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            yield layer, ".".join(["hdrcap", layer, *parts]), path
    for path in sorted(PKG.glob("*.py")):
        name = "hdrcap" if path.stem == "__init__" else f"hdrcap.{path.stem}"
        yield "hdrcap", name, path
    exp = PKG / "experiments"
    if exp.is_dir():
        for path in sorted(exp.rglob("*.py")):
            parts = [p for p in path.relative_to(exp).with_suffix("").parts if p != "__init__"]
            yield "experiments", ".".join(["hdrcap", "experiments", *parts]), path


def imports_of(name: str, path: Path) -> set[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved)."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)  # `from pkg import module`
    return out


MODULES = list(_modules())


def _violations(layer: str, name: str, imported: set[str]) -> list[str]:
    bad = []
    for mod in sorted(imported):
        if not mod.startswith("hdrcap"):
            continue
        if any(mod == f or mod.startswith(f + ".") for f in FORBIDDEN.get(layer, ())):
            bad.append(mod)
        if layer == "mock_camera" and mod.startswith("hdrcap.pipeline"):
            if not any(mod == m or mod.startswith(m + ".") for m in MOCK_CAMERA_MAY_READ):
                bad.append(mod)
        is_command = name.startswith("hdrcap.acquire.commands") or name == "hdrcap.acquire.cli"
        if not is_command and mod.startswith("hdrcap.acquire.commands"):
            bad.append(mod)
    return bad


@pytest.mark.parametrize("layer,name,path", MODULES, ids=[m[1] for m in MODULES])
def test_imports_point_downward(layer, name, path):
    bad = _violations(layer, name, imports_of(name, path))
    assert not bad, f"{name} imports {bad} against the layering"


def test_the_rule_test_can_fail(tmp_path):
    """The checker flags the import the layering forbids (pipeline importing the simulator)."""
    src = tmp_path / "denoise.py"
    src.write_text(
        "def f():\n    from hdrcap.mock_camera.sensor import PRESETS\n    from ..mock_camera import scenes\n"
    )
    imported = imports_of("hdrcap.pipeline.denoise", src)
    assert "hdrcap.mock_camera.scenes" in _violations("pipeline", "hdrcap.pipeline.denoise", imported)
    assert "hdrcap.mock_camera.sensor" in _violations("pipeline", "hdrcap.pipeline.denoise", imported)
    assert _violations("acquire", "hdrcap.acquire.job", {"hdrcap.acquire.commands.merge"})
    assert not _violations("acquire", "hdrcap.acquire.cli", {"hdrcap.acquire.commands.merge"})
    assert _violations("mock_camera", "hdrcap.mock_camera.dng", {"hdrcap.pipeline.merge"})
    assert not _violations("mock_camera", "hdrcap.mock_camera.sensor", {"hdrcap.pipeline.params"})


def test_every_module_is_seen():
    """The walk covers all four layers (a moved folder would silently check nothing)."""
    layers = {m[0] for m in MODULES}
    assert {"pipeline", "planner", "mock_camera", "acquire", "hdrcap"} <= layers
    assert sum(1 for m in MODULES if m[0] == "pipeline") >= 10
