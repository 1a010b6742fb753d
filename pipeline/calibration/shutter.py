"""Per-time shutter corrections, measured once for a camera (``hdrcap calibrate --shutter``).

Real shutters miss their nominal times by a few percent, systematically per time (and nominal
third stops are rounded: 1/125 s is not 2^-7 s). A bracket can estimate its own exposure ratios
only where its frames share well-exposed photosites (:mod:`hdrcap.pipeline.exposure_ratio`);
a camera's ladder of times, shot once on a static scene with times close enough to overlap,
measures every time's correction, which the merge then applies to any bracket:

* every frame's log correction l_i = log(t_eff,i / t_nom,i) comes from the pair estimator of
  :func:`~hdrcap.pipeline.exposure_ratio.estimate_exposure_ratios` (photosites well exposed in
  both frames of a pair, robust weighted mean of log(s_j / s_i), weighted least squares over
  the pairs) with the dark level of the calibration's model (offset map plus g t D_j, Eq. 5
  without a dark frame), its covariance included;
* the corrections of each nominal time are averaged over its frames, L_k, and anchored at the
  reference time (by default the longest): factor_k = exp(L_k - L_ref), so the reference's
  factor is 1 and the others are ratios of effective times measured against it (the paper's
  Sec. 7 normalisation, made once);
* the standard error of each factor combines the estimator's covariance, propagated through
  the averaging and the anchoring, with the frame-to-frame jitter: the scatter of the frames of
  one time about their mean beyond what the estimator's covariance explains (pooled over the
  times with >= 2 frames; bias drift between frames shows up here too), divided by the frame
  counts of the time and of the reference.

Units: times in s, factors and standard errors relative (dimensionless).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from hdrcap.pipeline.calibration.frames import check_shape, frame_data, frame_name, frame_time
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.exposure_ratio import RatioOptions, estimate_exposure_ratios, subsample_window
from hdrcap.pipeline.params import Calibration, ShutterTable
from hdrcap.pipeline.times import find_exposure, unique_exposures

__all__ = ["estimate_shutter_table", "shutter_summary"]


def _model_dark_level(calibration: Calibration, window, t: float) -> np.ndarray | float:
    """The dark level of a frame of nominal time ``t`` (s) on ``window``, DN: the offset map (or
    mu_R) plus g t D_j (or g t D), as the merge's model strategy has it (Eq. 5, no dark frame)."""
    p = calibration.params
    bias = p.mu_R if calibration.bias_map is None else np.asarray(calibration.bias_map[window], np.float64)
    dark = p.dark_current if calibration.dark_current_map is None else calibration.dark_current_map[window]
    return bias + p.g * t * np.asarray(dark, np.float64)


def _group_matrix(frame_times: list[float], times: list[float]) -> np.ndarray:
    """M (times x frames): row k averages the frames of time k."""
    M = np.zeros((len(times), len(frame_times)))
    for i, t in enumerate(frame_times):
        M[find_exposure(t, times), i] = 1.0
    return M / M.sum(axis=1, keepdims=True)


def _jitter(logs: np.ndarray, cov: np.ndarray, M: np.ndarray, counts: np.ndarray) -> float | None:
    """Relative frame-to-frame jitter of the effective time: the scatter of the frames of each
    time about their time's mean beyond the estimator's covariance (method of moments, pooled,
    floored at 0); None when no time has two frames."""
    dof = int(np.sum(counts - 1))
    if dof == 0:
        return None
    P = M[np.argmax(M > 0, axis=0)]  # row i: the averaging row of frame i's time
    R = np.eye(len(logs)) - P
    resid = R @ logs
    expected = float(np.trace(R @ cov @ R.T))
    return math.sqrt(max(float(resid @ resid) - expected, 0.0) / dof)


