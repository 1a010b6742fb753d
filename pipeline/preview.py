"""Tone-mapped previews of HDR mosaics (for looking at, never for measuring)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hdrcap.pipeline.io.files import atomic_output

__all__ = ["mosaic_to_rgb", "tonemap_log", "tonemap_log_colour", "preview_image", "write_preview_png"]


def mosaic_to_rgb(mosaic: np.ndarray, cfa: str | None) -> np.ndarray:
    """Half-resolution RGB from a Bayer mosaic by 2x2 binning (greens averaged).

    Parameters
    ----------
    mosaic : numpy.ndarray
        (H, W) values, any unit (e.g. irradiance, e-/s).
    cfa : str or None
        2x2 pattern read row by row (e.g. ``"RGGB"``); without one the single channel is
        repeated into grey at full resolution.

    Returns
    -------
    numpy.ndarray
        (H/2, W/2, 3) float64 RGB in the mosaic's unit (odd last row/column dropped), or
        (H, W, 3) grey.
    """
    m = np.asarray(mosaic, dtype=np.float64)
    if not cfa or len(cfa) != 4:
        return np.repeat(m[..., None], 3, axis=2)
    h, w = (m.shape[0] // 2) * 2, (m.shape[1] // 2) * 2
    tiles = [m[0:h:2, 0:w:2], m[0:h:2, 1:w:2], m[1:h:2, 0:w:2], m[1:h:2, 1:w:2]]
    rgb = np.zeros((h // 2, w // 2, 3))
    count = np.zeros(3)
    for letter, tile in zip(cfa, tiles):
        c = "RGB".index(letter)
        rgb[..., c] += tile
        count[c] += 1
    return rgb / np.maximum(count, 1)


def tonemap_log(rgb: np.ndarray, lo_pct: float = 0.5, hi_pct: float = 99.9) -> np.ndarray:
    """Logarithmic tone map to 8 bit between two percentiles of the positive values.

    Parameters
    ----------
    rgb : numpy.ndarray
        (..., 3) linear values, any unit.
    lo_pct, hi_pct : float
        Percentiles of the positive mean values mapped to black and white, %.

    Returns
    -------
    numpy.ndarray
        uint8 image of ``rgb``'s shape (log scale, gamma 1/1.2); all black without positive values.
    """
    levels = _log_levels(rgb.mean(axis=-1), lo_pct, hi_pct)
    if levels is None:
        return np.zeros(rgb.shape, dtype=np.uint8)
    return np.round(255 * _log_map(rgb, *levels)).astype(np.uint8)


def _log_levels(ref: np.ndarray, lo_pct: float, hi_pct: float) -> tuple[float, float] | None:
    """The values mapped to black and white: two percentiles of the positive ``ref`` (None if none)."""
    pos = ref[ref > 0]
    if pos.size == 0:
        return None
    lo, hi = np.percentile(pos, [lo_pct, hi_pct])
    return max(lo, hi * 1e-8), hi


def _log_map(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``x`` on a log scale from ``lo`` (0) to ``hi`` (1), clipped, gamma 1/1.2."""
    val = (np.log10(np.clip(x, lo, hi)) - np.log10(lo)) / max(np.log10(hi) - np.log10(lo), 1e-12)
    return np.clip(val, 0, 1) ** (1 / 1.2)


def tonemap_log_colour(rgb: np.ndarray, lo_pct: float = 0.5, hi_pct: float = 99.9) -> np.ndarray:
    """Logarithmic tone map of each pixel's largest channel, keeping its hue and saturation.

    The largest channel goes through the log map of :func:`tonemap_log` (same percentiles, of
    the largest channels); the others keep their ratio to it (negative values become 0).

    Parameters
    ----------
    rgb : numpy.ndarray
        (..., 3) linear RGB, any unit.
    lo_pct, hi_pct : float
        Percentiles of the positive largest channels mapped to black and white, %.

    Returns
    -------
    numpy.ndarray
        uint8 image of ``rgb``'s shape; all black without positive values.
    """
    rgb = np.clip(np.asarray(rgb, dtype=np.float64), 0, None)
    top = rgb.max(axis=-1)
    levels = _log_levels(top, lo_pct, hi_pct)
    if levels is None:
        return np.zeros(rgb.shape, dtype=np.uint8)
    val = _log_map(top, *levels)
    ratio = np.divide(rgb, top[..., None], out=np.zeros_like(rgb), where=top[..., None] > 0)
    return np.round(255 * ratio * val[..., None]).astype(np.uint8)


def preview_image(irradiance: np.ndarray, cfa: str | None) -> np.ndarray:
    """The 8-bit RGB image of a preview (what :func:`write_preview_png` writes).

    Parameters
    ----------
    irradiance : numpy.ndarray
        (H, W) irradiance mosaic, e-/s, or (H, W, 3) RGB (its hues kept, :func:`tonemap_log_colour`).
    cfa : str or None
        2x2 CFA pattern of the mosaic (None: grey; ignored for RGB).

    Returns
    -------
    numpy.ndarray
        uint8 (h, w, 3): half resolution for a CFA mosaic (:func:`mosaic_to_rgb`), else full.
    """
    if np.ndim(irradiance) == 3:
        return tonemap_log_colour(irradiance)
    return tonemap_log(mosaic_to_rgb(irradiance, cfa))


def write_preview_png(path: str | Path, irradiance: np.ndarray, cfa: str | None, force: bool = False) -> Path:
    """Write a log tone-mapped PNG preview of an irradiance mosaic (for looking at only).

    Parameters
    ----------
    path : str or Path
        Output PNG.
    irradiance : numpy.ndarray
        (H, W) irradiance mosaic, e-/s, or (H, W, 3) RGB (a developed image: its hues kept,
        :func:`tonemap_log_colour`).
    cfa : str or None
        2x2 CFA pattern of the mosaic (None: grey; ignored for RGB).
    force : bool
        Replace an existing file.

    Returns
    -------
    Path
        ``path``.
    """
    from PIL import Image

    img = preview_image(irradiance, cfa)
    with atomic_output(path, force=force, suffix=".png") as tmp:
        Image.fromarray(img, "RGB").save(tmp, format="PNG")
    return Path(path)
