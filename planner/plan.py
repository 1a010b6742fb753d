"""Greedy exposure planning for a target SNR (Eq. 18, Sec. 8) with model selection.

The scene enters as a weighted histogram of log-irradiance (each non-empty bin represented by
its darkest and brightest pixel, so the minimum over pixels is evaluated exactly at the
extremes). The planner

1. marks the eligible pixels: those with signal that are not saturated even at the shortest
   allowed exposure (the others are reported, never silently dropped);
2. selects, before planning, the PRNU model and each candidate time's dark strategy by the
   SNR they cost at the target level (model selection, :mod:`planner.select`); a time whose
   decision is a dark frame is offered to the search both with and without it;
3. starts from the longest allowed exposure that does not saturate the scene's bulk (all
   eligible pixels but the brightest ``highlight_fraction``, Sec. 8) and adds greedily the
   allowed exposure that lowers sum_j exp(-snr_j) most (Eq. 18), under the constraints
   (allowed times, maximum number of exposures, time budget, per-frame overhead), until the
   target holds at the chosen quantile of eligible pixels;
4. polishes the sequence (drops exposures that are no longer needed and shortens others while
   the target still holds; never the first), then selects the saturation model and the
   merge iterations.

Every frame costs its exposure time plus a per-frame overhead (default
:data:`DEFAULT_OVERHEAD_S`); a matched dark frame costs as much again.

All variances come from :mod:`pipeline.noise` through :mod:`planner.predict`.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import logsumexp

from hdrcap.pipeline.blocks import flat_blocks
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.times import find_exposure, same_exposure, unique_exposures
from hdrcap.planner import select
from hdrcap.planner.ladder import THIRD_STOP_LADDER
from hdrcap.planner.predict import (
    K_SIGMA,
    SystematicErrors,
    combine_terms,
    exposure_terms,
    systematic_errors_from_calibration,
    to_db,
    usable_fraction,
)

__all__ = [
    "Plan",
    "IrradianceHistogram",
    "irradiance_histogram",
    "plan_exposures",
    "plan_exhaustive",
    "plan_bracket",
    "DEFAULT_MAX_EXPOSURES",
    "DEFAULT_HIGHLIGHT_FRACTION",
    "DEFAULT_OVERHEAD_S",
    "bulk_irradiance",
    "first_exposure",
]

#: Cap on the number of exposures when the caller gives neither ``max_exposures`` nor a budget.
DEFAULT_MAX_EXPOSURES = 64

#: The scene's "bulk" is every eligible pixel but the brightest ``DEFAULT_HIGHLIGHT_FRACTION``
#: (highlights: light sources, speculars). The first exposure is the longest allowed time that
#: saturates at most this fraction of the eligible pixels (Sec. 8: "the longest exposure before
#: saturation").
DEFAULT_HIGHLIGHT_FRACTION = 0.05

#: Default per-frame overhead, s: what a tethered camera spends per frame besides the exposure
#: (shutter and mirror latency, writing the raw, downloading it over USB). See docs/planner.md.
DEFAULT_OVERHEAD_S = 1.0


@dataclass(frozen=True)
class IrradianceHistogram:
    """A scene as weighted irradiance values.

    ``X`` (e-/s, > 0) are the evaluation points (darkest and brightest pixel of each
    non-empty log-irradiance bin), ``weight`` the number of pixels each stands for,
    ``n_pixels`` the scene's size and ``n_nosignal`` the pixels with X <= 0.
    """

    X: np.ndarray
    weight: np.ndarray
    n_pixels: int
    n_nosignal: int


def irradiance_histogram(irradiance: ArrayLike, bins: int = 256) -> IrradianceHistogram:
    """Weighted histogram of log10(irradiance) over the pixels with X > 0.

    Parameters
    ----------
    irradiance : array_like
        Irradiance map or sample, e-/s per photosite.
    bins : int
        Number of log-irradiance bins.

    Returns
    -------
    IrradianceHistogram

    Raises
    ------
    InputError
        An empty map or NaN or infinite values.
    """
    x = np.asarray(irradiance, dtype=np.float64).ravel()
    if x.size == 0:
        raise InputError("the irradiance map is empty")
    # In blocks (cache-sized temporaries instead of a dozen full-size ones): first log10 of the
    # positive values, stored in order, then the bins; the same numbers as on the whole array
    lx = np.empty(x.size)
    n_pos = 0
    for xb in flat_blocks(x, _HIST_BLOCK):
        if not np.isfinite(xb).all():
            raise InputError("the irradiance map holds NaN or infinite values")
        pb = xb[xb > 0]
        np.log10(pb, out=lx[n_pos : n_pos + pb.size])
        n_pos += pb.size
    n_nosignal = int(x.size - n_pos)
    if n_pos == 0:
        return IrradianceHistogram(np.zeros(0), np.zeros(0), int(x.size), n_nosignal)
    lx = lx[:n_pos]
    lo, hi = lx.min(), lx.max()
    if hi - lo < 1e-9:
        first = next(xb[xb > 0][0] for xb in flat_blocks(x, _HIST_BLOCK) if (xb > 0).any())
        return IrradianceHistogram(np.array([first]), np.array([float(n_pos)]), int(x.size), n_nosignal)
    count = np.zeros(bins, dtype=np.int64)
    bmin = np.full(bins, np.inf)
    bmax = np.full(bins, -np.inf)
    done = 0
    for xb in flat_blocks(x, _HIST_BLOCK):
        pb = xb[xb > 0]
        lb = lx[done : done + pb.size]
        done += pb.size
        idx = ((lb - lo) / (hi - lo) * bins).astype(np.int64)
        np.minimum(idx, bins - 1, out=idx)
        count += np.bincount(idx, minlength=bins)
        np.minimum.at(bmin, idx, pb)
        np.maximum.at(bmax, idx, pb)
    count = count.astype(np.float64)
    keep = count > 0
    count, bmin, bmax = count[keep], bmin[keep], bmax[keep]
    single = bmin == bmax
    X = np.concatenate([bmin, bmax[~single]])
    w = np.concatenate([np.where(single, count, count / 2), count[~single] / 2])
    order = np.argsort(X, kind="stable")
    return IrradianceHistogram(X[order], w[order], int(x.size), n_nosignal)


#: Elements per block of :func:`irradiance_histogram`'s passes.
_HIST_BLOCK = 1 << 18


@dataclass
class Plan:
    """An exposure plan: what to capture, how to subtract the dark signal, how to merge.

    Attributes
    ----------
    exposures : list of float
        Exposure times, s, in capture order (the greedy's order: most useful first).
    darks : list of str
        Dark strategy per exposure: "matched" (take a dark frame of the same time), "master"
        (master dark from the library) or "model" (bias + calibrated dark current).
    predicted_min_snr_db : float
        Predicted SNR, dB, reached by the chosen quantile of eligible pixels (the minimum over
        them for quantile 1).
    total_time_s : float
        Exposure time of frames and matched dark frames plus the per-frame overhead, s.
    decisions : dict
        name -> {"choice", "reason", "figure"}: dark strategy, PRNU, saturation, iterations,
        eligibility.
    feasible : bool
        Whether the target holds at the quantile.
    message : str
        One paragraph for people: what was planned, what could not be, best figure.
    target_snr_db, quantile : float
        The request.
    n_dark : list of int
        Dark frames behind each exposure's dark subtraction: 1 for "matched" (one dark frame
        captured right after it), the frame count of the library's master dark for "master",
        0 for "model".
    curve : dict
        Predicted SNR curve: ``irradiance`` (e-/s), ``snr_db``, ``weight`` (pixels),
        ``eligible`` (bool) of the histogram points.
    saturation_sigmas : float
        Margin of the near-saturation rule the plan assumed (standard deviations of the raw
        value); the merge must use the same.
    overhead_s : float
        Per-frame overhead the plan counted, s.
    """

    exposures: list[float]
    darks: list[str]
    predicted_min_snr_db: float
    total_time_s: float
    decisions: dict[str, dict[str, Any]]
    feasible: bool
    message: str
    target_snr_db: float = float("nan")
    quantile: float = 1.0
    n_dark: list[int] = field(default_factory=list)
    curve: dict[str, list] = field(default_factory=dict)
    saturation_sigmas: float = K_SIGMA
    overhead_s: float = 0.0

    def merge_options(self) -> dict[str, Any]:
        """Keyword options for ``pipeline.merge.accumulator.merge_arrays`` (fields of ``MergeOptions``)
        that apply the decisions: ``iterations``, ``saturation`` ("threshold" |
        "probabilistic"), ``saturation_sigmas`` (the margin the plan assumed), ``prnu``
        ("map" | "scalar"); and, only when every exposure has the same dark strategy,
        ``dark_strategy`` (plus ``n_dark`` when that is "master" with one frame count). The
        per-exposure strategies and frame counts are :attr:`darks` and :attr:`n_dark`.

        Returns
        -------
        dict
            Keyword options of the merge.
        """
        from hdrcap.pipeline.planfile import decided_merge_options

        return decided_merge_options(self.decisions, list(self.darks), list(self.n_dark), self.saturation_sigmas)

    def explain(self) -> str:
        """The message and each model decision with the figure that drove it, one per line.

        Returns
        -------
        str
            Text for people (``hdrcap plan --explain``).
        """
        lines = [self.message, "decisions:"]
        for name, d in self.decisions.items():
            fig = d.get("figure")
            if isinstance(fig, float):
                fig = f"{fig:.4g}"
            lines.append(f"  {name}: {d['choice']}  [{fig} {d.get('unit', '')}]".rstrip())
            lines.append(f"      {d['reason']}")
        return "\n".join(lines)

    def to_dict(self, curve: bool = False) -> dict[str, Any]:
        """The plan as JSON-ready data (the schema of ``hdrcap plan --json``, docs/planner.md).

        Parameters
        ----------
        curve : bool
            Include the predicted SNR curve.

        Returns
        -------
        dict
        """
        out = {
            "exposures": list(self.exposures),
            "darks": list(self.darks),
            "n_dark": [int(n) for n in self.n_dark],
            "predicted_min_snr_db": _finite(self.predicted_min_snr_db),
            "total_time_s": self.total_time_s,
            "target_snr_db": self.target_snr_db,
            "quantile": self.quantile,
            "feasible": self.feasible,
            "message": self.message,
            "decisions": self.decisions,
            "merge_options": self.merge_options(),
            "overhead_s": float(self.overhead_s),
        }
        if curve:
            out["curve"] = self.curve
        return out


def _finite(v: float):
    return float(v) if np.isfinite(v) else None


# --------------------------------------------------------------------------- context


class _Context:
    """Everything the search needs, precomputed per candidate time on the histogram."""

    def __init__(
        self, calibration, hist, target_db, candidates, darks, n_dark, overhead, errors, prnu, quantile, k_sigma
    ):
        self.cal = calibration
        self.hist = hist
        self.target_db = float(target_db)
        self.cand = np.asarray(candidates, dtype=np.float64)
        self.darks = list(darks)
        self.n_dark = list(n_dark)
        self.overhead = float(overhead)
        self.errors = errors
        self.prnu = prnu
        self.quantile = float(quantile)
        X = hist.X
        self.X = X
        self.elig = eligible_mask(X, self.cand.min(), calibration, k_sigma)
        self.w_elig = np.where(self.elig, hist.weight, 0.0)
        terms = [
            exposure_terms(X, t, calibration, d, n or 1, "threshold", k_sigma)
            for t, d, n in zip(self.cand, self.darks, self.n_dark)
        ]
        self.W = np.array([tm.weight for tm in terms])
        self.CD = np.array([tm.c_dark for tm in terms])
        self.CB = np.array([tm.c_bias for tm in terms])
        self.k_sigma = k_sigma
        self.frame_time = self.cand + self.overhead
        self.cost_time = np.array(
            [(t + self.overhead) * (2.0 if d == "matched" else 1.0) for t, d in zip(self.cand, self.darks)]
        )
        self._groups: dict[tuple[int, int], Any] = {}
        # candidates of one exposure time with another dark strategy: a plan gives each time
        # one strategy (the merge matches frames to the plan by exposure time)
        self.rival = np.array(
            [
                [same_exposure(a, b) and da != db for b, db in zip(self.cand, self.darks)]
                for a, da in zip(self.cand, self.darks)
            ],
            dtype=bool,
        ).reshape(len(self.cand), -1)

    def excluded(self, idx) -> np.ndarray:
        """Candidates that would give an exposure time of ``idx`` a second dark strategy."""
        out = np.zeros(len(self.cand), bool)
        for i in idx:
            out |= self.rival[i]
        return out

    def _weight(self, i: int, m: int) -> np.ndarray:
        """Summed weight of ``m`` copies of candidate ``i`` (one shared dark frame, or one
        master dark, when its strategy takes one: :func:`planner.predict.exposure_terms`)."""
        if m == 1 or self.darks[i] == "model":
            return m * self.W[i]
        key = (i, m)
        if key not in self._groups:
            term = exposure_terms(
                self.X, self.cand[i], self.cal, self.darks[i], self.n_dark[i] or 1, "threshold", self.k_sigma, copies=m
            )
            self._groups[key] = m * term.weight
        return self._groups[key]

    def sums(self, idx):
        idx = list(idx)
        if not idx:
            z = np.zeros_like(self.X)
            return z, z.copy(), z.copy()
        counts = Counter(idx)
        sw = sum(self._weight(i, m) for i, m in counts.items())
        return sw, self.CD[idx].sum(0), self.CB[idx].sum(0)

    def snr(self, sw, scd, scb):
        return combine_terms(self.X, sw, scd, scb, self.errors, self.prnu).snr

    def quantile_db(self, snr_lin) -> float:
        """SNR (dB) reached by the ``quantile`` fraction of eligible pixels."""
        w = self.w_elig
        total = w.sum()
        if total <= 0:
            return float("nan")
        db = to_db(snr_lin)
        order = np.argsort(db, kind="stable")
        cw = np.cumsum(w[order]) / total
        k = int(np.searchsorted(cw, 1.0 - self.quantile + 1e-12, side="right"))
        k = min(k, len(order) - 1)
        # the pixel at cumulative fraction just above 1 - quantile
        return float(db[order][k]) if self.quantile < 1 else float(db[self.elig].min())

    def reached(self, snr_lin) -> bool:
        return self.quantile_db(snr_lin) >= self.target_db - 1e-9

    def penalty(self, snr_lin) -> float:
        """Eq. 18 in the log domain: log of the sum over eligible pixels of Q(snr) = exp(-snr)
        (:func:`log_penalty`; exp(-snr) itself underflows above snr = 745, 57.4 dB)."""
        return float(log_penalty(self.w_elig, snr_lin))

    def marginal(self, idx) -> tuple[np.ndarray, np.ndarray]:
        """What adding one more of each candidate to ``idx`` adds: its weight (C, bins; a copy
        of a time already chosen adds to its shared-dark group) and its capture time (C,), s."""
        counts = Counter(idx)
        add_w = self.W.copy()
        add_cost = self.cost_time.copy()
        for i, m in counts.items():
            add_w[i] = self._weight(i, m + 1) - self._weight(i, m)
            add_cost[i] = self.frame_time[i]
        return add_w, add_cost

    def time(self, idx) -> float:
        """Capture time of the exposures ``idx`` (repeats allowed), s: each frame's time plus the
        overhead, and one matched dark frame per candidate time, counted once."""
        counts = Counter(idx)
        return float(sum(m * self.frame_time[i] + (self.cost_time[i] - self.frame_time[i]) for i, m in counts.items()))


def eligible_mask(X: ArrayLike, t_min: float, calibration: Calibration, k_sigma: float = K_SIGMA) -> np.ndarray:
    """Pixels with signal that are usable (not predicted saturated) at the shortest time.

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s.
    t_min : float
        Shortest allowed exposure time, s.
    calibration : Calibration
        Camera model.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.

    Returns
    -------
    numpy.ndarray
        Boolean mask.
    """
    X = np.asarray(X, dtype=np.float64)

    def usable(x):
        return (x > 0) & (usable_fraction(x, t_min, calibration, "threshold", k_sigma) > 0)

    if X.size < _ELIGIBLE_DIRECT or not k_sigma >= 0:  # a negative margin need not be monotone in X
        return usable(X)
    # The rule is monotone in X (the predicted value and its sigma both grow with X): find its
    # limit by bisection, compare, and evaluate the rule itself only in a narrow band around the
    # limit, where rounding could decide (the same mask, without full-size float64 temporaries)
    lo, hi = _usable_limit(usable)
    if lo is None:
        return usable(X)
    out = (X > 0) & (X < lo)
    band = np.flatnonzero((X >= lo) & (X <= hi))
    out.flat[band] = usable(X.flat[band])
    return out


#: Maps smaller than this (elements) take :func:`eligible_mask`'s rule directly.
_ELIGIBLE_DIRECT = 1 << 16


def _usable_limit(usable) -> tuple[float | None, float | None]:
    """A band [lo, hi] of irradiance around the limit of the monotone rule ``usable`` (true
    below, false above), 1e-9 relative wide on each side; (None, None) where it has no finite
    positive limit to find this way (usable nowhere or everywhere up to 1e300)."""
    below, above = 1e-300, 1.0
    if not usable(np.array([below]))[0]:
        return None, None
    while usable(np.array([above]))[0]:
        below, above = above, above * 1e3
        if above > 1e300:
            return None, None
    for _ in range(200):  # geometric bisection: 1e-12 relative in well under 200 steps
        if above <= below * (1.0 + 1e-12):
            break
        mid = np.sqrt(below * above)
        if usable(np.array([mid]))[0]:
            below = mid
        else:
            above = mid
    return below * (1.0 - 1e-9), above * (1.0 + 1e-9)


def bulk_irradiance(
    irradiance: ArrayLike,
    t_min: float,
    calibration: Calibration,
    highlight_fraction: float = DEFAULT_HIGHLIGHT_FRACTION,
    k_sigma: float = K_SIGMA,
) -> float | None:
    """Brightest irradiance of the scene's bulk, e-/s (Sec. 8).

    The eligible pixels are those with signal that are not saturated at the shortest allowed
    time ``t_min`` (:func:`eligible_mask`); the bulk is all of them but the brightest
    ``floor(highlight_fraction * N)`` (N = number of eligible pixels). Saturation is monotone in
    the irradiance, so an exposure saturates at most that fraction of the eligible pixels exactly
    when it does not saturate the returned value. None when no pixel is eligible.

    Parameters
    ----------
    irradiance : array_like
        Irradiance map or sample, e-/s.
    t_min : float
        Shortest allowed exposure time, s.
    calibration : Calibration
        Camera model.
    highlight_fraction : float
        Fraction of the eligible pixels left out as highlights.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.

    Returns
    -------
    float or None
        The bulk's brightest irradiance, e-/s.
    """
    x = np.asarray(irradiance, dtype=np.float64).ravel()
    x = x[eligible_mask(x, t_min, calibration, k_sigma)]
    if x.size == 0:
        return None
    n_allow = int(np.floor(float(highlight_fraction) * x.size + 1e-9))
    k = x.size - 1 - min(n_allow, x.size - 1)  # ascending rank of the (n_allow + 1)-th brightest
    return float(np.partition(x, k)[k])


def first_exposure(x_bulk: float, times: Sequence[float], calibration: Calibration, k_sigma: float = K_SIGMA) -> float:
    """The first exposure of a plan: the longest of ``times`` that does not saturate ``x_bulk``
    (e-/s) under the merge's near-saturation rule (Eq. 11 extended: the predicted value plus
    ``k_sigma`` of its own standard deviation stays below v_sat); the shortest time when none does.

    Parameters
    ----------
    x_bulk : float
        Brightest irradiance of the bulk, e-/s (:func:`bulk_irradiance`).
    times : sequence of float
        Allowed exposure times, s.
    calibration : Calibration
        Camera model.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.

    Returns
    -------
    float
        The first exposure time, s.
    """
    times = sorted(float(t) for t in times)
    ok = [t for t in times if usable_fraction(x_bulk, t, calibration, "threshold", k_sigma) > 0]
    return ok[-1] if ok else times[0]


# --------------------------------------------------------------------------- validation


def _check_request(target_snr_db, allowed_times, max_exposures, time_budget, overhead, quantile):
    if not np.isfinite(target_snr_db):
        raise InputError(f"target SNR must be a finite number of dB, got {target_snr_db!r}")
    times = sorted(unique_exposures(float(t) for t in allowed_times))
    if not times:
        raise InputError("no allowed exposure times")
    if any(not (np.isfinite(t) and t > 0) for t in times):
        raise InputError(f"allowed exposure times must be positive seconds, got {allowed_times!r}")
    if max_exposures is not None and int(max_exposures) < 1:
        raise InputError(f"max exposures must be >= 1, got {max_exposures!r}")
    if time_budget is not None and not (np.isfinite(time_budget) and time_budget > 0):
        raise InputError(f"time budget must be a positive number of seconds, got {time_budget!r}")
    if not (np.isfinite(overhead) and overhead >= 0):
        raise InputError(f"per-frame overhead must be >= 0 s, got {overhead!r}")
    if quantile is not None and not (0 < quantile <= 1):
        raise InputError(f"quantile must be in (0, 1], got {quantile!r}")
    return times


def _library_n(dark_library: Mapping[float, int] | None, t: float) -> int:
    """Frame count of the library's master dark for exposure time ``t`` (s); 0 when there is none."""
    if not dark_library:
        return 0
    keys = list(dark_library)
    i = find_exposure(t, keys)
    return 0 if i is None else int(dark_library[keys[i]])


