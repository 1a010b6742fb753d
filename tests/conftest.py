"""Fixtures of every test folder. Every random generator in the tests is seeded."""

from __future__ import annotations

import signal
import threading
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


@pytest.fixture
def sigterm_guard():
    """Without a handler of the command's own, SIGTERM would end the test process: fail instead."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals are delivered to the main thread only")

    def unhandled(signum, _frame):
        raise AssertionError("SIGTERM reached the default handler: the command does not stop cleanly")

    old = signal.signal(signal.SIGTERM, unhandled)
    yield
    signal.signal(signal.SIGTERM, old)
