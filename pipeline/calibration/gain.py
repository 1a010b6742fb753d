"""The camera gain g, DN per electron: from flat pairs (Eq. 16, 17) and by the EMVA 1288
photon-transfer regression of the pair variance on the mean over 0-70 % of saturation, with
the dark temporal variance at each pair's exposure time (:class:`DarkVariance`) subtracted."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hdrcap.pipeline.calibration.stats import PairStats
from hdrcap.pipeline.times import unique_exposures

__all__ = [
    "prnu_correction_factor",
    "gain_from_pair",
    "gain_from_pairs",
    "PhotonTransferFit",
    "photon_transfer_gain",
    "DarkVariance",
    "fit_dark_variance",
    "usable_pairs",
    "nonlinearity_warnings",
    "linear_range_warnings",
]


def prnu_correction_factor(mu_X: float, sigma2_a: float, mu_D: float = 0.0) -> float:
    """Eq. 17: k = (mu_X (1 + sigma_a^2) + mu_D) / (mu_X + mu_D).

    Parameters
    ----------
    mu_X : float
        Mean light signal of the flats (e.g. DN or electrons).
    sigma2_a : float
        Spatial variance of the per-photosite gain a_j, dimensionless.
    mu_D : float
        Mean dark signal of the flats, same unit as ``mu_X``.

    Returns
    -------
    float
        k, dimensionless (>= 1).
    """
    return (mu_X * (1.0 + sigma2_a) + mu_D) / (mu_X + mu_D)


def gain_from_pair(pair: PairStats, mu_R: float, sigma2_R: float, k: float = 1.0) -> tuple[float, float]:
    """Camera gain from one flat pair, Eq. 16: g = (1/k) (var - sigma2_R) / (mean - mu_R).

    Parameters
    ----------
    pair : PairStats
        The flat pair (its ``variance`` is half the variance of the difference), DN, DN^2.
    mu_R : float
        Bias level, DN.
    sigma2_R : float
        Readout variance, DN^2.
    k : float
        Eq. 17 correction for the PRNU and the dark signal, dimensionless.

    Returns
    -------
    g, stderr : float
        DN per electron; the error comes from the pair variance's fourth-moment standard error.

    Raises
    ------
    ValueError
        The pair lies at or below the bias level.
    """
    signal = pair.mean - mu_R
    if signal <= 0:
        raise ValueError("flat pair at or below the bias level")
    g = (pair.variance - sigma2_R) / signal / k
    return float(g), float(pair.variance_stderr / signal / k)


def gain_from_pairs(
    pairs: list[PairStats], mu_R: float, sigma2_R: float, k: float = 1.0, sigma2_R_stderr: float = 0.0
) -> tuple[float, float, list[float]]:
    """Inverse-variance weighted average of Eq. 16 over several flat pairs.

    Sec. 6: "several gain estimates obtained from distinct flat frame differences should be
    averaged".

    Parameters
    ----------
    pairs : list of PairStats
        Flat pairs, DN, DN^2.
    mu_R : float
        Bias level, DN.
    sigma2_R : float
        Readout variance, DN^2.
    k : float
        Eq. 17 correction, dimensionless.
    sigma2_R_stderr : float
        Standard error of ``sigma2_R``, DN^2 (common to every pair).

    Returns
    -------
    g, stderr : float
        DN per electron; the error includes the common error of sigma2_R.
    per_pair_gains : list of float
        Eq. 16 of each pair, DN per electron.

    Raises
    ------
    ValueError
        No pairs, or a pair at or below the bias level.
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


def photon_transfer_gain(
    means: Sequence[float] | np.ndarray,
    variances: Sequence[float] | np.ndarray,
    saturation: float,
    fit_fraction: float = 0.7,
    variance_stderr: Sequence[float] | np.ndarray | None = None,
    common_stderr: float = 0.0,
) -> PhotonTransferFit:
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

    Parameters
    ----------
    means : array_like
        Mean above dark of each level, DN.
    variances : array_like
        Temporal variance above dark of each level, DN^2.
    saturation : float
        Saturation level above dark, DN.
    fit_fraction : float
        Upper end of the fit range, fraction of ``saturation``.
    variance_stderr : array_like, optional
        Standard error of each level's variance, DN^2.
    common_stderr : float
        Standard error of the dark variance subtracted from every level, DN^2.

    Returns
    -------
    PhotonTransferFit
        K (DN per electron), its standard error and the points.

    Raises
    ------
    ValueError
        Fewer than three levels inside the fit range.
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