# --------------------------------------------------------------------------- planning


def plan_exposures(
    calibration: Calibration,
    irradiance: ArrayLike,
    target_snr_db: float,
    allowed_times: Sequence[float] | None = None,
    *,
    max_exposures: int | None = None,
    time_budget: float | None = None,
    overhead: float = DEFAULT_OVERHEAD_S,
    quantile: float | None = None,
    errors: SystematicErrors | None = None,
    dark_library: Mapping[float, int] | None = None,
    tolerance_db: float = 0.2,
    k_sigma: float = K_SIGMA,
    bins: int = 256,
    polish: bool = True,
    uniform_darks: bool = False,
    highlight_fraction: float = DEFAULT_HIGHLIGHT_FRACTION,
    bulk_first: bool = True,
) -> Plan:
    """Plan the exposures that reach ``target_snr_db`` on a scene (Eq. 18, Sec. 8).

    Parameters
    ----------
    calibration : Calibration
        Camera model.
    irradiance : array_like
        Irradiance map (or any sample of pixel irradiances), e-/s per photosite.
    target_snr_db : float
        Required SNR of the merged estimate, dB (20 log10).
    allowed_times : sequence of float, optional
        Exposure times the camera offers, s (default: the 1/3-EV ladder 1/8000..30 s).
    max_exposures : int, optional
        Maximum number of exposures (dark frames not counted).
    time_budget : float, optional
        Maximum total capture time (frames, dark frames, overheads), s.
    overhead : float
        Per-frame overhead (download, shutter latency), s; default :data:`DEFAULT_OVERHEAD_S`.
    quantile : float, optional
        Fraction of eligible pixels that must reach the target (default 1: all pixels that are
        not saturated even at the shortest allowed time).
    errors : SystematicErrors, optional
        Systematic errors of the simpler models (default: from the calibration).
    dark_library : mapping float -> int, optional
        Master darks available in the calibration's library: exposure time (s) -> frame count.
    tolerance_db : float
        A simpler model is chosen when it costs at most this much SNR at every irradiance bin.
    k_sigma : float
        Saturation margin of the threshold rule (standard deviations of the value).
    bins : int
        Number of log-irradiance bins.
    polish : bool
        Drop unneeded and shorten exposures after the greedy phase.
    uniform_darks : bool
        One dark strategy for all exposures (for a merge that takes a single strategy): when
        the per-exposure selection mixes strategies, plan again with dark frames for every
        exposure (master darks when the library has one for every allowed time, else matched).
    highlight_fraction : float
        The first exposure is the longest allowed time that saturates at most this fraction of
        the eligible pixels (:func:`bulk_irradiance`, :func:`first_exposure`); Eq. 18's greedy
        adds the others. It is captured first and never dropped by the polish.
    bulk_first : bool
        Start from that exposure (default). False: Eq. 18's greedy chooses every exposure
        (faster plans when the per-frame overhead is near 0; see docs/planner.md).

    Returns
    -------
    Plan
    """
    times = _check_request(
        target_snr_db,
        allowed_times if allowed_times is not None else THIRD_STOP_LADDER,
        max_exposures,
        time_budget,
        overhead,
        quantile,
    )
    if not (np.isfinite(highlight_fraction) and 0 <= highlight_fraction < 1):
        raise InputError(f"highlight fraction must be in [0, 1), got {highlight_fraction!r}")
    q = 1.0 if quantile is None else float(quantile)
    errors = errors if errors is not None else systematic_errors_from_calibration(calibration)
    hist = irradiance_histogram(irradiance, bins)
    elig = eligible_mask(hist.X, times[0], calibration, k_sigma) if hist.X.size else np.zeros(0, bool)
    decisions: dict[str, dict[str, Any]] = {
        "eligibility": select.eligibility_decision(hist, elig, times[0], calibration)
    }
    if not elig.any():
        msg = decisions["eligibility"]["reason"] + "; nothing to plan"
        return Plan(
            [],
            [],
            float("nan"),
            0.0,
            decisions,
            False,
            msg,
            float(target_snr_db),
            q,
            [],
            {},
            float(k_sigma),
            float(overhead),
        )

    # 1. model selection before planning: PRNU model and each allowed time's dark strategy
    Xe = hist.X[elig]
    target_lin = 10.0 ** (target_snr_db / 20.0)
    decisions["prnu"] = select.prnu_decision(errors, target_lin, calibration, tolerance_db)
    t_best = select.longest_usable_time(Xe, times, calibration, k_sigma)
    dark_choice = [
        select.dark_decision_for_time(
            Xe, t, calibration, errors, target_lin, _library_n(dark_library, t), overhead, tolerance_db, k_sigma, t_best
        )
        for t in times
    ]
    if uniform_darks:
        _force_one_dark_strategy(dark_choice, times, dark_library)
    cand_t, cand_dec = _candidates(times, dark_choice, uniform_darks)
    darks = [d["choice"] for d in cand_dec]
    ctx = _Context(
        calibration,
        hist,
        target_snr_db,
        cand_t,
        darks,
        _dark_counts(cand_t, darks, dark_library),
        overhead,
        errors,
        decisions["prnu"]["choice"],
        q,
        k_sigma,
    )
    # 2. the first exposure: the longest that does not saturate the scene's bulk (Sec. 8)
    x_bulk = bulk_irradiance(irradiance, times[0], calibration, highlight_fraction, k_sigma)
    assert x_bulk is not None  # hist.X are pixel values (the bins' extremes), some eligible
    t_first = first_exposure(x_bulk, times, calibration, k_sigma)
    t_seed, seeds = _seeds(ctx, t_first, time_budget, bulk_first)
    # 3. Eq. 18's greedy from each seed, polished; 4. the models of the merge
    chosen, limit, ok = _search(ctx, seeds, _exposure_cap(max_exposures, time_budget), time_budget, polish)
    if bulk_first:
        decisions["first_exposure"] = _first_decision(x_bulk, highlight_fraction, t_first, t_seed, ctx, k_sigma)
    decisions["dark_strategy"] = select.summarise_dark_decisions(
        [cand_dec[i] for i in chosen], [float(ctx.cand[i]) for i in chosen]
    )
    if chosen:
        decisions.update(_merge_model_decisions(ctx, chosen, tolerance_db, k_sigma))
    return _make_plan(ctx, chosen, ok, limit, decisions, max_exposures, time_budget, k_sigma)


