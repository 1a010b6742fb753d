"""Write a CFA mosaic as a minimal, valid DNG 1.4 file.

The file is a little-endian TIFF with one uncompressed 16-bit CFA image in IFD0 and an EXIF
sub-IFD. It carries what LibRaw (rawpy, HDRMerge) needs: the CFA pattern, BlackLevel,
WhiteLevel, a colour matrix, the camera make/model/serial, the capture timestamp, and
ExposureTime, FNumber and ISO both in IFD0 (TIFF/EP) and in the EXIF IFD (LibRaw takes the
ISO from the EXIF IFD to compute exposure values).

No TIFF library writes an EXIF sub-IFD with DNG tags, so this is the one hand-written
encoder of the project; :func:`pipeline.io.read_raw` reads the files back through rawpy.
"""

from __future__ import annotations

import datetime as _dt
import struct
from fractions import Fraction

import numpy as np

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


def write_dng(
    fileobj,
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
) -> None:
    """Write ``mosaic`` (2-D uint16 CFA data) as a DNG to the binary file object ``fileobj``.

    Parameters
    ----------
    exposure_time : float
        Seconds; written as the rational of :func:`exposure_rational`.
    iso : int
        ISO speed, written to IFD0 and to the EXIF IFD.
    black_level, white_level : float, int
        DN, written to BlackLevel and WhiteLevel.
    cfa : str
        Bayer pattern of the 2x2 tile, e.g. ``"RGGB"``.
    timestamp : datetime
        Capture time (DateTime, DateTimeOriginal); defaults to now (UTC).
    """
    mosaic = np.ascontiguousarray(mosaic)
    if mosaic.ndim != 2 or mosaic.dtype != np.uint16:
        raise ValueError("the mosaic must be a 2-D uint16 array")
    h, w = mosaic.shape
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ValueError(f"LibRaw reads no raw image under {MIN_SIDE} photosites a side, got {w}x{h}")
    ts = (timestamp or _dt.datetime.now(_dt.timezone.utc)).strftime("%Y:%m:%d %H:%M:%S")
    exp = exposure_rational(exposure_time)
    fnum = _rational(f_number, 100)
    model_full = f"{make} {model}"

    ifd0 = _IFD()
    ifd0.add(254, _LONG, 0)
    ifd0.add(256, _LONG, w)
    ifd0.add(257, _LONG, h)
    ifd0.add(258, _SHORT, 16)
    ifd0.add(259, _SHORT, 1)
    ifd0.add(262, _SHORT, 32803)  # CFA
    if description:
        ifd0.add(270, _ASCII, description)
    ifd0.add(271, _ASCII, make)
    ifd0.add(272, _ASCII, model)
    ifd0.add(273, _LONG, 0)  # strip offset, patched below
    ifd0.add(274, _SHORT, 1)
    ifd0.add(277, _SHORT, 1)
    ifd0.add(278, _LONG, h)
    ifd0.add(279, _LONG, h * w * 2)
    ifd0.add(284, _SHORT, 1)
    ifd0.add(305, _ASCII, software)
    ifd0.add(306, _ASCII, ts)
    ifd0.add(33421, _SHORT, [2, 2])
    ifd0.add(33422, _BYTE, [CFA_CODES[c] for c in cfa])
    ifd0.add(33434, _RATIONAL, [exp])
    ifd0.add(33437, _RATIONAL, [fnum])
    ifd0.add(34665, _LONG, 0)  # EXIF IFD offset, patched below
    ifd0.add(34855, _SHORT, min(int(iso), 65535))
    ifd0.add(50706, _BYTE, [1, 4, 0, 0])
    ifd0.add(50707, _BYTE, [1, 1, 0, 0])
    ifd0.add(50708, _ASCII, model_full)
    ifd0.add(50710, _BYTE, [0, 1, 2])
    ifd0.add(50711, _SHORT, 1)
    ifd0.add(50713, _SHORT, [1, 1])
    ifd0.add(50714, _RATIONAL, [_rational(black_level, 1000)])
    ifd0.add(50717, _LONG, int(white_level))
    ifd0.add(50721, _SRATIONAL, [(1, 1), (0, 1), (0, 1), (0, 1), (1, 1), (0, 1), (0, 1), (0, 1), (1, 1)])
    ifd0.add(50728, _RATIONAL, [(1, 1), (1, 1), (1, 1)])
    ifd0.add(50735, _ASCII, serial)
    ifd0.add(50778, _SHORT, 21)

    exif = _IFD()
    exif.add(33434, _RATIONAL, [exp])
    exif.add(33437, _RATIONAL, [fnum])
    exif.add(34855, _SHORT, min(int(iso), 65535))
    exif.add(36864, _UNDEFINED, list(b"0230"))
    exif.add(36867, _ASCII, ts)
    exif.add(36868, _ASCII, ts)

    # Layout: header (8) | IFD0 | EXIF IFD | image data (2-byte aligned).
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
    fileobj.write(bytes(out))
    fileobj.write(mosaic.astype("<u2", copy=False).tobytes())
