"""Accuracy of an HDR estimate against a known truth (simulator) or another estimate.

Pure functions for the paper's evaluation (Sec. 7): SNR and efficiency (Cramér-Rao bound /
MSE) per irradiance bin from Monte-Carlo merges against the simulator's truth, paired
comparisons between two merges of the same data, normal Q-Q data (Fig. 6) and the weights of
every Table 1 method against the output value at constant irradiance (Fig. 2). The
Monte-Carlo driver that draws the frames from the simulator is :mod:`hdrcap.experiments.snr`:
this module knows nothing of cameras.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from hdrcap.pipeline.noise import exposure_weight, merged_variance
from hdrcap.pipeline.params import SensorParams

__all__ = [
    "error_against_truth",
    "log_bins",
    "bound_variance",
    "snr_per_bin",
    "paired_difference",
    "qq_data",
    "gaussianity",
    "weights_vs_output",
]


def error_against_truth(estimate: np.ndarray, sigma: np.ndarray, nexp: np.ndarray, truth: np.ndarray) -> dict:
    """Summarise the error of ``estimate`` against ``truth`` where some exposure was usable.

    Parameters
    ----------
    estimate, sigma : numpy.ndarray
        Merged irradiance and its standard deviation, e-/s.
    nexp : numpy.ndarray
        Unsaturated exposures per photosite (0: excluded).
    truth : numpy.ndarray
        True irradiance, e-/s.

    Returns
    -------
    dict
        ``n_used`` and ``saturated_everywhere`` (photosites), ``median_abs_relative_error`` and
        ``rms_relative_error`` (dimensionless), ``z_mean`` and ``z_std`` of the z-scores
        (estimate - truth) / sigma (1 for an honest sigma), ``fraction_abs_z_gt_3`` and
        ``fraction_abs_z_gt_6``, ``median_snr_db`` (dB). Only the two counts when no photosite
        was usable.
    """
    est = np.asarray(estimate, dtype=np.float64)
    sig = np.asarray(sigma, dtype=np.float64)
    tru = np.asarray(truth, dtype=np.float64)
    ok = (np.asarray(nexp) > 0) & (sig > 0)
    if not ok.any():
        return {"n_used": 0, "saturated_everywhere": int(est.size)}
    err = est[ok] - tru[ok]
    z = err / sig[ok]
    rel = np.abs(err) / np.maximum(tru[ok], 1e-300)
    return {
        "n_used": int(ok.sum()),
        "saturated_everywhere": int((np.asarray(nexp) == 0).sum()),
        "median_abs_relative_error": float(np.median(rel)),
        "rms_relative_error": float(np.sqrt(np.mean(rel**2))),
        "z_mean": float(z.mean()),
        "z_std": float(z.std()),
        "fraction_abs_z_gt_3": float(np.mean(np.abs(z) > 3)),
        "fraction_abs_z_gt_6": float(np.mean(np.abs(z) > 6)),
        "median_snr_db": float(np.median(20 * np.log10(np.maximum(np.abs(est[ok]) / sig[ok], 1e-12)))),
    }


def log_bins(truth: np.ndarray, n_bins: int) -> np.ndarray:
    """Logarithmically spaced bin edges spanning ``truth``.

    Parameters
    ----------
    truth : numpy.ndarray
        True irradiance, e-/s, > 0 with some range.
    n_bins : int
        Number of bins.

    Returns
    -------
    numpy.ndarray
        ``n_bins + 1`` edges, e-/s; the last lies just above the maximum so that it is binned.

    Raises
    ------
    ValueError
        A truth that is not positive or has no range.
    """
    tru = np.asarray(truth, dtype=np.float64)
    lo, hi = float(tru.min()), float(tru.max())
    if not (lo > 0 and hi > lo):
        raise ValueError("log_bins needs a positive truth with some range")
    edges = np.logspace(np.log10(lo), np.log10(hi), int(n_bins) + 1)
    edges[-1] = np.nextafter(hi, np.inf)
    return edges


def bound_variance(
    truth: ArrayLike,
    times: Sequence[float],
    params: SensorParams,
    a: ArrayLike = 1.0,
    D: ArrayLike | None = None,
    dark: str = "matched",
    n_dark: int = 1,
) -> np.ndarray:
    """The practical Cramér-Rao bound 1 / sum_i w_i(X) (Eq. 12, 13) at the true irradiance.

    An exposure counts when its expected raw value mu_R + g t (a X + D) lies below v_sat;
    w_i is :func:`pipeline.noise.exposure_weight` (Eq. 13 for ``dark="matched"``).

    Parameters
    ----------
    truth : array_like
        True irradiance X, e-/s.
    times : sequence of float
        Exposure times, s.
    params : SensorParams
        Sensor parameters (g in DN/e-, sigma2_R in DN^2, mu_R and v_sat in DN).
    a : array_like
        PRNU factor (scalar or map), dimensionless.
    D : array_like, optional
        Dark current, e-/s (default ``params.dark_current``).
    dark : str
        Dark strategy of the merge (``"matched"``: Eq. 13).
    n_dark : int
        Dark frames behind each dark subtraction.

    Returns
    -------
    numpy.ndarray
        The variance, (e-/s)^2; ``inf`` where every exposure saturates.
    """
    X = np.asarray(truth, dtype=np.float64)
    D = params.dark_current if D is None else D
    t = np.asarray(times, dtype=np.float64).reshape((-1,) + (1,) * X.ndim)
    expected = params.mu_R + params.g * t * (np.asarray(a) * X + np.asarray(D))
    return merged_variance(
        X,
        np.asarray(times, dtype=np.float64),
        params.g,
        params.sigma2_R,
        D,
        a,
        dark,
        n_dark,
        usable=expected < params.v_sat,
    )


def snr_per_bin(
    estimates: np.ndarray,
    truth: np.ndarray,
    edges: np.ndarray,
    bound: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> dict:
    """SNR, bias and efficiency of repeated estimates in irradiance bins (Sec. 7, Fig. 4).

    Errors are taken relative to the truth, e = (estimate - X) / X, so that photosites of a
    bin with slightly different irradiance pool fairly. Per bin:
    ``snr_db = -10 log10(mean e^2)`` (bias included, as in the paper), ``bias = mean e``,
    ``snr_db_se`` its Monte-Carlo standard error (delta method), ``bound_snr_db =
    -10 log10(mean(bound / X^2))`` and ``efficiency = mean(bound / X^2) / mean(e^2)``.

    Parameters
    ----------
    estimates : numpy.ndarray
        Shape (n_repetitions, ...) or the truth's shape, e-/s.
    truth : numpy.ndarray
        True irradiance, e-/s, shape ``estimates.shape[1:]``.
    edges : numpy.ndarray
        Bin edges (e.g. :func:`log_bins`).
    bound : numpy.ndarray, optional
        Bound variance per photosite, (e-/s)^2 (e.g. :func:`bound_variance`).
    valid : numpy.ndarray, optional
        Boolean mask of photosites to use (e.g. not saturated everywhere).

    Returns
    -------
    dict
        Lists per bin: ``center``, ``n``, ``snr_db``, ``snr_db_se``, ``bias``, ``mse_rel`` and,
        with ``bound``, ``bound_snr_db`` and ``efficiency``. Empty bins give None.
    """
    tru = np.asarray(truth, dtype=np.float64)
    est = np.asarray(estimates, dtype=np.float64)
    if est.shape == tru.shape:
        est = est[None]
    err = (est - tru) / tru
    sq = err**2
    bins = np.digitize(tru, edges) - 1
    use = np.ones(tru.shape, bool) if valid is None else np.asarray(valid, bool)
    out: dict[str, list] = {k: [] for k in ("center", "n", "snr_db", "snr_db_se", "bias", "mse_rel")}
    if bound is not None:
        out["bound_snr_db"], out["efficiency"] = [], []
        brel = np.asarray(bound, dtype=np.float64) / tru**2
    for k in range(len(edges) - 1):
        sel = (bins == k) & use
        out["center"].append(float(np.sqrt(edges[k] * edges[k + 1])))
        n = int(sel.sum()) * est.shape[0]
        out["n"].append(n)
        if n < 2:
            for key in out:
                if key not in ("center", "n"):
                    out[key].append(None)
            continue
        s = sq[:, sel].ravel()
        mse = float(s.mean())
        out["mse_rel"].append(mse)
        out["bias"].append(float(err[:, sel].mean()))
        out["snr_db"].append(float(-10 * np.log10(mse)))
        out["snr_db_se"].append(float(10 / np.log(10) * s.std() / np.sqrt(n) / mse))
        if bound is not None:
            b = float(np.mean(brel[sel]))
            out["bound_snr_db"].append(float(-10 * np.log10(b)) if np.isfinite(b) else None)
            out["efficiency"].append(b / mse if np.isfinite(b) else None)
    return out


def paired_difference(
    est_a: np.ndarray, est_b: np.ndarray, truth: np.ndarray, edges: np.ndarray, valid: np.ndarray | None = None
) -> dict:
    """Paired comparison of two merges of the same frames, per irradiance bin.

    d = e_a^2 - e_b^2 with e = (estimate - X)/X; per bin the mean of d and its standard error
    (photosites and repetitions treated as independent samples). A negative mean means ``a``
    has the lower mean squared error.

    Parameters
    ----------
    est_a, est_b : numpy.ndarray
        The two merges, e-/s, shape (n_repetitions, ...) or the truth's shape.
    truth : numpy.ndarray
        True irradiance, e-/s.
    edges : numpy.ndarray
        Bin edges, e-/s (e.g. :func:`log_bins`).
    valid : numpy.ndarray, optional
        Boolean mask of photosites to use.

    Returns
    -------
    dict
        Lists per bin: ``center`` (e-/s), ``mean`` and ``se`` of d (dimensionless), ``ratio``
        (MSE_a / MSE_b); None for bins with fewer than two samples.
    """
    tru = np.asarray(truth, dtype=np.float64)
    a = np.asarray(est_a, dtype=np.float64)
    b = np.asarray(est_b, dtype=np.float64)
    if a.shape == tru.shape:
        a, b = a[None], b[None]
    ea, eb = ((a - tru) / tru) ** 2, ((b - tru) / tru) ** 2
    d = ea - eb
    bins = np.digitize(tru, edges) - 1
    use = np.ones(tru.shape, bool) if valid is None else np.asarray(valid, bool)
    out: dict[str, list] = {"center": [], "mean": [], "se": [], "ratio": []}
    for k in range(len(edges) - 1):
        sel = (bins == k) & use
        out["center"].append(float(np.sqrt(edges[k] * edges[k + 1])))
        if sel.sum() * a.shape[0] < 2:
            for key in ("mean", "se", "ratio"):
                out[key].append(None)
            continue
        dk = d[:, sel].ravel()
        out["mean"].append(float(dk.mean()))
        out["se"].append(float(dk.std(ddof=1) / np.sqrt(dk.size)))
        out["ratio"].append(float(ea[:, sel].mean() / eb[:, sel].mean()))
    return out


def qq_data(samples: ArrayLike) -> dict:
    """Normal Q-Q data of one sample (Fig. 6).

    Parameters
    ----------
    samples : array_like
        One sample (any unit, e.g. DN), flattened.

    Returns
    -------
    dict
        ``theoretical`` normal quantiles against the standardised ordered sample
        (``ordered``), the Q-Q correlation ``r``, the Shapiro-Wilk p-value ``shapiro_p``, and
        ``mean``, ``std`` (the sample's unit) and ``n``.
    """
    from scipy import stats

    x = np.asarray(samples, dtype=np.float64).ravel()
    (osm, osr), (slope, intercept, r) = stats.probplot(x, dist="norm")
    sd = x.std(ddof=1)
    z = (osr - x.mean()) / sd if sd > 0 else np.zeros_like(osr)
    p = float(stats.shapiro(x).pvalue) if sd > 0 else 0.0
    return {
        "theoretical": osm.tolist(),
        "ordered": z.tolist(),
        "r": float(r) if sd > 0 else 0.0,
        "shapiro_p": p,
        "mean": float(x.mean()),
        "std": float(sd),
        "n": int(x.size),
    }


def gaussianity(samples: np.ndarray, alpha: float = 0.05) -> dict:
    """Shapiro-Wilk test on many photosites at once (rows = photosites, columns = frames).

    Under a Gaussian model the fraction of photosites rejected at level ``alpha`` is
    ``alpha`` (binomial spread); a clearly larger fraction shows the approximation breaks.

    Parameters
    ----------
    samples : numpy.ndarray
        (photosites, frames) raw values, any unit (e.g. DN).
    alpha : float
        Level of the test.

    Returns
    -------
    dict
        ``rejection_rate`` (fraction), its binomial standard error under the Gaussian
        hypothesis ``rate_se_if_gaussian``, ``n_pixels``, ``n_samples``, ``alpha`` and
        ``constant_pixels`` (photosites with zero spread, counted as rejected).
    """
    from scipy import stats

    s = np.asarray(samples, dtype=np.float64)
    sd = s.std(axis=1)
    p = np.zeros(s.shape[0])
    ok = sd > 0
    if ok.any():
        p[ok] = stats.shapiro(s[ok], axis=1).pvalue
    rate = float(np.mean(p < alpha))
    return {
        "rejection_rate": rate,
        "rate_se_if_gaussian": float(np.sqrt(alpha * (1 - alpha) / s.shape[0])),
        "n_pixels": int(s.shape[0]),
        "n_samples": int(s.shape[1]),
        "alpha": alpha,
        "constant_pixels": int((~ok).sum()),
    }


def weights_vs_output(
    params: SensorParams, X: float, methods: Sequence[str] | None = None, n: int = 64, D: float | None = None
) -> dict:
    """Weights of each Table 1 method against the output value at constant irradiance (Fig. 2).

    Exposure times are chosen so that the expected output above black, v = g t (X + D), runs
    from 1 DN to v_sat - mu_R; each method's weight is evaluated at that (noise-free) output
    and normalised to a maximum of 1. ``optimal`` is Eq. 13 at the true X
    (:func:`pipeline.noise.exposure_weight`, matched dark frame).

    Parameters
    ----------
    params : SensorParams
        Sensor parameters.
    X : float
        The constant irradiance, e-/s.
    methods : sequence of str, optional
        Methods of :data:`pipeline.merge.weighting.WEIGHTING_METHODS` (default: all).
    n : int
        Number of output values.
    D : float, optional
        Dark current, e-/s (default ``params.dark_current``).

    Returns
    -------
    dict
        ``v`` (output above black, DN), ``t`` (exposure times, s), ``X`` (e-/s), ``sigma2_R``
        (DN^2) and ``weights`` (method -> normalised weights).
    """
    from hdrcap.pipeline.merge.weighting import WEIGHTING_METHODS

    D = params.dark_current if D is None else D
    v = np.linspace(1.0, params.v_sat - params.mu_R, n, endpoint=False)
    t = v / (params.g * (X + D))
    out = {"v": v.tolist(), "t": t.tolist(), "X": X, "sigma2_R": params.sigma2_R, "weights": {}}
    for name in methods or list(WEIGHTING_METHODS):
        if name == "optimal":
            w = exposure_weight(X, t, params.g, params.sigma2_R, D, 1.0, "matched")
        else:
            w = WEIGHTING_METHODS[name](v, t, params)
        w = np.asarray(w, dtype=np.float64)
        out["weights"][name] = (w / w.max()).tolist() if w.max() > 0 else w.tolist()
    return out
