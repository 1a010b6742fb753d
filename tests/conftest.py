"""Shared test fixtures. Every random generator in the tests is seeded."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def emva_dataset_dir() -> Path | None:
    """The EMVA 1288 reference set 001, or None when it is not on this machine."""
    env = os.environ.get("HDRCAP_EMVA_REF001")
    path = Path(env) if env else REPO.parent / "shared" / "datasets" / "emva1288-ref001"
    return path if (path / "EMVA1288_Data.txt").is_file() else None


@pytest.fixture
def emva_dir() -> Path:
    path = emva_dataset_dir()
    if path is None:
        pytest.skip("EMVA 1288 reference set 001 not found (set HDRCAP_EMVA_REF001 or put it in ../shared/datasets)")
    return path


def run_cli(*args, cwd=None, check=False, timeout=600, env=None) -> subprocess.CompletedProcess:
    """Run ``hdrcap ARGS`` in a subprocess (``python -m hdrcap``, the installed package)."""
    full_env = dict(os.environ)
    if env:
        full_env.update(env)
    proc = subprocess.run(
        [sys.executable, "-m", "hdrcap", *map(str, args)],
        cwd=cwd or REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=full_env,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"hdrcap {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


@pytest.fixture
def cli():
    return run_cli
