"""Robust statistics of raw frames: sigma-clipped means, EMVA 1288 pair variances, and a
streaming, sigma-clipped per-photosite mean of many frames.

Outliers (cosmic rays, hot and dead pixels) are rejected by sigma clipping: spatially (robust
median/MAD clip of each frame and of each pair difference) and temporally (per-photosite
rejection of the extreme sample, :class:`PixelStack`). Every accumulation is float64; memory
holds a few maps, never a stack of frames. Units: DN, DN^2.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrcap.pipeline.calibration import _kernels as _k
from hdrcap.pipeline.calibration.frames import frame_data, frame_time
from hdrcap.pipeline.times import same_exposure

__all__ = [
    "DEFAULT_CLIP",
    "as_correction_map",
    "robust_mean_std",
    "PairStats",
    "pair_statistics",
    "PairTap",
    "PixelStack",
]

#: Default clipping threshold, in standard deviations.
DEFAULT_CLIP = 5.0

#: A pair's photosites are censored when their pair mean lies within this many standard
#: deviations of one frame's deviation from it (half the difference's) of the clip level.
CENSOR_SIGMA = 3.5

_MAD_TO_SIGMA = 1.4826


# --------------------------------------------------------------------------- spatial statistics


#: Photosites in the regular subsample of the robust clip bounds and floors.
_SUBSAMPLE = 200_003


def _subsample(x: np.ndarray, n: int = _SUBSAMPLE) -> np.ndarray:
    """A regular subsample of at most about ``n`` values of ``x`` (flattened)."""
    flat = x.ravel()
    if flat.size <= n:
        return flat
    step = flat.size // n
    return flat[::step]


def as_correction_map(x: np.ndarray | float | None, shape: tuple[int, ...]) -> np.ndarray:
    """An offset or rate for :meth:`PixelStack.add_corrected`: a map of ``shape`` as it is
    (contiguous), a numpy scalar as a (1, 1) array of its type, a Python number (or None: 0) as
    a (1, 1) float32 array (numpy's float32 arithmetic casts a Python number to float32).

    Parameters
    ----------
    x : numpy.ndarray, float or None
        The offset (DN) or rate (DN/s).
    shape : tuple of int
        Frame shape.

    Returns
    -------
    numpy.ndarray
    """
    if x is None:
        return np.zeros((1, 1), np.float32)
    if isinstance(x, np.ndarray) and x.ndim:
        if x.shape != tuple(shape):
            raise ValueError(f"map of shape {x.shape} for frames of shape {tuple(shape)}")
        return np.ascontiguousarray(x)
    if isinstance(x, (np.ndarray, np.generic)):
        return np.full((1, 1), x, dtype=x.dtype)
    return np.full((1, 1), x, np.float32)


def robust_mean_std(
    x: np.ndarray, clip: float | None = DEFAULT_CLIP, mask: np.ndarray | None = None
) -> tuple[float, float, np.ndarray]:
    """Sigma-clipped spatial mean and standard deviation of ``x``.

    The clip interval is median +- ``clip`` robust sigmas (1.4826 MAD, taken from a regular
    subsample for speed; the sample standard deviation when the MAD is zero).

    Parameters
    ----------
    x : numpy.ndarray
        Values, DN (any real dtype).
    clip : float or None
        Clipping threshold, robust standard deviations; None disables clipping.
    mask : numpy.ndarray of bool, optional
        Photosites to consider (all by default).

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
    """median +- clip robust sigmas (1.4826 MAD; the standard deviation when the MAD is 0).
    Integer values (raw frames and their differences) take :func:`_int_median_mad` (the same
    values as numpy's medians, from counts instead of a sort)."""
    med, mad = _int_median_mad(sub) if _countable(sub) else _float_median_mad(sub)
    scale = _MAD_TO_SIGMA * mad
    if scale == 0.0:
        scale = float(np.std(sub.astype(np.float64)))
    return med - clip * scale, med + clip * scale


def _float_median_mad(sub: np.ndarray) -> tuple[float, float]:
    """The median of ``sub`` and the median absolute deviation from it (float64)."""
    sub = sub.astype(np.float64)
    med = float(np.median(sub))
    return med, float(np.median(np.abs(sub - med)))


def _countable(x: np.ndarray) -> bool:
    """Integer values within a range that counting covers (at most 2^20 codes)."""
    return x.size > 0 and np.issubdtype(x.dtype, np.integer) and int(x.max()) - int(x.min()) < 1 << 20


def _median_of_counts(counts: np.ndarray, offset: int, n: int) -> float:
    """The median of ``n`` integers given their counts (value = index + ``offset``), as
    numpy's: the middle value, or the mean of the two middle ones."""
    cum = np.cumsum(counts)
    v1 = int(np.searchsorted(cum, (n - 1) // 2, side="right")) + offset
    v2 = int(np.searchsorted(cum, n // 2, side="right")) + offset
    return (float(v1) + float(v2)) / 2.0


def _int_median_mad(x: np.ndarray) -> tuple[float, float]:
    """:func:`_float_median_mad` of integer values, bit for bit, by counting: the median is an
    integer or half an integer, so twice the absolute deviations are integers too."""
    x = x.astype(np.int64)
    lo = int(x.min())
    med = _median_of_counts(np.bincount(x - lo), lo, x.size)
    dev2 = np.abs(2 * x - int(2 * med))
    return med, _median_of_counts(np.bincount(dev2), 0, x.size) / 2.0


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
        Photosites kept and rejected (by the clip and the censoring).
    exposure_time : float
        Seconds.
    n_censored : int
        Photosites left out because their pair mean lies near the clip level (see
        :func:`pair_statistics`), included in ``n_rejected``.
    """

    mean_a: float
    mean_b: float
    variance: float
    variance_stderr: float
    n_used: int
    n_rejected: int
    exposure_time: float = 0.0
    n_censored: int = 0

    @property
    def mean(self) -> float:
        """Mean of the two frames' means, DN."""
        return 0.5 * (self.mean_a + self.mean_b)


def pair_statistics(
    a: np.ndarray,
    b: np.ndarray,
    clip: float | None = DEFAULT_CLIP,
    exposure_time: float = 0.0,
    upper: float | None = None,
) -> PairStats:
    """EMVA 1288 temporal variance of a pair of frames, with outliers clipped.

    sigma^2 = (1/2NM) sum_j (y_A,j - y_B,j)^2 - 1/2 (mu_A - mu_B)^2, where the sum runs over
    the photosites kept by a robust ``clip``-sigma clip of the difference y_A - y_B (a cosmic
    ray or a hot pixel hit in one frame) and of each frame (hot or dead photosites). The fixed
    pattern (DSNU, PRNU) cancels in the difference.

    Near saturation, photosites are censored on their pair mean: those with
    (y_A + y_B)/2 >= ``upper`` - 3.5 s (s the robust standard deviation of (y_A - y_B)/2) are
    left out, so that a kept photosite is clipped in neither frame (3.5 sigma). Selecting on
    the sum leaves the variance of the difference unbiased: for Poisson counts the variance of
    a - b given a + b = n is n, so the kept photosites' variance matches their mean. Leaving
    out the photosites clipped in either frame instead (a selection on the difference) biases
    the variance low (-0.6 % with 0.14 % clipped photosites, -3.8 % with 1.1 %).

    Parameters
    ----------
    a, b : numpy.ndarray
        The two frames, DN, same shape.
    clip : float or None
        Clipping threshold, robust standard deviations; None keeps every photosite.
    exposure_time : float
        Exposure time of the pair, s (recorded in the result).
    upper : float, optional
        Clip level of the raw values (e.g. v_sat), DN; None censors nothing.

    Returns
    -------
    PairStats
        Means (DN), variance and its standard error (DN^2), photosites kept and rejected.

    Raises
    ------
    ValueError
        Frames of different shapes, or fewer than 16 photosites left after clipping.
    """
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"pair of frames with different shapes {a.shape} and {b.shape}")
    bounds = (0.0,) * 6
    if clip is not None:
        sa, sb = _subsample(a), _subsample(b)
        if np.issubdtype(sa.dtype, np.integer) and np.issubdtype(sb.dtype, np.integer):
            diff = sa.astype(np.int64) - sb  # exact, as the float64 difference of integers
        else:
            diff = sa.astype(np.float64) - sb.astype(np.float64)
        bounds = (*_clip_bounds(sa, clip), *_clip_bounds(sb, clip), *_clip_bounds(diff, clip))
    limit = 0.0 if upper is None else _censor_limit(a, b, float(upper))
    # one fused pass for the kept photosites and their means, one for the moments (no masks):
    # (1/2n) sum d^2 - 1/2 (mu_A - mu_B)^2 == 1/2 mean of (d - (mu_A - mu_B))^2 over the kept photosites
    f32_total = np.result_type(np.float32, b.dtype) == np.float32
    n, mu_a, mu_b, s2, m4, n_censored = _k.pair_fused(
        np.ascontiguousarray(a), np.ascontiguousarray(b), *bounds, clip is not None, limit, f32_total, upper is not None
    )
    if n < 16:
        raise ValueError("fewer than 16 photosites survive clipping")
    var = 0.5 * s2
    var_stderr = 0.5 * np.sqrt(max(m4 - s2 * s2, 0.0) / n)
    d = a.size
    return PairStats(
        float(mu_a), float(mu_b), var, float(var_stderr), int(n), int(d - n), float(exposure_time), int(n_censored)
    )


def _censor_limit(a: np.ndarray, b: np.ndarray, upper: float) -> float:
    """The float32 limit of the pair total a + b of :func:`pair_statistics`' censoring: photosites
    whose pair mean lies within CENSOR_SIGMA robust sigmas of half the difference below
    ``upper`` (DN) are left out."""
    sa, sb = _subsample(a), _subsample(b)
    if np.issubdtype(sa.dtype, np.integer) and np.issubdtype(sb.dtype, np.integer):
        diff = sa.astype(np.int64) - sb  # twice the half difference, exact
    else:
        diff = sa.astype(np.float64) - sb
    _med, mad = _int_median_mad(diff) if _countable(diff) else _float_median_mad(diff)
    # the half difference's MAD is half the difference's (exact: a power of two)
    scale = _MAD_TO_SIGMA * (mad / 2.0) or float(np.std(diff / 2.0))
    return float(np.float32(2.0 * (upper - CENSOR_SIGMA * scale)))


@dataclass
class PairTap:
    """Pass frames through unchanged, recording the pair statistics of consecutive frames at
    one exposure time (frames 1-2, 3-4, ... of a run).

    Holds one frame at a time. Iterate it in place of ``frames``; :attr:`pairs` fills as the
    consumer advances.

    Attributes
    ----------
    frames : iterable of frames
        The frames (``data`` in DN, ``exposure_time`` in s), consumed once.
    clip : float or None
        Clipping threshold of :func:`pair_statistics`, robust standard deviations.
    pairs : list of PairStats
        The pairs seen so far (means DN, variance DN^2, exposure time s).
    """

    frames: Iterable
    clip: float | None = DEFAULT_CLIP
    pairs: list = field(default_factory=list)

    def __iter__(self) -> Iterator[Any]:
        pending = None
        for fr in self.frames:
            yield fr  # the consumer checks the frame (size, order) before it is paired
            data, t = frame_data(fr), frame_time(fr)
            if pending is not None and same_exposure(pending[1], t) and pending[0].shape == data.shape:
                self.pairs.append(pair_statistics(pending[0], data, self.clip, t))
                pending = None
            else:
                pending = (data, t)


# --------------------------------------------------------------------------- per-photosite stacks

#: Frames :meth:`PixelStack.add_corrected` queues and then adds in one pass over the stack's maps
#: (the frames are kept, not copied, until then: memory-mapped frames cost no copy); the
#: arguments of :func:`~._kernels.stack_add_batch`.
BATCH = 8

#: The offset and rate of raw frames in the queue (:meth:`PixelStack.add`).
_NO_MAP = np.zeros((1, 1), np.float32)


class PixelStack:
    """Streaming, sigma-clipped per-photosite weighted mean of many frames.

    Holds float64 sums (weighted sum and sum of squares, relative to the first frame) and the
    extreme sample of every photosite with its weight: memory does not grow with the number of
    frames. Samples can be censored per photosite (a clipped value): once any is, the stack also
    keeps per-photosite weight sums and counts. At the end, the largest and the smallest sample
    of a photosite are rejected when they lie more than ``clip`` standard deviations from the weighted mean of the other
    samples (the standard deviation is the photosite's own, floored by the median over the
    frame, so that two or three frames are enough). A single cosmic-ray hit per photosite and
    stack is removed; a stable hot pixel is kept (it is real signal).

    Parameters
    ----------
    shape : tuple of int
        Frame shape.
    """

    def __init__(self, shape: tuple[int, ...]) -> None:
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
        # per-photosite weight sums and sample counts: allocated at the first censored sample
        self._swm: np.ndarray | None = None
        self._cnt: np.ndarray | None = None
        # the frames add_corrected queued (added in one pass, :data:`BATCH` at a time)
        self._queue: list[tuple] = []
        self._queue_key: tuple = (None, None, None)
        self._spare_ref: np.ndarray | None = None
        self._queue_rate: np.ndarray | None = None
        self._set_ref = False

    def add(self, values: np.ndarray, weight: float = 1.0, censor: np.ndarray | None = None) -> None:
        """Add one frame. Without ``censor``, a 2-D frame is queued and :data:`BATCH` queued
        frames are added in one pass (the stack keeps ``values``, not a copy, until then: it
        must not change).

        Parameters
        ----------
        values : numpy.ndarray
            The frame (any real dtype), DN or any unit common to the stack.
        weight : float
            Scalar weight of the frame (inverse relative variance), dimensionless.
        censor : numpy.ndarray of bool, optional
            Photosites whose sample is left out (e.g. clipped at saturation).
        """
        values = np.asarray(values)
        if values.shape != self.shape:
            raise ValueError(f"frame shape {values.shape} differs from the stack's {self.shape}")
        if censor is None and values.ndim == 2:  # queued: added in one pass with the next ones
            self._enqueue(np.ascontiguousarray(values), False, _NO_MAP, _NO_MAP, 0.0, 1.0, weight, None, 0)
            return
        self._flush()
        if self._ref is None:
            self._ref = self._take_ref()
            np.copyto(self._ref, values, casting="unsafe")
            self._w0 = float(weight)
        w = float(weight)
        values = np.ascontiguousarray(values)
        if self._swm is None and censor is not None and censor.any():
            self._swm = np.full(self.shape, self.sw, np.float64)
            self._cnt = np.full(self.shape, self.n, np.float64)
        if self._wmax is None and (w != self._w0 or self._swm is not None):
            self._wmax = np.full(self.shape, self._w0, np.float32)
            self._wmin = np.full(self.shape, self._w0, np.float32)
        if self._swm is not None:
            censor = np.zeros(self.shape, bool) if censor is None else np.ascontiguousarray(censor, dtype=bool)
            self._add_censored(values, w, censor)
        elif self._wmax is None:
            _k.stack_add_equal(values, self._ref, w, self._s, self._q, self._max, self._min)
        else:
            _k.stack_add(values, self._ref, w, self._s, self._q, self._max, self._min, self._wmax, self._wmin)
        self.n += 1
        self.sw += w

    def add_corrected(
        self,
        data: np.ndarray,
        offset: np.ndarray,
        rate: np.ndarray,
        t: float,
        scale: float,
        weight: float = 1.0,
        upper: float | None = None,
        n_upper: int = 0,
    ) -> None:
        """Add the frame ((data - offset) - rate * t) / scale, each step rounded to float32 as
        numpy computes the image, without making it: the frame is queued and :data:`BATCH`
        queued frames are added in one pass over the stack's maps (bit for bit :meth:`add` of
        each image in turn). The stack keeps ``data``, ``offset`` and ``rate`` (no copy) until
        then: they must not change.

        Parameters
        ----------
        data : numpy.ndarray
            The raw frame, DN.
        offset, rate : numpy.ndarray
            Offset (DN) and dark rate (DN/s) maps of the frame's shape, or (1, 1) arrays for a
            scalar offset and no rate (:func:`as_correction_map`).
        t : float
            Exposure time, s.
        scale : float
            Divisor of the corrected frame (rounded to float32).
        weight : float
            Scalar weight of the frame (inverse relative variance), dimensionless.
        upper : float, optional
            Raw values at or above it (DN) are censored (left out).
        n_upper : int
            Photosites of ``data`` at or above ``upper`` (0: nothing censored in this frame).
        """
        data = np.ascontiguousarray(data)
        if data.shape != self.shape:
            raise ValueError(f"frame shape {data.shape} differs from the stack's {self.shape}")
        self._enqueue(data, True, offset, rate, t, scale, weight, upper, n_upper)

    def _enqueue(self, data, corrected, offset, rate, t, scale, weight, upper, n_upper) -> None:
        """Queue a frame for :meth:`_flush` (arguments of :meth:`add_corrected`; ``corrected``
        False: the raw values, as :meth:`add`), making the choices :meth:`add` makes frame by
        frame: the reference, then the weight sums and counts at the first censored sample (the
        frames queued before it are in their fill), then the extremes' weights."""
        rate_on = rate.size == data.size
        other_rate = rate_on and self._queue_rate is not None and self._queue_rate is not rate
        key = self._queue_key
        if self._queue and (corrected != key[0] or data.dtype != key[1] or offset is not key[2] or other_rate):
            self._flush()
        self._queue_key = (corrected, data.dtype, offset)
        if rate_on:
            self._queue_rate = rate
        w = float(weight)
        if self._ref is None:
            self._ref = self._take_ref()
            self._w0 = w
            self._set_ref = True
        censor = upper is not None and n_upper > 0
        if self._swm is None and censor:
            self._swm = np.full(self.shape, self.sw, np.float64)
            self._cnt = np.full(self.shape, self.n, np.float64)
        if self._wmax is None and (w != self._w0 or self._swm is not None):
            self._wmax = np.full(self.shape, self._w0, np.float32)
            self._wmin = np.full(self.shape, self._w0, np.float32)
        # numpy compares a float frame with a Python number in the frame's type
        up = 0.0 if not censor else float(data.dtype.type(upper) if data.dtype.kind == "f" else upper)
        self._queue.append((data, rate_on, rate.dtype.type(t), np.float32(scale), w, up, censor, self._swm is not None))
        self.n += 1
        self.sw += w
        if len(self._queue) >= BATCH:
            self._flush()

    def _take_ref(self) -> np.ndarray:
        """The reference frame's buffer (the one :meth:`reset` kept, else a new one)."""
        buf, self._spare_ref = self._spare_ref, None
        return np.empty(self.shape, np.float32) if buf is None else buf

    def reset(self) -> None:
        """Empty the stack for a new series of frames of the same shape, keeping its maps'
        memory (no new pages to fault in: a 24 Mpixel stack is ~0.6 GB)."""
        self._queue = []
        self._queue_rate = None
        self._set_ref = False
        self.n = 0
        self.sw = 0.0
        self._spare_ref = self._ref if self._ref is not None else self._spare_ref
        self._ref = None
        self._s.fill(0.0)
        self._q.fill(0.0)
        self._max.fill(-np.inf)
        self._min.fill(np.inf)
        self._w0 = None
        self._wmax = self._wmin = self._swm = self._cnt = None

    def _flush(self) -> None:
        """Add the queued frames in one pass (:func:`~._kernels.stack_add_batch`)."""
        if not self._queue:
            return
        frames = [entry[0] for entry in self._queue]
        frames += [np.zeros((1, 1), frames[0].dtype)] * (BATCH - len(frames))
        f0, f1, f2, f3, f4, f5, f6, f7 = frames  # BATCH frames, the kernel's f0 ... f7
        corrected, _dtype, offset = self._queue_key
        none = np.zeros((1, 1))
        none32 = np.zeros((1, 1), np.float32)
        rate = none32 if self._queue_rate is None else self._queue_rate
        cols = list(zip(*self._queue))
        _k.stack_add_batch(
            f0,
            f1,
            f2,
            f3,
            f4,
            f5,
            f6,
            f7,
            len(self._queue),
            corrected,
            offset,
            rate,
            np.array(cols[1], bool),
            np.array(cols[2], rate.dtype),
            np.array(cols[3], np.float32),
            np.array(cols[4], np.float64),
            np.array(cols[5], np.float64),
            np.array(cols[6], bool),
            np.array(cols[7], bool),
            self._set_ref,
            self._ref,
            self._s,
            self._q,
            self._max,
            self._min,
            none32 if self._wmax is None else self._wmax,
            none32 if self._wmin is None else self._wmin,
            none if self._swm is None else self._swm,
            none if self._cnt is None else self._cnt,
        )
        self._queue = []
        self._queue_rate = None
        self._set_ref = False

    def _add_censored(self, values: np.ndarray, w: float, censor: np.ndarray) -> None:
        """Add a frame with weight ``w`` skipping the ``censor`` photosites (one fused pass):
        sums, extremes, per-photosite weight sums and counts."""
        _k.stack_add_censored(
            values,
            self._ref,
            w,
            censor,
            self._s,
            self._q,
            self._swm,
            self._cnt,
            self._max,
            self._min,
            self._wmax,
            self._wmin,
        )

    def result(self, clip: float | None = DEFAULT_CLIP) -> tuple[np.ndarray, np.ndarray | None, int]:
        """Clipped weighted mean map and its standard error map.

        The variance floors come from a regular subsample of about 200 000 photosites; the maps
        are then computed in one fused pass (rows in parallel, no full-size temporaries).

        Parameters
        ----------
        clip : float or None
            Rejection threshold, standard deviations; None keeps every sample.

        Returns
        -------
        mean : numpy.ndarray (float32)
            Per-photosite weighted mean, unit of the frames.
        stderr : numpy.ndarray (float32) or None
            Standard error of ``mean`` from the photosite's scatter (floored by the median
            scatter over the frame); None with a single frame.
        n_rejected : int
            Samples rejected over the whole stack.
        """
        if self.n == 0 or self._ref is None or self._w0 is None:  # the first frame sets both
            raise ValueError("empty stack")
        self._flush()
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
        none = np.zeros((1, 1))
        rejected = _k.stack_result(
            self._s,
            self._q,
            none if self._swm is None else self._swm,
            none if self._cnt is None else self._cnt,
            float(self.sw),
            float(self.n),
            self._max,
            none if self._wmax is None else self._wmax,
            self._min,
            none if self._wmin is None else self._wmin,
            float(self._w0),
            self._ref,
            0.0 if clip is None else float(clip) * float(clip),
            do_max,
            do_min,
            np.array([floors.get("max", 0.0), floors.get("min", 0.0), floors["var"]]),
            mean,
            err,
        )
        return mean, err, rejected

    def _block(self, idx, rows, clip, do_max, do_min, floors):
        """Statistics of a subsample (flat indices ``idx``) or of a block of ``rows``."""

        def get(a):
            if a is None:  # all weights equal
                a = np.broadcast_to(np.float32(self._w0), self.shape)
            return a.ravel()[idx].astype(np.float64) if idx is not None else a[rows].astype(np.float64)

        s, q = get(self._s), get(self._q)
        if self._swm is None:
            sw = np.full(s.shape, self.sw)
            cnt = np.full(s.shape, float(self.n))
        else:
            sw, cnt = get(self._swm), get(self._cnt)
        new_floors = {}
        nrej = 0
        for key, on, sign, va, wa in (
            ("max", do_max, +1, self._max, self._wmax),
            ("min", do_min, -1, self._min, self._wmin),
        ):
            if not on:
                continue
            v, w = get(va), get(wa)
            few = cnt < (3 if key == "max" else 4)  # too few uncensored samples to reject one
            v = np.where(few, 0.0, v)
            w = np.where(few, 0.0, w)
            s_o = s - w * v
            sw_o = sw - w
            with np.errstate(invalid="ignore", divide="ignore"):  # photosites without samples
                mean_o = s_o / sw_o
            var_o = np.maximum(q - w * v * v - sw_o * mean_o**2, 0.0) / np.maximum(cnt - 2, 1)
            if floors is None:
                floor = float(np.median(var_o[~few])) if not few.all() else 0.0
            else:
                floor = floors[key]
            new_floors[key] = floor
            dev = sign * (v - mean_o)
            rej = dev * dev * w > clip * clip * np.maximum(var_o, floor) * (1.0 + w / np.maximum(sw_o, 1e-300))
            s[rej] -= (w * v)[rej]
            q[rej] -= (w * v * v)[rej]
            sw[rej] -= w[rej]
            cnt[rej] -= 1
            nrej += int(rej.sum())
        none = sw <= 0  # every sample censored: the first (censored) value, 100 % error
        sw = np.where(none, 1.0, sw)
        mean_rel = s / sw
        var1 = np.maximum(q - sw * mean_rel**2, 0.0) / np.maximum(cnt - 1, 1)  # per unit weight
        floor = float(np.median(var1[~none])) if floors is None else floors["var"]
        new_floors["var"] = floor
        err = np.sqrt(np.maximum(var1, floor) / sw)
        ref = get(self._ref)
        mean = mean_rel + ref
        err = np.where(none, np.abs(ref), err)
        return mean, err, nrej, new_floors

    def n_uncensored(self) -> np.ndarray | None:
        """Uncensored samples per photosite (float64 map), or None when nothing was censored.

        Returns
        -------
        numpy.ndarray or None
        """
        self._flush()
        return None if self._cnt is None else self._cnt.copy()
