"""One frame larger than memory: ``hdrcap merge --chunks ROWS`` merges bands of rows through dask.array.

The mosaic is cut into bands of whole rows (tiles; an even number of rows, whole CFA periods).
Every input is a :class:`RowFile`: rows of a 2-D array at a known place in a file, read with
``pread`` only when a tile needs them (nothing stays mapped, so the pages read count in no
process's resident memory once the tile is done):

* uncompressed DNG frames and dark frames: the image strips in the raw file itself (the file
  :func:`pipeline.io.raw.read_raw` memory-maps); every other format (LibRaw: NEF, CR2, compressed
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

import contextlib
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
from numpy.typing import DTypeLike

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.raw import RawFrame
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.result import HdrResult

__all__ = [
    "RowFile",
    "row_source",
    "parse_memory",
    "machine_memory",
    "default_memory_budget",
    "chunk_rows_for",
    "in_memory_bytes",
    "tiling_rows",
    "merge_tiled",
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

    def __getitem__(self, key: slice | tuple[slice, ...]) -> np.ndarray:
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
    def create(cls, path: str | os.PathLike, shape: tuple[int, int], dtype: DTypeLike) -> RowFile:
        """A new zero-filled file for an array of ``shape`` (sparse where the file system allows)."""
        dtype = np.dtype(dtype)
        h, w = (int(s) for s in shape)
        with open(path, "wb") as fh:
            fh.truncate(h * w * dtype.itemsize)
        return cls(str(path), 0, dtype, (h, w), w * dtype.itemsize)


def _memmap_of(arr: np.ndarray) -> np.memmap | None:
    """The file-backed memory map ``arr`` is a view of, or None."""
    base: object = arr
    while base is not None and not isinstance(base, np.memmap):
        base = getattr(base, "base", None)
    return base if isinstance(base, np.memmap) and getattr(base, "filename", None) else None


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
    for other formats (:func:`pipeline.io.raw.tiff_dimensions`)."""
    from hdrcap.pipeline.io.raw import tiff_dimensions

    return tiff_dimensions(path)


