"""The speed/accuracy trade of the ML merge: every knob on the same simulated data.

Knobs (``pipeline.merge.accumulator.merge_arrays`` options unless said otherwise):

* iterations 0 (the non-saturated average the merge starts from: ``merge_weighted`` with
  uniform weights), 1, 2, 3, converged (the default: up to 20, tolerance 1e-6);
* saturation ``threshold`` (Eq. 11 + near-saturation rule) vs ``probabilistic`` (Eq. 8-10),
  and the near-saturation margin ``saturation_sigmas`` 0 / 1 / 3 (default 3);
* PRNU ``map`` (per photosite, Eq. 14) vs ``scalar`` (a = 1);
* darks ``matched`` (one dark frame per exposure) vs ``master`` (16 dark frames averaged per
  exposure time) vs ``model`` (no dark frame: bias + calibrated dark current);
* input arrays uint16 (native) vs float32 vs float64 (float frames are stored as float32 and
  take float64 weights; uint16 frames take float32 weights where the merge's bounds allow: this
  measures both and checks the results agree).

Data: the evaluation's gradient (4 decades, 6 exposures two stops apart, 1/1024..1 s) on
camera-A and camera-B with the sensor's true PRNU and dark-current maps and Table 2's v_sat
(mean - 3 sigma of a saturation frame, as a user's calibration gives). Per configuration:
median merge time over ``--timing-runs`` runs (s per megapixel, after a warm-up run that
compiles the kernels for the configuration's array types), mean and minimum efficiency (Cramér-Rao bound of the matched-dark setting / MSE)
over irradiance bins, mean SNR, the largest |bias| of any bin (relative), the standard deviation
of z = (estimate - X) / sigma (1 = honest sigma) and the capture time the dark strategy costs.

Usage::

    python benchmarks/bench_trade.py [--size 1024x256] [--reps 3] [--markdown] [--only SETTING...]

Prints JSON (``--markdown``: also the README table) and writes ``trade.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

N_MASTER = 16

CONFIGS = {
    # name: (merge options or None for the iterations-0 start, dark kind, input dtype)
    "recommended (defaults, matched darks)": ({}, "matched", "uint16"),
    "iterations 0 (non-saturated average)": (None, "matched", "uint16"),
    "iterations 1": ({"iterations": 1}, "matched", "uint16"),
    "iterations 2": ({"iterations": 2}, "matched", "uint16"),
    "iterations 3": ({"iterations": 3}, "matched", "uint16"),
    "saturation probabilistic": ({"saturation": "probabilistic"}, "matched", "uint16"),
    "near-saturation margin 0 sigma": ({"saturation_sigmas": 0.0}, "matched", "uint16"),
    "near-saturation margin 1 sigma": ({"saturation_sigmas": 1.0}, "matched", "uint16"),
    "PRNU scalar": ({"prnu": "scalar"}, "matched", "uint16"),
    f"darks master ({N_MASTER} frames)": ({"dark_strategy": "master", "n_dark": N_MASTER}, "master", "uint16"),
    "darks model (no dark frames)": ({"dark_strategy": "model"}, "model", "uint16"),
    "input float32": ({}, "matched", "float32"),
    "input float64": ({}, "matched", "float64"),
}


def run_camera(camera: str, shape, reps: int, seed: int, timing_runs: int, n_bins: int, only=None) -> dict:
    from hdrcap.experiments import make_setup, simulate_bracket_arrays
    from hdrcap.mock_camera import PRESETS
    from hdrcap.pipeline.evaluation import bound_variance, log_bins, snr_per_bin
    from hdrcap.pipeline.merge.accumulator import merge_arrays
    from hdrcap.pipeline.merge.weighting import merge_weighted

    spec = PRESETS[camera]
    setup = make_setup(spec, shape=shape, seed=seed, params=spec.nominal_params())
    calib, times, truth = setup.calibration, list(setup.times), setup.scene
    brackets = []
    for r in range(reps):
        rng = np.random.default_rng([seed, 2000 + r])
        frames, darks = simulate_bracket_arrays(setup, rng)
        masters = [
            np.mean([setup.sensor.expose(truth, t, dark=True, rng=rng) for _ in range(N_MASTER)], axis=0) for t in times
        ]
        brackets.append((frames, darks, masters))
    p = calib.params
    edges = log_bins(truth, n_bins)
    bound = bound_variance(truth, times, p, a=calib.prnu, D=calib.dark_current_map, dark="matched")
    valid = np.isfinite(bound)

    def run(cfg, frames, darks, masters):
        opts, dark_kind, dtype = cfg
        vals = [f.astype(dtype) for f in frames] if dtype != "uint16" else frames
        if opts is None:
            return merge_weighted(vals, times, calib, darks, method="uniform")
        d = {"matched": darks, "master": masters, "model": None}[dark_kind]
        return merge_arrays(vals, times, calib, darks=d, **opts)

    out = {
        "camera": camera,
        "shape": list(shape),
        "reps": reps,
        "v_sat": p.v_sat,
        "exposure_times": times,
        "configs": {},
    }
    mp = truth.size / 1e6
    ref = None
    for name, cfg in CONFIGS.items():
        if only and name not in only:
            continue
        run(cfg, *brackets[0])  # warm-up: compiles the kernels for this configuration's types
        secs = []
        for _ in range(timing_runs):
            t0 = time.perf_counter()
            run(cfg, *brackets[0])
            secs.append(time.perf_counter() - t0)
        results = [run(cfg, *b) for b in brackets]
        est = np.stack([r.irradiance.astype(np.float64) for r in results])
        sig = np.stack([r.sigma.astype(np.float64) for r in results])
        res = snr_per_bin(est, truth, edges, bound=bound, valid=valid)
        eff = np.array([e for e in res["efficiency"] if e is not None])
        snr = np.array([s for s in res["snr_db"] if s is not None])
        bias = np.array([b for b in res["bias"] if b is not None])
        ok = valid[None] & (sig > 0)
        z = ((est - truth) / np.where(ok, sig, 1.0))[ok]
        capture = sum(times) + {"matched": sum(times), "master": 0.0, "model": 0.0}[cfg[1]]
        row = {
            "seconds_per_megapixel": float(np.median(secs)) / mp,
            "mean_efficiency": float(eff.mean()),
            "min_efficiency": float(eff.min()),
            "mean_snr_db": float(snr.mean()),
            "max_abs_bias": float(np.abs(bias).max()),
            "mean_abs_bias": float(np.abs(bias).mean()),
            "z_std": float(z.std()),
            "capture_seconds_per_bracket": capture,
            "note": "master darks: 16 frames per exposure time, captured once and reused" if cfg[1] == "master" else "",
        }
        if name == "recommended (defaults, matched darks)":
            ref = est
        elif ref is not None and cfg[2] != "uint16":
            row["max_relative_difference_to_uint16_input"] = float(np.max(np.abs(est - ref) / np.abs(ref).clip(1e-30)))
        out["configs"][name] = row
    return out


def markdown(all_results: list[dict]) -> str:
    cams = [r["camera"] for r in all_results]
    head = (
        "| setting | "
        + " | ".join(f"{c}: s/MP | {c}: eff. mean (min) | {c}: max bias | {c}: z std" for c in cams)
        + " |"
    )
    sep = "|---|" + "---|---|---|---|" * len(cams)
    lines = [head, sep]
    for name in all_results[0]["configs"]:
        cells = []
        for r in all_results:
            row = r["configs"][name]
            cells += [
                f"{row['seconds_per_megapixel']:.2f}",
                f"{row['mean_efficiency']:.3f} ({row['min_efficiency']:.2f})",
                f"{100 * row['max_abs_bias']:.2f} %",
                f"{row['z_std']:.2f}",
            ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", nargs="+", default=["camera-A", "camera-B"])
    ap.add_argument("--size", default="1024x256", help="WIDTHxHEIGHT")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--timing-runs", type=int, default=3)
    ap.add_argument("--bins", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "_work" / "trade")
    ap.add_argument("--only", nargs="+", choices=list(CONFIGS), help="run these settings only (default: all)")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    results = [
        run_camera(c, (h, w), args.reps, args.seed, args.timing_runs, args.bins, args.only) for c in args.cameras
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "trade.json").write_text(json.dumps(results, indent=1))
    print(json.dumps(results, indent=1))
    if args.markdown:
        print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
