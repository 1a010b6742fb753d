"""PNG plots of a calibration: photon-transfer curve, PRNU histogram and map, dark-current fit.

Uses matplotlib's Agg backend (no display). Every file is written atomically and never
overwritten without ``force``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .io import atomic_output
from .params import Calibration

__all__ = ["write_report"]


def _save(fig, path: Path, force: bool) -> Path:
    with atomic_output(path, force=force, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return path


def write_report(calib: Calibration, out_dir, force: bool = False) -> list[Path]:
    """Write ``ptc.png``, ``prnu_hist.png``, ``prnu_map.png`` and ``dark_current.png`` (when
    the data exist) into ``out_dir``; return the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = calib.provenance.get("calibration", {})
    p = calib.params
    written = []

    ptc = info.get("ptc")
    if ptc and ptc.get("means"):
        x = np.asarray(ptc["means"], float)
        y = np.asarray(ptc["variances"], float)
        used = np.asarray(ptc.get("used", [True] * len(x)), bool)
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        ax.plot(x[~used], y[~used], "o", mfc="none", color="0.5", label="not fitted")
        ax.plot(x[used], y[used], "o", color="C0", label="fitted (0-70 % of saturation)")
        xx = np.linspace(0, max(x.max(), 1), 100)
        ax.plot(xx, p.g * xx, "-", color="C3",
                label=f"g = {p.g:.4g} ± {calib.stderr.get('g', float('nan')):.2g} DN/e⁻")
        ax.set_xlabel("mean above dark μ_y − μ_y.dark (DN)")
        ax.set_ylabel("temporal variance above dark (DN²)")
        ax.set_title("Photon transfer")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        written.append(_save(fig, out / "ptc.png", force))
        plt.close(fig)

    if calib.prnu is not None:
        a = calib.prnu
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        ax.hist(a.ravel(), bins=200, color="C0", log=True)
        ax.set_xlabel("per-photosite gain a_j (Eq. 14)")
        ax.set_ylabel("photosites")
        ax.set_title(f"PRNU: std {np.std(a) * 100:.3f} % (estimate noise included)")
        fig.tight_layout()
        written.append(_save(fig, out / "prnu_hist.png", force))
        plt.close(fig)
        fig, ax = plt.subplots(figsize=(6.4, 5.0))
        lo, hi = np.percentile(a, [0.5, 99.5])
        im = ax.imshow(a, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        fig.colorbar(im, ax=ax, label="a_j")
        ax.set_title("PRNU map")
        fig.tight_layout()
        written.append(_save(fig, out / "prnu_map.png", force))
        plt.close(fig)

    ds = info.get("dark_series")
    if ds and len(ds.get("times", [])) >= 2:
        t = np.asarray(ds["times"], float)
        lv = np.asarray(ds["levels"], float)
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        ax.plot(t, lv, "o", color="C0", label="master-dark level")
        fit = info.get("dark_fit") or {}
        if "slope_DN_per_s" in fit and np.isfinite(fit["slope_DN_per_s"]):
            b0 = fit.get("intercept_DN")
            if b0 is None:
                b0 = float(np.mean(lv - fit["slope_DN_per_s"] * t))
            tt = np.linspace(0, t.max(), 50)
            ax.plot(tt, b0 + fit["slope_DN_per_s"] * tt, "-", color="C3",
                    label=f"D = {p.dark_current:.3g} e⁻/s")
        ax.set_xlabel("exposure time (s)")
        ax.set_ylabel("mean dark value (DN)")
        ax.set_title("Dark current")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        written.append(_save(fig, out / "dark_current.png", force))
        plt.close(fig)
    return written
