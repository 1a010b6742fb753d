"""Model selection: model only what the scene requires (each decision with its figure).

Every decision compares the predicted SNR (:func:`planner.predict.predict_snr`, variances
from :mod:`pipeline.noise`) of a simpler model with the full one and takes the simpler one
when it costs at most ``tolerance_db`` at every eligible irradiance bin:

* dark strategy per exposure time: without a dark frame the per-photosite dark current and
  bias errors stay in the estimate (they do not average out); the cost at the target level is
  10 log10(1 + T^2 b^2 / X^2) dB for a systematic error b (e-/s) at irradiance X and target
  SNR T. Above the tolerance a master dark from the library is used when there is one (no
  capture time), else a matched dark frame (costs t + overhead and adds its read noise). The
  planner then offers such a time both with that dark and without a dark frame, and keeps the
  dark only when the SNR it buys (the systematic error is part of the predicted SNR) is
  cheaper than more exposures;
* PRNU: a scalar gain leaves a relative error p (the PRNU spread) in every photosite: cost
  10 log10(1 + T^2 p^2) dB;
* saturation: the probabilistic model (Eq. 8-10, a censored likelihood) keeps the information
  of samples within k sigma of v_sat that the threshold rule drops, and of the saturated ones;
  gain = predicted SNR difference (reported; not chosen automatically, see
  :func:`saturation_decision`);
* iterations: weights evaluated at the previous estimate instead of the truth; the start is
  the non-saturated (uniform) average; the number of re-weighting steps after which the
  predicted SNR is within the tolerance of the converged merge.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from hdrcap.pipeline.merge.options import CENSORED_SPACING
from hdrcap.pipeline.params import Calibration
from hdrcap.planner.predict import K_SIGMA, SystematicErrors, exposure_terms, predict_snr, usable_fraction

if TYPE_CHECKING:  # planner.plan imports this module
    from hdrcap.planner.plan import IrradianceHistogram

__all__ = [
    "target_loss_db",
    "dark_decision_for_time",
    "longest_usable_time",
    "RELEVANCE_FACTOR",
    "summarise_dark_decisions",
    "prnu_decision",
    "saturation_decision",
    "iterations_decision",
    "eligibility_decision",
    "MAX_ITERATIONS",
    "CONVERGED_ITERATIONS",
    "full_well_clips_first",
]

MAX_ITERATIONS = 8


#: Iterations asked of the merge when they must converge (the merge's default; it stops each
#: photosite at its tolerance, so this costs time only where needed).
CONVERGED_ITERATIONS = 20


def target_loss_db(bias: ArrayLike, X: ArrayLike, target_lin: float) -> np.ndarray:
    """SNR lost at the target level by a systematic error ``bias`` (e-/s) at irradiance X, dB:
    10 log10(1 + T^2 bias^2 / X^2).

    Parameters
    ----------
    bias : array_like
        RMS systematic error, e-/s.
    X : array_like
        Irradiance, e-/s.
    target_lin : float
        Target SNR, linear.

    Returns
    -------
    numpy.ndarray
        The loss, dB.
    """
    X = np.asarray(X, dtype=np.float64)
    return 10.0 * np.log10(1.0 + (target_lin * np.asarray(bias, dtype=np.float64) / X) ** 2)


#: An exposure more than this factor shorter than the longest usable time of a pixel carries
#: a small share of that pixel's weight (about 1/RELEVANCE_FACTOR or less); its dark error is
#: judged only where it matters.
RELEVANCE_FACTOR = 8.0


def longest_usable_time(
    Xe: np.ndarray, times: Sequence[float], calibration: Calibration, k_sigma: float = K_SIGMA
) -> np.ndarray:
    """For each irradiance, the longest of ``times`` at which it is not predicted saturated
    (0 where none is).

    Parameters
    ----------
    Xe : array_like
        Irradiances, e-/s.
    times : sequence of float
        Exposure times, s.
    calibration : Calibration
        Camera model.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.

    Returns
    -------
    numpy.ndarray
        Per irradiance the longest usable time, s (0 where none is).
    """
    Xe = np.asarray(Xe, dtype=np.float64)
    best = np.zeros_like(Xe)
    for t in sorted(times):
        best = np.where(usable_fraction(Xe, t, calibration, "threshold", k_sigma) > 0, t, best)
    return best


def dark_decision_for_time(
    Xe: np.ndarray,
    t: float,
    calibration: Calibration,
    errors: SystematicErrors,
    target_lin: float,
    n_library: int,
    overhead: float,
    tolerance_db: float,
    k_sigma: float = K_SIGMA,
    t_best: np.ndarray | None = None,
) -> dict:
    """Dark strategy for an exposure of ``t`` s on the eligible irradiances ``Xe`` (e-/s).

    The cost of skipping the dark frame is evaluated where the exposure matters: where it is
    usable and within a factor :data:`RELEVANCE_FACTOR` of the longest usable time
    ``t_best`` (per irradiance; default: everywhere it is usable).

    Parameters
    ----------
    Xe : numpy.ndarray
        Eligible irradiances, e-/s.
    t : float
        Exposure time, s.
    calibration : Calibration
        Camera model.
    errors : SystematicErrors
        Systematic errors of the dark model.
    target_lin : float
        Target SNR, linear.
    n_library : int
        Frames of the library's master dark for ``t`` (0: none).
    overhead : float
        Per-frame overhead, s (the cost of a matched dark frame is t + overhead).
    tolerance_db : float
        SNR loss the dark model may cost, dB.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.
    t_best : array_like, optional
        Per irradiance the longest usable time, s (:func:`longest_usable_time`).

    Returns
    -------
    dict
        ``choice`` ("model", "master" or "matched"), ``reason``, ``figure`` (dB lost without a
        dark frame) and ``time`` (s).
    """
    p = calibration.params
    use = usable_fraction(Xe, t, calibration, "threshold", k_sigma) > 0
    if t_best is not None:
        use &= t * RELEVANCE_FACTOR >= np.asarray(t_best)
    b = float(np.hypot(errors.dark_current, errors.bias / (t * p.g)))
    loss = float(target_loss_db(b, Xe[use], target_lin).max()) if use.any() else 0.0
    if loss <= tolerance_db:
        choice, why = "model", f"no dark frame: the dark model's error ({b:.3g} e-/s) costs {loss:.3f} dB at the target"
    elif n_library >= 1:
        choice, why = "master", f"master dark of {n_library} frames: the dark model would cost {loss:.3f} dB"
    else:
        choice, why = (
            "matched",
            (
                f"matched dark frame (+{t + overhead:.4g} s): the dark model would cost "
                f"{loss:.3f} dB and the library has no master dark for this time"
            ),
        )
    return {"choice": choice, "reason": why, "figure": loss, "time": float(t)}


def summarise_dark_decisions(per_exposure: list[dict], exposures: list[float]) -> dict:
    """One decision entry for the dark strategies of the planned exposures.

    Parameters
    ----------
    per_exposure : list of dict
        The dark decision of each planned exposure (:func:`dark_decision_for_time`).
    exposures : list of float
        The planned exposure times, s.

    Returns
    -------
    dict
        The decision: ``choice``, ``reason`` (text), ``figure`` and its ``unit``.
    """
    reasons = [f"{t:.6g} s: {d['reason']}" for t, d in zip(exposures, per_exposure)]
    return {
        "choice": [d["choice"] for d in per_exposure],
        "reason": "; ".join(reasons) if reasons else "no exposures",
        "figure": [round(d["figure"], 4) for d in per_exposure],
        "unit": "dB lost at the target without a dark frame, per exposure",
    }


def prnu_decision(errors: SystematicErrors, target_lin: float, calibration: Calibration, tolerance_db: float) -> dict:
    """Per-photosite PRNU map or a scalar gain.

    Parameters
    ----------
    errors : SystematicErrors
        Its ``prnu`` is the relative PRNU spread (what a scalar gain leaves), ``prnu_map`` the
        map's own relative error (what the map leaves).
    target_lin : float
        Target SNR, linear.
    calibration : Calibration
        Camera model (without a PRNU map the choice is "scalar").
    tolerance_db : float
        SNR loss a scalar gain may cost, dB.

    Returns
    -------
    dict
        The decision: ``choice``, ``reason`` (text), ``figure`` and its ``unit``.
    """
    # SNR lost at the target by a scalar gain, relative to the map (which has its own error)
    loss = float(10.0 * np.log10((1.0 + (target_lin * errors.prnu) ** 2) / (1.0 + (target_lin * errors.prnu_map) ** 2)))
    if calibration.prnu is None:
        return {
            "choice": "scalar",
            "reason": "the calibration has no PRNU map",
            "figure": loss,
            "unit": "dB lost at the target with a scalar gain",
        }
    if loss <= tolerance_db:
        why = f"scalar gain: the PRNU spread {100 * errors.prnu:.3g} % costs {loss:.3f} dB at the target"
        choice = "scalar"
    else:
        why = (
            f"per-photosite PRNU map: a scalar gain would cost {loss:.3f} dB more (spread {100 * errors.prnu:.3g} %, "
            f"map error {100 * errors.prnu_map:.3g} %)"
        )
        choice = "map"
    return {"choice": choice, "reason": why, "figure": loss, "unit": "dB lost at the target with a scalar gain"}


def full_well_clips_first(calibration: Calibration) -> bool:
    """Whether the full well, not the ADC, limits the raw values: v_sat lies more than 3 read-noise
    sigma below the ADC's largest value (camera-A: 3709 against 4095 DN; camera-B: 1023 = 1023).

    Parameters
    ----------
    calibration : Calibration
        Camera model (v_sat, white level in DN; sigma2_R in DN^2).

    Returns
    -------
    bool
    """
    p = calibration.params
    return bool(p.white_level - p.v_sat > 3.0 * np.sqrt(p.sigma2_R))


def saturation_decision(
    Xe: np.ndarray,
    exposures: Sequence[float],
    darks: Sequence[str],
    n_dark: Sequence[int],
    calibration: Calibration,
    errors: SystematicErrors,
    prnu: str,
    tolerance_db: float,
    k_sigma: float = K_SIGMA,
) -> dict:
    """The saturation model: the threshold rule; the probabilistic model's predicted SNR gain
    is reported but it is not chosen automatically.

    The merge's probabilistic model is the censored (Tobit) likelihood of Eq. 8-10 (a saturated
    sample contributes its survival probability), and its predicted gain uses the same
    likelihood's expected information (:func:`planner.predict.censored_information_fraction`).
    On sensors that follow the model (camera-A, camera-B) its centred estimate is now within z mean
    -0.07..+0.05 of the truth in every band of k = (E v - v_sat)/sigma_v from -3 to +3
    (tests/pipeline/merge/test_censored_likelihood.py; the threshold rule's own is -0.17..-0.20 at k
    in -3..-2), but it is still not chosen unasked: on the realistic camera-R its z mean near the
    clip levels is 0.1-0.6 lower than the threshold rule's (k in -3..+3, matched darks, estimated
    calibration and effective times; benchmarks/bench_honesty.py, docs/merge.md's honesty table): it
    relies on the samples just below v_sat, where the model's remaining errors (there, mostly the
    shutter's: with camera-R's shutter errors switched off the gap is 0-0.24; with its nonlinearity
    switched off it stays) weigh more; and it costs several times the merge time.
    A user asks for it with ``--saturation probabilistic``.

    It helps only where consecutive exposures are at most
    :data:`pipeline.merge.options.CENSORED_SPACING` apart: with wider spacing the exposure below
    a clip holds too little of the information just above it, the censored likelihood's sigma
    is not trustworthy there, and the merge keeps the threshold estimate
    (``MergeOptions.censored_spacing``; docs/merge.md, item 5 and *Stability at the extremes*),
    so the predicted gain near the clip levels is not realised; the reason says so.

    Parameters
    ----------
    Xe : numpy.ndarray
        Eligible irradiances, e-/s (histogram points).
    exposures : sequence of float
        The planned exposure times, s.
    darks : sequence of str
        Dark strategy per exposure.
    n_dark : sequence of int
        Dark frames behind each exposure's dark subtraction (0 counts as 1).
    calibration : Calibration
        Camera model.
    errors : SystematicErrors
        Systematic errors of the simpler models.
    prnu : {"map", "scalar"}
        The PRNU model.
    tolerance_db : float
        SNR loss a simpler model may cost, dB.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.

    Returns
    -------
    dict
        The decision: ``choice``, ``reason`` (text), ``figure`` and its ``unit``.
    """
    kw: dict[str, Any] = dict(errors=errors, prnu=prnu, k_sigma=k_sigma)
    thr = predict_snr(Xe, exposures, calibration, darks, [n or 1 for n in n_dark], saturation="threshold", **kw).snr_db
    prob = predict_snr(
        Xe, exposures, calibration, darks, [n or 1 for n in n_dark], saturation="probabilistic", **kw
    ).snr_db
    gain = np.where(np.isfinite(thr), prob - thr, np.where(np.isfinite(prob), np.inf, 0.0))
    g = float(gain.max()) if gain.size else 0.0
    frac = float(np.mean(gain > tolerance_db)) if gain.size else 0.0
    times = np.sort(np.asarray(exposures, dtype=np.float64))
    spacing = float(np.max(times[1:] / times[:-1])) if times.size > 1 else 1.0
    if g > tolerance_db:
        choice = "threshold"
        why = (
            f"threshold rule (Eq. 11): the probabilistic model (Eq. 8-10) would add up to {g:.3f} dB "
            f"({100 * frac:.3g} % of irradiance bins gain more than {tolerance_db:g} dB; censored likelihood) "
            "but on a realistic sensor it is less accurate near the clip levels than the threshold rule "
            "(simulated camera-R: z mean 0.1-0.6 lower); not chosen automatically"
        )
        if spacing > CENSORED_SPACING * (1 + 1e-9):
            why += (
                f"; with exposures up to {spacing:.3g}x apart (more than {CENSORED_SPACING:g}x) the merge "
                "keeps the threshold estimate near the clip levels anyway (the censored likelihood cannot be "
                "trusted there), so most of that gain would not be realised"
            )
    else:
        choice = "threshold"
        why = f"threshold rule (Eq. 11): the probabilistic model would add at most {g:.3f} dB"
    return {
        "choice": choice,
        "reason": why,
        "figure": g if np.isfinite(g) else 1e9,
        "unit": "dB gained by the probabilistic model (max over bins)",
    }


def _iteration_losses(Xe, exposures, darks, n_dark, calibration, errors, prnu, k_sigma):
    """Worst SNR loss (dB over bins) after k = 1..MAX_ITERATIONS re-weighting steps."""
    Xe = np.asarray(Xe, dtype=np.float64)
    nd = [n or 1 for n in n_dark]
    kw: dict[str, Any] = dict(errors=errors, prnu=prnu, k_sigma=k_sigma)
    opt = predict_snr(Xe, exposures, calibration, darks, nd, **kw).snr_db
    # start: the non-saturated average (uniform weights over usable samples)
    su = np.zeros_like(Xe)
    suv = np.zeros_like(Xe)
    for t, d, n in zip(exposures, darks, nd):
        term = exposure_terms(Xe, t, calibration, d, n, "threshold", k_sigma)
        su += term.usable
        suv += term.usable * term.variance
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(su > 0, np.sqrt(suv) / np.maximum(su, 1e-300) / Xe, 0.0)
    losses = []
    for _ in range(MAX_ITERATIONS):
        low, high = (
            predict_snr(Xe, exposures, calibration, darks, nd, weight_at=Xe * (1 + sgn * delta), **kw)
            for sgn in (-1.0, 1.0)
        )
        worse = high.snr_db < low.snr_db
        worst_db = np.where(worse, high.snr_db, low.snr_db)
        worst_var = np.where(worse, high.variance, low.variance)
        fin = np.isfinite(opt)
        losses.append(float(np.max(opt[fin] - worst_db[fin])) if fin.any() else 0.0)
        delta = np.where(np.isfinite(worst_var), np.sqrt(worst_var) / Xe, 0.0)
    return losses


def iterations_decision(
    Xe: np.ndarray,
    exposures: Sequence[float],
    darks: Sequence[str],
    n_dark: Sequence[int],
    calibration: Calibration,
    errors: SystematicErrors,
    prnu: str,
    tolerance_db: float,
    k_sigma: float = K_SIGMA,
    saturation: str = "threshold",
) -> dict:
    """Number of merge re-weighting steps (Fig. 3) needed to be within the tolerance.

    Floors on top of the predicted loss, for samples that saturate: when a planned exposure
    saturates some of the irradiances ``Xe``, at least 2 (the near-saturation rule drops a
    sample by its value predicted from the previous estimate, so it acts from the second step
    on), and :data:`CONVERGED_ITERATIONS` where the full well clips before the ADC (measured on
    camera-A: one step leaves up to 438 of 12288 photosites beyond 6 sigma, two steps up to 3,
    converged ones up to 3); :data:`CONVERGED_ITERATIONS` with the probabilistic saturation
    model (its Newton steps must converge; the merge stops each photosite at its tolerance, so
    this costs time only where needed).

    Parameters
    ----------
    Xe : numpy.ndarray
        Eligible irradiances, e-/s (histogram points).
    exposures : sequence of float
        The planned exposure times, s.
    darks : sequence of str
        Dark strategy per exposure.
    n_dark : sequence of int
        Dark frames behind each exposure's dark subtraction (0 counts as 1).
    calibration : Calibration
        Camera model.
    errors : SystematicErrors
        Systematic errors of the simpler models.
    prnu : {"map", "scalar"}
        The PRNU model.
    tolerance_db : float
        SNR loss a simpler model may cost, dB.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.
    saturation : {"threshold", "probabilistic"}
        The saturation model chosen.

    Returns
    -------
    dict
        The decision: ``choice``, ``reason`` (text), ``figure`` and its ``unit``.
    """
    losses = _iteration_losses(Xe, exposures, darks, n_dark, calibration, errors, prnu, k_sigma)
    k = next((i + 1 for i, loss in enumerate(losses) if loss <= tolerance_db), MAX_ITERATIONS)
    why = f"{k} re-weighting step(s): predicted loss against the converged merge " + ", ".join(
        f"{loss:.3f} dB after {i + 1}" for i, loss in enumerate(losses[: max(k, 2)])
    )
    figure = losses[k - 1]
    saturates = any(np.any(usable_fraction(Xe, t, calibration, "threshold", k_sigma) == 0) for t in set(exposures))
    if saturation == "probabilistic":
        k = CONVERGED_ITERATIONS
        why = (
            f"{k} re-weighting steps (stop at the merge's tolerance): the probabilistic saturation model's "
            f"Newton steps must converge; without it " + why
        )
    elif saturates and full_well_clips_first(calibration):
        k = CONVERGED_ITERATIONS
        why = (
            f"{k} re-weighting steps (stop at the merge's tolerance): planned exposures saturate some pixels and "
            f"the full well clips before the ADC, so saturated samples slip under v_sat until the estimate has "
            f"converged; without it " + why
        )
    elif saturates and k < 2:
        k = 2
        why = (
            "2 re-weighting steps: planned exposures saturate some pixels and the near-saturation rule acts "
            "from the second step on; without it " + why
        )
    return {"choice": k, "reason": why, "figure": figure, "unit": "dB lost against the converged merge"}


def eligibility_decision(hist: IrradianceHistogram, elig: np.ndarray, t_min: float, calibration: Calibration) -> dict:
    """Which pixels the target applies to, and which the camera cannot measure.

    Parameters
    ----------
    hist : IrradianceHistogram
        The scene.
    elig : numpy.ndarray
        Boolean mask of the eligible histogram points.
    t_min : float
        Shortest allowed exposure time, s.
    calibration : Calibration
        Camera model.

    Returns
    -------
    dict
        The decision: ``choice``, ``reason`` (text), ``figure`` and its ``unit``.
    """
    inelig = ~elig & (hist.X > 0)
    n_sat = float(hist.weight[inelig].sum())
    n = max(hist.n_pixels, 1)
    parts = [f"{hist.n_pixels - n_sat - hist.n_nosignal:.0f} of {hist.n_pixels} pixels eligible"]
    if n_sat > 0:
        x_lim = float(hist.X[inelig].min())
        parts.append(
            f"{100 * n_sat / n:.3g} % of pixels ({n_sat:.0f}) are brighter than the shortest allowed "
            f"exposure ({t_min:.4g} s) can measure (X >= {x_lim:.4g} e-/s): excluded, the merge reports "
            "lower bounds there"
        )
    if hist.n_nosignal:
        parts.append(f"{hist.n_nosignal} pixels without signal (X <= 0) excluded")
    return {
        "choice": "not saturated at the shortest time",
        "reason": "; ".join(parts),
        "figure": n_sat / n,
        "unit": "fraction of pixels saturated even at the shortest time",
    }
