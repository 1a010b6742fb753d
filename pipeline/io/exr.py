"""EXR files: channels (float32, half or uint) and a JSON header, written atomically.

The metadata goes into one string attribute ``hdrcap`` (JSON, full precision); its scalar string
entries are also written as plain header attributes so that any EXR viewer shows them. A merge
result is read and written through :mod:`hdrcap.pipeline.io.results`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hdrcap.pipeline.blocks import flat_blocks
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import atomic_output, check_readable, quiet_stderr

__all__ = [
    "EXR_COMPRESSIONS",
    "EXR_PRECISIONS",
    "HALF_RANGE",
    "HALF_RELATIVE_ERROR",
    "ExrContent",
    "ExrRows",
    "as_stored",
    "read_exr",
    "ExrLayout",
    "read_exr_layout",
    "stored_precisions",
    "write_exr",
]


class ExrContent(NamedTuple):
    """What an EXR file holds: its channels and hdrcap's header.

    Attributes
    ----------
    channels : dict of str to numpy.ndarray
        2-D arrays of one shape, by channel name.
    header : dict
        The JSON metadata hdrcap wrote (empty for a file hdrcap did not write).
    """

    channels: dict[str, np.ndarray]
    header: dict[str, Any]

    @property
    def shape(self) -> tuple[int, int]:
        """Size (rows, columns) of the channels."""
        h, w = np.shape(next(iter(self.channels.values())))
        return int(h), int(w)


_META_KEY = "hdrcap"


#: EXR compression names accepted by :func:`write_exr`, and OpenEXR's constant for each.
_EXR_CODES = {
    "zip": "ZIP_COMPRESSION",
    "zips": "ZIPS_COMPRESSION",
    "piz": "PIZ_COMPRESSION",
    "zstd": "ZSTD_COMPRESSION",
    "rle": "RLE_COMPRESSION",
    "none": "NO_COMPRESSION",
}


EXR_COMPRESSIONS = tuple(_EXR_CODES)


#: Channel precisions accepted by :func:`write_exr` and their numpy dtype (EXR FLOAT, HALF,
#: UINT); ``"auto"`` is half when the channel fits :data:`HALF_RANGE`, else float.
EXR_PRECISIONS = {"float": np.float32, "half": np.float16, "uint": np.uint32, "auto": None}


#: Smallest and largest magnitude a half stores with full relative precision (normal range).
HALF_RANGE = (float(np.finfo(np.float16).tiny), float(np.finfo(np.float16).max))


#: Largest relative rounding error of a value stored as half in :data:`HALF_RANGE` (2**-11).
HALF_RELATIVE_ERROR = 2.0**-11


def _stored_as(name: str, arr: Any, precision: str) -> str:
    """The precision (``float``, ``half`` or ``uint``) a channel is stored in, checked against
    the whole channel without converting it: refused where the conversion would lose more than
    :data:`HALF_RELATIVE_ERROR` (half) or anything at all (uint). An array already of the
    target type (float16 for half or auto, uint32 for uint) is stored as it is."""
    if precision not in EXR_PRECISIONS:
        raise ValueError(f"channel {name!r}: precision must be one of {', '.join(EXR_PRECISIONS)}, got {precision!r}")
    if name == "irradiance" and precision != "float":
        raise ValueError("the irradiance channel is always stored as float (32 bits)")
    if np.dtype(arr.dtype) == np.float16 and precision in ("half", "auto"):
        return "half"  # already half: stored as it is, nothing to lose or check
    if precision in ("half", "auto"):
        lo, hi = _magnitude_range(arr)
        fits = lo is None or hi is None or (lo >= HALF_RANGE[0] and hi <= HALF_RANGE[1])
        if precision == "auto":
            return "half" if fits else "float"
        if not fits:
            raise ValueError(
                f"channel {name!r}: values {lo:.3g}..{hi:.3g} are outside the half range "
                f"{HALF_RANGE[0]:.3g}..{HALF_RANGE[1]:.3g}; store it as float"
            )
    elif precision == "uint" and not _whole_uint32(arr):
        raise ValueError(f"channel {name!r}: uint needs whole numbers 0..2**32-1")
    return precision


def _exr_channel(name: str, arr: np.ndarray, precision: str) -> np.ndarray:
    """``arr`` converted to the dtype it is stored in (:func:`_stored_as`)."""
    arr = np.asarray(arr)
    return np.ascontiguousarray(arr, dtype=EXR_PRECISIONS[_stored_as(name, arr, precision)])


#: Elements of a channel checked at a time by :func:`_magnitude_range` and :func:`_whole_uint32`
#: (small temporaries that stay in the CPU cache, instead of full-size masks and copies).
_CHECK_BLOCK = 1 << 16


def _magnitude_range(arr: np.ndarray) -> tuple[float | None, float | None]:
    """(min, max) of |value| over the finite non-zero values of ``arr`` (same unit); (None,
    None) when there are none."""
    lo, hi = math.inf, -math.inf
    for blk in flat_blocks(arr, _CHECK_BLOCK):
        mag = np.abs(blk, dtype=np.float64) if blk.dtype.kind in "iub" else np.abs(blk)
        ok = np.isfinite(mag) & (mag != 0)
        if ok.any():
            lo = min(lo, float(mag.min(where=ok, initial=math.inf)))
            hi = max(hi, float(mag.max(where=ok, initial=-math.inf)))
    return (None, None) if hi < 0 else (lo, hi)


def _whole_uint32(arr: np.ndarray) -> bool:
    """Whether every value of ``arr`` is a whole number in 0..2**32-1 (what EXR UINT stores)."""
    if arr.dtype.kind == "b" or (arr.dtype.kind == "u" and arr.dtype.itemsize <= 4):
        return True  # every value fits, without a scan
    if arr.dtype.kind in "iu":
        return arr.size == 0 or (int(arr.min()) >= 0 and int(arr.max()) <= 2**32 - 1)
    if arr.dtype.kind != "f":
        return False
    for blk in flat_blocks(arr, _CHECK_BLOCK):
        if not ((blk >= 0) & (blk <= 2**32 - 1) & (blk == np.floor(blk))).all():
            return False  # NaN fails every comparison, inf the range
    return True


def as_stored(channels: dict[str, Any], precision: dict[str, str] | None = None) -> dict[str, np.ndarray]:
    """The channels as :func:`write_exr` stores and :func:`read_exr` returns them: float32,
    rounded through each channel's storage precision (half keeps 11 significant bits).

    Parameters
    ----------
    channels : mapping of str to array
        2-D channels.
    precision : dict, optional
        Channel name -> precision, as for :func:`write_exr` (default float for every channel).

    Returns
    -------
    dict of str to numpy.ndarray
        float32 arrays equal to what reading the written file gives.
    """
    precision = precision or {}
    return {
        name: np.ascontiguousarray(_exr_channel(name, arr, precision.get(name, "float")), dtype=np.float32)
        for name, arr in channels.items()
    }


def _set_exr_threads(openexr, threads: int | None) -> None:
    """Size OpenEXR's global thread pool: ``threads``, or the CPUs (at most 8) if it is empty."""
    if threads is None:
        threads = openexr.global_thread_count() or min(os.cpu_count() or 1, 8)
    if openexr.global_thread_count() != threads:
        openexr.set_global_thread_count(threads)


