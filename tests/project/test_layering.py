"""The import rules of the layering hold: imports point downward only.

Faces (``hdrcap.api``, ``hdrcap.cli``, ``hdrcap.batch``, ``hdrcap.bluesky``, ``hdrcap.serve``,
``hdrcap.experiments``) -> ``acquire`` (cameras and capture) -> ``planner`` -> ``pipeline``; ``acquire`` -> ``mock_camera`` (the
simulated camera backend) -> pipeline's shared types and file formats. ``pipeline`` imports
nothing of ours above it; no library module imports the command line, and the command line is
the only importer of click. Every import statement counts, also those inside functions (lazy
imports).
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
#: Face packages inside the ``hdrcap`` folder itself.
FACES = ("cli", "batch", "bluesky", "serve", "experiments")

_ABOVE_PIPELINE = (
    "hdrcap.planner",
    "hdrcap.acquire",
    "hdrcap.mock_camera",
    "hdrcap.experiments",
    "hdrcap.api",
    "hdrcap.cli",
    "hdrcap.batch",
    "hdrcap.bluesky",
    "hdrcap.serve",
)
#: What each layer may not import (prefixes of absolute module names).
FORBIDDEN = {
    "pipeline": _ABOVE_PIPELINE,
    "planner": (
        "hdrcap.acquire",
        "hdrcap.mock_camera",
        "hdrcap.experiments",
        "hdrcap.api",
        "hdrcap.cli",
        "hdrcap.batch",
        "hdrcap.bluesky",
        "hdrcap.serve",
    ),
    "mock_camera": (
        "hdrcap.planner",
        "hdrcap.acquire",
        "hdrcap.experiments",
        "hdrcap.api",
        "hdrcap.cli",
        "hdrcap.batch",
        "hdrcap.bluesky",
        "hdrcap.serve",
    ),
    "acquire": ("hdrcap.experiments", "hdrcap.api", "hdrcap.cli", "hdrcap.batch", "hdrcap.bluesky", "hdrcap.serve"),
    "api": ("hdrcap.cli", "hdrcap.batch", "hdrcap.bluesky", "hdrcap.experiments", "hdrcap.serve"),
    "batch": ("hdrcap.cli", "hdrcap.api", "hdrcap.bluesky", "hdrcap.serve"),
    # the Bluesky detector drives acquire (the capture session and merge), never a command
    "bluesky": ("hdrcap.cli", "hdrcap.api", "hdrcap.batch", "hdrcap.experiments", "hdrcap.serve"),
    # the web page: reads run folders (acquire), results (pipeline) and archives (batch)
    "serve": ("hdrcap.cli", "hdrcap.api", "hdrcap.bluesky", "hdrcap.experiments"),
    "experiments": ("hdrcap.cli", "hdrcap.batch", "hdrcap.api", "hdrcap.acquire", "hdrcap.bluesky", "hdrcap.serve"),
}
#: The only modules of pipeline the simulator may read: shared parameter and error types, the
#: time rule and the file formats it writes (never the estimator's noise model or merge).
MOCK_CAMERA_MAY_READ = (
    "hdrcap.pipeline.params",
    "hdrcap.pipeline.errors",
    "hdrcap.pipeline.times",
    "hdrcap.pipeline.io",
    "hdrcap.pipeline.schema",
)


def _layer_of(name: str) -> str:
    parts = name.split(".")
    if len(parts) == 1:
        return "hdrcap"
    if parts[1] in SUBPACKAGES or parts[1] in FACES or parts[1] == "api":
        return parts[1]
    return "hdrcap"


def _modules():
    """(layer, absolute module name, path) of every module of the project."""
    for layer, folder in SUBPACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            yield layer, ".".join(["hdrcap", layer, *parts]), path
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        name = ".".join(["hdrcap", *parts])
        yield _layer_of(name), name, path


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
        if mod == "click" or mod.startswith("click."):
            if layer != "cli":
                bad.append(mod)
            continue
        if not mod.startswith("hdrcap"):
            continue
        if any(mod == f or mod.startswith(f + ".") for f in FORBIDDEN.get(layer, ())):
            bad.append(mod)
        if layer == "mock_camera" and mod.startswith("hdrcap.pipeline"):
            if not any(mod == m or mod.startswith(m + ".") for m in MOCK_CAMERA_MAY_READ):
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
        "def f():\n    from hdrcap.mock_camera.sensor import PRESETS\n    from ...mock_camera import scenes\n"
    )
    imported = imports_of("hdrcap.pipeline.denoise.filter", src)
    assert "hdrcap.mock_camera.scenes" in _violations("pipeline", "hdrcap.pipeline.denoise.filter", imported)
    assert "hdrcap.mock_camera.sensor" in _violations("pipeline", "hdrcap.pipeline.denoise.filter", imported)
    assert _violations("acquire", "hdrcap.acquire.capture.job", {"hdrcap.cli.commands.merge"})
    assert _violations("api", "hdrcap.api", {"hdrcap.cli.util"})
    assert _violations("api", "hdrcap.api", {"click"})
    assert _violations("bluesky", "hdrcap.bluesky.detector", {"hdrcap.cli.commands.capture"})
    assert _violations("bluesky", "hdrcap.bluesky.detector", {"click"})
    assert not _violations("bluesky", "hdrcap.bluesky.detector", {"hdrcap.acquire.capture.run", "ophyd_async.core"})
    assert _violations("pipeline", "hdrcap.pipeline.merge.files", {"click.core"})
    assert not _violations("cli", "hdrcap.cli", {"click", "hdrcap.cli.commands.merge"})
    assert _violations("mock_camera", "hdrcap.mock_camera.dng", {"hdrcap.pipeline.merge.accumulator"})
    assert _violations("serve", "hdrcap.serve.app", {"hdrcap.cli.util"})
    assert _violations("serve", "hdrcap.serve.app", {"click"})
    assert _violations("acquire", "hdrcap.acquire.capture.runfolder", {"hdrcap.serve.runs"})
    assert not _violations("serve", "hdrcap.serve.series", {"hdrcap.batch.archive", "hdrcap.acquire.capture.manifest"})
    assert not _violations("mock_camera", "hdrcap.mock_camera.sensor", {"hdrcap.pipeline.params"})
    assert _violations("pipeline", "hdrcap.pipeline.compat", {"hdrcap.acquire.camera.types"})


def test_every_module_is_seen():
    """The walk covers every layer (a moved folder would silently check nothing)."""
    layers = {m[0] for m in MODULES}
    assert {
        "pipeline",
        "planner",
        "mock_camera",
        "acquire",
        "hdrcap",
        "api",
        "cli",
        "batch",
        "bluesky",
        "serve",
        "experiments",
    } <= layers
    assert sum(1 for m in MODULES if m[0] == "pipeline") >= 10
    assert sum(1 for m in MODULES if m[0] == "cli") >= 10


TESTS = Path(__file__).resolve().parents[1]
BENCHMARKS = TESTS.parent / "benchmarks"
#: Module names of the benchmark scripts and of the test modules.
_BENCH_NAMES = {p.stem for p in BENCHMARKS.glob("*.py")}
_TEST_NAMES = {p.stem for p in TESTS.rglob("test_*.py")}


def _test_imports_of(path: Path) -> list[str]:
    """What a test file imports that a test may not: a test module, a benchmark script, or
    anything reached by changing ``sys.path`` (a call, not text in a script it writes)."""
    bad = []
    where = path.relative_to(TESTS) if path.is_relative_to(TESTS) else path
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [node.module]
        for name in names:
            parts = name.split(".")
            if parts[0] in _BENCH_NAMES or parts[-1] in _TEST_NAMES or parts[0] == "benchmarks":
                bad.append(f"{where}:{node.lineno}: imports {name}")
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in ("insert", "append")
            and ast.unparse(node.func.value) == "sys.path"
        ):
            bad.append(f"{where}:{node.lineno}: changes sys.path")
    return bad


def test_no_test_imports_a_test_module_or_a_benchmark():
    """Shared test code lives in tests/helpers (or the library), never in a test module or a
    benchmark script: each test file runs on its own."""
    bad = [line for path in sorted(TESTS.rglob("*.py")) for line in _test_imports_of(path)]
    assert not bad, "\n".join(bad)


def test_the_test_import_rule_can_fail(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import sys\nsys.path.insert(0, 'x')\nfrom bench_batch import main\nfrom tests.x.test_api import y\n"
    )
    assert len(_test_imports_of(sample)) == 3
