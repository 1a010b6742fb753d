"""Dark frames: master darks per exposure time and the dark current (Eq. 7 averaged).

Master darks are the clipped per-photosite means of N dark frames at one exposure time
(streamed one time after the other); the dark current D comes from a straight-line fit of
their levels against the exposure time (>= 6 times), the per-photosite dark-current map from
the same fit at every photosite. Units: DN, DN/s, s.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..times import find_exposure, unique_exposures
from .frames import check_shape, frame_data, frame_name, group_by_exposure
from .stats import PixelStack, robust_mean_std

__all__ = ["MasterDark", "DarkFit", "fit_dark_current", "stream_master_darks", "DarkSeries"]


@dataclass(frozen=True)
class MasterDark:
    """A master dark: the clipped per-photosite mean of N dark frames at one exposure time.

    Attributes
    ----------
    data : numpy.ndarray (float32)
        Mean dark frame, DN (bias included).
    n_frames : int
        N, the number of frames averaged (the merge's dark variance is divided by it).
    exposure_time : float
        Seconds.
    level, level_stderr : float
        Clipped spatial mean and its temporal standard error, DN.
    """

    data: np.ndarray
    n_frames: int
    exposure_time: float
    level: float
    level_stderr: float


@dataclass(frozen=True)
class DarkFit:
    """Dark current from a dark series (Eq. 7 averaged): level(t) = b0 + g D t.

    Attributes
    ----------
    slope, slope_stderr : float
        DN per second.
    intercept : float
        DN.
    times, levels : numpy.ndarray
        The series, s and DN.
    """

    slope: float
    slope_stderr: float
    intercept: float
    times: np.ndarray
    levels: np.ndarray


def fit_dark_current(times: Sequence[float] | np.ndarray, levels: Sequence[float] | np.ndarray,
                     level_stderr: Sequence[float] | np.ndarray | None = None) -> DarkFit:
    """Straight-line fit of master-dark levels against exposure time (>= 6 times).

    Weighted least squares when ``level_stderr`` is given; the slope's standard error is the
    larger of the propagated one and the one from the residuals.

    Parameters
    ----------
    times : array_like
        Exposure times, s.
    levels : array_like
        Master-dark levels, DN.
    level_stderr : array_like, optional
        Standard error of each level, DN.

    Returns
    -------
    DarkFit
        Slope g D (DN/s), its standard error and the intercept (DN).

    Raises
    ------
    ValueError
        Fewer than six distinct exposure times.
    """
    t = np.asarray(times, float)
    y = np.asarray(levels, float)
    n_times = len(unique_exposures(t))
    if n_times < 6:
        raise ValueError(f"dark current needs dark frames at >= 6 exposure times, got {n_times}")
    w = np.ones_like(t) if level_stderr is None else 1.0 / np.maximum(np.asarray(level_stderr, float), 1e-12) ** 2
    A = np.stack([np.ones_like(t), t], axis=1)
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    b0, slope = cov @ (A.T @ (w * y))
    resid = y - (b0 + slope * t)
    chi2 = float(np.sum(w * resid**2)) / max(t.size - 2, 1)
    se = float(np.sqrt(cov[1, 1] * max(chi2, 1.0 if level_stderr is not None else chi2)))
    return DarkFit(float(slope), se, float(b0), t, y)


def _master(stack: PixelStack, t: float, clip: float | None) -> MasterDark:
    """The master dark of a stack of dark frames at ``t`` seconds."""
    mean_map, err_map, _ = stack.result(clip)
    level, _sd, keep = robust_mean_std(mean_map, clip)
    if err_map is not None:
        level_se = float(np.sqrt(np.mean(err_map[keep] ** 2) / keep.sum()))
    else:
        level_se = float("nan")
    return MasterDark(mean_map.astype(np.float32), stack.n, float(t), float(level), level_se)


def stream_master_darks(darks: Iterable, clip: float | None,
                        shape: tuple[int, ...] | None) -> Iterator[MasterDark]:
    """Master darks per exposure time, streamed one run of frames after the other.

    Parameters
    ----------
    darks : iterable of frames
        Dark frames ordered by exposure time (``data`` in DN, ``exposure_time`` in s).
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables outlier rejection.
    shape : tuple of int or None
        Size of the bias frames, which every dark must have (None: not checked).

    Returns
    -------
    iterator of MasterDark
        One per exposure time, in the order of the frames.

    Raises
    ------
    InputError
        Frames of another size, or frames of one exposure time that are not consecutive.
    """
    seen: list[float] = []
    idx = 0
    for t, group in group_by_exposure(darks):
        if find_exposure(t, seen) is not None:
            name = frame_name(group[0], "dark", idx)
            raise InputError(f"{name}: dark frames at {t:g} s are not consecutive; order them by exposure time")
        seen.append(t)
        stack = None
        for fr in group:
            data = frame_data(fr)
            check_shape(data, shape, frame_name(fr, "dark", idx), "the bias frames")
            if stack is None:
                stack = PixelStack(data.shape)
            stack.add(data)
            idx += 1
        yield _master(stack, t, clip)


@dataclass
class DarkSeries:
    """The master darks of a dark series, reduced as they arrive.

    Keeps each master's time (s), level and its error (DN) and frame count, and the
    frame-count weighted sums of the per-photosite straight-line fit (float64 maps), not the
    masters themselves.
    """

    times: list[float] = field(default_factory=list)
    levels: list[float] = field(default_factory=list)
    level_stderr: list[float] = field(default_factory=list)
    n_frames: list[int] = field(default_factory=list)
    _sy: np.ndarray | None = None
    _sty: np.ndarray | None = None
    _sn: float = 0.0
    _st: float = 0.0
    _stt: float = 0.0

    def add(self, master: MasterDark) -> None:
        """Add one master dark.

        Parameters
        ----------
        master : MasterDark
            The master dark (DN) at its exposure time (s).
        """
        self.times.append(master.exposure_time)
        self.levels.append(master.level)
        self.level_stderr.append(master.level_stderr)
        self.n_frames.append(master.n_frames)
        if self._sy is None:
            self._sy = np.zeros(master.data.shape, np.float64)
            self._sty = np.zeros(master.data.shape, np.float64)
        w = float(master.n_frames)
        self._sy += w * master.data
        self._sty += (w * master.exposure_time) * master.data
        self._sn += w
        self._st += w * master.exposure_time
        self._stt += w * master.exposure_time**2

    def n_times(self) -> int:
        """Distinct exposure times in the series.

        Returns
        -------
        int
        """
        return len(unique_exposures(self.times))

    def fit(self) -> DarkFit:
        """Dark current of the mean levels (:func:`fit_dark_current`, weighted by the levels'
        errors when every one is finite).

        Returns
        -------
        DarkFit
            Slope in DN/s.
        """
        se = None if any(not np.isfinite(x) for x in self.level_stderr) else self.level_stderr
        return fit_dark_current(self.times, self.levels, se)

    def slope_map(self) -> np.ndarray:
        """Per-photosite slope of the straight-line fit, DN/s (float32).

        Returns
        -------
        numpy.ndarray
        """
        den = self._sn * self._stt - self._st * self._st
        return ((self._sn * self._sty - self._st * self._sy) / den).astype(np.float32)

    def to_dict(self) -> dict[str, list]:
        """The series for the provenance and the report plots (times s, levels DN).

        Returns
        -------
        dict
        """
        return {"times": self.times, "levels": self.levels, "level_stderr": self.level_stderr,
                "n_frames": self.n_frames}