def _exposure_cap(max_exposures: int | None, time_budget: float | None) -> int:
    """Most exposures the search may choose: the request's limit, else a default unless a budget limits."""
    if max_exposures is not None:
        return int(max_exposures)
    return DEFAULT_MAX_EXPOSURES if time_budget is None else 10**6


def _force_one_dark_strategy(
    dark_choice: list[dict], times: Sequence[float], dark_library: Mapping[float, int] | None
) -> None:
    """When the per-exposure decisions mix strategies, give every time dark frames (master darks
    when the library has one for every time, else matched); the decisions are changed in place."""
    if len({d["choice"] for d in dark_choice}) <= 1:
        return
    forced = "master" if all(_library_n(dark_library, t) for t in times) else "matched"
    for d in dark_choice:
        if d["choice"] != forced:
            d["reason"] = f"{forced} (one strategy for all exposures was asked; alone: {d['choice']})"
            d["choice"] = forced


def _candidates(times: Sequence[float], dark_choice: list[dict], uniform_darks: bool) -> tuple[list[float], list[dict]]:
    """Candidates of the search: each allowed time with its decided dark strategy and, where that
    is a dark frame, also without one.

    The greedy then pays for a dark frame only when the SNR it buys is cheaper in capture time
    than more exposures (the systematic error of the dark model is part of the predicted SNR, so
    the target still holds).
    """
    cand_t, cand_dec = [], []
    for t, dec in zip(times, dark_choice):
        if dec["choice"] != "model" and not uniform_darks:
            cand_t.append(t)
            cand_dec.append(
                {
                    **dec,
                    "choice": "model",
                    "reason": (
                        f"no dark frame: the dark model costs {dec['figure']:.3f} dB at the target, yet the plan reaches the "
                        f"target for less capture time without it (the alternative: {dec['choice']})"
                    ),
                }
            )
        cand_t.append(t)
        cand_dec.append(dec)
    return cand_t, cand_dec


