"""Predicted SNR of a merged exposure set (Eq. 12, 13, Sec. 8).

The variance of every exposure comes from :mod:`pipeline.noise` (``exposure_variance`` /
``exposure_weight``): this module never writes the noise formula itself. It adds what the
planner needs on top:

* which samples the merge will use: the threshold rule of Eq. 11 extended by the merge's
  near-saturation rule (a sample is dropped when its value predicted from the irradiance lies within ``k_sigma``
  of its own standard deviation of ``v_sat``), or, for the probabilistic saturation model
  (Eq. 8-10, a censored likelihood), the share of a sample's information the censored
  (Tobit) likelihood keeps;
* the *systematic* per-photosite errors a simpler model leaves in the estimate (dark current
  and bias not measured by a dark frame, PRNU ignored by a scalar gain). They do not average
  out over exposures, so the predicted SNR is X / sqrt(Var + bias^2) ("total-error SNR");
* weights evaluated at a wrong irradiance (a merge stopped after few iterations).

Units: X in e-/s per photosite, t in s, values in DN.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import log_ndtr, ndtr

from hdrcap.pipeline.blocks import flat_blocks
from hdrcap.pipeline.noise import Numeric, dark_factor, exposure_variance, exposure_weight, variance_core
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.times import same_exposure

__all__ = [
    "K_SIGMA",
    "SystematicErrors",
    "systematic_errors_from_calibration",
    "mean_dark_current",
    "predicted_value",
    "censored_information_fraction",
    "usable_fraction",
    "ExposureTerms",
    "exposure_terms",
    "SnrPrediction",
    "combine_terms",
    "predict_snr",
    "shared_dark_copies",
    "to_db",
]

#: Samples whose predicted value lies within this many of their own standard deviations of
#: v_sat are treated as saturated (the merge's near-saturation rule, an extension of Eq. 11).
K_SIGMA = 3.0


def to_db(snr_linear: ArrayLike) -> np.ndarray:
    """20 log10(SNR); -inf where the SNR is 0.

    Parameters
    ----------
    snr_linear : array_like
        SNR, linear (X / standard deviation).

    Returns
    -------
    numpy.ndarray
        SNR, dB.
    """
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.asarray(snr_linear, dtype=np.float64))


@dataclass(frozen=True)
class SystematicErrors:
    """Per-photosite errors that a simpler model leaves in the estimate (RMS over photosites).

    Attributes
    ----------
    dark_current : float
        RMS error of the dark current subtracted when no dark frame is taken ("model"
        strategy), e-/s. Appears in the estimate x_i as an error of the same size, e-/s.
    bias : float
        RMS error of the bias level subtracted by the "model" strategy, DN; appears in x_i as
        bias / (t g).
    prnu : float
        Relative RMS spread of the per-photosite gain a (dimensionless); a scalar gain leaves
        a relative error of this size in every photosite's estimate.
    prnu_map : float
        Relative RMS standard error of the PRNU map a_j (dimensionless): what the map itself
        leaves in every photosite's estimate (the merge's ``sigma_calibration``).
    """

    dark_current: float = 0.0
    bias: float = 0.0
    prnu: float = 0.0
    prnu_map: float = 0.0

    def __post_init__(self) -> None:
        for name in ("dark_current", "bias", "prnu", "prnu_map"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"SystematicErrors.{name} must be finite and >= 0, got {v!r}")


def mean_dark_current(calibration: Calibration) -> float:
    """Mean dark current of the calibration, e-/s (the map's mean when there is a map).

    Parameters
    ----------
    calibration : Calibration
        Camera model.

    Returns
    -------
    float
        Mean dark current, e-/s.
    """
    if calibration.dark_current_map is not None:
        return _map_mean(calibration.dark_current_map)
    return float(calibration.params.dark_current)


#: Means of calibration maps already computed, by the map's identity (a plan asks for the mean
#: dark current hundreds of times; a 24 Mpixel map takes ~30 ms to average). Calibration maps
#: are never modified in place.
_MAP_MEANS: dict[int, tuple[weakref.ref, float]] = {}


def _map_mean(arr) -> float:
    """np.mean of a map, computed once per map object (float)."""
    hit = _MAP_MEANS.get(id(arr))
    if hit is not None and hit[0]() is arr:
        return hit[1]
    value = float(np.mean(arr))
    try:
        ref = weakref.ref(arr)
    except TypeError:  # not weak-referenceable (e.g. a list): no caching
        return value
    for key in [k for k, (r, _) in _MAP_MEANS.items() if r() is None]:
        del _MAP_MEANS[key]
    _MAP_MEANS[id(arr)] = (ref, value)
    return value


def _rms(arr, chunk: int = 1 << 20) -> float:
    """Root mean square of a map (float64 accumulation, ``chunk`` values at a time: no
    full-size float64 copy), 0 for None."""
    if arr is None:
        return 0.0
    a = np.asarray(arr).ravel()
    if not a.size:
        return 0.0
    total = sum(float(np.sum(np.square(b, dtype=np.float64))) for b in flat_blocks(a, chunk))
    return float(np.sqrt(total / a.size))


def systematic_errors_from_calibration(
    calibration: Calibration, dark_rel_error: float | None = None
) -> SystematicErrors:
    """Default :class:`SystematicErrors` of a calibration: the per-photosite errors that the
    merge puts into ``sigma_calibration`` (RMS over the photosites; the standard error of a
    spatial mean would be 40-100 times too small).

    * dark current: the RMS standard error of the dark-current map (without a map: the
      standard error of the calibrated D), combined with a relative error ``dark_rel_error``
      of the mean dark current: 0.05 with a map (temperature drift of ~0.3 C with the 6.3 C
      doubling law), 0.3 without one (a scalar D ignores the dark-current non-uniformity,
      typically tens of percent);
    * bias: the RMS standard error of the bias map (without a map: the offset non-uniformity
      ``bias_dsnu_DN`` combined with the standard error of mu_R);
    * PRNU: the spread of the calibration's PRNU map (what ``prnu="scalar"`` leaves; 0 without
      a map: nothing to choose) and the RMS standard error of the map itself (``prnu_map``).

    Parameters
    ----------
    calibration : Calibration
        Camera model (its standard errors, maps and parameters).
    dark_rel_error : float, optional
        Relative error of the mean dark current (default as above).

    Returns
    -------
    SystematicErrors
    """
    D = mean_dark_current(calibration)
    if dark_rel_error is None:
        dark_rel_error = 0.05 if calibration.dark_current_map is not None else 0.3
    se = calibration.stderr or {}
    if calibration.dark_current_map is not None and calibration.dark_current_map_stderr is not None:
        dark_se = _rms(calibration.dark_current_map_stderr)
    else:
        dark_se = float(se.get("dark_current", 0.0))
    dark = float(np.hypot(dark_se, dark_rel_error * D))
    if calibration.bias_map is not None:
        bias = _rms(calibration.bias_map_stderr)
    else:
        dsnu = ((calibration.provenance or {}).get("calibration") or {}).get("bias_dsnu_DN") or 0.0
        bias = float(np.hypot(float(se.get("mu_R", 0.0)), float(dsnu)))
    prnu = float(np.std(calibration.prnu)) if calibration.prnu is not None else 0.0
    prnu_map = _rms(calibration.prnu_stderr) if calibration.prnu is not None else 0.0
    return SystematicErrors(dark_current=dark, bias=bias, prnu=prnu, prnu_map=prnu_map)


def predicted_value(X: Numeric, t: ArrayLike, calibration: Calibration) -> np.ndarray:
    """Mean raw value mu_R + g t (X + D) of a photosite of irradiance X at time t, DN (Eq. 2).

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s.
    t : array_like
        Exposure time, s.
    calibration : Calibration
        Camera model (mean dark current).

    Returns
    -------
    numpy.ndarray
        Mean raw value, DN.
    """
    p = calibration.params
    X = np.asarray(X, dtype=np.float64)
    return p.mu_R + p.g * np.asarray(t, dtype=np.float64) * (X + mean_dark_current(calibration))


def _value_sigma(X, t, calibration: Calibration):
    """Standard deviation of the raw value, DN: Var(x_i) of :func:`exposure_variance` with no
    dark term, scaled back by (t g)^2 (Eq. 3)."""
    p = calibration.params
    t = np.asarray(t, dtype=np.float64)
    var_x = exposure_variance(X, t, p.g, p.sigma2_R, mean_dark_current(calibration), 1.0, "model")
    return np.sqrt(var_x) * t * p.g


def censored_information_fraction(z: ArrayLike) -> np.ndarray:
    """Expected Fisher information about the mean of one Gaussian sample censored from above
    (Tobit), in units of the uncensored sample's 1/s^2:

    Phi(z) - z phi(z) + phi(z)^2 / (1 - Phi(z)),  z = (c - E x)/s,

    the unsaturated part Phi(z) plus the censored part (1 - Phi(z)) lambda(z) (lambda(z) - z),
    lambda = phi/(1 - Phi) the inverse Mills ratio (the survival function's log-derivatives;
    the merge's variances are held at the estimate, Eq. 13, so only the mean depends on X).

    Parameters
    ----------
    z : array_like
        Distance of the censoring point above the mean, in standard deviations.

    Returns
    -------
    numpy.ndarray
        Information fraction in [0, 1]: 1 far below the censoring point, 0 far above.
    """
    z = np.asarray(z, dtype=np.float64)
    log_phi = -0.5 * z * z - 0.5 * np.log(2.0 * np.pi)
    phi = np.exp(log_phi)
    phi_lam = np.exp(2.0 * log_phi - log_ndtr(-z))  # phi^2 / (1 - Phi), finite for every z
    return np.clip(ndtr(z) - z * phi + phi_lam, 0.0, 1.0)


def usable_fraction(
    X: Numeric, t: ArrayLike, calibration: Calibration, saturation: str = "threshold", k_sigma: float = K_SIGMA
) -> np.ndarray:
    """Fraction of a sample's information the merge keeps, in [0, 1].

    ``"threshold"``: 1 where the predicted value plus ``k_sigma`` of its standard deviation is
    below v_sat, else 0 (Eq. 11 with the merge's near-saturation rule: predicted within k sigma of
    v_sat counts as saturated).
    ``"probabilistic"``: the expected Fisher information of the merge's censored (Tobit)
    likelihood (Eq. 8-10, a saturated sample contributes its survival probability) relative to
    an unsaturated sample's, :func:`censored_information_fraction` at z = (v_sat - v)/s: the
    unsaturated part Phi(z) plus what the censored samples carry. Where the full well clips
    first, the values that slip under v_sat (a fraction Phi(-3) of the clipped ones) are left
    out, as is the dark level's share of s (about 1 % of the variance at a clip level).

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s.
    t : array_like
        Exposure time, s.
    calibration : Calibration
        Camera model.
    saturation : {"threshold", "probabilistic"}
        Saturation model.
    k_sigma : float
        Margin of the threshold rule, standard deviations of the raw value.

    Returns
    -------
    numpy.ndarray
        Usable fraction in [0, 1].
    """
    v = predicted_value(X, t, calibration)
    s = _value_sigma(X, t, calibration)
    vsat = calibration.params.v_sat
    if saturation == "threshold":
        return (v + k_sigma * s < vsat).astype(np.float64)
    if saturation == "probabilistic":
        return censored_information_fraction((vsat - v) / s)
    raise ValueError(f"saturation must be 'threshold' or 'probabilistic', got {saturation!r}")


@dataclass(frozen=True)
class ExposureTerms:
    """What one exposure adds to the merge at each irradiance: usable weight W = u w
    ((e-/s)^-2), and the coefficients of the systematic dark (1 for the model strategy) and
    bias (1/(t g) for the model strategy, 1/(e-/s)/DN... i.e. e-/s per DN) errors."""

    weight: np.ndarray
    c_dark: np.ndarray
    c_bias: np.ndarray
    usable: np.ndarray
    variance: np.ndarray


def exposure_terms(
    X: Numeric,
    t: float,
    calibration: Calibration,
    dark: str = "model",
    n_dark: float = 1,
    saturation: str = "threshold",
    k_sigma: float = K_SIGMA,
    weight_at: ArrayLike | None = None,
    copies: int = 1,
) -> ExposureTerms:
    """Per-irradiance contribution of one exposure of ``t`` seconds with dark strategy ``dark``.

    The weight is the optimal weight of Eq. 13 (from :func:`pipeline.noise.exposure_weight`)
    evaluated at ``weight_at`` (default: the true irradiance ``X``), times the usable fraction.
    ``variance`` is the true Var(x_i) at ``X``.

    ``copies`` frames of this time that share one dark frame (``matched``, or one ``master``
    dark) form a group whose generalised least-squares variance is
    [Var(v)/n + k Var(b)]/(t g a)^2: each copy's terms are those of an independent sample with
    the dark factor n k, so that the n copies' weights sum to the group's.

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s.
    t : float
        Exposure time, s.
    calibration : Calibration
        Camera model.
    dark : str
        Dark strategy ("matched", "master", "model").
    n_dark : float
        Frames behind the dark subtraction.
    saturation : {"threshold", "probabilistic"}
        Saturation model.
    k_sigma : float
        Margin of the threshold rule, standard deviations of the raw value.
    weight_at : array_like, optional
        Irradiance at which the weight is evaluated, e-/s.
    copies : int
        Frames of this time sharing its dark frame (>= 1).

    Returns
    -------
    ExposureTerms
    """
    p = calibration.params
    X = np.asarray(X, dtype=np.float64)
    D = mean_dark_current(calibration)
    mu_w = X if weight_at is None else np.asarray(weight_at, dtype=np.float64)
    u = usable_fraction(X, t, calibration, saturation, k_sigma)
    if copies == 1:
        var = exposure_variance(X, t, p.g, p.sigma2_R, D, 1.0, dark, n_dark)
        w = exposure_weight(mu_w, t, p.g, p.sigma2_R, D, 1.0, dark, n_dark) * u
    else:
        k = dark_factor(dark, n_dark) * copies
        var = np.asarray(variance_core(np.maximum(X, 0.0), t, p.g, p.sigma2_R, D, 1.0, k), dtype=np.float64)
        w = u / variance_core(np.maximum(mu_w, 0.0), t, p.g, p.sigma2_R, D, 1.0, k)
    is_model = 1.0 if str(getattr(dark, "value", dark)) == "model" else 0.0
    return ExposureTerms(weight=w, c_dark=w * is_model, c_bias=w * is_model / (t * p.g), usable=u, variance=var)


@dataclass(frozen=True)
class SnrPrediction:
    """Predicted merge quality at each irradiance ``X`` (e-/s).

    ``snr`` is the total-error ratio X / sqrt(variance + bias^2); ``variance`` the random part
    ((e-/s)^2, inf where no exposure is usable); ``bias`` the RMS systematic error (e-/s);
    ``n_usable`` the number of exposures the merge keeps (fractional for the probabilistic
    saturation model).
    """

    X: np.ndarray
    snr: np.ndarray
    variance: np.ndarray
    bias: np.ndarray
    n_usable: np.ndarray

    @property
    def snr_db(self) -> np.ndarray:
        """The SNR, dB (:func:`to_db`)."""
        return to_db(self.snr)


def combine_terms(
    X: Numeric,
    sum_w: np.ndarray,
    sum_cd: np.ndarray,
    sum_cb: np.ndarray,
    errors: SystematicErrors,
    prnu: str = "map",
    sum_w2v: np.ndarray | None = None,
) -> SnrPrediction:
    """Merged variance 1/sum W (Eq. 12), or sum W^2 Var / (sum W)^2 when the weights are
    not the inverse variances (``sum_w2v``), the systematic error of the weighted mean, and the
    total-error SNR.

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s.
    sum_w : numpy.ndarray
        Sum of the usable weights, (e-/s)^-2.
    sum_cd, sum_cb : numpy.ndarray
        Sums of the weighted dark (dimensionless) and bias (e-/s per DN) error coefficients.
    errors : SystematicErrors
        Systematic errors of the simpler models.
    prnu : {"map", "scalar"}
        The PRNU model (a scalar gain adds ``errors.prnu * X``, the map its own error
        ``errors.prnu_map * X``).
    sum_w2v : numpy.ndarray, optional
        Sum of W^2 Var(x_i), when the weights are not the inverse variances.

    Returns
    -------
    SnrPrediction
        ``n_usable`` is left at 0 (the caller knows it).
    """
    X = np.asarray(X, dtype=np.float64)
    ok = sum_w > 0
    safe = np.where(ok, sum_w, 1.0)
    if sum_w2v is None:
        var = np.where(ok, 1.0 / safe, np.inf)
    else:
        var = np.where(ok, sum_w2v / safe**2, np.inf)
    bias2 = (errors.dark_current * sum_cd / safe) ** 2 + (errors.bias * sum_cb / safe) ** 2
    if prnu == "scalar":
        bias2 = bias2 + (errors.prnu * X) ** 2
    elif prnu == "map":
        bias2 = bias2 + (errors.prnu_map * X) ** 2
    else:
        raise ValueError(f"prnu must be 'map' or 'scalar', got {prnu!r}")
    bias2 = np.where(ok, bias2, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = np.where(ok, np.maximum(X, 0.0) / np.sqrt(var + bias2), 0.0)
    return SnrPrediction(X=X, snr=snr, variance=var, bias=np.sqrt(bias2), n_usable=np.zeros_like(X))


def _per_exposure(values: str | float | Iterable[Any] | None, n: int, name: str) -> list[Any]:
    if values is None or isinstance(values, (str, int, float)):
        return [values] * n
    each = list(values)
    if len(each) != n:
        raise ValueError(f"{name} has {len(each)} entries for {n} exposures")
    return each


def shared_dark_copies(times: Sequence[float], darks: Sequence[str], n_dark: Sequence[float]) -> list[int]:
    """Per exposure, how many exposures share its dark frame: those of the same time
    (:func:`pipeline.times.same_exposure`) and the same ``matched`` or ``master`` strategy (and
    master-dark frame count), as a capture session takes one dark frame (or serves one master
    dark) per exposure time; 1 for ``model``.

    Parameters
    ----------
    times : sequence of float
        Exposure times, s.
    darks : sequence of str
        Dark strategy per exposure.
    n_dark : sequence of float
        Master-dark frame count per exposure.

    Returns
    -------
    list of int
        Group size per exposure (>= 1).
    """
    keys = [(float(t), str(getattr(d, "value", d)), n) for t, d, n in zip(times, darks, n_dark)]
    return [
        1 if d == "model" else sum(1 for u, e, m in keys if e == d and m == n and same_exposure(u, t))
        for t, d, n in keys
    ]


def predict_snr(
    X: Numeric,
    times: Sequence[float],
    calibration: Calibration,
    darks: str | Sequence[str] = "model",
    n_dark: float | Sequence[float] = 1,
    *,
    errors: SystematicErrors | None = None,
    prnu: str = "map",
    saturation: str = "threshold",
    k_sigma: float = K_SIGMA,
    weight_at: ArrayLike | None = None,
) -> SnrPrediction:
    """Predicted SNR of the merge of exposures ``times`` at irradiance ``X`` (Eq. 12, 13; Sec. 8).

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s per photosite (pixels or histogram bins).
    times : sequence of float
        Exposure times, s (repeats allowed: repeats of a ``matched`` or ``master`` time share
        one dark frame, :func:`shared_dark_copies`).
    calibration : Calibration
        Camera model; its mean dark current and the scalar parameters are used.
    darks : str or sequence of str
        Dark strategy per exposure ("matched", "master", "model").
    n_dark : float or sequence of float
        Frames in the master dark per exposure (``"master"`` only).
    errors : SystematicErrors, optional
        Systematic errors of the simpler models (default: none).
    prnu : {"map", "scalar"}
        Whether the merge corrects PRNU per photosite or with a scalar gain.
    saturation : {"threshold", "probabilistic"}
        Saturation model of the merge.
    k_sigma : float
        Margin of the threshold rule, standard deviations of the value.
    weight_at : array_like, optional
        Irradiance at which the merge evaluates its weights (default: the true X, i.e. a
        converged merge).

    Returns
    -------
    SnrPrediction
    """
    X = np.asarray(X, dtype=np.float64)
    times = [float(t) for t in times]
    errors = errors or SystematicErrors()
    dark_each = _per_exposure(darks, len(times), "darks")
    n_dark_each = _per_exposure(n_dark, len(times), "n_dark")
    sw = np.zeros_like(X)
    scd = np.zeros_like(X)
    scb = np.zeros_like(X)
    sw2v = np.zeros_like(X) if weight_at is not None else None
    nu = np.zeros_like(X)
    copies = shared_dark_copies(times, dark_each, n_dark_each)
    for t, d, n, m in zip(times, dark_each, n_dark_each, copies):
        term = exposure_terms(X, t, calibration, d, n if n else 1, saturation, k_sigma, weight_at, m)
        sw += term.weight
        scd += term.c_dark
        scb += term.c_bias
        nu += term.usable
        if sw2v is not None:
            sw2v += term.weight**2 * term.variance
    pred = combine_terms(X, sw, scd, scb, errors, prnu, sw2v)
    return SnrPrediction(X=pred.X, snr=pred.snr, variance=pred.variance, bias=pred.bias, n_usable=nu)
