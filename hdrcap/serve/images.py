"""PNG images of a merge for the web page: the tone-mapped preview and maps of SNR, sigma and the
quality flags, drawn with :mod:`hdrcap.pipeline.plotting` (no pyplot) into memory."""

from __future__ import annotations

import io
import math

import numpy as np

from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import QUALITY_BITS

__all__ = ["MAP_KINDS", "png_bytes", "preview_png", "map_png", "binned"]

#: The maps :func:`map_png` draws.
MAP_KINDS = ("snr", "sigma", "quality")
#: Longest side of a map, in cells (a larger mosaic is averaged over blocks of photosites).
MAP_CELLS = 800


def png_bytes(rgb: np.ndarray) -> bytes:
    """``rgb`` (uint8, (H, W, 3)) as PNG file content.

    Parameters
    ----------
    rgb : numpy.ndarray

    Returns
    -------
    bytes
    """
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb), "RGB").save(buf, format="PNG")
    return buf.getvalue()


def _cfa(result: HdrResult) -> str | None:
    cfa = result.header.get("cfa_pattern")
    return cfa if isinstance(cfa, str) and len(cfa) == 4 else None


def preview_png(irradiance: np.ndarray, cfa: str | None) -> bytes:
    """The log tone-mapped preview of an irradiance mosaic (:func:`hdrcap.pipeline.preview.preview_image`).

    Parameters
    ----------
    irradiance : numpy.ndarray
        (H, W) mosaic, e-/s.
    cfa : str or None
        2x2 CFA pattern (half-resolution colour), None for grey.

    Returns
    -------
    bytes
        PNG.
    """
    from hdrcap.pipeline.preview import preview_image

    return png_bytes(preview_image(irradiance, cfa))


def binned(values: np.ndarray, cells: int = MAP_CELLS, reduce: str = "mean") -> np.ndarray:
    """``values`` reduced over square blocks so that the longer side has at most ``cells``
    cells (NaN ignored; a block of NaN stays NaN).

    Parameters
    ----------
    values : numpy.ndarray
        (H, W).
    cells : int
    reduce : {"mean", "max"}

    Returns
    -------
    numpy.ndarray
        float64 (ceil(H/k), ceil(W/k)) with k the block side.
    """
    v = np.asarray(values, dtype=np.float64)
    k = max(1, math.ceil(max(v.shape) / cells))
    if k == 1:
        return v
    h, w = v.shape
    pad = np.full((math.ceil(h / k) * k, math.ceil(w / k) * k), np.nan)
    pad[:h, :w] = v
    blocks = pad.reshape(pad.shape[0] // k, k, pad.shape[1] // k, k)
    ok = np.isfinite(blocks)
    if reduce == "max":
        out = np.where(ok, blocks, -np.inf).max(axis=(1, 3))
        return np.where(np.isfinite(out), out, np.nan)
    n = ok.sum(axis=(1, 3))
    total = np.where(ok, blocks, 0).sum(axis=(1, 3))
    return np.divide(total, n, out=np.full(n.shape, np.nan), where=n > 0)


def map_png(result: HdrResult, kind: str) -> bytes:
    """A map of the merge with its colour bar or legend.

    - ``snr``: 20 log10(irradiance / sigma), dB, where measured (nexp > 0, sigma > 0).
    - ``sigma``: log10 of sigma, in the header's unit, where measured.
    - ``quality``: the quality flags, one colour per flag (the lowest bit set), with the count
      of photosites of each.

    Parameters
    ----------
    result : HdrResult
    kind : {"snr", "sigma", "quality"}

    Returns
    -------
    bytes
        PNG.
    """
    from hdrcap.pipeline.plotting import new_figure

    h, w = result.shape
    aspect = h / max(w, 1)
    fig, ax = new_figure(figsize=(5.0, max(2.0, min(5.0, 3.6 * aspect + 0.4))))
    ax.set_axis_off()
    measured = np.asarray(result.nexp) > 0
    if kind == "quality":
        _quality_axes(fig, ax, result)
    else:
        irr = np.asarray(result.irradiance, dtype=np.float64)
        sig = np.asarray(result.sigma, dtype=np.float64)
        ok = measured & (sig > 0) & np.isfinite(irr) & np.isfinite(sig)
        if kind == "snr":
            with np.errstate(divide="ignore", invalid="ignore"):
                val = np.where(ok & (irr > 0), 20 * np.log10(np.abs(irr) / sig), np.nan)
            label, cmap = "SNR, dB", "viridis"
        elif kind == "sigma":
            val = np.where(ok, np.log10(np.where(ok, sig, 1.0)), np.nan)
            label, cmap = f"log10 sigma, {_short_unit(result.header.get('unit'))}", "magma"
        else:
            raise ValueError(f"unknown map {kind!r}")
        img = binned(val)
        finite = img[np.isfinite(img)]
        lo, hi = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
        if hi <= lo:
            hi = lo + 1
        from matplotlib import colormaps

        cm = colormaps[cmap].with_extremes(bad="#888888")
        im = ax.imshow(img, cmap=cm, vmin=lo, vmax=hi, interpolation="nearest")
        bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
        bar.set_label(label, fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight", pad_inches=0.08)
    return buf.getvalue()


def _short_unit(unit: str | None) -> str:
    """The irradiance unit for an axis label (``e-/s``, ``DN/s``)."""
    from hdrcap.pipeline.schema import UNIT_DN, UNIT_ELECTRONS

    return {UNIT_ELECTRONS: "e-/s", UNIT_DN: "DN/s (gain unknown)"}.get(unit or "", unit or "irradiance unit")


def _quality_axes(fig, ax, result: HdrResult) -> None:
    """The quality map: each photosite coloured by its lowest flag bit (black: trusted)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    q = np.zeros(result.shape, np.uint8) if result.quality is None else np.asarray(result.quality, np.uint8)
    names = list(QUALITY_BITS)
    colours = ["#000000", "#e41a1c", "#377eb8", "#ff7f00", "#984ea3", "#ffff33", "#4daf4a", "#a65628", "#f781bf"]
    code = np.zeros(q.shape, np.int16)
    for i, name in reversed(list(enumerate(names))):  # the lowest bit wins
        code[(q & QUALITY_BITS[name]) != 0] = i + 1
    cmap = ListedColormap(colours[: len(names) + 1])
    img = binned(code.astype(np.float64), reduce="max")
    ax.imshow(np.nan_to_num(img), cmap=cmap, vmin=-0.5, vmax=len(names) + 0.5, interpolation="nearest")
    counts = {name: int(np.count_nonzero(q & QUALITY_BITS[name])) for name in names}
    handles = [Patch(color=colours[0], label=f"trusted: {int(np.count_nonzero(q == 0))}")]
    handles += [Patch(color=colours[i + 1], label=f"{name}: {counts[name]}") for i, name in enumerate(names)]
    ax.legend(handles=handles, loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=9, frameon=False)
    if result.quality is None:
        ax.set_title("no quality flags recorded by this merge", fontsize=9)
