"""Raw frames in: camera raw files (LibRaw, or uncompressed DNGs read directly), 8- to 16-bit
PNG/TIFF images, and the sanity checks every frame passes (exposure time, white and black level,
CFA). What a file does not say (a PNG's levels and CFA) comes from a
:class:`~pipeline.io.frameformat.FrameFormat`, or is assumed and recorded in ``RawFrame.assumed``.

Raw frames are returned as the CFA mosaic the sensor wrote (rawpy's ``raw_image_visible``),
never demosaiced. Every problem with an input file raises :class:`~pipeline.errors.InputError`
with a one-line message naming the file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import math
import os
import re
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import check_readable, one_line, quiet_stderr
from hdrcap.pipeline.io.frameformat import FrameFormat, aligned_step, image_levels

__all__ = [
    "BAD_VALUES",
    "BLACK_LEVEL_SPREAD",
    "IMAGE_EXTENSIONS",
    "MAX_RAW_COMPRESSION",
    "RAW_EXTENSIONS",
    "RawFrame",
    "adc_maximum",
    "check_bad_values",
    "check_exposure_time",
    "check_frames",
    "read_frame",
    "with_format",
    "read_image16",
    "read_raw",
    "tiff_dimensions",
]

RAW_EXTENSIONS = {".dng", ".nef", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw", ".raw"}


IMAGE_EXTENSIONS = {".png", ".tif", ".tiff"}


@dataclass(frozen=True)
class RawFrame:
    """One raw exposure: the CFA mosaic and what the file says about it.

    Attributes
    ----------
    data : numpy.ndarray
        uint16 mosaic, DN, shape (height, width).
    exposure_time : float
        Seconds.
    iso : float or None
        ISO speed from EXIF.
    black_level : float or None
        Black level written in the file, DN (None for plain images).
    white_level : float or None
        White level written in the file, DN.
    cfa_pattern : str or None
        2x2 Bayer tile, e.g. ``"RGGB"``; None for monochrome.
    path : str or None
        Source file.
    camera : str or None
        Make and model.
    timestamp : str or None
        Capture time (EXIF DateTimeOriginal or LibRaw's timestamp, ISO 8601).
    masked : numpy.ndarray or None
        bool map, shape of ``data``: photosites whose decoded value was impossible (above the
        white level's ADC range) and that the reader masked instead of refusing the file
        (``bad_values="mask"``); their ``data`` values are left as decoded and must not be used.
        None: nothing masked.
    bits : int or None
        Significant bits of the values (N), when known.
    quantisation_step : float
        DN between two adjacent codes: 1, or 2^(16 - N) for N-bit data stored MSB-aligned in
        16-bit words (the readout variance is at least its square / 12).
    serial : str or None
        Camera serial number (DNG CameraSerialNumber or EXIF BodySerialNumber).
    assumed : tuple of str
        What the reader assumed because the file does not say it (keys of
        :data:`pipeline.io.frameformat.ASSUMED`: a PNG's black level, CFA pattern, ...).
    """

    data: np.ndarray
    exposure_time: float
    iso: float | None = None
    black_level: float | None = None
    white_level: float | None = None
    cfa_pattern: str | None = None
    path: str | None = None
    camera: str | None = None
    timestamp: str | None = None
    masked: np.ndarray | None = None
    bits: int | None = None
    quantisation_step: float = 1.0
    serial: str | None = None
    assumed: tuple[str, ...] = ()

    @property
    def n_masked(self) -> int:
        """Number of masked photosites (see ``masked``)."""
        return 0 if self.masked is None else int(np.count_nonzero(self.masked))

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape


def check_exposure_time(t: Any, where: object = None) -> float:
    """Check an exposure time: a finite number of seconds > 0.

    Parameters
    ----------
    t : object
        The exposure time, s (a number or a numeric string).
    where : str, optional
        Prefix of the error message (e.g. the file name).

    Returns
    -------
    float
        ``t`` in seconds.

    Raises
    ------
    InputError
        ``t`` is missing, not a number, not finite or not positive.
    """
    prefix = f"{where}: " if where is not None else ""
    try:
        t = float(t)
    except (TypeError, ValueError):
        raise InputError(f"{prefix}exposure time {t!r} is not a number") from None
    if not (np.isfinite(t) and t > 0):
        raise InputError(f"{prefix}exposure time must be a positive number of seconds, got {t!r}")
    return t


def _rational_seconds(value) -> float | None:
    """A TIFF RATIONAL/number as a float; None for a zero denominator or a non-number."""
    if isinstance(value, tuple) and len(value) == 2:
        return float(Fraction(int(value[0]), int(value[1]))) if value[1] else None
    if isinstance(value, (int, float)):
        return float(value)
    return None


def _exif_values(page, path: Path) -> dict[str, Any]:
    """Exact ExposureTime (s), ISO, timestamp and camera from IFD0 or its EXIF IFD.

    Raises :class:`InputError` when IFD0 and the EXIF IFD both give an exposure time and they
    differ (one of them is corrupt, and nothing tells which), or when the one given is 0/0.
    """
    tags = page.tags
    exif = tags["ExifTag"].value if "ExifTag" in tags else {}
    if not isinstance(exif, dict):
        exif = {}
    out: dict[str, Any] = {}
    for key, code in (("ExposureTime", 33434), ("ISOSpeedRatings", 34855), ("DateTimeOriginal", 36867)):
        val = exif.get(key)
        if val is None and code in tags:
            val = tags[code].value
        out[key] = val
    out["camera"] = " ".join(str(tags[c].value).strip() for c in (271, 272) if c in tags) or None
    serial = exif.get("BodySerialNumber") or (tags[50735].value if 50735 in tags else None)
    out["serial"] = (str(serial).strip() or None) if serial is not None else None
    t = out["ExposureTime"]
    if t is not None:
        out["ExposureTime"] = _rational_seconds(t)
        if out["ExposureTime"] is None:
            raise InputError(f"{path}: corrupt EXIF ExposureTime {t!r}")
        if 33434 in tags and "ExposureTime" in exif:
            t0 = _rational_seconds(tags[33434].value)
            if t0 is None or not math.isclose(t0, out["ExposureTime"], rel_tol=1e-6):
                raise InputError(
                    f"{path}: the metadata contradicts itself: ExposureTime {t0!r} s in IFD0, "
                    f"{out['ExposureTime']!r} s in the EXIF IFD (corrupt file)"
                )
    iso = out["ISOSpeedRatings"]
    if isinstance(iso, (tuple, list)):
        out["ISOSpeedRatings"] = iso[0] if iso else None
    return out


#: Tag of tifffile's message for an IFD entry it could not read: code, byte offset, reason.
_BAD_TAG = re.compile(r"TiffTag (\d+) @(\d+)> ([^'\"]+)")


class _TiffComplaints(logging.Handler):
    """Collects what tifffile logs (unreadable tag entries, bad IFD offsets) in this thread."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.thread = threading.get_ident()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.messages.append(record.getMessage())


@contextlib.contextmanager
def _tiff_complaints() -> Iterator[list[str]]:
    """Yield the list that receives tifffile's warnings logged by this thread meanwhile."""
    logger = logging.getLogger("tifffile")
    handler = _TiffComplaints()
    logger.addHandler(handler)
    try:
        yield handler.messages
    finally:
        logger.removeHandler(handler)


def _tag_complaint(message: str) -> str:
    """tifffile's message about a broken IFD entry, as a short phrase naming the tag."""
    import tifffile

    m = _BAD_TAG.search(message)
    if m is None:
        return re.sub(
            r"<(tifffile\.)?[\w.]+(?: \d+)?(?: @(\d+))?>", lambda k: f"at byte {k[2]}:" if k[2] else "", message
        ).strip()
    code, offset, reason = int(m.group(1)), int(m.group(2)), m.group(3).strip()
    name = tifffile.TIFF.TAGS.get(code, "unknown tag")
    return f"IFD entry at byte {offset} (tag {code}, {name}): {reason}"


def _refuse_corrupt_dng(path: Path, page, complaints: list[str]) -> None:
    """A DNG whose directory tifffile could not read in full is refused: a dropped tag (white
    level, CFA pattern, strip offsets, ...) would silently become its default value."""
    is_dng = path.suffix.lower() == ".dng" or 50706 in page.tags
    if is_dng and complaints:
        raise InputError(f"{path}: corrupt DNG directory: {_tag_complaint(complaints[0])}")


#: Largest ratio of the raw image's size (bits per sample times photosites) to the bytes it is
#: stored in: lossless raw codecs reach about 2 on sensor data; more means corrupt dimensions,
#: which LibRaw would allocate before it notices that the data are missing.
MAX_RAW_COMPRESSION = 8


def _refuse_impossible_size(path: Path, tif) -> None:
    """Refuse a raw image whose stated dimensions cannot fit in its stored data."""
    from hdrcap.pipeline.io.dngread import raw_page

    try:
        page = raw_page(tif)
    except Exception:  # noqa: BLE001  (tags tifffile cannot interpret: LibRaw decides)
        return
    if page is not None:
        _refuse_oversized_page(path, page)


def _refuse_oversized_page(path: Path, page) -> None:
    """Refuse a TIFF page whose stated dimensions need more than :data:`MAX_RAW_COMPRESSION`
    times its stored bytes (a corrupt size tag would make the decoder allocate gigabytes)."""
    try:
        stored = sum(page.databytecounts)
        bits = page.bitspersample if isinstance(page.bitspersample, int) else max(page.bitspersample)
        need = page.imagewidth * page.imagelength * max(int(page.samplesperpixel), 1) * bits / 8
    except Exception:  # noqa: BLE001  (tags tifffile cannot interpret: the decoder decides)
        return
    if need > MAX_RAW_COMPRESSION * max(stored, 1):
        raise InputError(
            f"{path}: impossible raw image dimensions {page.imagewidth}x{page.imagelength} "
            f"({bits}-bit) for {stored} bytes of image data (corrupt file)"
        )


def tiff_dimensions(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """(rows, columns) of the largest image of a TIFF-based file (DNG, TIFF), from its tags
    without decoding; None for other formats or a file tifffile cannot parse. What tifffile
    logs about a damaged file is kept off the terminal (the reader refuses such a file later).

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    tuple of int or None
        (rows, columns) of the image with the most photosites, or None.
    """
    import tifffile

    try:
        with _tiff_complaints(), tifffile.TiffFile(path) as tif:
            pages = list(tif.pages)
            for page in list(pages):
                pages.extend(getattr(page, "pages", None) or [])
            dims = [(int(p.imagelength), int(p.imagewidth)) for p in pages if isinstance(p, tifffile.TiffPage)]
    except Exception:  # noqa: BLE001  (not a TIFF: the caller decides)
        return None
    return max(dims, key=lambda d: d[0] * d[1]) if dims else None


def _refuse_unreadable_dng(path: Path, err: BaseException) -> None:
    """Refuse a ``.dng`` file with a TIFF header whose first directory tifffile cannot read.

    Other raw formats go to LibRaw then; a DNG would be decoded without the checks of its CFA
    tags (:func:`_refuse_inconsistent_cfa`), and LibRaw fills what it cannot read from memory
    an earlier call left behind.
    """
    if path.suffix.lower() != ".dng":
        return
    with open(path, "rb") as fh:
        header = fh.read(4)
    if header in (b"II*\x00", b"MM\x00*"):
        raise InputError(f"{path}: corrupt DNG directory ({one_line(err)})")


def _tag_values(tag) -> np.ndarray:
    """The values of a TIFF tag as a flat integer array (BYTE tags come as ``bytes``)."""
    value = tag.value
    return np.frombuffer(value, np.uint8) if isinstance(value, bytes) else np.ravel(value).astype(np.int64)


def _refuse_inconsistent_cfa(path: Path, tif) -> None:
    """Refuse a raw file whose colour filter array tags contradict each other.

    In every directory that has them (IFD0 and its SubIFDs, whatever their other tags say),
    CFARepeatPatternDim gives (rows, columns), CFAPattern needs rows x columns entries and each
    entry indexes CFAPlaneColor (default red, green, blue). LibRaw reads the pattern into an
    uninitialised buffer of the repeat's size: missing entries are whatever an earlier call
    left there, and the same bytes decode to a different colour layout (or none) from one call
    to the next.
    """
    first = tif.pages[0]
    for page in [first, *(getattr(first, "pages", None) or [])]:
        if 33421 in page.tags or 33422 in page.tags:
            _check_cfa_tags(path, page)


def _check_cfa_tags(path: Path, page) -> None:
    """One directory's CFA tags (see :func:`_refuse_inconsistent_cfa`)."""
    try:
        dims = tuple(_tag_values(page.tags[33421])) if 33421 in page.tags else ()
        codes = _tag_values(page.tags[33422]) if 33422 in page.tags else None
        n_planes = len(_tag_values(page.tags[50710])) if 50710 in page.tags else 3
    except Exception as err:  # noqa: BLE001  (tifffile cannot read a tag: as corrupt as a wrong count)
        raise InputError(f"{path}: corrupt colour filter tags ({type(err).__name__})") from None
    if len(dims) != 2 or min(dims) < 1 or codes is None or len(codes) != dims[0] * dims[1]:
        found = "no CFAPattern" if codes is None else f"a CFAPattern of {len(codes)} entries"
        raise InputError(
            f"{path}: corrupt colour filter tags: CFARepeatPatternDim {list(map(int, dims))} "
            f"with {found} (need rows x columns entries)"
        )
    if codes.max() >= n_planes:
        raise InputError(
            f"{path}: corrupt colour filter tags: CFAPattern colour {int(codes.max())} "
            f"beyond the {n_planes} colours of CFAPlaneColor"
        )


def _tiff_raw(path: Path, mmap: bool) -> tuple[dict[str, Any], Any]:
    """EXIF values and, for a simple DNG, its decoded raw image (else None) of a TIFF-based raw
    file (DNG, NEF, ...); ``({}, None)`` for other formats.

    Raises :class:`InputError` when the image data runs past the end of the file, when a DNG
    has directory entries tifffile cannot read, or when its metadata contradicts itself.
    """
    import tifffile

    from hdrcap.pipeline.io.dngread import decode_dng

    with _tiff_complaints() as complaints:
        try:
            tif = tifffile.TiffFile(path)
        except Exception as err:  # noqa: BLE001  (not a TIFF container, e.g. CR3, RAF: LibRaw's values are used)
            _refuse_unreadable_dng(path, err)
            return {}, None
        with tif:
            try:
                page = tif.pages[0]
                if not isinstance(page, tifffile.TiffPage):  # tifffile reads the first IFD as a page
                    raise TypeError("the first IFD is not a TIFF page")
                exif_tag = page.tags.get(34665)
                if exif_tag is not None:
                    exif_tag.value  # noqa: B018  (parse the EXIF IFD now, inside the complaint log)
                size = path.stat().st_size
                ends = [o + n for o, n in zip(page.dataoffsets, page.databytecounts)]
            except Exception as err:  # noqa: BLE001  (a TIFF header but no readable first IFD: LibRaw decides)
                _refuse_unreadable_dng(path, err)
                return {}, None
            exif = _exif_values(page, path)
            if ends and max(ends) > size:
                raise InputError(f"{path}: truncated raw file (image data runs past the end of the file)")
            _refuse_impossible_size(path, tif)
            try:
                direct = decode_dng(path, tif, mmap=mmap)
            except InputError:
                raise
            except Exception:  # noqa: BLE001  (tags tifffile cannot interpret: LibRaw decides)
                direct = None
            _refuse_corrupt_dng(path, page, complaints)  # IFD0, the EXIF IFD and the raw image's SubIFD
            _refuse_inconsistent_cfa(path, tif)
    return exif, direct


@dataclass(frozen=True)
class _Decoded:
    """What a raw decoder gives besides the EXIF values: pixels, levels, LibRaw's metadata."""

    data: np.ndarray
    cfa: str | None
    black: float
    white: float
    shutter: float | None = None
    iso: float | None = None
    timestamp: str | None = None


def _libraw_decode(path: Path) -> _Decoded:
    """Decode any raw format with rawpy (LibRaw): visible mosaic, levels, CFA, shutter, ISO, time."""
    import rawpy

    try:
        with quiet_stderr(), rawpy.imread(str(path)) as raw:
            data = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            other = _libraw_other(path, raw)
            desc = raw.color_desc.decode("ascii", "replace")
            pattern = raw.raw_pattern
            if raw.num_colors >= 3 and pattern is not None and pattern.shape == (2, 2):
                cfa = "".join(desc[int(i)] for i in pattern.ravel())
            else:
                cfa = None
            return _Decoded(
                data=data,
                cfa=cfa,
                black=float(np.mean(raw.black_level_per_channel)),
                white=float(raw.white_level),
                shutter=float(other.shutter_speed) if other.shutter_speed else None,
                iso=float(other.iso_speed) if other.iso_speed else None,
                timestamp=other.timestamp.isoformat() if other.timestamp else None,
            )
    except NotImplementedError as err:  # rawpy: a CFA layout it cannot describe (e.g. "filters: 148")
        raise InputError(f"{path}: unsupported colour filter layout ({err})") from None
    except rawpy.LibRawFileUnsupportedError:
        raise InputError(f"{path}: not a raw file LibRaw can read") from None
    except rawpy.LibRawIOError:
        raise InputError(f"{path}: truncated or unreadable raw file") from None
    except rawpy.LibRawError as err:
        raise InputError(f"{path}: cannot decode raw data ({type(err).__name__})") from None


def _libraw_other(path: Path, raw):
    """rawpy's ``other`` metadata (shutter, ISO, capture time); an impossible capture time (rawpy
    raises ValueError for e.g. the year 22026) is corrupt metadata and refused."""
    try:
        return raw.other
    except (ValueError, OverflowError) as err:
        raise InputError(f"{path}: impossible capture time in the raw metadata ({err})") from None


def adc_maximum(white_level: float) -> int:
    """The largest value an ADC whose white level is ``white_level`` can write, DN.

    The white level rounded up to a whole number of bits (2**bits - 1): LibRaw's white level of
    some cameras lies a little below the largest raw value, but no value can exceed the bit
    depth the white level implies.

    Parameters
    ----------
    white_level : float
        DN, > 0.

    Returns
    -------
    int
        DN, 2**bits - 1 with bits the bit length of ``ceil(white_level)``, at most 65535.
    """
    return min((1 << int(math.ceil(white_level)).bit_length()) - 1, 65535)


#: Colours of a 2x2 CFA tile that make a colour mosaic (Bayer RGB, or four-colour CMYG).
_CFA_COLOURS = ({"R", "G", "B"}, {"C", "M", "Y", "G"})


#: What :func:`read_raw` does with decoded values no sensor writes (above the white level's ADC
#: range): ``refuse`` the file (InputError), or ``mask`` them (:attr:`RawFrame.masked`).
BAD_VALUES = ("refuse", "mask")


def check_bad_values(bad_values: str) -> str:
    """Check a ``bad_values`` option.

    Parameters
    ----------
    bad_values : str
        What to do with impossible raw values: one of :data:`BAD_VALUES` (``refuse``, ``mask``).

    Returns
    -------
    str
        ``bad_values`` unchanged.

    Raises
    ------
    InputError
        Any other value.
    """
    if bad_values not in BAD_VALUES:
        raise InputError(f"bad values must be refused or masked (refuse, mask), got {bad_values!r}")
    return bad_values


def _check_decoded(path: Path, dec: _Decoded, bad_values: str = "refuse") -> np.ndarray | None:
    """Refuse decoded raw data that cannot be what a sensor wrote.

    Impossible dimensions, levels that contradict each other (black level not below the white
    level, negative or non-finite), a 2x2 CFA tile that is no colour mosaic, and pixel values
    above the ADC range the white level implies (:func:`adc_maximum`): all signs of a corrupt
    file or a wrong decode, never merged silently. With ``bad_values="mask"`` the impossible
    pixel values (a per-photosite problem) are returned as a mask instead of refused; every
    other problem is still refused.

    Returns
    -------
    numpy.ndarray or None
        bool map of the impossible values (``mask`` only), None when there are none.
    """
    data = dec.data
    if data.ndim != 2 or min(data.shape) < 2:
        raise InputError(f"{path}: impossible raw image dimensions {'x'.join(map(str, data.shape[::-1]))}")
    black, white = dec.black, dec.white
    if not (math.isfinite(white) and 0 < white <= 65535):
        raise InputError(f"{path}: impossible white level {white!r} DN (corrupt metadata)")
    if not (math.isfinite(black) and 0 <= black < white):
        raise InputError(
            f"{path}: black level {black!r} DN is not between 0 and the white level {white:g} DN (corrupt metadata)"
        )
    if dec.cfa is not None and not any(set(dec.cfa) == colours for colours in _CFA_COLOURS):
        raise InputError(f"{path}: CFA pattern {dec.cfa!r} is not a colour filter mosaic (corrupt metadata)")
    top = adc_maximum(white)
    high = int(data.max())
    if high <= top:
        return None
    bad = data > top
    if bad_values == "mask":
        return bad
    raise InputError(
        f"{path}: {int(np.count_nonzero(bad))} photosites above the white level ({high} DN > {top} DN, "
        f"the {top.bit_length()}-bit range of white level {white:g} DN): corrupt raw data "
        "(--bad-values mask merges the file without them)"
    )


def _direct_is_complete(exif: dict[str, Any], exposure_time: float | None) -> bool:
    """Whether the EXIF values leave nothing for LibRaw to supply (time, ISO, timestamp)."""
    has_time = exposure_time is not None or exif.get("ExposureTime") is not None
    return has_time and bool(exif.get("ISOSpeedRatings")) and bool(exif.get("DateTimeOriginal"))


def read_raw(
    path: str | os.PathLike[str],
    exposure_time: float | None = None,
    *,
    mmap: bool = True,
    bad_values: str = "refuse",
    fmt: FrameFormat | None = None,
) -> RawFrame:
    """Read a camera raw file (DNG, NEF, CR2, ...).

    An uncompressed DNG (8/16-bit strips or tiles, Bayer CFA, single black and white level) is
    decoded directly from the file (:mod:`pipeline.io.dngread`); every other file goes through
    rawpy (LibRaw). Both give the same visible CFA mosaic (LibRaw's ``raw_image_visible``) and
    levels.

    Parameters
    ----------
    path : str or os.PathLike
        The raw file.
    exposure_time : float, optional
        Seconds; overrides the file's EXIF ExposureTime.
    mmap : bool
        Map the pixels of a contiguous little-endian 16-bit DNG from the file (copy-on-write;
        the file must not be truncated or rewritten in place while the frame is in use), instead
        of reading them into memory.
    bad_values : {"refuse", "mask"}
        Pixel values above the white level's ADC range (:func:`adc_maximum`): refuse the file
        (default), or mask them (:attr:`RawFrame.masked`; the pixels keep their decoded values).
        Problems that are not per photosite (dimensions, levels, exposure time) are always
        refused.
    fmt : FrameFormat, optional
        What the user says about the frames: its CFA pattern, black and white level replace the
        file's; its bits set the quantisation step (MSB-aligned data: 2^(16 - bits) DN).

    Returns
    -------
    RawFrame
        uint16 mosaic (DN), exposure time (s), ISO, black and white levels (DN), CFA pattern,
        camera, serial, capture time and the masked photosites.
    """
    check_bad_values(bad_values)
    path = Path(path)
    check_readable(path)
    exif, direct = _tiff_raw(path, mmap)
    if direct is not None and _direct_is_complete(exif, exposure_time):
        dec = _Decoded(data=direct.data, cfa=direct.cfa_pattern, black=direct.black_level, white=direct.white_level)
    else:
        dec = _libraw_decode(path)
    dec, bits, step = _with_format(path, dec, fmt)
    masked = _check_decoded(path, dec, bad_values)
    t = exposure_time if exposure_time is not None else exif.get("ExposureTime")
    t = t if t is not None else dec.shutter
    if t is None:
        raise InputError(f"{path}: no exposure time in EXIF; give it explicitly (--times)")
    return RawFrame(
        data=dec.data,
        exposure_time=check_exposure_time(t, path),
        iso=float(exif["ISOSpeedRatings"]) if exif.get("ISOSpeedRatings") else dec.iso,
        black_level=dec.black,
        white_level=dec.white,
        cfa_pattern=dec.cfa,
        path=str(path),
        camera=exif.get("camera"),
        timestamp=exif.get("DateTimeOriginal") or dec.timestamp,
        masked=masked,
        bits=bits,
        quantisation_step=step,
        serial=exif.get("serial"),
    )


def _with_format(path: Path, dec: _Decoded, fmt: FrameFormat | None) -> tuple[_Decoded, int | None, float]:
    """A raw file's decoded levels and CFA with the user's format applied, its significant bits
    (None unless given) and quantisation step (DN)."""
    if fmt is None or not fmt.given:
        return dec, None, 1.0
    changes: dict[str, Any] = {}
    if fmt.cfa is not None:
        changes["cfa"] = fmt.cfa_pattern
    if fmt.black_level is not None:
        changes["black"] = float(fmt.black_level)
    if fmt.white_level is not None:
        changes["white"] = float(fmt.white_level)
    step = 1.0 if fmt.bits is None else aligned_step(dec.data, 16, int(fmt.bits), path)
    return dataclasses.replace(dec, **changes), fmt.bits, step


def _first_tiff_page(path: Path) -> tuple[np.ndarray, int]:
    """The pixels of a TIFF file's first page and its bits per sample.

    Never ``tifffile.imread``: it builds the file's image series by iterating its pages, which
    never ends on a circular chain of directories (a corrupt next-IFD offset). Counting the
    pages follows the chain with a guard that logs the loop (a complaint that refuses the file).
    """
    import tifffile

    with tifffile.TiffFile(path) as tif:
        len(tif.pages)  # walks the directory chain: a loop or a bad offset is logged
        page = tif.pages[0]
        _refuse_oversized_page(path, page)
        per_sample = getattr(page, "bitspersample", 16)
        bits = per_sample if isinstance(per_sample, int) else max(per_sample)
        return page.asarray(), int(bits)


def _image_pixels(path: Path) -> tuple[np.ndarray, int]:
    """A PNG's or TIFF's pixels and bits per sample (8, 16, or a TIFF's 10/12/14)."""
    with _tiff_complaints() as complaints:
        try:
            if path.suffix.lower() in (".tif", ".tiff"):
                data, bits = _first_tiff_page(path)
            else:
                from PIL import Image

                with Image.open(path) as im:
                    im.load()
                    data = np.array(im)
                bits = 8 if data.dtype == np.uint8 else 16
        except InputError:
            raise
        except Exception as err:  # PIL/tifffile raise many types for bad files
            raise InputError(f"{path}: cannot read image ({type(err).__name__}: {one_line(err)})") from None
    if complaints:  # a directory entry or page tifffile skipped: the pixels may be anything
        raise InputError(f"{path}: corrupt TIFF: {_tag_complaint(complaints[0])}")
    if data.ndim != 2:
        raise InputError(f"{path}: expected a single-channel (raw mosaic) image, got shape {data.shape}")
    if data.dtype not in (np.uint8, np.uint16):
        if np.issubdtype(data.dtype, np.integer) and data.min() >= 0 and data.max() < 65536:
            data = data.astype(np.uint16)
        else:
            raise InputError(f"{path}: expected 8- to 16-bit unsigned integer pixels, got {data.dtype}")
    return data.astype(np.uint16, copy=False), min(bits, 16)


def read_image16(path: str | os.PathLike[str], exposure_time: float | None, fmt: FrameFormat | None = None) -> RawFrame:
    """Read a single-channel PNG or TIFF (8 to 16 bits per sample) as a raw frame.

    Such files carry no exposure time, levels or CFA pattern: the time is required, the rest
    comes from ``fmt`` or is assumed (:func:`pipeline.io.frameformat.image_levels`: white level
    from the bit depth, MSB alignment detected in 16-bit words, black level 0 DN, monochrome),
    and what was assumed is listed in ``RawFrame.assumed``.

    Parameters
    ----------
    path : str or os.PathLike
        The image (single channel, 8 to 16 bits per sample).
    exposure_time : float or None
        Seconds (such files carry none); None is refused.
    fmt : FrameFormat, optional
        CFA pattern, black and white level (DN), significant bits.

    Returns
    -------
    RawFrame
        uint16 values (DN), the exposure time (s), black and white level (DN), CFA pattern,
        significant bits, quantisation step (DN) and what was assumed.

    Raises
    ------
    InputError
        No exposure time, an unreadable file, not a single-channel 8- to 16-bit image, or
        values that contradict ``fmt.bits``.
    """
    path = Path(path)
    check_readable(path)
    if exposure_time is None:
        raise InputError(f"{path}: a PNG/TIFF frame needs an explicit exposure time (--times)")
    t = check_exposure_time(exposure_time, path)
    data, stored_bits = _image_pixels(path)
    lv = image_levels(data, stored_bits, fmt, path)
    return RawFrame(
        data=data,
        exposure_time=t,
        black_level=lv.black_level,
        white_level=lv.white_level,
        cfa_pattern=lv.cfa_pattern,
        path=str(path),
        bits=lv.bits,
        quantisation_step=lv.step,
        assumed=lv.assumed,
    )


def read_frame(
    path: str | os.PathLike[str],
    exposure_time: float | None = None,
    *,
    mmap: bool = True,
    bad_values: str = "refuse",
    fmt: FrameFormat | None = None,
) -> RawFrame:
    """Read a raw file or a PNG/TIFF frame, choosing the reader by file type.

    Parameters
    ----------
    path : str or os.PathLike
        Raw file (:func:`read_raw`) or PNG/TIFF (:func:`read_image16`).
    exposure_time : float, optional
        Seconds; required for PNG/TIFF, overrides EXIF for raw files.
    mmap : bool
        See :func:`read_raw`.
    bad_values : {"refuse", "mask"}
        See :func:`read_raw` (a PNG/TIFF frame's values cannot exceed its bit depth: nothing to
        refuse or mask).
    fmt : FrameFormat, optional
        What the user says about the frame (CFA, levels, bits): see :func:`read_raw` and
        :func:`read_image16`.

    Returns
    -------
    RawFrame
    """
    check_bad_values(bad_values)
    path = Path(path)
    check_readable(path)
    if path.suffix.lower() in IMAGE_EXTENSIONS:
        return read_image16(path, exposure_time, fmt)
    return read_raw(path, exposure_time, mmap=mmap, bad_values=bad_values, fmt=fmt)


def with_format(frame: RawFrame, fmt: FrameFormat | None) -> RawFrame:
    """A frame in memory with the user's format applied, as :func:`read_frame` applies it to a
    file: the CFA pattern, black and white level given replace the frame's; the bits given set
    the quantisation step (MSB-aligned integer data: 2^(C - bits) DN, C the word's 8 or 16 bits).

    Parameters
    ----------
    frame : RawFrame
        The frame.
    fmt : FrameFormat or None
        What the user says (None: the frame unchanged).

    Returns
    -------
    RawFrame
        A new frame (pixels shared), or ``frame`` when ``fmt`` says nothing.

    Raises
    ------
    InputError
        Values that contradict ``fmt.bits``, or a black level not below the white level.
    """
    if fmt is None or not fmt.given:
        return frame
    changes: dict[str, Any] = {}
    if fmt.cfa is not None:
        changes["cfa_pattern"] = fmt.cfa_pattern
    if fmt.black_level is not None:
        changes["black_level"] = float(fmt.black_level)
    if fmt.white_level is not None:
        changes["white_level"] = float(fmt.white_level)
    if fmt.bits is not None:
        data = np.asarray(frame.data)
        stored = 8 if data.dtype == np.uint8 else 16
        integer = data.dtype.kind in "ui"
        changes["bits"] = int(fmt.bits)
        changes["quantisation_step"] = (
            aligned_step(data, stored, int(fmt.bits), frame.path or "frame") if integer else 1.0
        )
    out = dataclasses.replace(frame, **changes)
    black, white = out.black_level or 0.0, out.white_level
    if white is not None and black >= white:
        raise InputError(f"{frame.path or 'frame'}: black level {black:g} DN is not below the white level {white:g} DN")
    return out


#: Rows of a frame read into its duplicate-finding fingerprint (evenly spaced, whole rows).
_SAMPLE_ROWS = 16


def _pixel_sample(data: np.ndarray) -> bytes:
    """A cheap fingerprint of a 2-D frame's pixels: its shape, dtype and a few whole rows."""
    rows = np.unique(np.linspace(0, data.shape[0] - 1, _SAMPLE_ROWS).astype(int))
    head = f"{data.shape}{data.dtype}".encode()
    return hashlib.blake2b(head + np.ascontiguousarray(data[rows]).tobytes(), digest_size=16).digest()


#: Largest difference of the black levels of two frames of one set, as a fraction of the white
#: level (LibRaw measures some cameras' black level per frame from masked photosites).
BLACK_LEVEL_SPREAD = 0.01


def _check_same_sensor(frame: RawFrame, first: RawFrame, what: str) -> None:
    """Refuse a frame whose file metadata contradicts the first frame's: another CFA pattern,
    white level or black level (a corrupt tag that fell back to its default)."""
    name, ref = frame.path or "<array>", first.path or f"the first {what}"
    if frame.cfa_pattern != first.cfa_pattern:
        raise InputError(f"{name}: CFA pattern {frame.cfa_pattern} differs from {ref} ({first.cfa_pattern})")
    if frame.white_level is None or first.white_level is None:
        return
    if frame.white_level != first.white_level:
        raise InputError(f"{name}: white level {frame.white_level:g} DN differs from {ref} ({first.white_level:g} DN)")
    if abs((frame.black_level or 0.0) - (first.black_level or 0.0)) > BLACK_LEVEL_SPREAD * first.white_level:
        raise InputError(
            f"{name}: black level {frame.black_level or 0:g} DN differs from {ref} ({first.black_level or 0:g} DN)"
        )


def check_frames(frames: Iterable[RawFrame], what: str = "frame") -> list[RawFrame]:
    """Check a set of frames can be merged together: same size and sensor metadata, no duplicates.

    Frames must share their size, CFA pattern and white level, and their black levels may differ
    by at most :data:`BLACK_LEVEL_SPREAD` of the white level.

    Duplicates are the same file given twice or two frames with identical pixel data. Frames are
    paired by a sample of their pixels (a few whole rows) and a pair is confirmed by comparing
    all pixels, so two different exposures never collide and no frame is hashed in full.

    Parameters
    ----------
    frames : iterable of RawFrame
        The frames, in the order given.
    what : str
        Their name in error messages ("frame", "dark frame").

    Returns
    -------
    list of RawFrame
        The frames.
    """
    frames = list(frames)
    if not frames:
        raise InputError(f"no {what}s given")
    shape = frames[0].shape
    seen_paths: dict[str, str] = {}
    seen_data: dict[bytes, list[RawFrame]] = {}
    for fr in frames:
        name = fr.path or "<array>"
        if fr.shape != shape:
            raise InputError(
                f"{name}: size {fr.shape[1]}x{fr.shape[0]} differs from {frames[0].path or 'the first ' + what} "
                f"({shape[1]}x{shape[0]})"
            )
        _check_same_sensor(fr, frames[0], what)
        if fr.path is not None:
            real = os.path.realpath(fr.path)
            if real in seen_paths:
                raise InputError(f"{name}: the same file is given twice")
            seen_paths[real] = name
        same_sample = seen_data.setdefault(_pixel_sample(fr.data), [])
        for other in same_sample:
            if np.array_equal(other.data, fr.data):
                raise InputError(f"{name}: duplicate {what}, its pixels are identical to {other.path or '<array>'}")
        same_sample.append(fr)
    return frames
