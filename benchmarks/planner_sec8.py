"""Sec. 8 of the paper on the simulator: exposure counts for 15/25/30 dB on camera-B, greedy
against exhaustive search, against naive brackets, and capture + merge against truth.

Prints one JSON object. Run from the repository root:
``python benchmarks/planner_sec8.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from hdrcap.mock_camera import PRESETS, SimulatedSensor
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.merge import accumulator as merge_mod
from hdrcap.pipeline.params import Calibration
from hdrcap.planner import (
    SystematicErrors,
    plan_bracket,
    plan_exhaustive,
    plan_exposures,
    predict_snr,
    systematic_errors_from_calibration,
)
from hdrcap.planner.ladder import THIRD_STOP_LADDER
from hdrcap.planner.plan import DEFAULT_OVERHEAD_S
from hdrcap.planner.predict import usable_fraction


def _merge(values, times, cal, **options):
    return merge_mod.merge_arrays(values, times, cal, **options), "merge_arrays"


def bulk_time(X, spec, highlight_fraction=0.05, k_sigma=3.0):
    """Independent of the planner: the longest ladder time at which at most ``highlight_fraction``
    of the eligible pixels (not saturated at the shortest time) come within ``k_sigma`` sigma of
    v_sat, from the simulator's parameters."""
    p = spec.nominal_params()
    x = np.asarray(X, dtype=np.float64).ravel()

    def saturated(t):
        e = t * (x + p.dark_current)
        return p.mu_R + p.g * e + k_sigma * np.sqrt(p.g**2 * e + p.sigma2_R) >= p.v_sat

    elig = ~saturated(min(THIRD_STOP_LADDER))
    return max(t for t in THIRD_STOP_LADDER if np.sum(saturated(t) & elig) <= highlight_fraction * elig.sum())


def sec8(shape):
    spec = PRESETS["camera-B"]
    cal = Calibration(spec.nominal_params())
    X = make_scene("hdr", shape, decades=4, x_max=2e5)
    out = {
        "scene": f"hdr {shape[1]}x{shape[0]}, 4 decades, 20..2e5 e-/s",
        "paper_counts": [3, 8, 15],
        "default_overhead_s": DEFAULT_OVERHEAD_S,
        "bulk_time_s": bulk_time(X, spec),
    }
    for label, kw in (
        ("default", {}),
        ("no_systematic_errors", {"errors": SystematicErrors()}),
        ("no_systematic_errors_zero_overhead", {"errors": SystematicErrors(), "overhead": 0.0}),
        ("eq18_greedy_only", {"errors": SystematicErrors(), "polish": False}),
        ("eq18_greedy_only_zero_overhead", {"errors": SystematicErrors(), "polish": False, "overhead": 0.0}),
    ):
        rows = []
        for target in (15, 25, 30):
            t0 = time.perf_counter()
            p = plan_exposures(cal, X, target, **kw)
            rows.append(
                {
                    "target_db": target,
                    "n_exposures": len(p.exposures),
                    "n_matched_darks": p.darks.count("matched"),
                    "total_time_s": round(p.total_time_s, 4),
                    "shutter_open_s": round(
                        sum(t * (2 if d == "matched" else 1) for t, d in zip(p.exposures, p.darks)), 4
                    ),
                    "first_exposure_s": p.exposures[0],
                    "first_saturates_fraction": float(np.mean(usable_fraction(X, p.exposures[0], cal) == 0)),
                    "predicted_min_snr_db": round(p.predicted_min_snr_db, 3),
                    "feasible": p.feasible,
                    "plan_seconds": round(time.perf_counter() - t0, 3),
                }
            )
        out[label] = rows
    # a scene with a real bulk: first exposure against the independently computed bulk time
    rng = np.random.default_rng(5)
    bulk = 10 ** rng.normal(np.log10(2e3), 0.25, 16000)
    Xb = np.clip(np.concatenate([bulk, 10 ** rng.uniform(np.log10(20), np.log10(2e5), 4000)]), 20, 2e5)
    out["bulk_scene"] = {
        "bulk_time_s": bulk_time(Xb, spec),
        "first_exposure_s": {str(tg): plan_exposures(cal, Xb, tg).exposures[0] for tg in (15, 25, 30)},
    }
    return out


