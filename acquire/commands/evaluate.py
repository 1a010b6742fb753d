"""``hdrcap evaluate``: the paper's Sec. 7 on the simulated cameras (Table 2).

This module holds the Monte-Carlo driver (it draws frames from :mod:`mock_camera`, so it lives
on the ``acquire`` side of the import rule) and the command that writes the plots and one JSON
file with every number. The statistics are the pure functions of :mod:`pipeline.evaluation`.

Setting (the paper's ground-truth experiment, simulated): a horizontal logarithmic gradient
over ``decades`` (4) decades, ``n_exp`` (6) exposures spaced by a factor ``ratio`` (4, two
stops) up to 1 s, the brightest point at ``fill`` (80 %) of the usable range in the shortest
exposure, one matched dark frame per exposure, and a perfect calibration (nominal parameters,
the sensor's true PRNU and dark-current maps; v_sat 5 sigma_R below the saturated output,
see :func:`evaluation_params`).
Every row of the gradient is an independent sample of the same irradiances; ``reps``
repetitions multiply the samples. All methods merge the very same frames.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import click
import numpy as np

from hdrcap.pipeline.errors import HdrcapError, InputError

__all__ = ["EvalSetup", "evaluation_params", "make_setup", "TEN_X_READOUT", "ZERO_READOUT", "simulate_bracket_arrays", "merge_method", "snr_experiment",
           "qq_experiment", "run_evaluation", "BASELINES", "CURVES", "OPTIMAL_OPTIONS", "command"]

#: The Table 1 baselines, in the paper's order.
BASELINES = ("uniform", "mann-picard", "debevec-malik", "mitsunaga-nayar", "reinhard", "robertson", "tsin",
             "kirk-andersen")
#: Curves of the SNR plots: the baselines, Eq. 13 at the observed value (one pass), and the
#: maximum-likelihood merge of pipeline.merge ("optimal").
CURVES = BASELINES + ("optimal@observed", "optimal-defaults", "optimal")

#: Options of the ML merge for the ``optimal`` curve: Eq. 11 threshold only. The evaluation's
#: v_sat already lies 5 sigma_R below the saturated output (:func:`evaluation_params`), so the
#: merge's extra near-saturation rule (drop samples predicted within 3 sigma of v_sat) is off;
#: ``optimal-defaults`` shows the merge with its defaults (rule on) for comparison.
OPTIMAL_OPTIONS = {"saturation_sigmas": 0.0}


def TEN_X_READOUT(spec):
    """``spec`` with 10x the readout noise sigma_R (Fig. 5b) and the bias raised to 6 sigma_R so
    that dark values are not clipped at 0 DN (clipping would hide variance from every method)."""
    s2 = 100.0 * spec.sigma2_R
    return spec.replace(sigma2_R=s2, mu_R=max(spec.mu_R, round(6.0 * np.sqrt(s2))))


def ZERO_READOUT(spec):
    """``spec`` with no electronic readout noise (quantisation only, 1/12 DN^2) and no dark
    current (Fig. 5a, Appendix A)."""
    return spec.replace(sigma2_R=1.0 / 12.0, dark_current=0.0)


@dataclass(frozen=True)
class EvalSetup:
    """One simulated experiment.

    Attributes
    ----------
    spec : mock_camera.SensorSpec
        Sensor physics.
    times : tuple of float
        Exposure times, s, increasing.
    scene : numpy.ndarray
        True irradiance, e-/s (rows: independent samples of the same gradient).
    calibration : pipeline.params.Calibration
        The (perfect) calibration the merges use.
    sensor : mock_camera.SimulatedSensor
        The sensor instance (fixed patterns drawn from the seed).
    """

    spec: object
    times: tuple
    scene: np.ndarray
    calibration: object
    sensor: object


def evaluation_params(spec):
    """Nominal parameters with v_sat = (mean saturated output) - 5 sigma_R.

    Table 2's v_sat is the saturation frame's mean - 3 std (Sec. 6); at that margin 0.1 % of
    full-well-clipped samples still slip under v_sat (camera-A), and each is a gross error that
    no weighting can undo, which would hide the differences between weightings. The ML merge
    rejects them by its predicted-saturation rule; the baselines have none. With 5 sigma_R the
    slip rate is 3e-7 and every method sees the same clean set of usable samples.
    """
    p = spec.nominal_params()
    return p.replace(v_sat=float(min(p.v_sat, spec.v_saturation - 5.0 * np.sqrt(p.sigma2_R))))


def make_setup(spec, shape=(64, 256), seed: int = 0, decades: float = 4.0, n_exp: int = 6, ratio: float = 4.0,
               t_max: float = 1.0, fill: float = 0.8, params=None) -> EvalSetup:
    """Build the experiment of the module docstring for sensor ``spec``; ``params`` (a
    :class:`pipeline.params.SensorParams`) replaces :func:`evaluation_params` when given."""
    from hdrcap.mock_camera import SimulatedSensor
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.pipeline.params import Calibration

    p = evaluation_params(spec) if params is None else params
    times = tuple(float(t_max / ratio ** (n_exp - 1 - k)) for k in range(n_exp))
    x_max = fill * (p.v_sat - p.mu_R) / (p.g * times[0])
    scene = make_scene("gradient", shape, decades=decades, x_max=x_max)
    sensor = SimulatedSensor(spec, shape, seed=seed)
    calib = Calibration(params=p, prnu=sensor.prnu.astype(np.float32),
                        dark_current_map=sensor.dark_current_map().astype(np.float32),
                        provenance={"source": f"perfect calibration of simulated {spec.name}"})
    return EvalSetup(spec=spec, times=times, scene=scene, calibration=calib, sensor=sensor)


def simulate_bracket_arrays(setup: EvalSetup, rng: np.random.Generator):
    """One bracket: ``(frames, darks)``, lists of uint16 arrays, one per exposure time."""
    s = setup.sensor
    frames = [s.expose(setup.scene, t, rng=rng) for t in setup.times]
    darks = [s.expose(setup.scene, t, dark=True, rng=rng) for t in setup.times]
    return frames, darks


def merge_method(name: str, frames, darks, times, calibration, **options):
    """Merge with curve ``name`` of :data:`CURVES`; returns a :class:`pipeline.merge.MergeResult`.

    ``optimal`` is the maximum-likelihood merge (:func:`pipeline.merge.merge_arrays` with
    ``options``; before it exists, the skeleton :func:`pipeline.merge.merge_frames`);
    ``optimal-defaults`` the same merge with its default options.
    ``optimal@observed`` is the registry's Eq. 13 at the observed value (one pass).
    """
    from hdrcap.pipeline import merge as merge_mod
    from hdrcap.pipeline.weighting import merge_weighted

    if name == "optimal-defaults":
        name, options = "optimal", {}
    if name == "optimal":
        if hasattr(merge_mod, "merge_arrays"):
            return merge_mod.merge_arrays(frames, list(times), calibration, darks=darks, **options)
        from hdrcap.pipeline.io import RawFrame

        fr = [RawFrame(data=np.asarray(f), exposure_time=t) for f, t in zip(frames, times)]
        dk = [RawFrame(data=np.asarray(d), exposure_time=t) for d, t in zip(darks, times)] if darks else None
        try:
            return merge_mod.merge_frames(fr, calibration, dk)
        except InputError:  # the skeleton refuses identical dark frames (zero read noise)
            return merge_mod.merge_frames(fr, calibration, None)
    method = "optimal" if name == "optimal@observed" else name
    return merge_weighted(frames, times, calibration, darks, method=method)


def snr_experiment(setup: EvalSetup, reps: int = 4, seed: int = 0, curves: Sequence[str] = CURVES,
                   n_bins: int = 24, keep: bool = False, options: dict | None = None) -> dict:
    """Monte-Carlo SNR of every curve against the truth and the bound, per irradiance bin.

    Returns a dict with the setting, ``bins`` (edges), ``bound_snr_db`` per bin, and per curve
    the :func:`pipeline.evaluation.snr_per_bin` results, the paired comparison against
    ``optimal`` (:func:`pipeline.evaluation.paired_difference`) and the merge time (s per
    megapixel). ``keep=True`` adds the stacked estimates under ``"estimates"`` (not JSON).
    """
    from hdrcap.pipeline.evaluation import bound_variance, log_bins, paired_difference, snr_per_bin

    calib = setup.calibration
    p = calib.params
    truth = setup.scene
    est = {c: [] for c in curves}
    seconds = {c: 0.0 for c in curves}
    for r in range(reps):
        rng = np.random.default_rng([seed, 1000 + r])
        frames, darks = simulate_bracket_arrays(setup, rng)
        for c in curves:
            t0 = time.perf_counter()
            opts = dict(OPTIMAL_OPTIONS if options is None else options)
            res = merge_method(c, frames, darks, setup.times, calib, **opts)
            seconds[c] += time.perf_counter() - t0
            est[c].append(np.asarray(res.irradiance, dtype=np.float64))
    stacks = {c: np.stack(v) for c, v in est.items()}
    edges = log_bins(truth, n_bins)
    bound = bound_variance(truth, setup.times, p, a=calib.prnu, D=calib.dark_current_map, dark="matched")
    valid = np.isfinite(bound)
    mp = truth.size * reps / 1e6
    out = {
        "camera": setup.spec.name,
        "g": p.g, "sigma2_R": p.sigma2_R, "v_sat": p.v_sat, "mu_R": p.mu_R, "dark_current": p.dark_current,
        "exposure_times": list(setup.times),
        "irradiance_range": [float(truth.min()), float(truth.max())],
        "shape": list(truth.shape), "reps": reps, "seed": seed,
        "samples_per_bin": None,
        "bins": edges.tolist(),
        "curves": {},
    }
    for c in curves:
        res = snr_per_bin(stacks[c], truth, edges, bound=bound, valid=valid)
        if "optimal" in stacks and c != "optimal":
            res["vs_optimal"] = paired_difference(stacks[c], stacks["optimal"], truth, edges, valid=valid)
        res["seconds_per_megapixel"] = seconds[c] / mp
        out["curves"][c] = res
    first = out["curves"][curves[0]]
    out["center"] = first["center"]
    out["samples_per_bin"] = first["n"]
    out["bound_snr_db"] = first.get("bound_snr_db")
    if keep:
        out["estimates"] = stacks
        out["truth"] = truth
        out["bound"] = bound
    return out


def qq_experiment(spec, n_frames: int = 36, n_pixels: int = 400, seed: int = 0, levels_e=None) -> dict:
    """Normal Q-Q data of raw outputs at three levels (Fig. 6) and Shapiro-Wilk rejection rates.

    A flat field is exposed ``n_frames`` times; each photosite's ``n_frames`` outputs form one
    sample. Levels (mean collected electrons): right above the noise floor (where the signal
    equals the readout noise, at least 3 e-), mid range, and right before saturation (4 output
    standard deviations below v_sat). Per level: the Q-Q data of the first photosite and the
    rejection rate over ``n_pixels`` photosites (:func:`pipeline.evaluation.gaussianity`).
    """
    from hdrcap.mock_camera import SimulatedSensor
    from hdrcap.pipeline.evaluation import gaussianity, qq_data

    p = spec.nominal_params()
    sigma_r_e = np.sqrt(p.sigma2_R) / p.g
    e_max = (p.v_sat - p.mu_R) / p.g
    if levels_e is None:
        e_floor = max(3.0, sigma_r_e)
        e_high = e_max
        for _ in range(20):  # solve g E + 4 sqrt(g^2 E + sigma2_R) = v_sat - mu_R
            e_high = e_max - 4.0 * np.sqrt(p.g**2 * e_high + p.sigma2_R) / p.g
        levels_e = {"noise_floor": e_floor, "mid_range": 0.5 * e_max, "near_saturation": e_high}
    spec0 = spec.replace(dark_current=0.0, prnu=0.0)
    sensor = SimulatedSensor(spec0, (1, n_pixels), seed=seed)
    out = {"camera": spec.name, "sigma2_R": p.sigma2_R, "g": p.g, "n_frames": n_frames, "levels": {}}
    t = 1.0
    for k, (name, e) in enumerate(levels_e.items()):
        rng = np.random.default_rng([seed, 77, k])
        s = np.stack([sensor.expose(e / t, t, rng=rng)[0].astype(np.float64) for _ in range(n_frames)], axis=1)
        out["levels"][name] = {"electrons": float(e), "mean_dn": float(s.mean()),
                               "qq": qq_data(s[0]), "test": gaussianity(s)}
    return out


# ---------------------------------------------------------------------------------------- plots


_STYLE = {
    "uniform": ("tab:gray", ":"), "mann-picard": ("tab:brown", "--"), "debevec-malik": ("tab:orange", "-"),
    "mitsunaga-nayar": ("tab:green", "-"), "reinhard": ("tab:olive", "--"), "robertson": ("tab:purple", "-"),
    "tsin": ("tab:pink", "-"), "kirk-andersen": ("tab:cyan", "-"), "optimal@observed": ("tab:blue", ":"),
    "optimal-defaults": ("tab:red", ":"),
    "optimal": ("tab:red", "-"),
}


def _plot_snr(ax, res, title, key="snr_db"):
    c = np.asarray(res["center"])
    for name, r in res["curves"].items():
        y = np.array([np.nan if v is None else v for v in r[key]], dtype=float)
        color, ls = _STYLE.get(name, ("k", "-"))
        ax.plot(c, y, color=color, ls=ls, lw=1.6 if name == "optimal" else 1.1, label=name)
    if key == "snr_db" and res.get("bound_snr_db"):
        b = np.array([np.nan if v is None else v for v in res["bound_snr_db"]], dtype=float)
        ax.plot(c, b, color="k", lw=2.2, alpha=0.35, label="bound 1/Σw")
    ax.set_xscale("log")
    ax.set_xlabel("irradiance X (e⁻/s)")
    ax.set_ylabel("SNR (dB)" if key == "snr_db" else "efficiency = bound / MSE")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.25)


def _save(fig, path: Path, force: bool):
    from hdrcap.pipeline.io import atomic_output

    with atomic_output(path, force=force) as tmp:
        fig.savefig(tmp, dpi=72, format="png")


def write_plots(results: dict, out: Path, force: bool) -> list[str]:
    """Write the PNG plots of :func:`run_evaluation`'s results; returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    snr = results["snr"]
    for fname, keys, titles, key in (
        ("fig4_snr.png", ("camera-A", "camera-B"), ("(a) camera-A", "(b) camera-B"), "snr_db"),
        ("fig5_readout.png", ("camera-B zero readout", "camera-B 10x readout"),
         ("(a) camera-B, zero readout noise, D = 0", "(b) camera-B, 10x readout noise σ_R"), "snr_db"),
        ("efficiency.png", ("camera-A", "camera-B"), ("(a) camera-A", "(b) camera-B"), "efficiency"),
    ):
        keys = [k for k in keys if k in snr]
        if not keys:
            continue
        fig, axes = plt.subplots(1, len(keys), figsize=(5.2 * len(keys), 3.8), squeeze=False)
        for ax, k, tt in zip(axes[0], keys, titles):
            _plot_snr(ax, snr[k], tt, key)
            if key == "efficiency":
                ax.set_ylim(0, 1.1)
        axes[0][-1].legend(fontsize=6.5, loc="lower right" if key == "snr_db" else "lower left", ncol=2)
        fig.tight_layout()
        _save(fig, out / fname, force)
        plt.close(fig)
        written.append(fname)

    wv = results.get("weights_vs_output")
    if wv:
        fig, axes = plt.subplots(1, len(wv), figsize=(4.2 * len(wv), 3.5), squeeze=False)
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
        _save(fig, out / "fig2_weights.png", force)
        plt.close(fig)
        written.append("fig2_weights.png")

    qq = results.get("qq")
    if qq:
        rows = list(qq.items())
        fig, axes = plt.subplots(len(rows), 3, figsize=(9.5, 3.0 * len(rows)), squeeze=False)
        for i, (label, d) in enumerate(rows):
            for ax, (lname, lv) in zip(axes[i], d["levels"].items()):
                q = lv["qq"]
                ax.plot(q["theoretical"], q["ordered"], "o", ms=3)
                lim = [min(q["theoretical"]), max(q["theoretical"])]
                ax.plot(lim, lim, "k-", lw=0.8)
                ax.set_title(f"{label}: {lname.replace('_', ' ')}\n{lv['electrons']:.3g} e⁻, "
                             f"r = {q['r']:.3f}, reject {lv['test']['rejection_rate']:.0%}", fontsize=8)
                ax.set_xlabel("normal quantile", fontsize=8)
                ax.set_ylabel("standardised sample", fontsize=8)
        fig.tight_layout()
        _save(fig, out / "fig6_qq.png", force)
        plt.close(fig)
        written.append("fig6_qq.png")
    return written


