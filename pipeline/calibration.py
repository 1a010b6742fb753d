"""Camera calibration (Sec. 6 of the paper, with the EMVA 1288 photon-transfer method).

Estimators for the noise model of :mod:`pipeline.params` from bias, saturation, flat-field
and dark frames, each with its standard error, plus the calibration file I/O.

* readout noise mu_R, sigma2_R from bias frames; sigma2_R from the difference of two frames so
  that the fixed pattern (DSNU) cancels; a per-photosite offset map from several frames;
* saturation limit v_sat = mean - 3 std of a saturation frame (Sec. 6);
* per-photosite gain a_j from dark-corrected flat fields averaged over many frames (Eq. 14);
* camera gain g from flat pairs (Eq. 16, 17) and from the EMVA 1288 photon-transfer
  regression of the pair variance on the mean over 0-70 % of saturation;
* dark current D (mean and per photosite) from dark frames at >= 6 exposure times, and
  master darks averaged over N frames.

Frames are streamed: every estimator takes an iterable and holds at most a few float64 maps
(sums, not frame stacks), so memory does not grow with the number of frames. Outliers
(cosmic rays, hot pixels, dead pixels) are rejected by sigma clipping: spatially (robust
median/MAD clip of each frame and of each pair difference) and temporally (per-photosite
rejection of the extreme sample when it lies more than ``clip`` standard deviations away from
the mean of the others).

Units follow DESIGN.md: DN for raw values, DN^2 for variances, DN per electron for g,
electrons per second for D, seconds for t. Pure functions: no files, no clock, except the
clearly separated I/O section at the end (:func:`save_calibration`, :func:`load_calibration`).
"""

from __future__ import annotations

import datetime as _dt
import io as _io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from . import _calib_kernels as _k
from .errors import InputError
from .params import Calibration, SensorParams

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "DEFAULT_CLIP",
    "robust_mean_std",
    "PairStats",
    "pair_statistics",
    "PixelStack",
    "ReadoutEstimate",
    "estimate_readout",
    "estimate_saturation",
    "gain_from_pair",
    "gain_from_pairs",
    "PhotonTransferFit",
    "photon_transfer_gain",
    "prnu_correction_factor",
    "DarkFit",
    "fit_dark_current",
    "MasterDark",
    "FlatResult",
    "estimate_flats",
    "calibrate",
    "save_calibration",
    "load_calibration",
    "calibration_summary",
]

#: Identifier and version of the calibration file format (see docs/calibration.md).
FORMAT = "hdrcap-calibration"
FORMAT_VERSION = 1

#: Default clipping threshold, in standard deviations.
DEFAULT_CLIP = 5.0

_MAD_TO_SIGMA = 1.4826


def _name(frame, kind: str, index: int) -> str:
    path = getattr(frame, "path", None)
    return str(path) if path else f"{kind} frame #{index + 1}"


def _data(frame) -> np.ndarray:
    data = getattr(frame, "data", frame)
    return np.asarray(data)


# --------------------------------------------------------------------------- spatial statistics


def _subsample(x: np.ndarray, n: int = 200_003) -> np.ndarray:
    flat = x.ravel()
    if flat.size <= n:
        return flat
    step = flat.size // n
    return flat[::step]


def robust_mean_std(x: np.ndarray, clip: float | None = DEFAULT_CLIP, mask: np.ndarray | None = None):
    """Sigma-clipped spatial mean and standard deviation of ``x``.

    The clip interval is median +- ``clip`` robust sigmas (1.4826 MAD, taken from a regular
    subsample for speed; the sample standard deviation when the MAD is zero). ``clip=None``
    disables clipping.

    Returns
    -------
    mean, std : float
        Mean and standard deviation (ddof 1) of the kept values, float64 accumulation.
    keep : numpy.ndarray of bool
        The kept photosites.
    """
    x = np.asarray(x)
    if clip is None:
        keep = np.ones(x.shape, dtype=bool) if mask is None else mask.copy()
    else:
        lo, hi = _clip_bounds(_subsample(x if mask is None else x[mask]), clip)
        keep = (x >= lo) & (x <= hi)
        if mask is not None:
            keep &= mask
    shift = float(x.flat[0])
    n, mean, m2 = _k.masked_moments(x, keep, shift)
    if n < 2:
        raise ValueError("fewer than two photosites survive clipping")
    return float(mean), float(np.sqrt(max(m2, 0.0) / (n - 1))), keep


def _clip_bounds(sub: np.ndarray, clip: float) -> tuple[float, float]:
    """median +- clip robust sigmas (1.4826 MAD; the standard deviation when the MAD is 0)."""
    sub = sub.astype(np.float64)
    med = float(np.median(sub))
    scale = _MAD_TO_SIGMA * float(np.median(np.abs(sub - med)))
    if scale == 0.0:
        scale = float(np.std(sub))
    return med - clip * scale, med + clip * scale


@dataclass(frozen=True)
class PairStats:
    """Statistics of two frames taken under identical conditions (EMVA 1288 pair).

    Attributes
    ----------
    mean_a, mean_b : float
        Spatial means of the two frames over the kept photosites, DN.
    variance : float
        Temporal variance per frame, DN^2:
        (1/2NM) sum (y_A - y_B)^2 - 1/2 (mu_A - mu_B)^2 over the kept photosites.
    variance_stderr : float
        Standard error of ``variance`` from the fourth moment of the difference, DN^2.
    n_used, n_rejected : int
        Photosites kept and rejected by the clip.
    exposure_time : float
        Seconds.
    """

    mean_a: float
    mean_b: float
    variance: float
    variance_stderr: float
    n_used: int
    n_rejected: int
    exposure_time: float = 0.0

    @property
    def mean(self) -> float:
        return 0.5 * (self.mean_a + self.mean_b)


