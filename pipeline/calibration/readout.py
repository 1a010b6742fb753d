"""Readout noise from bias frames (Sec. 6): mu_R, sigma2_R and the per-photosite offset map.

sigma2_R comes from the difference of frame pairs, so that the fixed offset pattern (bias
DSNU) cancels; with a single frame it falls back to the frame's spatial variance. Units: DN,
DN^2, s.

Quantisation-limited bias frames (EMVA 1288): below 0.24 DN^2 the measured dark variance is
dominated by the rounding of the ADC, whose noise is not the 1/12 DN^2 of a dithered quantiser
(an undithered one gives anything from 0 to 1/4 DN^2, depending on where the bias level falls
between two codes). The standard then reports the dark noise as 0.49 DN (0.24 DN^2), an upper
limit: sigma2_R is set to 0.24 DN^2, flagged ``quantisation_limited``, with the standard error
of that upper limit when the true readout variance (quantisation included) lies anywhere in
[1/12, 0.24] DN^2 (the model's floor: the rounding of a signal dithered by its own shot noise
adds 1/12 DN^2). The mean of an undithered quantiser is not linear either: the bias level's
standard error includes the quantiser's bias of the mean (rectangular within half a code when
nothing dithers it; smaller with read noise or offset non-uniformity, :func:`quantiser_errors`)
and the frame-to-frame scatter of the frame means (bias drift) beyond the read noise. Above the
limit the variance's standard error includes the spread of readout variances that rounding can
turn into the measured one (:func:`quantiser_errors`; negligible from about 0.5 DN^2). Frames
constant at 0 DN are refused: the camera clips its black level, and the read noise is not in
the data.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from hdrcap.pipeline.calibration.frames import check_shape, frame_data, frame_name, frame_time
from hdrcap.pipeline.calibration.stats import DEFAULT_CLIP, PairStats, PixelStack, pair_statistics, robust_mean_std
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.times import same_exposure

__all__ = [
    "ReadoutEstimate",
    "estimate_readout",
    "quantiser_errors",
    "QUANTISATION_VARIANCE",
    "QUANTISATION_LIMIT",
    "QUANTISATION_LIMIT_STDERR",
]

#: Variance of a uniform quantiser with a 1 DN step (a dithered signal's rounding noise), DN^2.
QUANTISATION_VARIANCE = 1.0 / 12.0

#: EMVA 1288: a dark variance below this is dominated by the quantisation noise, DN^2; the
#: dark noise is then reported as sigma_y.dark = sqrt(0.24) = 0.49 DN, an upper limit.
QUANTISATION_LIMIT = 0.24

#: Standard error of the upper limit ``QUANTISATION_LIMIT`` as a value of sigma2_R, DN^2: the root
#: mean square distance to a true readout variance uniform in [1/12, 0.24] DN^2, (0.24 - 1/12)/sqrt(3).
QUANTISATION_LIMIT_STDERR = (QUANTISATION_LIMIT - QUANTISATION_VARIANCE) / np.sqrt(3.0)


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
    quantisation_limited : bool
        The measured variance lay below :data:`QUANTISATION_LIMIT` (EMVA 1288's rule applied:
        ``sigma2_R`` is that upper limit).
    measured_sigma2 : float
        The variance the frames gave before the rule, DN^2 (= ``sigma2_R`` when not limited).
    drift : float
        Standard deviation of the frame-to-frame bias level beyond the read noise, DN (0 when
        not resolved, NaN with one frame).
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
    quantisation_limited: bool = False
    measured_sigma2: float = float("nan")
    drift: float = float("nan")


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


def _rounded_moments(read_variance: float, spatial_variance: float, n_phase: int = 64):
    """Bias of the mean and of the variance of round(mu + n), n ~ N(0, ``read_variance``), as
    periodic functions of the level's phase mu in [0, 1), averaged over photosites whose levels
    spread by ``spatial_variance`` (DN^2; each Fourier component k damped by
    exp(-2 pi^2 k^2 spatial_variance)): (mean bias, variance bias), DN and DN^2, on ``n_phase``
    phases. The variance bias is relative to the dithered model read_variance + 1/12."""
    from scipy.special import ndtr

    mu = np.arange(n_phase) / n_phase
    codes = np.arange(-20, 21, dtype=np.float64)[:, None]
    s = max(float(np.sqrt(read_variance)), 1e-9)
    prob = ndtr((codes + 0.5 - mu) / s) - ndtr((codes - 0.5 - mu) / s)
    mean = (codes * prob).sum(axis=0)
    var = (codes * codes * prob).sum(axis=0) - mean * mean
    k = np.fft.fftfreq(n_phase, 1.0 / n_phase)
    damp = np.exp(-2.0 * np.pi**2 * k * k * max(spatial_variance, 0.0))
    dm = np.fft.ifft(np.fft.fft(mean - mu) * damp).real
    dv = np.fft.ifft(np.fft.fft(var - read_variance - QUANTISATION_VARIANCE) * damp).real
    return dm, dv


def quantiser_errors(measured: float, spatial_variance: float = 0.0) -> tuple[float, float, float]:
    """What the rounding of the ADC leaves unknown in a bias level and a readout variance.

    The variance of rounded values is not the dithered model sigma_e^2 + 1/12: it depends on
    where the level lies between two codes (from 0 to 1/4 DN^2 without dither). From the
    variance ``measured`` alone, the electronic read variance sigma_e^2 lies in the interval of
    values whose rounded variance can reach it at some phase (:func:`_rounded_moments`, the
    photosites' offset spread ``spatial_variance`` averaging the phases).

    Parameters
    ----------
    measured : float
        Temporal variance of the rounded bias values (pair difference), DN^2.
    spatial_variance : float
        Spread of the photosites' bias levels (DSNU^2), DN^2.

    Returns
    -------
    lo, hi : float
        The readout variance sigma_e^2 + 1/12 compatible with ``measured``, DN^2.
    mean_u2 : float
        Mean square bias of the bias level's mean over an unknown phase at the least dither
        compatible (``lo``), DN^2: 1/12 (a rectangular half code) without dither, negligible
        from a read noise of 0.6 DN.
    """
    grid = np.linspace(0.0, max(1.5 * measured, 1.0), 301)
    inside = []
    for s2 in grid:
        _dm, dv = _rounded_moments(s2, spatial_variance)
        base = s2 + QUANTISATION_VARIANCE
        inside.append(base + dv.min() <= measured <= base + dv.max())
    ok = np.asarray(inside)
    if not ok.any():  # measured between two grid points' ranges: the nearest dithered value
        ok = np.abs(grid + QUANTISATION_VARIANCE - measured) == np.min(np.abs(grid + QUANTISATION_VARIANCE - measured))
    lo, hi = float(grid[ok].min()), float(grid[ok].max())
    dm, _dv = _rounded_moments(lo, spatial_variance)
    return lo + QUANTISATION_VARIANCE, hi + QUANTISATION_VARIANCE, float(np.mean(dm * dm))


def _interval_u2(value: float, lo: float, hi: float) -> float:
    """Mean square distance from ``value`` to a truth uniform in [lo, hi] (0 when lo == hi)."""
    if hi <= lo:
        return (value - lo) ** 2
    return ((value - lo) ** 3 + (hi - value) ** 3) / (3.0 * (hi - lo))


def _frame_drift(means: list[tuple[float, float, str]], sigma2: float, P: int) -> float:
    """Standard deviation of the frames' bias level beyond the read noise's share, DN (method of
    moments on the clipped frame means, floored at 0; NaN with one frame)."""
    if len(means) < 2:
        return float("nan")
    levels = np.array([m for m, _, _ in means])
    return float(np.sqrt(max(float(np.var(levels, ddof=1)) - sigma2 / P, 0.0)))


def _check_not_clipped(means: list[tuple[float, float, str]]) -> None:
    """Refuse bias frames constant at 0 DN: a clipped black level hides the read noise."""
    if all(m == 0 and sd == 0 for m, sd, _ in means):
        raise InputError(
            f"{means[0][2]}: bias frames are 0 DN everywhere: the camera clips its black level, so the read "
            "noise is not in the data; use raw frames with the black level kept"
        )


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
        mu_R (DN), sigma2_R (DN^2), their standard errors, the offset map and the DSNU (DN);
        quantisation-limited frames (variance < 0.24 DN^2) give sigma2_R = 0.24 DN^2, an upper
        limit (module docstring).

    Raises
    ------
    InputError
        No frames, frames of mixed size or exposure time, a frame with signal (its level
        differs from the other bias frames or it lies above a quarter of ``white_level``), or
        frames constant at 0 DN (a clipped black level).
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
    measured = sigma2
    P = int(mean_map.size)
    drift = _frame_drift(series.means, sigma2, P)
    dsnu2 = 0.0 if not np.isfinite(dsnu) else dsnu * dsnu
    lo, hi, mean_u2 = quantiser_errors(measured, dsnu2)
    mu_se = float(np.sqrt(mu_se**2 + (0.0 if not np.isfinite(drift) else drift * drift / n) + mean_u2))
    limited = sigma2 < QUANTISATION_LIMIT
    if limited:
        _check_not_clipped(series.means)
        sigma2, sigma2_se = QUANTISATION_LIMIT, float(QUANTISATION_LIMIT_STDERR)
        method = f"{method}, quantisation-limited: {measured:.3g} DN^2 < 0.24 DN^2, set to 0.24 DN^2 (EMVA 1288)"
    else:
        sigma2_se = float(np.sqrt(sigma2_se**2 + _interval_u2(measured, lo, max(hi, lo))))
    return ReadoutEstimate(
        float(mu),
        mu_se,
        float(sigma2),
        float(sigma2_se),
        bias_map,
        method,
        n,
        float(series.exposure_time),
        dsnu,
        quantisation_limited=limited,
        measured_sigma2=float(measured),
        drift=drift,
    )