# ------------------------------------------------------------------------------------ the run


def run_evaluation(out: Path | None = None, quick: bool = False, seed: int = 0, force: bool = False,
                   progress=None) -> dict:
    """Run Sec. 7 on camera-A and camera-B; with ``out``, write ``evaluation.json`` and PNGs."""
    from hdrcap.mock_camera import PRESETS
    from hdrcap.pipeline.evaluation import weights_vs_output

    say = progress or (lambda msg: None)
    shape = (32, 192) if quick else (64, 768)
    reps = 2 if quick else 6
    n_bins = 16 if quick else 40
    base_b = PRESETS["camera-B"]
    cases = {
        "camera-A": PRESETS["camera-A"],
        "camera-B": base_b,
        "camera-B zero readout": ZERO_READOUT(base_b),
        "camera-B 10x readout": TEN_X_READOUT(base_b),
    }
    results: dict = {"seed": seed, "quick": quick, "snr": {}, "notes": {
        "snr_db": "-10 log10(mean ((estimate - X)/X)^2) over the photosites and repetitions of each bin",
        "efficiency": "mean(bound/X^2) / mean(((estimate - X)/X)^2); bound = 1/sum_i w_i(X), Eq. 12-13",
        "optimal": "maximum-likelihood merge of pipeline.merge (iterative Eq. 12-13), options " + json.dumps(OPTIMAL_OPTIONS),
        "optimal-defaults": "the same merge with its default options (near-saturation rule 3 sigma on)",
        "optimal@observed": "Eq. 13 evaluated at each sample's observed value, one pass",
        "zero readout": "sigma2_R = 1/12 DN^2 (quantisation only), no dark current",
        "10x readout": "sigma_R x 10 (sigma2_R x 100), bias raised to 6 sigma_R so that no value clips at 0",
    }}
    t_start = time.perf_counter()
    for label, spec in cases.items():
        say(f"SNR experiment: {label}")
        setup = make_setup(spec, shape=shape, seed=seed)
        results["snr"][label] = snr_experiment(setup, reps=reps, seed=seed, n_bins=n_bins)
    say("weights against output value (Fig. 2)")
    wv = {}
    for label in ("camera-B", "camera-B zero readout", "camera-B 10x readout"):
        p = evaluation_params(cases[label])
        wv[label] = weights_vs_output(p, X=1000.0)
    results["weights_vs_output"] = wv
    say("Gaussian check (Fig. 6)")
    results["qq"] = {"camera-B": qq_experiment(base_b, seed=seed, n_pixels=200 if quick else 400),
                     "camera-B zero readout": qq_experiment(cases["camera-B zero readout"], seed=seed,
                                                            n_pixels=200 if quick else 400)}
    results["summary"] = summarise(results)
    results["seconds"] = round(time.perf_counter() - t_start, 2)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        from hdrcap.pipeline.io import atomic_output

        results["plots"] = write_plots(results, out, force)
        with atomic_output(out / "evaluation.json", force=force) as tmp:
            tmp.write_text(json.dumps(results, indent=1, sort_keys=True))
    return results


