"""Matching exposure times: one rule, one tolerance, used everywhere.

Two exposure times name the same exposure when they agree within a relative tolerance of
``EXPOSURE_RTOL`` (0.1 %). Real cameras report the time they applied as an EXIF rational
(1/3 s is stored as 1/3, asked for as 0.3333), libgphoto2 rounds a requested time to the
nearest allowed one, and files store times in single precision; all of these differ from the
nominal time by far less than 0.1 %. Adjacent steps of any shutter ladder (1/3 EV: 26 %) differ
by far more, so the rule never joins two distinct exposures.

Every place that asks "is this the same exposure?" (a dark frame for a bright frame, a planned
time for a captured frame, a master dark from the library, a series of calibration frames at
one time) calls :func:`same_exposure`, :func:`find_exposure` or uses :class:`ExposureMap`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, MutableMapping
from typing import Generic, TypeVar

__all__ = [
    "EXPOSURE_RTOL",
    "BULB_ATOL_S",
    "BULB_RTOL",
    "same_exposure",
    "same_bulb_exposure",
    "find_exposure",
    "unique_exposures",
    "ExposureMap",
]

#: Relative tolerance within which two exposure times (seconds) are the same exposure.
EXPOSURE_RTOL: float = 1e-3

#: A bulb exposure is timed by the host (USB latency, tens of ms) and cameras write its EXIF
#: time rounded (often to whole seconds): the file and the measured open time agree within
#: ``max(BULB_ATOL_S, BULB_RTOL * t)``, still far less than a 1/3-EV step above 30 s (26 %).
BULB_ATOL_S: float = 0.5
BULB_RTOL: float = 0.01

V = TypeVar("V")


def same_exposure(a: float, b: float, rtol: float = EXPOSURE_RTOL) -> bool:
    """Whether two exposure times name the same exposure.

    Parameters
    ----------
    a, b : float
        Exposure times, s.
    rtol : float
        Relative tolerance (default :data:`EXPOSURE_RTOL`).

    Returns
    -------
    bool
        ``|a - b| <= rtol * max(|a|, |b|)``.
    """
    return math.isclose(float(a), float(b), rel_tol=rtol, abs_tol=0.0)


def same_bulb_exposure(file_s: float, measured_s: float) -> bool:
    """Whether a bulb frame's file time and the open time the host measured agree.

    Parameters
    ----------
    file_s : float
        Exposure time in the file (EXIF), s.
    measured_s : float
        Time between the shutter's press and release as measured around the release, s.

    Returns
    -------
    bool
        ``|file_s - measured_s| <= max(BULB_ATOL_S, BULB_RTOL * measured_s)``.
    """
    return abs(float(file_s) - float(measured_s)) <= max(BULB_ATOL_S, BULB_RTOL * abs(float(measured_s)))


def find_exposure(t: float, times: Iterable[float], rtol: float = EXPOSURE_RTOL) -> int | None:
    """Index of the time in ``times`` that is the same exposure as ``t`` (the closest one).

    Parameters
    ----------
    t : float
        Exposure time to look up, s.
    times : iterable of float
        Candidate exposure times, s.
    rtol : float
        Relative tolerance (default :data:`EXPOSURE_RTOL`).

    Returns
    -------
    int or None
        Position of the closest candidate within the tolerance, or None when there is none.
    """
    best, best_d = None, math.inf
    for i, c in enumerate(times):
        if same_exposure(t, c, rtol):
            d = abs(float(c) - float(t))
            if d < best_d:
                best, best_d = i, d
    return best


def unique_exposures(times: Iterable[float], rtol: float = EXPOSURE_RTOL) -> list[float]:
    """The distinct exposures among ``times``, in order of first appearance.

    Parameters
    ----------
    times : iterable of float
        Exposure times, s.
    rtol : float
        Relative tolerance (default :data:`EXPOSURE_RTOL`).

    Returns
    -------
    list of float
        The first time seen of each distinct exposure, s.
    """
    out: list[float] = []
    for t in times:
        if find_exposure(t, out, rtol) is None:
            out.append(float(t))
    return out


class ExposureMap(MutableMapping[float, V], Generic[V]):
    """A dict keyed by exposure time, s, whose look-ups follow :func:`same_exposure`.

    Setting a key that is the same exposure as an existing key replaces that entry (the first
    key is kept). Iteration is in insertion order.
    """

    def __init__(self, items: Iterable[tuple[float, V]] = (), rtol: float = EXPOSURE_RTOL) -> None:
        self._keys: list[float] = []
        self._values: list[V] = []
        self.rtol = rtol
        for k, v in items:
            self[k] = v

    def _index(self, t: float) -> int | None:
        return find_exposure(t, self._keys, self.rtol)

    def __getitem__(self, t: float) -> V:
        i = self._index(t)
        if i is None:
            raise KeyError(t)
        return self._values[i]

    def __setitem__(self, t: float, value: V) -> None:
        i = self._index(t)
        if i is None:
            self._keys.append(float(t))
            self._values.append(value)
        else:
            self._values[i] = value

    def __delitem__(self, t: float) -> None:
        i = self._index(t)
        if i is None:
            raise KeyError(t)
        del self._keys[i]
        del self._values[i]

    def __iter__(self) -> Iterator[float]:
        return iter(list(self._keys))

    def __len__(self) -> int:
        return len(self._keys)

    def __repr__(self) -> str:
        return f"ExposureMap({dict(zip(self._keys, self._values))!r})"