def _dark_counts(cand_t: Sequence[float], darks: Sequence[str], dark_library: Mapping[float, int] | None) -> list[int]:
    """Dark frames behind each candidate's dark subtraction (master: the library's count)."""
    return [
        _library_n(dark_library, t) if d == "master" else (1 if d == "matched" else 0) for t, d in zip(cand_t, darks)
    ]


def _seeds(
    ctx: _Context, t_first: float, time_budget: float | None, bulk_first: bool
) -> tuple[float | None, list[list[int]]]:
    """The seed of the search: the bulk exposure (with and without a dark frame when both are
    candidates); a time budget too small for it moves it down the ladder. Returns the seed time
    (None when nothing fits) and the seeds (candidate indices; one empty seed without bulk_first)."""
    cand_t = ctx.cand
    fits = [i for i in range(len(cand_t)) if time_budget is None or ctx.cost_time[i] <= time_budget * (1 + 1e-12)]
    t_seed = max((float(cand_t[i]) for i in fits if cand_t[i] <= t_first), default=None)
    if not bulk_first or t_seed is None:
        return t_seed, [[]]
    return t_seed, [[i] for i in fits if same_exposure(cand_t[i], t_seed)]


def _search(
    ctx: _Context, seeds: list[list[int]], cap: int, time_budget: float | None, polish: bool
) -> tuple[list[int], str, bool]:
    """Eq. 18's greedy from each seed, and the same per second of capture time; the fastest
    feasible plan wins, else the one with the least penalty. Returns the chosen candidates, why
    the search stopped short ("" when the target holds) and whether it holds."""
    runs = []
    for seed in seeds:
        for per_second in (False, True) if polish else (False,):
            chosen, limit = _greedy(ctx, cap, time_budget, per_second, seed)
            ok = bool(chosen) and ctx.reached(ctx.snr(*ctx.sums(chosen)))
            if ok and polish:
                chosen = _capture_order(ctx, _polish(ctx, chosen, len(seed)), len(seed))
            score = ctx.time(chosen) if ok else ctx.penalty(ctx.snr(*ctx.sums(chosen)))
            runs.append((not ok, score, chosen, limit, ok))
    runs.sort(key=lambda r: (r[0], r[1]))
    _, _, chosen, limit, ok = runs[0]
    return chosen, limit, ok