def summarise(results: dict) -> dict:
    """Per case and curve: mean and minimum efficiency over bins, mean SNR loss to optimal (dB)."""
    summ = {}
    for label, res in results["snr"].items():
        opt = res["curves"].get("optimal")
        rows = {}
        for name, r in res["curves"].items():
            eff = [e for e in r["efficiency"] if e is not None]
            row = {"mean_efficiency": float(np.mean(eff)) if eff else None,
                   "min_efficiency": float(np.min(eff)) if eff else None}
            if opt is not None:
                d = [a - b for a, b in zip(r["snr_db"], opt["snr_db"]) if a is not None and b is not None]
                row["mean_snr_minus_optimal_db"] = float(np.mean(d)) if d else None
                row["min_snr_minus_optimal_db"] = float(np.min(d)) if d else None
            rows[name] = row
        summ[label] = rows
    return summ


def _print_summary(results: dict) -> None:
    for label, rows in results["summary"].items():
        click.echo(f"{label}: mean efficiency (bound/MSE) and mean SNR - optimal (dB) per method")
        for name, row in rows.items():
            d = row.get("mean_snr_minus_optimal_db")
            click.echo(f"  {name:18s} eff {row['mean_efficiency']:.3f} (min {row['min_efficiency']:.3f})"
                       + (f"  {d:+.2f} dB" if d is not None else ""))
    for label, d in results["qq"].items():
        rates = ", ".join(f"{k} {v['test']['rejection_rate']:.0%}" for k, v in d["levels"].items())
        click.echo(f"Gaussian check {label}: Shapiro-Wilk rejection at 5 %: {rates}")


