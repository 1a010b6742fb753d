"""One frame larger than memory: ``hdrcap merge --chunks ROWS`` merges bands of rows through dask.array.

The mosaic is cut into bands of whole rows (tiles; an even number of rows, whole CFA periods).
Every input is a :class:`RowFile`: rows of a 2-D array at a known place in a file, read with
``pread`` only when a tile needs them (nothing stays mapped, so the pages read count in no
process's resident memory once the tile is done):

* uncompressed DNG frames and dark frames: the image strips in the raw file itself (the file
  :func:`pipeline.io.read_raw` memory-maps); every other format (LibRaw: NEF, CR2, compressed
  DNG, ...; PNG/TIFF) is decoded whole once per file and spilled to a temporary file beside
  the output, with a warning;
* the calibration's maps: the uncompressed members of the calibration archive (memory-mapped
  by :func:`pipeline.calibration.load_calibration`), else spilled like a decoded frame;
* master darks (one file, or the dark library's) likewise.

Everything that is not per photosite is done ONCE, on the whole frame, before the tiles:
the effective exposure times (:meth:`pipeline.merge.accumulator.MergeAccumulator.apply_exposure_times`,
on the same regular subsample of rows and columns the in-memory merge uses, read row by row),
the dark frame serving each exposure, the plan's options. Each tile is then an ordinary
:class:`pipeline.merge.accumulator.MergeAccumulator` merge of its rows with those times; the one choice a
merge makes from whole-frame extrema (float32 or float64 weights) is made from the extrema of
all tiles, and a tile that chose otherwise is merged again. The outputs go to temporary files
(row by row), then into the EXR scanline block by block; nothing holds a whole channel. The
EXR equals the in-memory merge's bit for bit, every channel and the header.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import re
import sys
import tempfile
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io import RawFrame

__all__ = [
    "RowFile",
    "row_source",
    "parse_memory",
    "machine_memory",
    "default_memory_budget",
    "chunk_rows_for",
    "in_memory_bytes",
    "tiling_rows",
    "TiledMerge",
    "merge_tiled",
    "write_exr_rows",
]

#: Resident memory of the process before any pixel is held (interpreter, numpy, numba's
#: compiled kernels, dask, OpenEXR), bytes; measured 150-180 MB, rounded up.
BASELINE_BYTES = 256 * 2**20

#: Bytes per photosite a tile needs besides its inputs (merge outputs, the float64 temporaries
#: of the total sigma and the calibration terms, the stacked channels of the dask block);
#: measured about 80 on 2.5-Mpixel tiles (benchmarks/bench_chunks.py), rounded up.
TILE_BYTES_PER_PHOTOSITE = 100

#: Bytes per photosite of the in-memory merge besides its inputs (which it holds whole: the
#: mapped frames and calibration maps); measured about 25 on 25 Mpixels, rounded up.
MERGE_BYTES_PER_PHOTOSITE = 40

_UNITS = {"": 1, "B": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


# ------------------------------------------------------------------------------ rows of files
@dataclass(frozen=True)
class RowFile:
    """Rows of a 2-D array stored row by row in a file, read (or written) on demand.

    Attributes
    ----------
    path : str
        The file.
    offset : int
        Byte offset of the first photosite of the first row.
    dtype : numpy.dtype
        Pixel type.
    shape : (int, int)
        Rows, columns.
    row_bytes : int
        Bytes from one row's start to the next's (>= columns x item size).
    """

    path: str
    offset: int
    dtype: np.dtype
    shape: tuple[int, int]
    row_bytes: int

    @property
    def ndim(self) -> int:
        return 2

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape)) * self.dtype.itemsize

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` (clipped to the array), a new C-contiguous array.

        Parameters
        ----------
        r0, r1 : int
            First row and one past the last.

        Returns
        -------
        numpy.ndarray
            Shape (rows, columns), ``dtype``.
        """
        h, w = self.shape
        r0, r1 = max(0, min(r0, h)), max(0, min(r1, h))
        n, item = max(r1 - r0, 0), self.dtype.itemsize
        if n == 0 or w == 0:
            return np.empty((n, w), self.dtype)
        count = (n - 1) * self.row_bytes + w * item
        buf = np.fromfile(self.path, np.uint8, count=count, offset=self.offset + r0 * self.row_bytes)
        if buf.size != count:
            raise InputError(f"{self.path}: truncated while reading rows {r0}..{r1 - 1}")
        return np.ndarray((n, w), self.dtype, buffer=buf, strides=(self.row_bytes, item)).copy()

    def take(self, index: np.ndarray) -> np.ndarray:
        """The rows of ``index`` (row numbers), stacked; one read per row."""
        return np.stack([self.rows(int(r), int(r) + 1)[0] for r in index]) if len(index) else self.rows(0, 0)

    def __getitem__(self, key) -> np.ndarray:
        """``self[rows, cols]`` with slices (what ``dask.array.from_array`` asks for)."""
        key = key if isinstance(key, tuple) else (key,)
        rows = key[0] if key else slice(None)
        r0, r1, step = rows.indices(self.shape[0])
        block = self.rows(r0, r1)[::step] if step > 0 else self.rows(r1 + 1, r0 + 1)[::step]
        return block[(slice(None), *key[1:])]

    def write(self, r0: int, block: np.ndarray) -> None:
        """Write ``block`` (rows, columns) at row ``r0`` (a file made by :meth:`create`)."""
        data = np.ascontiguousarray(block, dtype=self.dtype)
        with open(self.path, "r+b") as fh:
            fh.seek(self.offset + r0 * self.row_bytes)
            data.tofile(fh)

    def mapped(self) -> np.ndarray:
        """A fresh read-only memory map of the array (pages are read only when touched)."""
        h, w = self.shape
        item = self.dtype.itemsize
        size = (h - 1) * self.row_bytes + w * item if h else 0
        raw = np.memmap(self.path, np.uint8, mode="r", offset=self.offset, shape=(max(size, 1),))
        return np.ndarray((h, w), self.dtype, buffer=raw, strides=(self.row_bytes, item))

    @classmethod
    def create(cls, path: str | os.PathLike, shape: tuple[int, int], dtype) -> RowFile:
        """A new zero-filled file for an array of ``shape`` (sparse where the file system allows)."""
        dtype = np.dtype(dtype)
        h, w = (int(s) for s in shape)
        with open(path, "wb") as fh:
            fh.truncate(h * w * dtype.itemsize)
        return cls(str(path), 0, dtype, (h, w), w * dtype.itemsize)


