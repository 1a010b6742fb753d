"""The calibration's view of an input frame, and frame series grouped by exposure time.

A frame is any object with ``data`` (a 2-D raw mosaic, DN), ``exposure_time`` (s) and
optionally ``path`` and ``white_level`` (e.g. :class:`hdrcap.pipeline.io.raw.RawFrame`), or a
bare array (exposure time 0 s).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.times import same_exposure

__all__ = ["frame_name", "frame_data", "frame_time", "check_shape", "group_by_exposure"]


def frame_name(frame: Any, kind: str, index: int) -> str:
    """The name of a frame in messages: its path, else ``"<kind> frame #<index + 1>"``.

    Parameters
    ----------
    frame : frame or array
        The frame.
    kind : str
        ``"bias"``, ``"flat"``, ... for frames without a path.
    index : int
        Position of the frame in its series, 0-based.

    Returns
    -------
    str
    """
    path = getattr(frame, "path", None)
    return str(path) if path else f"{kind} frame #{index + 1}"


def frame_data(frame: Any) -> np.ndarray:
    """The frame's raw values, DN (its ``data``, or the frame itself when it is an array).

    Parameters
    ----------
    frame : frame or array
        The frame.

    Returns
    -------
    numpy.ndarray
    """
    data = getattr(frame, "data", frame)
    return np.asarray(data)


def frame_time(frame: Any) -> float:
    """The frame's exposure time, s (0 when it has none).

    Parameters
    ----------
    frame : frame or array
        The frame.

    Returns
    -------
    float
    """
    return float(getattr(frame, "exposure_time", 0.0) or 0.0)


def check_shape(data: np.ndarray, shape: tuple[int, ...] | None, name: str, first_name: str | None) -> None:
    """Refuse a frame that is not a 2-D mosaic or whose size differs from the first frame's.

    Parameters
    ----------
    data : numpy.ndarray
        The frame's values, DN.
    shape : tuple of int or None
        Shape of the first frame (None: this is the first).
    name, first_name : str
        Names of this frame and of the first one, for the message.

    Raises
    ------
    InputError
        Not 2-D, or a size that differs from ``shape``.
    """
    if data.ndim != 2:
        raise InputError(f"{name}: expected a 2-D raw mosaic, got shape {data.shape}")
    if shape is not None and data.shape != shape:
        raise InputError(
            f"{name}: size {data.shape[1]}x{data.shape[0]} differs from {first_name} ({shape[1]}x{shape[0]})"
        )


def group_by_exposure(frames: Iterable) -> Iterator[tuple[float, list]]:
    """Runs of consecutive frames of the same exposure time, one run at a time (streaming).

    Parameters
    ----------
    frames : iterable of frames
        Frames in capture order.

    Returns
    -------
    iterator of (float, list)
        The exposure time of the run, s, and its frames.
    """
    group: list = []
    t0 = 0.0
    for fr in frames:
        t = frame_time(fr)
        if group and not same_exposure(t, t0):
            yield t0, group
            group = []
        if not group:
            t0 = t
        group.append(fr)
    if group:
        yield t0, group
