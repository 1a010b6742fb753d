"""Write a CFA mosaic as a minimal, valid DNG 1.4 file.

The file is a little-endian TIFF with one uncompressed 16-bit CFA image in IFD0 and an EXIF
sub-IFD. It carries what LibRaw (rawpy, HDRMerge) needs: the CFA pattern, BlackLevel,
WhiteLevel, a colour matrix, the camera make/model/serial, the capture timestamp, and
ExposureTime, FNumber and ISO both in IFD0 (TIFF/EP) and in the EXIF IFD (LibRaw takes the
ISO from the EXIF IFD to compute exposure values).

No TIFF library writes an EXIF sub-IFD with DNG tags, so this is the one hand-written
encoder of the project; :func:`hdrcap.pipeline.io.raw.read_raw` reads the files back through rawpy.
"""

from __future__ import annotations

import datetime as _dt
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import BinaryIO

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["write_dng", "exposure_rational", "CFA_CODES", "MIN_SIDE"]

CFA_CODES = {"R": 0, "G": 1, "B": 2}

#: LibRaw (rawpy, HDRMerge) rejects raw images smaller than this on either side.
MIN_SIDE = 22

# TIFF field types
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _UNDEFINED, _SRATIONAL = 1, 2, 3, 4, 5, 7, 10
_SIZES = {_BYTE: 1, _ASCII: 1, _SHORT: 2, _LONG: 4, _RATIONAL: 8, _UNDEFINED: 1, _SRATIONAL: 8}


def exposure_rational(t: float) -> tuple[int, int]:
    """The exposure time ``t`` (s) as the TIFF RATIONAL written to the file.

    The simulated camera exposes for exactly ``num/den`` seconds, so the file never lies.
    """
    if not (t > 0 and np.isfinite(t)):
        raise ValueError(f"exposure time must be finite and > 0, got {t!r}")
    f = Fraction(t).limit_denominator(1_000_000_000 if t < 4 else 1000)
    if f == 0 or f.numerator >= 2**32 or f.denominator >= 2**32:
        raise ValueError(f"exposure time {t!r} s cannot be written as a TIFF rational")
    return f.numerator, f.denominator


def _rational(x: float, den: int = 1_000_000) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(den)
    return f.numerator, f.denominator


class _IFD:
    def __init__(self):
        self.entries: dict[int, tuple[int, list]] = {}

    def add(self, tag: int, typ: int, values) -> None:
        if typ == _ASCII:
            values = list(values.encode("ascii", "replace") + b"\0")
        elif not isinstance(values, (list, tuple)):
            values = [values]
        self.entries[tag] = (typ, list(values))

    def _payload(self, typ, values) -> bytes:
        if typ in (_BYTE, _ASCII, _UNDEFINED):
            return bytes(values)
        if typ == _SHORT:
            return struct.pack(f"<{len(values)}H", *values)
        if typ == _LONG:
            return struct.pack(f"<{len(values)}I", *values)
        if typ == _RATIONAL:
            return b"".join(struct.pack("<II", *v) for v in values)
        if typ == _SRATIONAL:
            return b"".join(struct.pack("<ii", *v) for v in values)
        raise ValueError(typ)

    def size(self) -> int:
        n = len(self.entries)
        extra = sum(
            (len(p) + (len(p) & 1)) for p in (self._payload(t, v) for t, v in self.entries.values()) if len(p) > 4
        )
        return 2 + 12 * n + 4 + extra

    def encode(self, offset: int, next_ifd: int = 0) -> bytes:
        """Serialise this IFD placed at file ``offset``; out-of-line data follows it."""
        n = len(self.entries)
        data_off = offset + 2 + 12 * n + 4
        head = [struct.pack("<H", n)]
        tail = []
        for tag in sorted(self.entries):
            typ, values = self.entries[tag]
            payload = self._payload(typ, values)
            count = len(values)
            if len(payload) <= 4:
                head.append(struct.pack("<HHI", tag, typ, count) + payload.ljust(4, b"\0"))
            else:
                head.append(struct.pack("<HHII", tag, typ, count, data_off))
                if len(payload) & 1:
                    payload += b"\0"
                tail.append(payload)
                data_off += len(payload)
        head.append(struct.pack("<I", next_ifd))
        return b"".join(head) + b"".join(tail)


@dataclass(frozen=True)
class _Capture:
    """What the tags say about one capture (the values as written)."""

    exposure: tuple[int, int]
    f_number: tuple[int, int]
    iso: int
    timestamp: str


