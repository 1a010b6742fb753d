"""The weighting functions of Table 1 and a plug-compatible weighted-average merge.

Every previous method merges the per-exposure estimates x_i with a weighted mean (Eq. 1),
mu = sum_i w(v_i) x_i / sum_i w(v_i), and differs only in the weight it gives to the
observed output value v_i. This module implements each weight of Table 1 for a **linear**
raw sensor, registered by name in :data:`WEIGHTING_METHODS` (the style of colour-hdri's
``weighting_function_Debevec1997``), and :func:`merge_weighted`, which merges a bracket
with any of them into the same :class:`pipeline.result.HdrResult` as the optimal merge.

Linear sensor. All weights take ``v``, the raw value minus the black level (bias) in DN, as
the camera outputs it. For a linear camera the inverse response of Table 1 is
g(v) = f^-1(v) = v / g (electrons; g is the camera gain in DN/e-), so g'(v) = 1/g and
d/dv log g(v) = 1/v. Substituting gives the closed forms listed in each docstring. Note that
Mann-Picard and Mitsunaga-Nayar coincide (w = v) on a linear sensor, and Robertson is
t^2 v (~ t^3 at constant irradiance, Sec. 7).

Following their papers, every baseline evaluates its weight at the OBSERVED value, so the
noise of the sample leaks into its own weight (one reason they lose, Sec. 7). Tsin and
Kirk-Andersen use the camera model's standard deviation / variance evaluated at the observed
value (:func:`pipeline.noise.exposure_variance` at x = v/(t g), without dark-frame variance or
PRNU, which those papers do not model). The registry's ``optimal`` is Eq. 13 evaluated at the
observed value, single pass; the real optimal estimator is the iterative maximum-likelihood
merge of :mod:`pipeline.merge.accumulator`, which evaluates Eq. 13 at the current estimate.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.darks import DarkResolver
from hdrcap.pipeline.noise import DarkStrategy, exposure_variance
from hdrcap.pipeline.params import Calibration, SensorParams
from hdrcap.pipeline.result import HdrResult

__all__ = [
    "WEIGHTING_METHODS",
    "weighting_function_Uniform",
    "weighting_function_MannPicard",
    "weighting_function_DebevecMalik",
    "weighting_function_MitsunagaNayar",
    "weighting_function_Reinhard",
    "weighting_function_Robertson",
    "weighting_function_Tsin",
    "weighting_function_KirkAndersen",
    "weighting_function_Optimal",
    "weights",
    "merge_weighted",
]


def _v_max(params: SensorParams) -> float:
    """Largest usable output value above black, DN: v_sat - mu_R."""
    return float(params.v_sat - params.mu_R)


def _pos(v) -> np.ndarray:
    return np.maximum(np.asarray(v, dtype=np.float64), 0.0)


def weighting_function_Uniform(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Uniform weight, w = 1 (Sec. 7; Table 1 lists its alternatives; shown optimal in [1]
    under other assumptions).

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model (unused).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t``.
    """
    return np.ones(np.broadcast(np.asarray(v), np.asarray(t)).shape)


