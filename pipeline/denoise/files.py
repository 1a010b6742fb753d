"""From a merge (a result in memory or its EXR file) to the denoised result: the one path every door takes.

:func:`denoise_result` filters a :class:`hdrcap.pipeline.result.HdrResult` in memory (the
Python API); :func:`denoise_file` reads a merge's EXR and filters it in memory or tile by tile
(:mod:`hdrcap.pipeline.denoise.tiled`), the same result bit for bit (``hdrcap denoise``). Either
result carries the filtered ``irradiance`` and ``sigma`` (Sec. 9,
:func:`hdrcap.pipeline.denoise.filter.denoise`), every other channel unchanged, and the input's
header with ``sigma`` saying what the new sigma means and ``denoise`` the settings;
:func:`hdrcap.pipeline.io.results.write_result` writes it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdrcap.pipeline.denoise.filter import (
    DEFAULT_RADIUS,
    DEFAULT_RANGE_SCALE,
    DEFAULT_SPATIAL_SIGMA,
    SIGMA_MEANING,
    DenoiseSettings,
    denoise,
)
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.result import MEDIAN_SAMPLES, HdrResult

__all__ = [
    "LAYOUT_CHOICES",
    "DenoiseOptions",
    "DenoiseFigures",
    "layout_from_metadata",
    "denoise_result",
    "denoise_file",
]

#: Layouts a caller may ask for: ``auto`` is ``cfa`` when the header names a Bayer tile, else ``mono``.
LAYOUT_CHOICES = ("auto", "cfa", "mono")

#: Rows the figures of :func:`denoise_file` read at a time (a tiled result's channels are files).
_FIGURE_ROWS = 256


def layout_from_metadata(metadata: Mapping[str, Any]) -> str:
    """The layout a merge's header implies.

    Parameters
    ----------
    metadata : mapping
        A merge's header (:attr:`hdrcap.pipeline.result.HdrResult.header`, an EXR's hdrcap header).

    Returns
    -------
    str
        ``"cfa"`` when ``cfa_pattern`` names a 2x2 Bayer pattern, else ``"mono"``.

    Examples
    --------
    >>> layout_from_metadata({"cfa_pattern": "RGGB"}), layout_from_metadata({"cfa_pattern": "none"})
    ('cfa', 'mono')
    """
    cfa = metadata.get("cfa_pattern")
    if isinstance(cfa, str) and len(cfa) == 4 and set(cfa) <= set("RGBE") and len(set(cfa)) > 1:
        return "cfa"
    return "mono"


@dataclass(frozen=True)
class DenoiseOptions:
    """The filter as a caller asks for it: None for a default, the layout ``auto`` or given.

    Attributes
    ----------
    method : {"adaptive", "constant"}
        Range bandwidth ``range_scale`` x each photosite's sigma (Sec. 9), or ``bandwidth`` for all.
    range_scale : float or None
        K, dimensionless (adaptive; default :data:`hdrcap.pipeline.denoise.filter.DEFAULT_RANGE_SCALE`).
    bandwidth : float or None
        Constant range bandwidth, the irradiance's unit (constant method; ``inf``: a Gaussian).
    radius : int or None
        Half-width of the square support, same-colour steps (default 2).
    spatial_sigma : float or None
        Spatial standard deviation, same-colour steps (default 1.5).
    layout : {"auto", "cfa", "mono"}
        :data:`LAYOUT_CHOICES`.

    Raises
    ------
    InputError
        An unknown layout.

    Examples
    --------
    >>> DenoiseOptions(radius=1).settings({"cfa_pattern": "GRBG"}).to_dict()["layout"]
    'cfa'
    """

    method: str = "adaptive"
    range_scale: float | None = None
    bandwidth: float | None = None
    radius: int | None = None
    spatial_sigma: float | None = None
    layout: str = "auto"

    def __post_init__(self) -> None:
        if self.layout not in LAYOUT_CHOICES:
            raise InputError(f"layout must be auto, cfa or mono, got {self.layout!r}")

    def settings(self, header: Mapping[str, Any]) -> DenoiseSettings:
        """The filter's settings for a merge with this header (``auto``: its ``cfa_pattern``).

        Parameters
        ----------
        header : mapping
            The merge's header.

        Returns
        -------
        DenoiseSettings

        Raises
        ------
        InputError
            Invalid settings (the constant method without a bandwidth, a radius < 0, ...).
        """
        return DenoiseSettings(
            method=self.method,
            range_scale=DEFAULT_RANGE_SCALE if self.range_scale is None else self.range_scale,
            bandwidth=self.bandwidth,
            radius=DEFAULT_RADIUS if self.radius is None else self.radius,
            spatial_sigma=DEFAULT_SPATIAL_SIGMA if self.spatial_sigma is None else self.spatial_sigma,
            layout=layout_from_metadata(header) if self.layout == "auto" else self.layout,
        )


@dataclass(frozen=True)
class DenoiseFigures:
    """What :func:`denoise_file` reports beside its result.

    Attributes
    ----------
    median_relative_sigma_before, median_relative_sigma_after : float or None
        Median of sigma / |irradiance| before and after the filter, dimensionless, over the
        photosites the filter changes (nexp > 0, quality 0) of a regular subsample of at most
        about :data:`hdrcap.pipeline.result.MEDIAN_SAMPLES` photosites (the same ones in memory
        and tiled); None when none counts.
    unchanged_nexp0 : int
        Photosites left as they were (nexp 0 or a quality bit set).
    chunk_rows, tiles : int or None
        Rows per tile and tiles filtered (None in memory).
    """

    median_relative_sigma_before: float | None
    median_relative_sigma_after: float | None
    unchanged_nexp0: int
    chunk_rows: int | None = None
    tiles: int | None = None


def _header(
    header: Mapping[str, Any], settings: DenoiseSettings, options: DenoiseOptions, unchanged: int, source: str | None
) -> dict[str, Any]:
    """The input's header with ``sigma`` saying what the filtered sigma means and ``denoise``
    what was done: the filter, its settings, where the layout came from, the input file (when
    one), what the input's sigma meant, the photosites left unchanged, hdrcap's version."""
    from hdrcap import __version__

    entry: dict[str, Any] = {
        "filter": "bilateral, range bandwidth from the predicted uncertainty (Granados et al., Sec. 9)",
        "settings": settings.to_dict(),
        "layout_source": "header cfa_pattern" if options.layout == "auto" else "layout option",
    }
    if source is not None:
        entry["source_file"] = source
    entry.update(
        input_sigma=header.get("sigma") or "standard deviation of irradiance",
        unchanged_nexp0=int(unchanged),
        hdrcap_version=__version__,
    )
    return {**header, "sigma": SIGMA_MEANING, "denoise": entry}


def denoise_result(
    result: HdrResult,
    options: DenoiseOptions | None = None,
    *,
    name: str = "denoise input",
    source_file: str | None = None,
) -> HdrResult:
    """Filter a merge in memory (Sec. 9): a new result, ``result`` unchanged.

    Parameters
    ----------
    result : HdrResult
        The merge: irradiance and sigma in the header's unit, nexp, quality (photosites with
        nexp 0 or a quality bit set are left unchanged and never used as neighbours).
    options : DenoiseOptions, optional
        The filter (default: adaptive, K = 3, radius 2, spatial sigma 1.5, layout from the header).
    name : str
        Prefix of error messages (e.g. the file name).
    source_file : str, optional
        The file the merge was read from, recorded under ``denoise``.

    Returns
    -------
    HdrResult
        Filtered ``irradiance`` and its propagated ``sigma`` (float32, same unit; the sigma does
        not include the bias the filter introduces), the other channels shared with ``result``,
        the header with ``sigma`` = :data:`hdrcap.pipeline.denoise.filter.SIGMA_MEANING` and
        the ``denoise`` entry.

    Raises
    ------
    InputError
        Bad settings; non-finite irradiance; sigma not finite and > 0 where the filter uses it.
    """
    opts = options or DenoiseOptions()
    settings = opts.settings(result.header)
    res = denoise(result.irradiance, result.sigma, result.nexp, settings, name=name, quality=result.quality)
    header = _header(result.header, settings, opts, res.info["unchanged_nexp0"], source_file)
    return result.replace(irradiance=res.irradiance, sigma=res.sigma, header=header)


def denoise_file(
    path: str | os.PathLike[str],
    options: DenoiseOptions | None = None,
    *,
    rows: int | None = None,
    scratch_dir: str | os.PathLike[str] | None = None,
    progress: bool = False,
) -> tuple[HdrResult, DenoiseFigures]:
    """Read a merge's EXR and filter it (Sec. 9), in memory or tile by tile: the same result,
    every channel bit for bit and the header.

    Parameters
    ----------
    path : str or path-like
        The EXR (``hdrcap merge``): channels ``irradiance`` and ``sigma``, optionally ``nexp``,
        ``quality``, ``sigma_calibration`` (other channels are not read).
    options : DenoiseOptions, optional
        The filter (default :class:`DenoiseOptions`).
    rows : int, optional
        Filter tiles of this many rows (even; raised to the filter's reach) read a band at a
        time from the file, for images larger than memory; None: the whole image in memory.
    scratch_dir : str or path-like, optional
        Folder of the tiles' temporary channel files (default: the system's temporary folder).
    progress : bool
        A progress bar on stderr (tiles).

    Returns
    -------
    (HdrResult, DenoiseFigures)
        The filtered merge as :func:`denoise_result` gives it (``denoise.source_file`` naming
        ``path``; tiled: channels memory-mapped from deleted files, which the mappings keep
        until the arrays are gone, POSIX), and the figures of the summary.

    Raises
    ------
    InputError
        Missing or unreadable file, no irradiance or sigma channel, channel sizes that differ,
        bad settings or channels the filter refuses, odd ``rows``.
    """
    from hdrcap.pipeline.io.exr import ExrRows, read_exr_layout
    from hdrcap.pipeline.io.results import read_result

    opts = options or DenoiseOptions()
    if rows is None:
        source = read_result(path)
        result = denoise_result(source, opts, name=str(path), source_file=str(path))
        before, after, _ = _medians(source.irradiance, source.sigma, result)
        figures = DenoiseFigures(before, after, result.header["denoise"]["unchanged_nexp0"])
        return result, figures
    layout = read_exr_layout(path)
    missing = [c for c in ("irradiance", "sigma") if c not in layout.channels]
    if missing:
        raise InputError(f"{path}: no {' or '.join(missing)} channel; expected a merge result")
    settings = opts.settings(layout.header)  # bad settings refused before any pixel is read
    from hdrcap.pipeline.denoise.tiled import denoise_tiled

    tiled = denoise_tiled(
        path, list(layout.channels), layout.shape, settings, rows=rows, scratch_dir=scratch_dir, progress=progress
    )
    ch = tiled.channels
    result = HdrResult(
        ch["irradiance"], ch["sigma"], ch["nexp"], ch.get("quality"), ch.get("sigma_calibration"), layout.header
    )
    irr0, sig0 = (ExrRows(str(path), n, layout.shape) for n in ("irradiance", "sigma"))
    before, after, unchanged = _medians(irr0, sig0, result)
    result = result.replace(header=_header(layout.header, settings, opts, unchanged, str(path)))
    return result, DenoiseFigures(before, after, unchanged, tiled.rows, tiled.tiles)


def _medians(irradiance: Any, sigma: Any, after: HdrResult) -> tuple[float | None, float | None, int]:
    """Median relative sigma of the input (``irradiance``, ``sigma``: arrays or
    :class:`hdrcap.pipeline.io.exr.ExrRows`) and of ``after`` over the photosites the filter
    changes of the regular subsample (every ``size // MEDIAN_SAMPLES``-th photosite of the
    flattened image), and how many photosites it left unchanged; read a block of rows at a time."""
    from hdrcap.pipeline.io.files import release_mapped_pages

    h, w = after.shape
    step = max(1, h * w // MEDIAN_SAMPLES)
    ratios: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    unchanged = 0
    for r0 in range(0, h, _FIGURE_ROWS):
        r1 = min(r0 + _FIGURE_ROWS, h)
        flags = [after.nexp[r0:r1]] if after.quality is None else [after.nexp[r0:r1], after.quality[r0:r1]]
        ok = np.asarray(flags[0]) > 0
        if len(flags) > 1:
            ok &= np.asarray(flags[1]) == 0
        unchanged += ok.size - int(np.count_nonzero(ok))
        pick = np.arange((-r0 * w) % step, ok.size, step)  # flat index a multiple of step
        sel = ok.ravel()[pick]
        blocks = [irradiance[r0:r1], sigma[r0:r1], after.irradiance[r0:r1], after.sigma[r0:r1]]
        for k, out in enumerate(ratios):
            irr, sig = (np.asarray(a, np.float32).ravel()[pick][sel] for a in blocks[2 * k : 2 * k + 2])
            out.append(sig / np.maximum(np.abs(irr), 1e-30))
        release_mapped_pages([*flags, *blocks])
    medians = [np.concatenate(r) if r else np.empty(0, np.float32) for r in ratios]
    before, filtered = (float(np.median(m)) if m.size else None for m in medians)
    return before, filtered, unchanged
