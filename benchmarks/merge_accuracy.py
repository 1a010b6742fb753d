"""Accuracy figures of the optimal merge against the simulator's truth and the practical bound
(the same Monte Carlo as tests/pipeline/merge/test_optimal_merge.py, larger), plus the EMVA 1288
two-bracket check. Prints one JSON object.

Usage: python benchmarks/merge_accuracy.py [--seeds 4]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the tests package: the Monte Carlo is that of the test


def _figures(mc):
    X, err, sig, nexp, bound = mc["X"], mc["err"], mc["sigma"], mc["nexp"], mc["bound"]
    sel = np.isfinite(bound) & (X / np.sqrt(bound) > 10 ** (3 / 20)) & (nexp > 0)
    zb, z = err[sel] / np.sqrt(bound[sel]), err[sel] / sig[sel]
    return {
        "n": int(sel.sum()),
        "bias_in_sd": round(float(zb.mean()), 4),
        "mse_over_bound": round(float(np.mean(zb**2)), 4),
        "z_std": round(float(z.std()), 4),
        "beyond_6_sigma": int(np.sum(np.abs(z) > 6)),
        "flagged_with_usable_exposure": int(np.sum(np.isfinite(bound) & (nexp == 0))),
    }


def main(argv=None):
    from tests.pipeline.merge import test_optimal_merge as T

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args(argv)
    seeds = tuple(range(10, 10 + args.seeds))
    out = {}
    for cam in ("camera-A", "camera-B"):
        out[f"{cam} matched"] = _figures(T._monte_carlo(cam, "matched", seeds=seeds))
    for dark in ("master", "model"):
        out[f"camera-A {dark}"] = _figures(T._monte_carlo("camera-A", dark, seeds=seeds))
    out["camera-A matched probabilistic"] = _figures(
        T._monte_carlo("camera-A", "matched", seeds=seeds, saturation="probabilistic")
    )
    from tests.helpers.datasets import emva_dataset_dir

    emva = emva_dataset_dir()
    if emva is not None:
        from hdrcap.pipeline.merge.accumulator import merge_arrays
        from hdrcap.pipeline.params import Calibration, SensorParams

        ds, steps, load = T._emva_steps(emva)
        g, mu_R, s2 = T._photon_transfer([steps[10], steps[25]], load)
        cal = Calibration(SensorParams(g=g, mu_R=mu_R, sigma2_R=s2, v_sat=4095.0, white_level=4095.0))
        chosen = [steps[i] for i in (1, 5, 15, 30)]
        res = []
        for k in (0, 1):
            pairs = [load(s, k) for s in chosen]
            res.append(
                merge_arrays([b for b, _ in pairs], [s.exposure_time for s in chosen], cal, [d for _, d in pairs])
            )
        a, b = res
        ok = (a.nexp > 0) & (b.nexp > 0)
        z = (a.irradiance[ok] - b.irradiance[ok]) / np.hypot(a.sigma[ok], b.sigma[ok])
        out["emva1288 snap_001 vs snap_002"] = {
            "gain_DN_per_e": round(g, 4),
            "z_mean": round(float(z.mean()), 4),
            "z_std": round(float(z.std()), 4),
        }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
