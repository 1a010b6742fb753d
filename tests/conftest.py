"""Fixtures of every test folder. Every random generator in the tests is seeded."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.cli import run_cli
from tests.helpers.datasets import emva_dataset_dir


@pytest.fixture
def emva_dir() -> Path:
    path = emva_dataset_dir()
    if path is None:
        pytest.skip("EMVA 1288 reference set 001 not found (set HDRCAP_EMVA_REF001 or put it in ../shared/datasets)")
    return path


@pytest.fixture
def cli():
    return run_cli