def _rows_of(src: Any, r0: int, r1: int) -> np.ndarray:
    """Rows ``r0:r1`` of a channel: an array, or an object with ``rows(r0, r1)`` (a file read
    on demand)."""
    return np.asarray(src.rows(r0, r1) if hasattr(src, "rows") else src[r0:r1])


def _decide_in_blocks(name: str, src: Any, want: str, rows: int) -> str:
    """``auto``/``half`` of a channel decided from the whole channel's extrema, read block by
    block (as :func:`_stored_as` decides it for a whole array): ``half``, ``float``, or the
    refusal."""
    from hdrcap.pipeline.io.files import release_mapped_pages

    if want not in ("auto", "half"):
        return _stored_as(name, np.empty((0, 0), np.float32), want)  # checks the name and precision only
    lo, hi = math.inf, 0.0
    for r0 in range(0, int(np.shape(src)[0]), rows):
        block = _rows_of(src, r0, r0 + rows)
        mag = np.abs(block[np.isfinite(block) & (block != 0)])
        if mag.size:
            lo, hi = min(lo, float(mag.min())), max(hi, float(mag.max()))
        release_mapped_pages([block])
    return _stored_as(name, np.array([lo, hi] if hi > 0 else [], np.float32), want)


def _header_attributes(header: dict[str, Any]) -> dict[str, str]:
    """The EXR attributes of hdrcap's header: the JSON, and each string entry on its own."""
    attrs = {_META_KEY: json.dumps(header, sort_keys=True, default=_json_default)}
    for key, val in header.items():
        if isinstance(val, str):
            attrs[f"{_META_KEY}:{key}"] = val
    return attrs


