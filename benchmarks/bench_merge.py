"""Benchmark of the optimal merge kernel; prints one JSON object.

6 brackets + 6 dark frames of MPIX megapixels (uint16, in memory), merged with at least 3
iterations (tolerance 0, so every photosite does exactly ``--iterations`` steps), against one
``np.sum`` of the same 12-frame stack measured in the same run. The whole command (``hdrcap
merge`` from DNG files to EXR against HDRMerge) is ``benchmarks/bench_command.py``.

Usage: python benchmarks/bench_merge.py [--mpix 24] [--iterations 3]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_command import TIMES, shape_for  # noqa: E402  (after the path set-up above)


def _frames(shape, seed=0):
    """Bracket + darks from the simulator, generated in tiles of rows (memory)."""
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.mock_camera.sensor import PRESETS, SimulatedSensor

    spec = PRESETS["camera-A"]
    h, w = shape
    values = [np.empty(shape, np.uint16) for _ in TIMES]
    darks = [np.empty(shape, np.uint16) for _ in TIMES]
    tile = max(2, (4_000_000 // w) // 2 * 2)
    for r0 in range(0, h, tile):
        r1 = min(h, r0 + tile)
        sensor = SimulatedSensor(spec, (r1 - r0, w), seed=seed + r0)
        scene = make_scene("hdr", (r1 - r0, w), 4.0, 2e5)
        for i, t in enumerate(TIMES):
            values[i][r0:r1] = sensor.expose(scene, t)
            darks[i][r0:r1] = sensor.expose(scene, t, dark=True)
    return values, darks, spec


def bench_kernel(shape, iterations, repeats=3):
    from hdrcap.pipeline.merge.accumulator import merge_arrays
    from hdrcap.pipeline.params import Calibration

    values, darks, spec = _frames(shape)
    cal = Calibration(spec.nominal_params())
    stack = np.stack(values + darks)
    merge_arrays([v[:64] for v in values], TIMES, cal, [d[:64] for d in darks])  # compile / load cache
    t_sum, t_merge = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        s = np.sum(stack)
        t_sum.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        res = merge_arrays(values, TIMES, cal, darks, iterations=iterations, tolerance=0.0)
        t_merge.append(time.perf_counter() - t0)
    del stack
    return {
        "shape": list(shape),
        "frames": len(values) + len(darks),
        "iterations_per_photosite": iterations,
        "iterations_used_mean": res.info["iterations_used_mean"],
        "np_sum_s": min(t_sum),
        "merge_s": min(t_merge),
        "ratio_merge_to_np_sum": min(t_merge) / min(t_sum),
        "finite": bool(np.isfinite(res.irradiance).all() and np.isfinite(res.sigma).all()),
        "checksum": float(s),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpix", type=float, default=24.0, help="megapixels per frame (default 24)")
    ap.add_argument("--iterations", type=int, default=3, help="iterations per photosite (>= 3)")
    ap.add_argument(
        "--no-hdrmerge",
        action="store_true",
        help="ignored (HDRMerge is compared in bench_command.py); accepted for run_all.py",
    )
    args = ap.parse_args(argv)
    shape = shape_for(args.mpix)
    import numba
    from numba.core import config

    import hdrcap.pipeline.merge.kernels  # noqa: F401  (sets numba's CPU features before anything compiles)

    report = {
        "mpix": args.mpix,
        "cpu_count": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "vector_width": "512-bit (prefer-256-bit lifted)"
        if (config.CPU_FEATURES or "").endswith("-prefer-256-bit")
        else "numba default",
    }
    report["kernel"] = bench_kernel(shape, max(3, args.iterations))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
