"""The saturation limit v_sat = mean - 3 std of saturation frames (Sec. 6), DN."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from hdrcap.pipeline.calibration.frames import check_shape, frame_data, frame_name
from hdrcap.pipeline.calibration.stats import DEFAULT_CLIP, PixelStack, pair_statistics, robust_mean_std
from hdrcap.pipeline.errors import InputError

__all__ = ["estimate_saturation"]


def _pooled_limit(ms: list[float], vs: list[float], ns: list[int], n_sigma: float):
    """Pool the frames' clipped means (DN) and variances (DN^2), weighted by their photosite
    counts; return (v_sat, stderr, mean, std) in DN."""
    ns_a = np.array(ns, float)
    mean = float(np.sum(ns_a * ms) / ns_a.sum())
    var = float(np.sum(ns_a * (np.array(vs) + (np.array(ms) - mean) ** 2)) / ns_a.sum())
    std = float(np.sqrt(var))
    P = float(ns_a.sum())
    se = std * np.sqrt(1.0 / P + n_sigma**2 / (2.0 * P))
    return mean - n_sigma * std, float(max(se, 1e-12)), mean, std


def estimate_saturation(
    frames: Iterable, clip: float | None = DEFAULT_CLIP, n_sigma: float = 3.0
) -> tuple[float, float, float, float, int, np.ndarray | None]:
    """Saturation limit v_sat = mean - 3 std of saturation frames (Sec. 6), DN.

    With several frames the clipped spatial means and variances are pooled; the standard
    error combines the errors of the mean (std/sqrt(P)) and of the standard deviation
    (std/sqrt(2P)).

    Parameters
    ----------
    frames : iterable of frames
        Saturation frames (every photosite at full well; ``data`` in DN), consumed once.
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables outlier rejection.
    n_sigma : float
        Standard deviations below the mean, 3 in Sec. 6.

    Returns
    -------
    v_sat, stderr, mean, std : float
        The limit, its standard error, the pooled mean and standard deviation, DN.
    n_frames : int
        Frames used.
    saturation_map : numpy.ndarray (float32) or None
        With >= 3 frames, the per-photosite limit: the photosite's clipped mean minus
        ``n_sigma`` temporal standard deviations (pooled from the frame-pair differences), DN;
        else None.

    Raises
    ------
    InputError
        No frame, or frames of mixed size.
    """
    ms, vs, ns = [], [], []
    shape = first = None
    stack = None
    pending, pair_vars = None, []
    for i, fr in enumerate(frames):
        data = frame_data(fr)
        name = frame_name(fr, "saturation", i)
        check_shape(data, shape, name, first)
        if stack is None:
            shape, first = data.shape, name
            stack = PixelStack(shape)
        m, s, keep = robust_mean_std(data, clip)
        ms.append(m)
        vs.append(s * s)
        ns.append(int(keep.sum()))
        stack.add(data)
        if pending is None:
            pending = data
        else:
            pair_vars.append(pair_statistics(pending, data, clip).variance)
            pending = None
    if stack is None:  # made at the first frame
        raise InputError("no saturation frame given")
    sat_map = None
    if stack.n >= 3:
        mean_map, _, _ = stack.result(clip)
        sat_map = (mean_map - n_sigma * np.sqrt(max(float(np.mean(pair_vars)), 0.0))).astype(np.float32)
    del stack
    v_sat, se, mean, std = _pooled_limit(ms, vs, ns, n_sigma)
    return v_sat, se, mean, std, len(ms), sat_map
