"""The paper's Sec. 7 on the simulated cameras (Table 2): SNR of every weighting against the bound.

Setting (the paper's ground-truth experiment, simulated): a horizontal logarithmic gradient
over ``decades`` (4) decades, ``n_exp`` (6) exposures spaced by a factor ``ratio`` (4, two
stops) up to 1 s, the brightest point at ``fill`` (80 %) of the usable range in the shortest
exposure, one matched dark frame per exposure, and a perfect calibration (nominal parameters,
the sensor's true PRNU and dark-current maps; v_sat 5 sigma_R below the saturated output,
see :func:`evaluation_params`).
Every row of the gradient is an independent sample of the same irradiances; ``reps``
repetitions multiply the samples. All methods merge the very same frames.

The frames come from :mod:`hdrcap.mock_camera`; the statistics are the pure functions of
:mod:`hdrcap.pipeline.evaluation`; the figures are drawn by :mod:`hdrcap.experiments.figures`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.mock_camera import PRESETS, SensorSpec, SimulatedSensor
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.evaluation import (
    bound_variance,
    gaussianity,
    log_bins,
    paired_difference,
    qq_data,
    snr_per_bin,
    weights_vs_output,
)
from hdrcap.pipeline.io.files import atomic_output
from hdrcap.pipeline.merge.accumulator import merge_arrays
from hdrcap.pipeline.merge.weighting import merge_weighted
from hdrcap.pipeline.params import Calibration, SensorParams
from hdrcap.pipeline.result import HdrResult

__all__ = [
    "EvalSetup",
    "evaluation_params",
    "make_setup",
    "TEN_X_READOUT",
    "ZERO_READOUT",
    "simulate_bracket_arrays",
    "merge_method",
    "snr_experiment",
    "qq_experiment",
    "evaluation_cases",
    "run_evaluation",
    "summarise",
    "BASELINES",
    "CURVES",
    "OPTIMAL_OPTIONS",
]

#: The Table 1 baselines, in the paper's order.
BASELINES = (
    "uniform",
    "mann-picard",
    "debevec-malik",
    "mitsunaga-nayar",
    "reinhard",
    "robertson",
    "tsin",
    "kirk-andersen",
)
#: Curves of the SNR plots: the baselines, Eq. 13 at the observed value (one pass), and the
#: maximum-likelihood merge of pipeline.merge.accumulator ("optimal").
CURVES = BASELINES + ("optimal@observed", "optimal-defaults", "optimal")

#: Options of the ML merge for the ``optimal`` curve: Eq. 11 threshold only. The evaluation's
#: v_sat already lies 5 sigma_R below the saturated output (:func:`evaluation_params`), so the
#: merge's extra near-saturation rule (drop samples predicted within 3 sigma of v_sat) is off;
#: ``optimal-defaults`` shows the merge with its defaults (rule on) for comparison.
OPTIMAL_OPTIONS = {"saturation_sigmas": 0.0}

#: What each figure of ``evaluation.json`` means (written into the file).
NOTES = {
    "snr_db": "-10 log10(mean ((estimate - X)/X)^2) over the photosites and repetitions of each bin",
    "efficiency": "mean(bound/X^2) / mean(((estimate - X)/X)^2); bound = 1/sum_i w_i(X), Eq. 12-13",
    "optimal": "maximum-likelihood merge of pipeline.merge.accumulator (iterative Eq. 12-13), options "
    + json.dumps(OPTIMAL_OPTIONS),
    "optimal-defaults": "the same merge with its default options (near-saturation rule 3 sigma on)",
    "optimal@observed": "Eq. 13 evaluated at each sample's observed value, one pass",
    "zero readout": "sigma2_R = 1/12 DN^2 (quantisation only), no dark current",
    "10x readout": "sigma_R x 10 (sigma2_R x 100), bias raised to 6 sigma_R so that no value clips at 0",
}


def TEN_X_READOUT(spec: SensorSpec) -> SensorSpec:  # noqa: N802 - a named variant of a sensor
    """``spec`` with 10x the readout noise sigma_R (Fig. 5b).

    The bias is raised to 6 sigma_R so that dark values are not clipped at 0 DN (clipping would
    hide variance from every method).

    Parameters
    ----------
    spec : SensorSpec
        Sensor physics.

    Returns
    -------
    SensorSpec
        The variant: sigma2_R x 100 (DN^2), mu_R >= 6 sigma_R (DN).
    """
    s2 = 100.0 * spec.sigma2_R
    return spec.replace(sigma2_R=s2, mu_R=max(spec.mu_R, round(6.0 * np.sqrt(s2))))


def ZERO_READOUT(spec: SensorSpec) -> SensorSpec:  # noqa: N802 - a named variant of a sensor
    """``spec`` with no electronic readout noise and no dark current (Fig. 5a, Appendix A).

    Parameters
    ----------
    spec : SensorSpec
        Sensor physics.

    Returns
    -------
    SensorSpec
        The variant: sigma2_R = 1/12 DN^2 (quantisation only), dark current 0 e-/s.
    """
    return spec.replace(sigma2_R=1.0 / 12.0, dark_current=0.0)


@dataclass(frozen=True)
class EvalSetup:
    """One simulated experiment.

    Attributes
    ----------
    spec : SensorSpec
        Sensor physics.
    times : tuple of float
        Exposure times, s, increasing.
    scene : numpy.ndarray
        True irradiance, e-/s (rows: independent samples of the same gradient).
    calibration : Calibration
        The (perfect) calibration the merges use.
    sensor : SimulatedSensor
        The sensor instance (fixed patterns drawn from the seed).
    """

    spec: SensorSpec
    times: tuple[float, ...]
    scene: np.ndarray
    calibration: Calibration
    sensor: SimulatedSensor


def evaluation_params(spec: SensorSpec) -> SensorParams:
    """Nominal parameters with v_sat = (mean saturated output) - 5 sigma_R.

    Table 2's v_sat is the saturation frame's mean - 3 std (Sec. 6); at that margin 0.1 % of
    full-well-clipped samples still slip under v_sat (camera-A), and each is a gross error that
    no weighting can undo, which would hide the differences between weightings. The ML merge
    rejects them by its predicted-saturation rule; the baselines have none. With 5 sigma_R the
    slip rate is 3e-7 and every method sees the same clean set of usable samples.

    Parameters
    ----------
    spec : SensorSpec
        Sensor physics.

    Returns
    -------
    SensorParams
        The nominal parameters with the lowered v_sat, DN.
    """
    p = spec.nominal_params()
    return p.replace(v_sat=float(min(p.v_sat, spec.v_saturation - 5.0 * np.sqrt(p.sigma2_R))))


def make_setup(
    spec: SensorSpec,
    shape: tuple[int, int] = (64, 256),
    seed: int = 0,
    decades: float = 4.0,
    n_exp: int = 6,
    ratio: float = 4.0,
    t_max: float = 1.0,
    fill: float = 0.8,
    params: SensorParams | None = None,
) -> EvalSetup:
    """Build the experiment of the module docstring for sensor ``spec``.

    Parameters
    ----------
    spec : SensorSpec
        Sensor physics.
    shape : (int, int)
        Image size (rows, columns), photosites; every row is one sample of the gradient.
    seed : int
        Seed of the sensor's fixed patterns.
    decades : float
        Dynamic range of the gradient, orders of magnitude.
    n_exp : int
        Number of exposures.
    ratio : float
        Factor between consecutive exposure times.
    t_max : float
        Longest exposure time, s.
    fill : float
        Brightest point as a fraction of the usable range (v_sat - mu_R) in the shortest exposure.
    params : SensorParams, optional
        Replaces :func:`evaluation_params` as the calibration's parameters.

    Returns
    -------
    EvalSetup
    """
    p = evaluation_params(spec) if params is None else params
    times = tuple(float(t_max / ratio ** (n_exp - 1 - k)) for k in range(n_exp))
    x_max = fill * (p.v_sat - p.mu_R) / (p.g * times[0])
    scene = make_scene("gradient", shape, decades=decades, x_max=x_max)
    sensor = SimulatedSensor(spec, shape, seed=seed)
    calib = Calibration(
        params=p,
        prnu=sensor.prnu.astype(np.float32),
        dark_current_map=sensor.dark_current_map().astype(np.float32),
        provenance={"source": f"perfect calibration of simulated {spec.name}"},
    )
    return EvalSetup(spec=spec, times=times, scene=scene, calibration=calib, sensor=sensor)


def simulate_bracket_arrays(setup: EvalSetup, rng: np.random.Generator) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """One bracket of ``setup`` with one matched dark frame per exposure.

    Parameters
    ----------
    setup : EvalSetup
        The experiment.
    rng : numpy.random.Generator
        Source of the noise.

    Returns
    -------
    (frames, darks) : lists of numpy.ndarray
        Raw values, uint16 DN, one per exposure time of ``setup.times``.
    """
    s = setup.sensor
    frames = [s.expose(setup.scene, t, rng=rng) for t in setup.times]
    darks = [s.expose(setup.scene, t, dark=True, rng=rng) for t in setup.times]
    return frames, darks


def merge_method(
    name: str,
    frames: Sequence[np.ndarray],
    darks: Sequence[np.ndarray] | None,
    times: Sequence[float],
    calibration: Calibration,
    **options: Any,
) -> HdrResult:
    """Merge with curve ``name`` of :data:`CURVES`.

    ``optimal`` is the maximum-likelihood merge (:func:`pipeline.merge.accumulator.merge_arrays` with
    ``options``); ``optimal-defaults`` the same merge with its default options;
    ``optimal@observed`` the registry's Eq. 13 at the observed value (one pass); the others
    the Table 1 weightings of :func:`pipeline.merge.weighting.merge_weighted`.

    Parameters
    ----------
    name : str
        A curve of :data:`CURVES`.
    frames, darks : sequences of numpy.ndarray
        Raw frames and their matched dark frames, DN.
    times : sequence of float
        Exposure times, s.
    calibration : Calibration
        Camera model.
    **options
        Options of the ML merge (``optimal`` only).

    Returns
    -------
    HdrResult
        Irradiance (e-/s), sigma (e-/s) and nexp per photosite.
    """
    if name == "optimal-defaults":
        name, options = "optimal", {}
    if name == "optimal":
        return merge_arrays(frames, list(times), calibration, darks=darks, **options)
    method = "optimal" if name == "optimal@observed" else name
    return merge_weighted(frames, times, calibration, darks, method=method)


def _monte_carlo(
    setup: EvalSetup, reps: int, seed: int, curves: Sequence[str], options: dict
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Merge ``reps`` seeded brackets with every curve; the stacked estimates and merge seconds."""
    est: dict[str, list] = {c: [] for c in curves}
    seconds = {c: 0.0 for c in curves}
    for r in range(reps):
        rng = np.random.default_rng([seed, 1000 + r])
        frames, darks = simulate_bracket_arrays(setup, rng)
        for c in curves:
            t0 = time.perf_counter()
            res = merge_method(c, frames, darks, setup.times, setup.calibration, **options)
            seconds[c] += time.perf_counter() - t0
            est[c].append(np.asarray(res.irradiance, dtype=np.float64))
    return {c: np.stack(v) for c, v in est.items()}, seconds