def write_exr(
    path: str | os.PathLike[str],
    channels: dict[str, Any],
    header: dict[str, Any] | None = None,
    *,
    force: bool = False,
    compression: str = "zip",
    precision: dict[str, str] | None = None,
    threads: int | None = None,
    block_rows: int | None = None,
) -> Path:
    """Write channels and a header as a single-part scanline EXR, atomically, block by block.

    The header goes into one string attribute ``hdrcap`` (JSON, full precision), and its
    string entries are also written as plain attributes so that any EXR viewer shows them.
    :func:`read_exr` reads every precision back as float32.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; its folder must exist.
    channels : dict of str to array
        2-D arrays of one shape by name (or, with ``block_rows``, objects with ``shape`` and
        ``rows(r0, r1)`` that read a file on demand).
    header : dict, optional
        JSON-ready metadata.
    force : bool
        Replace an existing file.
    compression : str
        One of :data:`EXR_COMPRESSIONS`: ``zip`` (default) and ``zips`` are the smallest of the
        lossless codecs OpenEXR < 3.4 reads, ``zstd`` as small and faster but needs OpenEXR >=
        3.4 to read, ``rle``/``none`` the fastest and largest, ``piz`` between
        (docs/merge.md, "Speed and memory").
    precision : dict, optional
        Channel name -> ``"float"`` (32-bit, the default for every channel), ``"half"`` (16-bit
        float: relative rounding error at most :data:`HALF_RELATIVE_ERROR`, 0.05 %; refused when
        a finite non-zero value lies outside :data:`HALF_RANGE`), ``"auto"`` (half if the
        channel fits that range, else float) or ``"uint"`` (32-bit unsigned: whole numbers
        only, lossless). ``irradiance`` is always float.
    threads : int, optional
        OpenEXR's compression threads (its global thread pool, which this sets). Default: the
        pool as it is, or the number of CPUs (at most 8) if it has no threads.
    block_rows : int, optional
        Scanlines written at a time (default 512). Each channel's rows are read only then (the
        pages of memory-mapped channels are released after each block: channels larger than
        memory) and converted to their stored type in a buffer reused for every block, so no
        full-size copy of a channel is made. The file's bytes do not depend on it.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        No channels, channels of different shapes, an unknown compression or precision, a
        channel that does not fit its precision.
    OutputExistsError
        The file exists and ``force`` is false.
    """
    import OpenEXR

    if not channels:
        raise ValueError("an EXR needs at least one channel")
    if compression not in _EXR_CODES or not hasattr(OpenEXR, _EXR_CODES[compression]):
        raise ValueError(f"EXR compression must be one of {', '.join(_EXR_CODES)}, got {compression!r}")
    precision = precision or {}
    unknown = set(precision) - set(channels)
    if unknown:
        raise ValueError(f"precision given for channels the image does not have: {', '.join(sorted(unknown))}")
    shape = tuple(np.shape(next(iter(channels.values()))))
    for name, arr in channels.items():
        if tuple(np.shape(arr)) != shape:
            raise ValueError(f"channel {name!r} has shape {np.shape(arr)}, expected {shape}")
    attrs = _header_attributes(dict(header or {}))
    _set_exr_threads(OpenEXR, threads)
    rows = int(block_rows) if block_rows else _WRITE_ROWS
    return _write_scanlines(Path(path), channels, attrs, precision, compression, force, rows)


#: Scanlines handed to OpenEXR at a time by :func:`write_exr` (its thread pool compresses
#: them in 16-line chunks; a block of every channel is a few MB, converted into reused buffers).
_WRITE_ROWS = 512


def _write_scanlines(
    path: Path, channels: dict[str, Any], attrs: dict[str, str], precision: dict[str, str], compression, force, rows
) -> Path:
    """:func:`write_exr` block of ``rows`` scanlines by block (OpenEXR's scanline writer): each
    channel's block is converted to its stored type in a buffer reused for every block (none
    when it already is of that type), so no full-size copy of a channel is made."""
    import Imath
    import OpenEXR

    from hdrcap.pipeline.io.files import release_mapped_pages

    h, w = (int(n) for n in np.shape(next(iter(channels.values()))))
    in_file = {n for n, src in channels.items() if _in_file(src)}  # checked block by block, pages released
    stored = {
        n: _decide_in_blocks(n, src, precision.get(n, "float"), rows)
        if n in in_file
        else _stored_as(n, src, precision.get(n, "float"))
        for n, src in channels.items()
    }
    kinds = {"float": Imath.PixelType.FLOAT, "half": Imath.PixelType.HALF, "uint": Imath.PixelType.UINT}
    head = OpenEXR.Header(w, h)
    head["channels"] = {name: Imath.Channel(Imath.PixelType(kinds[stored[name]])) for name in channels}
    head["compression"] = Imath.Compression(int(getattr(OpenEXR, _EXR_CODES[compression])))
    head["type"] = b"scanlineimage"  # what OpenEXR.File writes: the same bytes as its whole-image writer
    for key, val in attrs.items():
        head[key] = val.encode()
    buffers: dict[str, np.ndarray] = {}
    with atomic_output(path, force=force, suffix=".exr") as tmp:
        exr = OpenEXR.OutputFile(str(tmp), head)
        try:
            for r0 in range(0, h, rows):
                n = min(rows, h - r0)
                blocks = {name: _rows_of(src, r0, r0 + n) for name, src in channels.items()}
                data = {n: _stored_block(n, b, stored[n], buffers, rows, n in in_file) for n, b in blocks.items()}
                exr.writePixels(data, n)
                release_mapped_pages(blocks.values())
        finally:
            exr.close()
    return path