@dataclass(frozen=True)
class DarkVariance:
    """Temporal variance of a dark frame against exposure time, sigma^2_y.dark(t) = a + b t.

    The readout variance plus the dark shot noise g^2 D t (EMVA 1288 subtracts it, measured at
    each exposure time, from the variance of the light pairs).

    Attributes
    ----------
    intercept : float
        a, DN^2.
    slope : float
        b, DN^2 per second.
    cov : tuple of float
        Covariance of (a, b): (var a, cov ab, var b), DN^4, DN^4/s, DN^4/s^2.
    n_pairs : int
        Dark pairs in the fit.
    times : tuple of float
        Their exposure times, s.
    """

    intercept: float
    slope: float
    cov: tuple[float, float, float]
    n_pairs: int
    times: tuple[float, ...]

    def at(self, t: float) -> tuple[float, float]:
        """The dark temporal variance at ``t`` seconds and its standard error, DN^2.

        Parameters
        ----------
        t : float
            Exposure time, s.

        Returns
        -------
        value, stderr : float
        """
        va, cab, vb = self.cov
        return self.intercept + self.slope * t, float(np.sqrt(max(va + 2 * t * cab + t * t * vb, 0.0)))


def fit_dark_variance(pairs: Sequence[PairStats]) -> DarkVariance | None:
    """Weighted straight-line fit of the dark pairs' temporal variance against exposure time.

    Weights are the inverse squared fourth-moment standard errors of the pair variances; the
    covariance is scaled up by the reduced chi-square when the points scatter more than their
    errors say.

    Parameters
    ----------
    pairs : sequence of PairStats
        Dark pairs (variance DN^2, exposure time s).

    Returns
    -------
    DarkVariance or None
        None with fewer than two distinct exposure times (the line is not determined).
    """
    if len(unique_exposures([p.exposure_time for p in pairs])) < 2:
        return None
    t = np.array([p.exposure_time for p in pairs], float)
    v = np.array([p.variance for p in pairs], float)
    w = 1.0 / np.maximum(np.array([p.variance_stderr for p in pairs], float), 1e-12) ** 2
    A = np.stack([np.ones_like(t), t], axis=1)
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    a, b = cov @ (A.T @ (w * v))
    if t.size > 2:
        chi2 = float(np.sum(w * (v - a - b * t) ** 2)) / (t.size - 2)
        cov = cov * max(chi2, 1.0)
    return DarkVariance(
        float(a),
        float(b),
        (float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])),
        int(t.size),
        tuple(float(x) for x in t),
    )


#: A pair is left out of the gain when more than this fraction of its photosites is censored
#: near saturation (its statistics would describe a minority of the sensor).
MAX_CENSORED_FRACTION = 0.5


def usable_pairs(
    pairs: Sequence[PairStats], mu_R: float, saturation: float, max_censored: float = MAX_CENSORED_FRACTION
) -> tuple[list[PairStats], list[dict]]:
    """The flat pairs that can give the gain, and a record of every pair and why.

    A pair is usable when its mean lies above the bias and at most ``max_censored`` of its
    photosites were censored near saturation; its level does not matter otherwise (censoring
    keeps its statistics unbiased up to saturation).

    Parameters
    ----------
    pairs : sequence of PairStats
        The flat pairs (DN, DN^2).
    mu_R : float
        Bias level, DN.
    saturation : float
        Saturation level above the bias, DN (for the recorded fraction).
    max_censored : float
        Largest censored fraction of a usable pair.

    Returns
    -------
    usable : list of PairStats
    log : list of dict
        Per pair: ``t`` (s), ``level`` (DN above bias), ``fraction_of_saturation``, ``n_used``,
        ``n_censored``, ``used`` (bool) and ``reason``.
    """
    usable, log = [], []
    for p in pairs:
        level = p.mean - mu_R
        frac = p.n_censored / max(p.n_used + p.n_rejected, 1)
        if level <= 0:
            reason = "at or below the bias level"
        elif frac > max_censored:
            reason = f"{100 * frac:.0f} % of photosites censored near saturation"
        else:
            reason = ""
            usable.append(p)
        log.append(
            {
                "t": p.exposure_time,
                "level": level,
                "fraction_of_saturation": level / saturation,
                "n_used": p.n_used,
                "n_censored": p.n_censored,
                "used": not reason,
                "reason": reason or "usable",
            }
        )
    return usable, log


