"""Runs of the batch archive as the batch makes them, without a merge."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from hdrcap.batch import archive as archive_mod
from hdrcap.batch.archive import ArchiveRun

#: Photosites (rows, columns) of :func:`archive_run`'s channels.
SHAPE = (6, 8)
#: A calibration record as the batch makes it (identity, parameters, provenance) and the header
#: entry it stands for.
CALIBRATION = {"sha256": "ab" * 32, "params": {"gain": 0.5, "read_noise": 2.0}, "provenance": {"source": "test"}}


def archive_run(i: int, seed: int | None = None, shape=SHAPE, calibration=CALIBRATION) -> ArchiveRun:
    """Run ``i`` of a small archive: seeded channels (``seed``, default ``i``), a header naming
    ``i`` and ``calibration`` (a record as the batch makes it)."""
    rng = np.random.default_rng(i if seed is None else seed)
    irr = rng.lognormal(5, 2, shape).astype(np.float32)
    channels = {
        "irradiance": irr,
        "sigma": (0.05 * irr + 1).astype(np.float32),
        "nexp": rng.integers(0, 4, shape).astype(np.float32),
    }
    return ArchiveRun(
        folder=f"/runs/{i:03d}",
        start_time=f"2026-01-0{1 + i % 9}T10:00:00+00:00",
        channels=channels,
        header={
            "unit": "electrons per second per photosite",
            "i": i,
            "calibration": {"params": calibration["params"], "provenance": calibration["provenance"]},
        },
        exposure_times=[0.001, 0.01],
        plan=None,
        merge_options={"iterations": 20},
        calibration=calibration,
    )


def _interrupted(*args, **kwargs):
    raise KeyboardInterrupt


@contextmanager
def commit_interrupted(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Inside the block, a writer fails at the commit itself, after writing its runs' chunks:
    writing the consolidated metadata raises KeyboardInterrupt, which the block must raise (the
    private step is replaced on purpose: no public door fails there). Restored after."""
    with monkeypatch.context() as patch, pytest.raises(KeyboardInterrupt):
        patch.setattr(archive_mod, "_write_consolidated", _interrupted)
        yield
