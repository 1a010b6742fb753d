"""The merge's quality flags: saturated, defective and masked photosites (the ``quality`` channel).

The bits are :data:`pipeline.schema.QUALITY_BITS`. A photosite without a usable sample is
``saturated`` (``nexp = 0``, a lower bound); a defective one (the calibration's
``defect_map``, :data:`pipeline.params.DEFECT_BITS`) carries its defect bits and is no
measurement (``nexp = 0``, ``sigma = 0``); a sample masked in a frame (an impossible raw value)
is no sample of that frame and its photosite carries the ``masked`` bit. :func:`drop_masked`
prepares a frame before the kernels, the other functions fix their outputs up after them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.kernel_inputs import CalibrationMaps, map_values
from hdrcap.pipeline.params import DEFECT_BITS, SensorParams
from hdrcap.pipeline.schema import QUALITY_BITS

__all__ = ["quality_channel", "flag_defects", "flag_clip_rejected", "drop_masked", "flag_masked", "clear_unmeasured"]

_DEFECTS = np.uint8(sum(DEFECT_BITS.values()))


def quality_channel(nexp: np.ndarray, defect_map: np.ndarray | None) -> np.ndarray:
    """The per-photosite quality bit field (:data:`pipeline.schema.QUALITY_BITS`).

    Parameters
    ----------
    nexp : numpy.ndarray
        Unsaturated exposures used per photosite, as the iterations left it (0: saturated in
        every exposure, or no usable sample).
    defect_map : numpy.ndarray or None
        The calibration's defect bits (uint8, :data:`pipeline.params.DEFECT_BITS`), or None.

    Returns
    -------
    numpy.ndarray
        uint8, the shape of ``nexp``: defect bits | 16 where ``nexp == 0``.
    """
    q = (nexp == 0).view(np.uint8)  # a new array of 0/1: scaled in place, no further copies
    q *= np.uint8(QUALITY_BITS["saturated"])
    if defect_map is not None:
        dm = np.asarray(defect_map)
        if dm.shape != q.shape:
            raise InputError(f"calibration defect map has shape {dm.shape}, the frames {q.shape}")
        q |= dm.astype(np.uint8) & _DEFECTS
    return q


def flag_defects(
    irr: np.ndarray, sig: np.ndarray, nexp: np.ndarray, defect_map: np.ndarray | None
) -> tuple[np.ndarray, int]:
    """Mark defective photosites as no measurement, in place.

    Parameters
    ----------
    irr, sig, nexp : numpy.ndarray
        The merge's irradiance, sigma (e-/s) and usable-sample counts; ``sig`` and ``nexp``
        are set to 0 at defects (the irradiance keeps the kernel's value, which must not be
        used).
    defect_map : numpy.ndarray or None
        The calibration's defect bits, or None.

    Returns
    -------
    (numpy.ndarray, int)
        The quality channel (:func:`quality_channel`, from ``nexp`` before the change) and the
        number of defects.
    """
    quality = quality_channel(nexp, defect_map)
    if defect_map is None:  # no defect bits in the quality channel
        return quality, 0
    bad = (quality & _DEFECTS) != 0
    nexp[bad] = 0
    sig[bad] = 0
    return quality, int(bad.sum())


def flag_clip_rejected(quality: np.ndarray, rules: np.ndarray) -> None:
    """Set the ``clip_rejected`` bit where the merge's clip rule rejected a sample, in place.

    Parameters
    ----------
    quality : numpy.ndarray
        The quality channel, uint8; changed in place.
    rules : numpy.ndarray
        The merge kernel's rule bits per photosite, uint8 (bit
        :data:`pipeline.merge.kernels.RULE_CLIP`: a sample was rejected as possibly clipped).
    """
    from hdrcap.pipeline.merge.kernels import RULE_CLIP

    hit = (rules & np.uint8(RULE_CLIP)) != 0
    quality[hit] |= np.uint8(QUALITY_BITS["clip_rejected"])


def drop_masked(v: np.ndarray, mask: np.ndarray, v_sat: float, threshold: bool) -> np.ndarray:
    """The frame with its masked samples made no sample for the kernels (Eq. 11 drops them).

    With the threshold model a uint16 frame keeps its type: masked values at or above v_sat
    stay as they are (no copy), others become 65535 (the kernels drop values >= v_sat). The
    censored likelihood (Eq. 8-10) would read such a value as saturated, i.e. information: for
    it, and for float frames, a float32 copy with NaN (dropped by both models). The flags of the
    photosites this leaves without a sample are fixed after the kernels (:func:`flag_masked`).

    Parameters
    ----------
    v : numpy.ndarray
        uint16 or float32 mosaic, DN.
    mask : numpy.ndarray
        bool, True where the sample is masked.
    v_sat : float
        Saturation level, DN.
    threshold : bool
        The threshold saturation model (Eq. 11) is used.

    Returns
    -------
    numpy.ndarray
        ``v`` itself, or a copy with the masked samples replaced.
    """
    if threshold and v.dtype == np.uint16 and v_sat <= 65535:
        if np.all(v[mask] >= v_sat):
            return v
        out = v.copy()
        out[mask] = 65535
        return out
    out = v.astype(np.float32, copy=True)
    out[mask] = np.nan
    return out


def flag_masked(
    outputs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    masks: Sequence[np.ndarray | None],
    times: Sequence[float],
    params: SensorParams,
    maps: CalibrationMaps,
) -> dict[str, Any]:
    """The masked samples' fix-up after the kernels, in place.

    The ``masked`` bit where a frame was masked; where that left no usable sample (``nexp =
    0``, no defect), the lower bound of the shortest exposure not masked (as the kernel's,
    Eq. 11 at v_sat), or, masked in every frame, no information: irradiance and sigma 0 and no
    ``saturated`` bit.

    Parameters
    ----------
    outputs : (numpy.ndarray, numpy.ndarray, numpy.ndarray, numpy.ndarray)
        The merge's irradiance and sigma (e-/s), ``nexp`` and quality channel; changed in
        place.
    masks : sequence of numpy.ndarray or None
        Per frame, its masked samples (None: none).
    times : sequence of float
        Per frame, the exposure time the merge used, s.
    params : SensorParams
        The camera model's scalars (g, v_sat).
    maps : CalibrationMaps
        The merge's PRNU, dark-current and bias maps.

    Returns
    -------
    dict
        ``masked_per_frame`` (masked samples per frame), ``masked_photosites`` (photosites
        masked in at least one frame), ``masked_everywhere`` (in every frame).
    """
    irr, sig, nexp, quality = outputs
    counts = [0 if m is None else int(np.count_nonzero(m)) for m in masks]
    out = {"masked_per_frame": counts, "masked_photosites": 0, "masked_everywhere": 0}
    if not any(counts):
        return out
    hit = np.zeros(irr.shape, bool)
    for m in masks:
        if m is not None:
            hit |= m
    quality[hit] |= np.uint8(QUALITY_BITS["masked"])
    rows, cols = np.nonzero(hit & (nexp == 0) & ((quality & _DEFECTS) == 0))
    t_min = np.full(rows.size, np.inf)
    for m, t in zip(masks, times):
        keep = slice(None) if m is None else ~m[rows, cols]
        t_min[keep] = np.minimum(t_min[keep], t)
    bias, dark, prnu = (map_values(arg, (rows, cols)) for arg in (maps.bias, maps.dark_current, maps.prnu))
    with np.errstate(invalid="ignore", divide="ignore"):
        bound = ((float(params.v_sat) - bias) / (float(params.g) * t_min) - dark) / prnu
    none = ~np.isfinite(t_min)
    irr[rows, cols] = np.where(none, 0.0, bound)
    sig[rows[none], cols[none]] = 0.0
    quality[rows[none], cols[none]] &= ~np.uint8(QUALITY_BITS["saturated"])
    out["masked_photosites"] = int(np.count_nonzero(hit))
    out["masked_everywhere"] = int(np.count_nonzero(none))
    return out


def clear_unmeasured(sigma_calibration: np.ndarray, quality: np.ndarray, nexp: np.ndarray) -> None:
    """Set the calibration's error to 0 where the photosite is no measurement, in place.

    Parameters
    ----------
    sigma_calibration : numpy.ndarray
        The calibration's part of sigma, e-/s, float32; changed in place.
    quality : numpy.ndarray
        The quality channel: any bit but ``masked`` and ``clip_rejected`` makes the photosite
        no measurement.
    nexp : numpy.ndarray
        Usable samples per photosite (0: no measurement).
    """
    still = np.uint8(QUALITY_BITS["masked"] | QUALITY_BITS["clip_rejected"])  # bits of a measurement
    sigma_calibration[((quality & ~still) != 0) | (nexp == 0)] = 0.0