def _check_mosaic(mosaic: np.ndarray) -> np.ndarray:
    """A C-contiguous 2-D uint16 mosaic that LibRaw will read (>= MIN_SIDE a side)."""
    mosaic = np.ascontiguousarray(mosaic)
    if mosaic.ndim != 2 or mosaic.dtype != np.uint16:
        raise ValueError("the mosaic must be a 2-D uint16 array")
    h, w = mosaic.shape
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ValueError(f"LibRaw reads no raw image under {MIN_SIDE} photosites a side, got {w}x{h}")
    return mosaic


def _image_tags(ifd: _IFD, h: int, w: int, cfa: str) -> None:
    """TIFF baseline and TIFF/EP tags of one uncompressed 16-bit CFA strip, or of a monochrome
    (LinearRaw, one sample) image for ``cfa == "mono"`` (offset patched later)."""
    ifd.add(254, _LONG, 0)  # NewSubFileType: main image
    ifd.add(256, _LONG, w)
    ifd.add(257, _LONG, h)
    ifd.add(258, _SHORT, 16)  # BitsPerSample
    ifd.add(259, _SHORT, 1)  # no compression
    ifd.add(262, _SHORT, 34892 if cfa == "mono" else 32803)  # PhotometricInterpretation: LinearRaw or CFA
    ifd.add(273, _LONG, 0)  # StripOffsets, patched by _layout
    ifd.add(274, _SHORT, 1)  # Orientation
    ifd.add(277, _SHORT, 1)  # SamplesPerPixel
    ifd.add(278, _LONG, h)  # RowsPerStrip
    ifd.add(279, _LONG, h * w * 2)  # StripByteCounts
    ifd.add(284, _SHORT, 1)  # PlanarConfiguration
    if cfa != "mono":
        ifd.add(33421, _SHORT, [2, 2])  # CFARepeatPatternDim
        ifd.add(33422, _BYTE, [CFA_CODES[c] for c in cfa])  # CFAPattern


def _camera_tags(ifd: _IFD, cap: _Capture, make: str, model: str, software: str, description: str) -> None:
    """Who made the file and how it was exposed (IFD0; the EXIF IFD offset patched later)."""
    if description:
        ifd.add(270, _ASCII, description)
    ifd.add(271, _ASCII, make)
    ifd.add(272, _ASCII, model)
    ifd.add(305, _ASCII, software)
    ifd.add(306, _ASCII, cap.timestamp)
    ifd.add(33434, _RATIONAL, [cap.exposure])
    ifd.add(33437, _RATIONAL, [cap.f_number])
    ifd.add(34665, _LONG, 0)  # ExifIFD offset, patched by _layout
    ifd.add(34855, _SHORT, cap.iso)


def _dng_tags(
    ifd: _IFD,
    unique_model: str,
    serial: str,
    black_level: float,
    white_level: int,
    color_matrix: ArrayLike | None = None,
    as_shot_neutral: Sequence[float] | None = None,
    mono: bool = False,
) -> None:
    """DNG 1.4 tags: version, camera model, CFA layout, black and white levels, the colour
    matrix (XYZ to camera, default identity), the white balance (AsShotNeutral, default neutral),
    serial number and the D65 illuminant; a monochrome image (``mono``) has no CFA layout and no
    colour tags."""
    matrix = np.eye(3) if color_matrix is None else np.asarray(color_matrix, dtype=float)
    neutral = (1.0, 1.0, 1.0) if as_shot_neutral is None else tuple(float(v) for v in as_shot_neutral)
    if matrix.shape != (3, 3) or len(neutral) != 3 or not all(v > 0 for v in neutral):
        raise ValueError("the colour matrix must be 3x3 and AsShotNeutral three positive values")
    ifd.add(50706, _BYTE, [1, 4, 0, 0])  # DNGVersion
    ifd.add(50707, _BYTE, [1, 1, 0, 0])  # DNGBackwardVersion
    ifd.add(50708, _ASCII, unique_model)  # UniqueCameraModel
    if not mono:
        ifd.add(50710, _BYTE, [0, 1, 2])  # CFAPlaneColor
        ifd.add(50711, _SHORT, 1)  # CFALayout: rectangular
    ifd.add(50713, _SHORT, [1, 1])  # BlackLevelRepeatDim
    ifd.add(50714, _RATIONAL, [_rational(black_level, 1000)])
    ifd.add(50717, _LONG, int(white_level))
    if not mono:
        ifd.add(50721, _SRATIONAL, [_rational(v, 10000) for v in matrix.ravel()])  # ColorMatrix1
        ifd.add(50728, _RATIONAL, [_rational(v, 10000) for v in neutral])  # AsShotNeutral
    ifd.add(50735, _ASCII, serial)  # CameraSerialNumber
    if not mono:
        ifd.add(50778, _SHORT, 21)  # CalibrationIlluminant1: D65


