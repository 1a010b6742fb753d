"""Small DNG files of a fixed made-up camera, for the readers' and the commands' tests."""

from __future__ import annotations

import datetime as dt

from hdrcap.mock_camera.dng import write_dng


def write_test_dng(path, data, t=1 / 250, iso=400, cfa="RGGB", black=128, white=4095):
    """Write ``data`` (DN) as a DNG of a fixed camera (Acme Sim 1, serial 42, a fixed capture
    time) with the given exposure time (s), ISO, CFA pattern and levels; return ``path``."""
    with open(path, "wb") as f:
        write_dng(
            f,
            data,
            exposure_time=t,
            iso=iso,
            black_level=black,
            white_level=white,
            cfa=cfa,
            make="Acme",
            model="Sim 1",
            serial="42",
            timestamp=dt.datetime(2026, 1, 2, 3, 4, 5),
        )
    return path
