"""Accuracy of an HDR estimate against a known truth (simulator) or another estimate."""

from __future__ import annotations

import numpy as np

__all__ = ["error_against_truth"]


def error_against_truth(estimate: np.ndarray, sigma: np.ndarray, nexp: np.ndarray, truth: np.ndarray) -> dict:
    """Summarise the error of ``estimate`` against ``truth`` where some exposure was usable.

    Returns the median absolute relative error, the mean and standard deviation of the
    z-scores (estimate - truth) / sigma (1 for an honest sigma), the fraction of |z| > 3 and
    > 6, and how many photosites were saturated everywhere (excluded).
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
