"""Defective photosites: dead, weak, hot and stuck, from the PRNU map, the bias map (DSNU) and
the dark-current map, as a bit field per photosite.

EMVA 1288 (Release 3.1/4.0, defect-pixel characterisation) describes defects as photosites
whose dark signal (DSNU image) or photo-response (PRNU image) deviates from the mean, and
reports how many deviate by more than a given amount; it fixes no single threshold. hdrcap
uses these thresholds (:class:`DefectThresholds`, documented in docs/calibration.md):

* **dead** -- relative response a_j below ``dead_response`` (0.1): no usable response to light;
* **stuck** -- no response either (a_j below ``dead_response``) and an offset (bias map) more
  than ``stuck_sigma`` (6) standard deviations from mu_R, the standard deviation combining the
  bias DSNU and the offset map's own noise sigma2_R / n_bias: the photosite writes its own
  constant value whatever the light;
* **weak** -- a_j below 1 - max(``weak_deviation``, ``weak_sigma`` s_j) with s_j the PRNU
  spread and the a_j error combined (0.1 and 6: a response at least 10 % low and far outside
  the PRNU distribution), and not dead;
* **hot** -- dark current D_j above D by more than ``hot_sigma`` (6) times the combined spread
  of the dark current (DCNU) and the D_j error (needs a dark series).

A dead or stuck photosite gets the neutral PRNU gain a_j = 1 (so that the calibration file
stays valid: every a_j > 0); a weak one keeps its measured a_j (its response is real, only
low). The flag, not the value, tells the merge not to trust them. Units: a_j dimensionless,
DN, e-/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrcap.pipeline.calibration import _kernels as _k
from hdrcap.pipeline.params import DEFECT_BITS

__all__ = ["DEFECT_BITS", "DefectThresholds", "response_defects", "hot_defects", "neutral_prnu", "defect_counts"]


@dataclass(frozen=True)
class DefectThresholds:
    """Thresholds of the defect classes (see the module docstring).

    Attributes
    ----------
    dead_response : float
        a_j below this is no response (dead, or stuck with an abnormal offset).
    weak_deviation : float
        Least relative loss of response of a weak photosite.
    weak_sigma : float
        Least loss of a weak photosite, in standard deviations of a_j (PRNU and error).
    stuck_sigma : float
        Least offset of a stuck photosite from mu_R, in standard deviations of the bias map.
    hot_sigma : float
        Least excess dark current of a hot photosite, in standard deviations (DCNU and error).
    """

    dead_response: float = 0.1
    weak_deviation: float = 0.1
    weak_sigma: float = 6.0
    stuck_sigma: float = 6.0
    hot_sigma: float = 6.0


def response_defects(
    prnu: np.ndarray,
    prnu_stderr: np.ndarray | None,
    prnu_std: float,
    bias_map: np.ndarray | None,
    mu_R: float,
    sigma2_R: float,
    n_bias: int,
    dsnu: float,
    thresholds: DefectThresholds = DefectThresholds(),
) -> np.ndarray:
    """Dead, weak and stuck photosites from the PRNU map and the bias map.

    Parameters
    ----------
    prnu : numpy.ndarray
        a_j (Eq. 14), mean about 1.
    prnu_stderr : numpy.ndarray or None
        Standard error of each a_j.
    prnu_std : float
        Spatial spread of a_j without the estimation noise.
    bias_map : numpy.ndarray or None
        Per-photosite mean bias, DN (None: stuck photosites cannot be told from dead ones).
    mu_R, sigma2_R : float
        Bias level (DN) and readout variance (DN^2).
    n_bias : int
        Bias frames averaged in ``bias_map``.
    dsnu : float
        Spatial spread of the offset map without its noise, DN (NaN: unknown, taken as 0).
    thresholds : DefectThresholds

    Returns
    -------
    numpy.ndarray (uint8)
        Bit field of :data:`DEFECT_BITS` (dead, weak, stuck set here).
    """
    # one fused pass (float64 per photosite, no full-size temporaries)
    prnu = np.ascontiguousarray(prnu)
    out = np.zeros(prnu.shape, np.uint8)
    d = 0.0 if not np.isfinite(dsnu) else float(dsnu)
    bias_sd = float(np.sqrt(d * d + sigma2_R / max(n_bias, 1)))
    none = np.zeros((1, 1), np.float32)
    t = thresholds
    _k.response_defect_bits(
        prnu,
        none if prnu_stderr is None else np.ascontiguousarray(prnu_stderr),
        prnu_stderr is not None,
        float(prnu_std) ** 2,
        none if bias_map is None else np.ascontiguousarray(bias_map),
        bias_map is not None,
        float(mu_R),
        bias_sd,
        np.array([t.dead_response, t.weak_deviation, t.weak_sigma, t.stuck_sigma], np.float64),
        np.array([DEFECT_BITS["dead"], DEFECT_BITS["stuck"], DEFECT_BITS["weak"]], np.uint8),
        out,
    )
    return out


def hot_defects(
    raw: np.ndarray, raw_stderr: np.ndarray, D: float, dcnu_sd: float, thresholds: DefectThresholds = DefectThresholds()
) -> np.ndarray:
    """Hot photosites: dark current far above the population's.

    Parameters
    ----------
    raw, raw_stderr : numpy.ndarray
        Per-photosite regression dark current and its standard error, e-/s.
    D : float
        The scalar dark current, e-/s.
    dcnu_sd : float
        Spread of the dark current over normal photosites beyond the estimation noise, e-/s.
    thresholds : DefectThresholds

    Returns
    -------
    numpy.ndarray of bool
    """
    raw = np.ascontiguousarray(raw)
    out = np.empty(raw.shape, bool)
    _k.hot_mask(raw, np.ascontiguousarray(raw_stderr), float(D), float(dcnu_sd) ** 2, float(thresholds.hot_sigma), out)
    return out


def neutral_prnu(
    prnu: np.ndarray, prnu_stderr: np.ndarray | None, defects: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, float]:
    """a_j = 1 for dead and stuck photosites, the map renormalised to mean 1 over the normal ones.

    Parameters
    ----------
    prnu, prnu_stderr : numpy.ndarray
        a_j (Eq. 14) and its standard error (or None).
    defects : numpy.ndarray (uint8)
        Bit field of :data:`DEFECT_BITS`.

    Returns
    -------
    prnu, prnu_stderr : numpy.ndarray (float32)
        The neutralised, renormalised maps (new arrays).
    prnu_std : float
        Spatial spread of a_j over the normal photosites without the estimation noise.
    """
    normal = defects == 0
    a = np.array(prnu, np.float32)
    a[(defects & (DEFECT_BITS["dead"] | DEFECT_BITS["stuck"])) != 0] = 1.0
    scale = float(np.mean(a[normal], dtype=np.float64)) if normal.any() else 1.0
    a /= np.float32(scale)
    err = None if prnu_stderr is None else (np.asarray(prnu_stderr, np.float32) / np.float32(scale))
    var = float(np.var(a[normal], dtype=np.float64)) if normal.any() else 0.0
    noise = float(np.mean(np.square(err[normal], dtype=np.float64))) if err is not None and normal.any() else 0.0
    return a, err, float(np.sqrt(max(var - noise, 0.0)))


def defect_counts(defects: np.ndarray) -> dict[str, int]:
    """Photosites of each kind (a photosite may count in several) and in total.

    Parameters
    ----------
    defects : numpy.ndarray (uint8)

    Returns
    -------
    dict
        ``dead``, ``weak``, ``hot``, ``stuck`` and ``total`` (any flag).
    """
    counts = {k: int(np.count_nonzero(defects & bit)) for k, bit in DEFECT_BITS.items()}
    counts["total"] = int(np.count_nonzero(defects))
    return counts
