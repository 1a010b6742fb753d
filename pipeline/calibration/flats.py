"""Flat fields: the per-photosite gain map a_j (PRNU, Eq. 14) and the flat pairs for the gain.

Each flat is dark-corrected, normalised by its clipped spatial mean and accumulated with a
weight proportional to its level; consecutive flats of one exposure time form the pairs of
Eq. 16 and of the photon-transfer regression. Photosites at or above saturation are censored
per frame (left out of a_j; pairs censor on the pair mean, see
:func:`~hdrcap.pipeline.calibration.stats.pair_statistics`); a frame is refused only when most
of it is clipped. Units: DN, DN/s, s; a_j is dimensionless.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrcap.pipeline.calibration import _kernels as _k
from hdrcap.pipeline.calibration.frames import check_shape, frame_data, frame_name, frame_time
from hdrcap.pipeline.calibration.stats import (
    DEFAULT_CLIP,
    PairStats,
    PixelStack,
    _clip_bounds,
    _subsample,
    as_correction_map,
    pair_statistics,
)
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.times import same_exposure

__all__ = ["FlatResult", "estimate_flats"]


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
    frames : list of dict
        Per flat, in input order: ``file``, ``t`` (s), ``level`` (DN above dark),
        ``clipped`` (photosites at or above v_sat), ``prnu`` (whether it entered a_j) and
        ``note`` (why not, or what was censored).
    skipped_pairs : list of dict
        Pairs that gave no statistics (``files``, ``t``, ``reason``).
    n_never_measured : int
        Photosites clipped in every flat of the PRNU map (a_j is then a lower bound with a
        100 % standard error).
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
    frames: list = field(default_factory=list)
    skipped_pairs: list = field(default_factory=list)
    n_never_measured: int = 0


#: A flat with more than this fraction of its photosites clipped is a saturation frame.
SATURATED_FRACTION = 0.5
#: A flat with more than this fraction clipped stays out of the PRNU map (a_j near the clip
#: would be a truncated mean); its pairs still serve the gain.
PRNU_CLIPPED_FRACTION = 0.01


def _check_clipped(n_clipped: int, size: int, v_sat: float, name: str) -> None:
    """Refuse a flat with most of its ``size`` photosites at or above ``v_sat`` (DN)."""
    frac = float(n_clipped) / size
    if frac > SATURATED_FRACTION:
        raise InputError(
            f"{name}: flat field is saturated ({100 * frac:.1f} % of photosites at or above "
            f"v_sat = {v_sat:.1f} DN); lower the exposure"
        )


class _PairWorker:
    """:func:`~hdrcap.pipeline.calibration.stats.pair_statistics` of the flat pairs in one
    background thread (its kernel releases the GIL: the next flat's level and the stack's
    additions run meanwhile), at most :attr:`window` pairs ahead; on leaving, every pair's
    result is appended to ``pairs`` in the order given, and a pair whose photosites were all
    censored or clipped away (a ValueError) to ``skipped`` with its reason."""

    window = 2

    def __init__(self, pairs: list[PairStats], skipped: list[dict]):
        self.pairs, self.skipped = pairs, skipped
        self.jobs: list[tuple[Any, list[str], float]] = []
        self.done = 0

    def __enter__(self) -> _PairWorker:
        from concurrent.futures import ThreadPoolExecutor

        self.pool = ThreadPoolExecutor(1, thread_name_prefix="hdrcap-flat-pairs")
        return self

    def submit(self, a, b, clip, t: float, upper: float, files: list[str]) -> None:
        """Queue the pair (a, b) of exposure time ``t`` (files named ``files``)."""
        while len(self.jobs) - self.done >= self.window:  # bounded: each job holds two frames
            self.jobs[self.done][0].exception()
            self.done += 1
        self.jobs.append((self.pool.submit(pair_statistics, a, b, clip, t, upper=upper), files, t))

    def __exit__(self, *exc) -> None:
        self.pool.shutdown(wait=True)
        if exc[0] is not None:
            return
        for job, files, t in self.jobs:
            try:
                self.pairs.append(job.result())
            except ValueError as err:  # every photosite censored or clipped away
                self.skipped.append({"files": files, "t": t, "reason": str(err)})


def _flat_level(
    data: np.ndarray, offset: np.ndarray, rate: np.ndarray, t: float, v_sat: float, clip: float | None, name: str
) -> tuple[float, int]:
    """The clipped spatial mean of the dark-corrected flat, (data - offset) - rate * t in
    float32 (DN; :func:`~.stats.robust_mean_std` of that image), and the photosites at or above
    ``v_sat``, in one pass without making the image; refuses a mostly clipped flat."""
    tr = rate.dtype.type(t)
    lo = hi = 0.0
    if clip is not None:
        sub = _subsample(data).astype(np.float32)
        sub -= _subsample(offset) if offset.size == data.size else offset[0, 0]
        if rate.size == data.size:
            sub -= _subsample(rate) * tr
        lo, hi = (float(np.float32(b)) for b in _clip_bounds(sub, clip))  # the float32 image's comparison
    n, mean, _m2, n_clipped = _k.flat_moments(data, offset, rate, tr, lo, hi, clip is not None, float(v_sat))
    _check_clipped(n_clipped, data.size, v_sat, name)
    if n < 2:
        raise ValueError("fewer than two photosites survive clipping")
    return float(mean), int(n_clipped)


def _prnu_weight(level: float) -> float:
    """Weight of a flat at ``level`` DN: ~ level (inverse relative shot-noise variance),
    quantised to 1/16 octave so that flats at one level share one weight (no weight maps)."""
    return float(2.0 ** (np.round(np.log2(level) * 16) / 16))


def _prnu_map(mean_map: np.ndarray, err_map: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Eq. 14: the clipped weighted mean of the normalised flats renormalised to mean 1 (in
    place), its standard-error map, and the PRNU spread without the estimation noise."""
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
    return prnu, err_map, prnu_std