def nonlinearity_warnings(
    means: np.ndarray,
    variances: np.ndarray,
    variance_stderr: np.ndarray,
    g: float,
    saturation: float,
    n_sigma: float = 4.0,
    min_relative: float = 0.01,
) -> list[str]:
    """Photon-transfer points that depart from the straight line sigma^2 = g mu.

    A point departs when its variance differs from g mu by more than ``n_sigma`` standard
    errors and by more than ``min_relative`` of g mu; near saturation this is the sign of a
    non-linear response (a compressing full well, a clipping ADC), which the gain must not
    include and a merge should not trust.

    Parameters
    ----------
    means, variances, variance_stderr : numpy.ndarray
        Photon-transfer points: mean above dark (DN), variance above dark (DN^2) and its
        standard error (DN^2).
    g : float
        The gain, DN per electron.
    saturation : float
        Saturation level above dark, DN.
    n_sigma, min_relative : float
        Thresholds.

    Returns
    -------
    list of str
        One warning naming the lowest departing level (empty when the points are linear).
    """
    x = np.asarray(means, float)
    model = g * x
    resid = np.asarray(variances, float) - model
    se = np.asarray(variance_stderr, float)
    bad = (x > 0) & (np.abs(resid) > n_sigma * se) & (np.abs(resid) > min_relative * model)
    if not bad.any():
        return []
    i = int(np.flatnonzero(bad)[np.argmin(x[bad])])
    n_above = int(np.count_nonzero(bad & (x >= x[i])))
    return [
        f"photon transfer is not linear from {100 * x[i] / saturation:.0f} % of saturation "
        f"({x[i]:.0f} DN above dark): variance {100 * resid[i] / model[i]:+.1f} % from g mu "
        f"({resid[i] / se[i]:+.1f} sigma), {n_above} of {int(np.count_nonzero(x >= x[i]))} "
        "levels from there depart; keep flats for the PRNU map and exposures below this level"
    ]


def linear_range_warnings(
    levels: Sequence[float] | np.ndarray, saturation: float, fit_fraction: float = 0.7
) -> list[str]:
    """A warning when every flat pair that gave the gain lies above the EMVA 1288 linear range.

    Near full well many sensors compress their response; the variance then falls faster than
    the mean and Eq. 16 comes out low (camera-R of the simulator: -1.1 % with every pair at
    87.5 % of saturation, six times its standard error on 256 x 256 photosites). Pairs at one
    level, or only above ``fit_fraction`` of saturation, cannot show it: the photon-transfer
    residuals (:func:`nonlinearity_warnings`) need points inside the linear range.

    Parameters
    ----------
    levels : array_like
        Mean above the bias of every pair that gave the gain, DN.
    saturation : float
        Saturation level above the bias, DN.
    fit_fraction : float
        Upper end of the linear range (EMVA 1288: 0.7), fraction of ``saturation``.

    Returns
    -------
    list of str
        One warning naming the pairs' range of levels, or none when a pair lies within the range.
    """
    frac = np.asarray(levels, float) / saturation
    if frac.size == 0 or np.any(frac <= fit_fraction):
        return []
    lo, hi = 100 * float(frac.min()), 100 * float(frac.max())
    span = f"{lo:.0f} %" if round(lo) == round(hi) else f"{lo:.0f}-{hi:.0f} %"
    return [
        f"gain from flat pairs at {span} of saturation only, above the EMVA 1288 linear range "
        f"(0-{100 * fit_fraction:.0f} %): a response that compresses near full well biases it low and "
        "pairs there cannot show it; add flat pairs at lower levels (a photon-transfer series)"
    ]
