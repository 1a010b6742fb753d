"""Time the uncertainty-driven bilateral filter (pipeline.denoise.filter) on a 24 Mpixel mosaic.

Prints one JSON object: image size, settings, threads, the median and all of ``--runs`` timed
runs after one warm-up (which also loads or compiles the numba kernel), Mpixel/s, the CPU
time of the runs and the load average (the machine may be shared).

    python benchmarks/bench_denoise.py [--width 6000] [--height 4000] [--runs 3] [--method adaptive]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numba  # noqa: E402
import numpy as np  # noqa: E402

from hdrcap.pipeline.denoise.filter import DenoiseSettings, denoise  # noqa: E402


def make_input(h: int, w: int, seed: int = 0):
    """A merged-looking mosaic: log-uniform irradiance in 8x8 blocks (edges), Poisson-like
    sigma, noise added, 0.1 % photosites saturated everywhere (nexp = 0)."""
    rng = np.random.default_rng(seed)
    blocks = 10 ** rng.uniform(1, 5, size=(h // 8 + 1, w // 8 + 1))
    truth = np.repeat(np.repeat(blocks, 8, 0), 8, 1)[:h, :w].astype(np.float32)
    sigma = np.sqrt(truth * 4.0 + 25.0).astype(np.float32)
    irr = (truth + sigma * rng.standard_normal((h, w), dtype=np.float32)).astype(np.float32)
    nexp = np.full((h, w), 3, np.float32)
    nexp[rng.random((h, w)) < 1e-3] = 0
    return irr, sigma, nexp


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=6000)
    ap.add_argument("--height", type=int, default=4000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--method", choices=("adaptive", "constant"), default="adaptive")
    ap.add_argument("--radius", type=int, default=None)
    args = ap.parse_args(argv)
    irr, sigma, nexp = make_input(args.height, args.width)
    kw = {"method": args.method}
    if args.method == "constant":
        kw["bandwidth"] = 100.0
    if args.radius is not None:
        kw["radius"] = args.radius
    settings = DenoiseSettings(**kw)
    t0 = time.perf_counter()
    denoise(irr, sigma, nexp, settings)
    warm = time.perf_counter() - t0
    times, cpu = [], []
    for _ in range(args.runs):
        t0, c0 = time.perf_counter(), time.process_time()
        denoise(irr, sigma, nexp, settings)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    med = statistics.median(times)
    mpx = args.width * args.height / 1e6
    print(
        json.dumps(
            {
                "benchmark": "denoise",
                "width": args.width,
                "height": args.height,
                "mpixel": mpx,
                "settings": settings.to_dict(),
                "numba_threads": numba.get_num_threads(),
                "cpu_count": os.cpu_count(),
                "warmup_s": round(warm, 3),
                "runs_s": [round(t, 3) for t in times],
                "median_s": round(med, 3),
                "mpixel_per_s": round(mpx / med, 2),
                "cpu_s_median": round(statistics.median(cpu), 3),
                "load_average_1min": round(os.getloadavg()[0], 2),
                "note": "wall time of the full pipeline.denoise.filter.denoise call (validation, allocation, kernel); "
                "cpu_s is the process CPU time over all threads: cpu_s / threads is the wall time to expect "
                "on an otherwise idle machine",
            },
            sort_keys=True,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