def _merge_model_decisions(ctx: _Context, chosen: list[int], tolerance_db: float, k_sigma: float) -> dict:
    """The saturation model and the merge iterations the chosen sequence needs."""
    exposures = [float(ctx.cand[i]) for i in chosen]
    darks = [ctx.darks[i] for i in chosen]
    n_dark = [ctx.n_dark[i] for i in chosen]
    Xe = ctx.X[ctx.elig]
    saturation = select.saturation_decision(
        Xe, exposures, darks, n_dark, ctx.cal, ctx.errors, ctx.prnu, tolerance_db, k_sigma
    )
    iterations = select.iterations_decision(
        Xe, exposures, darks, n_dark, ctx.cal, ctx.errors, ctx.prnu, tolerance_db, k_sigma, saturation["choice"]
    )
    return {"saturation": saturation, "iterations": iterations}


def _make_plan(
    ctx: _Context,
    chosen: list[int],
    ok: bool,
    limit: str,
    decisions: dict,
    max_exposures: int | None,
    time_budget: float | None,
    k_sigma: float,
) -> Plan:
    """The :class:`Plan` of the chosen candidates: predicted figures, message and SNR curve."""
    snr_lin = ctx.snr(*ctx.sums(chosen))
    plan_darks = [ctx.darks[i] for i in chosen]
    min_db = ctx.quantile_db(snr_lin) if chosen else float("-inf")
    total = ctx.time(chosen)
    msg = _message(
        ok,
        ctx.target_db,
        ctx.quantile,
        min_db,
        chosen,
        plan_darks,
        total,
        limit,
        decisions,
        max_exposures,
        time_budget,
        ctx,
    )
    curve = {
        "irradiance": ctx.hist.X.tolist(),
        "snr_db": [_finite(v) for v in to_db(snr_lin)],
        "weight": ctx.hist.weight.tolist(),
        "eligible": ctx.elig.tolist(),
    }
    return Plan(
        [float(ctx.cand[i]) for i in chosen],
        plan_darks,
        float(min_db),
        float(total),
        decisions,
        ok,
        msg,
        ctx.target_db,
        ctx.quantile,
        [ctx.n_dark[i] for i in chosen],
        curve,
        float(k_sigma),
        float(ctx.overhead),
    )