def pair_statistics(a: np.ndarray, b: np.ndarray, clip: float | None = DEFAULT_CLIP,
                    exposure_time: float = 0.0) -> PairStats:
    """EMVA 1288 temporal variance of a pair of frames, with outliers clipped.

    sigma^2 = (1/2NM) sum_j (y_A,j - y_B,j)^2 - 1/2 (mu_A - mu_B)^2, where the sum runs over
    the photosites kept by a robust ``clip``-sigma clip of the difference y_A - y_B (a cosmic
    ray or a hot pixel hit in one frame) and of each frame (hot or dead photosites). The fixed
    pattern (DSNU, PRNU) cancels in the difference.
    """
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"pair of frames with different shapes {a.shape} and {b.shape}")
    if clip is None:
        keep = np.ones(a.shape, dtype=bool)
    else:
        sa, sb = _subsample(a).astype(np.float64), _subsample(b).astype(np.float64)
        keep = _k.pair_keep(a, b, *_clip_bounds(sa, clip), *_clip_bounds(sb, clip), *_clip_bounds(sa - sb, clip))
    # (1/2n) sum d^2 - 1/2 (mu_A - mu_B)^2 == 1/2 mean of (d - (mu_A - mu_B))^2 over the kept photosites
    n, mu_a, mu_b, s2, m4 = _k.pair_moments(a, b, keep)
    if n < 16:
        raise ValueError("fewer than 16 photosites survive clipping")
    var = 0.5 * s2
    var_stderr = 0.5 * np.sqrt(max(m4 - s2 * s2, 0.0) / n)
    d = a.size
    return PairStats(float(mu_a), float(mu_b), var, float(var_stderr), int(n), int(d - n), float(exposure_time))


# --------------------------------------------------------------------------- per-photosite stacks


