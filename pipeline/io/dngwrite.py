"""Write a merged irradiance mosaic as a linear floating-point CFA DNG (as HDRMerge writes).

The DNG holds one uncompressed CFA image of IEEE floats (SampleFormat 3, 32 or 16 bits per
photosite) in IFD0, written with tifffile's writer and the DNG tags as extra tags. Its values
are the merge's irradiance (Eq. 12) in the unit of the merge (e-/s per photosite, or DN/s
after self-calibration) times ``2**-k``: k = 0 for 32-bit floats; for 16-bit floats the
smallest k that brings the largest value under half's maximum (a power of two scales a float
exactly). BlackLevel is 0, WhiteLevel the smallest integer not below the largest value (so
nothing is clipped by a raw developer), and the unit and the scale are written in
ImageDescription. The colour matrices, calibration illuminants, white balance (AsShotNeutral),
orientation and camera make and model of the first source frame are copied when it is a DNG
that has them. A non-DNG raw (CR2, NEF, ARW, ...) has no DNG colour tags: LibRaw's colour matrix
of the camera (``rgb_xyz_matrix``, Adobe's XYZ-to-camera matrix for D65) becomes ColorMatrix1
with CalibrationIlluminant1 D65, and the camera's white balance multipliers AsShotNeutral
(:func:`colour_from_libraw`). Without either, an identity colour matrix (D65) and a neutral
white balance.

:class:`CameraColour` is that colour metadata in one value: the merge records it in the EXR
header (``camera_colour``) so that ``hdrcap develop`` works from the EXR alone.

A DNG carries no uncertainty: sigma, sigma_calibration, nexp and quality stay in the EXR.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import atomic_output
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import UNIT_ELECTRONS

__all__ = [
    "CameraColour",
    "DngFloatLayout",
    "COPIED_TAGS",
    "camera_colour",
    "colour_from_dng_tags",
    "colour_from_libraw",
    "colour_tags",
    "dng_layout",
    "write_float_dng",
    "source_colour_tags",
]

_CFA_CODES = {"R": 0, "G": 1, "B": 2}

#: DNG/TIFF tags copied from the first source frame when present (number -> name):
#: colour matrices, camera calibrations, analog balance, white balance, forward matrices,
#: calibration illuminants, orientation, make, model and unique camera model.
COPIED_TAGS = {
    271: "Make",
    272: "Model",
    274: "Orientation",
    50708: "UniqueCameraModel",
    50721: "ColorMatrix1",
    50722: "ColorMatrix2",
    50723: "CameraCalibration1",
    50724: "CameraCalibration2",
    50727: "AnalogBalance",
    50728: "AsShotNeutral",
    50729: "AsShotWhiteXY",
    50778: "CalibrationIlluminant1",
    50779: "CalibrationIlluminant2",
    50964: "ForwardMatrix1",
    50965: "ForwardMatrix2",
}

#: Written when the source frame has no colour matrix: identity, D65, neutral white balance.
_DEFAULT_COLOUR = [
    (50721, 10, 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
    (50728, 5, 3, (1, 1, 1, 1, 1, 1), True),
    (50778, 3, 1, 21, True),
]

#: Largest finite float16 (65504).
_HALF_MAX = float(np.finfo(np.float16).max)


@dataclass(frozen=True)
class DngFloatLayout:
    """How the irradiance is stored in the float DNG.

    Attributes
    ----------
    bits : int
        32 or 16 bits per photosite (IEEE float).
    exponent : int
        k of the scale: stored value = irradiance * 2**-k (0 for 32 bits).
    white_level : int
        WhiteLevel tag, in stored units: ceil of the largest stored value, at least 1.
    """

    bits: int
    exponent: int
    white_level: int

    @property
    def scale(self) -> float:
        """Irradiance per stored unit (2**k)."""
        return 2.0**self.exponent


def dng_layout(irradiance: np.ndarray, bits: int = 32) -> DngFloatLayout:
    """The storage of ``irradiance`` in a float DNG of ``bits`` bits per photosite.

    Parameters
    ----------
    irradiance : numpy.ndarray
        2-D float mosaic (the merge's unit), all finite.
    bits : {32, 16}
        Float width.

    Returns
    -------
    DngFloatLayout

    Raises
    ------
    InputError
        Other widths, non-finite values, or a maximum too large for a 32-bit WhiteLevel.
    """
    if bits not in (16, 32):
        raise InputError(f"float DNG: bits per sample must be 16 or 32, got {bits}")
    if not np.all(np.isfinite(irradiance)):
        raise InputError("float DNG: the irradiance holds NaN or infinite values, which a raw developer cannot use")
    top = max(float(np.max(irradiance, initial=0.0)), 0.0)
    exponent = 0
    if bits == 16 and top > _HALF_MAX / 2:
        exponent = math.ceil(math.log2(top / (_HALF_MAX / 2)))
    white = max(1, math.ceil(top / 2.0**exponent))
    if white >= 2**32:
        raise InputError(f"float DNG: largest irradiance {top:.4g} exceeds the 32-bit WhiteLevel; use --dng-bits 16")
    return DngFloatLayout(bits, exponent, white)


def _tag_entry(tag) -> tuple | None:
    """A tifffile extratag tuple reproducing the TIFF tag ``tag`` (None for odd types)."""
    value = tag.value
    if tag.dtype == 2:  # ASCII
        return (tag.code, "s", 0, str(value), True)
    if isinstance(value, (int, float)):
        value = (value,)
    value = tuple(int(v) if not isinstance(v, float) else v for v in np.ravel(value))
    if tag.dtype in (5, 10):  # (S)RATIONAL: count is the number of fractions
        if len(value) % 2:
            return None
        return (tag.code, int(tag.dtype), len(value) // 2, value, True)
    return (tag.code, int(tag.dtype), len(value), value, True)


def source_colour_tags(path: str | os.PathLike[str]) -> list[tuple]:
    """The :data:`COPIED_TAGS` of a DNG's IFD0, as tifffile extratags.

    Parameters
    ----------
    path : str or Path
        A source frame; anything tifffile cannot open (PNG, non-TIFF raw) gives no tags.

    Returns
    -------
    list of tuple
        ``(code, dtype, count, value, True)`` per tag present.
    """
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            if not isinstance(page, tifffile.TiffPage):  # tifffile reads the first IFD as a page
                return []
            tags = page.tags
            entries = [_tag_entry(tags[code]) for code in COPIED_TAGS if code in tags]
    except (OSError, ValueError, tifffile.TiffFileError):
        return []
    return [e for e in entries if e is not None]


#: EXIF LightSource code of D65: the illuminant of LibRaw's colour matrices (Adobe's D65 matrix).
D65_LIGHT_SOURCE = 21

#: The 3x3 matrices of :class:`CameraColour` and the DNG tag of each.
_MATRIX_TAGS = {
    "color_matrix_1": 50721,
    "color_matrix_2": 50722,
    "camera_calibration_1": 50723,
    "camera_calibration_2": 50724,
    "forward_matrix_1": 50964,
    "forward_matrix_2": 50965,
}
#: The vectors of :class:`CameraColour`: DNG tag, length, TIFF type (5 RATIONAL).
_VECTOR_TAGS = {"analog_balance": (50727, 3), "as_shot_neutral": (50728, 3), "as_shot_white_xy": (50729, 2)}
_ILLUMINANT_TAGS = {"illuminant_1": 50778, "illuminant_2": 50779}


def _floats(value, n: int, what: str) -> tuple[float, ...] | None:
    """``n`` finite floats from a number sequence or TIFF (S)RATIONAL pairs (None stays None)."""
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise InputError(f"camera colour: {what} is not a list of numbers") from None
    if arr.size == 2 * n:  # (numerator, denominator) pairs as tifffile gives them
        num, den = arr[0::2], arr[1::2]
        if np.any(den == 0):
            raise InputError(f"camera colour: {what} has a zero denominator")
        arr = num / den
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise InputError(f"camera colour: {what} needs {n} finite numbers, got {arr.size}")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class CameraColour:
    """The colour metadata of a raw file, in the DNG 1.4 specification's terms (Chapter 6).

    Attributes
    ----------
    color_matrix_1 : tuple of 9 float
        ColorMatrix1: CIE XYZ to the camera's reference space under ``illuminant_1``, row by row.
    illuminant_1 : int
        CalibrationIlluminant1, an EXIF LightSource code (21 D65, 17 standard light A, 23 D50, ...).
    color_matrix_2 : tuple of 9 float, optional
        ColorMatrix2 under ``illuminant_2`` (DNG readers interpolate between the two).
    illuminant_2 : int, optional
        CalibrationIlluminant2.
    camera_calibration_1, camera_calibration_2 : tuple of 9 float, optional
        CameraCalibration1/2 (this unit's deviation from the model); identity when absent.
    forward_matrix_1, forward_matrix_2 : tuple of 9 float, optional
        ForwardMatrix1/2: white-balanced camera space to XYZ D50.
    analog_balance : tuple of 3 float, optional
        AnalogBalance; ones when absent.
    as_shot_neutral : tuple of 3 float, optional
        AsShotNeutral: the camera values of a neutral surface in the scene's light (the white
        balance), any scale.
    as_shot_white_xy : tuple of 2 float, optional
        AsShotWhiteXY: the white's CIE 1931 chromaticity, when a file gives it instead.
    source : str
        Where the values come from (file and reader).
    """

    color_matrix_1: tuple[float, ...]
    illuminant_1: int = D65_LIGHT_SOURCE
    color_matrix_2: tuple[float, ...] | None = None
    illuminant_2: int | None = None
    camera_calibration_1: tuple[float, ...] | None = None
    camera_calibration_2: tuple[float, ...] | None = None
    forward_matrix_1: tuple[float, ...] | None = None
    forward_matrix_2: tuple[float, ...] | None = None
    analog_balance: tuple[float, ...] | None = None
    as_shot_neutral: tuple[float, ...] | None = None
    as_shot_white_xy: tuple[float, ...] | None = None
    source: str = ""

    def __post_init__(self) -> None:
        for name in _MATRIX_TAGS:
            object.__setattr__(self, name, _floats(getattr(self, name), 9, name))
        for name, (_, n) in _VECTOR_TAGS.items():
            object.__setattr__(self, name, _floats(getattr(self, name), n, name))
        if self.color_matrix_1 is None:
            raise InputError("camera colour: no ColorMatrix1")
        if abs(np.linalg.det(np.reshape(self.color_matrix_1, (3, 3)))) < 1e-12:
            raise InputError("camera colour: ColorMatrix1 is singular (no camera-to-XYZ matrix)")
        if self.as_shot_neutral is not None and min(self.as_shot_neutral) <= 0:
            raise InputError(f"camera colour: AsShotNeutral must be positive, got {self.as_shot_neutral}")
        for name in _ILLUMINANT_TAGS:
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, int(value))

    def to_attrs(self) -> dict:
        """The fields that are set, as a JSON-ready dict (the EXR header's ``camera_colour``)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self).items() if v is not None}

    @classmethod
    def from_attrs(cls, attrs: dict) -> CameraColour:
        """The inverse of :meth:`to_attrs`; a malformed entry raises :class:`InputError`."""
        if not isinstance(attrs, dict):
            raise InputError("camera colour: the header entry camera_colour is not a mapping")
        unknown = set(attrs) - {f for f in cls.__dataclass_fields__}
        if unknown:
            raise InputError(f"camera colour: unknown field(s) {', '.join(sorted(unknown))} in camera_colour")
        try:
            return cls(**attrs)
        except (TypeError, ValueError) as err:
            raise InputError(f"camera colour: malformed camera_colour in the header ({err})") from None


def colour_from_dng_tags(tags: dict, source: str = "") -> CameraColour | None:
    """The :class:`CameraColour` of a DNG's IFD0 tags.

    Parameters
    ----------
    tags : dict
        Tag code -> value as tifffile reads it ((S)RATIONALs as flat numerator, denominator pairs).
    source : str
        Recorded in :attr:`CameraColour.source`.

    Returns
    -------
    CameraColour or None
        None when there is no ColorMatrix1 (50721).
    """
    if 50721 not in tags:
        return None
    fields: dict[str, Any] = {name: tags.get(code) for name, code in _MATRIX_TAGS.items()}
    fields.update({name: tags.get(code) for name, (code, _) in _VECTOR_TAGS.items()})
    fields.update({name: tags[code] for name, code in _ILLUMINANT_TAGS.items() if code in tags})
    fields.setdefault("illuminant_1", D65_LIGHT_SOURCE)
    return CameraColour(**fields, source=source)


def colour_from_libraw(
    rgb_xyz_matrix: ArrayLike, camera_whitebalance: Sequence[float], color_desc: bytes | str, source: str = ""
) -> CameraColour | None:
    """The :class:`CameraColour` of LibRaw's metadata (rawpy's attributes of the same names).

    LibRaw's ``rgb_xyz_matrix`` is Adobe's XYZ-to-camera matrix for D65 (one row per camera
    colour, in ``color_desc`` order): it becomes ColorMatrix1 with CalibrationIlluminant1 D65.
    The camera's white balance multipliers ``m`` (per colour) become AsShotNeutral = m_G / m
    (a neutral surface reads 1/m: the multipliers equalise it).

    Parameters
    ----------
    rgb_xyz_matrix : array_like
        (3 or 4, 3) XYZ-to-camera rows; all zero when LibRaw knows no matrix for the camera.
    camera_whitebalance : sequence of float
        As-shot multipliers per colour; zeros when unknown.
    color_desc : bytes or str
        The colours of the rows, e.g. ``b"RGBG"``.
    source : str
        Recorded in :attr:`CameraColour.source`.

    Returns
    -------
    CameraColour or None
        None without a usable matrix or without R, G and B colours.
    """
    desc = color_desc.decode("ascii", "replace") if isinstance(color_desc, bytes) else str(color_desc)
    if not all(c in desc for c in "RGB"):
        return None
    rows = [desc.index(c) for c in "RGB"]
    matrix = np.asarray(rgb_xyz_matrix, dtype=np.float64)
    if matrix.ndim != 2 or matrix.shape[1] != 3 or matrix.shape[0] <= max(rows):
        return None
    cm = matrix[rows]
    if not np.all(np.isfinite(cm)) or abs(np.linalg.det(cm)) < 1e-12:
        return None
    neutral = None
    wb = np.asarray(camera_whitebalance, dtype=np.float64).ravel()
    if wb.size > max(rows):
        m = wb[rows]
        if np.all(np.isfinite(m)) and np.all(m > 0):
            neutral = tuple(float(v) for v in m[1] / m)
    return CameraColour(color_matrix_1=tuple(cm.ravel()), as_shot_neutral=neutral, source=source)


def camera_colour(path: str | os.PathLike[str]) -> CameraColour | None:
    """The colour metadata of a raw file: its DNG colour tags, else LibRaw's camera matrix.

    Parameters
    ----------
    path : str or Path
        A raw frame (DNG, CR2, NEF, ...). Anything else gives None.

    Returns
    -------
    CameraColour or None
        None when the file has neither DNG colour tags nor a matrix LibRaw knows.
    """
    import tifffile

    from hdrcap.pipeline.io.raw import _tiff_complaints

    path = Path(path)
    try:
        with _tiff_complaints(), tifffile.TiffFile(path) as tif:  # what tifffile logs stays off the terminal
            page = tif.pages[0]
            if not isinstance(page, tifffile.TiffPage):  # tifffile reads the first IFD as a page
                raise TypeError("the first IFD is not a TIFF page")
            tags = {code: tag.value for code, tag in page.tags.items() if code in COPIED_TAGS}
        found = colour_from_dng_tags(tags, source=f"{path.name}: DNG colour tags")
    except InputError as err:
        raise InputError(f"{path}: {err}") from None
    except Exception:  # noqa: BLE001  (no page, unreadable tags: the file has no colour metadata we can use)
        found = None
    if found is not None or path.suffix.lower() == ".dng" or path.suffix.lower() not in _LIBRAW_SUFFIXES:
        return found
    import rawpy

    try:
        with rawpy.imread(str(path)) as raw:
            return colour_from_libraw(
                raw.rgb_xyz_matrix, raw.camera_whitebalance, raw.color_desc, source=f"{path.name}: LibRaw"
            )
    except (rawpy.LibRawError, NotImplementedError, OSError):
        return None


#: Raw formats whose colour matrix comes from LibRaw (non-DNG camera raws).
_LIBRAW_SUFFIXES = {".nef", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw", ".raw"}


def _rational_entry(code: int, values, signed: bool) -> tuple:
    """A tifffile extratag of (S)RATIONALs (denominator 10**6; signed for matrices)."""
    pairs = []
    for v in values:
        pairs += [int(round(v * 1_000_000)), 1_000_000]
    return (code, 10 if signed else 5, len(values), tuple(pairs), True)


def colour_tags(colour: CameraColour) -> list[tuple]:
    """The DNG tags of ``colour`` as tifffile extratags (ColorMatrix1/2, calibrations, forward
    matrices, AnalogBalance, AsShotNeutral or AsShotWhiteXY, CalibrationIlluminant1/2).

    Parameters
    ----------
    colour : CameraColour

    Returns
    -------
    list of tuple
        ``(code, dtype, count, value, True)`` per tag set in ``colour``.
    """
    out = [
        _rational_entry(code, getattr(colour, name), True)
        for name, code in _MATRIX_TAGS.items()
        if getattr(colour, name) is not None
    ]
    for name, (code, _) in _VECTOR_TAGS.items():
        if getattr(colour, name) is not None:
            out.append(_rational_entry(code, getattr(colour, name), False))
    for name, code in _ILLUMINANT_TAGS.items():
        if getattr(colour, name) is not None:
            out.append((code, 3, 1, int(getattr(colour, name)), True))
    return out


def _cfa_codes(cfa: str) -> tuple[int, int, int, int]:
    """CFAPattern bytes of a 2x2 Bayer tile such as ``"RGGB"``."""
    if len(cfa) != 4 or any(c not in _CFA_CODES for c in cfa):
        raise InputError(f"float DNG: needs a 2x2 Bayer CFA pattern, the merge has {cfa!r}")
    codes = [_CFA_CODES[c] for c in cfa]
    return codes[0], codes[1], codes[2], codes[3]


def _dng_tags(cfa: str, layout: DngFloatLayout, colour: list[tuple]) -> list[tuple]:
    """CFA layout, DNG version, levels and colour tags (tifffile extratags)."""
    have = {e[0] for e in colour}
    tags: list[tuple] = [
        (33421, 3, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, 1, 4, _cfa_codes(cfa), True),  # CFAPattern
        (50706, 1, 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, 1, 4, (1, 4, 0, 0), True),  # DNGBackwardVersion: floats need a 1.4 reader
        (50710, 1, 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, 3, 1, 1, True),  # CFALayout: rectangular
        (50713, 3, 2, (1, 1), True),  # BlackLevelRepeatDim
        (50714, 4, 1, 0, True),  # BlackLevel
        (50717, 4, 1, layout.white_level, True),  # WhiteLevel
    ]
    if 50708 not in have:
        tags.append((50708, "s", 0, "hdrcap merge", True))
    if 50721 not in have:
        tags += [e for e in _DEFAULT_COLOUR if e[0] not in have]
    return tags + colour


def _libraw_colour_tags(source, have: set[int]) -> list[tuple]:
    """The colour tags LibRaw gives a non-DNG source (:func:`camera_colour`), minus ``have``."""
    try:
        found = camera_colour(source)
    except InputError:
        return []
    return [] if found is None else [e for e in colour_tags(found) if e[0] not in have]


def write_float_dng(
    path: str | os.PathLike[str],
    result: HdrResult,
    *,
    bits: int = 32,
    force: bool = False,
    source: str | Path | None = None,
) -> DngFloatLayout:
    """Write the irradiance of a merge as a linear float CFA DNG.

    Parameters
    ----------
    path : str or Path
        Output file (written atomically; an existing file only with ``force``).
    result : HdrResult
        A merge: its irradiance (unit in ``header["unit"]``) and the CFA pattern in
        ``header["cfa_pattern"]``.
    bits : {32, 16}
        Float width per photosite.
    force : bool
        Overwrite an existing file.
    source : str or Path, optional
        Frame whose colour tags are copied; default the first of ``header["source_files"]``.

    Returns
    -------
    DngFloatLayout
        The stored scale and white level: irradiance = stored value * ``layout.scale``.

    Raises
    ------
    InputError
        No Bayer CFA pattern, non-finite irradiance, or an unusable width.
    """
    import tifffile

    irr = np.asarray(result.irradiance, dtype=np.float32)
    if irr.ndim != 2:
        raise InputError(f"float DNG: the irradiance must be a 2-D mosaic, got shape {irr.shape}")
    cfa = str(result.header.get("cfa_pattern") or "none")
    layout = dng_layout(irr, bits)
    _cfa_codes(cfa)
    if source is None:
        sources = result.header.get("source_files") or []
        source = sources[0] if sources else None
    colour = source_colour_tags(source) if source is not None else []
    if source is not None and not any(e[0] == 50721 for e in colour):
        colour += _libraw_colour_tags(source, {e[0] for e in colour})
    unit = result.header.get("unit") or UNIT_ELECTRONS
    # A power of two scales a float32 exactly: the only rounding is float16's, when bits is 16.
    scaled = irr if layout.exponent == 0 else irr * np.float32(2.0**-layout.exponent)
    stored = scaled.astype(np.float32 if bits == 32 else np.float16, copy=False)
    from hdrcap import __version__

    description = f"hdrcap merged irradiance: value * 2^{layout.exponent} = irradiance in {unit}"
    with atomic_output(path, force=force, suffix=".dng") as tmp:
        with tifffile.TiffWriter(tmp, bigtiff=False) as tw:
            tw.write(
                stored,
                photometric=32803,
                subfiletype=0,
                compression=None,
                metadata=None,
                description=description,
                software=f"hdrcap {__version__}",
                extratags=_dng_tags(cfa, layout, colour),
            )
    return layout
