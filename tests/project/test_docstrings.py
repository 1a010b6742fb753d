"""Every public function of pipeline and planner documents its parameters and what it returns
(numpydoc ``Parameters`` / ``Returns`` sections, with units in the descriptions)."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import hdrcap.pipeline
import hdrcap.planner


def _public_functions():
    for pkg in (hdrcap.pipeline, hdrcap.planner):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            if info.name.rsplit(".", 1)[-1].startswith("_"):
                continue
            mod = importlib.import_module(info.name)
            for name in getattr(mod, "__all__", ()):
                obj = getattr(mod, name, None)
                if inspect.isfunction(obj) and obj.__module__ == mod.__name__:
                    yield f"{info.name}.{name}", obj


FUNCTIONS = sorted(_public_functions())


def _gaps(fn) -> list[str]:
    doc = inspect.getdoc(fn) or ""
    sig = inspect.signature(fn)
    gaps = []
    if any(p.name not in ("self", "cls") for p in sig.parameters.values()) and "Parameters\n----------" not in doc:
        gaps.append("Parameters")
    returns = sig.return_annotation not in (None, "None", inspect.Signature.empty) or "return " in inspect.getsource(fn)
    if returns and "Returns\n-------" not in doc and "Yields\n------" not in doc:
        gaps.append("Returns")
    return gaps


def test_there_is_something_to_check():
    assert len(FUNCTIONS) > 100


@pytest.mark.parametrize("name,fn", FUNCTIONS, ids=[n for n, _ in FUNCTIONS])
def test_numpydoc_sections(name, fn):
    assert not _gaps(fn), f"{name}: docstring lacks {', '.join(_gaps(fn))}"