class PixelStack:
    """Streaming, sigma-clipped per-photosite weighted mean of many frames.

    Holds float64 sums (weighted sum and sum of squares, relative to the first frame) and the
    extreme sample of every photosite with its weight: memory does not grow with the number of
    frames. At the end, the largest and the smallest sample of a photosite are rejected when
    they lie more than ``clip`` standard deviations from the weighted mean of the other
    samples (the standard deviation is the photosite's own, floored by the median over the
    frame, so that two or three frames are enough). A single cosmic-ray hit per photosite and
    stack is removed; a stable hot pixel is kept (it is real signal).

    Parameters
    ----------
    shape : tuple of int
        Frame shape.
    """

    def __init__(self, shape):
        self.shape = tuple(shape)
        self.n = 0
        self.sw = 0.0
        self._ref: np.ndarray | None = None
        self._s = np.zeros(self.shape, np.float64)
        self._q = np.zeros(self.shape, np.float64)
        self._max = np.full(self.shape, -np.inf, np.float32)
        self._min = np.full(self.shape, np.inf, np.float32)
        # weights of the extreme samples: allocated only once the weights differ
        self._w0: float | None = None
        self._wmax: np.ndarray | None = None
        self._wmin: np.ndarray | None = None

    def add(self, values: np.ndarray, weight: float = 1.0) -> None:
        """Add one frame (any real dtype) with a scalar weight (inverse relative variance)."""
        values = np.asarray(values)
        if values.shape != self.shape:
            raise ValueError(f"frame shape {values.shape} differs from the stack's {self.shape}")
        if self._ref is None:
            self._ref = np.array(values, dtype=np.float32, copy=True)
            self._w0 = float(weight)
        w = float(weight)
        values = np.ascontiguousarray(values)
        if self._wmax is None and w != self._w0:
            self._wmax = np.full(self.shape, self._w0, np.float32)
            self._wmin = np.full(self.shape, self._w0, np.float32)
        if self._wmax is None:
            _k.stack_add_equal(values, self._ref, w, self._s, self._q, self._max, self._min)
        else:
            _k.stack_add(values, self._ref, w, self._s, self._q, self._max, self._min, self._wmax, self._wmin)
        self.n += 1
        self.sw += w

    def result(self, clip: float | None = DEFAULT_CLIP, block_rows: int = 256):
        """Clipped weighted mean map and its standard error map.

        Computed in blocks of ``block_rows`` rows so that the memory stays a few maps.

        Returns
        -------
        mean : numpy.ndarray (float32)
        stderr : numpy.ndarray (float32) or None
            Standard error of ``mean`` from the photosite's scatter (floored by the median
            scatter over the frame); None with a single frame.
        n_rejected : int
            Samples rejected over the whole stack.
        """
        if self.n == 0:
            raise ValueError("empty stack")
        if self.n == 1:
            return self._ref.copy(), None, 0
        do_max = clip is not None and self.n >= 3
        do_min = clip is not None and self.n >= 4
        # the floors (median scatter) come from a regular subsample of photosites
        idx = np.arange(0, self._s.size, max(1, self._s.size // 200_003))
        sub = self._block(idx, None, clip, do_max, do_min, None)
        floors = sub[3]
        mean = np.empty(self.shape, np.float32)
        err = np.empty(self.shape, np.float32)
        rejected = 0
        for r0 in range(0, self.shape[0], block_rows):
            rows = slice(r0, min(r0 + block_rows, self.shape[0]))
            m, e, nrej, _ = self._block(None, rows, clip, do_max, do_min, floors)
            mean[rows] = m
            err[rows] = e
            rejected += nrej
        return mean, err, rejected

    def _block(self, idx, rows, clip, do_max, do_min, floors):
        """Statistics of a subsample (flat indices ``idx``) or of a block of ``rows``."""

        def get(a):
            if a is None:  # all weights equal
                a = np.broadcast_to(np.float32(self._w0), self.shape)
            return a.ravel()[idx].astype(np.float64) if idx is not None else a[rows].astype(np.float64)

        s, q = get(self._s), get(self._q)
        sw = np.full(s.shape, self.sw)
        cnt = np.full(s.shape, float(self.n))
        new_floors = {}
        nrej = 0
        for key, on, sign, va, wa in (("max", do_max, +1, self._max, self._wmax),
                                       ("min", do_min, -1, self._min, self._wmin)):
            if not on:
                continue
            v, w = get(va), get(wa)
            s_o = s - w * v
            sw_o = sw - w
            mean_o = s_o / sw_o
            var_o = np.maximum(q - w * v * v - sw_o * mean_o**2, 0.0) / np.maximum(cnt - 2, 1)
            floor = float(np.median(var_o)) if floors is None else floors[key]
            new_floors[key] = floor
            dev = sign * (v - mean_o)
            rej = dev * dev * w > clip * clip * np.maximum(var_o, floor) * (1.0 + w / sw_o)
            s[rej] -= (w * v)[rej]
            q[rej] -= (w * v * v)[rej]
            sw[rej] -= w[rej]
            cnt[rej] -= 1
            nrej += int(rej.sum())
        mean_rel = s / sw
        var1 = np.maximum(q - sw * mean_rel**2, 0.0) / np.maximum(cnt - 1, 1)  # per unit weight
        floor = float(np.median(var1)) if floors is None else floors["var"]
        new_floors["var"] = floor
        err = np.sqrt(np.maximum(var1, floor) / sw)
        ref = get(self._ref)
        return mean_rel + ref, err, nrej, new_floors


# --------------------------------------------------------------------------- readout noise


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


def _check_shape(data, shape, name, first_name):
    if data.ndim != 2:
        raise InputError(f"{name}: expected a 2-D raw mosaic, got shape {data.shape}")
    if shape is not None and data.shape != shape:
        raise InputError(
            f"{name}: size {data.shape[1]}x{data.shape[0]} differs from {first_name} ({shape[1]}x{shape[0]})"
        )


def estimate_readout(frames: Iterable, clip: float | None = DEFAULT_CLIP, white_level: float | None = None
                     ) -> ReadoutEstimate:
    """mu_R, sigma2_R and the offset map from bias frames (zero or shortest exposure).

    sigma2_R is half the clipped variance of the difference of consecutive pairs (frames 1-2,
    3-4, ...), averaged over pairs, so that the fixed offset pattern cancels; with a single
    frame it falls back to the frame's spatial variance (which includes DSNU). mu_R is the
    clipped spatial mean over all frames.

    Raises
    ------
    InputError
        No frames, frames of mixed size or exposure time, or a frame with signal (its level
        differs from the other bias frames or it lies above a quarter of ``white_level``).
    """
    stack = None
    shape = first = t0 = None
    means, pairs, pending = [], [], None
    names = []
    for i, fr in enumerate(frames):
        data = _data(fr)
        name = _name(fr, "bias", i)
        _check_shape(data, shape, name, first)
        t = float(getattr(fr, "exposure_time", 0.0) or 0.0)
        if shape is None:
            shape, first, t0 = data.shape, name, t
            stack = PixelStack(shape)
        elif not np.isclose(t, t0, rtol=1e-6, atol=1e-9):
            raise InputError(f"{name}: bias exposure time {t:g} s differs from {first} ({t0:g} s)")
        m, s, _ = robust_mean_std(data, clip)
        wl = white_level if white_level is not None else getattr(fr, "white_level", None)
        if wl and m > 0.25 * float(wl):
            raise InputError(f"{name}: not a bias frame, its mean {m:.1f} DN is above a quarter of the white level")
        means.append((m, s, name))
        names.append(name)
        stack.add(data)
        if pending is None:
            pending = data
        else:
            pairs.append(pair_statistics(pending, data, clip, t))
            pending = None
    if stack is None:
        raise InputError("no bias frames given (need at least one, two for the pair-difference read noise)")
    n = stack.n
    levels = np.array([m for m, _, _ in means])
    spread = float(np.median([s for _, s, _ in means]))
    if n >= 2:
        low = float(np.min(levels))
        for m, s, name in means:
            # light or a long exposure only adds signal: compare with the darkest bias frame;
            # a bias frame's mean moves by ~sigma/sqrt(P) between frames, allow for drift
            if m - low > max(2.0, 0.5 * spread):
                raise InputError(f"{name}: bias frame with signal? its mean {m:.2f} DN lies above the "
                                 f"darkest bias frame ({low:.2f} DN)")
    mean_map, _, _ = stack.result(clip)
    P = mean_map.size
    if pairs:
        w = np.array([p.n_used for p in pairs], float)
        sigma2 = float(np.sum(w * [p.variance for p in pairs]) / w.sum())
        sigma2_se = float(np.sqrt(np.sum((w * [p.variance_stderr for p in pairs]) ** 2)) / w.sum())
        method = "pair-difference"
        mu, dsnu_total, _ = robust_mean_std(mean_map, clip)
        # spatial variance of the mean map = DSNU^2 + sigma2/n
        dsnu2 = max(dsnu_total**2 - sigma2 / n, 0.0)
        mu_se = float(np.sqrt(sigma2 / (n * P) + dsnu2 / P))
        dsnu = float(np.sqrt(dsnu2))
        bias_map = mean_map.astype(np.float32)
    else:
        mu, sd, keep = robust_mean_std(mean_map, clip)
        vals = mean_map[keep] - mu
        sigma2 = sd * sd
        m4 = float(np.mean(vals**4))
        sigma2_se = float(np.sqrt(max(m4 - sigma2**2, 0.0) / vals.size))
        method = "spatial"
        mu_se = float(np.sqrt(sigma2 / P))
        dsnu = float("nan")
        bias_map = None
    return ReadoutEstimate(float(mu), mu_se, sigma2, sigma2_se, bias_map, method, n, float(t0), dsnu)


# --------------------------------------------------------------------------- saturation


def estimate_saturation(frames: Iterable, clip: float | None = DEFAULT_CLIP, n_sigma: float = 3.0):
    """Saturation limit v_sat = mean - 3 std of saturation frames (Sec. 6), DN.

    With several frames the clipped spatial means and variances are pooled. Returns
    ``(v_sat, stderr, mean, std, n_frames, saturation_map)``; the standard error combines the
    errors of the mean (std/sqrt(P)) and of the standard deviation (std/sqrt(2P)). When the
    data allow (>= 3 frames) ``saturation_map`` is the per-photosite limit, the photosite's
    clipped mean minus 3 temporal standard deviations (pooled from the frame-pair differences,
    float32, DN); else None.
    """
    ms, vs, ns = [], [], []
    shape = first = None
    stack = None
    pending, pair_vars = None, []
    for i, fr in enumerate(frames):
        data = _data(fr)
        name = _name(fr, "saturation", i)
        _check_shape(data, shape, name, first)
        if shape is None:
            shape, first = data.shape, name
        m, s, keep = robust_mean_std(data, clip)
        ms.append(m)
        vs.append(s * s)
        ns.append(int(keep.sum()))
        if stack is None:
            stack = PixelStack(shape)
        stack.add(data)
        if pending is None:
            pending = data
        else:
            pair_vars.append(pair_statistics(pending, data, clip).variance)
            pending = None
    if not ms:
        raise InputError("no saturation frame given")
    sat_map = None
    if stack.n >= 3:
        mean_map, _, _ = stack.result(clip)
        sat_map = (mean_map - n_sigma * np.sqrt(max(float(np.mean(pair_vars)), 0.0))).astype(np.float32)
    del stack
    ns_a = np.array(ns, float)
    mean = float(np.sum(ns_a * ms) / ns_a.sum())
    var = float(np.sum(ns_a * (np.array(vs) + (np.array(ms) - mean) ** 2)) / ns_a.sum())
    std = float(np.sqrt(var))
    P = float(ns_a.sum())
    se = std * np.sqrt(1.0 / P + n_sigma**2 / (2.0 * P))
    return mean - n_sigma * std, float(max(se, 1e-12)), mean, std, len(ms), sat_map


# --------------------------------------------------------------------------- gain


def prnu_correction_factor(mu_X: float, sigma2_a: float, mu_D: float = 0.0) -> float:
    """Eq. 17: k = (mu_X (1 + sigma_a^2) + mu_D) / (mu_X + mu_D) (irradiance and dark current
    in the same unit, e.g. electrons per second)."""
    return (mu_X * (1.0 + sigma2_a) + mu_D) / (mu_X + mu_D)


def gain_from_pair(pair: PairStats, mu_R: float, sigma2_R: float, k: float = 1.0):
    """Camera gain from one flat pair, Eq. 16: g = (1/k) (var/2 of the difference - sigma2_R)
    / (mean - mu_R), DN per electron. Returns ``(g, stderr)`` (stderr from the pair variance's
    fourth-moment standard error)."""
    signal = pair.mean - mu_R
    if signal <= 0:
        raise ValueError("flat pair at or below the bias level")
    g = (pair.variance - sigma2_R) / signal / k
    return float(g), float(pair.variance_stderr / signal / k)


def gain_from_pairs(pairs: list[PairStats], mu_R: float, sigma2_R: float, k: float = 1.0,
                    sigma2_R_stderr: float = 0.0):
    """Inverse-variance weighted average of Eq. 16 over several flat pairs (Sec. 6: "several
    gain estimates obtained from distinct flat frame differences should be averaged").

    Returns ``(g, stderr, per_pair_gains)``; the standard error includes the common error of
    sigma2_R.
    """
    if not pairs:
        raise ValueError("no flat pairs")
    est = [gain_from_pair(p, mu_R, sigma2_R, k) for p in pairs]
    g_i = np.array([e[0] for e in est])
    s_i = np.array([e[1] for e in est])
    w = 1.0 / np.maximum(s_i, 1e-300) ** 2
    g = float(np.sum(w * g_i) / w.sum())
    se = 1.0 / np.sqrt(w.sum())
    mean_signal_inv = float(np.sum(w / np.array([p.mean - mu_R for p in pairs])) / w.sum())
    se = float(np.hypot(se, sigma2_R_stderr * mean_signal_inv / k))
    return g, se, g_i.tolist()


@dataclass(frozen=True)
class PhotonTransferFit:
    """EMVA 1288 photon-transfer regression: variance above dark against mean above dark.

    Attributes
    ----------
    g, g_stderr : float
        Slope through the origin (the system gain K), DN per electron, and its standard error
        from the fit residuals.
    means, variances : numpy.ndarray
        mu_y - mu_y.dark (DN) and sigma^2_y - sigma^2_y.dark (DN^2) of every level.
    used : numpy.ndarray of bool
        Levels inside the fit range (0 to ``fit_fraction`` of saturation).
    saturation : float
        Saturation level above dark used for the range, DN.
    """

    g: float
    g_stderr: float
    means: np.ndarray
    variances: np.ndarray
    used: np.ndarray
    saturation: float


def photon_transfer_gain(means, variances, saturation: float, fit_fraction: float = 0.7,
                         variance_stderr=None, common_stderr: float = 0.0) -> PhotonTransferFit:
    """System gain K by the EMVA 1288 photon-transfer method.

    Least-squares slope through the origin of sigma^2_y - sigma^2_y.dark against
    mu_y - mu_y.dark over the levels with mu_y - mu_y.dark <= ``fit_fraction`` * saturation
    (EMVA 1288: 0-70 % of saturation). The pair variance of each level is
    (1/2NM) sum (y_A - y_B)^2 - 1/2 (mu_A - mu_B)^2 (:func:`pair_statistics`).

    The standard error is the larger of the one from the fit residuals and the propagated one:
    sqrt(sum x_k^2 s_k^2) / sum x_k^2 from the per-level ``variance_stderr`` s_k (the variance
    error grows with the level, so residuals alone understate it), plus the error
    ``common_stderr`` of a dark variance subtracted from every level (it shifts all points
    together: sum x_k / sum x_k^2 times it).
    """
    x = np.asarray(means, float)
    y = np.asarray(variances, float)
    used = (x <= fit_fraction * saturation) & (x > 0)
    if used.sum() < 3:
        raise ValueError(f"only {int(used.sum())} levels within {fit_fraction:.0%} of saturation; need >= 3")
    xu, yu = x[used], y[used]
    sxx = float(np.sum(xu * xu))
    g = float(np.sum(xu * yu) / sxx)
    resid = yu - g * xu
    se = float(np.sqrt(np.sum(resid**2) / (xu.size - 1) / sxx))
    if variance_stderr is not None:
        sk = np.asarray(variance_stderr, float)[used]
        model = np.hypot(np.sqrt(np.sum(xu**2 * sk**2)) / sxx, common_stderr * np.sum(xu) / sxx)
        se = max(se, float(model))
    return PhotonTransferFit(g, se, x, y, used, float(saturation))


# --------------------------------------------------------------------------- dark current


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
        The series.
    """

    slope: float
    slope_stderr: float
    intercept: float
    times: np.ndarray
    levels: np.ndarray


def fit_dark_current(times, levels, level_stderr=None) -> DarkFit:
    """Straight-line fit of master-dark levels against exposure time (>= 6 times).

    Weighted least squares when ``level_stderr`` is given; the slope's standard error is the
    larger of the propagated one and the one from the residuals.
    """
    t = np.asarray(times, float)
    y = np.asarray(levels, float)
    if np.unique(t).size < 6:
        raise ValueError(f"dark current needs dark frames at >= 6 exposure times, got {np.unique(t).size}")
    w = np.ones_like(t) if level_stderr is None else 1.0 / np.maximum(np.asarray(level_stderr, float), 1e-12) ** 2
    A = np.stack([np.ones_like(t), t], axis=1)
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    b0, slope = cov @ (A.T @ (w * y))
    resid = y - (b0 + slope * t)
    chi2 = float(np.sum(w * resid**2)) / max(t.size - 2, 1)
    se = float(np.sqrt(cov[1, 1] * max(chi2, 1.0 if level_stderr is not None else chi2)))
    return DarkFit(float(slope), se, float(b0), t, y)


# --------------------------------------------------------------------------- flats


@dataclass
class FlatResult:
    """Everything the flat fields give: PRNU map (Eq. 14), pairs for the gain.

    Attributes
    ----------
    prnu : numpy.ndarray (float32)
        a_j, mean 1.
    prnu_stderr : numpy.ndarray (float32)
        Estimated standard error of each a_j (scatter of the frames, floored by the median).
    prnu_std : float
        Spatial standard deviation of a_j after removing the estimation noise.
    pairs : list of PairStats
        Consecutive frames with the same exposure time.
    levels : list of (time, level above dark in DN, name)
    n_frames, n_prnu_frames, n_rejected : int
    mean_level : float
        Mean level above dark of the frames in the PRNU map, DN.
    """

    prnu: np.ndarray
    prnu_stderr: np.ndarray | None
    prnu_std: float
    pairs: list
    levels: list
    n_frames: int
    n_prnu_frames: int
    n_rejected: int
    mean_level: float = float("nan")


def estimate_flats(frames: Iterable, dark_reference, v_sat: float, sigma2_R: float,
                   clip: float | None = DEFAULT_CLIP, dark_rate_map: np.ndarray | None = None,
                   prnu_max_fraction: float = 0.9, mu_R: float | None = None) -> FlatResult:
    """Stream flat fields: the dark-corrected PRNU map a_j (Eq. 14) and the flat pairs.

    Each flat f_i is dark-corrected with ``dark_reference`` (the bias map, or mu_R, in DN)
    plus ``dark_rate_map`` * t (DN/s) when given, normalised by its clipped spatial mean, and
    accumulated with weight proportional to its level (inverse of its relative shot-noise
    variance); the clipped weighted mean over frames is renormalised to mean 1 (Eq. 14).
    Frames above ``prnu_max_fraction`` of saturation only serve the gain.

    Raises
    ------
    InputError
        Mixed sizes, a flat that is dark (level below 3 sigma_R above the bias) or saturated
        (more than 1 % of photosites at or above v_sat), or no usable flat.
    """
    shape = first = None
    stack = None
    pairs, levels = [], []
    pending = None
    n = 0
    prnu_levels: list[float] = []
    sat_span = v_sat - (mu_R if mu_R is not None else float(np.mean(dark_reference)))
    for i, fr in enumerate(frames):
        data = _data(fr)
        name = _name(fr, "flat", i)
        _check_shape(data, shape, name, first)
        if shape is None:
            shape, first = data.shape, name
            stack = PixelStack(shape)
        t = float(getattr(fr, "exposure_time", 0.0) or 0.0)
        sat_frac = float(np.count_nonzero(data >= v_sat)) / data.size
        if sat_frac > 1e-2:
            raise InputError(f"{name}: flat field is saturated ({100 * sat_frac:.1f} % of photosites at or above "
                             f"v_sat = {v_sat:.1f} DN); lower the exposure")
        corr = data.astype(np.float32)  # an image (float32); the stack accumulates in float64
        corr -= dark_reference
        if dark_rate_map is not None and t > 0:
            corr -= dark_rate_map * t
        level, _, _ = robust_mean_std(corr, clip)
        if level < 3.0 * np.sqrt(sigma2_R):
            raise InputError(f"{name}: flat field is dark (mean {level:.1f} DN above the bias, below "
                             f"3 sigma_R = {3 * np.sqrt(sigma2_R):.1f} DN)")
        levels.append((t, float(level), name))
        if level <= prnu_max_fraction * sat_span:
            prnu_levels.append(level)
            corr /= level
            # weight ~ level (inverse relative shot-noise variance), quantised to 1/16 octave
            # so that flats at one level share one weight (no per-photosite weight maps)
            stack.add(corr, weight=float(2.0 ** (np.round(np.log2(level) * 16) / 16)))
        del corr
        if pending is not None and np.isclose(pending[1], t, rtol=1e-6, atol=1e-9):
            pairs.append(pair_statistics(pending[0], data, clip, t))
            pending = None
        else:
            pending = (data, t)
        n += 1
    if n == 0:
        raise InputError("no flat fields given")
    if stack.n == 0:
        raise InputError(f"every flat field is above {prnu_max_fraction:.0%} of saturation; none can give the PRNU map")
    mean_map, err_map, rejected = stack.result(clip)
    n_prnu = stack.n
    del stack  # free the sums before building the maps
    norm = float(mean_map.mean())
    mean_map /= np.float32(norm)
    prnu = mean_map
    if err_map is not None:
        err_map /= np.float32(norm)
        spatial = float(np.var(prnu, dtype=np.float64))
        noise = float(np.mean(np.square(err_map, dtype=np.float64)))
        prnu_std = float(np.sqrt(max(spatial - noise, 0.0)))
    else:
        prnu_std = float(np.std(prnu, dtype=np.float64))
    return FlatResult(prnu, err_map, prnu_std, pairs, levels, n, n_prnu, rejected, float(np.mean(prnu_levels)))


# --------------------------------------------------------------------------- the whole calibration


def _group_by_time(frames: Iterable, kind: str) -> Iterator[tuple[float, list]]:
    """Yield (time, [frames]) for consecutive frames with the same exposure time (streaming
    one group at a time)."""
    group, t0 = [], None
    for fr in frames:
        t = float(getattr(fr, "exposure_time", 0.0) or 0.0)
        if group and not np.isclose(t, t0, rtol=1e-6, atol=1e-9):
            yield t0, group
            group = []
        if not group:
            t0 = t
        group.append(fr)
    if group:
        yield t0, group


def _stream_darks(darks: Iterable, clip, shape, bias_map, mu_R):
    """Master darks per exposure time, streamed group by group. Yields MasterDark and
    accumulates nothing else."""
    seen = set()
    idx = 0
    for t, group in _group_by_time(darks, "dark"):
        key = round(t, 12)
        if key in seen:
            name = _name(group[0], "dark", idx)
            raise InputError(f"{name}: dark frames at {t:g} s are not consecutive; order them by exposure time")
        seen.add(key)
        stack = None
        for fr in group:
            data = _data(fr)
            name = _name(fr, "dark", idx)
            _check_shape(data, shape, name, "the bias frames")
            if stack is None:
                stack = PixelStack(data.shape)
            stack.add(data)
            idx += 1
        mean_map, err_map, _ = stack.result(clip)
        level, sd, keep = robust_mean_std(mean_map, clip)
        if err_map is not None:
            level_se = float(np.sqrt(np.mean(err_map[keep] ** 2) / keep.sum()))
        else:
            level_se = float("nan")
        yield MasterDark(mean_map.astype(np.float32), stack.n, float(t), float(level), level_se), group


def calibrate(bias: Iterable, saturation: Iterable | None = None, flats: Iterable | None = None,
              darks: Iterable | None = None, *, clip: float | None = DEFAULT_CLIP, gain_method: str = "auto",
              white_level: float | None = None, fit_fraction: float = 0.7, dark_sink=None,
              provenance: dict | None = None) -> Calibration:
    """Full Sec. 6 calibration from streamed frames (any iterables of objects with ``data``,
    ``exposure_time`` and optional ``path``/``white_level``, e.g. :class:`pipeline.io.RawFrame`).

    Order: bias (mu_R, sigma2_R, offset map) -> darks (master darks, dark current) ->
    saturation (v_sat) -> flats (PRNU map Eq. 14, gain from pairs Eq. 16-17 and from the
    photon-transfer regression). Each iterable is consumed once.

    Parameters
    ----------
    gain_method : {"auto", "pairs", "ptc"}
        ``auto``: the photon-transfer regression when the flats cover >= 3 exposure levels
        within ``fit_fraction`` of saturation, else the Eq. 16 pair average.
    dark_sink : callable, optional
        Called as ``dark_sink(master_dark)`` for every master dark (e.g. to store it in a
        dark library) so that the masters need not stay in memory.
    clip : float or None
        Sigma-clipping threshold; None disables all outlier rejection.

    Returns
    -------
    Calibration
        params, maps, ``stderr`` of every scalar and ``provenance`` (methods, frame counts,
        the photon-transfer and dark-series points for plots).
    """
    if gain_method not in ("auto", "pairs", "ptc"):
        raise ValueError(f"gain_method must be auto, pairs or ptc, got {gain_method!r}")
    prov: dict[str, Any] = dict(provenance or {})
    ro = estimate_readout(bias, clip, white_level)
    shape = None if ro.bias_map is None else ro.bias_map.shape
    dark_ref = ro.bias_map if ro.bias_map is not None else ro.mu_R
    counts = {"bias": ro.n_frames, "saturation": 0, "flat": 0, "dark": 0}
    stderr = {"mu_R": ro.mu_R_stderr, "sigma2_R": ro.sigma2_R_stderr}
    info: dict[str, Any] = {"sigma2_R_method": ro.method, "bias_exposure_time": ro.exposure_time,
                            "bias_dsnu_DN": ro.dsnu, "clip_sigma": clip}

    # darks: per-time master darks, per-pixel regression sums, levels for the mean fit
    dark_slope_map = None
    dark_fit = None
    if darks is not None:
        times, lv, lse, nd = [], [], [], []
        sy = sty = None
        sn = st = stt = 0.0
        for master, _group in _stream_darks(darks, clip, shape, ro.bias_map, ro.mu_R):
            times.append(master.exposure_time)
            lv.append(master.level)
            lse.append(master.level_stderr)
            nd.append(master.n_frames)
            counts["dark"] += master.n_frames
            if sy is None:
                sy = np.zeros(master.data.shape, np.float64)
                sty = np.zeros(master.data.shape, np.float64)
            w = float(master.n_frames)
            sy += w * master.data
            sty += (w * master.exposure_time) * master.data
            sn += w
            st += w * master.exposure_time
            stt += w * master.exposure_time**2
            if dark_sink is not None:
                dark_sink(master)
        if times:
            info["dark_series"] = {"times": times, "levels": lv, "level_stderr": lse, "n_frames": nd}
            if len(set(round(t, 12) for t in times)) >= 6:
                se = None if any(not np.isfinite(x) for x in lse) else lse
                dark_fit = fit_dark_current(times, lv, se)
                den = sn * stt - st * st
                dark_slope_map = ((sn * sty - st * sy) / den).astype(np.float32)  # DN/s per photosite
            elif dark_sink is None:
                raise InputError(f"dark current needs dark frames at >= 6 exposure times, got {len(times)} "
                                 "(or give a dark library to store master darks only)")
            del sy, sty

    # saturation
    sat_map = None
    if saturation is not None:
        v_sat, v_sat_se, sat_mean, sat_std, n_sat, sat_map = estimate_saturation(saturation, clip)
        counts["saturation"] = n_sat
        info["saturation_frame"] = {"mean": sat_mean, "std": sat_std}
        stderr["v_sat"] = v_sat_se
        info["v_sat_method"] = "saturation frame: mean - 3 std (Sec. 6)"
    else:
        if white_level is None:
            raise InputError("no saturation frame and no white level: cannot set v_sat")
        v_sat = float(white_level)
        stderr["v_sat"] = 0.0
        info["v_sat_method"] = "white level (no saturation frame given)"
    if v_sat <= ro.mu_R:
        raise InputError(f"saturation limit {v_sat:.1f} DN is not above the bias level {ro.mu_R:.1f} DN; "
                         "is the saturation frame a dark or bias frame?")

    if flats is None:
        raise InputError("no flat fields given: the gain g and the PRNU map need flat fields")
    fl = estimate_flats(flats, dark_ref, v_sat, ro.sigma2_R, clip, dark_slope_map, mu_R=ro.mu_R)
    counts["flat"] = fl.n_frames
    prnu_stderr = fl.prnu_stderr
    if prnu_stderr is not None and ro.bias_map is not None:
        # the offset map's own noise (sigma2_R / n_bias) is common to every flat: add it
        prnu_stderr = np.square(prnu_stderr)
        prnu_stderr += np.float32(ro.sigma2_R / ro.n_frames / fl.mean_level**2)
        np.sqrt(prnu_stderr, out=prnu_stderr)
    if not fl.pairs:
        raise InputError("the gain needs at least two flat fields at the same exposure time (a pair, Eq. 16)")
    sigma2_a = fl.prnu_std**2
    # Eq. 17 with the dark signal / light signal ratio of the flats (from the dark fit when known)
    t_flat = float(np.mean([p.exposure_time for p in fl.pairs]))
    dark_dn = dark_fit.slope * t_flat if dark_fit is not None else 0.0
    k = prnu_correction_factor(fl.mean_level, sigma2_a, max(dark_dn, 0.0))
    g_pairs, g_pairs_se, per_pair = None, None, []
    sat_span = v_sat - ro.mu_R
    ok_pairs = [p for p in fl.pairs if p.mean - ro.mu_R <= 0.8 * sat_span]
    if ok_pairs:
        g_pairs, g_pairs_se, per_pair = gain_from_pairs(ok_pairs, ro.mu_R, ro.sigma2_R, k, ro.sigma2_R_stderr)
    ptc = None
    x = np.array([p.mean - ro.mu_R for p in fl.pairs])
    y = np.array([p.variance - ro.sigma2_R for p in fl.pairs])
    if dark_slope_map is not None:  # dark signal above bias at each pair's time (in DN)
        x = x - np.array([dark_fit.slope * p.exposure_time for p in fl.pairs])
    n_levels = int(np.unique(np.round(x[(x > 0) & (x <= fit_fraction * sat_span)], 6)).size)
    if n_levels >= 3:
        ptc = photon_transfer_gain(x, y, sat_span, fit_fraction, [p.variance_stderr for p in fl.pairs],
                                   ro.sigma2_R_stderr)
    if gain_method == "ptc" and ptc is None:
        raise InputError(f"the photon-transfer regression needs flat pairs at >= 3 levels within "
                         f"{fit_fraction:.0%} of saturation; got {n_levels}")
    if gain_method == "pairs" and g_pairs is None:
        raise InputError("no flat pair below 80 % of saturation for Eq. 16")
    use_ptc = gain_method == "ptc" or (gain_method == "auto" and ptc is not None)
    if use_ptc:
        g, g_se, g_method = ptc.g, ptc.g_stderr, "EMVA 1288 photon-transfer regression (0-70 % of saturation)"
    else:
        if g_pairs is None:
            raise InputError("no flat pair below 80 % of saturation for the gain (Eq. 16)")
        g, g_se, g_method = g_pairs, g_pairs_se, f"flat pairs, Eq. 16-17 (k = {k:.6f}), {len(ok_pairs)} pairs"
    if not (np.isfinite(g) and g > 0):
        raise InputError(f"gain estimate {g!r} is not positive: are the flats really flat and unsaturated?")
    stderr["g"] = g_se
    info["gain_method"] = g_method
    info["gain_pairs"] = {"g": g_pairs, "g_stderr": g_pairs_se, "per_pair": per_pair, "k_eq17": k}
    if ptc is not None:
        info["ptc"] = {"g": ptc.g, "g_stderr": ptc.g_stderr, "means": ptc.means.tolist(),
                       "variances": ptc.variances.tolist(), "used": ptc.used.tolist(), "saturation": ptc.saturation}
    else:
        info["ptc"] = {"means": x.tolist(), "variances": y.tolist(), "used": [False] * len(x), "saturation": sat_span}
    info["flat_levels"] = [{"t": t, "level": lv_, "file": nm} for t, lv_, nm in fl.levels]
    info["prnu_frames"] = fl.n_prnu_frames
    info["prnu_rejected_samples"] = fl.n_rejected

    # dark current in electrons per second
    D, D_se, dmap = 0.0, 0.0, None
    if dark_fit is not None:
        D = max(dark_fit.slope / g, 0.0)
        D_se = float(np.hypot(dark_fit.slope_stderr / g, D * g_se / g))
        dmap = (dark_slope_map / g).astype(np.float32)
        info["dark_fit"] = {"slope_DN_per_s": dark_fit.slope, "slope_stderr": dark_fit.slope_stderr,
                            "intercept_DN": dark_fit.intercept, "D_raw_e_per_s": dark_fit.slope / g}
        stderr["dark_current"] = D_se
    if fl.prnu_stderr is not None:
        stderr["prnu_std"] = float(fl.prnu_std / np.sqrt(2 * fl.prnu.size)) if fl.prnu_std > 0 else 0.0
    wl = float(white_level) if white_level is not None else float(max(v_sat, 1.0))
    params = SensorParams(g=float(g), mu_R=float(ro.mu_R), sigma2_R=float(ro.sigma2_R), v_sat=float(v_sat),
                          white_level=max(wl, float(v_sat)), dark_current=float(D),
                          name=str(prov.get("camera", "") or ""))
    prov.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    prov["frame_counts"] = counts
    prov["n_frames"] = int(sum(counts.values()))
    prov["prnu_std"] = fl.prnu_std
    prov["calibration"] = info
    return Calibration(params=params, prnu=fl.prnu, bias_map=ro.bias_map, dark_current_map=dmap,
                       stderr={k_: float(v) for k_, v in stderr.items()}, provenance=prov,
                       prnu_stderr=prnu_stderr, saturation_map=sat_map)


def calibration_summary(calib: Calibration) -> dict:
    """The one-line summary printed by ``hdrcap calibrate --json``."""
    p = calib.params
    prov = calib.provenance
    se = calib.stderr
    prnu_std = prov.get("prnu_std")
    if prnu_std is None and calib.prnu is not None:
        prnu_std = float(np.std(calib.prnu))
    return {
        "g": p.g, "g_stderr": se.get("g"),
        "mu_R": p.mu_R, "mu_R_stderr": se.get("mu_R"),
        "sigma2_R": p.sigma2_R, "sigma2_R_stderr": se.get("sigma2_R"),
        "v_sat": p.v_sat, "v_sat_stderr": se.get("v_sat"),
        "prnu_std": prnu_std,
        "dark_current": p.dark_current, "dark_current_stderr": se.get("dark_current"),
        "n_frames": prov.get("n_frames"),
        "gain_method": prov.get("calibration", {}).get("gain_method"),
    }


# --------------------------------------------------------------------------- file I/O

_MAP_FIELDS = ("prnu", "prnu_stderr", "bias_map", "dark_current_map", "saturation_map")


def _jsonable(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in calibration metadata")


def save_calibration(path, calibration: Calibration, force: bool = False) -> Path:
    """Write ``calibration`` to ``path`` atomically (never overwriting without ``force``).

    Format (docs/calibration.md): a compressed NumPy ``.npz`` archive with float32 maps
    ``prnu``, ``prnu_stderr``, ``bias_map``, ``dark_current_map`` (each optional) and a
    ``metadata`` entry holding UTF-8 JSON: ``format``, ``version``, ``shape``, ``params``,
    ``stderr``, ``provenance``, ``maps``. Any file name is accepted.
    """
    from hdrcap import __version__
    from .io import atomic_output

    arrays = {}
    shape = None
    for name in _MAP_FIELDS:
        arr = getattr(calibration, name, None)
        if arr is None:
            continue
        arr = np.ascontiguousarray(arr, dtype=np.float32)
        if shape is not None and arr.shape != shape:
            raise ValueError(f"calibration map {name} has shape {arr.shape}, expected {shape}")
        shape = arr.shape
        arrays[name] = arr
    prov = dict(calibration.provenance)
    prov.setdefault("hdrcap_version", __version__)
    meta = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "shape": list(shape) if shape else None,
        "params": calibration.params.to_dict(),
        "stderr": dict(calibration.stderr),
        "provenance": prov,
        "maps": sorted(arrays),
        "dark_library": getattr(calibration, "dark_library", None),
    }
    text = json.dumps(meta, sort_keys=True, default=_jsonable, allow_nan=True)
    arrays["metadata"] = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)
    path = Path(path)
    with atomic_output(path, force=force, suffix=".tmp") as tmp:
        buf = _io.BytesIO()
        np.savez_compressed(buf, **arrays)
        tmp.write_bytes(buf.getvalue())
    return path


def load_calibration(path) -> Calibration:
    """Read a calibration file written by :func:`save_calibration`.

    Checks the format name, the version (files of a newer major version are refused) and that
    every map has the recorded shape.

    Raises
    ------
    InputError
        Missing or unreadable file, not a calibration file, unsupported version, bad shape.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such calibration file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a calibration file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "metadata" not in z.files:
                raise InputError(f"{path}: not an hdrcap calibration file (no metadata entry)")
            meta = json.loads(bytes(z["metadata"]).decode("utf-8"))
            maps = {name: z[name] for name in _MAP_FIELDS if name in z.files}
    except InputError:
        raise
    except (OSError, ValueError, KeyError, json.JSONDecodeError, EOFError) as err:
        raise InputError(f"{path}: not a readable hdrcap calibration file ({type(err).__name__})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"{path}: not an hdrcap calibration file (format {meta.get('format')!r})"
                         if isinstance(meta, dict) else f"{path}: not an hdrcap calibration file")
    version = meta.get("version")
    if not isinstance(version, int) or version < 1 or version > FORMAT_VERSION:
        raise InputError(f"{path}: calibration format version {version!r} is not supported "
                         f"(this hdrcap reads versions 1..{FORMAT_VERSION})")
    shape = tuple(meta["shape"]) if meta.get("shape") else None
    for name, arr in maps.items():
        if arr.ndim != 2 or (shape is not None and arr.shape != shape):
            raise InputError(f"{path}: map {name} has shape {arr.shape}, the file says {shape}")
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{path}: map {name} holds NaN or infinite values")
    try:
        params = SensorParams(**meta["params"])
    except (TypeError, ValueError, KeyError) as err:
        raise InputError(f"{path}: bad camera parameters ({err})") from None
    if "prnu" in maps and not np.all(maps["prnu"] > 0):
        raise InputError(f"{path}: PRNU map has non-positive gains")
    return Calibration(
        params=params,
        prnu=maps.get("prnu"),
        bias_map=maps.get("bias_map"),
        dark_current_map=maps.get("dark_current_map"),
        stderr={k: float(v) for k, v in (meta.get("stderr") or {}).items() if v is not None},
        provenance=dict(meta.get("provenance") or {}),
        prnu_stderr=maps.get("prnu_stderr"),
        saturation_map=maps.get("saturation_map"),
        dark_library=meta.get("dark_library"),
    )
