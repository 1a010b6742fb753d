"""Tasks for the batch's local worker pool in tests (importable by its spawned workers)."""

from __future__ import annotations

import os
import tempfile


def die_on_poison(source, folder: str) -> str:
    """The run's folder; a run named ``poison`` leaves a file in ``folder`` (one per try) and
    ends its worker process with exit status 7, as a crash would."""
    if source.folder.endswith("/poison"):
        tempfile.NamedTemporaryFile(dir=folder, prefix="poison-", delete=False).close()
        os._exit(7)
    return source.folder