def tiling_rows(
    frames: Sequence[Path],
    n_darks: int,
    calibration: Calibration,
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
    fmt: Any = None  # the request's FrameFormat (what the files do not say)

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

    def open(self, path, t=None, *, formatted: bool = True) -> tuple[RawFrame, int]:
        """Read one file's metadata (with the request's format unless not ``formatted``: a
        master dark is data) and keep its rows as a source; the pixels are not held."""
        from hdrcap.pipeline.io.raw import read_frame

        fr = read_frame(path, t, fmt=self.fmt if formatted else None)
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
    from hdrcap.pipeline.merge.accumulator import MergeAccumulator
    from hdrcap.pipeline.merge.precision import extrema

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
            maps = self.maps
            ext = {"a": extrema(maps.prnu), "D": extrema(maps.dark_current), "bias": extrema(maps.bias)}
            if self.master_dark is not None:
                ext["master"] = extrema((master, True, 0.0))
            for i, (d, kind) in enumerate(zip(darks, self.frames.kinds)):
                if kind == 0 and d.dtype != np.uint16:
                    ext[f"dark{i}"] = extrema((d, True, 0.0))
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
            assert src is not None  # every frame's dark level was resolved before (_resolve_darks)
            dark = src.data if dark_for is None else dark_for(i, src.data)
            n_dark = src.n_frames if strategy is DarkStrategy.MASTER else None
            acc.add(blocks[k], t, dark, strategy=strategy, n_dark=n_dark)
        return acc

    def merge_block(self, blocks: Sequence[np.ndarray], r0: int, forced: bool | None = None) -> np.ndarray:
        """Merge one tile starting at row ``r0`` (float32/float64 weights as ``forced`` says,
        None: the tile's own choice); returns its channels stacked (C, rows, columns), float32,
        and records its figures in :attr:`tiles`."""
        _, _, tile_cls = _accumulator_classes()
        opts = dict(self.options, exposure_times="nominal")  # the times given are the effective ones
        acc = self.accumulate(tile_cls, blocks, self.times, opts)
        acc.forced_single = forced
        result = acc.result()
        result.info.update(self.exposure_info)  # the in-memory merge's (nominal, shutter table, estimate)
        if self.selfcal is not None:
            from hdrcap.pipeline.calibration.selfcal import apply_self_calibration

            result = apply_self_calibration(result, self.selfcal, times_applied=self.selfcal_times)
        channels = result.channels()
        self.tiles[r0] = {
            "info": result.info,
            "extrema": acc.extrema,
            "single": acc.own_single if forced is None else forced,
            "size": result.irradiance.size,
            "channels": set(channels),
        }
        # a channel the tile has not (sigma_calibration when no calibration error entered) is
        # NaN here and left out of the result when no tile has it
        out = np.full((len(_CHANNELS),) + result.irradiance.shape, np.nan, np.float32)
        for k, c in enumerate(_CHANNELS):
            if c in channels:
                out[k] = channels[c]
        return out


def _whole_info(tiles: list[dict[str, Any]], shape, single: bool) -> dict[str, Any]:
    """The merge's ``info`` of the whole frame: the first tile's, with the counts summed (the
    mean iteration count from the exact integer sum of the tiles' counts)."""
    info = dict(tiles[0]["info"])
    total_iters = sum(round(t["info"]["iterations_used_mean"] * t["size"]) for t in tiles)
    info["saturated_everywhere"] = sum(t["info"]["saturated_everywhere"] for t in tiles)
    info["defects_flagged"] = sum(t["info"]["defects_flagged"] for t in tiles)
    for key in ("clip_rejected", "clip_rejected_samples", "censored_fallback"):
        if info.get(key) is not None:
            info[key] = sum(t["info"][key] for t in tiles)
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
    return bool(probe._single_precision_safe(*probe._kernel_frames()))


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
    return list(acc.frames.times), acc._exposure_info()


def _resolve_darks(plan: _Plan, strategy_for, library, warn) -> list[str]:
    """Which dark level serves each frame, decided once before any tile (with the in-memory
    merge's errors and warnings): the strategies, the dark library's masters as row sources;
    returns the per-frame dark sources recorded in the header."""
    from hdrcap.pipeline.merge.darks import DarkResolver
    from hdrcap.pipeline.merge.files import missing_dark, warn_short_master

    resolver = DarkResolver(**plan.resolver_args, library=library)
    for d, k in zip(plan.dark_meta, plan.dark_src):
        resolver.add_dark(np.zeros((1, 1), plan.inputs.sources[k].dtype), d.exposure_time, str(d.path))
    used: list[str] = []
    warned: set[str] = set()
    for fr in plan.frames:
        strategy, n_planned = strategy_for(fr)
        src = resolver.resolve(fr.exposure_time, strategy, camera=fr.camera, iso=fr.iso)
        if src is None:
            raise missing_dark(fr, strategy, resolver)
        if src.origin == "library" and all(src.source != name for _t, _n, name, _k in plan.library):
            assert src.data is not None and src.n_frames is not None  # a library master: its data and N
            if np.shape(src.data) != fr.shape:
                raise InputError(f"{src.source}: dark frame size differs from the bracket's")
            k = plan.inputs.add(np.asarray(src.data, np.float32), f"library{len(plan.library)}")
            plan.library.append((fr.exposure_time, float(src.n_frames), src.source, k))
        warn_short_master(src, strategy, n_planned, fr.exposure_time, warned, warn)
        plan.strategies.append(strategy)
        used.append(f"{strategy}: {src.source}" if strategy.value != "model" else "model")
    return used


def _no_pixels(frames: list[RawFrame]) -> list[RawFrame]:
    """The frames with their pixels replaced by a zero-stride placeholder of the same shape (the
    checks are done; the pixels are read per tile from the row sources; no mapping stays)."""
    return [dataclasses.replace(fr, data=np.broadcast_to(np.zeros((), fr.data.dtype), fr.shape)) for fr in frames]


def _open_all(inputs: _Inputs, calib, frame_paths, times, dark_paths, on_frame=None) -> _Plan:
    """Open the bracket and its dark frames (metadata, row sources), checked as the in-memory
    merge checks them (``on_frame`` sees each frame); the calibration's maps as row sources."""
    from hdrcap.pipeline.io.raw import check_frames

    if times:
        if len(times) != len(frame_paths):
            raise InputError(f"--times gives {len(times)} exposure times for {len(frame_paths)} frames")
    else:
        times = [None] * len(frame_paths)
    dk = [inputs.open(p) for p in dark_paths]
    dark_meta = _no_pixels(check_frames([d for d, _k in dk], "dark frame")) if dk else []
    opened = [inputs.open(p, t) for p, t in zip(frame_paths, times)]
    for fr, _k in opened:
        if on_frame is not None:
            on_frame(fr)
    frames = _no_pixels(check_frames([fr for fr, _k in opened]))
    shape = frames[0].shape
    if dark_meta and dark_meta[0].shape != shape:
        raise InputError(f"{dark_meta[0].path}: dark frame size differs from the bracket's")
    cal_src = _calibration_sources(calib, inputs, shape)
    return _Plan(calib, shape, inputs, frames, [k for _f, k in opened], dark_meta, [k for _d, k in dk], cal_src)


def merge_tiled(
    req: Any,
    prep: Any,
    calib: Any,
    times: Sequence[float | None] | None,
    rows: int,
    selfcal: Any = None,
    selfcal_times: bool = True,
    *,
    progress: bool = False,
    warn: Callable[[str], None] | None = None,
    on_frame: Callable[[RawFrame], None] | None = None,
) -> HdrResult:
    """Merge raw files tile by tile (bands of ``rows`` rows); the engine of
    :func:`pipeline.merge.files.merge_files` for frames larger than the memory budget.

    The result equals the in-memory merge's: every channel bit for bit, and the header (with
    the tiling recorded under ``merge.tiling``).

    Parameters
    ----------
    req : pipeline.merge.files.MergeRequest
        The request (frames and dark frames are files).
    prep : pipeline.merge.files.Prepared
        Its options, dark strategies and header entries.
    calib : Calibration
        The camera model; its maps are read per tile.
    times : sequence of float, optional
        Exposure times of the frames, s (None: the files').
    rows : int
        Rows per tile, even (whole CFA periods).
    selfcal : SelfCalibration, optional
        The bracket's self-calibration, applied per tile as the in-memory merge applies it.
    selfcal_times : bool
        Whether the merge used the effective exposure times.
    progress : bool
        A progress bar on stderr.
    warn : callable, optional
        Called with one-line warnings.
    on_frame : callable, optional
        Called with each frame's metadata once it is opened (the request's checks).

    Returns
    -------
    HdrResult
        Channels memory-mapped from files that are already deleted (the mappings keep them
        until the arrays are gone; POSIX), and the complete header.
    """
    from hdrcap.pipeline.merge.files import _finish, check_plan_covered

    warn = warn or (lambda m: print(f"hdrcap: warning: {m}", file=sys.stderr))
    if rows < 2 or rows % 2:
        raise InputError(f"--chunks {rows}: give an even number of rows (whole CFA periods), >= 2")
    spill_root = Path(req.scratch_dir) if req.scratch_dir else Path(tempfile.gettempdir())
    with tempfile.TemporaryDirectory(prefix=".hdrcap-tiles-", dir=spill_root) as spill:
        inputs = _Inputs(spill, warn, fmt=req.frame_format)
        p = _open_all(inputs, calib, [Path(f) for f in req.frames], times, [Path(d) for d in req.darks], on_frame)
        if prep.master_dark is not None:
            md, p.master_src = inputs.open(Path(prep.master_dark), 1.0 if prep.master_plain else None, formatted=False)
            if md.shape != p.shape:
                raise InputError(f"{md.path}: master dark size differs from the bracket's")
            prep.master_dark_time(md)
        p.options = prep.options
        p.resolver_args = {k: v for k, v in prep.resolver_args.items() if k != "library"}
        used = _resolve_darks(p, prep.strategy_for, prep.resolver_args.get("library"), warn)
        if prep.plan is not None:
            check_plan_covered(prep.plan, p.frames, warn)
        p.selfcal, p.selfcal_times = selfcal, selfcal_times
        p.times, p.exposure_info = _effective_times(p)
        channels, info = _run_tiles(p, rows, spill, progress)
        spilled = sum(1 for s in p.inputs.sources if s.path.startswith(spill))
        info["tiling"] = {"rows": rows, "tiles": len(p.tiles), "remerged": info.pop("_remerged"), "spilled": spilled}
        frames = p.frames
    whole = HdrResult(
        channels["irradiance"],
        channels["sigma"],
        channels["nexp"],
        quality=channels.get("quality"),
        sigma_calibration=channels.get("sigma_calibration"),
        header={"merge": info},
    )
    result = _finish(whole, frames, calib, dict(prep.entries, dark_sources=used), req.header, None, True, warn)
    if selfcal is not None:  # the tiles' arrays hold it already; the header says it
        from hdrcap.pipeline.calibration.selfcal import self_calibration_header

        result = result.replace(header=self_calibration_header(result.header, selfcal, times_applied=selfcal_times))
    return result


def _run_tiles(p: _Plan, rows: int, spill: str, progress: bool) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Merge every tile through dask.array (inputs ``from_array`` of the row sources, one
    ``map_blocks`` task per tile, ``store`` into temporary channel files), merge again the tiles
    whose float32/float64 choice differs from the whole frame's; returns the channels (read-only
    maps of their files) and the merge's record of the whole frame."""
    import dask
    import dask.array as da

    h, w = p.shape
    token = uuid.uuid4().hex
    arrays = [
        da.from_array(
            src, chunks=(rows, w), name=f"hdrcap-rows-{k}-{token}", lock=False, meta=np.empty((0, 0), src.dtype)
        )
        for k, src in enumerate(p.inputs.sources)
    ]
    dtypes = {"quality": np.uint8}
    outs = {
        name: RowFile.create(Path(spill) / f"out-{name}.bin", (h, w), dtypes.get(name, np.float32))
        for name in _CHANNELS
    }

    class Writer:
        """The target of ``dask.array.store``: a tile's channels into their files."""

        def __setitem__(self, key, value):
            r0 = key[1].start or 0
            for name, arr in zip(_CHANNELS, value):
                outs[name].write(r0, np.nan_to_num(arr) if outs[name].dtype.kind == "u" else arr)

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
    bar: contextlib.AbstractContextManager[Any] = contextlib.nullcontext()
    if progress:
        from dask.diagnostics import ProgressBar

        bar = ProgressBar(out=sys.stderr)
    # One tile at a time: the merge kernel is itself parallel over the rows of a tile.
    with dask.config.set(scheduler="synchronous"), bar:
        # store() writes into any object with numpy-style __setitem__ (its documented contract);
        # its annotation names only array-likes
        da.store(merged, Writer(), lock=False)  # type: ignore[arg-type]
    if len(p.tiles) != len(arrays[0].chunks[0]):
        raise RuntimeError(f"{len(p.tiles)} of {len(arrays[0].chunks[0])} tiles were merged")
    single = _global_single(p, _combine([t["extrema"] for t in p.tiles.values()]))
    again = [r0 for r0, t in p.tiles.items() if t["single"] != single]
    for r0 in again:
        Writer()[(slice(None), slice(r0, r0 + rows))] = p.merge_block(p.read(r0, r0 + rows), r0, forced=single)
    tiles = [p.tiles[r0] for r0 in sorted(p.tiles)]
    info = _whole_info(tiles, p.shape, single)
    info["_remerged"] = len(again)
    present = {name: out.mapped() for name, out in outs.items() if any(name in t["channels"] for t in tiles)}
    return present, info
