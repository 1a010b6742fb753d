"""``hdrcap denoise --chunks ROWS``: the bilateral filter (Sec. 9) of a merged EXR, tile by tile.

The EXR is read a band of rows at a time (OpenEXR's scanline reader: only those rows are
decoded), each band extended by the filter's reach (:func:`pipeline.denoise.filter.support_depth`
rows above and below, ``dask.array.map_overlap`` with no padding at the image's edges, where
the filter itself stops) and filtered by :func:`pipeline.denoise.filter.denoise`; the overlap is then
cut off. A photosite's result depends on no photosite farther away than that reach, and the
filter computes each photosite in the same order whatever its neighbourhood holds beyond it,
so the tiles' results are the whole image's, bit for bit, and tile borders are invisible. The
filtered channels go to temporary files, then with the other channels (copied a band at a time)
into the output EXR.
"""

from __future__ import annotations

import sys
import tempfile
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr_layout, write_exr
from hdrcap.pipeline.merge.tiled import RowFile

__all__ = [
    "ExrRows",
    "exr_layout",
    "exr_pixel_types",
    "output_precision",
    "median_relative_sigma",
    "denoise_tiled",
    "TiledDenoise",
]


@dataclass
class ExrRows:
    """Rows of one channel of a scanline EXR, as float32, decoded on demand (what
    ``dask.array.from_array`` and :func:`pipeline.merge.tiled.write_exr_rows` read).

    Attributes
    ----------
    path : str
        The EXR.
    name : str
        The channel.
    shape : (int, int)
        Rows, columns of the data window.
    """

    path: str
    name: str
    shape: tuple[int, int]
    dtype: np.dtype = np.dtype(np.float32)
    ndim: int = 2

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` (clipped), float32 (half and uint channels converted exactly)."""
        import Imath
        import OpenEXR

        h, w = self.shape
        r0, r1 = max(0, min(r0, h)), max(0, min(r1, h))
        if r1 <= r0:
            return np.empty((0, w), np.float32)
        f = OpenEXR.InputFile(self.path)
        try:
            y0 = f.header()["dataWindow"].min.y
            raw = f.channel(self.name, Imath.PixelType(Imath.PixelType.FLOAT), y0 + r0, y0 + r1 - 1)
        finally:
            f.close()
        return np.frombuffer(raw, np.float32).reshape(r1 - r0, w).copy()

    def __getitem__(self, key) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        r0, r1, step = key[0].indices(self.shape[0])
        if step != 1:
            raise IndexError("rows of an EXR channel are read with step 1")
        return self.rows(r0, r1)[(slice(None), *key[1:])]


def exr_layout(path: Path) -> tuple[dict[str, Any], list[str], tuple[int, int]]:
    """An EXR's hdrcap metadata, channel names and size, without reading its pixels.

    Parameters
    ----------
    path : Path
        The EXR file.

    Returns
    -------
    (dict, list of str, (int, int))
        The header attributes hdrcap wrote, the channel names, the size (rows, columns).

    Raises
    ------
    InputError
        Not a readable EXR, or corrupt hdrcap metadata.
    """
    layout = read_exr_layout(path)
    return layout.header, list(layout.channels), layout.shape


def exr_pixel_types(path: Path) -> dict[str, str]:
    """How each channel of an EXR is stored, from its header only (no pixels read).

    Parameters
    ----------
    path : pathlib.Path
        A readable EXR.

    Returns
    -------
    dict of str to str
        Channel name -> ``"float"``, ``"half"`` or ``"uint"``.
    """
    return read_exr_layout(path).channels


def output_precision(stored: dict[str, str], sigma: str = "auto") -> dict[str, str]:
    """Storage precision of each channel of a filtered EXR: ``irradiance`` float32, the filtered
    ``sigma`` as ``hdrcap merge --sigma-precision`` stores it (:func:`hdrcap.pipeline.io.exr.write_exr`'s
    ``auto``: half where the channel fits half's range, at most 0.05 % lost), every other channel
    as the input stored it (its values were read from that type: lossless).

    Parameters
    ----------
    stored : dict of str to str
        :func:`exr_pixel_types` of the input.
    sigma : {"auto", "half", "float"}
        Precision of the filtered sigma.

    Returns
    -------
    dict of str to str
        Channel name -> precision for :func:`hdrcap.pipeline.io.exr.write_exr`.
    """
    out = dict(stored, irradiance="float")
    if "sigma" in stored:
        out["sigma"] = sigma  # write_exr's "auto": the rule behind `hdrcap merge --sigma-precision`
    return out


@dataclass
class TiledDenoise:
    """What :func:`denoise_tiled` did: header, photosites left unchanged, the median relative
    sigma before and after on a regular subsample (at most about a million photosites), tiles."""

    attrs: dict[str, Any]
    unchanged_nexp0: int
    median_relative_sigma_before: float | None
    median_relative_sigma_after: float | None
    rows: int
    tiles: int


#: The JSON's median relative sigmas are taken over at most about this many photosites.
MEDIAN_SAMPLES = 1_000_000


def _sample_step(size: int) -> int:
    """Step of the regular subsample (of the flattened image) the median relative sigmas use."""
    return max(1, size // MEDIAN_SAMPLES)


def median_relative_sigma(irr: np.ndarray, sig: np.ndarray, ok: np.ndarray) -> float | None:
    """Median of sigma / |irradiance| over the photosites ``ok`` of a regular subsample (every
    :func:`_sample_step`-th photosite of the flattened image: the tiles of :func:`denoise_tiled`
    sample the same ones).

    Parameters
    ----------
    irr, sig : numpy.ndarray
        Irradiance and its sigma, e-/s, one shape.
    ok : numpy.ndarray of bool
        Photosites to count.

    Returns
    -------
    float or None
        Dimensionless; None when no photosite counts.
    """
    step = _sample_step(irr.size)
    pick = ok.ravel()[::step]
    return _median([(irr.ravel()[::step][pick], sig.ravel()[::step][pick])])


def _median(pairs: list[tuple[np.ndarray, np.ndarray]]) -> float | None:
    if not pairs:
        return None
    irr = np.concatenate([p[0] for p in pairs])
    sig = np.concatenate([p[1] for p in pairs])
    return float(np.median(sig / np.maximum(np.abs(irr), 1e-30))) if irr.size else None


def denoise_tiled(
    input_exr: Path,
    output: Path,
    settings,
    *,
    rows: int,
    precision: dict[str, str] | None = None,
    compression: str = "zip",
    attrs: dict[str, Any],
    names: list[str],
    shape: tuple[int, int],
    header_entry,
    force: bool = False,
    progress: bool = False,
) -> TiledDenoise:
    """Filter ``input_exr`` tile by tile into ``output`` (the same channels and header as the
    in-memory ``hdrcap denoise``, ``irradiance`` and ``sigma`` filtered).

    Parameters
    ----------
    input_exr, output : pathlib.Path
        The merged EXR and the filtered one.
    settings : pipeline.denoise.filter.DenoiseSettings
    rows : int
        Rows per tile (even), before the overlap.
    precision : dict, optional
        Channel storage (:func:`output_precision`; default float for every channel).
    compression : str
        EXR compression, one of :data:`hdrcap.pipeline.io.exr.EXR_COMPRESSIONS`.
    attrs, names, shape
        :func:`exr_layout` of ``input_exr``.
    header_entry : callable
        ``header_entry(unchanged_nexp0)`` -> the header's ``denoise`` entry.
    force : bool
        Replace an existing output.
    progress : bool
        A progress bar on stderr.

    Returns
    -------
    TiledDenoise
    """
    import dask
    import dask.array as da

    from hdrcap.pipeline.denoise.filter import SIGMA_MEANING, denoise, support_depth

    if rows < 2 or rows % 2:
        raise InputError(f"--chunks {rows}: give an even number of rows (whole CFA periods), >= 2")
    h, w = shape
    depth = support_depth(settings)
    rows = max(rows, depth + depth % 2)  # a band at least as tall as the reach (dask would merge bands)
    token = uuid.uuid4().hex
    src = {n: ExrRows(str(input_exr), n, shape) for n in names}
    used = [n for n in ("irradiance", "sigma", "nexp", "quality") if n in src]
    arrays = [
        da.from_array(src[n], chunks=(rows, w), name=f"hdrcap-exr-{n}-{token}", meta=np.empty((0, 0), np.float32))
        for n in used
    ]
    sample_step = _sample_step(h * w)
    samples: dict[int, tuple] = {}

    def block(*blocks, block_info=None):
        """Filter an extended band; irradiance + 1j sigma (complex64 holds both float32 exactly)."""
        ch = dict(zip(used, blocks))
        first = max(block_info[0]["chunk-location"][0] * rows - depth, 0)
        name = f"{input_exr} (the tile from row {first}; rows below counted from there)"
        res = denoise(ch["irradiance"], ch["sigma"], ch.get("nexp"), settings, name=name, quality=ch.get("quality"))
        out = np.empty(res.irradiance.shape, np.complex64)
        out.real, out.imag = res.irradiance, res.sigma
        return out

    def valid_rows(r0, r1):
        """Photosites the filter changes (nexp > 0 and quality 0) in rows r0:r1."""
        ok = np.ones((r1 - r0, w), bool)
        if "nexp" in src:
            ok &= src["nexp"].rows(r0, r1) > 0
        if "quality" in src:
            ok &= src["quality"].rows(r0, r1) == 0
        return ok

    filtered = da.map_overlap(
        block,
        *arrays,
        depth={0: depth, 1: 0},
        boundary="none",
        trim=True,
        dtype=np.complex64,
        meta=np.empty((0, 0), np.complex64),
    )
    with tempfile.TemporaryDirectory(
        prefix=".hdrcap-tiles-", dir=output.parent if output.parent.is_dir() else "."
    ) as tmp:
        outs = {n: RowFile.create(Path(tmp) / f"{n}.bin", shape, np.float32) for n in ("irradiance", "sigma")}

        def write(core, block_info=None):
            """Write a band's filtered rows (the overlap cut off); per row, the photosites left
            unchanged. Its figures for the summary are kept in ``samples`` (this process)."""
            r0 = block_info[0]["array-location"][0][0]
            irr, sig = core.real, core.imag
            valid = valid_rows(r0, r0 + irr.shape[0])
            outs["irradiance"].write(r0, irr)
            outs["sigma"].write(r0, sig)
            pick = np.arange((-r0 * w) % sample_step, irr.size, sample_step)
            ok = valid.ravel()[pick]
            before = [src[n].rows(r0, r0 + irr.shape[0]).ravel()[pick][ok] for n in ("irradiance", "sigma")]
            samples[r0] = (before, (irr.ravel()[pick][ok], sig.ravel()[pick][ok]))
            return (~valid).sum(axis=1)

        written = filtered.map_blocks(write, dtype=np.int64, drop_axis=1, meta=np.empty((0,), np.int64))
        with dask.config.set(scheduler="synchronous"):
            if progress:
                from dask.diagnostics import ProgressBar

                with ProgressBar(out=sys.stderr):
                    per_row = written.compute()
            else:
                per_row = written.compute()
        if len(samples) != len(filtered.chunks[0]):
            raise RuntimeError(f"{len(samples)} of {len(filtered.chunks[0])} tiles were written")
        counts = {0: int(per_row.sum())}
        unchanged = sum(counts.values())
        out_attrs = dict(attrs)
        out_attrs["sigma"] = SIGMA_MEANING
        out_attrs["denoise"] = header_entry(unchanged)
        channels = {n: outs.get(n, src[n]) for n in names}
        write_exr(
            output, channels, out_attrs, force=force, compression=compression, precision=precision, block_rows=rows
        )
    ordered = [samples[r0] for r0 in sorted(samples)]
    return TiledDenoise(
        out_attrs,
        unchanged,
        _median([s[0] for s in ordered]),
        _median([s[1] for s in ordered]),
        rows,
        len(samples),
    )