def log_penalty(weights: ArrayLike, snr_lin: ArrayLike, axis: int = -1) -> np.ndarray | float:
    """log sum_j w_j exp(-snr_j) (Eq. 18) by log-sum-exp: finite for any SNR (the direct sum
    underflows to 0 above snr = 745, 57.4 dB, and every plan then looks equally good).

    Parameters
    ----------
    weights : array_like
        Histogram weight of each eligible irradiance bin (0: not eligible), >= 0.
    snr_lin : array_like
        Linear SNR per bin, broadcast with ``weights``.
    axis : int
        Axis of the bins.

    Returns
    -------
    numpy.ndarray or float
        The log penalty; -inf when no bin has weight.
    """
    w = np.asarray(weights, dtype=np.float64)
    snr_lin = np.asarray(snr_lin, dtype=np.float64)
    w, snr_lin = np.broadcast_arrays(w, snr_lin)
    with np.errstate(divide="ignore"):
        return logsumexp(np.where(w > 0, -snr_lin, -np.inf), b=w, axis=axis)


def _greedy(ctx: _Context, cap: int, budget: float | None, per_second: bool = False, seed=()):
    """Eq. 18 greedily: starting from ``seed`` (candidate indices), add the candidate that lowers
    sum exp(-snr) most until the target holds (``per_second``: most per second of capture time),
    comparing the penalties in the log domain (:func:`log_penalty`).

    Returns the chosen candidate indices (in order) and the reason the search stopped when the
    target was not reached ("" when reached).
    """
    chosen: list[int] = [int(i) for i in seed][: max(cap, 0)]
    sw, scd, scb = ctx.sums(chosen)
    current = ctx.penalty(ctx.snr(sw, scd, scb))
    used = ctx.time(chosen)
    while True:
        if chosen and ctx.reached(ctx.snr(sw, scd, scb)):
            return chosen, ""
        if len(chosen) >= cap:
            return chosen, "max_exposures"
        fits = np.ones(len(ctx.cand), bool) if budget is None else used + ctx.cost_time <= budget * (1 + 1e-12)
        fits &= ~ctx.excluded(chosen)
        if not fits.any():
            return chosen, "time_budget"
        # penalty after adding each candidate, all at once: (C, B)
        add_w, add_cost = ctx.marginal(chosen)
        if budget is not None:
            fits &= used + add_cost <= budget * (1 + 1e-12)
        snr_all = combine_terms(ctx.X[None, :], sw + add_w, scd + ctx.CD, scb + ctx.CB, ctx.errors, ctx.prnu).snr
        pen = log_penalty(ctx.w_elig[None, :], snr_all, axis=1)
        pen = np.where(fits, pen, np.inf)
        if per_second:
            # (P_now - P_new) / cost is proportional to -expm1(log P_new - log P_now) / cost
            with np.errstate(invalid="ignore", over="ignore"):
                gain = np.where(fits, -np.expm1(pen - current) / add_cost, -np.inf)
            best = int(np.argmax(gain))
        else:
            best = int(np.argmin(pen))  # ties: the shorter time (candidates ascend)
        if not pen[best] < current + math.log1p(-1e-12):
            return chosen, "no_gain"
        chosen.append(best)
        used += add_cost[best]
        sw, scd, scb = sw + add_w[best], scd + ctx.CD[best], scb + ctx.CB[best]
        current = float(pen[best])