@click.command("evaluate", short_help="Reproduce the paper's Sec. 7 evaluation: SNR per weighting vs the bound, Q-Q, efficiency.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder for evaluation.json and the PNG plots.")
@click.option("--quick", is_flag=True, help="Smaller images and fewer repetitions (about 4x faster).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--denoise", is_flag=True, help="Also run pipeline.denoise.evaluate_denoising (Sec. 9).")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one line of JSON.")
def command(out, quick, seed, denoise, force, as_json):
    """Reproduce the paper's evaluation (Sec. 7) on simulated camera-A and camera-B.

    Writes evaluation.json (every number) and fig2_weights.png, fig4_snr.png,
    fig5_readout.png, fig6_qq.png and efficiency.png into OUT: SNR against irradiance of
    every Table 1 weighting and of the maximum-likelihood merge with the Cramér-Rao bound,
    the zero and 10x readout-noise cases, weights against output value, normal Q-Q plots
    and the efficiency (bound / MSE) per irradiance bin.
    """
    from hdrcap.acquire.cliutil import echo_json

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if not force:
        for name in ("evaluation.json", "fig4_snr.png"):
            if (out / name).exists():
                raise InputError(f"{out / name}: exists; use --force to overwrite")
    evaluate_denoising = None
    if denoise:
        try:
            from hdrcap.pipeline.denoise import evaluate_denoising
        except ImportError as err:
            raise HdrcapError(f"--denoise needs pipeline.denoise.evaluate_denoising, which is not available ({err})")
    say = None if as_json else (lambda msg: click.echo(msg, err=True))
    results = run_evaluation(out, quick=quick, seed=seed, force=force, progress=say)
    summary = {"out": str(out), "plots": results["plots"], "seconds": results["seconds"],
               "summary": results["summary"]}
    if evaluate_denoising is not None:
        summary["denoise"] = evaluate_denoising(out, seed=seed, quick=quick)
    if as_json:
        echo_json(summary)
    else:
        _print_summary(results)
        click.echo(f"wrote {out / 'evaluation.json'} and {', '.join(results['plots'])} "
                   f"in {results['seconds']:.1f} s")
