"""Honesty table of the merge's stated sigma: z = (estimate - truth) / sigma against the simulator's
truth, with a calibration ESTIMATED from simulated frames of the same sensor (never the truth).

Per camera (camera-A, camera-B, camera-R: the realistic preset, defect photosites excluded),
dark strategy (matched, master per time, one master dark at t_ref, model) and saturation model
(threshold, probabilistic): z mean and z spread (standard deviation)

* per irradiance decade (photosites away from every clip level, |k| > 3 for every exposure), and
* per band of k = (E[v] - v_sat) / sigma_v around each exposure's clip level (the exposure whose
  clip level is nearest, bands of one sigma from -3 to +3), leaving out the shortest exposure's
  clip level (above it there is only a lower bound; see :func:`z_table`).

The calibration: 2 bias frames, 1 saturation frame, 16 flat fields, a dark series at 6 exposure
times (2 frames each): :func:`hdrcap.experiments.calibrated.estimated_calibration`. The scene: half the
photosites log-uniform over 1-10^4 e-/s, half placed uniformly in k in [-4, 4] around the clip
level of one of the exposures. Exposure times: the effective ones the merge estimates from the
bracket, as ``hdrcap merge`` does by default (``exposure_times="effective"``); ``--times
nominal`` merges with the nominal times, ``--times oracle`` with the simulator's true
effective times (camera-R's shutter errors of +-3 %: an upper bound of what estimated
effective times can do).

Prints one JSON object (``--markdown``: the tables of docs/merge.md).

Usage: python benchmarks/bench_honesty.py [--size 192] [--seeds 1] [--markdown] [--times effective|nominal|oracle]
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from hdrcap.experiments.calibrated import estimated_calibration
from hdrcap.experiments.extremes import nearest_clip
from hdrcap.mock_camera.sensor import PRESETS, SimulatedSensor
from hdrcap.pipeline.merge.accumulator import merge_arrays

CAMERAS = ("camera-A", "camera-B", "camera-R")
TIMES = (0.125, 0.5, 2.0, 8.0, 30.0)
TIME_MODES = ("effective", "nominal", "oracle")
N_MASTER = 8
T_REF = 8.0
DECADES = ((0, 1), (1, 2), (2, 3), (3, 4))
K_EDGES = (-3, -2, -1, 0, 1, 2, 3)
STRATEGIES = ("matched", "master", "master@t_ref", "model")
SATURATIONS = ("threshold", "probabilistic")


def clip_scene(spec, shape, times, rng) -> np.ndarray:
    """Irradiance map, e-/s: half log-uniform over 1-10^4, half uniform in k in [-4, 4] around
    the clip level of a random exposure (k from the true model at a = 1 and the mean dark
    current; the bands are computed later per photosite from the truth)."""
    p = spec.nominal_params()
    n = int(np.prod(shape))
    X = 10 ** rng.uniform(0.0, 4.0, n)
    near = rng.random(n) < 0.5
    t = np.asarray(times)[rng.integers(0, len(times), n)]
    k = rng.uniform(-4.0, 4.0, n)
    # E[v] = mu_R + g t u, sd = sqrt(g^2 t u + s2): solve mu_R + g t u = v_sat + k sd for u by iteration
    u = (p.v_sat - p.mu_R) / (p.g * t)
    for _ in range(6):
        u = (p.v_sat + k * np.sqrt(p.g**2 * t * u + p.sigma2_R) - p.mu_R) / (p.g * t)
    X[near] = np.maximum(u - spec.dark_current, 1e-3)[near]
    return X.reshape(shape)


def _stats(z: np.ndarray, zg: np.ndarray) -> dict[str, Any]:
    if z.size < 20:
        return {"n": int(z.size), "mean": None, "std": None, "mean_gain_referred": None}
    return {
        "n": int(z.size),
        "mean": round(float(z.mean()), 3),
        "std": round(float(z.std()), 3),
        "mean_gain_referred": round(float(zg.mean()), 3),
    }


def z_table(z, zg, X, k, ok, shortest) -> dict[str, Any]:
    """z mean and spread per irradiance decade (|k| > 3) and per band of k; ``zg`` is z against
    the truth scaled by the estimated gain's error (common to every photosite, reported in the
    merge's header rather than in sigma).

    The bands of k leave out the photosites whose nearest clip level is the shortest
    exposure's (``shortest``): above it no sample measures the irradiance (the merge reports a
    lower bound, nexp = 0), so the photosites that keep an estimate there are a selection by
    their own noise (the unsaturated draws), biased whatever the estimator; their share with an
    estimate is ``shortest_clip_measured``."""
    lx = np.log10(X)
    far = np.abs(k) > 3
    out: dict[str, Any] = {"decades": {}, "k_bands": {}}
    for lo, hi in DECADES:
        m = ok & far & (lx >= lo) & (lx < hi)
        out["decades"][f"1e{lo}-1e{hi}"] = _stats(z[m], zg[m])
    for lo, hi in zip(K_EDGES[:-1], K_EDGES[1:]):
        m = ok & ~shortest & (k >= lo) & (k < hi)
        out["k_bands"][f"{lo:+d}..{hi:+d}"] = _stats(z[m], zg[m])
    near = shortest & (np.abs(k) < 3)
    out["shortest_clip_measured"] = round(float(ok[near].mean()), 3) if near.any() else None
    return out


def _bracket(sensor, X, rng):
    """Light frames and dark frames per strategy, simulated once per camera."""
    lights = [sensor.expose(X, t, rng=rng) for t in TIMES]
    matched = [sensor.expose(X, t, dark=True, rng=rng) for t in TIMES]
    masters = [
        np.mean([sensor.expose(X, t, dark=True, rng=rng) for _ in range(N_MASTER)], axis=0).astype(np.float32)
        for t in TIMES
    ]
    tref = np.mean([sensor.expose(X, T_REF, dark=True, rng=rng) for _ in range(N_MASTER)], axis=0).astype(np.float32)
    return lights, {
        "matched": (matched, {}),
        "master": (masters, {"dark_strategy": "master", "n_dark": N_MASTER}),
        "master@t_ref": (tref, {"n_dark": N_MASTER, "master_dark_time": T_REF}),
        "model": (None, {"dark_strategy": "model"}),
    }


def run_camera(cam: str, size: int, seed: int, times_mode: str) -> dict[str, Any]:
    """All strategies and saturation models of one camera and seed: z per merge, and the mask."""
    spec = PRESETS[cam]
    shape = (size, size)
    sensor = SimulatedSensor(spec, shape, seed=seed)
    rng = np.random.default_rng([seed, 31])
    cal = estimated_calibration(sensor, rng)
    X = clip_scene(spec, shape, TIMES, rng)
    k, which = nearest_clip(sensor, X, TIMES, spec.nominal_params().v_sat)
    shortest = which == int(np.argmin(TIMES))
    defect = np.zeros(shape, bool)
    for m in sensor.defects.values():
        defect |= m
    times = [t * sensor.shutter_factor(t) if times_mode == "oracle" else t for t in TIMES]
    estimate_times = "effective" if times_mode == "effective" else "nominal"
    lights, darks = _bracket(sensor, X, rng)
    out = {}
    for name, (d, opts) in darks.items():
        for sat in SATURATIONS:
            res = merge_arrays(lights, times, cal, d, saturation=sat, exposure_times=estimate_times, **opts)
            ok = (res.nexp > 0) & ~defect & (res.sigma > 0)
            sig = np.where(ok, res.sigma, 1.0)
            z = np.where(ok, (res.irradiance.astype(np.float64) - X) / sig, 0.0)
            zg = np.where(ok, (res.irradiance.astype(np.float64) - X * spec.g / cal.params.g) / sig, 0.0)
            out[(name, sat)] = (z, zg, X, k, ok, shortest)
    return out


def honesty(size: int = 192, seeds=(1,), times_mode: str = "effective", cameras=CAMERAS) -> dict[str, Any]:
    """The honesty table (see the module docstring); seeds pooled."""
    result: dict[str, Any] = {
        "settings": {
            "size": size,
            "seeds": list(seeds),
            "times_s": list(TIMES),
            "n_master": N_MASTER,
            "t_ref_s": T_REF,
            "exposure_times": times_mode,
            "calibration": "estimated: 2 bias, 1 saturation, 16 flats, darks at 1-32 s x 2",
        }
    }
    for cam in cameras:
        pooled: dict[tuple, list] = {}
        for seed in seeds:
            for key, arrays in run_camera(cam, size, seed, times_mode).items():
                pooled.setdefault(key, []).append(arrays)
        result[cam] = {
            f"{s} {sat}": z_table(*(np.concatenate([r[i].ravel() for r in rows]) for i in range(6)))
            for (s, sat), rows in pooled.items()
        }
    return result


def _cell(st) -> str:
    if st["mean"] is None:
        return "—"
    return f"{st['mean']:+.2f} / {st['std']:.2f} ({st['mean_gain_referred']:+.2f})"


def markdown(result: dict[str, Any]) -> str:
    """Two tables: z mean / z spread per irradiance decade, and per band of k."""
    lines = []
    for part, title in (("decades", "irradiance decade, e-/s (|k| > 3)"), ("k_bands", "band of k")):
        first = next(iter(result[c] for c in result if c != "settings"))
        cols = list(next(iter(first.values()))[part])
        extra = part == "k_bands"  # the share of photosites measured at the shortest exposure's clip
        lines += [
            f"z mean / z spread (z mean with the estimated gain's common error removed) per {title}:",
            "",
            "| camera | darks | saturation | "
            + " | ".join(cols)
            + (" | measured at t_min's clip |" if extra else " |"),
            "|---|---|---|" + "---|" * (len(cols) + extra),
        ]
        for cam, rows in result.items():
            if cam == "settings":
                continue
            for key, tab in rows.items():
                strat, sat = key.split(" ")
                cells = [_cell(tab[part][c]) for c in cols]
                if extra:
                    cells.append(f"{tab['shortest_clip_measured']:.3f}")
                lines.append(f"| {cam} | {strat} | {sat} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=192, help="mosaic side, photosites")
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument(
        "--times", choices=TIME_MODES, default="effective", help="exposure times of the merge (default: estimated)"
    )
    ap.add_argument("--camera", action="append", choices=CAMERAS)
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    result = honesty(args.size, tuple(range(1, 1 + args.seeds)), args.times, tuple(args.camera or CAMERAS))
    print(markdown(result) if args.markdown else json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