def greedy_vs_exhaustive():
    out = {}
    cands = [1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1]
    for overhead in (0.002, DEFAULT_OVERHEAD_S):
        rows = []
        for cam in ("camera-A", "camera-B"):
            cal = Calibration(PRESETS[cam].nominal_params())
            for decades, x_max in ((2, 5e4), (3, 5e4), (3.5, 2e5)):
                X = make_scene("hdr", (48, 48), decades=decades, x_max=x_max)
                for target in (15, 20, 25):
                    g = plan_exposures(
                        cal, X, target, cands, errors=SystematicErrors(), max_exposures=6, overhead=overhead
                    )
                    ex = plan_exhaustive(cal, X, target, cands, 6, errors=SystematicErrors(), overhead=overhead)
                    if ex is None or not g.feasible:
                        continue
                    # the same search among sequences that hold the planner's first (bulk) exposure
                    exf = plan_exhaustive(
                        cal, X, target, cands, 6, errors=SystematicErrors(), overhead=overhead, first=g.exposures[0]
                    )
                    pure = plan_exposures(
                        cal,
                        X,
                        target,
                        cands,
                        errors=SystematicErrors(),
                        max_exposures=6,
                        overhead=overhead,
                        bulk_first=False,
                    )
                    rows.append(
                        {
                            "camera": cam,
                            "decades": decades,
                            "target_db": target,
                            "ratio": round(g.total_time_s / ex[1], 4),
                            "ratio_same_first": round(g.total_time_s / exf[1], 4),
                            "ratio_without_bulk_first": round(pure.total_time_s / ex[1], 4),
                            "greedy": g.exposures,
                            "exhaustive": ex[0],
                            "exhaustive_same_first": exf[0],
                        }
                    )
        out[f"overhead_{overhead:g}s"] = {
            "cases": len(rows),
            **{
                f"{stat}_{key}": round(float(fn([r[key] for r in rows])), 4)
                for key in ("ratio", "ratio_same_first", "ratio_without_bulk_first")
                for stat, fn in (("max", np.max), ("mean", np.mean))
            },
            "rows": rows,
        }
    return out


def brackets(shape):
    cal = Calibration(PRESETS["camera-B"].nominal_params())
    X = make_scene("hdr", shape, decades=4, x_max=2e5)
    rows = []
    for overhead in (0.0, DEFAULT_OVERHEAD_S):
        for target in (15, 20, 25, 30):
            p = plan_exposures(cal, X, target, errors=SystematicErrors(), overhead=overhead)
            row = {
                "overhead_s": overhead,
                "target_db": target,
                "plan_time_s": round(p.total_time_s, 4),
                "plan_n": len(p.exposures),
            }
            for step in (1, 2):
                seq, total = plan_bracket(cal, X, target, step, errors=SystematicErrors(), overhead=overhead)
                row[f"bracket_{step}ev_time_s"] = round(total, 4)
                row[f"bracket_{step}ev_n"] = len(seq)
                row[f"ratio_{step}ev"] = round(p.total_time_s / total, 4)
            rows.append(row)
    return rows


def capture_merge(seeds):
    spec = PRESETS["camera-B"]
    H, W = 32, 128
    X = make_scene("gradient", (H, W), decades=3, x_max=1e5)
    sensor = SimulatedSensor(spec, (H, W), seed=3)
    cal = Calibration(
        spec.nominal_params(),
        prnu=sensor.prnu.astype(np.float32),
        dark_current_map=sensor.dark_current_map().astype(np.float32),
    )
    rows = []
    for target in (20.0, 26.0):
        plan = plan_exposures(cal, X, target)
        err2 = np.zeros((H, W))
        for s in range(seeds):
            rng = np.random.default_rng([11, s])
            res, how = _merge(
                [sensor.expose(X, t, rng=rng) for t in plan.exposures], plan.exposures, cal, **plan.merge_options()
            )
            err2 += ((res.irradiance - X) / X) ** 2
        meas = -10 * np.log10(err2.sum(0) / (seeds * H))
        opts = plan.merge_options()
        pred = predict_snr(
            X[0],
            plan.exposures,
            cal,
            plan.darks,
            errors=systematic_errors_from_calibration(cal),
            prnu=opts["prnu"],
            saturation=opts["saturation"],
        ).snr_db
        margin = 10 * np.log10(1 + 3 * np.sqrt(2 / (seeds * H)))
        rows.append(
            {
                "target_db": target,
                "merge": how,
                "merge_options": plan.merge_options(),
                "n_exposures": len(plan.exposures),
                "fraction_columns_at_target": float(np.mean(meas >= target - margin)),
                "min_measured_db": round(float(meas.min()), 3),
                "median_measured_minus_predicted_db": round(float(np.median(meas - pred)), 3),
                "mc_margin_db": round(margin, 3),
            }
        )
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    shape = (96, 128) if args.quick else (384, 512)
    out = {
        "sec8": sec8(shape),
        "greedy_vs_exhaustive": greedy_vs_exhaustive(),
        "brackets": brackets(shape),
        "capture_merge": capture_merge(8 if args.quick else 16),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