def _in_file(src: Any) -> bool:
    """Whether a channel is read from a file: an object with ``rows(r0, r1)`` or a memory map."""
    base = src
    while isinstance(base, np.ndarray) and not isinstance(base, np.memmap):
        base = base.base
    return not isinstance(src, np.ndarray) or isinstance(base, np.memmap)


def _stored_block(
    name: str, block: np.ndarray, stored: str, buffers: dict[str, np.ndarray], rows: int, check: bool
) -> np.ndarray:
    """A block of rows of a channel in its stored type, C-contiguous: the block itself when it
    already is, else converted into ``buffers[name]`` (made once, ``rows`` rows); ``check``: a
    uint channel not checked as a whole (one read from a file) is checked here."""
    dtype = np.dtype(EXR_PRECISIONS[stored])
    if block.dtype == dtype and block.flags.c_contiguous:
        return block
    if check and stored == "uint" and not _whole_uint32(block):
        raise ValueError(f"channel {name!r}: uint needs whole numbers 0..2**32-1")
    buf = buffers.get(name)
    if buf is None:
        buf = buffers[name] = np.empty((rows, block.shape[1]), dtype)
    out = buf[: block.shape[0]]
    np.copyto(out, block, casting="unsafe")
    return out


def _json_default(obj: Any) -> Any:
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in the EXR header")


def _parse_header(path: Path, meta: Any) -> dict[str, Any]:
    if meta is None:
        return {}
    try:
        return json.loads(meta)
    except (TypeError, ValueError):
        raise InputError(f"{path}: corrupt hdrcap metadata in the EXR header") from None


def read_exr(
    path: str | os.PathLike[str], channels: Iterable[str] | None = None, *, native: bool = False
) -> ExrContent:
    """Read an EXR written by :func:`write_exr` (or any scanline EXR).

    Parameters
    ----------
    path : str or os.PathLike
        The EXR file.
    channels : iterable of str, optional
        Keep only these channels (those the file has; the others are decoded by OpenEXR but
        neither converted nor kept). Default: every channel.
    native : bool
        Keep each channel in the type the file stores (float32, float16 for half, uint32 for
        uint) instead of converting it to float32: for a caller that writes channels back
        unchanged (:func:`write_exr` stores a channel already in its target type as it is).

    Returns
    -------
    ExrContent
        The channels (float32 unless ``native``) and the header hdrcap wrote (empty for other
        files).

    Raises
    ------
    InputError
        Missing or unreadable file, corrupt hdrcap metadata.
    """
    import OpenEXR

    path = Path(path)
    check_readable(path)
    _set_exr_threads(OpenEXR, None)  # decompression on the thread pool, as write_exr compresses
    try:
        with quiet_stderr(), OpenEXR.File(str(path)) as exr:  # OpenEXR's own messages: ours says it
            # read everything inside the context: the header is released when the file closes;
            # the pixel arrays own their memory: float channels are kept without a copy (half
            # and uint ones converted exactly)
            meta = exr.header().get(_META_KEY)
            wanted = None if channels is None else set(channels)
            data = {
                name: np.ascontiguousarray(ch.pixels, dtype=None if native else np.float32)
                for name, ch in exr.channels().items()
                if wanted is None or name in wanted
            }
    except Exception as err:
        raise InputError(f"{path}: not a readable EXR file ({err})") from None
    return ExrContent(data, _parse_header(path, meta))


