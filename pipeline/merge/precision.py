"""The precision of the merge's weights: float32 where provably safe, else float64.

The iterations' weights and their sums may be computed in float32 (twice the SIMD width, see
:mod:`pipeline.merge.kernels`) when bounds of every float32 quantity, from the pixel types, the
calibration and the exposure times, lie well inside the float32 range (1e-30 to 1e30).
:func:`single_precision_safe` is that rule; the switch that turns float32 weights off for
every merge is :data:`pipeline.merge.accumulator.SINGLE_PRECISION_WEIGHTS`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from hdrcap.pipeline.merge.frames import FrameBook
from hdrcap.pipeline.merge.kernel_inputs import CalibrationMaps, MapTuple
from hdrcap.pipeline.params import SensorParams

__all__ = ["extrema", "single_precision_safe"]


def extrema(arg: MapTuple) -> tuple[float, float]:
    """The least and largest value of a kernel map argument.

    Maps are scanned on every call (about 3 % of a merge with two 4-megapixel maps), so a map
    changed in place is seen as it is now.

    Parameters
    ----------
    arg : MapTuple
        (array, is_map, scalar).

    Returns
    -------
    (float, float)
        (min, max) of the map, or (scalar, scalar); (nan, nan) when the map has a non-finite
        value.
    """
    arr, is_map, scalar = arg
    if not is_map:
        return float(scalar), float(scalar)
    lo, hi = float(np.min(arr)), float(np.max(arr))
    return (lo, hi) if np.isfinite(lo) and np.isfinite(hi) else (math.nan, math.nan)


def _dark_level_bound(darks: Sequence[np.ndarray], book: FrameBook, maps: CalibrationMaps, master: np.ndarray) -> float:
    """The largest |b_i| over the frames' dark levels, DN (the dark current at its largest)."""
    d_hi = extrema(maps.dark_current)[1]
    b_lo, b_hi = extrema(maps.bias)
    m_lo, m_hi = extrema((master, True, 0.0)) if book.master_dark is not None else (0.0, 0.0)
    b_abs = 0.0
    for d, kind, coef in zip(darks, book.kinds, book.coefs):
        if kind == 0:
            lo, hi = (0.0, 65535.0) if d.dtype == np.uint16 else extrema((d, True, 0.0))
        else:
            lo, hi = (b_lo, b_hi) if kind == 1 else (m_lo, m_hi)
            lo, hi = lo - abs(coef) * d_hi, hi + abs(coef) * d_hi
        b_abs = max(b_abs, abs(lo), abs(hi))
    return b_abs


def single_precision_safe(
    values: Sequence[np.ndarray],
    darks: Sequence[np.ndarray],
    master: np.ndarray,
    book: FrameBook,
    params: SensorParams,
    maps: CalibrationMaps,
) -> bool:
    """Whether the weights and their sums may be computed in float32.

    Integer frames only; float dark frames and maps are bounded by their extrema.

    Parameters
    ----------
    values : sequence of numpy.ndarray
        The frames as the kernel takes them, DN.
    darks : sequence of numpy.ndarray
        Their dark frames (a placeholder where a frame has none), DN.
    master : numpy.ndarray
        The single master dark as float32 (a placeholder without one), DN.
    book : FrameBook
        The frames' times and dark levels.
    params : SensorParams
        The camera model's scalars.
    maps : CalibrationMaps
        The merge's PRNU, dark-current and bias maps.

    Returns
    -------
    bool
        True when every bound lies within 1e-30 to 1e30.
    """
    if not all(v.dtype == np.uint16 for v in values):
        return False
    g, s2, v_sat = float(params.g), float(params.sigma2_R), float(params.v_sat)
    t = np.asarray(book.times, np.float64)
    a_lo, a_hi = extrema(maps.prnu)
    d_lo, d_hi = extrema(maps.dark_current)
    b_lo, b_hi = extrema(maps.bias)
    if not (a_lo > 0 and d_lo >= 0 and s2 > 0):
        return False
    b_abs = _dark_level_bound(darks, book, maps, master)
    tg_lo, tg_hi = float(t.min()) * g, float(t.max()) * g
    x_max = (abs(v_sat) + b_abs) / (tg_lo * a_lo)
    u_max = a_hi * x_max + d_hi
    var_hi = g * tg_hi * (u_max + d_hi) + 2.0 * s2
    w_hi = (tg_hi * a_hi) ** 2 / s2
    w_lo = (tg_lo * a_lo) ** 2 / var_hi
    n = len(values)
    bounds = [
        x_max,
        u_max,
        var_hi,
        w_hi * n,
        w_hi * n * x_max,
        (tg_hi * a_hi) ** 2,
        abs(v_sat) + abs(b_lo) + abs(b_hi),
    ]
    small = [s2, w_lo, (tg_lo * a_lo) ** 2]
    return bool(np.all(np.isfinite(bounds + small)) and max(bounds) <= 1e30 and min(small) >= 1e-30)