def estimate_flats(
    frames: Iterable,
    dark_reference: np.ndarray | float,
    v_sat: float,
    sigma2_R: float,
    clip: float | None = DEFAULT_CLIP,
    dark_rate_map: np.ndarray | None = None,
    prnu_max_fraction: float = 0.9,
    mu_R: float | None = None,
) -> FlatResult:
    """Stream flat fields: the dark-corrected PRNU map a_j (Eq. 14) and the flat pairs.

    Each flat f_i is dark-corrected with ``dark_reference`` plus ``dark_rate_map`` * t when
    given, normalised by its clipped spatial mean, and accumulated with weight proportional to
    its level (inverse of its relative shot-noise variance); the clipped weighted mean over
    frames is renormalised to mean 1 (Eq. 14). Photosites at or above ``v_sat`` are censored
    in that frame; frames above ``prnu_max_fraction`` of saturation, or with more than 1 % of
    their photosites clipped, only serve the gain. Pairs censor photosites whose pair mean lies
    near ``v_sat``.

    Parameters
    ----------
    frames : iterable of frames
        Flat fields (``data`` in DN, ``exposure_time`` in s), consumed once.
    dark_reference : numpy.ndarray or float
        The bias map or mu_R, DN.
    v_sat : float
        Saturation limit, DN.
    sigma2_R : float
        Readout variance, DN^2 (a flat below 3 sigma_R above the bias is refused).
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables outlier rejection.
    dark_rate_map : numpy.ndarray, optional
        Per-photosite dark signal rate, DN/s.
    prnu_max_fraction : float
        Flats above this fraction of the span from bias to saturation are left out of a_j.
    mu_R : float, optional
        Bias level, DN (default: the mean of ``dark_reference``).

    Returns
    -------
    FlatResult
        a_j and its standard error, the flat pairs and the level (DN) of every flat.

    Raises
    ------
    InputError
        Mixed sizes, a flat that is dark (level below 3 sigma_R above the bias) or saturated
        (more than half of its photosites at or above v_sat), or no flat for the PRNU map.
    """
    shape = first = None
    stack = None
    pairs: list[PairStats] = []
    levels = []
    pending = None
    n = 0
    prnu_levels: list[float] = []
    notes: list[dict] = []
    skipped: list[dict] = []
    sat_span = v_sat - (mu_R if mu_R is not None else float(np.mean(dark_reference)))
    no_rate = as_correction_map(None, ())
    # the pairs' statistics in a thread of their own, in order (the next flat's level meanwhile)
    with _PairWorker(pairs, skipped) as pair_worker:
        for i, fr in enumerate(frames):
            data = np.ascontiguousarray(frame_data(fr))
            name = frame_name(fr, "flat", i)
            check_shape(data, shape, name, first)
            if stack is None:
                shape, first = data.shape, name
                stack = PixelStack(shape)
                offset = as_correction_map(dark_reference, shape)
                rate = as_correction_map(dark_rate_map, shape)
            t = frame_time(fr)
            level, n_clipped = _flat_level(data, offset, rate if t > 0 else no_rate, t, v_sat, clip, name)
            if level < 3.0 * np.sqrt(sigma2_R):
                raise InputError(
                    f"{name}: flat field is dark (mean {level:.1f} DN above the bias, below "
                    f"3 sigma_R = {3 * np.sqrt(sigma2_R):.1f} DN)"
                )
            levels.append((t, float(level), name))
            in_prnu, note = _prnu_use(level, sat_span, prnu_max_fraction, n_clipped, data.size)
            if in_prnu:
                prnu_levels.append(level)
                stack.add_corrected(
                    data, offset, rate if t > 0 else no_rate, t, level, _prnu_weight(level), v_sat, n_clipped
                )
            notes.append(
                {"file": name, "t": t, "level": float(level), "clipped": n_clipped, "prnu": in_prnu, "note": note}
            )
            if pending is not None and same_exposure(pending[1], t):
                pair_worker.submit(pending[0], data, clip, t, v_sat, [pending[2], name])
                pending = None
            else:
                pending = (data, t, name)
            n += 1
    if stack is None:  # made at the first flat
        raise InputError("no flat fields given")
    if stack.n == 0:
        raise InputError(f"every flat field is above {prnu_max_fraction:.0%} of saturation; none can give the PRNU map")
    mean_map, err_map, rejected = stack.result(clip)
    n_prnu = stack.n
    counts = stack.n_uncensored()
    n_never = 0 if counts is None else int(np.count_nonzero(counts == 0))
    del stack, counts  # free the sums before building the maps
    prnu, err_map, prnu_std = _prnu_map(mean_map, err_map)
    return FlatResult(
        prnu,
        err_map,
        prnu_std,
        pairs,
        levels,
        n,
        n_prnu,
        rejected,
        float(np.mean(prnu_levels)),
        notes,
        skipped,
        n_never,
    )


def _prnu_use(level: float, sat_span: float, max_fraction: float, n_clipped: int, size: int) -> tuple[bool, str]:
    """Whether a flat at ``level`` DN above dark (``n_clipped`` of ``size`` photosites at or
    above v_sat; ``sat_span`` DN from bias to v_sat) enters the PRNU map, and why or how."""
    if level > max_fraction * sat_span:
        return False, f"above {max_fraction:.0%} of saturation: gain only"
    if n_clipped > PRNU_CLIPPED_FRACTION * size:
        return False, f"{100 * n_clipped / size:.2g} % of photosites clipped: gain only"
    if n_clipped:
        return True, f"{n_clipped} clipped photosites censored in the PRNU map"
    return True, ""