def weighting_function_MannPicard(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Mann & Picard (1995), Table 1: w = 1 / (d/dv log g(v)).

    The certainty of an output value is the inverse of the quantisation step in log
    exposure. Linear sensor: g(v) = v/g, d/dv log g(v) = 1/v, hence **w = v** (clipped at 0).

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    return np.broadcast_to(_pos(v), np.broadcast(np.asarray(v), np.asarray(t)).shape).copy()


def weighting_function_DebevecMalik(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Debevec & Malik (1997), Table 1 hat: w = min(v - v_min, v_max - v).

    Linear sensor: v_min = 0 (the black level), v_max = v_sat - mu_R; clipped at 0.

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    v = np.asarray(v, dtype=np.float64)
    w = np.maximum(np.minimum(v, _v_max(params) - v), 0.0)
    return np.broadcast_to(w, np.broadcast(v, np.asarray(t)).shape).copy()


def weighting_function_MitsunagaNayar(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Mitsunaga & Nayar (1999), Table 1 SNR weight: w = g(v) / g'(v) (Appendix A, Eq. 19).

    Linear sensor: g(v)/g'(v) = (v/g)/(1/g) = **v** (clipped at 0); in expectation
    v = g mu_X t, i.e. w ~ t, the optimal weight when readout noise vanishes (Appendix A).

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    return weighting_function_MannPicard(v, t, params)


def weighting_function_Reinhard(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Reinhard et al. (2005), Table 1 SNR times hat: w = g(v)/g'(v) [1 - (v/v_mid - 1)^12].

    Linear sensor: w = v [1 - (v/v_mid - 1)^12] with v_mid = (v_sat - mu_R)/2, clipped at 0.

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    v = np.asarray(v, dtype=np.float64)
    v_mid = 0.5 * _v_max(params)
    w = np.maximum(v * (1.0 - (v / v_mid - 1.0) ** 12), 0.0)
    return np.broadcast_to(w, np.broadcast(v, np.asarray(t)).shape).copy()


def weighting_function_Robertson(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Robertson et al. (2003), Table 1 variance weight: w = t^2 / (d/dv log g(v)).

    The output variance is replaced by the Mann-Picard term. Linear sensor: **w = t^2 v**
    (clipped at 0), ~ t^3 at constant irradiance (Sec. 7).

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    t = np.asarray(t, dtype=np.float64)
    return t * t * _pos(v)


def _observed_variance(v, t, params: SensorParams) -> np.ndarray:
    """Var(x_i) of the model at the observed value: x = v/(t g), shot + readout noise only
    (no dark-frame variance, no PRNU), from :func:`pipeline.noise.exposure_variance`.
    Equals (g v + sigma2_R) / (t g)^2."""
    t = np.asarray(t, dtype=np.float64)
    x_obs = np.asarray(v, dtype=np.float64) / (t * params.g)
    return exposure_variance(x_obs, t, params.g, params.sigma2_R, D=0.0, a=1.0, dark=DarkStrategy.MODEL)


def weighting_function_Tsin(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Tsin, Ramesh & Kanade (2001), Table 1 standard-deviation weight: w = t / sigma_g(v).

    sigma_g(v) is the standard deviation of g(v) = v/g, which Tsin et al. estimate from the
    images; here it is the calibrated model's value at the observed output,
    sigma_v^2 = g v + sigma2_R (Eq. 3 with E = v/g). Since Var(x_i) = sigma_g(v)^2 / t^2, the
    weight is **w = 1 / sqrt(Var(x_i)) = t g / sqrt(g v + sigma2_R)**: the square root of the
    inverse variance, hence sub-optimal (it over-weights values near the noise floor).

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    return 1.0 / np.sqrt(_observed_variance(v, t, params))


def weighting_function_KirkAndersen(v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Kirk & Andersen (2006), Table 1 variance weight: w = t^2 / (g'(v)^2 sigma_v^2).

    Linear sensor, their simplified noise model (shot + readout noise, no dark-current shot
    noise, no spatial noise) evaluated at the observed value: sigma_v^2 = g v + sigma2_R,
    g'(v) = 1/g, hence **w = t^2 g^2 / (g v + sigma2_R) = 1 / Var(x_i | observed v)**.

    Parameters
    ----------
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model: g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN).
    **model
        Ignored (keeps one signature for every method).

    Returns
    -------
    numpy.ndarray
        Weights, float64, the broadcast shape of ``v`` and ``t`` (relative: only their ratios
        across exposures matter).
    """
    return 1.0 / _observed_variance(v, t, params)


def weighting_function_Optimal(
    v: ArrayLike,
    t: ArrayLike,
    params: SensorParams,
    *,
    a: float | np.ndarray = 1.0,
    D: float | np.ndarray | None = None,
    dark: DarkStrategy | str = DarkStrategy.MATCHED,
    n_dark: float = 1,
    **model: Any,
) -> np.ndarray:
    """Granados et al. (2010), Eq. 13, evaluated at the OBSERVED value (single pass):

    w = t^2 g^2 a^2 / (g^2 t (a x + 2D) + 2 sigma2_R) with x = max(v/(t g a) - D/a, 0) for one
    matched dark frame; other dark strategies as in :func:`pipeline.noise.exposure_variance`.
    This is what a one-pass merge can do from a single sample; the maximum-likelihood merge
    (:mod:`pipeline.merge.accumulator`) evaluates Eq. 13 at the current estimate instead, iteratively.

    Parameters
    ----------
    v, t, params
        As :func:`weighting_function_Uniform`; ``v`` includes the dark signal g t D.
    a : float or numpy.ndarray
        PRNU gain (mean 1).
    D : float or numpy.ndarray, optional
        Dark current, e-/s (default ``params.dark_current``).
    dark : {"matched", "master", "model"}
        Dark strategy.
    n_dark : float
        Frames in a master dark.

    Returns
    -------
    numpy.ndarray
        Inverse variances of the single-sample estimates, s^2 e-^-2 (float64), the broadcast
        shape of ``v`` and ``t``.
    """
    D = params.dark_current if D is None else D
    t = np.asarray(t, dtype=np.float64)
    x_obs = (np.asarray(v, dtype=np.float64) / (t * params.g) - D) / a
    return 1.0 / exposure_variance(x_obs, t, params.g, params.sigma2_R, D, a, dark, n_dark)


#: Registry: method name -> weighting function ``w(v, t, params, **model)``.
WEIGHTING_METHODS: dict[str, Callable[..., np.ndarray]] = {
    "uniform": weighting_function_Uniform,
    "mann-picard": weighting_function_MannPicard,
    "debevec-malik": weighting_function_DebevecMalik,
    "mitsunaga-nayar": weighting_function_MitsunagaNayar,
    "reinhard": weighting_function_Reinhard,
    "robertson": weighting_function_Robertson,
    "tsin": weighting_function_Tsin,
    "kirk-andersen": weighting_function_KirkAndersen,
    "optimal": weighting_function_Optimal,
}


def weights(method: str, v: ArrayLike, t: ArrayLike, params: SensorParams, **model: Any) -> np.ndarray:
    """Weight of a registered method (Table 1).

    Parameters
    ----------
    method : str
        A name of :data:`WEIGHTING_METHODS`.
    v : array_like
        Observed raw value minus black level, DN.
    t : array_like
        Exposure time, s.
    params : SensorParams
        Camera model.
    **model
        Further model inputs of the method (``a``, ``D``, ``dark``, ``n_dark``).

    Returns
    -------
    numpy.ndarray
        Weights (unit of the method), float64.
    """
    try:
        fn = WEIGHTING_METHODS[method]
    except KeyError:
        raise InputError(f"unknown weighting {method!r}; choose from {', '.join(WEIGHTING_METHODS)}") from None
    return fn(v, t, params, **model)


def _model_maps(calibration: Calibration):
    """(PRNU gain a, dark current D in e-/s, bias in DN) of the calibration: maps where it has
    them, else its scalars."""
    p = calibration.params
    a = calibration.prnu if calibration.prnu is not None else 1.0
    D = calibration.dark_current_map if calibration.dark_current_map is not None else p.dark_current
    bias = calibration.bias_map if calibration.bias_map is not None else p.mu_R
    return a, D, bias


def _dark_levels(values, times, calibration: Calibration, darks, n_dark) -> tuple[list, DarkStrategy]:
    """Per-exposure dark level b_i (DN) and the dark strategy: the bias plus the calibrated
    dark current without darks (``model``), else the dark frame that
    :class:`pipeline.merge.darks.DarkResolver` serves each exposure time (``matched``; ``master``
    when each dark averages ``n_dark`` > 1 frames)."""
    p = calibration.params
    _a, D, bias = _model_maps(calibration)
    if darks is None:
        return [bias + t * p.g * D for t in times], DarkStrategy.MODEL
    if isinstance(darks, np.ndarray) and darks.ndim == 2:
        darks = [darks] * len(times)
    darks = list(darks)
    if len(darks) != len(times):
        raise InputError(f"{len(darks)} dark frames for {len(times)} exposures: give one per exposure")
    resolver = DarkResolver(frames_per_dark=n_dark)
    for d, t in zip(darks, times):
        if np.shape(d) != np.shape(values[0]):
            raise InputError(f"dark frame of shape {np.shape(d)} does not match the frames' {np.shape(values[0])}")
        resolver.add_dark(d, t)
    strategy = DarkStrategy.MATCHED if n_dark == 1 else DarkStrategy.MASTER
    levels = []
    for t in times:
        src = resolver.resolve(t, strategy)
        assert src is not None  # every exposure time has its dark frame (added above)
        levels.append(np.asarray(src.data, dtype=np.float64))
    return levels, strategy


def _check_bracket(values, times, method: str) -> tuple[list, list[float], tuple]:
    """The bracket as lists (frames, exposure times in s) and its shape; InputError when the
    method is unknown, the lengths differ, a time is not positive or the sizes differ."""
    if method not in WEIGHTING_METHODS:
        raise InputError(f"unknown weighting {method!r}; choose from {', '.join(WEIGHTING_METHODS)}")
    values = list(values)
    times = [float(t) for t in times]
    if not values or len(values) != len(times):
        raise InputError(f"{len(values)} frames for {len(times)} exposure times")
    if any(not (t > 0 and np.isfinite(t)) for t in times):
        raise InputError(f"exposure times must be finite and > 0, got {times}")
    shape = np.shape(values[0])
    if any(np.shape(v) != shape for v in values):
        raise InputError("frames of the bracket differ in size")
    return values, times, shape


def _weighted_mean(values, times, blacks, weigh, params: SensorParams, a, bias, shape):
    """Eq. 1 over the usable samples (raw value below v_sat, Eq. 11): the estimate (e-/s; the
    plain mean where every usable weight is 0, 0 where nothing is usable), the weights and
    usable masks per exposure, and the number of usable samples per photosite."""
    sw = np.zeros(shape)
    swx = np.zeros(shape)
    sx = np.zeros(shape)
    n_ok = np.zeros(shape)
    ws, oks = [], []
    for raw, t, b in zip(values, times, blacks):
        raw = np.asarray(raw, dtype=np.float64)
        ok = raw < params.v_sat
        x = (raw - b) / (t * params.g * a)
        w = np.where(ok, weigh(raw - bias, t), 0.0)
        sw += w
        swx += w * np.where(ok, x, 0.0)
        sx += np.where(ok, x, 0.0)
        n_ok += ok
        ws.append(w)
        oks.append(ok)
    has_w = sw > 0
    plain = n_ok > 0
    irr = np.where(has_w, swx / np.where(has_w, sw, 1.0), np.where(plain, sx / np.maximum(n_ok, 1), 0.0))
    return irr, ws, oks, has_w, n_ok


def _propagated_sigma(ws, oks, has_w, times, mu_var, params: SensorParams, D, a, strategy, n_dark):
    """Standard deviation of the weighted mean, e-/s: sqrt(sum w_i^2 s_i^2) / sum w_i with
    s_i^2 the model's variance at ``mu_var`` (the plain-mean fallback uses w = 1)."""
    num = np.zeros(np.shape(mu_var))
    den = np.zeros(np.shape(mu_var))
    for w, ok, t in zip(ws, oks, times):
        wi = np.where(has_w, w, ok.astype(np.float64))
        s2 = exposure_variance(mu_var, t, params.g, params.sigma2_R, D, a, strategy, n_dark)
        num += wi * wi * s2
        den += wi
    return np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0) ** 2), 0.0)


def merge_weighted(
    values: Sequence[np.ndarray],
    times: Sequence[float],
    calibration: Calibration,
    darks: np.ndarray | Sequence[np.ndarray] | None = None,
    method: str = "uniform",
    *,
    n_dark: float = 1,
    variance_at: np.ndarray | None = None,
) -> HdrResult:
    """Merge a bracket with a Table 1 weighting (Eq. 1) into irradiance and uncertainty.

    Per exposure x_i = (v_i - b_i) / (t_i g a) (Eq. 6, the same estimate the optimal merge
    uses: dark subtracted, PRNU corrected), usable where the raw value is below v_sat
    (Eq. 11). The weight w_i = ``method``(v_i - bias, t_i) is taken from the observed value.
    The estimate is mu = sum w_i x_i / sum w_i over usable samples; where all usable weights
    are 0 (e.g. a hat at the noise floor) the plain mean of the usable samples is used.

    ``sigma`` is the propagated standard deviation of this weighted mean under the calibrated
    model (Sec. 7): sigma^2 = sum w_i^2 s_i^2 / (sum w_i)^2, with s_i^2 =
    :func:`pipeline.noise.exposure_variance` at ``variance_at`` (default: the estimate
    itself, clipped at 0). It ignores the weights' own randomness, so it understates the
    error of weights taken from the observed value at low counts.

    Parameters
    ----------
    values : sequence of 2-D arrays
        Raw frames, DN (uint16 or float), one per exposure.
    times : sequence of float
        Exposure times, s.
    calibration : Calibration
        Camera model; ``prnu``, ``bias_map`` and ``dark_current_map`` are used when present.
    darks : sequence of 2-D arrays or 2-D array, optional
        One dark frame per exposure (matched; a master dark when ``n_dark`` > 1), or one
        array used for every exposure. Without darks the bias and calibrated dark current
        are subtracted (``model`` strategy).
    method : str
        A name of :data:`WEIGHTING_METHODS`.
    n_dark : float
        Number of frames averaged in each dark (1: matched dark frames).
    variance_at : array_like, optional
        Irradiance (e-/s) at which to evaluate s_i^2, e.g. the simulator's truth.

    Returns
    -------
    HdrResult
        float32 irradiance (e-/s), sigma (e-/s) and nexp; saturated-everywhere photosites
        get the lower bound (v_sat - bias)/(t_min g a) with nexp = 0 and sigma = 0.
    """
    values, times, shape = _check_bracket(values, times, method)
    p = calibration.params
    a, D, bias = _model_maps(calibration)
    blacks, strategy = _dark_levels(values, times, calibration, darks, n_dark)
    model = {"a": a, "D": D, "dark": strategy, "n_dark": n_dark}
    fn = WEIGHTING_METHODS[method]
    irr, ws, oks, has_w, n_ok = _weighted_mean(
        values, times, blacks, lambda v, t: fn(v, t, p, **model), p, a, bias, shape
    )
    mu_var = irr if variance_at is None else np.broadcast_to(np.asarray(variance_at, dtype=np.float64), shape)
    sigma = _propagated_sigma(ws, oks, has_w, times, mu_var, p, D, a, strategy, n_dark)
    sat = n_ok == 0
    if np.any(sat):  # the lower bound of the shortest exposure at v_sat
        irr = np.where(sat, (p.v_sat - bias) / (min(times) * p.g * a), irr)
        sigma = np.where(sat, 0.0, sigma)
    info = {
        "method": f"weighted mean, {method} weighting (Table 1)",
        "weighting": method,
        "dark_strategy": strategy.value,
        "n_dark": n_dark,
        "exposure_times": times,
        "n_frames": len(values),
        "saturated_everywhere": int(sat.sum()),
        "sigma": "propagated std of the weighted mean: sum w^2 s^2 / (sum w)^2 (pipeline.noise)",
    }
    return HdrResult(
        irradiance=irr.astype(np.float32),
        sigma=sigma.astype(np.float32),
        nexp=n_ok.astype(np.float32),
        header={"merge": info},
    )