def estimate_shutter_table(
    frames: Iterable,
    calibration: Calibration,
    *,
    reference: float | None = None,
    options: RatioOptions | None = None,
    max_photosites: int = 250_000,
) -> ShutterTable:
    """Per-time shutter corrections from frames of a static scene (module docstring).

    Parameters
    ----------
    frames : iterable of frames
        Objects with ``data`` (2-D raw mosaic, DN), ``exposure_time`` (nominal, s) and optional
        ``path``: a static scene (a flat field or any scene that does not change) at the
        camera's exposure times, several frames per time allowed, adjacent times close enough
        that some photosites are well exposed in both (SNR >= ``options.min_snr`` in the shorter,
        <= ``options.max_level`` of the range in the longer). Streamed: only a subsample of at
        most ``max_photosites`` photosites of each frame is kept.
    calibration : Calibration
        The camera's calibration: g (DN/e-), sigma2_R (DN^2), v_sat (DN), the offset and dark
        current maps (dark level of each frame) and the defect map (photosites left out).
    reference : float, optional
        Reference time, s (one of the frames' times): its factor is 1. Default: the longest.
    options : RatioOptions, optional
        The pair estimator's settings (default :class:`RatioOptions()`).
    max_photosites : int
        Photosites of the subsample used.

    Returns
    -------
    ShutterTable

    Raises
    ------
    InputError
        Fewer than two distinct times, frames of different sizes, a reference time that is not
        among the frames', or a time that shares no well-exposed photosites with the chain of
        frames that reaches the reference (the message names it).
    """
    p = calibration.params
    values, darks, times = [], [], []
    window = excl = shape = first = None
    for k, fr in enumerate(frames):
        v = frame_data(fr)
        t = frame_time(fr)
        name = frame_name(fr, "shutter", k)
        check_shape(v, shape, name, first)
        if shape is None:
            shape, first = v.shape, name
            window = subsample_window(shape, max_photosites)
            if calibration.defect_map is not None:
                check_shape(np.asarray(calibration.defect_map), shape, "the calibration's defect map", name)
                excl = np.asarray(calibration.defect_map[window]) != 0
        if not (math.isfinite(t) and t > 0):
            raise InputError(f"{name}: shutter frames need an exposure time > 0, got {t!r}")
        values.append(np.asarray(v[window]))
        darks.append(_model_dark_level(calibration, window, t))
        times.append(t)
    distinct = sorted(unique_exposures(times))
    if len(distinct) < 2:
        raise InputError(f"shutter corrections need frames at >= 2 exposure times, got {len(distinct)}")
    ref_t = max(distinct) if reference is None else float(reference)
    ref = find_exposure(ref_t, distinct)
    if ref is None:
        raise InputError(
            f"shutter reference time {ref_t:g} s is not among the frames' times ({', '.join(f'{t:g}' for t in distinct)} s)"
        )
    est = estimate_exposure_ratios(
        values,
        darks,
        times,
        float(p.g),
        float(p.sigma2_R),
        float(p.v_sat),
        dark_factors=[0.0] * len(values),
        exclude=excl,
        options=options or RatioOptions(),
    )
    _check_connected(est, times, distinct, ref)
    M = _group_matrix(times, distinct)
    counts = np.array([int(np.count_nonzero(row)) for row in M])
    logs = np.log(np.asarray(est.factors))
    anchor = M - M[ref]  # L_k - L_ref
    assert est.covariance is not None  # estimate_exposure_ratios always computes it
    cov = anchor @ est.covariance @ anchor.T
    jitter = _jitter(logs, est.covariance, M, counts)
    var = np.diag(cov).copy()
    if jitter is not None:
        var += jitter**2 * (1.0 / counts + 1.0 / counts[ref])
    var[ref] = 0.0
    return ShutterTable(
        times=tuple(float(t) for t in distinct),
        factors=tuple(float(f) for f in np.exp(anchor @ logs)),
        stderr=tuple(float(s) for s in np.sqrt(np.maximum(var, 0.0))),
        reference=float(distinct[ref]),
        frames=tuple(int(c) for c in counts),
        jitter=jitter,
    )


def _check_connected(est, times: list[float], distinct: list[float], ref: int) -> None:
    """Refuse when a frame's time is not linked to the reference time by overlapping pairs."""
    ref_sets = {est.linked_set[i] for i, t in enumerate(times) if find_exposure(t, distinct) == ref} - {-1}
    for i, t in enumerate(times):
        if est.linked_set[i] not in ref_sets:
            raise InputError(
                f"shutter frame at {t:g} s shares no well-exposed photosites with the frames linked to the "
                f"reference time {distinct[ref]:g} s: add frames at times in between, or a scene with a "
                "wider range of irradiance"
            )


def shutter_summary(table: ShutterTable) -> dict:
    """The table as the calibration summary shows it.

    Parameters
    ----------
    table : ShutterTable

    Returns
    -------
    dict
        ``reference`` (s), ``jitter`` (relative or None) and ``times``: one entry per time with
        ``t`` (s), ``factor``, ``stderr`` (relative) and ``frames``.
    """
    return {
        "reference": table.reference,
        "jitter": table.jitter,
        "times": [
            {"t": t, "factor": f, "stderr": s, "frames": n}
            for t, f, s, n in zip(table.times, table.factors, table.stderr, table.frames)
        ],
    }
