"""Figure 7 of the paper for a plan: the planned sequence over the irradiance histogram and
the predicted SNR curve (drawn with :mod:`hdrcap.pipeline.plotting`; an I/O function)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.plotting import new_figure, save_figure
from hdrcap.planner.plan import Plan
from hdrcap.planner.predict import K_SIGMA, predict_snr, usable_fraction

__all__ = ["exposure_ranges", "plot_plan"]


def exposure_ranges(
    times: Sequence[float], calibration: Calibration, x_lo: float, x_hi: float, k_sigma: float = K_SIGMA
) -> list[tuple[float, float]]:
    """Irradiance range each exposure measures: from SNR 1 (0 dB) to saturation.

    Parameters
    ----------
    times : sequence of float
        Exposure times, s.
    calibration : Calibration
        Camera model.
    x_lo, x_hi : float
        The scene's irradiance range, e-/s; the search grid extends one decade beyond it.
    k_sigma : float
        Margin of the near-saturation rule, standard deviations of the raw value.

    Returns
    -------
    list of (float, float)
        Per exposure the lowest and highest irradiance it measures, e-/s (NaN when none).
    """
    grid = np.logspace(np.log10(x_lo) - 1, np.log10(x_hi) + 1, 2000)
    out = []
    for t in times:
        ok = usable_fraction(grid, t, calibration, "threshold", k_sigma) > 0
        ok &= predict_snr(grid, [t], calibration, "model").snr >= 1.0
        out.append((float(grid[ok].min()), float(grid[ok].max())) if ok.any() else (np.nan, np.nan))
    return out


def plot_plan(
    plan: Plan, calibration: Calibration, path: str | Path, force: bool = False, title: str | None = None
) -> Path:
    """Write the plan's figure (Fig. 7) as PNG.

    (a) The irradiance histogram with the planned exposures' ranges in capture order, (b) the
    predicted SNR against irradiance with the target.

    Parameters
    ----------
    plan : Plan
        The plan (its ``curve`` holds the histogram and the predicted SNR).
    calibration : Calibration
        Camera model the plan was made for.
    path : str or Path
        Output PNG.
    force : bool
        Replace an existing file.
    title : str, optional
        Title of panel (a) (default: the sequence's length and total time).

    Returns
    -------
    Path
        ``path``.
    """
    X = np.asarray(plan.curve.get("irradiance", []), dtype=np.float64)
    w = np.asarray(plan.curve.get("weight", []), dtype=np.float64)
    snr = np.array([np.nan if v is None else v for v in plan.curve.get("snr_db", [])], dtype=np.float64)
    elig = np.asarray(plan.curve.get("eligible", []), dtype=bool)
    fig, (ax1, ax2) = new_figure(2, 1, figsize=(8, 7), sharex=True, gridspec_kw={"height_ratios": [1.2, 1]})
    if X.size:
        edges = np.logspace(np.log10(X.min()) - 0.01, np.log10(X.max()) + 0.01, 65)
        ax1.hist(X, bins=edges, weights=w, color="0.75", label="pixels")
        ax1.set_yscale("log")
        ax1.set_ylabel("pixels per bin")
        ymax = max(w.sum(), 1.0)
        ranges = exposure_ranges(plan.exposures, calibration, X.min(), X.max())
        n = max(len(plan.exposures), 1)
        for i, ((lo, hi), t, d) in enumerate(zip(ranges, plan.exposures, plan.darks)):
            y = ymax ** (0.15 + 0.8 * (i + 0.5) / n)
            col = {"matched": "tab:red", "master": "tab:purple"}.get(d, "tab:blue")
            ax1.plot([lo, hi], [y, y], color=col, lw=3, solid_capstyle="butt")
            label = f"1/{1 / t:.0f}" if t < 0.25 else f"{t:g}"
            ax1.text(hi, y, f" {i + 1}: {label} s", va="center", fontsize=7)
        ax1.set_ylim(0.5, ymax**1.05 * 2)
        ax1.set_title(
            title
            or f"Planned sequence: {len(plan.exposures)} exposures, {plan.total_time_s:.4g} s "
            f"(blue: no dark frame, red: matched dark, purple: master dark)",
            fontsize=9,
        )
        order = np.argsort(X)
        ax2.plot(X[order], snr[order], color="tab:green", lw=1.2, label="predicted SNR")
        if (~elig).any():
            ax2.plot(
                X[~elig],
                np.zeros((~elig).sum()),
                "x",
                color="tab:red",
                ms=3,
                label="not eligible (saturated at the shortest time)",
            )
        ax2.axhline(plan.target_snr_db, color="k", ls="--", lw=0.8, label=f"target {plan.target_snr_db:g} dB")
        ax2.set_xscale("log")
        ax2.set_ylabel("predicted SNR, dB")
        ax2.set_xlabel("irradiance, e-/s per photosite")
        fin = snr[np.isfinite(snr)]
        if fin.size:
            ax2.set_ylim(min(fin.min(), plan.target_snr_db) - 3, max(fin.max(), plan.target_snr_db) + 3)
        ax2.legend(fontsize=8, loc="lower right")
        ax2.grid(alpha=0.3)
    state = "feasible" if plan.feasible else "INFEASIBLE"
    fig.text(0.01, 0.005, f"{state}: predicted min {plan.predicted_min_snr_db:.2f} dB", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=110)
