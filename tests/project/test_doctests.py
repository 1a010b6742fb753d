"""Every docstring example of the library runs and shows what the code does (doctest).

Docstrings are contracts with a runnable example; this runs them all in ``make test``. The
public API must keep at least five (``pytest --doctest-modules hdrcap/api.py`` runs the same).
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

import hdrcap

PKG = Path(hdrcap.__file__).resolve().parent


def _modules_with_examples() -> list[str]:
    """Names of the library modules whose source holds a ``>>>`` example."""
    roots = {"hdrcap": PKG}
    for sub in ("pipeline", "planner", "mock_camera", "acquire"):
        roots[f"hdrcap.{sub}"] = Path(importlib.import_module(f"hdrcap.{sub}").__file__).resolve().parent
    names = set()
    for prefix, folder in roots.items():
        for path in folder.rglob("*.py"):
            if prefix == "hdrcap" and path.relative_to(folder).parts[0] in (
                "pipeline",
                "planner",
                "mock_camera",
                "acquire",
            ):
                continue
            if ">>> " not in path.read_text():
                continue
            parts = [p for p in path.relative_to(folder).with_suffix("").parts if p != "__init__"]
            names.add(".".join([prefix, *parts]))
    return sorted(names)


MODULES = _modules_with_examples()
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def test_the_api_has_runnable_examples():
    finder = doctest.DocTestFinder()
    api = importlib.import_module("hdrcap.api")
    with_examples = [t for t in finder.find(api) if t.examples]
    assert len(with_examples) >= 5, [t.name for t in with_examples]
    assert "hdrcap.api" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=FLAGS, verbose=False, report=True)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"
