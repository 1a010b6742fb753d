"""HDR merge (walking-skeleton version).

One re-weighting step of the paper's estimator: start from the non-saturated average of the
per-exposure estimates x_i (Eq. 6), weight each usable sample by the inverse of the model
variance at that estimate (Eq. 13, :func:`pipeline.noise.exposure_variance`), and report the
weighted mean with its standard deviation 1/sqrt(sum w) (Eq. 12). Samples at or above
v_sat are excluded (Eq. 11). The full iterative ML merge with dark strategies, the
probabilistic saturation model and a compiled kernel replaces this in the optimal-merge issue.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .errors import InputError
from .io import RawFrame, check_frames
from .noise import exposure_variance
from .params import Calibration

__all__ = ["MergeResult", "merge_frames"]


@dataclass
class MergeResult:
    """Irradiance (e-/s per photosite), its standard deviation (same unit) and the number of
    unsaturated exposures used per photosite (0: saturated everywhere, irradiance is a lower
    bound). ``info`` records the options and inputs."""

    irradiance: np.ndarray
    sigma: np.ndarray
    nexp: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def merge_frames(
    frames: Sequence[RawFrame],
    calibration: Calibration,
    darks: Sequence[RawFrame] | None = None,
) -> MergeResult:
    """Merge a bracket of raw frames into irradiance and uncertainty (Eq. 6, 11-13).

    Parameters
    ----------
    frames : sequence of RawFrame
        The bracket; any order.
    calibration : Calibration
        Camera model (g, mu_R, sigma2_R, v_sat, D; optional PRNU and dark-current maps).
    darks : sequence of RawFrame, optional
        One matching dark frame per exposure (same exposure time). Without darks the bias
        level and the calibrated dark current are subtracted.
    """
    frames = check_frames(frames)
    p = calibration.params
    shape = frames[0].shape
    if darks:
        darks = check_frames(darks, "dark frame")
        if darks[0].shape != shape:
            raise InputError(f"{darks[0].path}: dark frame size differs from the bracket's")
        by_time = {}
        for d in darks:
            by_time.setdefault(round(d.exposure_time, 12), d)
        missing = [f for f in frames if round(f.exposure_time, 12) not in by_time]
        if missing:
            raise InputError(
                f"{missing[0].path}: no dark frame with exposure time {missing[0].exposure_time:g} s"
            )
        dark_strategy = "matched"
    else:
        by_time = {}
        dark_strategy = "model"
    a = calibration.prnu if calibration.prnu is not None else 1.0
    D = calibration.dark_current_map if calibration.dark_current_map is not None else p.dark_current
    bias = calibration.bias_map if calibration.bias_map is not None else p.mu_R

    sum_x = np.zeros(shape)
    n_ok = np.zeros(shape)
    xs, oks = [], []
    for fr in frames:
        t = fr.exposure_time
        v = fr.data.astype(np.float64)
        if dark_strategy == "matched":
            b = by_time[round(t, 12)].data.astype(np.float64)
        else:
            b = bias + t * p.g * D
        x = (v - b) / (t * p.g * a)
        ok = v < p.v_sat
        xs.append(x)
        oks.append(ok)
        sum_x += np.where(ok, x, 0.0)
        n_ok += ok
    mu0 = np.where(n_ok > 0, sum_x / np.maximum(n_ok, 1), 0.0)

    sw = np.zeros(shape)
    swx = np.zeros(shape)
    for fr, x, ok in zip(frames, xs, oks):
        w = 1.0 / exposure_variance(mu0, fr.exposure_time, p.g, p.sigma2_R, D, a, dark_strategy)
        sw += np.where(ok, w, 0.0)
        swx += np.where(ok, w * x, 0.0)
    irr = np.where(sw > 0, swx / np.where(sw > 0, sw, 1.0), 0.0)
    sigma = np.where(sw > 0, 1.0 / np.sqrt(np.where(sw > 0, sw, 1.0)), 0.0)

    # Saturated everywhere: lower bound from the shortest exposure at the saturation limit.
    sat = n_ok == 0
    if np.any(sat):
        t_min = min(fr.exposure_time for fr in frames)
        bound = (p.v_sat - (bias if dark_strategy == "model" else p.mu_R)) / (t_min * p.g * a)
        irr = np.where(sat, bound, irr)
        sigma = np.where(sat, 0.0, sigma)
    info = {
        "method": "one-step inverse-variance (skeleton)",
        "dark_strategy": dark_strategy,
        "exposure_times": [fr.exposure_time for fr in frames],
        "n_frames": len(frames),
        "n_darks": len(darks or []),
        "saturated_everywhere": int(sat.sum()),
    }
    return MergeResult(
        irradiance=irr.astype(np.float32),
        sigma=sigma.astype(np.float32),
        nexp=n_ok.astype(np.float32),
        info=info,
    )
