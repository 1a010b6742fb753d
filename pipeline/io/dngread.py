"""Direct decoding of simple DNG files: uncompressed CFA strips or tiles, read with tifffile.

A DNG whose raw image is stored uncompressed (8 or 16 bits per photosite, in strips or tiles,
either byte order) needs no raw decoder: its pixels are the bytes of the file. This module reads
them (memory-mapped when the strips are one contiguous little-endian 16-bit block, as the
simulator and most uncompressed converters write them) and gives the same pixels and levels as
LibRaw's ``raw_image_visible``, ``black_level_per_channel`` and ``white_level``.

Everything outside that simple case (compressed data, linearisation tables, per-channel or
masked-area black levels, opcode lists, odd active areas, several raw images, non-Bayer CFA) is
left to LibRaw: :func:`decode_dng` returns None and :func:`pipeline.io.raw.read_raw` falls back.
Inconsistent files (image data beyond the end of the file, strips or tiles that do not cover
the stated dimensions) raise :class:`~pipeline.errors.InputError`.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hdrcap.pipeline.errors import InputError

if TYPE_CHECKING:
    import tifffile

__all__ = ["DngPixels", "decode_dng", "raw_page"]

#: TIFF tags read here (numbers from the TIFF 6.0 and DNG 1.4 specifications).
_NEW_SUBFILE_TYPE, _PHOTOMETRIC, _CFA = 254, 262, 32803
_CFA_REPEAT_DIM, _CFA_PATTERN, _CFA_PLANE_COLOR, _CFA_LAYOUT = 33421, 33422, 50710, 50711
_BLACK_REPEAT_DIM, _BLACK_LEVEL, _WHITE_LEVEL, _ACTIVE_AREA = 50713, 50714, 50717, 50829
#: Tags whose presence changes what LibRaw returns (linearisation table, black-level deltas,
#: masked areas, opcode lists): such files go to LibRaw.
_LIBRAW_ONLY_TAGS = (50712, 50715, 50716, 50830, 51008, 51009, 51022)
#: The four Bayer tiles LibRaw reports as a 2x2 pattern of R, G, B.
_BAYER = ("RGGB", "BGGR", "GRBG", "GBRG")
_COLOURS = "RGB"


@dataclass(frozen=True)
class DngPixels:
    """The raw image of a DNG, as LibRaw would return it.

    Attributes
    ----------
    data : numpy.ndarray
        uint16 CFA mosaic, DN, shape (height, width); read-only-backed by the file when it was
        memory-mapped (copy-on-write: writing to it never changes the file).
    cfa_pattern : str
        2x2 Bayer tile of the visible area, e.g. ``"RGGB"``.
    black_level : float
        DN, LibRaw's integer black level (the file's value rounded down).
    white_level : float
        DN.
    """

    data: np.ndarray
    cfa_pattern: str
    black_level: float
    white_level: float


def raw_page(tif: tifffile.TiffFile) -> tifffile.TiffPage | None:
    """The one full-resolution CFA image of an open :class:`tifffile.TiffFile`, or None.

    Looks at IFD0 and its SubIFDs (where DNG converters put the raw image behind a preview).

    Parameters
    ----------
    tif : tifffile.TiffFile
        The open file.

    Returns
    -------
    tifffile.TiffPage or None
        None when there is no such image or more than one.
    """
    first = tif.pages[0]
    candidates = [first] + list(getattr(first, "pages", None) or [])
    raws = [p for p in candidates if _tag(p, _NEW_SUBFILE_TYPE, 0) == 0 and _tag(p, _PHOTOMETRIC) == _CFA]
    return raws[0] if len(raws) == 1 else None


def decode_dng(path: Path, tif: tifffile.TiffFile, mmap: bool = True) -> DngPixels | None:
    """Decode the raw image of a simple DNG, or return None when LibRaw has to.

    Parameters
    ----------
    path : pathlib.Path
        The file (named in error messages; memory-mapped when ``mmap``).
    tif : tifffile.TiffFile
        ``path`` opened with tifffile.
    mmap : bool
        Map a contiguous little-endian 16-bit image instead of reading it into memory.

    Returns
    -------
    DngPixels or None
        None for anything but an uncompressed Bayer DNG that LibRaw reads verbatim.

    Raises
    ------
    InputError
        The image data runs past the end of the file or does not match the dimensions.
    """
    import tifffile

    first = tif.pages[0]
    if not isinstance(first, tifffile.TiffPage) or 50706 not in first.tags:  # DNGVersion: not a DNG
        return None
    page = raw_page(tif)
    if page is None or not _is_simple(page):
        return None
    cfa = _bayer_pattern(page)
    levels = _levels(page)
    crop = _active_area(page)
    if cfa is None or levels is None or crop is None:
        return None
    _check_layout(path, page)
    data = _pixels(path, page, mmap)
    top, left, bottom, right = crop
    if (top, left, bottom, right) != (0, 0, page.imagelength, page.imagewidth):
        data = data[top:bottom, left:right]
    return DngPixels(data=data, cfa_pattern=cfa, black_level=levels[0], white_level=levels[1])


def _tag(page, code: int, default=None):
    tag = page.tags.get(code)
    return default if tag is None else tag.value


def _is_simple(page) -> bool:
    """Uncompressed, one unsigned 8/16-bit sample per photosite, nothing LibRaw transforms."""
    return (
        int(page.compression) == 1
        and page.samplesperpixel == 1
        and page.bitspersample in (8, 16)
        and int(page.sampleformat) == 1
        and _tag(page, 266, 1) == 1  # FillOrder
        and _tag(page, 317, 1) == 1  # Predictor
        and _tag(page, _CFA_LAYOUT, 1) == 1
        and not any(code in page.tags for code in _LIBRAW_ONLY_TAGS)
        and page.imagedepth == 1
    )


def _bayer_pattern(page) -> str | None:
    """The 2x2 Bayer tile from CFARepeatPatternDim, CFAPattern and CFAPlaneColor, or None."""
    if tuple(_tag(page, _CFA_REPEAT_DIM, ())) != (2, 2) or tuple(_tag(page, _CFA_PLANE_COLOR, (0, 1, 2))) != (0, 1, 2):
        return None
    codes = _tag(page, _CFA_PATTERN, b"")
    codes = tuple(codes) if not isinstance(codes, int) else (codes,)
    if len(codes) != 4 or any(c not in (0, 1, 2) for c in codes):
        return None
    pattern = "".join(_COLOURS[c] for c in codes)
    return pattern if pattern in _BAYER else None


def _rational(value) -> float | None:
    """A TIFF SHORT/LONG/RATIONAL value of count 1 as a float, else None."""
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, tuple) and len(value) == 1:
        return _rational(value[0])
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value) and value[1]:
        return value[0] / value[1]
    return None


def _levels(page) -> tuple[float, float] | None:
    """(black, white) in DN as LibRaw reports them, or None for per-channel levels."""
    if tuple(_tag(page, _BLACK_REPEAT_DIM, (1, 1))) != (1, 1):
        return None
    black = _rational(_tag(page, _BLACK_LEVEL, 0))
    white = _rational(_tag(page, _WHITE_LEVEL))
    if black is None or white is None or black < 0 or not 0 < white <= 65535:
        return None
    return float(math.floor(black)), float(white)


def _active_area(page) -> tuple[int, int, int, int] | None:
    """(top, left, bottom, right) of the visible area; None when LibRaw would shift the CFA."""
    h, w = page.imagelength, page.imagewidth
    area = _tag(page, _ACTIVE_AREA)
    if area is None:
        return 0, 0, h, w
    area = tuple(int(v) for v in area)
    top, left, bottom, right = area
    if len(area) != 4 or any(v % 2 for v in area) or not (0 <= top < bottom <= h and 0 <= left < right <= w):
        return None
    return area


def _chunk_bytes(page) -> list[int]:
    """Bytes each strip or tile must hold for the stated dimensions."""
    item = page.bitspersample // 8
    h, w = page.imagelength, page.imagewidth
    if page.is_tiled:
        th, tw = page.tilelength, page.tilewidth
        n = math.ceil(h / th) * math.ceil(w / tw)
        return [th * tw * item] * n
    rows = min(page.rowsperstrip or h, h)
    return [min(rows, h - r0) * w * item for r0 in range(0, h, rows)]


def _check_layout(path: Path, page) -> None:
    """Refuse strips/tiles past the end of the file or not covering the image."""
    size = path.stat().st_size
    offsets, counts = page.dataoffsets, page.databytecounts
    if any(o + n > size for o, n in zip(offsets, counts)):
        raise InputError(f"{path}: truncated raw file (image data runs past the end of the file)")
    need = _chunk_bytes(page)
    kind = "tiles" if page.is_tiled else "strips"
    if len(need) != len(offsets) or any(n < k for n, k in zip(counts, need)):
        raise InputError(
            f"{path}: raw image data does not match its dimensions ({page.imagewidth}x"
            f"{page.imagelength}: {len(offsets)} {kind} of {min(counts, default=0)}.."
            f"{max(counts, default=0)} bytes, expected {len(need)} of {max(need, default=0)})"
        )


def _pixels(path: Path, page, mmap: bool) -> np.ndarray:
    """The full raw image as uint16: mapped when it is one contiguous native block, else decoded."""
    h, w = page.imagelength, page.imagewidth
    offsets = page.dataoffsets
    contiguous = not page.is_tiled and all(
        offsets[i + 1] == offsets[i] + n for i, n in enumerate(_chunk_bytes(page)[:-1])
    )
    native = page.bitspersample == 16 and (page.parent.byteorder == "<") == (sys.byteorder == "little")
    if contiguous and native:
        if mmap:
            mapped = np.memmap(path, dtype=np.uint16, mode="c", offset=offsets[0], shape=(h, w))
            return mapped.view(np.ndarray)
        return np.fromfile(path, dtype=np.uint16, count=h * w, offset=offsets[0]).reshape(h, w)
    return np.asarray(page.asarray(), dtype=np.uint16).reshape(h, w)
