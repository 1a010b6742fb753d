"""The calibration's maps as the merge kernels take them, and the inputs of one kernel call.

A per-photosite quantity of the camera model (PRNU gain a, dark current D in e-/s, bias in DN)
is passed to :mod:`pipeline.merge.kernels` as a :data:`MapTuple` ``(array, is_map, scalar)``:
a float32 map of the image's shape when ``is_map``, else ``scalar`` with a 1x1 placeholder
array (the kernels' :class:`pipeline.merge.kernels.MapArg`). This module builds them from a
:class:`pipeline.params.Calibration` without importing the kernels (numba), and reads them
back at chosen photosites.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.params import Calibration

if TYPE_CHECKING:
    from hdrcap.pipeline.merge.kernels import CameraConstants, FrameTable, MapSet

__all__ = ["MapTuple", "CalibrationMaps", "KernelInputs", "calibration_maps", "map_arg", "map_values"]

#: A kernel map argument: (float32 array or 1x1 placeholder, is_map, scalar).
MapTuple = tuple[np.ndarray, bool, float]


class CalibrationMaps(NamedTuple):
    """The calibration's maps of one merge, each a :data:`MapTuple`: ``prnu`` (gain a, mean 1;
    scalar 1 with ``prnu="scalar"``), ``dark_current`` (D, e-/s) and ``bias`` (DN); and which
    PRNU the merge uses (``prnu_used``: ``"map"`` or ``"scalar"``)."""

    prnu: MapTuple
    dark_current: MapTuple
    bias: MapTuple
    prnu_used: str


class KernelInputs(NamedTuple):
    """The inputs shared by :func:`pipeline.merge.kernels.merge_kernel` and
    :func:`pipeline.merge.kernels.calibration_terms_kernel`: plain lists of the frames'
    ``values`` and ``darks`` (DN; a 1x1 placeholder where a frame has no dark frame of its own)
    and the kernels' ``frames``, ``camera`` and ``maps`` tuples."""

    values: list[np.ndarray]
    darks: list[np.ndarray]
    frames: FrameTable
    camera: CameraConstants
    maps: MapSet


def map_arg(arr: Any, shape: Sequence[int], scalar: float, what: str) -> MapTuple:
    """A calibration map, or its scalar where there is none, as a kernel map argument.

    Parameters
    ----------
    arr : array_like or None
        The map (any numeric type), or None.
    shape : (int, int)
        The frames' shape (rows, columns).
    scalar : float
        The value where there is no map (unit of the map).
    what : str
        The map's name, for the error message.

    Returns
    -------
    MapTuple
        (float32 contiguous map, True, scalar), or (1x1 zeros, False, scalar) without a map.

    Raises
    ------
    InputError
        The map's shape is not ``shape``.
    """
    if arr is None:
        return np.zeros((1, 1), np.float32), False, float(scalar)
    arr = np.asarray(arr)
    if arr.shape != tuple(shape):
        raise InputError(f"calibration {what} map has shape {arr.shape}, the frames {tuple(shape)}")
    return np.ascontiguousarray(arr, dtype=np.float32), True, float(scalar)


def _finite_positive(arr: np.ndarray) -> bool:
    """Whether every value of ``arr`` is finite and > 0, from its least and largest value (a NaN
    makes the least NaN): two passes without the full-size masks (0.1 s at 24 Mpixel)."""
    lo, hi = arr.min(), arr.max()
    return bool(np.isfinite(lo) and np.isfinite(hi) and lo > 0)


def calibration_maps(calibration: Calibration, shape: Sequence[int], prnu: str) -> CalibrationMaps:
    """The PRNU, dark-current and bias maps of a merge as kernel map arguments.

    Parameters
    ----------
    calibration : Calibration
        Camera model and maps; without a map its scalar is used (a = 1, ``dark_current``,
        ``mu_R``).
    shape : (int, int)
        The frames' shape (rows, columns).
    prnu : {"map", "scalar"}
        Use the calibration's PRNU map (when it has one), or a = 1.

    Returns
    -------
    CalibrationMaps

    Raises
    ------
    InputError
        A map of another shape, or a PRNU map not finite and > 0 everywhere.
    """
    p = calibration.params
    use_map = prnu == "map" and calibration.prnu is not None
    a = map_arg(calibration.prnu if use_map else None, shape, 1.0, "PRNU")
    if use_map and not _finite_positive(a[0]):
        raise InputError("calibration PRNU map must be finite and > 0")
    dark_current = map_arg(calibration.dark_current_map, shape, p.dark_current, "dark-current")
    bias = map_arg(calibration.bias_map, shape, p.mu_R, "bias")
    return CalibrationMaps(a, dark_current, bias, "map" if use_map else "scalar")


def map_values(arg: MapTuple, index: Any) -> np.ndarray | float:
    """A kernel map argument's values at some photosites, float64.

    Parameters
    ----------
    arg : MapTuple
        (array, is_map, scalar).
    index : tuple
        Any numpy index of the image (slices, or arrays of rows and columns).

    Returns
    -------
    numpy.ndarray or float
        The map at ``index`` as float64, or the scalar as float.
    """
    arr, is_map, scalar = arg
    return np.asarray(arr[index], np.float64) if is_map else float(scalar)
