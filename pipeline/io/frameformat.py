"""What a frame's file may not say: CFA pattern, black and white level, significant bits.

Raw files (DNG, NEF, ...) carry their levels and CFA pattern; PNG and TIFF frames of scientific
and machine-vision cameras carry only their pixels and a bit depth (8, 16, or a TIFF's 10/12/14
bits per sample). :class:`FrameFormat` is what the user says about such frames (``hdrcap merge
--cfa --black-level --white-level --bits``, the same keywords in the API): the reader
(:func:`pipeline.io.raw.read_frame`) sets the fields of every :class:`~pipeline.io.raw.RawFrame`
from the file and from it, and records in ``RawFrame.assumed`` what it had to assume.

N-bit data in wider words (``--bits N``) are stored either LSB-aligned (values 0 .. 2^N - 1) or
MSB-aligned (shifted left: every value a multiple of 2^(C - N) in a C-bit word, e.g. 12-bit data
in 16 bits is 0, 16, 32 ... 65520). MSB alignment is detected from the values (every value a
multiple of a power of two) and sets the quantisation step, 2^(C - N) DN: the readout variance
cannot be below step^2 / 12 (the rounding of a signal dithered by its own noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hdrcap.pipeline.errors import InputError

__all__ = [
    "ASSUMED",
    "CFA_CHOICES",
    "FrameFormat",
    "ImageLevels",
    "image_levels",
    "aligned_step",
    "check_cfa_option",
    "describe_assumed",
]

#: What a PNG/TIFF reader may have had to assume (the keys of ``RawFrame.assumed``): ``msb``
#: (MSB alignment detected from the values), ``white_level`` (from the bit depth),
#: ``white_level_unknown`` (16-bit words, bits not known), ``black_level`` (unknown), ``cfa``
#: (no CFA pattern said: monochrome).
ASSUMED = ("msb", "white_level", "white_level_unknown", "black_level", "cfa")

#: The values of ``--cfa``: a 2x2 Bayer tile read row by row, or ``mono`` (no colour filter).
CFA_CHOICES = ("RGGB", "BGGR", "GRBG", "GBRG", "mono")


def check_cfa_option(cfa: str | None) -> str | None:
    """Check a ``--cfa`` value.

    Parameters
    ----------
    cfa : str or None
        One of :data:`CFA_CHOICES` (any case), or None (from the file).

    Returns
    -------
    str or None
        The Bayer tile in upper case, ``"mono"``, or None.

    Raises
    ------
    InputError
        Any other value.
    """
    if cfa is None:
        return None
    text = str(cfa).strip()
    value = "mono" if text.lower() in ("mono", "none", "monochrome") else text.upper()
    if value not in CFA_CHOICES:
        raise InputError(f"CFA pattern {cfa!r}: choose from {', '.join(CFA_CHOICES)}")
    return value


@dataclass(frozen=True)
class FrameFormat:
    """What the user says about a bracket's frames, overriding (or completing) their files.

    Attributes
    ----------
    cfa : str or None
        2x2 Bayer tile (``RGGB``, ``BGGR``, ``GRBG``, ``GBRG``) or ``mono``; None: the file's
        (PNG/TIFF: monochrome, assumed).
    black_level : float or None
        DN; None: the file's (PNG/TIFF: 0, assumed).
    white_level : float or None
        DN; None: the file's (PNG/TIFF: from the bit depth and alignment).
    bits : int or None
        Significant bits N of the values (1..16); None: from the file (a TIFF's bits per sample,
        MSB alignment detected in 16-bit words).

    Examples
    --------
    >>> FrameFormat(cfa="gbrg", bits=8)
    FrameFormat(cfa='GBRG', black_level=None, white_level=None, bits=8)
    """

    cfa: str | None = None
    black_level: float | None = None
    white_level: float | None = None
    bits: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "cfa", check_cfa_option(self.cfa))
        if self.bits is not None and not (isinstance(self.bits, (int, np.integer)) and 1 <= int(self.bits) <= 16):
            raise InputError(f"--bits {self.bits!r}: give the significant bits of the data, 1 to 16")
        for name in ("black_level", "white_level"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(float(value)) and float(value) >= 0):
                raise InputError(f"--{name.replace('_', '-')} {value!r}: give a finite number of DN >= 0")
        if self.white_level is not None and float(self.white_level) <= 0:
            raise InputError(f"--white-level {self.white_level!r}: give a number of DN > 0")
        if self.black_level is not None and self.white_level is not None and self.black_level >= self.white_level:
            raise InputError(
                f"--black-level {self.black_level:g} DN is not below --white-level {self.white_level:g} DN"
            )

    @property
    def given(self) -> bool:
        """Whether anything is set."""
        return any(v is not None for v in (self.cfa, self.black_level, self.white_level, self.bits))

    @property
    def cfa_pattern(self) -> str | None:
        """The CFA pattern as :class:`~pipeline.io.raw.RawFrame` holds it (None for ``mono``);
        only meaningful when ``cfa`` is set."""
        return None if self.cfa in (None, "mono") else self.cfa


def aligned_step(data: np.ndarray, stored_bits: int, bits: int, where: object) -> float:
    """The quantisation step of N-bit data in ``stored_bits``-bit words, from the values.

    MSB-aligned data are all multiples of 2^(stored_bits - bits) (and not all 0): step
    2^(stored_bits - bits) DN. LSB-aligned data lie within 0 .. 2^bits - 1: step 1 DN.

    Parameters
    ----------
    data : numpy.ndarray
        The stored values, DN.
    stored_bits : int
        Bits of the words (8, 16, a TIFF's bits per sample).
    bits : int
        Significant bits N (<= ``stored_bits``).
    where : object
        Named in error messages (the file).

    Returns
    -------
    float
        Step, DN.

    Raises
    ------
    InputError
        ``bits`` above ``stored_bits``, or values that are neither N-bit LSB- nor MSB-aligned.
    """
    if bits > stored_bits:
        raise InputError(f"{where}: --bits {bits} exceeds the file's {stored_bits}-bit values")
    if bits == stored_bits:
        return 1.0
    shift = stored_bits - bits
    high = int(np.max(data)) if data.size else 0
    if high > 0 and _trailing_zeros(data) >= shift:
        return float(1 << shift)
    if high <= (1 << bits) - 1:
        return 1.0
    raise InputError(
        f"{where}: values up to {high} DN are neither {bits}-bit data (at most {(1 << bits) - 1} DN) nor "
        f"{bits}-bit data MSB-aligned in {stored_bits}-bit words (multiples of {1 << shift}); check --bits"
    )


def _trailing_zeros(data: np.ndarray) -> int:
    """The largest k with every value a multiple of 2^k (16 when all are 0)."""
    ored = int(np.bitwise_or.reduce(np.asarray(data, dtype=np.uint32).ravel())) if data.size else 0
    if ored == 0:
        return 16
    return (ored & -ored).bit_length() - 1


@dataclass(frozen=True)
class ImageLevels:
    """The levels of a PNG/TIFF frame (:func:`image_levels`).

    Attributes
    ----------
    bits : int
        Significant bits N.
    step : float
        Quantisation step, DN.
    black_level : float or None
        DN; None when neither the file nor the format says it.
    white_level : float or None
        DN; None for 16-bit values whose bit depth nothing says (LSB-aligned, no ``bits``).
    cfa_pattern : str or None
        Bayer tile, None for monochrome.
    assumed : tuple of str
        What was assumed because neither the file nor the format said it (keys of
        :data:`ASSUMED`).
    """

    bits: int
    step: float
    black_level: float | None
    white_level: float | None
    cfa_pattern: str | None
    assumed: tuple[str, ...]


def image_levels(data: np.ndarray, stored_bits: int, fmt: FrameFormat | None, where: object) -> ImageLevels:
    """Bits, quantisation step, black and white level and CFA of a PNG/TIFF frame.

    From ``fmt`` where it says them; else: the bits from the file (``stored_bits``; in 16-bit
    words whose values are all multiples of 2^k, 16 - k bits MSB-aligned, said in ``assumed``),
    the white level (2^N - 1) x step (None for 16-bit values that are not MSB-aligned: nothing
    says how many bits they have), no black level (None: a self-calibration estimates it) and
    no CFA (monochrome), each recorded in ``assumed``.

    Parameters
    ----------
    data : numpy.ndarray
        The stored values, DN.
    stored_bits : int
        Bits per sample of the file (8, 16, or a TIFF's 10/12/14).
    fmt : FrameFormat or None
        What the user said.
    where : object
        Named in error messages (the file).

    Returns
    -------
    ImageLevels

    Raises
    ------
    InputError
        ``fmt.bits`` that the values contradict (:func:`aligned_step`).

    Examples
    --------
    >>> import numpy as np
    >>> lv = image_levels(np.array([[16, 4080], [65520, 32]], np.uint16), 16, None, "x.tif")
    >>> lv.bits, lv.step, lv.white_level
    (12, 16.0, 65520.0)
    """
    fmt = fmt or FrameFormat()
    assumed: list[str] = []
    if fmt.bits is not None:
        bits = int(fmt.bits)
        step = aligned_step(data, stored_bits, bits, where)
    else:
        shift = min(_trailing_zeros(data), 8) if stored_bits == 16 and np.any(data) else 0
        bits, step = stored_bits - shift, float(1 << shift)
        if shift:
            assumed.append("msb")
    white: float | None
    if fmt.white_level is not None:
        white = float(fmt.white_level)
    elif fmt.bits is None and stored_bits == 16 and step == 1:
        white = None  # 16-bit words, nothing says how many bits the data have
        assumed.append("white_level_unknown")
    else:
        white = float((1 << bits) - 1) * step
        if fmt.bits is None:
            assumed.append("white_level")
    black: float | None = None
    if fmt.black_level is not None:
        black = float(fmt.black_level)
    else:
        assumed.append("black_level")
    if fmt.cfa is not None:
        cfa = fmt.cfa_pattern
    else:
        cfa = None
        assumed.append("cfa")
    if black is not None and white is not None and black >= white:
        raise InputError(f"{where}: black level {black:g} DN is not below the white level {white:g} DN")
    return ImageLevels(bits, step, black, white, cfa, tuple(assumed))


def describe_assumed(
    assumed: tuple[str, ...], bits: int | None, step: float, white_level: float | None, high: int | None = None
) -> str:
    """What a reader assumed about a frame, as one phrase for a warning.

    Parameters
    ----------
    assumed : tuple of str
        Keys of :data:`ASSUMED`.
    bits : int or None
        The frame's significant bits.
    step : float
        Its quantisation step, DN.
    white_level : float or None
        Its white level, DN.
    high : int, optional
        Its largest value, DN (named when the white level is unknown).

    Returns
    -------
    str
        E.g. ``"white level 255 DN from the 8-bit depth; black level unknown (...)"``.

    Examples
    --------
    >>> describe_assumed(("white_level", "cfa"), 8, 1.0, 255.0)
    'white level 255 DN from the 8-bit depth; no colour filter (monochrome)'
    """
    words = {
        "msb": f"{bits}-bit data MSB-aligned in 16-bit words (every value a multiple of {step:g}: quantisation "
        f"step {step:g} DN)",
        "white_level": f"white level {white_level:g} DN from the {bits}-bit depth" if white_level else "",
        "white_level_unknown": "white level unknown: 16-bit values"
        + (f" (the largest is {high} DN)" if high is not None else "")
        + ", give --bits or --white-level if the data have fewer bits",
        "black_level": "black level unknown (a self-calibration estimates it from the bracket)",
        "cfa": "no colour filter (monochrome)",
    }
    return "; ".join(words[k] for k in assumed if words.get(k))