def _exif_ifd(cap: _Capture) -> _IFD:
    """The EXIF sub-IFD: exposure, aperture, ISO (LibRaw reads the ISO here), dates."""
    exif = _IFD()
    exif.add(33434, _RATIONAL, [cap.exposure])
    exif.add(33437, _RATIONAL, [cap.f_number])
    exif.add(34855, _SHORT, cap.iso)
    exif.add(36864, _UNDEFINED, list(b"0230"))  # ExifVersion
    exif.add(36867, _ASCII, cap.timestamp)  # DateTimeOriginal
    exif.add(36868, _ASCII, cap.timestamp)  # DateTimeDigitized
    return exif


def _layout(ifd0: _IFD, exif: _IFD) -> bytes:
    """Header (8 bytes) | IFD0 | EXIF IFD | image data, each 2-byte aligned: patch the EXIF
    and strip offsets into IFD0 and return everything before the image data."""
    ifd0_off = 8
    exif_off = ifd0_off + ifd0.size()
    exif_off += exif_off & 1
    data_off = exif_off + exif.size()
    data_off += data_off & 1
    ifd0.add(34665, _LONG, exif_off)
    ifd0.add(273, _LONG, data_off)
    out = bytearray(b"II*\0" + struct.pack("<I", ifd0_off))
    out += ifd0.encode(ifd0_off)
    out += b"\0" * (exif_off - len(out))
    out += exif.encode(exif_off)
    out += b"\0" * (data_off - len(out))
    return bytes(out)


def write_dng(
    fileobj: BinaryIO,
    mosaic: np.ndarray,
    *,
    exposure_time: float,
    iso: int,
    black_level: float,
    white_level: int,
    cfa: str = "RGGB",
    make: str = "hdrcap",
    model: str = "Simulated",
    serial: str = "0",
    timestamp: _dt.datetime | None = None,
    f_number: float = 8.0,
    software: str = "hdrcap",
    description: str = "",
    color_matrix: ArrayLike | None = None,
    as_shot_neutral: Sequence[float] | None = None,
) -> None:
    """Write ``mosaic`` (2-D uint16 CFA data) as a DNG to the binary file object ``fileobj``.

    Parameters
    ----------
    fileobj : binary file
        Where the bytes go (written in two calls: the tags, then the image data).
    mosaic : numpy.ndarray
        2-D uint16 raw mosaic, DN, at least :data:`MIN_SIDE` photosites a side.
    exposure_time : float
        Seconds; written as the rational of :func:`exposure_rational`.
    iso : int
        ISO speed, written to IFD0 and to the EXIF IFD.
    black_level, white_level : float, int
        DN, written to BlackLevel and WhiteLevel.
    cfa : str
        Bayer pattern of the 2x2 tile, e.g. ``"RGGB"``, or ``"mono"``: a monochrome image
        (PhotometricInterpretation LinearRaw, one sample, no colour tags).
    make, model, serial, software, description : str
        Written to Make, Model (and ``make model`` to UniqueCameraModel), CameraSerialNumber,
        Software and ImageDescription (omitted when empty).
    timestamp : datetime
        Capture time (DateTime, DateTimeOriginal); defaults to now (UTC).
    f_number : float
        Aperture, written as a rational.
    color_matrix : array_like, optional
        3x3 ColorMatrix1 (XYZ to camera, D65), written as signed rationals; default identity.
    as_shot_neutral : sequence of 3 float, optional
        AsShotNeutral (camera-space white balance, > 0); default (1, 1, 1).

    Raises
    ------
    ValueError
        A mosaic that is not 2-D uint16 or is too small; an exposure time that is not a
        positive finite rational; a colour matrix that is not 3x3 or a non-positive neutral.
    """
    mosaic = _check_mosaic(mosaic)
    h, w = mosaic.shape
    cap = _Capture(
        exposure=exposure_rational(exposure_time),
        f_number=_rational(f_number, 100),
        iso=min(int(iso), 65535),
        timestamp=(timestamp or _dt.datetime.now(_dt.UTC)).strftime("%Y:%m:%d %H:%M:%S"),
    )
    ifd0 = _IFD()
    _image_tags(ifd0, h, w, cfa)
    _camera_tags(ifd0, cap, make, model, software, description)
    _dng_tags(
        ifd0, f"{make} {model}", serial, black_level, white_level, color_matrix, as_shot_neutral, mono=cfa == "mono"
    )
    fileobj.write(_layout(ifd0, _exif_ifd(cap)))
    fileobj.write(mosaic.astype("<u2", copy=False).tobytes())
