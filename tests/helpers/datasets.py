"""Real data sets the tests use when they are on the machine."""

from __future__ import annotations

import os
from pathlib import Path

from tests.helpers import REPO


def emva_dataset_dir() -> Path | None:
    """The EMVA 1288 reference set 001, or None when it is not on this machine."""
    env = os.environ.get("HDRCAP_EMVA_REF001")
    path = Path(env) if env else REPO.parent / "shared" / "datasets" / "emva1288-ref001"
    return path if (path / "EMVA1288_Data.txt").is_file() else None