def snr_experiment(
    setup: EvalSetup,
    reps: int = 4,
    seed: int = 0,
    curves: Sequence[str] = CURVES,
    n_bins: int = 24,
    keep: bool = False,
    options: dict | None = None,
) -> dict:
    """Monte-Carlo SNR of every curve against the truth and the bound, per irradiance bin (Fig. 4).

    Parameters
    ----------
    setup : EvalSetup
        The experiment (:func:`make_setup`).
    reps : int
        Repetitions (independent brackets).
    seed : int
        Seed of the noise.
    curves : sequence of str
        Curves of :data:`CURVES` to merge with.
    n_bins : int
        Logarithmic irradiance bins.
    keep : bool
        Add the stacked estimates (e-/s), the truth (e-/s) and the bound ((e-/s)^2) under
        ``"estimates"``, ``"truth"`` and ``"bound"`` (not JSON).
    options : dict, optional
        Options of the ML merge (default :data:`OPTIMAL_OPTIONS`).

    Returns
    -------
    dict
        The setting, ``bins`` (edges, e-/s), ``center``, ``samples_per_bin``, ``bound_snr_db``
        per bin, and under ``curves`` per curve the :func:`pipeline.evaluation.snr_per_bin`
        results, the paired comparison against ``optimal`` (``vs_optimal``,
        :func:`pipeline.evaluation.paired_difference`) and the merge time
        (``seconds_per_megapixel``, s per megapixel).
    """
    calib = setup.calibration
    p = calib.params
    truth = setup.scene
    stacks, seconds = _monte_carlo(setup, reps, seed, curves, dict(OPTIMAL_OPTIONS if options is None else options))
    edges = log_bins(truth, n_bins)
    prnu = 1.0 if calib.prnu is None else calib.prnu  # None: a_j = 1 everywhere
    bound = bound_variance(truth, setup.times, p, a=prnu, D=calib.dark_current_map, dark="matched")
    valid = np.isfinite(bound)
    mp = truth.size * reps / 1e6
    out = {
        "camera": setup.spec.name,
        "g": p.g,
        "sigma2_R": p.sigma2_R,
        "v_sat": p.v_sat,
        "mu_R": p.mu_R,
        "dark_current": p.dark_current,
        "exposure_times": list(setup.times),
        "irradiance_range": [float(truth.min()), float(truth.max())],
        "shape": list(truth.shape),
        "reps": reps,
        "seed": seed,
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


def _qq_levels(p: SensorParams) -> dict[str, float]:
    """Right above the noise floor (signal = readout noise, at least 3 e-), mid range, and 4 output
    standard deviations below v_sat; mean collected electrons."""
    sigma_r_e = np.sqrt(p.sigma2_R) / p.g
    e_max = (p.v_sat - p.mu_R) / p.g
    e_high = e_max
    for _ in range(20):  # solve g E + 4 sqrt(g^2 E + sigma2_R) = v_sat - mu_R
        e_high = e_max - 4.0 * np.sqrt(p.g**2 * e_high + p.sigma2_R) / p.g
    return {"noise_floor": max(3.0, sigma_r_e), "mid_range": 0.5 * e_max, "near_saturation": e_high}


def qq_experiment(
    spec: SensorSpec, n_frames: int = 36, n_pixels: int = 400, seed: int = 0, levels_e: dict[str, float] | None = None
) -> dict:
    """Normal Q-Q data of raw outputs at three levels (Fig. 6) and Shapiro-Wilk rejection rates.

    A flat field is exposed ``n_frames`` times; each photosite's ``n_frames`` outputs form one
    sample. Per level: the Q-Q data of the first photosite and the rejection rate over
    ``n_pixels`` photosites (:func:`pipeline.evaluation.gaussianity`).

    Parameters
    ----------
    spec : SensorSpec
        Sensor physics (its dark current and PRNU are switched off).
    n_frames : int
        Frames per level (sample size per photosite).
    n_pixels : int
        Photosites per level.
    seed : int
        Seed of the sensor and the noise.
    levels_e : dict, optional
        Level name -> mean collected electrons, e-. Default: right above the noise floor (where
        the signal equals the readout noise, at least 3 e-), mid range, and right before
        saturation (4 output standard deviations below v_sat).

    Returns
    -------
    dict
        ``camera``, ``sigma2_R`` (DN^2), ``g`` (DN/e-), ``n_frames`` and per level ``electrons``,
        ``mean_dn`` (DN), ``qq`` (:func:`pipeline.evaluation.qq_data`) and ``test``.
    """
    p = spec.nominal_params()
    if levels_e is None:
        levels_e = _qq_levels(p)
    sensor = SimulatedSensor(spec.replace(dark_current=0.0, prnu=0.0), (1, n_pixels), seed=seed)
    levels: dict[str, dict] = {}
    out = {"camera": spec.name, "sigma2_R": p.sigma2_R, "g": p.g, "n_frames": n_frames, "levels": levels}
    t = 1.0
    for k, (name, e) in enumerate(levels_e.items()):
        rng = np.random.default_rng([seed, 77, k])
        s = np.stack([sensor.expose(e / t, t, rng=rng)[0].astype(np.float64) for _ in range(n_frames)], axis=1)
        levels[name] = {
            "electrons": float(e),
            "mean_dn": float(s.mean()),
            "qq": qq_data(s[0]),
            "test": gaussianity(s),
        }
    return out


def evaluation_cases() -> dict[str, SensorSpec]:
    """The four sensors of Sec. 7: camera-A, camera-B and camera-B with zero and 10x readout noise.

    Returns
    -------
    dict
        Label -> sensor physics.
    """
    base_b = PRESETS["camera-B"]
    return {
        "camera-A": PRESETS["camera-A"],
        "camera-B": base_b,
        "camera-B zero readout": ZERO_READOUT(base_b),
        "camera-B 10x readout": TEN_X_READOUT(base_b),
    }


def run_evaluation(
    out: Path | None = None,
    quick: bool = False,
    seed: int = 0,
    force: bool = False,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Run Sec. 7 on camera-A and camera-B; with ``out``, write ``evaluation.json`` and the PNGs.

    Parameters
    ----------
    out : path, optional
        Output folder (created if missing).
    quick : bool
        Smaller images and fewer repetitions (about 4x faster).
    seed : int
        Seed of every random draw.
    force : bool
        Replace existing outputs.
    progress : callable, optional
        Called with one line of text per step.

    Returns
    -------
    dict
        ``snr`` (per case, :func:`snr_experiment`), ``weights_vs_output`` (Fig. 2), ``qq``
        (Fig. 6), ``summary`` (:func:`summarise`), ``notes``, ``seconds`` (s) and, with ``out``,
        ``plots`` (file names).
    """
    say = progress or (lambda msg: None)
    shape = (32, 192) if quick else (64, 768)
    reps = 2 if quick else 6
    n_bins = 16 if quick else 40
    n_pixels = 200 if quick else 400
    cases = evaluation_cases()
    results: dict = {"seed": seed, "quick": quick, "snr": {}, "notes": dict(NOTES)}
    t_start = time.perf_counter()
    for label, spec in cases.items():
        say(f"SNR experiment: {label}")
        results["snr"][label] = snr_experiment(
            make_setup(spec, shape=shape, seed=seed), reps=reps, seed=seed, n_bins=n_bins
        )
    say("weights against output value (Fig. 2)")
    results["weights_vs_output"] = {
        label: weights_vs_output(evaluation_params(cases[label]), X=1000.0)
        for label in ("camera-B", "camera-B zero readout", "camera-B 10x readout")
    }
    say("Gaussian check (Fig. 6)")
    results["qq"] = {
        label: qq_experiment(cases[label], seed=seed, n_pixels=n_pixels)
        for label in ("camera-B", "camera-B zero readout")
    }
    results["summary"] = summarise(results)
    results["seconds"] = round(time.perf_counter() - t_start, 2)
    if out is not None:
        _write_results(results, Path(out), force)
    return results


def _write_results(results: dict, out: Path, force: bool) -> None:
    """The PNGs (their names under ``results["plots"]``) and ``evaluation.json`` into ``out``."""
    from hdrcap.experiments.figures import write_plots

    out.mkdir(parents=True, exist_ok=True)
    results["plots"] = write_plots(results, out, force)
    with atomic_output(out / "evaluation.json", force=force) as tmp:
        tmp.write_text(json.dumps(results, indent=1, sort_keys=True))


def summarise(results: dict) -> dict:
    """Per case and curve: mean and minimum efficiency over bins, mean SNR loss to optimal.

    Parameters
    ----------
    results : dict
        The result of :func:`run_evaluation` (its ``snr`` entry is used).

    Returns
    -------
    dict
        Case -> curve -> ``mean_efficiency``, ``min_efficiency`` (bound / MSE) and, when the
        case has an ``optimal`` curve, ``mean_snr_minus_optimal_db`` and
        ``min_snr_minus_optimal_db`` (dB).
    """
    summ = {}
    for label, res in results["snr"].items():
        opt = res["curves"].get("optimal")
        rows = {}
        for name, r in res["curves"].items():
            eff = [e for e in r["efficiency"] if e is not None]
            row = {
                "mean_efficiency": float(np.mean(eff)) if eff else None,
                "min_efficiency": float(np.min(eff)) if eff else None,
            }
            if opt is not None:
                d = [a - b for a, b in zip(r["snr_db"], opt["snr_db"]) if a is not None and b is not None]
                row["mean_snr_minus_optimal_db"] = float(np.mean(d)) if d else None
                row["min_snr_minus_optimal_db"] = float(np.min(d)) if d else None
            rows[name] = row
        summ[label] = rows
    return summ
