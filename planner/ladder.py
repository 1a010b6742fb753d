"""Camera shutter-speed ladders (nominal 1/3-EV values as cameras label them)."""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from hdrcap.pipeline.params import THIRD_STOP_TIMES

__all__ = ["THIRD_STOP_LADDER", "shutter_ladder", "parse_time"]

#: The usual 1/3-EV shutter ladder of a camera, 1/8000 s to 30 s, in seconds (55 values).
THIRD_STOP_LADDER: tuple[float, ...] = THIRD_STOP_TIMES


def shutter_ladder(t_min: float = 1 / 8000, t_max: float = 30.0) -> tuple[float, ...]:
    """The nominal 1/3-EV ladder restricted to [t_min, t_max] seconds (ascending)."""
    eps = 1e-9
    out = tuple(t for t in THIRD_STOP_LADDER if t_min * (1 - eps) <= t <= t_max * (1 + eps))
    if not out:
        raise ValueError(f"no ladder value within {t_min:g}..{t_max:g} s")
    return out


def parse_time(text: str) -> float:
    """Parse an exposure time: seconds (``0.01``) or a fraction (``1/8000``)."""
    try:
        value = float(Fraction(text.strip())) if "/" in text else float(text)
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"not an exposure time: {text!r} (use seconds or a fraction like 1/250)") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"exposure time must be a positive number of seconds, got {text!r}")
    return value