@dataclass(frozen=True)
class ExrRows:
    """Rows of one channel of a scanline EXR, as float32, decoded only when asked for (OpenEXR's
    scanline reader decodes just those rows): what ``dask.array.from_array`` and
    :func:`write_exr` (``block_rows``) read.

    Attributes
    ----------
    path : str
        The EXR.
    name : str
        The channel.
    shape : (int, int)
        Rows, columns of the data window (:func:`read_exr_layout`).

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> path = Path(tempfile.mkdtemp()) / "a.exr"
    >>> _ = write_exr(path, {"x": np.arange(12, dtype=np.float32).reshape(4, 3)})
    >>> ExrRows(str(path), "x", (4, 3)).rows(1, 3).tolist()
    [[3.0, 4.0, 5.0], [6.0, 7.0, 8.0]]
    """

    path: str
    name: str
    shape: tuple[int, int]
    dtype: np.dtype = np.dtype(np.float32)
    ndim: int = 2

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` (clipped to the channel), float32 (half and uint converted exactly).

        Parameters
        ----------
        r0, r1 : int
            First row and one past the last.

        Returns
        -------
        numpy.ndarray
            (rows, columns), float32, a new array.

        Raises
        ------
        InputError
            The file is no longer a readable EXR with this channel.
        """
        import Imath
        import OpenEXR

        h, w = self.shape
        r0, r1 = max(0, min(r0, h)), max(0, min(r1, h))
        if r1 <= r0:
            return np.empty((0, w), np.float32)
        try:
            f = OpenEXR.InputFile(self.path)
            try:
                y0 = f.header()["dataWindow"].min.y
                raw = f.channel(self.name, Imath.PixelType(Imath.PixelType.FLOAT), y0 + r0, y0 + r1 - 1)
            finally:
                f.close()
        except Exception as err:
            raise InputError(f"{self.path}: rows {r0}..{r1 - 1} of channel {self.name!r} unreadable ({err})") from None
        return np.frombuffer(raw, np.float32).reshape(r1 - r0, w).copy()

    def __getitem__(self, key: slice | tuple[slice, ...]) -> np.ndarray:
        """``self[rows, cols]`` with slices, rows with step 1 (what ``dask.array.from_array`` asks)."""
        keys = key if isinstance(key, tuple) else (key,)
        r0, r1, step = keys[0].indices(self.shape[0])
        if step != 1:
            raise IndexError("rows of an EXR channel are read with step 1")
        return self.rows(r0, r1)[(slice(None), *keys[1:])]


class ExrLayout(NamedTuple):
    """An EXR's header, channel names and size, read without its pixels.

    Attributes
    ----------
    header : dict
        The JSON metadata hdrcap wrote (empty for other files).
    channels : tuple of str
        The channel names.
    shape : (int, int)
        Rows, columns.
    """

    header: dict[str, Any]
    channels: tuple[str, ...]
    shape: tuple[int, int]


def read_exr_layout(path: str | os.PathLike[str]) -> ExrLayout:
    """An EXR's header, channel names and size, without reading its pixels (OpenEXR's
    header-only reader, which refuses a corrupt file with an error rather than a crash).

    Parameters
    ----------
    path : str or os.PathLike
        The EXR file.

    Returns
    -------
    ExrLayout

    Raises
    ------
    InputError
        Missing or unreadable file, corrupt hdrcap metadata.
    """
    import OpenEXR

    path = Path(path)
    check_readable(path)
    try:
        with quiet_stderr(), OpenEXR.File(str(path), header_only=True) as exr:
            head = exr.header()
            meta = head.get(_META_KEY)
            (x0, y0), (x1, y1) = head["dataWindow"]
            names = tuple(str(c.name) for c in head["channels"])
    except Exception as err:
        raise InputError(f"{path}: not a readable EXR file ({err})") from None
    return ExrLayout(_parse_header(path, meta), names, (int(y1 - y0 + 1), int(x1 - x0 + 1)))


#: numpy types of the stored channels by the precision names of :func:`write_exr`.
_PRECISION_OF_DTYPE = {"float32": "float", "float16": "half", "uint32": "uint"}


def stored_precisions(path: str | os.PathLike[str]) -> dict[str, str]:
    """How each channel of an EXR is stored (reads the pixels: for checks, not for pipelines).

    Parameters
    ----------
    path : str or os.PathLike
        The EXR file.

    Returns
    -------
    dict of str to str
        Channel name -> ``"float"``, ``"half"`` or ``"uint"``.

    Raises
    ------
    InputError
        Missing or unreadable file.
    """
    content = read_exr(path, native=True)
    return {name: _PRECISION_OF_DTYPE[str(arr.dtype)] for name, arr in content.channels.items()}
