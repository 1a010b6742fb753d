"""Figures of the experiments: Sec. 7 (Figs. 2, 4, 5, 6 and the efficiency) and Fig. 8d.

Every figure is drawn with :func:`hdrcap.pipeline.plotting.new_figure` and written with
:func:`hdrcap.pipeline.plotting.save_figure` (atomic, never over an existing file unless
``force``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hdrcap.pipeline.denoise.filter import DEFAULT_RANGE_SCALE
from hdrcap.pipeline.plotting import new_figure, save_figure

if TYPE_CHECKING:
    from hdrcap.experiments.denoising import DenoisedScene

__all__ = ["write_plots", "plot_denoising"]

#: Colour and line style of each curve.
_STYLE = {
    "uniform": ("tab:gray", ":"),
    "mann-picard": ("tab:brown", "--"),
    "debevec-malik": ("tab:orange", "-"),
    "mitsunaga-nayar": ("tab:green", "-"),
    "reinhard": ("tab:olive", "--"),
    "robertson": ("tab:purple", "-"),
    "tsin": ("tab:pink", "-"),
    "kirk-andersen": ("tab:cyan", "-"),
    "optimal@observed": ("tab:blue", ":"),
    "optimal-defaults": ("tab:red", ":"),
    "optimal": ("tab:red", "-"),
}

#: The SNR figures: file name, cases, panel titles, the per-bin figure plotted.
_SNR_FIGURES = (
    ("fig4_snr.png", ("camera-A", "camera-B"), ("(a) camera-A", "(b) camera-B"), "snr_db"),
    (
        "fig5_readout.png",
        ("camera-B zero readout", "camera-B 10x readout"),
        ("(a) camera-B, zero readout noise, D = 0", "(b) camera-B, 10x readout noise σ_R"),
        "snr_db",
    ),
    ("efficiency.png", ("camera-A", "camera-B"), ("(a) camera-A", "(b) camera-B"), "efficiency"),
)

_DPI = 72


def _values(seq) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in seq], dtype=float)


def _plot_snr(ax, res: dict, title: str, key: str = "snr_db") -> None:
    """One panel: ``key`` per irradiance bin of every curve (and the bound for the SNR)."""
    c = np.asarray(res["center"])
    for name, r in res["curves"].items():
        color, ls = _STYLE.get(name, ("k", "-"))
        ax.plot(c, _values(r[key]), color=color, ls=ls, lw=1.6 if name == "optimal" else 1.1, label=name)
    if key == "snr_db" and res.get("bound_snr_db"):
        ax.plot(c, _values(res["bound_snr_db"]), color="k", lw=2.2, alpha=0.35, label="bound 1/Σw")
    ax.set_xscale("log")
    ax.set_xlabel("irradiance X (e⁻/s)")
    ax.set_ylabel("SNR (dB)" if key == "snr_db" else "efficiency = bound / MSE")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.25)


def _snr_figures(snr: dict, out: Path, force: bool) -> list[str]:
    written = []
    for fname, keys, titles, key in _SNR_FIGURES:
        present = [k for k in keys if k in snr]
        if not present:
            continue
        fig, axes = new_figure(1, len(present), figsize=(5.2 * len(present), 3.8), squeeze=False)
        for ax, k, tt in zip(axes[0], present, titles):
            _plot_snr(ax, snr[k], tt, key)
            if key == "efficiency":
                ax.set_ylim(0, 1.1)
        axes[0][-1].legend(fontsize=6.5, loc="lower right" if key == "snr_db" else "lower left", ncol=2)
        fig.tight_layout()
        save_figure(fig, out / fname, force, dpi=_DPI)
        written.append(fname)
    return written


def _weights_figure(wv: dict, path: Path, force: bool) -> None:
    """Fig. 2: the weight of each method against the output value at constant irradiance."""
    fig, axes = new_figure(1, len(wv), figsize=(4.2 * len(wv), 3.5), squeeze=False)
    for ax, (label, d) in zip(axes[0], wv.items()):
        for name, w in d["weights"].items():
            color, ls = _STYLE.get(name, ("k", "-"))
            ax.plot(d["v"], w, color=color, ls=ls, lw=1.6 if name == "optimal" else 1.0, label=name)
        ax.set_title(f"{label} (σ_R² = {d['sigma2_R']:.3g} DN²)", fontsize=9)
        ax.set_xlabel("output value v − μ_R (DN)")
        ax.set_ylabel("weight (normalised)")
        ax.grid(True, alpha=0.25)
    axes[0][-1].legend(fontsize=6.5, ncol=2)
    fig.tight_layout()
    save_figure(fig, path, force, dpi=_DPI)


def _qq_figure(qq: dict, path: Path, force: bool) -> None:
    """Fig. 6: normal Q-Q plots of the raw outputs, one row per case, one column per level."""
    rows = list(qq.items())
    fig, axes = new_figure(len(rows), 3, figsize=(9.5, 3.0 * len(rows)), squeeze=False)
    for i, (label, d) in enumerate(rows):
        for ax, (lname, lv) in zip(axes[i], d["levels"].items()):
            q = lv["qq"]
            ax.plot(q["theoretical"], q["ordered"], "o", ms=3)
            lim = [min(q["theoretical"]), max(q["theoretical"])]
            ax.plot(lim, lim, "k-", lw=0.8)
            ax.set_title(
                f"{label}: {lname.replace('_', ' ')}\n{lv['electrons']:.3g} e⁻, "
                f"r = {q['r']:.3f}, reject {lv['test']['rejection_rate']:.0%}",
                fontsize=8,
            )
            ax.set_xlabel("normal quantile", fontsize=8)
            ax.set_ylabel("standardised sample", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, force, dpi=_DPI)


def write_plots(results: dict, out: Path, force: bool) -> list[str]:
    """Write the PNG plots of :func:`hdrcap.experiments.snr.run_evaluation`'s results.

    Parameters
    ----------
    results : dict
        The evaluation's results (``snr``, optional ``weights_vs_output`` and ``qq``).
    out : Path
        Existing output folder.
    force : bool
        Replace existing files.

    Returns
    -------
    list of str
        The names of the written files, in ``out``.
    """
    out = Path(out)
    written = _snr_figures(results["snr"], out, force)
    if results.get("weights_vs_output"):
        _weights_figure(results["weights_vs_output"], out / "fig2_weights.png", force)
        written.append("fig2_weights.png")
    if results.get("qq"):
        _qq_figure(results["qq"], out / "fig6_qq.png", force)
        written.append("fig6_qq.png")
    return written


def plot_denoising(path: Path, scenes: dict[str, DenoisedScene]) -> Path:
    """Fig. 8d: per scene the truth, the best constant-bandwidth and the adaptive result, and the
    normalised MSE against the range bandwidth. An existing file is replaced.

    Parameters
    ----------
    path : Path
        Output PNG.
    scenes : dict
        Scene name -> its filtered images and errors.

    Returns
    -------
    Path
        ``path``.
    """
    from matplotlib.colors import LogNorm

    n = len(scenes)
    fig, axes = new_figure(n, 4, figsize=(17, 3.8 * n), squeeze=False, gridspec_kw={"width_ratios": [1, 1, 1.12, 1.15]})
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.06, top=0.95, wspace=0.45, hspace=0.3)
    for row, (name, sc) in enumerate(scenes.items()):
        lo, hi = float(sc.truth.min()), float(sc.truth.max())
        norm = LogNorm(vmin=lo, vmax=hi)
        for ax, img, title in (
            (axes[row, 0], sc.truth, f"{name}: ground truth (e-/s)"),
            (axes[row, 1], sc.best_constant, f"best constant B={sc.best_bandwidth:.3g}: NMSE {sc.nmse_best:.3g}"),
            (axes[row, 2], sc.adaptive, f"adaptive K={DEFAULT_RANGE_SCALE:g}: NMSE {sc.nmse_adaptive:.3g}"),
        ):
            im = ax.imshow(np.clip(img, lo, hi), cmap="jet", norm=norm, interpolation="nearest")
            ax.set_title(title, fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
        fig.colorbar(im, ax=axes[row, 2], fraction=0.05, pad=0.02)
        ax = axes[row, 3]
        ax.loglog(sc.bandwidths, sc.nmse_constant, "o-", ms=3, label="constant bandwidth")
        ax.axhline(sc.nmse_adaptive, color="C3", label=f"adaptive (K={DEFAULT_RANGE_SCALE:g})")
        ax.axhline(sc.nmse_unfiltered, color="0.5", ls="--", label="unfiltered merge")
        ax.set_xlabel("range bandwidth B (e-/s)")
        ax.set_ylabel("normalised MSE")
        role = "Fig. 8d" if sc.claim else "control: no edges"
        ax.set_title(f"{name}: NMSE vs bandwidth ({role})", fontsize=9)
        ax.legend(fontsize=7)
    return save_figure(fig, path, force=True, dpi=80)
