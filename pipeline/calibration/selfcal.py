"""Self-calibration from the bracket: the camera model of a merge without a calibration.

What the files say is taken from their metadata: black level per CFA position, white level,
CFA pattern, exposure time and ISO. What they do not say is estimated from the bracket itself,
from the photosites that are exposed and unsaturated in two frames i < j (times t_i < t_j):

* the exposure ratio r = t_j / t_i (the effective one, shutter errors included) as
  sum (v_j - b) / sum (v_i - b) over those photosites (PRNU cancels: both frames see the same
  photosite);
* the gain g and the readout variance sigma_R^2 by a photon-transfer fit (EMVA 1288 style)
  of the variance of the pair difference d = (v_j - b) - r (v_i - b) against the signal: with
  Var(v) = g m + sigma_R^2 for a signal of m DN above black (Eq. 3),

      Var(d) = g m_j (1 + r) + sigma_R^2 (1 + r^2),

  fitted by weighted least squares over signal bins of every pair, with standard errors.
  Photosites are binned by their signal seen in a third frame of the bracket (the nearest
  longer one where it is unsaturated, else the nearest shorter one), whose noise is
  independent of the pair's: selecting photosites by signal then biases neither the ratio nor
  the variances, whatever the quantisation (a level computed from the pair itself is
  correlated with d on coarsely quantised data). A bracket of two frames bins by the
  combination of its two frames that is uncorrelated with d. Bins where either frame clips
  (at 0 DN or at saturation) are left out.

The fit says what the data support: sigma_R^2 is constrained to at least the quantisation
floor step^2 / 12 (the rounding of a signal dithered by its own noise; the step is 1 DN, or
2^(16 - N) for N-bit data stored MSB-aligned), the weights come from the fitted variance
(bounded by that floor, never from an observed variance near 0), and where the reduced chi^2
exceeds what its degrees of freedom allow (:data:`CHI2_LIMIT_PROBABILITY`) the model does not
describe the data: the stated errors are scaled by sqrt(chi^2 / dof) and a note says so. Where the
gain is not identifiable the merge works in DN per second. No relative standard error is
stated below :data:`MIN_RELATIVE_STDERR`.

PRNU is taken as 1 and dark current as 0 (a dark frame subtracts it where given). The
effective exposure times are the chain of estimated ratios, scaled so that their geometric
mean equals that of the nominal times. The statistical uncertainty of g and of every effective
time is a systematic relative error of the irradiance (Eq. 6: x = (v - b) / (t g)); it is
added to sigma by :func:`calibration_sigma`.

Where the gain cannot be estimated (too few pairs or signal levels, a fit with a relative
error above :data:`MAX_GAIN_RELATIVE_ERROR`), the result says so: the merge then works in DN per
second (g = 1 DN/e- assumed) and its sigma is relative only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.raw import RawFrame, check_frames
from hdrcap.pipeline.params import Calibration, SensorParams
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import UNIT_DN, UNIT_ELECTRONS
from hdrcap.pipeline.times import same_exposure

__all__ = [
    "SELF_CALIBRATED",
    "PairEstimate",
    "SelfCalibration",
    "self_calibration_header",
    "check_bracket",
    "cfa_black_tile",
    "saturation_level",
    "pair_estimate",
    "photon_transfer_fit",
    "estimate_black_level",
    "self_calibrate",
    "calibration_sigma",
    "apply_self_calibration",
]

#: The provenance source of a self-calibration (written in the EXR header).
SELF_CALIBRATED = "self-calibrated from the bracket"

#: Photosites a pair contributes at most (a regular subsample of rows of larger frames).
MAX_PAIR_SAMPLES = 2_000_000

#: Fewest photosites a pair needs for its ratio and its variances (fewer: no overlap).
MIN_PAIR_PHOTOSITES = 200

#: Fewest photosites a signal bin needs to enter the photon-transfer fit.
MIN_BIN_PHOTOSITES = 50

#: Signal bins per pair (logarithmic in the long frame's signal).
BINS_PER_PAIR = 24

#: Upper end of the signals used, as a fraction of the range from black to saturation (EMVA
#: 1288 fits up to 70 %; the long frame's noise must not reach saturation).
MAX_SIGNAL_FRACTION = 0.7

#: Largest relative standard error of the gain for the gain to count as estimated.
MAX_GAIN_RELATIVE_ERROR = 0.2

#: Largest rms relative misfit of the bin variances (beyond their own sampling scatter) for the
#: gain to count as estimated: above it the photon-transfer model misses the variances by so
#: much (a wrong black level gave 18-27 %, a right model 0-2 %) that the fitted slope describes
#: no camera, and scaling its error by sqrt(chi^2) does not make brackets agree.
MAX_MODEL_MISFIT = 0.1

#: Outlier rejection within a signal bin, in robust standard deviations (hot photosites,
#: motion): a Gaussian sample is rejected with probability 2e-9.
CLIP_SIGMAS = 6.0

#: Largest fraction of a bin's photosites that may clip (at 0 DN or at saturation, in either
#: frame) for the bin to enter the fit: clipping truncates the distribution of d.
MAX_CLIPPED_FRACTION = 1e-3

#: A reduced chi^2 above its quantile of this probability (for the fit's degrees of freedom)
#: says the photon-transfer model does not describe the data.
CHI2_LIMIT_PROBABILITY = 0.999

#: Smallest relative standard error stated for any estimate (below it, float rounding of the
#: sums, not the data, would decide).
MIN_RELATIVE_STDERR = 1e-6

#: Effective times further than this many standard errors from the nominal ones differ from them.
TIMES_DIFFER_SIGMAS = 3.0

#: Rounding is dithered (its error uniform, of variance step^2 / 12, and its mean linear) where
#: the signal's own noise has a standard deviation of at least this many quantisation steps
#: (the error's periodic part is then damped by exp(-2 pi^2 0.25) < 1 %); signal bins whose
#: shorter frame is noisier by less are left out of the fit.
DITHER_STEPS = 0.5


@dataclass(frozen=True)
class PairEstimate:
    """What one pair of frames (short i, long j) gives.

    Attributes
    ----------
    short, long : int
        Indices of the frames in the bracket (as given).
    ratio : float
        Effective exposure ratio t_j / t_i (dimensionless); the nominal one without overlap.
    ratio_stderr : float
        Its standard error (0 when nominal).
    n_photosites : int
        Photosites used (exposed and unsaturated in both frames, outliers removed).
    signal : numpy.ndarray
        Mean signal of the long frame per bin, DN above black.
    variance : numpy.ndarray
        Variance of the pair difference d per bin, DN^2.
    count : numpy.ndarray
        Photosites per bin.
    clipped_bins : int
        Bins left out because photosites clip in them (:data:`MAX_CLIPPED_FRACTION`).
    """

    short: int
    long: int
    ratio: float
    ratio_stderr: float
    n_photosites: int
    signal: np.ndarray = field(repr=False)
    variance: np.ndarray = field(repr=False)
    count: np.ndarray = field(repr=False)
    clipped_bins: int = 0

    @property
    def overlap(self) -> bool:
        """Whether the pair had photosites exposed and unsaturated in both frames."""
        return self.n_photosites >= MIN_PAIR_PHOTOSITES


@dataclass(frozen=True)
class SelfCalibration:
    """A camera model estimated from a bracket, with the uncertainty of every estimate.

    Attributes
    ----------
    calibration : Calibration
        The model the merge uses (g, sigma_R^2, black level(s), v_sat, D = 0, PRNU 1).
    effective_times : tuple of float
        Per frame (in the order given), s: the estimated exposure ratios chained, with the
        geometric mean of the nominal times.
    nominal_times : tuple of float
        Per frame, s (file metadata or ``--times``).
    time_relative_stderr : tuple of float
        Per frame, the relative standard error of its effective time (dimensionless).
    gain_known : bool
        Whether g was estimated; False: g = 1 DN/e- is assumed and the irradiance is in DN/s.
    pairs : tuple of PairEstimate
        The pairs of consecutive exposures.
    fit : dict
        The photon-transfer fit: g, sigma2_R, their standard errors (DN/e-, DN^2), reduced
        chi^2, number of bins.
    black_tile : numpy.ndarray
        Black level per 2x2 CFA position, DN.
    notes : tuple of str
        What was assumed (warnings the command line prints).
    quantisation_step : float
        DN between adjacent codes of the frames (the readout variance is at least its square / 12).
    black_source : str
        Where the black level comes from (the files, or estimated from the bracket).
    """

    calibration: Calibration
    effective_times: tuple[float, ...]
    nominal_times: tuple[float, ...]
    time_relative_stderr: tuple[float, ...]
    gain_known: bool
    pairs: tuple[PairEstimate, ...]
    fit: dict[str, Any]
    black_tile: np.ndarray
    notes: tuple[str, ...] = ()
    quantisation_step: float = 1.0
    black_source: str = "file metadata"

    @property
    def unit(self) -> str:
        """The irradiance unit of a merge with this model."""
        if self.gain_known:
            return UNIT_ELECTRONS
        return UNIT_DN

    @property
    def gain_relative_stderr(self) -> float:
        """Relative standard error of g (0 when g is assumed)."""
        return self.fit["g_stderr"] / self.fit["g"] if self.gain_known else 0.0

    def times_match_nominal(self) -> bool:
        """Whether every effective time is the nominal one within the exposure-matching
        tolerance (:func:`pipeline.times.same_exposure`)."""
        return all(same_exposure(a, b) for a, b in zip(self.effective_times, self.nominal_times))

    def times_beyond_errors(self) -> float:
        """The largest distance of an effective time from its nominal one, in its standard
        errors, when above :data:`TIMES_DIFFER_SIGMAS` (else 0: the times agree within their
        errors)."""
        z = max(
            (abs(e / n - 1.0) / max(s, MIN_RELATIVE_STDERR))
            for e, n, s in zip(self.effective_times, self.nominal_times, self.time_relative_stderr)
        )
        return float(z) if z > TIMES_DIFFER_SIGMAS else 0.0

    def header(self) -> dict[str, Any]:
        """The EXR header attribute: every estimated value with its standard error, the fit's
        diagnostics, what was assumed, and the nominal and effective exposure times."""
        p = self.calibration.params
        fit = self.fit
        return {
            "source": SELF_CALIBRATED,
            "gain": {
                "value": p.g,
                "stderr": fit.get("g_stderr"),
                "unit": "DN per electron",
                "estimated": self.gain_known,
                **(
                    {}
                    if self.gain_known
                    else {
                        "not_estimable": fit.get("not_estimable"),
                        "fitted": fit.get("g_fitted"),
                        "fitted_stderr": fit.get("g_fitted_stderr"),
                    }
                ),
            },
            "read_noise_variance": {
                "value": p.sigma2_R,
                "stderr": fit.get("sigma2_R_stderr"),
                "unit": "DN^2",
                "fitted": fit.get("sigma2_R_fitted"),
                "quantisation_floor": fit.get("sigma2_R_floor", self.quantisation_step**2 / 12.0),
                "at_floor": bool(fit.get("constrained", False)) or p.sigma2_R > float(fit.get("sigma2_R", p.sigma2_R)),
            },
            "quantisation_step": self.quantisation_step,
            "photon_transfer_fit": {
                k: fit[k]
                for k in (
                    "reduced_chi2",
                    "dof",
                    "chi2_limit",
                    "model_rejected",
                    "stderr_scale",
                    "relative_misfit",
                    "n_bins",
                    "n_bins_undithered",
                    "n_photosites",
                    "max_weight_ratio",
                )
                if k in fit
            },
            "black_level_per_cfa_position": np.asarray(self.black_tile).tolist(),
            "black_level_source": self.black_source,
            "white_level": p.white_level,
            "saturation_level": p.v_sat,
            "nominal_exposure_times": list(self.nominal_times),
            "effective_exposure_times": list(self.effective_times),
            "effective_time_relative_stderr": list(self.time_relative_stderr),
            "time_scale": "geometric mean of the effective times = that of the nominal times",
            "exposure_ratios": [
                {
                    "short": q.short,
                    "long": q.long,
                    "ratio": q.ratio,
                    "stderr": q.ratio_stderr,
                    "photosites": q.n_photosites,
                    "bins": int(q.count.size),
                    "bins_clipped": q.clipped_bins,
                }
                for q in self.pairs
            ],
            "assumed": {"prnu": 1.0, "dark_current": 0.0},
            "sigma": (
                "includes the statistical uncertainty of the gain and of the effective exposure times"
                if self.gain_known
                else "relative only: computed with an assumed gain of 1 DN/e-, not a measured uncertainty"
            ),
            "notes": list(self.notes),
        }


# ---------------------------------------------------------------------------------- metadata


def check_bracket(frames: Sequence[RawFrame]) -> None:
    """Refuse a bracket whose frames cannot share one self-calibration.

    Parameters
    ----------
    frames : sequence of RawFrame
        The bracket.

    Raises
    ------
    InputError
        Frames of different cameras, sizes, CFA patterns, ISO, or white levels; fewer than two
        frames.
    """
    if len(frames) < 2:
        raise InputError("a merge without a calibration needs at least two frames (the bracket calibrates itself)")
    first = frames[0]
    for fr in frames[1:]:
        for what, a, b in (
            ("camera", first.camera, fr.camera),
            ("CFA pattern", first.cfa_pattern, fr.cfa_pattern),
            ("ISO", first.iso, fr.iso),
            ("white level", first.white_level, fr.white_level),
        ):
            if a != b:
                raise InputError(
                    f"{fr.path}: {what} {b} differs from {first.path}'s ({a}); merge frames of one "
                    "camera and setting, or give --calibration"
                )
        if fr.shape != first.shape:
            raise InputError(
                f"{fr.path}: size {fr.shape[1]}x{fr.shape[0]} differs from {first.path}'s "
                f"({first.shape[1]}x{first.shape[0]})"
            )


def cfa_black_tile(frame: RawFrame) -> np.ndarray:
    """Black level of each position of the 2x2 CFA tile, DN, from the file's metadata.

    Raw files are asked through LibRaw (``black_level_per_channel`` by ``raw_pattern``);
    frames without metadata (PNG/TIFF) give the frame's own black level, or 0.

    Parameters
    ----------
    frame : RawFrame
        A frame of the bracket.

    Returns
    -------
    numpy.ndarray
        float64, shape (2, 2), DN.
    """
    scalar = float(frame.black_level or 0.0)
    tile = np.full((2, 2), scalar)
    if frame.path is None or frame.black_level is None:
        return tile
    try:
        import rawpy

        with rawpy.imread(str(frame.path)) as raw:
            per = np.asarray(raw.black_level_per_channel, float)
            pattern = raw.raw_pattern
            if pattern is not None and np.shape(pattern) == (2, 2) and per.size == 4:
                tile = per[np.asarray(pattern)]
    except Exception:  # noqa: BLE001  (LibRaw cannot open it: the frame's own level)
        pass
    return tile


def _black_rows(tile: np.ndarray, rows: np.ndarray, width: int) -> np.ndarray:
    """The black level (DN) of the photosites in ``rows`` of a frame ``width`` wide."""
    cols = np.arange(width) % 2
    return tile[(rows % 2)[:, None], cols[None, :]]


def saturation_level(
    longest: np.ndarray,
    white_level: float,
    black: float,
    shorter: np.ndarray | None = None,
    ratio: float | None = None,
) -> float:
    """The raw value from which a sample counts as saturated, DN.

    Where the ADC clips first, values pile up at the white level: ``white_level``. Where the
    full well clips first, they pile up below it, spread by the read noise: the pile-up's
    median minus 3 robust standard deviations (Sec. 6: v_sat = mean - 3 std of a saturation
    frame). Without a pile-up, the white level. A peak whose photosites the next shorter frame
    sees at the peak's signal over the exposure ratio is a flat scene, not a pile-up (saturated
    photosites would have had more signal).

    Parameters
    ----------
    longest : numpy.ndarray
        The longest exposure of the bracket (or a subsample), DN.
    white_level : float
        The file's white level, DN.
    black : float
        Mean black level, DN.
    shorter : numpy.ndarray, optional
        The next shorter exposure (same photosites), DN.
    ratio : float, optional
        The exposure ratio of ``longest`` to ``shorter`` (nominal).

    Returns
    -------
    float
        v_sat, DN.
    """
    v = np.asarray(longest).ravel()
    n = v.size
    if n == 0 or np.count_nonzero(v >= white_level - 0.5) >= max(1, 1e-4 * n):
        return float(white_level)
    top = v[v > black + 0.5 * (white_level - black)]
    if top.size < max(20, 1e-4 * n):
        return float(white_level)
    hist, edges = np.histogram(top, bins=256)
    peak = int(np.argmax(hist))
    if hist[peak] < 10 * max(np.median(hist), 1):
        return float(white_level)
    centre = 0.5 * (edges[peak] + edges[peak + 1])
    window = 4 * (edges[1] - edges[0]) + 8
    near = top[np.abs(top - centre) <= window]
    med = float(np.median(near))
    if shorter is not None and ratio:
        there = np.abs(np.asarray(longest).ravel() - centre) <= window
        seen = (float(np.median(np.asarray(shorter).ravel()[there])) - black) * ratio
        if seen < 1.05 * (med - black):  # the shorter frame sees just this signal: a flat scene
            return float(white_level)
    spread = 1.4826 * float(np.median(np.abs(near - med)))
    return float(min(white_level, med - 3.0 * max(spread, 0.5)))


# ---------------------------------------------------------------------------------- pairs


def _row_sample(shape: tuple[int, int], max_samples: int) -> np.ndarray:
    """Rows of a regular subsample of at most ``max_samples`` photosites (an odd step, so that
    both CFA row parities stay)."""
    h, w = shape
    step = max(1, math.ceil(h * w / max_samples))
    step += 1 - step % 2 if step > 1 else 0
    return np.arange(0, h, step)


def _bin_stats(
    level: np.ndarray,
    d: np.ndarray,
    edges: np.ndarray,
    signal: np.ndarray | None = None,
    clipped: np.ndarray | None = None,
) -> tuple[list[tuple[float, float, int]], np.ndarray, int]:
    """Per bin of ``level``: the mean signal (of ``signal``, else of ``level``), the variance of
    ``d`` after outlier rejection, the count; the inlier mask; and the number of bins left out
    because more than :data:`MAX_CLIPPED_FRACTION` of their photosites clip (``clipped``, whose
    photosites never count)."""
    idx = np.digitize(level, edges) - 1
    keep = np.zeros(level.shape, bool)
    rows = []
    n_clipped = 0
    for b in range(len(edges) - 1):
        sel = np.flatnonzero(idx == b)
        if sel.size < MIN_BIN_PHOTOSITES:
            continue
        if clipped is not None:
            bad = clipped[sel]
            if np.mean(bad) > MAX_CLIPPED_FRACTION:
                n_clipped += 1
                continue
            sel = sel[~bad]
        db = d[sel]
        med = np.median(db)
        mad = 1.4826 * np.median(np.abs(db - med))
        ok = np.abs(db - med) <= CLIP_SIGMAS * max(mad, 1e-9) if mad > 0 else np.ones(sel.size, bool)
        good = db[ok]
        if good.size < MIN_BIN_PHOTOSITES:
            continue
        keep[sel[ok]] = True
        m = (signal if signal is not None else level)[sel[ok]]
        rows.append((float(np.mean(m)), float(np.var(good, ddof=1)), int(good.size)))
    return rows, keep, n_clipped


def _signal_level(a, b, r, noise):
    """The long frame's signal m_j (DN) from both frames, as the combination of a = v_i - b_i
    and b = v_j - b_j that is uncorrelated with d = b - r a: weights alpha (long) and beta
    (short) with beta / alpha = Var(v_j) / (r Var(v_i)) and alpha + beta / r = 1. Without a
    noise model (g, sigma_R^2), shot noise alone: alpha = beta = r / (1 + r)."""
    shot = (a + b) * r / (1.0 + r)
    if noise is None:
        return shot
    g, s2 = noise
    m = np.maximum(shot, 0.0)
    q = (g * m + s2) / (r * (g * m / r + s2))
    alpha = 1.0 / (1.0 + q / r)
    return alpha * (b + q * a)


def pair_estimate(
    short: np.ndarray,
    long: np.ndarray,
    black: np.ndarray,
    v_sat: float,
    nominal_ratio: float,
    i: int = 0,
    j: int = 1,
    noise: tuple[float, float] | None = None,
    level: np.ndarray | None = None,
    step: float = 1.0,
) -> PairEstimate:
    """Exposure ratio and difference variances of one pair of frames (see module docstring).

    Parameters
    ----------
    short, long : numpy.ndarray
        Raw values of the shorter and the longer exposure, same photosites, DN.
    black : numpy.ndarray
        Black level of those photosites, DN.
    v_sat : float
        Saturation level, DN.
    nominal_ratio : float
        t_j / t_i from the metadata (the starting value and the fallback), >= 1.
    i, j : int
        Indices of the two frames in the bracket (recorded).
    noise : (float, float), optional
        A provisional (g, sigma_R^2) (DN/e-, DN^2) for the signal level of a photosite computed
        from the pair (see :func:`_signal_level`); None: shot noise alone. Not used with ``level``.
    level : numpy.ndarray, optional
        Each photosite's long-frame signal (DN) from a third frame, NaN where unknown: the
        photosites are binned by it (independent of the pair's noise); the signal of a bin is
        the pair's own mean. None: binned by the pair's own level.
    step : float
        Quantisation step, DN (the lowest bin edge is at least one step).

    Returns
    -------
    PairEstimate
    """
    vi = short.astype(np.float64) - black
    vj = long.astype(np.float64) - black
    headroom = v_sat - float(np.mean(black))
    top = MAX_SIGNAL_FRACTION * headroom
    clipped = (short <= 0) | (long <= 0) | (short >= v_sat) | (long >= v_sat)
    r = float(nominal_ratio)
    empty = np.zeros(0)
    none = PairEstimate(i, j, float(nominal_ratio), 0.0, 0, empty, empty, np.zeros(0, int))
    for _ in range(3):
        lv_all = level if level is not None else _signal_level(vi, vj, r, noise)
        sel = np.isfinite(lv_all) & (lv_all > 0) & (lv_all < top)
        if level is None:
            sel &= ~clipped
        if np.count_nonzero(sel) < MIN_PAIR_PHOTOSITES:
            return none
        lv, a, b, clip = lv_all[sel], vi[sel], vj[sel], clipped[sel]
        lo = max(float(np.min(lv)), 1e-3 * headroom, float(step))
        if lo >= top:
            return none
        edges = np.geomspace(lo, top, BINS_PER_PAIR + 1)
        edges[0] = 0.0
        signal = 0.5 * (b + r * a) if level is not None else None
        rows, keep, n_clipped = _bin_stats(lv, b - r * a, edges, signal, clip if level is not None else None)
        if np.count_nonzero(keep) < MIN_PAIR_PHOTOSITES or np.sum(a[keep]) <= 0:
            return none
        r = float(np.sum(b[keep]) / np.sum(a[keep]))
    d = b - r * a
    signal = 0.5 * (b + r * a) if level is not None else None
    rows, keep, n_clipped = _bin_stats(lv, d, edges, signal, clip if level is not None else None)
    if np.count_nonzero(keep) < MIN_PAIR_PHOTOSITES:
        return none
    se = max(float(np.sqrt(np.sum(d[keep] ** 2)) / np.sum(a[keep])), MIN_RELATIVE_STDERR * r)
    sig, var, cnt = (np.array(c) for c in zip(*rows)) if rows else (empty, empty, np.zeros(0, int))
    return PairEstimate(i, j, r, se, int(np.count_nonzero(keep)), sig, var, cnt.astype(int), n_clipped)


def _weighted_fit(
    A: np.ndarray, y: np.ndarray, w: np.ndarray, floor: float
) -> tuple[np.ndarray, np.ndarray, bool, float]:
    """Weighted least squares of y = A (g, sigma_R^2) with sigma_R^2 >= ``floor``: the
    unconstrained solution, or, where it lies below the floor, g alone with sigma_R^2 = floor.
    Returns (coefficients, covariance, constrained, the unconstrained sigma_R^2)."""
    normal = A.T @ (A * w[:, None])
    coef = np.linalg.lstsq(normal, A.T @ (w * y), rcond=None)[0]
    if np.linalg.cond(normal) < 1e12 and coef[1] >= floor:
        return coef, np.linalg.inv(normal), False, float(coef[1])
    x1 = A[:, 0]
    sxx = float(np.sum(w * x1 * x1))
    g = float(np.sum(w * x1 * (y - floor * A[:, 1])) / sxx)
    return np.array([g, floor]), np.array([[1.0 / sxx, 0.0], [0.0, 0.0]]), True, float(coef[1])


def _fit_bins(
    x1: np.ndarray, x2: np.ndarray, y: np.ndarray, n: np.ndarray, floor: float
) -> tuple[np.ndarray, np.ndarray, bool, float, np.ndarray] | None:
    """The iterated weighted fit of :func:`photon_transfer_fit` over some bins: (coefficients,
    covariance, constrained, the unconstrained sigma_R^2, the fitted variances); None with
    fewer than 3 bins or a signal range under a factor 4."""
    sig = x1 / np.maximum(x2, 1)
    if y.size < 3 or sig.max() < 4 * max(sig.min(), 1e-12):
        return None
    A = np.column_stack([x1, x2])
    lowest = floor * x2  # no variance below the floor's share: bounded weights
    pred = np.maximum(y, lowest)
    for _ in range(20):
        w = np.maximum(n - 1, 1) / (2.0 * pred**2)
        coef, cov, constrained, fitted = _weighted_fit(A, y, w, floor)
        new = np.maximum(A @ coef, lowest)
        done = np.max(np.abs(new / pred - 1)) < 1e-9
        pred = new
        if done:
            break
    return coef, cov, constrained, fitted, pred


def photon_transfer_fit(pairs: Sequence[PairEstimate], floor: float = 1.0 / 12.0) -> dict[str, Any] | None:
    """Gain and readout variance from the difference variances of every pair (Eq. 3):
    Var(d) = g m_j (1 + r) + sigma_R^2 (1 + r^2), weighted least squares with sigma_R^2 >=
    ``floor`` and weights (n - 1) / (2 Var^2) (the variance of a sample variance), Var the
    fitted one (at least the floor's share: bounded weights), iterated to convergence; then
    again without the bins whose shorter frame's noise is under :data:`DITHER_STEPS`
    quantisation steps (undithered rounding: its variance is not step^2 / 12).

    Parameters
    ----------
    pairs : sequence of PairEstimate
    floor : float
        Smallest readout variance, DN^2: the quantisation floor step^2 / 12.

    Returns
    -------
    dict or None
        ``g`` (DN/e-), ``sigma2_R`` (DN^2), ``g_stderr``, ``sigma2_R_stderr`` (None when
        constrained to the floor), ``reduced_chi2``, ``dof``, ``chi2_limit`` (its
        :data:`CHI2_LIMIT_PROBABILITY` quantile), ``model_rejected`` (chi^2 above it),
        ``stderr_scale`` (sqrt of the reduced chi^2 when above 1: the standard errors are
        scaled by it), ``relative_misfit`` (rms relative deviation of the bin variances from the
        fit beyond their sampling scatter), ``n_bins`` (used), ``n_bins_undithered`` (left out), ``n_photosites``,
        ``sigma2_R_floor``, ``sigma2_R_fitted``
        (the unconstrained value), ``constrained``, ``max_weight_ratio`` (largest weight over
        the median); None with fewer than 3 bins or a signal range under a factor 4.
    """
    from scipy.stats import chi2 as chi2_dist

    cols: list[list[np.ndarray]] = [[], [], [], [], []]
    for q in pairs:
        if not q.overlap or not q.count.size:
            continue
        for c, v in zip(
            cols, (q.signal * (1.0 + q.ratio), np.full(q.signal.size, 1.0 + q.ratio**2), q.variance, q.count)
        ):
            c.append(v)
        cols[4].append(q.signal / q.ratio)  # the short frame's signal
    if not cols[2]:
        return None
    x1, x2, y, n, short = (np.concatenate(c) for c in cols)
    first = _fit_bins(x1, x2, y, n, floor)
    if first is None:
        return None
    coef, _, _, _, _ = first
    # the short frame's noise before rounding: g m_i + sigma_R^2 - step^2 / 12 (step^2 = 12 floor)
    dithered = coef[0] * short + coef[1] - floor >= (DITHER_STEPS**2) * 12.0 * floor
    found = _fit_bins(x1[dithered], x2[dithered], y[dithered], n[dithered], floor) if not dithered.all() else first
    if found is None:  # too few bins are dithered: all of them, the model's error says so
        found, dithered = first, np.ones(y.size, bool)
    coef, cov, constrained, fitted, pred = found
    y, n = y[dithered], n[dithered]
    w = np.maximum(n - 1, 1) / (2.0 * pred**2)
    rel2 = (y - pred) ** 2 / pred**2 - 2.0 / np.maximum(n - 1, 1)  # beyond the sample variances' own scatter
    misfit = float(np.sqrt(max(float(np.mean(rel2)), 0.0)))
    dof = max(y.size - (1 if constrained else 2), 1)
    chi2 = float(np.sum((y - pred) ** 2 * w) / dof)
    limit = float(chi2_dist.ppf(CHI2_LIMIT_PROBABILITY, dof) / dof)
    scale = math.sqrt(max(chi2, 1.0))
    g = float(coef[0])
    g_se = float(np.sqrt(cov[0, 0])) * scale
    s2_se = None if constrained else float(np.sqrt(cov[1, 1])) * scale
    return {
        "g": g,
        "sigma2_R": float(coef[1]),
        "g_stderr": max(g_se, MIN_RELATIVE_STDERR * abs(g)),
        "sigma2_R_stderr": None if s2_se is None else max(s2_se, MIN_RELATIVE_STDERR * float(coef[1])),
        "reduced_chi2": chi2,
        "dof": int(dof),
        "chi2_limit": limit,
        "model_rejected": bool(chi2 > limit),
        "stderr_scale": scale,
        "relative_misfit": misfit,
        "n_bins": int(y.size),
        "n_bins_undithered": int(np.count_nonzero(~dithered)),
        "n_photosites": int(n.sum()),
        "sigma2_R_floor": float(floor),
        "sigma2_R_fitted": fitted,
        "constrained": bool(constrained),
        "max_weight_ratio": float(np.max(w) / np.median(w)),
    }


# ---------------------------------------------------------------------------------- the model


def _chain_times(nominal: np.ndarray, order: np.ndarray, pairs: Sequence[PairEstimate]):
    """Effective times (s, frame order) from the ratios of consecutive pairs in ``order``,
    scaled to the nominal geometric mean, and their relative standard errors."""
    k = len(order)
    log_rel = np.zeros(k)
    A = np.zeros((k, max(k - 1, 1)))
    for m, q in enumerate(pairs):
        log_rel[m + 1] = log_rel[m] + math.log(q.ratio)
        A[m + 1 :, m] = 1.0
    shift = float(np.mean(np.log(nominal[order]) - log_rel))
    se_log = np.array([q.ratio_stderr / q.ratio for q in pairs] or [0.0])
    Ac = A - A.mean(axis=0)
    var = (Ac**2) @ (se_log**2)
    eff = np.empty(k)
    rel = np.empty(k)
    eff[order] = np.exp(log_rel + shift)
    rel[order] = np.maximum(np.sqrt(var), MIN_RELATIVE_STDERR)
    return eff, rel


def _third_frame_level(
    data: Sequence[np.ndarray], order: np.ndarray, m: int, black: np.ndarray, v_sat: float, nominal: np.ndarray
) -> np.ndarray:
    """The signal (DN, on the long frame's scale) of every photosite of the pair at positions
    ``m``, ``m + 1`` of ``order``, seen in the nearest longer frame where it is exposed and
    unsaturated, else in the nearest shorter one; NaN where neither has it."""
    j = order[m + 1]
    level = np.full(np.shape(data[j]), np.nan)
    for q in (m + 2, m - 1):
        if 0 <= q < len(order):
            k = order[q]
            v = data[k]
            ok = np.isnan(level) & (v > 0) & (v < v_sat)
            level[ok] = (v[ok] - black[ok]) * (nominal[j] / nominal[k])
    return level


def estimate_black_level(
    data: Sequence[np.ndarray], order: np.ndarray, nominal: np.ndarray, v_sat: float, step: float = 1.0
) -> tuple[float, float] | None:
    """The black level of a bracket whose files do not say it, DN, with its standard error.

    For the photosites of a signal bin (binned by a third frame, independent of the pair's
    noise), the mean raw values of a pair obey E[v_j] = r E[v_i] + (1 - r) b: the offset of
    the straight line through the bins' means is (1 - r) b (a dark current grows with the
    time as the signal does, so it enters r, not b). Each pair's b is weighted by its
    inverse variance; the standard error is scaled by sqrt(chi^2 / dof) of their agreement
    when above 1.

    Parameters
    ----------
    data : sequence of numpy.ndarray
        The frames (the same photosites), DN.
    order : numpy.ndarray
        Frame indices by increasing exposure time.
    nominal : numpy.ndarray
        Nominal exposure times per frame, s.
    v_sat : float
        Saturation level, DN.
    step : float
        Quantisation step, DN: bins whose short frame's spread is under
        :data:`DITHER_STEPS` steps are left out (the mean of undithered rounding is not linear).

    Returns
    -------
    (float, float) or None
        b and its standard error, DN; None with fewer than three frames or too few bins.
    """
    if len(order) < 3:
        return None
    zero = np.zeros(np.shape(data[0]))
    top = MAX_SIGNAL_FRACTION * v_sat
    est: list[tuple[float, float]] = []
    for m, (i, j) in enumerate(zip(order[:-1], order[1:])):
        level = _third_frame_level(data, order, m, zero, v_sat, nominal)
        vi, vj = np.asarray(data[i], np.float64), np.asarray(data[j], np.float64)
        clipped = (vi <= 0) | (vj <= 0) | (vi >= v_sat) | (vj >= v_sat)
        sel = np.isfinite(level) & (level > 0) & (level < top)
        if np.count_nonzero(sel) < MIN_PAIR_PHOTOSITES:
            continue
        lv = level[sel]
        edges = np.geomspace(max(float(np.min(lv)), 1e-3 * v_sat, 1.0), top, BINS_PER_PAIR + 1)
        edges[0] = 0.0
        idx = np.digitize(lv, edges) - 1
        a, b, clip = vi[sel], vj[sel], clipped[sel]
        pts = []
        for k in range(BINS_PER_PAIR):
            s = np.flatnonzero(idx == k)
            if s.size < MIN_BIN_PHOTOSITES or np.mean(clip[s]) > MAX_CLIPPED_FRACTION:
                continue
            if np.var(a[s]) < (DITHER_STEPS * step) ** 2:  # rounding not dithered: its mean is not linear
                continue
            pts.append((np.mean(a[s]), np.mean(b[s]), np.var(a[s]) / s.size, np.var(b[s]) / s.size))
        if len(pts) < 3:
            continue
        x, y, vx, vy = (np.array(c) for c in zip(*pts))
        if x.max() - x.min() < 4 * np.sqrt(np.max(vx) + 1e-12):
            continue
        r0 = nominal[j] / nominal[i]
        for _ in range(3):  # weights with the current slope (errors in both means)
            w = 1.0 / np.maximum(vy + r0 * r0 * vx, 1e-12)
            A = np.column_stack([x, np.ones_like(x)])
            cov = np.linalg.inv(A.T @ (A * w[:, None]))
            r0, c = cov @ (A.T @ (w * y))
        if abs(1.0 - r0) < 0.05:
            continue
        grad = np.array([c / (1.0 - r0) ** 2, 1.0 / (1.0 - r0)])
        est.append((float(c / (1.0 - r0)), float(grad @ cov @ grad)))
    if not est:
        return None
    vals, var = (np.array(c) for c in zip(*est))
    w = 1.0 / np.maximum(var, 1e-18)
    b = float(np.sum(w * vals) / np.sum(w))
    chi2 = float(np.sum(w * (vals - b) ** 2) / max(len(vals) - 1, 1))
    return b, float(np.sqrt(max(chi2, 1.0) / np.sum(w)))


def _pairs(
    data: Sequence[np.ndarray],
    order: np.ndarray,
    nominal: np.ndarray,
    black: np.ndarray,
    v_sat: float,
    step: float,
    noise: tuple[float, float] | None = None,
) -> list[PairEstimate]:
    """The :class:`PairEstimate` of every pair of consecutive exposures in ``order``: binned by
    a third frame when the bracket has one, else by the pair's own level (with ``noise``)."""
    third = len(order) >= 3
    return [
        pair_estimate(
            data[a],
            data[b],
            black,
            v_sat,
            nominal[b] / nominal[a],
            int(a),
            int(b),
            noise,
            level=_third_frame_level(data, order, m, black, v_sat, nominal) if third else None,
            step=step,
        )
        for m, (a, b) in enumerate(zip(order[:-1], order[1:]))
    ]


def self_calibrate(
    frames: Sequence[RawFrame], *, max_samples: int = MAX_PAIR_SAMPLES, warn: Callable[[str], None] | None = None
) -> SelfCalibration:
    """Estimate the camera model of a bracket from the bracket itself (see module docstring).

    Parameters
    ----------
    frames : sequence of RawFrame
        The bracket: one camera, one ISO, any order, at least two frames.
    max_samples : int
        Photosites per pair at most (a regular subsample of rows).
    warn : callable, optional
        Called with a one-line message for each assumption made (also kept in ``notes``).

    Returns
    -------
    SelfCalibration

    Raises
    ------
    InputError
        Mixed cameras, sizes, CFA patterns or ISO; a frame given twice; no photosite exposed
        and unsaturated in two frames of the bracket.
    """
    frames = list(frames)
    check_bracket(frames)
    check_frames(frames)
    notes: list[str] = []

    def note(msg: str) -> None:
        notes.append(msg)
        if warn is not None:
            warn(msg)

    first = frames[0]
    white = float(first.white_level or 65535.0)
    step = float(first.quantisation_step or 1.0)
    floor = step * step / 12.0
    tile = cfa_black_tile(first)
    levels = {0.0 if fr.black_level is None else fr.black_level for fr in frames}  # None: 0 DN assumed
    if len(levels) > 1:
        note(
            f"black levels differ between frames ({', '.join(f'{b:g}' for b in sorted(levels))} DN); "
            f"{first.path}'s used"
        )
    nominal = np.array([fr.exposure_time for fr in frames], float)
    order = np.argsort(nominal, kind="stable")
    rows = _row_sample(first.shape, max_samples)
    data = [np.asarray(fr.data)[rows] for fr in frames]
    longest = data[order[-1]]
    if first.white_level is None:
        white = _unknown_white_level(longest, note, first.path)

    def v_sat_for(black_level: float) -> float:
        if len(order) < 2:
            return saturation_level(longest, white, black_level)
        ratio = nominal[order[-1]] / nominal[order[-2]]
        return saturation_level(longest, white, black_level, data[order[-2]], ratio)

    black_source = "file metadata"
    if first.black_level is None:
        found = estimate_black_level(data, order, nominal, v_sat_for(0.0), step)
        if found is not None and found[1] > max(step, 1e-3 * white):  # not identified (e.g. a flat scene)
            found = None
        if found is None:
            note(f"{first.path}: no black level in the file, and the bracket cannot give one; 0 DN assumed")
            black_source = "assumed 0 DN (not in the files)"
        else:
            b0, b_se = max(found[0], 0.0), found[1]
            tile = np.full((2, 2), b0)
            black_source = f"estimated from the bracket: {b0:.3f} +- {b_se:.2g} DN"
            note(f"{first.path}: no black level in the file; {black_source} (--black-level to give it)")
    black = _black_rows(tile, rows, first.shape[1])
    v_sat = v_sat_for(float(tile.mean()))
    if v_sat < white:
        note(f"values pile up below the white level ({white:g} DN): saturation taken at {v_sat:.1f} DN")
    pairs = _pairs(data, order, nominal, black, v_sat, step)
    fit = photon_transfer_fit(pairs, floor)
    if len(frames) == 2 and fit and fit["g"] > 0:  # again, the pair's level uncorrelated with d where read noise counts
        pairs = _pairs(data, order, nominal, black, v_sat, step, (fit["g"], max(fit["sigma2_R"], floor)))
        fit = photon_transfer_fit(pairs, floor)
    for q in pairs:
        a, b = q.short, q.long
        if not q.overlap:
            note(
                f"no photosite is exposed and unsaturated (below {MAX_SIGNAL_FRACTION:.0%} of the range) in both {frames[a].path} "
                f"and {frames[b].path}: "
                f"their nominal exposure ratio {nominal[b] / nominal[a]:.4g} is assumed"
            )
    if not any(q.overlap for q in pairs):
        raise InputError(
            "no overlap between the exposures: no photosite is exposed and unsaturated in two frames, "
            "so the bracket cannot calibrate itself; give --calibration or a denser bracket"
        )
    eff, rel_t = _chain_times(nominal, order, pairs)
    _note_fit(fit, step, note)
    gain_known = bool(
        fit
        and fit["g"] > 0
        and fit["g_stderr"] < MAX_GAIN_RELATIVE_ERROR * fit["g"]
        and fit["relative_misfit"] <= MAX_MODEL_MISFIT
    )
    if fit is None or not gain_known:
        why = _not_estimable(fit)
        note(f"gain not estimable ({why}): irradiance in DN/s (g = 1 DN/e- assumed), sigma relative only")
        fit = {
            **(fit or {}),
            "g": 1.0,
            "g_stderr": None,
            "g_fitted": None if fit is None else fit["g"],
            "g_fitted_stderr": None if fit is None else fit["g_stderr"],
            "sigma2_R": (fit or {}).get("sigma2_R", 1.0),
            "sigma2_R_stderr": None,
            "not_estimable": why,
        }
    s2 = max(float(fit["sigma2_R"]), floor)
    mu = float(tile.mean())
    bias_map = None
    if np.ptp(tile) > 0:
        h, w = first.shape
        bias_map = _black_rows(tile, np.arange(h), w).astype(np.float32)
    params = SensorParams(
        g=float(fit["g"]),
        mu_R=mu,
        sigma2_R=s2,
        v_sat=float(v_sat),
        white_level=white,
        dark_current=0.0,
        name=first.camera or "",
    )
    stderr = {k: fit[f"{k}_stderr"] for k in ("g", "sigma2_R") if fit.get(f"{k}_stderr") is not None}
    calib = Calibration(
        params=params,
        bias_map=bias_map,
        stderr=stderr,
        provenance={
            "source": SELF_CALIBRATED,
            "camera": first.camera,
            "serial": first.serial,
            "iso": first.iso,
            "cfa_pattern": first.cfa_pattern,
            "gain_estimated": gain_known,
            "quantisation_step": step,
        },
    )
    return SelfCalibration(
        calibration=calib,
        effective_times=tuple(float(t) for t in eff),
        nominal_times=tuple(float(t) for t in nominal),
        time_relative_stderr=tuple(float(x) for x in rel_t),
        gain_known=gain_known,
        pairs=tuple(pairs),
        fit=fit,
        black_tile=tile,
        notes=tuple(notes),
        quantisation_step=step,
        black_source=black_source,
    )


def _unknown_white_level(longest: np.ndarray, note: Callable[[str], None], where: object) -> float:
    """The white level of frames whose files do not say it (16-bit words of fewer bits): the
    largest value of the longest frame where values pile up there (the ADC clips), else 65535 DN;
    a note says which."""
    high = int(np.max(longest)) if longest.size else 65535
    if high < 65535 and np.count_nonzero(longest == high) >= max(20, 1e-4 * longest.size):
        note(f"{where}: no white level in the file; values pile up at {high} DN, taken as the white level")
        return float(high)
    note(f"{where}: no white level in the file; 65535 DN assumed")
    return 65535.0


def _note_fit(fit: dict[str, Any] | None, step: float, note: Callable[[str], None]) -> None:
    """Say what the photon-transfer fit could not take from the data: a readout variance held
    at the quantisation floor, a model the data reject (errors scaled)."""
    if fit is None:
        return
    if fit["constrained"]:
        note(
            f"the fitted read-noise variance {fit['sigma2_R_fitted']:.3g} DN^2 lies below the quantisation floor "
            f"{fit['sigma2_R_floor']:.3g} DN^2 (step {step:g} DN): the gain is fitted with sigma_R^2 at the floor"
        )
    if fit["model_rejected"]:
        note(
            f"the photon-transfer model does not describe this bracket (reduced chi^2 {fit['reduced_chi2']:.3g} over "
            f"{fit['dof']} degrees of freedom, above the {fit['chi2_limit']:.3g} they allow): the standard errors of "
            f"the gain and read noise are scaled by sqrt(chi^2) = {fit['stderr_scale']:.3g}"
        )


def _not_estimable(fit: dict[str, Any] | None) -> str:
    """Why the gain was not estimated (a short phrase)."""
    if fit is None:
        return "too few photosites or signal levels: fewer than 3 signal bins or a range under a factor 4"
    if fit["g"] <= 0:
        return f"the fitted gain {fit['g']:.3g} DN/e- is not positive"
    if fit["relative_misfit"] > MAX_MODEL_MISFIT:
        return (
            f"the photon-transfer model misses the variances by {fit['relative_misfit']:.0%} rms (chi^2/dof "
            f"{fit['reduced_chi2']:.3g}): a wrong black level, non-linearity or motion?"
        )
    return (
        f"g = {fit['g']:.4g} +- {fit['g_stderr']:.2g} DN/e-: a relative standard error above "
        f"{MAX_GAIN_RELATIVE_ERROR:.0%}"
    )


def calibration_sigma(irradiance: np.ndarray, nexp: np.ndarray, selfcal: SelfCalibration) -> np.ndarray:
    """The irradiance's standard uncertainty due to the self-calibration's own estimates.

    x = (v - b) / (t g) (Eq. 6): a relative error of g or of an effective time is the same
    relative error of x. The exposure that dominates a photosite's estimate is its longest
    unsaturated one (the ``nexp``-th shortest: a longer exposure saturates first), so
    sigma_cal = |x| sqrt((s_g / g)^2 + (s_t / t)^2) of that exposure. Systematic: averaging
    over photosites does not reduce it.

    Parameters
    ----------
    irradiance : numpy.ndarray
        The merged irradiance, e-/s (or DN/s).
    nexp : numpy.ndarray
        Unsaturated exposures used per photosite.
    selfcal : SelfCalibration

    Returns
    -------
    numpy.ndarray
        float32, same unit as ``irradiance``; 0 where ``nexp`` is 0.
    """
    rel_t = np.asarray(selfcal.time_relative_stderr, float)[np.argsort(selfcal.nominal_times, kind="stable")]
    idx = np.clip(np.asarray(nexp).astype(np.int64) - 1, 0, rel_t.size - 1)
    rel = np.sqrt(selfcal.gain_relative_stderr**2 + rel_t[idx] ** 2)
    out = np.abs(irradiance) * rel
    return np.where(np.asarray(nexp) > 0, out, 0.0).astype(np.float32)


def apply_self_calibration(result: HdrResult, selfcal: SelfCalibration, *, times_applied: bool = True) -> HdrResult:
    """A merge that states its self-calibration: the unit, the header entry
    ``self_calibration`` (:meth:`SelfCalibration.header`), sigma including the calibration's
    own uncertainty (:func:`calibration_sigma`, added in quadrature) and the calibration part
    as ``sigma_calibration`` (added in quadrature to the merge's own calibration part when it
    has one).

    Parameters
    ----------
    result : HdrResult
        The merge (with its header).
    selfcal : SelfCalibration
        The bracket's self-calibration.
    times_applied : bool
        Whether the merge used the effective exposure times (False: the nominal ones, recorded).

    Returns
    -------
    HdrResult
        A new result; ``result`` is not changed.
    """
    cal = calibration_sigma(result.irradiance, result.nexp, selfcal)
    sigma = np.sqrt(np.square(result.sigma, dtype=np.float64) + np.square(cal, dtype=np.float64)).astype(np.float32)
    prior = result.sigma_calibration  # the merge's own calibration part (maps), if any
    sigma_cal = (
        cal
        if prior is None
        else np.sqrt(np.square(prior, dtype=np.float64) + np.square(cal, dtype=np.float64)).astype(np.float32)
    )
    header = self_calibration_header(result.header, selfcal, times_applied=times_applied)
    return result.replace(sigma=sigma, sigma_calibration=sigma_cal, header=header)


def self_calibration_header(
    header: dict[str, Any], selfcal: SelfCalibration, *, times_applied: bool = True
) -> dict[str, Any]:
    """A merge's header stating its self-calibration: the unit, ``self_calibration``
    (:meth:`SelfCalibration.header`) and what the sigma channels hold.

    Parameters
    ----------
    header : dict
        The merge's header.
    selfcal : SelfCalibration
        The bracket's self-calibration.
    times_applied : bool
        Whether the merge used the effective exposure times.

    Returns
    -------
    dict
        A new header.
    """
    head = selfcal.header()
    head["merged_with"] = "effective exposure times" if times_applied else "nominal exposure times"
    out = dict(header)
    out["self_calibration"] = head
    out["unit"] = selfcal.unit
    out["sigma"] = f"standard deviation of irradiance, same unit; {head['sigma']}"
    out["sigma_calibration"] = "the part of sigma due to the self-calibration's estimates (systematic)"
    return out
