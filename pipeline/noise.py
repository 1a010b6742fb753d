"""The camera noise model: the variance of one exposure's irradiance estimate.

This module is the single place where the variance of x_i (Eq. 6) is written. The merge,
the planner and the evaluation all call :func:`exposure_variance` (or its inverse,
:func:`exposure_weight`); nobody writes the formula again.

Dark strategies (how the dark level b_i of exposure i is obtained):

``matched``
    one dark frame taken at the same exposure time (the paper): Var(B) = g^2 t D + s_R^2 (Eq. 5).
``master``
    a master dark averaged from ``n_dark`` frames: Var(B) = (g^2 t D + s_R^2) / n_dark.
``model``
    no dark frame: bias level mu_R plus calibrated dark current t*g*D are subtracted;
    Var(B) = 0 (the calibration's own error is systematic, not per-sample noise).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from hdrcap.pipeline.dark_strategy import DarkStrategy

#: A number or an array of numbers: what the plain-arithmetic formulas take and return (numpy
#: arrays, Python floats, numpy scalars, and numba's float32/float64 scalars inside the kernels).
Numeric = float | np.floating | np.ndarray

__all__ = [
    "DarkStrategy",
    "dark_factor",
    "variance_of_rate",
    "variance_core",
    "difference_variance",
    "exposure_variance",
    "exposure_weight",
    "merged_variance",
    "snr",
    "snr_db",
    "fisher_information",
    "cramer_rao_bound",
]


def dark_factor(dark: DarkStrategy | str, n_dark: float = 1) -> float:
    """The factor k of the dark-level variance in Var(v_i - b_i) (Eq. 5).

    Parameters
    ----------
    dark : DarkStrategy or str
        Dark strategy.
    n_dark : float
        Frames averaged into the master dark (``master`` only; >= 1).

    Returns
    -------
    float
        1 (matched), 1/n_dark (master), 0 (model); dimensionless.
    """
    dark = DarkStrategy(dark)
    if dark is DarkStrategy.MATCHED:
        return 1.0
    if dark is DarkStrategy.MASTER:
        if not n_dark >= 1:
            raise ValueError(f"a master dark needs n_dark >= 1, got {n_dark!r}")
        return 1.0 / float(n_dark)
    return 0.0


def variance_of_rate(u: Numeric, g2t: Numeric, D: Numeric, sigma2_R: Numeric, k: float | np.floating) -> Numeric:
    """Var(v_i - b_i) = g^2 t (u + k D) + sigma_R^2 + k sigma_R^2: the raw value's variance
    (Eq. 3) plus k times the dark level's (Eq. 5), from the light frame's electron rate
    u = a max(mu, 0) + D. The one place the formula is written.

    Plain arithmetic without literals, so that it works on numpy arrays and, compiled by numba
    (inlined), on float32 or float64 scalars inside the merge kernel (:mod:`pipeline.merge.kernels`)
    in the precision of its arguments. With k = 0 it is Var(v_i) alone.

    Parameters
    ----------
    u : array_like
        Electron rate of the light frame, a max(mu, 0) + D, e-/s.
    g2t : array_like
        g^2 t, DN^2 s per e-.
    D : array_like
        Dark current, e-/s.
    sigma2_R : array_like
        Readout variance, DN^2.
    k : float
        :func:`dark_factor` (0: the variance of the raw value alone).

    Returns
    -------
    array_like
        Variance, DN^2.
    """
    return g2t * (u + k * D) + (sigma2_R + k * sigma2_R)


def difference_variance(
    mu_pos: Numeric, t: Numeric, g: float, sigma2_R: Numeric, D: Numeric, a: Numeric, k: float | np.floating
) -> Numeric:
    """Var(v_i - b_i) (Eq. 3, 5) of :func:`variance_of_rate` at the irradiance ``mu_pos``;
    scalar- and array-compatible.

    Parameters
    ----------
    mu_pos : array_like
        Irradiance estimate already clipped at 0, ``max(mu, 0)``, e-/s.
    t : array_like
        Exposure time, s.
    g : float
        Gain, DN/e-.
    a : array_like
        PRNU gain (mean 1).
    sigma2_R, D, k
        As :func:`variance_of_rate` (DN^2, e-/s, 1).

    Returns
    -------
    array_like
        Variance, DN^2.
    """
    return variance_of_rate(a * mu_pos + D, g * g * t, D, sigma2_R, k)


def variance_core(
    mu_pos: Numeric, t: Numeric, g: float, sigma2_R: Numeric, D: Numeric, a: Numeric, k: float | np.floating
) -> Numeric:
    """Var(x_i) = Var(v_i - b_i) / (t g a)^2 (Eq. 6); scalar- and array-compatible like
    :func:`difference_variance`.

    Parameters
    ----------
    mu_pos, t, g, sigma2_R, D, a, k
        As :func:`difference_variance` (e-/s, s, DN/e-, DN^2, e-/s, 1, 1).

    Returns
    -------
    array_like
        Variance of the single-exposure estimate, (e-/s)^2.
    """
    tga = t * g * a
    return difference_variance(mu_pos, t, g, sigma2_R, D, a, k) / (tga * tga)


def exposure_variance(
    mu: ArrayLike,
    t: ArrayLike,
    g: float,
    sigma2_R: float | np.ndarray,
    D: ArrayLike = 0.0,
    a: ArrayLike = 1.0,
    dark: DarkStrategy | str = DarkStrategy.MATCHED,
    n_dark: float = 1,
) -> np.ndarray:
    """Variance of the single-exposure estimate x_i, (e-/s)^2 (Eq. 3, 5, 6, 13).

    Var(x_i) = [g^2 t (a mu + D) + s_R^2 + k (g^2 t D + s_R^2)] / (t g a)^2, with k = 1 for a
    matched dark frame, 1/N for a master dark of N frames and 0 for the model strategy.
    With k = 1 this is the inverse of the paper's optimal weight, Eq. 13.

    Parameters
    ----------
    mu : array_like
        Current irradiance estimate, e-/s; negative values are treated as 0 (the model's
        variance cannot be below that of a dark pixel), the estimate itself is never clipped.
    t : array_like
        Exposure time, s (> 0).
    g : float
        Camera gain, DN/e-.
    sigma2_R : array_like
        Readout variance including quantisation, DN^2.
    D : array_like
        Dark current, e-/s.
    a : array_like
        Per-photosite PRNU gain (mean 1).
    dark : {"matched", "master", "model"}
        Dark strategy.
    n_dark : float
        Number of frames averaged in the master dark (``dark="master"`` only).

    Returns
    -------
    numpy.ndarray
        Variance in (e-/s)^2, float64, broadcast over the inputs.
    """
    k = dark_factor(dark, n_dark)
    mu = np.maximum(np.asarray(mu, dtype=np.float64), 0.0)
    t = np.asarray(t, dtype=np.float64)
    a = np.asarray(a, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64)
    return np.asarray(variance_core(mu, t, g, sigma2_R, D, a, k), dtype=np.float64)


def exposure_weight(
    mu: ArrayLike,
    t: ArrayLike,
    g: float,
    sigma2_R: float | np.ndarray,
    D: ArrayLike = 0.0,
    a: ArrayLike = 1.0,
    dark: DarkStrategy | str = DarkStrategy.MATCHED,
    n_dark: float = 1,
) -> np.ndarray:
    """Optimal weight w_i = 1 / Var(x_i) (Eq. 13).

    Parameters
    ----------
    mu, t, g, sigma2_R, D, a, dark, n_dark
        As :func:`exposure_variance`.

    Returns
    -------
    numpy.ndarray
        Weight, (e-/s)^-2, float64.
    """
    return 1.0 / exposure_variance(mu, t, g, sigma2_R, D, a, dark, n_dark)


def merged_variance(
    mu: ArrayLike,
    times: ArrayLike,
    g: float,
    sigma2_R: float | np.ndarray,
    D: ArrayLike = 0.0,
    a: ArrayLike = 1.0,
    dark: DarkStrategy | str = DarkStrategy.MATCHED,
    n_dark: float = 1,
    usable: ArrayLike | None = None,
) -> np.ndarray:
    """Variance of the ML estimate, 1 / sum_i w_i over the usable exposures (Eq. 12).

    Parameters
    ----------
    mu : array_like
        Irradiance, e-/s.
    times : array_like
        Exposure times, s, along the first axis.
    g, sigma2_R, D, a, dark, n_dark
        As :func:`exposure_variance`.
    usable : array_like of bool, optional
        Unsaturated samples, shape of the broadcast of ``times`` and ``mu`` (default: all).

    Returns
    -------
    numpy.ndarray
        Variance, (e-/s)^2; ``inf`` where no exposure is usable.
    """
    times = np.asarray(times, dtype=np.float64)
    mu = np.asarray(mu, dtype=np.float64)
    t = times.reshape(times.shape + (1,) * mu.ndim)
    w = exposure_weight(mu[None, ...], t, g, sigma2_R, D, a, dark, n_dark)
    if usable is not None:
        w = np.where(usable, w, 0.0)
    total = w.sum(axis=0)
    with np.errstate(divide="ignore"):
        return np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), np.inf)


def snr(
    mu: ArrayLike,
    times: ArrayLike,
    g: float,
    sigma2_R: float | np.ndarray,
    D: ArrayLike = 0.0,
    a: ArrayLike = 1.0,
    dark: DarkStrategy | str = DarkStrategy.MATCHED,
    n_dark: float = 1,
    usable: ArrayLike | None = None,
) -> np.ndarray:
    """SNR(X) = X sqrt(sum_i w_i(X)) (Sec. 8).

    Parameters
    ----------
    mu, times, g, sigma2_R, D, a, dark, n_dark, usable
        As :func:`merged_variance`.

    Returns
    -------
    numpy.ndarray
        Signal-to-noise ratio, linear (0 where no exposure is usable).
    """
    var = merged_variance(mu, times, g, sigma2_R, D, a, dark, n_dark, usable)
    mu = np.asarray(mu, dtype=np.float64)
    return np.where(np.isfinite(var), mu / np.sqrt(var), 0.0)


def snr_db(*args: Any, **kwargs: Any) -> np.ndarray:
    """SNR in decibels, 20 log10(SNR).

    Parameters
    ----------
    *args, **kwargs
        As :func:`snr`.

    Returns
    -------
    numpy.ndarray
        SNR, dB; -inf where the SNR is 0.
    """
    s = snr(*args, **kwargs)
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(s)


def fisher_information(
    X: ArrayLike, t: ArrayLike, g: float, sigma2_R: float | np.ndarray, D: Numeric = 0.0, a: Numeric = 1.0
) -> np.ndarray:
    """Fisher information of one unsaturated exposure about X.

    With s^2 = g^2 t (a X + D) + s_R^2 (dark level known exactly):
    I(X) = (g t a)^2 / s^2 + 1/2 (g^2 t a)^2 / s^4.

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s (negative values treated as 0).
    t : array_like
        Exposure time, s.
    g : float
        Gain, DN/e-.
    sigma2_R : array_like
        Readout variance, DN^2.
    D : array_like
        Dark current, e-/s.
    a : array_like
        PRNU gain (mean 1).

    Returns
    -------
    numpy.ndarray
        Fisher information, (e-/s)^-2.
    """
    X = np.maximum(np.asarray(X, dtype=np.float64), 0.0)
    t = np.asarray(t, dtype=np.float64)
    s2 = g * g * t * (a * X + D) + sigma2_R
    return (g * t * a) ** 2 / s2 + 0.5 * (g * g * t * a) ** 2 / s2**2


def cramer_rao_bound(
    X: ArrayLike, times: ArrayLike, g: float, sigma2_R: float | np.ndarray, D: Numeric = 0.0, a: Numeric = 1.0
) -> np.ndarray:
    """Cramér-Rao lower bound 1 / sum_i I_i(X) on Var(X_hat) for unsaturated exposures.

    Parameters
    ----------
    X : array_like
        Irradiance, e-/s.
    times : array_like
        Exposure times, s, along the first axis.
    g, sigma2_R, D, a
        As :func:`fisher_information`.

    Returns
    -------
    numpy.ndarray
        Lower bound of the variance, (e-/s)^2.
    """
    times = np.asarray(times, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    t = times.reshape(times.shape + (1,) * X.ndim)
    return 1.0 / fisher_information(X[None, ...], t, g, sigma2_R, D, a).sum(axis=0)
