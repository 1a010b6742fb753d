"""Metering: estimate a scene's irradiance map from one or two quick frames.

The first frame is taken at the shortest allowed time (it measures everything the camera can
measure at all); when part of the scene is not metered to 1/``meter_snr`` by it, further frames
follow, log-spaced up to ``max_time`` (with two frames: the shortest and ``max_time``). Each
photosite's estimate (Eq. 6) comes from the longest frame in which it is neither saturated nor
undetected, clipped to the bounds the other frames imply. The report says which irradiance ranges could not be
metered: brighter than the shortest exposure allows (lower bound only), below the detection
limit of the longest metering frame (upper bound only), and coarsely metered pixels (relative
error above 1/``meter_snr``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, overload

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.noise import exposure_variance
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.times import unique_exposures
from hdrcap.planner.ladder import THIRD_STOP_LADDER
from hdrcap.planner.predict import K_SIGMA

__all__ = ["MeterReport", "meter", "read_irradiance_map"]


@dataclass(frozen=True)
class MeterReport:
    """What metering measured and what it could not.

    Attributes
    ----------
    times : list of float
        Exposure times of the metering frames, s.
    n_pixels : int
        Photosites in the map.
    n_saturated : int
        Saturated even in the shortest frame: irradiance above ``bright_limit`` (e-/s); the map
        holds the lower bound there.
    bright_limit : float or None
        Brightest irradiance the shortest frame can meter, e-/s.
    n_dark : int
        Below the detection limit (3 sigma of the read noise) of the longest frame; the map
        holds that limit ``dark_limit`` (e-/s) there, an upper bound.
    dark_limit : float or None
        Detection limit of the longest metering frame, e-/s.
    status : numpy.ndarray
        Per photosite: 0 well metered, 1 coarse, 2 only bounded (gap), 3 below the detection
        limit, 4 saturated at the shortest time.
    n_gap : int
        Saturated in a longer frame and undetected in a shorter one: only bounded; the map
        spreads them log-uniformly over the bounds (ordered by their noisy estimate).
    n_coarse : int
        Metered with a relative error above 1/meter_snr.
    metered_range : (float, float) or None
        Irradiance range metered to within 1/meter_snr, e-/s.
    message : str
        One line for people.
    """

    times: list[float]
    n_pixels: int
    n_saturated: int
    bright_limit: float | None
    n_dark: int
    dark_limit: float | None
    n_coarse: int
    metered_range: tuple[float, float] | None
    message: str = ""
    n_gap: int = 0
    status: np.ndarray | None = None

    def to_dict(self) -> dict:
        """The report as JSON-ready data.

        Returns
        -------
        dict
            Every field but the per-photosite ``status`` map.
        """
        return {
            "times": self.times,
            "n_pixels": self.n_pixels,
            "n_saturated": self.n_saturated,
            "bright_limit": self.bright_limit,
            "n_dark": self.n_dark,
            "dark_limit": self.dark_limit,
            "n_coarse": self.n_coarse,
            "n_gap": self.n_gap,
            "metered_range": list(self.metered_range) if self.metered_range else None,
            "message": self.message,
        }


def _maps(calibration: Calibration, shape):
    p = calibration.params
    bias = calibration.bias_map if calibration.bias_map is not None else p.mu_R
    D = calibration.dark_current_map if calibration.dark_current_map is not None else p.dark_current
    a = calibration.prnu if calibration.prnu is not None else 1.0
    for name, m in (("bias_map", bias), ("dark_current_map", D), ("prnu", a)):
        if np.ndim(m) and np.shape(m) != tuple(shape):
            raise InputError(f"calibration {name} has shape {np.shape(m)}, the metering frame {tuple(shape)}")
    return bias, D, a


def _capture(capture_fn, t):
    v = np.asarray(capture_fn(t))
    if v.ndim != 2 or v.size == 0:
        raise InputError(f"metering frame at {t:g} s is not a 2-D image (shape {v.shape})")
    return v.astype(np.float64)


def _combine(frames, calibration, bias, D, a):
    """Combine metering frames (Eq. 6 per frame).

    Each photosite takes the estimate of the longest frame where it is neither saturated nor
    below that frame's detection limit (3 sigma of the read noise); the estimate is clipped to
    the bounds the other frames imply (saturated at t: X above the saturation irradiance of t;
    undetected at t: X below its detection limit). Photosites detected in no frame get the
    tightest upper bound (the detection limit of the longest unsaturated frame).
    Returns (X, time used, undetected mask, detection limit of the longest frame).
    """
    p = calibration.params
    shape = next(iter(frames.values())).shape
    X = np.full(shape, np.nan)
    t_used = np.full(shape, min(frames))
    lo = np.zeros(shape)
    hi = np.full(shape, np.inf)
    for t in sorted(frames):
        v = frames[t].astype(np.float64)
        x = (v - bias - t * p.g * D) / (t * p.g * a)
        sat = v >= p.v_sat
        detect = 3.0 * np.sqrt(p.sigma2_R) / (t * p.g * a)
        x_sat = (p.v_sat - bias - t * p.g * D) / (t * p.g * a)
        lo = np.where(sat, np.maximum(lo, x_sat), lo)
        undetected = ~sat & (x < detect)
        hi = np.where(undetected, np.minimum(hi, detect), hi)
        use = ~sat & ~undetected
        if t == min(frames):
            x_first = x
        X = np.where(use, x, X)
        t_used = np.where(use, t, t_used)
    unused = np.isnan(X)
    dark = unused & np.isfinite(hi) & (lo <= 0)
    gap = unused & np.isfinite(hi) & (lo > 0)
    X = np.where(dark, hi, X)
    if gap.any():
        # bounded on both sides only: spread log-uniformly over the bounds, ordered by the
        # (noisy) estimate of the shortest frame, so that a plan covers the whole interval
        order = np.argsort(np.argsort(x_first[gap], kind="stable"), kind="stable")
        f = (order + 0.5) / gap.sum()
        X[gap] = lo[gap] * (hi[gap] / lo[gap]) ** f
    X = np.where(np.isnan(X), lo, X)  # saturated everywhere: the lower bound
    X = np.clip(X, lo, hi)
    t_long = max(frames)
    return X, t_used, dark, gap, float(3.0 * np.sqrt(p.sigma2_R) / (t_long * p.g * np.mean(a)))


@overload
def meter(
    capture_fn: Callable[[float], np.ndarray],
    calibration: Calibration,
    allowed_times: Sequence[float] | None = ...,
    *,
    max_time: float = ...,
    meter_snr: float = ...,
    k_sigma: float = ...,
    max_frames: int = ...,
    return_report: Literal[False] = ...,
) -> np.ndarray: ...


@overload
def meter(
    capture_fn: Callable[[float], np.ndarray],
    calibration: Calibration,
    allowed_times: Sequence[float] | None = ...,
    *,
    max_time: float = ...,
    meter_snr: float = ...,
    k_sigma: float = ...,
    max_frames: int = ...,
    return_report: Literal[True],
) -> tuple[np.ndarray, MeterReport]: ...


def meter(
    capture_fn: Callable[[float], np.ndarray],
    calibration: Calibration,
    allowed_times: Sequence[float] | None = None,
    *,
    max_time: float = 1.0,
    meter_snr: float = 10.0,
    k_sigma: float = K_SIGMA,
    max_frames: int = 2,
    return_report: bool = False,
) -> np.ndarray | tuple[np.ndarray, MeterReport]:
    """Estimate the irradiance map (e-/s per photosite) from one or two quick frames.

    Parameters
    ----------
    capture_fn : callable
        ``capture_fn(t)`` takes a frame of ``t`` seconds and returns the raw mosaic (uint16, DN).
    calibration : Calibration
        Camera model (bias, gain, dark current, v_sat; maps when present).
    allowed_times : sequence of float, optional
        Exposure times the camera offers, s (default: the 1/3-EV ladder).
    max_time : float
        Longest metering exposure, s.
    meter_snr : float
        A pixel is well metered when its estimate's SNR (linear) is at least this.
    k_sigma : float
        Saturation margin used to choose the mid frame.
    max_frames : int
        Number of metering frames at most (the first is the shortest allowed time; each
        further one is the time that meters most of the pixels not yet metered to 1/meter_snr).
    return_report : bool
        Also return a :class:`MeterReport`.

    Returns
    -------
    numpy.ndarray or (numpy.ndarray, MeterReport)
        The irradiance map (float64, e-/s; lower bounds where saturated at the shortest time,
        the detection limit where below it).
    """
    times = sorted(
        unique_exposures(float(t) for t in (allowed_times if allowed_times is not None else THIRD_STOP_LADDER))
    )
    if not times or times[0] <= 0:
        raise InputError("metering needs positive allowed exposure times")
    if int(max_frames) < 1:
        raise InputError(f"metering needs at least one frame, got max_frames={max_frames!r}")
    p = calibration.params
    t1 = times[0]
    v1 = _capture(capture_fn, t1)
    bias, D, a = _maps(calibration, v1.shape)
    frames = {t1: v1}
    sat1 = v1 >= p.v_sat
    if int(max_frames) == 1:
        max_frames = 1
    while True:
        X, t_used, dark, gap, dark_limit = _combine(frames, calibration, bias, D, a)
        var = exposure_variance(X, t_used, p.g, p.sigma2_R, np.mean(D), a, "model")
        well = ~sat1 & ~dark & ~gap & (np.maximum(X, 0) >= meter_snr * np.sqrt(var))
        todo = ~sat1 & ~well
        cands = [t for t in times if t not in frames and t <= max_time * (1 + 1e-9)]
        if len(frames) >= int(max_frames) or not todo.any() or not cands:
            break
        # the frames are log-spaced between the shortest time and max_time
        t_long = max(t for t in times if t <= max_time * (1 + 1e-9)) if times[0] <= max_time else times[0]
        k = len(frames)
        goal = t1 * (t_long / t1) ** (k / (int(max_frames) - 1))
        best_t = min(cands, key=lambda t: (abs(np.log(t / goal)), -t))
        v = _capture(capture_fn, best_t)
        if v.shape != v1.shape:
            raise InputError(f"metering frames differ in size: {v1.shape} and {v.shape}")
        frames[best_t] = v
    var = exposure_variance(X, t_used, p.g, p.sigma2_R, np.mean(D), a, "model")
    snr = np.maximum(X, 0) / np.sqrt(var)
    coarse = ~sat1 & ~dark & ~gap & (snr < meter_snr)
    bright_limit = (p.v_sat - np.mean(bias) - t1 * p.g * np.mean(D)) / (t1 * p.g)
    X = np.where(sat1, np.maximum(X, bright_limit), X)
    good = ~sat1 & ~dark & ~coarse & ~gap
    status = np.select([sat1, dark, gap, coarse], [4, 3, 2, 1], 0).astype(np.int8)
    rng = (float(X[good].min()), float(X[good].max())) if good.any() else None
    n = int(X.size)
    parts = [f"metered with {len(frames)} frame(s) at " + ", ".join(f"{t:.4g} s" for t in frames)]
    if rng:
        parts.append(f"range {rng[0]:.4g}..{rng[1]:.4g} e-/s metered to within {100 / meter_snr:g} %")
    if sat1.any():
        parts.append(
            f"{100 * sat1.mean():.3g} % of pixels brighter than {bright_limit:.4g} e-/s "
            f"(saturated at the shortest time {t1:.4g} s): not meterable, lower bound kept"
        )
    if dark.any():
        parts.append(
            f"{100 * dark.mean():.3g} % of pixels below the detection limit {dark_limit:.4g} e-/s: "
            "not metered, the limit kept"
        )
    if gap.any():
        parts.append(
            f"{100 * gap.mean():.3g} % of pixels only bounded "
            f"({np.min(X[gap]):.4g}..{np.max(X[gap]):.4g} e-/s: "
            "saturated in a longer frame, undetected in a shorter one), spread over the bounds"
        )
    if coarse.any():
        parts.append(f"{100 * coarse.mean():.3g} % of pixels metered coarsely (error > {100 / meter_snr:g} %)")
    report = MeterReport(
        times=list(frames),
        n_pixels=n,
        n_saturated=int(sat1.sum()),
        bright_limit=float(bright_limit),
        n_dark=int(dark.sum()),
        dark_limit=float(dark_limit),
        n_coarse=int(coarse.sum()),
        n_gap=int(gap.sum()),
        status=status,
        metered_range=rng,
        message="; ".join(parts),
    )
    return (X, report) if return_report else X


def read_irradiance_map(path: str | Path) -> np.ndarray:
    """A scene's irradiance map from an EXR instead of metering (e.g. a previous merge or a truth).

    Parameters
    ----------
    path : str or Path
        EXR file with a channel ``irradiance`` (or ``Y``, ``R``, ``G``), e-/s per photosite.

    Returns
    -------
    numpy.ndarray
        The map, float64, e-/s.

    Raises
    ------
    InputError
        No such channel, or NaN or infinite values.
    """
    from hdrcap.pipeline.io.exr import read_exr

    names = ("irradiance", "Y", "R", "G")
    img = read_exr(path, channels=names)  # the others (sigma, nexp, ...) are not converted
    for name in names:
        if name in img.channels:
            data = np.asarray(img.channels[name], dtype=np.float64)
            break
    else:
        raise InputError(f"{path}: no irradiance, Y, R or G channel (has {', '.join(map(repr, img.channels))})")
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: the irradiance map holds NaN or infinite values")
    return data