def _memmap_of(arr: np.ndarray) -> np.memmap | None:
    base = arr
    while base is not None and not isinstance(base, np.memmap):
        base = getattr(base, "base", None)
    return base if base is not None and getattr(base, "filename", None) else None


def _file_rows(arr: np.ndarray) -> RowFile | None:
    """The :class:`RowFile` under a memory-mapped 2-D array, or None (not mapped, not row-major)."""
    m = _memmap_of(arr)
    if m is None or arr.ndim != 2 or arr.strides[1] != arr.itemsize or arr.strides[0] < arr.shape[1] * arr.itemsize:
        return None
    start = int(m.offset) + arr.__array_interface__["data"][0] - m.__array_interface__["data"][0]
    return RowFile(str(m.filename), start, arr.dtype, tuple(arr.shape), int(arr.strides[0]))


def row_source(arr: np.ndarray, spill_dir: str | os.PathLike, name: str) -> tuple[RowFile, bool]:
    """Rows of ``arr`` from a file: its own file when it is a row-major memory map, else a copy
    written to ``spill_dir`` (the caller then drops ``arr``).

    Parameters
    ----------
    arr : numpy.ndarray
        A 2-D array.
    spill_dir : path
        Folder for the copy.
    name : str
        File name of the copy (unique in ``spill_dir``).

    Returns
    -------
    (RowFile, bool)
        The rows, and whether they were spilled (copied).
    """
    arr = np.asarray(arr) if not isinstance(arr, np.ndarray) else arr
    if arr.ndim != 2:
        raise InputError(f"{name}: expected a 2-D array, got shape {arr.shape}")
    found = _file_rows(arr)
    if found is not None:
        return found, False
    out = RowFile.create(Path(spill_dir) / f"{name}.bin", arr.shape, arr.dtype)
    step = max(1, (64 << 20) // max(arr.shape[1] * arr.itemsize, 1))
    for r0 in range(0, arr.shape[0], step):
        out.write(r0, arr[r0 : r0 + step])
    return out, True


# ------------------------------------------------------------------------------ memory budget
def parse_memory(text: str) -> int:
    """Bytes from a size such as ``2GB``, ``1500M``, ``512MiB`` or ``3e9`` (K, M, G, T are powers
    of 1024, with or without ``B``/``iB``).

    Parameters
    ----------
    text : str
        The size.

    Returns
    -------
    int
        Bytes.

    Raises
    ------
    InputError
        Not a positive size.
    """
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([KMGT]?)(?:I?B)?\s*", str(text).upper())
    value = float(m[1]) * _UNITS[m[2]] if m else math.nan
    if not (math.isfinite(value) and value >= 1):
        raise InputError(f"memory size {text!r}: give a positive number with K, M, G or T, e.g. 2GB")
    return int(value)


def machine_memory() -> int:
    """Physical memory of this machine.

    Returns
    -------
    int
        Bytes (0 if the system does not say).
    """
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 0


def default_memory_budget() -> int:
    """The default ``--memory-budget``: half the machine's physical memory.

    Returns
    -------
    int
        Bytes (4 GiB if the physical memory cannot be read).
    """
    total = machine_memory()
    return total // 2 if total > 0 else 4 << 30


def in_memory_bytes(photosites: int, n_inputs: int, n_maps: int) -> int:
    """Estimated peak resident memory of the in-memory merge, bytes.

    Parameters
    ----------
    photosites : int
        Photosites per frame.
    n_inputs : int
        16-bit frames read (light frames, dark frames, master darks).
    n_maps : int
        float32 calibration maps.

    Returns
    -------
    int
        Bytes.
    """
    return BASELINE_BYTES + photosites * (2 * n_inputs + 4 * n_maps + MERGE_BYTES_PER_PHOTOSITE)


def chunk_rows_for(budget: int, width: int, n_inputs: int, n_maps: int) -> int:
    """Rows per tile so that one tile's working set stays within half of what ``budget`` leaves
    after the baseline (even, at least 2).

    Parameters
    ----------
    budget : int
        Memory budget, bytes.
    width : int
        Photosites per row.
    n_inputs, n_maps : int
        As :func:`in_memory_bytes`.

    Returns
    -------
    int
        Even number of rows, >= 2.
    """
    per_row = max(width, 1) * (2 * n_inputs + 4 * n_maps + TILE_BYTES_PER_PHOTOSITE)
    rows = int(max(budget - BASELINE_BYTES, 0) // 2 // per_row)
    return max(2, rows - rows % 2)


def _raw_dimensions(path: Path) -> tuple[int, int] | None:
    """(rows, columns) of the largest image in a TIFF-based raw file, without decoding; None
    for other formats (:func:`pipeline.io.tiff_dimensions`)."""
    from hdrcap.pipeline.io import tiff_dimensions

    return tiff_dimensions(path)


def tiling_rows(
    frames: Sequence[Path],
    n_darks: int,
    calibration,
    *,
    chunks: int | None,
    budget: int,
) -> int | None:
    """Rows per tile of a merge, or None to merge in memory.

    Parameters
    ----------
    frames : sequence of Path
        The bracket.
    n_darks : int
        Dark frames.
    calibration : Calibration
        Its maps count.
    chunks : int or None
        Rows asked for (``--chunks``): returned as they are (even, >= 2).
    budget : int
        Memory budget, bytes: without ``chunks``, tiles when :func:`in_memory_bytes` of the
        bracket exceeds it. Photosites per frame: the larger of the largest image in the first
        file's TIFF header and its size in bytes / 2 (an uncompressed 16-bit raw).

    Returns
    -------
    int or None
        Rows per tile (:func:`chunk_rows_for`), or None.
    """
    if chunks is not None:
        if chunks < 2 or chunks % 2:
            raise InputError(f"--chunks {chunks}: give an even number of rows (whole CFA periods), >= 2")
        return int(chunks)
    first = Path(frames[0])
    try:
        by_size = first.stat().st_size // 2
    except OSError:
        return None  # the merge reports the missing file
    dims = _raw_dimensions(first) or (1, 1)
    photosites = max(dims[0] * dims[1], by_size)
    width = dims[1] if dims[0] * dims[1] >= by_size else max(int(math.sqrt(photosites)), 1)
    n_maps = sum(isinstance(getattr(calibration, f.name), np.ndarray) for f in dataclasses.fields(calibration))
    if in_memory_bytes(photosites, len(frames) + n_darks, n_maps) <= budget:
        return None
    return chunk_rows_for(budget, width, len(frames) + n_darks, n_maps)


# ------------------------------------------------------------------------------ opening inputs
@dataclass
class _Inputs:
    """The files of a tiled merge: metadata frames (lazily mapped pixels) and their rows."""

    spill_dir: str
    warn: Callable[[str], None]
    sources: list[RowFile] = field(default_factory=list)
    warned: bool = False

    def add(self, arr: np.ndarray, name: str, what: str | None = None) -> int:
        src, spilled = row_source(arr, self.spill_dir, f"in{len(self.sources)}")
        if spilled and what and not self.warned:
            self.warned = True
            self.warn(
                f"{what}: not an uncompressed DNG: --chunks decodes each such file whole, once, into a temporary "
                "file beside the output (memory: one decoded frame at a time)"
            )
        self.sources.append(src)
        return len(self.sources) - 1

    def open(self, path, t=None) -> tuple[RawFrame, int]:
        """Read one file's metadata and keep its rows as a source; the pixels are not held."""
        from hdrcap.pipeline.io import read_frame

        fr = read_frame(path, t)
        k = self.add(fr.data, str(path), str(path))
        return dataclasses.replace(fr, data=self.sources[k].mapped()), k


def _calibration_sources(calib, inputs: _Inputs, shape) -> dict[str, int]:
    """Row sources of every map of the calibration (checked against the frames' size)."""
    out = {}
    for f in dataclasses.fields(calib):
        arr = getattr(calib, f.name)
        if isinstance(arr, np.ndarray):
            if arr.shape != tuple(shape):
                raise InputError(f"calibration {f.name} has shape {arr.shape}, the frames {tuple(shape)}")
            out[f.name] = inputs.add(arr, f"calibration {f.name}")
    return out


# ------------------------------------------------------------------------------ the accumulators
@functools.cache
def _accumulator_classes():
    """(MergeAccumulator, its subsample variant, its tile variant), imported on first use."""
    from hdrcap.pipeline.merge.accumulator import MergeAccumulator, _extrema

    class SampleAccumulator(MergeAccumulator):
        """Merges the regular subsample itself: its subsample is everything it holds."""

        def _subsample(self, max_photosites: int = 250_000):
            return slice(None), slice(None)

    class TileAccumulator(MergeAccumulator):
        """A tile's merge: records the extrema its float32/float64 choice depends on, and takes
        the choice made for the whole frame when one is given (``forced_single``)."""

        forced_single: bool | None = None
        extrema: dict[str, tuple[float, float]] | None = None
        own_single: bool | None = None

        def _single_precision_safe(self, values, darks, master) -> bool:
            ext = {"a": _extrema(self._a), "D": _extrema(self._D), "bias": _extrema(self._bias)}
            if self.master_dark is not None:
                ext["master"] = _extrema((master, True, 0.0))
            for i, (d, kind) in enumerate(zip(darks, self._kinds)):
                if kind == 0 and d.dtype != np.uint16:
                    ext[f"dark{i}"] = _extrema((d, True, 0.0))
            self.extrema = ext
            self.own_single = super()._single_precision_safe(values, darks, master)
            return self.own_single if self.forced_single is None else self.forced_single

    return MergeAccumulator, SampleAccumulator, TileAccumulator


def _combine(extrema: list[dict[str, tuple[float, float]]]) -> dict[str, tuple[float, float]]:
    """Whole-frame extrema from the tiles' (NaN anywhere: NaN)."""
    out: dict[str, tuple[float, float]] = {}
    for ext in extrema:
        for k, (lo, hi) in ext.items():
            if k not in out:
                out[k] = (lo, hi)
            else:
                plo, phi = out[k]
                nan = any(math.isnan(v) for v in (lo, hi, plo, phi))
                out[k] = (math.nan, math.nan) if nan else (min(lo, plo), max(hi, phi))
    return out


# ------------------------------------------------------------------------------ the merge
@dataclass
class TiledMerge:
    """What :func:`merge_tiled` did: the EXR's header attributes, the summary figures of
    :func:`pipeline.merge.files.summary`, the rows per tile, the tiles, how many were merged a
    second time (their float32/float64 choice differed from the whole frame's), the frames and
    dark frames read, and the inputs spilled to temporary files (not uncompressed DNG)."""

    attrs: dict[str, Any]
    summary: dict[str, Any]
    rows: int
    tiles: int
    remerged: int
    n_frames: int
    n_darks: int
    spilled: int


#: Channels of a tile, in the order of the dask block's first axis.
_CHANNELS = ("irradiance", "sigma", "nexp", "sigma_calibration", "quality")


def _strip_maps(calib):
    """The calibration without its maps (scalars and provenance only)."""
    return calib.replace(
        **{f.name: None for f in dataclasses.fields(calib) if isinstance(getattr(calib, f.name), np.ndarray)}
    )


@dataclass
class _Plan:
    """Everything decided once for the whole frame, and the merge of one tile from its rows.

    ``blocks`` below are the rows of every input source (:attr:`_Inputs.sources` order) of one
    tile, or of the subsample."""

    calib: Any
    shape: tuple[int, int]
    inputs: _Inputs
    frames: list[RawFrame]
    frame_src: list[int]
    dark_meta: list[RawFrame]
    dark_src: list[int]
    cal_src: dict[str, int]
    options: dict[str, Any] = field(default_factory=dict)
    master_src: int | None = None
    library: list[tuple[float, float, str, int]] = field(default_factory=list)  # (t, N, name, source)
    strategies: list[Any] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    exposure_info: dict[str, Any] = field(default_factory=dict)
    resolver_args: dict[str, Any] = field(default_factory=dict)
    selfcal: Any = None
    selfcal_times: bool = True
    extra: dict[str, Any] = field(default_factory=dict)
    tiles: dict[int, dict[str, Any]] = field(default_factory=dict)

    def read(self, r0: int, r1: int) -> list[np.ndarray]:
        """Rows ``r0:r1`` of every input."""
        return [src.rows(r0, r1) for src in self.inputs.sources]

    def accumulate(self, cls, blocks, times, options, *, master_dtype=None, dark_for=None):
        """An accumulator of class ``cls`` holding the frames' ``blocks`` with the given
        ``times`` and their dark levels, resolved as the in-memory merge resolves them."""
        from hdrcap.pipeline.merge.darks import DarkResolver
        from hdrcap.pipeline.noise import DarkStrategy

        resolver = DarkResolver(**self.resolver_args)
        for d, k in zip(self.dark_meta, self.dark_src):
            resolver.add_dark(blocks[k], d.exposure_time, str(d.path))
        for t, n, name, k in self.library:
            resolver.add_master(blocks[k], t, n, name)
        master = None if self.master_src is None else blocks[self.master_src]
        calib = self.calib.replace(**{name: blocks[k] for name, k in self.cal_src.items()})
        shape = blocks[self.frame_src[0]].shape
        acc = cls(calib, shape, master_dark=master, stream=False, **options)
        for i, (fr, k, t, strategy) in enumerate(zip(self.frames, self.frame_src, times, self.strategies)):
            src = resolver.resolve(fr.exposure_time, strategy, camera=fr.camera, iso=fr.iso)
            dark = src.data if dark_for is None else dark_for(i, src.data)
            n = src.n_frames if strategy is DarkStrategy.MASTER else None
            acc.add(blocks[k], t, dark, strategy=strategy, n_dark=n)
        return acc

    def merge_block(self, blocks: Sequence[np.ndarray], r0: int, forced: bool | None = None) -> np.ndarray:
        """Merge one tile starting at row ``r0`` (float32/float64 weights as ``forced`` says,
        None: the tile's own choice); returns its channels stacked (C, rows, columns), float32,
        and records its figures in :attr:`tiles`."""
        from hdrcap.pipeline.merge.files import build_hdr_image

        _, _, tile_cls = _accumulator_classes()
        opts = dict(self.options, exposure_times="nominal")  # the times given are the effective ones
        acc = self.accumulate(tile_cls, blocks, self.times, opts)
        acc.forced_single = forced
        result = acc.result()
        result.info.update(self.exposure_info)  # the in-memory merge's (nominal, shutter table, estimate)
        image = build_hdr_image(result, self.frames, self.calib, self.extra)
        if self.selfcal is not None:
            from hdrcap.pipeline.calibration.selfcal import apply_self_calibration

            apply_self_calibration(image, self.selfcal, times_applied=self.selfcal_times)
        self.tiles[r0] = {
            "info": result.info,
            "attrs": image.attrs,
            "extrema": acc.extrema,
            "single": acc.own_single if forced is None else forced,
            "summary": _tile_summary(result, r0, self.shape),
            "channels": set(image.channels),
        }
        # a channel the tile's image has not (sigma_calibration when no calibration error
        # entered) is NaN here and left out of the EXR when no tile has it
        out = np.full((len(_CHANNELS),) + result.irradiance.shape, np.nan, np.float32)
        for k, c in enumerate(_CHANNELS):
            if c in image.channels:
                out[k] = image.channels[c]
        return out


def _tile_summary(result, r0: int, shape) -> dict[str, Any]:
    """What :func:`pipeline.merge.files.summary` needs of one tile: extrema, counts and the
    photosites of the whole frame's regular subsample that lie in it (flat index a multiple of
    the whole frame's step)."""
    irr, sig, nexp = result.irradiance, result.sigma, result.nexp
    step = max(1, shape[0] * shape[1] // 1_000_000)
    pick = np.arange((-r0 * shape[1]) % step, irr.size, step)
    return {
        "size": irr.size,
        "min": float(irr.min()),
        "max": float(irr.max()),
        "unused": int((nexp <= 0).sum()),
        "defects": int(result.info.get("defects_flagged", 0)),
        "finite": bool(np.isfinite(irr).all() and np.isfinite(sig).all()),
        "sample": (irr.ravel()[pick], sig.ravel()[pick], nexp.ravel()[pick] > 0),
    }


def _whole_summary(tiles: list[dict[str, Any]], shape) -> dict[str, Any]:
    """:func:`pipeline.merge.files.summary` of the whole frame from its tiles' figures."""
    from hdrcap.pipeline.merge.files import _median_relative_sigma

    i, s, o = (np.concatenate([t["sample"][j] for t in tiles]) for j in range(3))
    n_defects = sum(t["defects"] for t in tiles)
    return {
        "shape": list(shape),
        "irradiance_min": min(t["min"] for t in tiles),
        "irradiance_max": max(t["max"] for t in tiles),
        "median_relative_sigma": _median_relative_sigma(i, s, o, max_samples=max(i.size, 1)),
        "saturated_everywhere": sum(t["unused"] for t in tiles) - n_defects,
        "defects_flagged": n_defects,
        "finite": all(t["finite"] for t in tiles),
    }


def _whole_info(tiles: list[dict[str, Any]], shape, single: bool) -> dict[str, Any]:
    """The merge's ``info`` of the whole frame: the first tile's, with the counts summed (the
    mean iteration count from the exact integer sum of the tiles' counts)."""
    info = dict(tiles[0]["info"])
    total_iters = sum(round(t["info"]["iterations_used_mean"] * t["summary"]["size"]) for t in tiles)
    info["saturated_everywhere"] = sum(t["info"]["saturated_everywhere"] for t in tiles)
    info["defects_flagged"] = sum(t["info"]["defects_flagged"] for t in tiles)
    info["iterations_used_mean"] = float(np.float64(total_iters) / max(shape[0] * shape[1], 1))
    info["iterations_used_max"] = max(t["info"]["iterations_used_max"] for t in tiles)
    info["weights_precision"] = "float32" if single else "float64"
    return info


def _global_single(plan: _Plan, extrema: dict[str, tuple[float, float]]) -> bool:
    """The float32/float64 choice of the whole frame: the merge's own rule
    (``_single_precision_safe``) evaluated on a 1x2 probe whose maps and dark levels hold the
    whole frame's extrema (the rule depends on nothing else)."""
    from hdrcap.pipeline.merge import accumulator as pm

    if not pm.SINGLE_PRECISION_WEIGHTS:
        return False

    def pair(key):
        return np.array([extrema[key]], np.float32)

    keys = {"prnu": "a", "dark_current_map": "D", "bias_map": "bias"}
    blocks: list[np.ndarray] = [np.zeros((1, 2), src.dtype) for src in plan.inputs.sources]
    probe_plan = dataclasses.replace(plan, calib=_strip_maps(plan.calib), cal_src={})
    for name, k in plan.cal_src.items():
        if name in keys:
            blocks[k] = pair(keys[name])
            probe_plan.cal_src[name] = k
    if plan.master_src is not None:
        blocks[plan.master_src] = pair("master")

    def dark_for(i, data):
        return pair(f"dark{i}") if data is not None and f"dark{i}" in extrema else data

    full_cls, _, _ = _accumulator_classes()
    opts = dict(plan.options, exposure_times="nominal")
    probe = probe_plan.accumulate(full_cls, blocks, plan.times, opts, dark_for=dark_for)
    own = [d for d in probe._darks if d is not None]
    hold = np.zeros((1, 1), own[0].dtype if own else np.float32)
    darks = [hold if d is None else d for d in probe._darks]
    m = np.zeros((1, 1), np.float32) if probe.master_dark is None else probe.master_dark.astype(np.float32)
    return bool(probe._single_precision_safe(list(probe._values), darks, m))


def _effective_times(plan: _Plan) -> tuple[list[float], dict[str, Any]]:
    """The exposure times every tile merges with and their header entries, decided once for the
    whole frame as the in-memory merge decides them: the calibration's shutter table, then the
    bracket's own estimate (:meth:`pipeline.merge.accumulator.MergeAccumulator.apply_exposure_times`) on the
    same subsample of rows and columns (read row by row) with the same dark levels.

    Returns
    -------
    (list of float, dict)
        Times, s, per frame; the merge's header entries of the exposure times.
    """
    full_cls, sample_cls, _ = _accumulator_classes()
    win_r, win_c = full_cls(_strip_maps(plan.calib), plan.shape, stream=False)._subsample()
    index = np.arange(plan.shape[0])[win_r]
    blocks = [src.take(index)[:, win_c] for src in plan.inputs.sources]
    acc = plan.accumulate(sample_cls, blocks, [fr.exposure_time for fr in plan.frames], plan.options)
    acc.apply_exposure_times()
    return list(acc._times), acc._exposure_info()


def _resolve_darks(plan: _Plan, strategy_for, library, warn) -> list[str]:
    """Which dark level serves each frame, decided once before any tile (with the in-memory
    merge's errors and warnings): the strategies, the dark library's masters as row sources;
    returns the per-frame dark sources recorded in the header."""
    from hdrcap.pipeline.merge.darks import DarkResolver
    from hdrcap.pipeline.merge.files import _missing_dark
    from hdrcap.pipeline.noise import DarkStrategy

    resolver = DarkResolver(**plan.resolver_args, library=library)
    for d, k in zip(plan.dark_meta, plan.dark_src):
        resolver.add_dark(np.zeros((1, 1), plan.inputs.sources[k].dtype), d.exposure_time, str(d.path))
    used, warned = [], set()
    for fr in plan.frames:
        strategy = strategy_for(fr)
        strategy, n_planned = (strategy, None) if isinstance(strategy, str) else strategy
        strategy = DarkStrategy(strategy)
        src = resolver.resolve(fr.exposure_time, strategy, camera=fr.camera, iso=fr.iso)
        if src is None:
            raise _missing_dark(fr, strategy, resolver)
        if src.origin == "library" and all(src.source != name for _t, _n, name, _k in plan.library):
            if np.shape(src.data) != fr.shape:
                raise InputError(f"{src.source}: dark frame size differs from the bracket's")
            k = plan.inputs.add(np.asarray(src.data, np.float32), f"library{len(plan.library)}")
            plan.library.append((fr.exposure_time, float(src.n_frames), src.source, k))
        short = src.origin == "frames" and strategy is DarkStrategy.MASTER and n_planned and src.n_frames < n_planned
        if short and src.source not in warned:
            warned.add(src.source)
            warn(
                f"the plan expects a master dark of {n_planned:g} frames at {fr.exposure_time:g} s; --darks gives "
                f"one of {src.n_frames:g} (set --master-dark-frames if a file averages more)"
            )
        plan.strategies.append(strategy)
        used.append(f"{strategy}: {src.source}" if strategy is not DarkStrategy.MODEL else "model")
    return used


def _no_pixels(frames: list[RawFrame]) -> list[RawFrame]:
    """The frames with their pixels replaced by a zero-stride placeholder of the same shape (the
    checks are done; the pixels are read per tile from the row sources; no mapping stays)."""
    return [dataclasses.replace(fr, data=np.broadcast_to(np.zeros((), fr.data.dtype), fr.shape)) for fr in frames]


def _open_all(inputs: _Inputs, calib, frame_paths, times, dark_paths) -> _Plan:
    """Open the bracket and its dark frames (metadata, row sources), checked as the in-memory
    merge checks them; the calibration's maps as row sources."""
    from hdrcap.pipeline.io import check_frames

    if times:
        if len(times) != len(frame_paths):
            raise InputError(f"--times gives {len(times)} exposure times for {len(frame_paths)} frames")
    else:
        times = [None] * len(frame_paths)
    dk = [inputs.open(p) for p in dark_paths]
    dark_meta = _no_pixels(check_frames([d for d, _k in dk], "dark frame")) if dk else []
    opened = [inputs.open(p, t) for p, t in zip(frame_paths, times)]
    frames = _no_pixels(check_frames([fr for fr, _k in opened]))
    shape = frames[0].shape
    if dark_meta and dark_meta[0].shape != shape:
        raise InputError(f"{dark_meta[0].path}: dark frame size differs from the bracket's")
    cal_src = _calibration_sources(calib, inputs, shape)
    return _Plan(calib, shape, inputs, frames, [k for _f, k in opened], dark_meta, [k for _d, k in dk], cal_src)


def merge_tiled(
    frame_paths: Sequence[Path],
    calib,
    options: dict,
    output: Path,
    *,
    rows: int,
    dark_paths: Sequence[Path] = (),
    times: Sequence[float] | None = None,
    plan=None,
    plan_file: str | None = None,
    dark_strategy: str | None = None,
    master_dark: Path | None = None,
    master_dark_frames: float | None = None,
    library: str | None = None,
    given: Callable[[str], bool] = lambda _name: False,
    selfcal=None,
    selfcal_times: bool = True,
    force: bool = False,
    compression: str = "zip",
    sigma_precision: str = "auto",
    progress: bool = False,
    warn: Callable[[str], None] | None = None,
) -> TiledMerge:
    """Merge raw files tile by tile (bands of ``rows`` rows) into the EXR ``output``.

    The arguments mean what they mean for :func:`pipeline.merge.files.merge_files` (optimal
    weighting) and ``hdrcap merge``; ``selfcal`` is the bracket's self-calibration when one was
    made (applied per tile, as the in-memory merge applies it to the whole image). The EXR
    equals the in-memory merge's: every channel bit for bit, and the header.

    Parameters
    ----------
    frame_paths : sequence of path
        The bracket.
    calib : Calibration
        The camera model; its maps are read per tile.
    options : dict
        Merge options (:func:`pipeline.merge.files.merge_options`).
    output : pathlib.Path
        The EXR.
    rows : int
        Rows per tile, even (whole CFA periods).

    Returns
    -------
    TiledMerge
    """
    from hdrcap.pipeline.merge.darks import default_strategy
    from hdrcap.pipeline.merge.files import _check_plan_covered, _plan_strategies
    from hdrcap.pipeline.noise import DarkStrategy
    from hdrcap.pipeline.planfile import apply_plan_options, planner_attribute

    warn = warn or (lambda m: print(f"hdrcap: warning: {m}", file=sys.stderr))
    if rows < 2 or rows % 2:
        raise InputError(f"--chunks {rows}: give an even number of rows (whole CFA periods), >= 2")
    options = dict(options)
    spill_root = output.parent if output.parent.is_dir() else Path(".")
    with tempfile.TemporaryDirectory(prefix=".hdrcap-tiles-", dir=spill_root) as spill:
        inputs = _Inputs(spill, warn)
        p = _open_all(inputs, calib, list(frame_paths), times, list(dark_paths))
        master_name = None
        if master_dark:
            plain = Path(master_dark).suffix.lower() in (".png", ".tif", ".tiff")  # no exposure time: used as is
            if plain:
                options["master_dark_time"] = None
            md, p.master_src = inputs.open(master_dark, 1.0 if plain else None)
            if md.shape != p.shape:
                raise InputError(f"{md.path}: master dark size differs from the bracket's")
            master_name = str(md.path)
        extra: dict[str, Any] = {"weighting": "optimal"}
        dark_strategy = None if dark_strategy is None else DarkStrategy(dark_strategy)
        taken = overridden = ignored = None
        if plan is not None:
            options, taken, overridden, ignored = apply_plan_options(plan, options, given)
            for name in ignored:
                warn(f"{plan.path}: merge option {name!r} is not one hdrcap merge knows; ignored")
            if dark_strategy:
                overridden["darks"] = {"plan": plan.data["darks"], "used": dark_strategy.value}
            strategy_for = _plan_strategies(plan, dark_strategy)
        else:
            only = options.get("dark_strategy") or default_strategy(bool(dark_paths), master_dark is not None)

            def strategy_for(_fr):
                return only

        if master_dark:
            options["dark_strategy"] = DarkStrategy.MASTER
            options.setdefault("master_dark_time", md.exposure_time)
        p.options = options
        p.resolver_args = {
            "frames_per_dark": master_dark_frames,
            "master_dark": master_name,
            "temperature": (calib.provenance or {}).get("temperature"),
        }
        extra["dark_sources"] = _resolve_darks(p, strategy_for, library, warn)
        if plan is not None:
            _check_plan_covered(plan, p.frames, warn)
        if master_dark:
            extra["master_dark_file"] = str(master_dark)
        if plan is not None:
            extra["planner"] = planner_attribute(
                plan.data, plan_file, plan.sha256, taken, overridden, options_ignored=ignored
            )
        p.extra, p.selfcal, p.selfcal_times = extra, selfcal, selfcal_times
        p.times, p.exposure_info = _effective_times(p)
        return _run_tiles(p, rows, output, spill, force, compression, sigma_precision, progress)


def _run_tiles(p: _Plan, rows: int, output: Path, spill: str, force, compression, sigma_precision, progress):
    """Merge every tile through dask.array (inputs ``from_array`` of the row sources, one
    ``map_blocks`` task per tile, ``store`` into temporary channel files), merge again the tiles
    whose float32/float64 choice differs from the whole frame's, and write the EXR."""
    import dask
    import dask.array as da

    from hdrcap.pipeline.merge.files import exr_precision

    h, w = p.shape
    token = uuid.uuid4().hex
    arrays = [
        da.from_array(
            src, chunks=(rows, w), name=f"hdrcap-rows-{k}-{token}", lock=False, meta=np.empty((0, 0), src.dtype)
        )
        for k, src in enumerate(p.inputs.sources)
    ]
    outs = {name: RowFile.create(Path(spill) / f"out-{name}.bin", (h, w), np.float32) for name in _CHANNELS}

    class Writer:
        """The target of ``dask.array.store``: a tile's channels into their files."""

        def __setitem__(self, key, value):
            r0 = key[1].start or 0
            for name, arr in zip(_CHANNELS, value):
                outs[name].write(r0, arr)

    def block(*blocks, block_info=None):
        return p.merge_block(blocks, block_info[None]["array-location"][1][0])

    merged = da.map_blocks(
        block,
        *arrays,
        dtype=np.float32,
        new_axis=0,
        chunks=((len(_CHANNELS),), arrays[0].chunks[0], (w,)),
        meta=np.empty((0, 0, 0), np.float32),
        name=f"hdrcap-tiles-{token}",  # named: dask would otherwise hash the function, pickling the plan's inputs
    )
    # One tile at a time: the merge kernel is itself parallel over the rows of a tile.
    with dask.config.set(scheduler="synchronous"):
        if progress:
            from dask.diagnostics import ProgressBar

            with ProgressBar(out=sys.stderr):
                da.store(merged, Writer(), lock=False)
        else:
            da.store(merged, Writer(), lock=False)
    if len(p.tiles) != len(arrays[0].chunks[0]):
        raise RuntimeError(f"{len(p.tiles)} of {len(arrays[0].chunks[0])} tiles were merged")
    single = _global_single(p, _combine([t["extrema"] for t in p.tiles.values()]))
    again = [r0 for r0, t in p.tiles.items() if t["single"] != single]
    for r0 in again:
        Writer()[(slice(None), slice(r0, r0 + rows))] = p.merge_block(p.read(r0, r0 + rows), r0, forced=single)
    tiles = [p.tiles[r0] for r0 in sorted(p.tiles)]
    attrs = dict(tiles[0]["attrs"], merge=_whole_info(tiles, p.shape, single))
    outs = {name: out for name, out in outs.items() if any(name in t["channels"] for t in tiles)}
    write_exr_rows(output, outs, attrs, exr_precision(outs, sigma_precision), compression, force, rows)
    spilled = sum(1 for s in p.inputs.sources if s.path.startswith(spill))
    summ = _whole_summary([t["summary"] for t in tiles], p.shape)
    return TiledMerge(attrs, summ, rows, len(tiles), len(again), len(p.frames), len(p.dark_meta), spilled)


def _decide_precision(name: str, src: RowFile, want: str, rows: int) -> str:
    """``auto``/``half`` of a channel decided as :func:`pipeline.io.write_exr` decides it, from
    the whole channel's extrema (read block by block): ``half``, ``float``, or the refusal."""
    from hdrcap.pipeline.io import _exr_channel

    if want not in ("auto", "half"):
        return want
    lo, hi = math.inf, 0.0
    for r0 in range(0, src.shape[0], rows):
        block = src.rows(r0, r0 + rows)
        mag = np.abs(block[np.isfinite(block) & (block != 0)])
        if mag.size:
            lo, hi = min(lo, float(mag.min())), max(hi, float(mag.max()))
    probe = np.array([lo, hi] if hi > 0 else [], np.float32)
    return "half" if _exr_channel(name, probe, want).dtype == np.float16 else "float"


def write_exr_rows(path: Path, outs: dict[str, Any], attrs, precision, compression, force, rows) -> Path:
    """:func:`pipeline.io.write_exr` of channels held in files, block of rows by block of rows:
    the same precisions, header and pixels (OpenEXR's scanline writer).

    Parameters
    ----------
    path : pathlib.Path
        The EXR.
    outs : dict of str to RowFile (or any object with ``shape`` and ``rows(r0, r1)``)
        The channels.
    attrs : dict
        Header attributes (JSON-ready), as :attr:`pipeline.io.HdrImage.attrs`.
    precision : dict of str to str
        Channel precisions as for :func:`pipeline.io.write_exr` (missing: float).
    compression : str
        One of :data:`pipeline.io.EXR_COMPRESSIONS`.
    force : bool
        Replace an existing file.
    rows : int
        Rows per block read and written.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    import json

    import Imath
    import OpenEXR

    from hdrcap.pipeline.io import _EXR_CODES, _META_KEY, _exr_channel, _json_default, _set_exr_threads, atomic_output

    if compression not in _EXR_CODES or not hasattr(Imath.Compression, _EXR_CODES[compression]):
        raise InputError(f"EXR compression {compression!r} is not available to the tiled writer")
    h, w = next(iter(outs.values())).shape
    decided = {name: _decide_precision(name, src, precision.get(name, "float"), rows) for name, src in outs.items()}
    kinds = {"float": Imath.PixelType.FLOAT, "half": Imath.PixelType.HALF, "uint": Imath.PixelType.UINT}
    header = OpenEXR.Header(w, h)
    header["channels"] = {name: Imath.Channel(Imath.PixelType(kinds[decided[name]])) for name in outs}
    header["compression"] = Imath.Compression(getattr(Imath.Compression, _EXR_CODES[compression]))
    header[_META_KEY] = json.dumps(attrs, sort_keys=True, default=_json_default).encode()
    for key, val in attrs.items():
        if isinstance(val, str):
            header[f"{_META_KEY}:{key}"] = val.encode()
    _set_exr_threads(OpenEXR, None)
    with atomic_output(path, force=force, suffix=".exr") as tmp:
        exr = OpenEXR.OutputFile(str(tmp), header)
        try:
            for r0 in range(0, h, rows):
                data = {name: _exr_channel(name, src.rows(r0, r0 + rows), decided[name]) for name, src in outs.items()}
                exr.writePixels({name: b.tobytes() for name, b in data.items()}, min(rows, h - r0))
        finally:
            exr.close()
    return path
