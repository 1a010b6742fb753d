"""Camera shutter-speed ladders (nominal 1/3-EV values as cameras label them)."""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction

import numpy as np

from hdrcap.pipeline.params import THIRD_STOP_TIMES

__all__ = ["THIRD_STOP_LADDER", "shutter_ladder", "parse_time", "parse_times", "parse_dark_library"]

#: The usual 1/3-EV shutter ladder of a camera, 1/8000 s to 30 s, in seconds (55 values).
THIRD_STOP_LADDER: tuple[float, ...] = THIRD_STOP_TIMES


def shutter_ladder(t_min: float = 1 / 8000, t_max: float = 30.0) -> tuple[float, ...]:
    """The nominal 1/3-EV ladder restricted to an interval.

    Parameters
    ----------
    t_min, t_max : float
        Bounds of the interval, s (inclusive).

    Returns
    -------
    tuple of float
        The ladder's times within the bounds, s, ascending.

    Raises
    ------
    ValueError
        No ladder value within the bounds.
    """
    eps = 1e-9
    out = tuple(t for t in THIRD_STOP_LADDER if t_min * (1 - eps) <= t <= t_max * (1 + eps))
    if not out:
        raise ValueError(f"no ladder value within {t_min:g}..{t_max:g} s")
    return out


def parse_time(text: str) -> float:
    """Parse an exposure time: seconds (``0.01``) or a fraction (``1/8000``).

    Parameters
    ----------
    text : str
        The time as written by a user.

    Returns
    -------
    float
        The exposure time, s, > 0.

    Raises
    ------
    ValueError
        Not a number or fraction, or not positive.
    """
    try:
        value = float(Fraction(text.strip())) if "/" in text else float(text)
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"not an exposure time: {text!r} (use seconds or a fraction like 1/250)") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"exposure time must be a positive number of seconds, got {text!r}")
    return value


def parse_times(texts: Sequence[str]) -> list[float] | None:
    """Parse several exposure times (:func:`parse_time`).

    Parameters
    ----------
    texts : sequence of str
        Times in seconds or fractions.

    Returns
    -------
    list of float or None
        The times, s, in the given order; None when ``texts`` is empty.

    Raises
    ------
    ValueError
        A text that is not an exposure time.
    """
    return [parse_time(t) for t in texts] if texts else None


def parse_dark_library(items: Sequence[str]) -> dict[float, int]:
    """Parse the master darks available, ``TIME:N`` each (e.g. ``1/250:16``).

    Parameters
    ----------
    items : sequence of str
        Exposure time (seconds or a fraction) and frame count of each master dark.

    Returns
    -------
    dict
        Exposure time, s -> number of dark frames averaged into the master dark.

    Raises
    ------
    ValueError
        An item that is not ``TIME:N``.
    """
    library = {}
    for item in items:
        try:
            t, n = item.split(":")
            library[parse_time(t)] = int(n)
        except ValueError:
            raise ValueError(f"--dark-library entries look like 1/250:16 (time:frames), got {item!r}") from None
    return library