def _capture_order(ctx: _Context, chosen: list[int], n_fixed: int = 0) -> list[int]:
    """The first ``n_fixed`` as they are, then most useful first: repeatedly the exposure of the
    set that lowers sum exp(-snr) most."""
    rest = list(chosen[n_fixed:])
    order: list[int] = list(chosen[:n_fixed])
    while rest:
        pens = [ctx.penalty(ctx.snr(*ctx.sums(order + [c]))) for c in rest]
        k = min(range(len(rest)), key=lambda i: (pens[i], ctx.cost_time[rest[i]]))
        order.append(rest.pop(k))
    return order


def _drop_unneeded(ctx: _Context, chosen: list[int], n_fixed: int = 0) -> list[int]:
    """Remove exposures (longest first, never the first ``n_fixed``) whose absence still meets
    the target."""
    kept: list[int | None] = list(chosen)
    for pos in sorted(range(n_fixed, len(chosen)), key=lambda k: -ctx.cost_time[chosen[k]]):
        rest = [c for k, c in enumerate(kept) if k != pos and c is not None]
        if rest and ctx.reached(ctx.snr(*ctx.sums(rest))):
            kept[pos] = None
    return [c for c in kept if c is not None]


def _polish(ctx: _Context, chosen: list[int], n_fixed: int = 0) -> list[int]:
    """Local search after the greedy: drop exposures the target does not need, then replace
    each (longest first) by one shorter exposure or by 2-4 copies of a shorter one whenever that
    costs less time and the target still holds. The first ``n_fixed`` stay as they are."""
    chosen = _drop_unneeded(ctx, chosen, n_fixed)
    order = np.argsort(ctx.cost_time, kind="stable")
    for _ in range(6):
        changed = False
        for pos in sorted(range(n_fixed, len(chosen)), key=lambda k: -ctx.cost_time[chosen[k]]):
            if pos >= len(chosen):
                continue
            base = chosen[:pos] + chosen[pos + 1 :]
            cost = ctx.time(chosen) - ctx.time(base)
            # replace it by the cheapest valid alternative: one shorter exposure, or 2..4 copies
            # of a shorter one when that saves at least 10 % of its time
            found, found_cost = None, cost * (1 - 1e-9)
            excluded = ctx.excluded(base)
            for c in order:
                if ctx.cost_time[c] >= found_cost:
                    break
                if excluded[c]:
                    continue
                for k in (1, 2, 3, 4):
                    new_cost = ctx.time(base + [int(c)] * k) - ctx.time(base)
                    if new_cost >= found_cost or (k > 1 and new_cost > 0.9 * cost):
                        break
                    trial = base[:pos] + [int(c)] * k + base[pos:]
                    if ctx.reached(ctx.snr(*ctx.sums(trial))):
                        found, found_cost = trial, new_cost
                        break
            if found is not None:
                chosen = found
                changed = True
        if not changed:
            break
    return _drop_unneeded(ctx, chosen, n_fixed)


def _first_decision(x_bulk, highlight_fraction, t_first, t_seed, ctx: _Context, k_sigma) -> dict:
    """The first exposure and the figure behind it (the bulk's brightest irradiance)."""
    unit = "e-/s, brightest irradiance of the bulk"
    if t_seed is None:
        return {"choice": None, "reason": "no allowed time fits the time budget", "figure": x_bulk, "unit": unit}
    sat = ctx.elig & (usable_fraction(ctx.X, t_seed, ctx.cal, "threshold", k_sigma) == 0)
    frac = float(ctx.w_elig[sat].sum() / max(ctx.w_elig.sum(), 1e-300))
    why = (
        f"{_fmt_t(t_first)}: the longest allowed time that does not saturate the bulk (all eligible pixels but "
        f"the brightest {100 * highlight_fraction:g} %, up to {x_bulk:.4g} e-/s; {k_sigma:g} sigma margin)"
    )
    if t_seed != t_first:
        why = f"{_fmt_t(t_seed)}, the longest that fits the time budget; wanted " + why
    why += f"; it saturates about {100 * frac:.3g} % of the eligible pixels"
    return {"choice": float(t_seed), "reason": why, "figure": x_bulk, "unit": unit}


def _fmt_t(t: float) -> str:
    return f"1/{1 / t:.0f} s" if t < 0.25 else f"{t:g} s"


def _message(ok, target, q, min_db, chosen, darks, total, limit, decisions, max_exposures, budget, ctx):
    exposures = [float(ctx.cand[i]) for i in chosen]
    where = "all eligible pixels" if q >= 1 else f"{100 * q:g} % of eligible pixels"
    n_m = sum(d == "matched" for d in darks)
    seq = ", ".join(_fmt_t(t) for t in exposures)
    parts = []
    if ok:
        parts.append(
            f"{len(exposures)} exposures ({seq}) plus {n_m} matched dark frames reach {target:g} dB "
            f"on {where}: "
            f"predicted {min_db:.2f} dB, total capture time {total:.4g} s."
        )
    else:
        why = {
            "max_exposures": f"the limit of {DEFAULT_MAX_EXPOSURES if max_exposures is None else max_exposures} "
            "exposures",
            "time_budget": f"the time budget of {budget:g} s" if budget is not None else "the time budget",
            "no_gain": "the allowed exposure times (no further exposure improves the darkest pixels)",
        }.get(limit, "the constraints")
        best = f"{min_db:.2f} dB" if np.isfinite(min_db) else "nothing"
        parts.append(
            f"INFEASIBLE: target {target:g} dB on {where} cannot be reached within {why}; "
            f"best achievable {best} with {len(exposures)} exposures ({seq or 'none'}), "
            f"total capture time {total:.4g} s."
        )
        failing = ctx.elig & (to_db(ctx.snr(*ctx.sums([]))) < target)
        if exposures:
            snr_now = to_db(ctx.snr(*ctx.sums(chosen)))
            failing = ctx.elig & (snr_now < target)
        if failing.any():
            xs = ctx.X[failing]
            frac = ctx.w_elig[failing].sum() / max(ctx.w_elig.sum(), 1e-300)
            parts.append(
                f"Below target: {100 * frac:.3g} % of eligible pixels, irradiance {xs.min():.4g}..{xs.max():.4g} e-/s."
            )
    elig = decisions.get("eligibility", {})
    if elig.get("figure", 0) and elig["figure"] > 0:
        parts.append(elig["reason"] + ".")
    return " ".join(parts)


