"""PNG plots of a calibration: photon-transfer curve, PRNU histogram and map, dark-current fit,
defect map, shutter corrections.

Figures come from :mod:`hdrcap.pipeline.plotting` (no display, no global backend). Every file
is written atomically and never overwritten without ``force``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.params import DEFECT_BITS, Calibration, ShutterTable
from hdrcap.pipeline.plotting import new_figure, save_figure

__all__ = ["write_report"]

_DPI = 100


def _ptc_plot(calib: Calibration, ptc: dict[str, Any], path: Path, force: bool) -> Path:
    """Photon transfer: variance above dark (DN^2) against mean above dark (DN), with the fit."""
    p = calib.params
    x = np.asarray(ptc["means"], float)
    y = np.asarray(ptc["variances"], float)
    used = np.asarray(ptc.get("used", [True] * len(x)), bool)
    fig, ax = new_figure(figsize=(6.4, 4.4))
    ax.plot(x[~used], y[~used], "o", mfc="none", color="0.5", label="not fitted")
    ax.plot(x[used], y[used], "o", color="C0", label="fitted (0-70 % of saturation)")
    xx = np.linspace(0, max(x.max(), 1), 100)
    ax.plot(xx, p.g * xx, "-", color="C3", label=f"g = {p.g:.4g} ± {calib.stderr.get('g', float('nan')):.2g} DN/e⁻")
    ax.set_xlabel("mean above dark μ_y − μ_y.dark (DN)")
    ax.set_ylabel("temporal variance above dark (DN²)")
    ax.set_title("Photon transfer")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=_DPI)


def _prnu_plots(a: np.ndarray, out: Path, force: bool) -> list[Path]:
    """Histogram and map of the per-photosite gain a_j (Eq. 14)."""
    fig, ax = new_figure(figsize=(6.4, 4.4))
    ax.hist(a.ravel(), bins=200, color="C0", log=True)
    ax.set_xlabel("per-photosite gain a_j (Eq. 14)")
    ax.set_ylabel("photosites")
    ax.set_title(f"PRNU: std {np.std(a) * 100:.3f} % (estimate noise included)")
    fig.tight_layout()
    written = [save_figure(fig, out / "prnu_hist.png", force=force, dpi=_DPI)]
    fig, ax = new_figure(figsize=(6.4, 5.0))
    lo, hi = np.percentile(a, [0.5, 99.5])
    im = ax.imshow(a, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="a_j")
    ax.set_title("PRNU map")
    fig.tight_layout()
    written.append(save_figure(fig, out / "prnu_map.png", force=force, dpi=_DPI))
    return written


def _dark_plot(calib: Calibration, series: dict[str, Any], fit: dict[str, Any], path: Path, force: bool) -> Path:
    """Master-dark levels (DN) against exposure time (s), with the dark-current line."""
    t = np.asarray(series["times"], float)
    lv = np.asarray(series["levels"], float)
    fig, ax = new_figure(figsize=(6.4, 4.4))
    ax.plot(t, lv, "o", color="C0", label="master-dark level")
    if "slope_DN_per_s" in fit and np.isfinite(fit["slope_DN_per_s"]):
        b0 = fit.get("intercept_DN")
        if b0 is None:
            b0 = float(np.mean(lv - fit["slope_DN_per_s"] * t))
        tt = np.linspace(0, t.max(), 50)
        ax.plot(tt, b0 + fit["slope_DN_per_s"] * tt, "-", color="C3", label=f"D = {calib.params.dark_current:.3g} e⁻/s")
    ax.set_xlabel("exposure time (s)")
    ax.set_ylabel("mean dark value (DN)")
    ax.set_title("Dark current")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=_DPI)


#: Colour of each kind of defect in the map (a photosite with several flags shows the last).
_DEFECT_COLOURS = {"dead": "black", "weak": "tab:blue", "hot": "tab:red", "stuck": "tab:orange"}


def _defect_plot(defects: np.ndarray, path: Path, force: bool) -> Path:
    """Map of the defective photosites, one colour per kind, with the counts in the legend.

    Each defect is drawn as a marker (not a pixel) so that a few photosites of a large mosaic
    stay visible."""
    fig, ax = new_figure(figsize=(6.4, 5.0))
    h, w = defects.shape
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    for kind, bit in DEFECT_BITS.items():
        ys, xs = np.nonzero(defects & bit)
        ax.plot(xs, ys, "s", ms=2.5, color=_DEFECT_COLOURS[kind], label=f"{kind}: {ys.size}", linestyle="none")
    ax.set_title(f"Defective photosites: {int(np.count_nonzero(defects))} of {defects.size}")
    ax.legend(loc="upper right", fontsize="small")
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=_DPI)


def _shutter_plot(table: ShutterTable, path: Path, force: bool) -> Path:
    """Shutter corrections: (t_eff/t_nom - 1) in % against the nominal time, with 1-sigma bars."""
    t = np.asarray(table.times)
    f = 100.0 * (np.asarray(table.factors) - 1.0)
    e = 100.0 * np.asarray(table.stderr)
    fig, ax = new_figure(figsize=(6.4, 4.0))
    ax.errorbar(t, f, yerr=e, fmt="o", color="C0", capsize=3, label="t_eff / t_nom − 1 (± 1 σ)")
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("nominal exposure time (s)")
    ax.set_ylabel(f"correction relative to {table.reference:g} s (%)")
    ax.set_title("Shutter corrections")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=_DPI)


def write_report(calib: Calibration, out_dir: str | os.PathLike[str], force: bool = False) -> list[Path]:
    """Write the plots of a calibration into ``out_dir`` (created when missing).

    Parameters
    ----------
    calib : Calibration
        A calibration whose provenance holds the photon-transfer points and the dark series
        (as :func:`hdrcap.pipeline.calibration.calibrate` records them).
    out_dir : str or path-like
        Output folder.
    force : bool
        Replace existing files.

    Returns
    -------
    list of Path
        The files written: ``ptc.png``, ``prnu_hist.png``, ``prnu_map.png``,
        ``dark_current.png``, ``defects.png`` and ``shutter.png``, each when its data exist.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = calib.provenance.get("calibration", {})
    written = []
    ptc = info.get("ptc")
    if ptc and ptc.get("means"):
        written.append(_ptc_plot(calib, ptc, out / "ptc.png", force))
    if calib.prnu is not None:
        written += _prnu_plots(calib.prnu, out, force)
    ds = info.get("dark_series")
    if ds and len(ds.get("times", [])) >= 2:
        written.append(_dark_plot(calib, ds, info.get("dark_fit") or {}, out / "dark_current.png", force))
    if calib.defect_map is not None:
        written.append(_defect_plot(calib.defect_map, out / "defects.png", force))
    if calib.shutter is not None:
        written.append(_shutter_plot(calib.shutter, out / "shutter.png", force))
    return written
