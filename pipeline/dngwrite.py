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
that has them; otherwise an identity colour matrix (D65) and a neutral white balance.

A DNG carries no uncertainty: sigma, sigma_calibration, nexp and quality stay in the EXR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .io import HdrImage, atomic_output

__all__ = ["DngFloatLayout", "COPIED_TAGS", "dng_layout", "write_float_dng", "source_colour_tags"]

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


def source_colour_tags(path) -> list[tuple]:
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
            tags = tif.pages[0].tags
            entries = [_tag_entry(tags[code]) for code in COPIED_TAGS if code in tags]
    except (OSError, ValueError, tifffile.TiffFileError):
        return []
    return [e for e in entries if e is not None]


def _cfa_codes(cfa: str) -> tuple[int, int, int, int]:
    """CFAPattern bytes of a 2x2 Bayer tile such as ``"RGGB"``."""
    if len(cfa) != 4 or any(c not in _CFA_CODES for c in cfa):
        raise InputError(f"float DNG: needs a 2x2 Bayer CFA pattern, the merge has {cfa!r}")
    return tuple(_CFA_CODES[c] for c in cfa)


def _dng_tags(cfa: str, layout: DngFloatLayout, colour: list[tuple]) -> list[tuple]:
    """CFA layout, DNG version, levels and colour tags (tifffile extratags)."""
    have = {e[0] for e in colour}
    tags = [
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


def write_float_dng(
    path, image: HdrImage, *, bits: int = 32, force: bool = False, source: str | Path | None = None
) -> DngFloatLayout:
    """Write the ``irradiance`` channel of ``image`` as a linear float CFA DNG.

    Parameters
    ----------
    path : str or Path
        Output file (written atomically; an existing file only with ``force``).
    image : HdrImage
        A merge result: the ``irradiance`` channel (unit in ``attrs["unit"]``) and the CFA pattern
        in ``attrs["cfa_pattern"]``.
    bits : {32, 16}
        Float width per photosite.
    force : bool
        Overwrite an existing file.
    source : str or Path, optional
        Frame whose colour tags are copied; default the first of ``attrs["source_files"]``.

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

    irr = np.asarray(image.channels["irradiance"], dtype=np.float32)
    if irr.ndim != 2:
        raise InputError(f"float DNG: the irradiance must be a 2-D mosaic, got shape {irr.shape}")
    cfa = str(image.attrs.get("cfa_pattern", "none"))
    layout = dng_layout(irr, bits)
    _cfa_codes(cfa)
    if source is None:
        sources = image.attrs.get("source_files") or []
        source = sources[0] if sources else None
    colour = source_colour_tags(source) if source is not None else []
    unit = image.attrs.get("unit", "electrons per second per photosite")
    # A power of two scales a float32 exactly: the only rounding is float16's, when bits is 16.
    stored = irr if layout.exponent == 0 else irr * np.float32(2.0**-layout.exponent)
    stored = stored.astype(np.float32 if bits == 32 else np.float16, copy=False)
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