# --------------------------------------------------------------------------- references


def plan_exhaustive(
    calibration: Calibration,
    irradiance: ArrayLike,
    target_snr_db: float,
    candidate_times: Sequence[float],
    max_exposures: int,
    *,
    overhead: float = DEFAULT_OVERHEAD_S,
    quantile: float | None = None,
    errors: SystematicErrors | None = None,
    darks: str = "model",
    k_sigma: float = K_SIGMA,
    bins: int = 256,
    first: float | None = None,
) -> tuple[list[float], float] | None:
    """Exhaustive search over all multisets of ``candidate_times`` of size <= ``max_exposures``:
    the sequence with the least total capture time that reaches the target (reference for the
    greedy planner). ``first``: only sequences that hold this time (one of the candidates), as
    the planner's sequences hold the bulk exposure. Returns (times, total_time_s), or None when
    nothing reaches the target.

    Parameters
    ----------
    calibration : Calibration
        Camera model.
    irradiance : array_like
        Irradiance map or sample, e-/s.
    target_snr_db : float
        Required SNR, dB.
    candidate_times : sequence of float
        Exposure times to combine, s.
    max_exposures : int
        Largest sequence.
    overhead : float
        Per-frame overhead, s.
    quantile : float, optional
        Fraction of eligible pixels that must reach the target (default 1).
    errors : SystematicErrors, optional
        Systematic errors (default: none).
    darks : str
        Dark strategy of every exposure.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.
    bins : int
        Number of log-irradiance bins.
    first : float, optional
        A time every sequence holds, s.

    Returns
    -------
    (list of float, float) or None
        The times, s, and the total capture time, s; None when nothing reaches the target.
    """
    times = _check_request(target_snr_db, candidate_times, max_exposures, None, overhead, quantile)
    errors = errors if errors is not None else SystematicErrors()
    hist = irradiance_histogram(irradiance, bins)
    ctx = _Context(
        calibration,
        hist,
        target_snr_db,
        times,
        [darks] * len(times),
        [1] * len(times),
        overhead,
        errors,
        "map",
        1.0 if quantile is None else quantile,
        k_sigma,
    )
    fixed: tuple[int, ...] = ()
    if first is not None:
        fixed = (int(np.argmin(np.abs(np.asarray(times) - float(first)))),)
    best = None
    for n in range(1, int(max_exposures) + 1):
        for rest in itertools.combinations_with_replacement(range(len(times)), n - len(fixed)):
            combo = fixed + rest
            tt = ctx.time(combo)
            if best is not None and tt >= best[1]:
                continue
            if ctx.reached(ctx.snr(*ctx.sums(combo))):
                best = ([float(ctx.cand[i]) for i in combo], tt)
    return best


def plan_bracket(
    calibration: Calibration,
    irradiance: ArrayLike,
    target_snr_db: float,
    step_ev: float,
    allowed_times: Sequence[float] | None = None,
    *,
    overhead: float = DEFAULT_OVERHEAD_S,
    errors: SystematicErrors | None = None,
    darks: str = "model",
    k_sigma: float = K_SIGMA,
    max_frames: int = 400,
    bins: int = 256,
) -> tuple[list[float], float] | None:
    """The naive alternative: a fixed bracket of ``step_ev`` EV steps, long enough to reach the
    target.

    The bracket starts at the longest time that still measures every eligible pixel's bright
    end (nothing eligible saturates) and grows by ``step_ev`` EV until the target holds; when
    even the longest allowed time does not suffice, the whole bracket is repeated. Times are
    the exact powers of two (not snapped to a ladder). Returns (times, total_time_s) with the
    least total time over the bracket lengths tried, or None.

    Parameters
    ----------
    calibration : Calibration
        Camera model.
    irradiance : array_like
        Irradiance map or sample, e-/s.
    target_snr_db : float
        Required SNR, dB.
    step_ev : float
        Bracket step, EV (factor 2^step_ev between times).
    allowed_times : sequence of float, optional
        Allowed exposure times, s (default: the 1/3-EV ladder); the bracket spans their range.
    overhead : float
        Per-frame overhead, s.
    errors : SystematicErrors, optional
        Systematic errors (default: none).
    darks : str
        Dark strategy of every exposure.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.
    max_frames : int
        Most frames of the repeated bracket.
    bins : int
        Number of log-irradiance bins.

    Returns
    -------
    (list of float, float) or None
        The times, s, and the total capture time, s; None when nothing reaches the target.
    """
    allowed = _check_request(
        target_snr_db, allowed_times if allowed_times is not None else THIRD_STOP_LADDER, None, None, overhead, None
    )
    errors = errors if errors is not None else SystematicErrors()
    hist = irradiance_histogram(irradiance, bins)
    t_lo_min, t_hi = allowed[0], allowed[-1]
    elig = eligible_mask(hist.X, t_lo_min, calibration, k_sigma)
    if not elig.any():
        return None
    x_max = hist.X[elig].max()
    # longest time (within the ladder) that does not saturate the brightest eligible pixel
    t0 = max(t for t in allowed if usable_fraction(x_max, t, calibration, "threshold", k_sigma) > 0)
    n_max = int(np.floor(np.log2(t_hi / t0) / step_ev)) + 1
    bracket_all = [t0 * 2.0 ** (step_ev * k) for k in range(max(n_max, 1))]
    ctx = _Context(
        calibration,
        hist,
        target_snr_db,
        bracket_all,
        [darks] * len(bracket_all),
        [1] * len(bracket_all),
        overhead,
        errors,
        "map",
        1.0,
        k_sigma,
    )
    ctx.elig = elig  # eligibility is judged at the ladder's shortest time, as for the plan
    ctx.w_elig = np.where(elig, hist.weight, 0.0)
    best = None
    for n in range(1, len(bracket_all) + 1):
        sw, scd, scb = ctx.sums(range(n))
        t_one = ctx.time(range(n))
        for m in range(1, max_frames // n + 1):
            if best is not None and m * t_one >= best[1]:
                break
            if ctx.reached(ctx.snr(m * sw, m * scd, m * scb)):
                best = (bracket_all[:n] * m, m * t_one)
                break
    return best
