"""Readout noise from bias frames (Sec. 6): mu_R, sigma2_R and the per-photosite offset map.

sigma2_R comes from the difference of frame pairs, so that the fixed offset pattern (bias
DSNU) cancels; with a single frame it falls back to the frame's spatial variance. Units: DN,
DN^2, s.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..times import same_exposure
from .frames import check_shape, frame_data, frame_name, frame_time
from .stats import DEFAULT_CLIP, PairStats, PixelStack, pair_statistics, robust_mean_std

__all__ = ["ReadoutEstimate", "estimate_readout"]


@dataclass(frozen=True)
class ReadoutEstimate:
    """Readout noise from bias frames (Sec. 6).

    Attributes
    ----------
    mu_R, mu_R_stderr : float
        Mean bias level and its standard error, DN.
    sigma2_R, sigma2_R_stderr : float
        Readout variance (quantisation included) and its standard error, DN^2.
    bias_map : numpy.ndarray or None
        Per-photosite clipped mean bias, DN (None with a single frame).
    method : str
        ``"pair-difference"`` (fixed pattern cancels) or ``"spatial"`` (one frame only;
        includes DSNU).
    n_frames : int
    exposure_time : float
        Seconds.
    dsnu : float
        Spatial standard deviation of the offset map (bias DSNU), DN, or NaN.
    """

    mu_R: float
    mu_R_stderr: float
    sigma2_R: float
    sigma2_R_stderr: float
    bias_map: np.ndarray | None
    method: str
    n_frames: int
    exposure_time: float
    dsnu: float = float("nan")


@dataclass
class _BiasSeries:
    """One pass over the bias frames: the per-photosite stack, each frame's clipped mean and
    standard deviation (DN) with its name, the consecutive pairs and the exposure time (s)."""

    stack: PixelStack
    means: list[tuple[float, float, str]]
    pairs: list[PairStats]
    exposure_time: float


def _read_bias(frames: Iterable, clip: float | None, white_level: float | None) -> _BiasSeries:
    """Stream the bias frames once; refuse mixed sizes or times and frames with signal."""
    stack = None
    shape = first = None
    t0 = 0.0
    means: list[tuple[float, float, str]] = []
    pairs: list[PairStats] = []
    pending = None
    for i, fr in enumerate(frames):
        data = frame_data(fr)
        name = frame_name(fr, "bias", i)
        check_shape(data, shape, name, first)
        t = frame_time(fr)
        if stack is None:
            shape, first, t0 = data.shape, name, t
            stack = PixelStack(shape)
        elif not same_exposure(t, t0):
            raise InputError(f"{name}: bias exposure time {t:g} s differs from {first} ({t0:g} s)")
        m, s, _ = robust_mean_std(data, clip)
        wl = white_level if white_level is not None else getattr(fr, "white_level", None)
        if wl and m > 0.25 * float(wl):
            raise InputError(f"{name}: not a bias frame, its mean {m:.1f} DN is above a quarter of the white level")
        means.append((m, s, name))
        stack.add(data)
        if pending is None:
            pending = data
        else:
            pairs.append(pair_statistics(pending, data, clip, t))
            pending = None
    if stack is None:
        raise InputError("no bias frames given (need at least one, two for the pair-difference read noise)")
    return _BiasSeries(stack, means, pairs, t0)


def _check_levels(means: list[tuple[float, float, str]]) -> None:
    """Refuse a bias frame whose mean lies clearly above the darkest one (light or a long
    exposure only adds signal; a bias frame's mean moves by ~sigma/sqrt(P) between frames)."""
    levels = np.array([m for m, _, _ in means])
    spread = float(np.median([s for _, s, _ in means]))
    low = float(np.min(levels))
    for m, _s, name in means:
        if m - low > max(2.0, 0.5 * spread):
            raise InputError(
                f"{name}: bias frame with signal? its mean {m:.2f} DN lies above the darkest bias frame ({low:.2f} DN)"
            )


def _from_pairs(mean_map: np.ndarray, pairs: list[PairStats], n: int, clip: float | None):
    """sigma2_R as the pixel-count weighted mean of the pair variances; mu_R, its error and
    the DSNU from the offset map (whose spatial variance is DSNU^2 + sigma2_R / n)."""
    P = mean_map.size
    w = np.array([p.n_used for p in pairs], float)
    sigma2 = float(np.sum(w * [p.variance for p in pairs]) / w.sum())
    sigma2_se = float(np.sqrt(np.sum((w * [p.variance_stderr for p in pairs]) ** 2)) / w.sum())
    mu, dsnu_total, _ = robust_mean_std(mean_map, clip)
    dsnu2 = max(dsnu_total**2 - sigma2 / n, 0.0)
    mu_se = float(np.sqrt(sigma2 / (n * P) + dsnu2 / P))
    return mu, mu_se, sigma2, sigma2_se, "pair-difference", float(np.sqrt(dsnu2)), mean_map.astype(np.float32)


def _from_one_frame(frame: np.ndarray, clip: float | None):
    """sigma2_R as the spatial variance of a single frame (DSNU included); no offset map."""
    P = frame.size
    mu, sd, keep = robust_mean_std(frame, clip)
    vals = frame[keep] - mu
    sigma2 = sd * sd
    m4 = float(np.mean(vals**4))
    sigma2_se = float(np.sqrt(max(m4 - sigma2**2, 0.0) / vals.size))
    return mu, float(np.sqrt(sigma2 / P)), sigma2, sigma2_se, "spatial", float("nan"), None


def estimate_readout(
    frames: Iterable, clip: float | None = DEFAULT_CLIP, white_level: float | None = None
) -> ReadoutEstimate:
    """mu_R, sigma2_R and the offset map from bias frames (zero or shortest exposure).

    sigma2_R is half the clipped variance of the difference of consecutive pairs (frames 1-2,
    3-4, ...), averaged over pairs, so that the fixed offset pattern cancels; with a single
    frame it falls back to the frame's spatial variance (which includes DSNU). mu_R is the
    clipped spatial mean over all frames.

    Parameters
    ----------
    frames : iterable of frames
        Bias frames (objects with ``data`` in DN, ``exposure_time`` in s, optional ``path``
        and ``white_level``), consumed once.
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables outlier rejection.
    white_level : float, optional
        ADC white level, DN (default: each frame's own); a frame above a quarter of it is
        refused.

    Returns
    -------
    ReadoutEstimate
        mu_R (DN), sigma2_R (DN^2), their standard errors, the offset map and the DSNU (DN).

    Raises
    ------
    InputError
        No frames, frames of mixed size or exposure time, or a frame with signal (its level
        differs from the other bias frames or it lies above a quarter of ``white_level``).
    """
    series = _read_bias(frames, clip, white_level)
    n = series.stack.n
    if n >= 2:
        _check_levels(series.means)
    mean_map, _, _ = series.stack.result(clip)
    if series.pairs:
        est = _from_pairs(mean_map, series.pairs, n, clip)
    else:
        est = _from_one_frame(mean_map, clip)
    mu, mu_se, sigma2, sigma2_se, method, dsnu, bias_map = est
    return ReadoutEstimate(float(mu), mu_se, sigma2, sigma2_se, bias_map, method, n, float(series.exposure_time), dsnu)
