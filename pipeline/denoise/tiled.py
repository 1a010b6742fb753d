"""The bilateral filter (Sec. 9) of a merged EXR tile by tile, into memory-mapped channels.

The EXR is read a band of rows at a time (:class:`hdrcap.pipeline.io.exr.ExrRows`: only those
rows are decoded), each band extended by the filter's reach
(:func:`hdrcap.pipeline.denoise.filter.support_depth` rows above and below,
``dask.array.map_overlap`` with no padding at the image's edges, where the filter itself stops)
and filtered by :func:`hdrcap.pipeline.denoise.filter.denoise`; the overlap is then cut off. A
photosite's result depends on no photosite farther away than that reach, and the filter computes
each photosite in the same order whatever its neighbourhood holds beyond it, so the tiles'
results are the whole image's, bit for bit, and tile borders are invisible. The filtered channels
and the channels carried over go to temporary files, returned as read-only memory maps.
"""

from __future__ import annotations

import os
import sys
import tempfile
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.denoise.filter import DenoiseSettings, denoise, support_depth
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import ExrRows
from hdrcap.pipeline.merge.tiled import RowFile

__all__ = ["TiledChannels", "tile_rows", "denoise_tiled"]

#: The channels the filter reads besides irradiance and sigma, and those carried over unchanged,
#: with the type :class:`hdrcap.pipeline.result.HdrResult` holds them in.
_CARRIED = {"nexp": np.float32, "quality": np.uint8, "sigma_calibration": np.float32}


@dataclass(frozen=True)
class TiledChannels:
    """What :func:`denoise_tiled` made.

    Attributes
    ----------
    channels : dict of str to numpy.ndarray
        ``irradiance`` and ``sigma`` filtered (float32), ``nexp`` (float32; 1 everywhere when the
        file has none), and ``quality`` (uint8) and ``sigma_calibration`` (float32) when the file
        has them, unchanged: read-only maps of files already deleted (the mappings keep them
        until the arrays are gone; POSIX).
    rows : int
        Rows per tile, before the overlap.
    tiles : int
        Tiles filtered.
    """

    channels: dict[str, np.ndarray]
    rows: int
    tiles: int


def tile_rows(rows: int, settings: DenoiseSettings) -> int:
    """Rows per tile: ``rows``, raised to the filter's reach (a band at least as tall as the
    overlap; dask would merge shorter bands).

    Parameters
    ----------
    rows : int
        Rows asked for, even (whole CFA periods), >= 2.
    settings : DenoiseSettings
        The filter's settings (its reach, :func:`hdrcap.pipeline.denoise.filter.support_depth`).

    Returns
    -------
    int
        Rows, even.

    Raises
    ------
    InputError
        ``rows`` odd or below 2.

    Examples
    --------
    >>> tile_rows(2, DenoiseSettings(radius=5)), tile_rows(64, DenoiseSettings())
    (10, 64)
    """
    if rows < 2 or rows % 2:
        raise InputError(f"--chunks {rows}: give an even number of rows (whole CFA periods), >= 2")
    depth = support_depth(settings)
    return max(rows, depth + depth % 2)


def denoise_tiled(
    path: str | os.PathLike[str],
    names: list[str] | tuple[str, ...],
    shape: tuple[int, int],
    settings: DenoiseSettings,
    *,
    rows: int,
    scratch_dir: str | os.PathLike[str] | None = None,
    progress: bool = False,
) -> TiledChannels:
    """Filter the ``irradiance`` and ``sigma`` of a merged EXR tile by tile (the whole-image
    filter's result, bit for bit), carrying ``nexp``, ``quality`` and ``sigma_calibration`` over.

    Parameters
    ----------
    path : str or path-like
        The merged EXR.
    names : sequence of str
        Its channels (:func:`hdrcap.pipeline.io.exr.read_exr_layout`); ``irradiance`` and
        ``sigma`` among them.
    shape : (int, int)
        Its size (rows, columns).
    settings : DenoiseSettings
        The filter's settings.
    rows : int
        Rows per tile (even), before the overlap (:func:`tile_rows`).
    scratch_dir : str or path-like, optional
        Folder of the temporary channel files (default: the system's temporary folder).
    progress : bool
        A progress bar on stderr.

    Returns
    -------
    TiledChannels

    Raises
    ------
    InputError
        Odd ``rows``; a tile the filter refuses (non-finite irradiance, sigma not finite and > 0
        where nexp > 0), named by its first row.
    """
    import dask
    import dask.array as da

    rows = tile_rows(rows, settings)
    depth = support_depth(settings)
    h, w = shape
    token = uuid.uuid4().hex
    src = {n: ExrRows(str(path), n, shape) for n in names if n in ("irradiance", "sigma", *_CARRIED)}
    used = [n for n in ("irradiance", "sigma", "nexp", "quality") if n in src]
    arrays = [
        da.from_array(src[n], chunks=(rows, w), name=f"hdrcap-exr-{n}-{token}", meta=np.empty((0, 0), np.float32))
        for n in used
    ]

    def block(*blocks: np.ndarray, block_info: Any = None) -> np.ndarray:
        """Filter an extended band; irradiance + 1j sigma (complex64 holds both float32 exactly)."""
        ch = dict(zip(used, blocks))
        first = max(block_info[0]["chunk-location"][0] * rows - depth, 0)
        name = f"{path} (the tile from row {first}; rows below counted from there)"
        quality = ch.get("quality")  # as the in-memory path holds it (HdrResult.quality)
        res = denoise(
            ch["irradiance"],
            ch["sigma"],
            ch.get("nexp"),
            settings,
            name=name,
            quality=None if quality is None else quality.astype(np.uint8),
        )
        out = np.empty(res.irradiance.shape, np.complex64)
        out.real, out.imag = res.irradiance, res.sigma
        return out

    filtered = da.map_overlap(
        block,
        *arrays,
        depth={0: depth, 1: 0},
        boundary="none",
        trim=True,
        dtype=np.complex64,
        meta=np.empty((0, 0), np.complex64),
    )
    kept = ["irradiance", "sigma", "nexp", *(n for n in ("quality", "sigma_calibration") if n in src)]
    with tempfile.TemporaryDirectory(prefix=".hdrcap-tiles-", dir=scratch_dir) as tmp:
        outs = {n: RowFile.create(Path(tmp) / f"{n}.bin", shape, _CARRIED.get(n, np.float32)) for n in kept}
        done: list[int] = []

        def write(core: np.ndarray, block_info: Any = None) -> np.ndarray:
            """Write a band's filtered rows (the overlap cut off) and its carried channels."""
            r0 = block_info[0]["array-location"][0][0]
            r1 = r0 + core.shape[0]
            outs["irradiance"].write(r0, core.real)
            outs["sigma"].write(r0, core.imag)
            for n in kept[2:]:
                outs[n].write(r0, src[n].rows(r0, r1) if n in src else np.ones((r1 - r0, w), np.float32))
            done.append(r0)
            return np.zeros(r1 - r0, np.int8)

        written = filtered.map_blocks(write, dtype=np.int8, drop_axis=1, meta=np.empty((0,), np.int8))
        with dask.config.set(scheduler="synchronous"):
            if progress:
                from dask.diagnostics import ProgressBar

                with ProgressBar(out=sys.stderr):
                    written.compute()
            else:
                written.compute()
        if len(done) != len(filtered.chunks[0]):
            raise RuntimeError(f"{len(done)} of {len(filtered.chunks[0])} tiles were written")
        channels = {n: out.mapped() for n, out in outs.items()}
    return TiledChannels(channels, rows, len(done))
