"""The calibration's "done when" on the realistic simulated sensor camera-R, per seed, as JSON.

The experiment and its figures are :mod:`hdrcap.experiments.realistic` (a calibration ESTIMATED
from camera-R's simulated frames, then a 4-decade gradient merged from a bracket of 0.08-300 s
with matched dark frames, against the simulator's truth); this prints them per seed with a
summary.

Usage: python benchmarks/bench_realistic.py [--size 256] [--seeds 1,2,3,4,5,6] [--ptc-levels 10]
[--spec '{"bias_drift": 0}'] [--exposure-times effective|nominal]
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from hdrcap.experiments.realistic import FLAT_LEVEL, TIMES, ptc_levels, run_case


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="photosites per side (default 256)")
    ap.add_argument("--seeds", default="1,2,3,4,5,6", help="sensor seeds, comma-separated")
    ap.add_argument("--ptc-levels", type=int, default=10, help="photon-transfer levels (0: flats at 87.5 %% only)")
    ap.add_argument("--spec", default="{}", help="JSON changes to camera-R's spec, e.g. '{\"bias_drift\": 0}'")
    ap.add_argument("--exposure-times", default="effective", choices=("effective", "nominal"))
    a = ap.parse_args(argv)
    changes = json.loads(a.spec)
    cases = [
        run_case(int(s), a.size, a.ptc_levels, a.exposure_times, **changes) for s in a.seeds.split(",") if s.strip()
    ]
    out = {
        "config": {
            "size": a.size,
            "ptc_levels": list(ptc_levels(a.ptc_levels)),
            "flat_level": FLAT_LEVEL,
            "times": list(TIMES),
            "spec_changes": changes,
            "exposure_times": a.exposure_times,
        },
        "cases": cases,
        "summary": {
            "g_error_pct": [min(c["g_error_pct"] for c in cases), max(c["g_error_pct"] for c in cases)],
            "z_spread": [min(c["z_spread"] for c in cases), max(c["z_spread"] for c in cases)],
            "beyond_6_sigma_max": max(c["beyond_6_sigma"] for c in cases),
            "worst_decade_bias_pct": [c["worst_decade_bias_pct"] for c in cases],
        },
    }
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
