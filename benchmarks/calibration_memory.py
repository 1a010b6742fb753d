"""Peak memory of a streamed calibration: 24 Mpixel frames, 100 flat fields (the claim: under 2 GB).

Frames are generated on the fly, one at a time, as a capture session would deliver them
(Gaussian approximation of the shot noise for speed: the point is the memory of the
estimators, not the physics), and fed to :func:`hdrcap.pipeline.calibration.calibrate`.
Prints one JSON object: peak resident memory (ru_maxrss and psutil's sampled peak), the
baseline before calibration, timings and the gain error.

    python benchmarks/calibration_memory.py [--mpix 24] [--flats 100]
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hdrcap.pipeline.calibration import calibrate  # noqa: E402
from hdrcap.pipeline.io.raw import RawFrame  # noqa: E402


def rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpix", type=float, default=24.0, help="frame size in megapixels (3:2 aspect)")
    ap.add_argument("--flats", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    w = int(round(np.sqrt(args.mpix * 1e6 * 1.5) / 2)) * 2
    h = int(round(args.mpix * 1e6 / w / 2)) * 2
    shape = (h, w)
    g, mu_R, s2R, white = 0.23, 128.0, 6.5, 16383
    rng = np.random.default_rng(args.seed)
    prnu = (1 + 0.01 * rng.standard_normal(shape, dtype=np.float32)).astype(np.float32)
    level = 3000.0  # DN above bias

    def frame(mean_dn: float | np.ndarray, var_dn, t, name):
        x = rng.standard_normal(shape, dtype=np.float32)
        x *= np.sqrt(var_dn).astype(np.float32) if isinstance(var_dn, np.ndarray) else np.float32(np.sqrt(var_dn))
        x += mean_dn
        np.rint(x, out=x)
        np.clip(x, 0, white, out=x)
        return RawFrame(x.astype(np.uint16), t, path=name, white_level=white)

    def bias():
        for i in range(2):
            yield frame(mu_R, s2R, 1e-4, f"bias_{i}")

    def sat():
        yield frame(np.float32(white - 500), s2R, 1.0, "saturation")

    def flats():
        sig = (prnu * np.float32(level)).astype(np.float32)
        var = (g * sig + s2R).astype(np.float32)
        sig += np.float32(mu_R)
        for i in range(args.flats):
            yield frame(sig, var, 0.01, f"flat_{i:03d}")

    peak_sampled = [0.0]
    stop = threading.Event()

    def sampler():
        while not stop.is_set():
            peak_sampled[0] = max(peak_sampled[0], rss_mb())
            time.sleep(0.05)

    base = rss_mb()
    th = threading.Thread(target=sampler, daemon=True)
    th.start()
    t0 = time.perf_counter()
    cal = calibrate(bias(), sat(), flats(), white_level=white)
    elapsed = time.perf_counter() - t0
    stop.set()
    th.join()
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB on Linux
    out = {
        "benchmark": "calibration_memory",
        "shape": list(shape),
        "megapixels": h * w / 1e6,
        "n_flats": args.flats,
        "peak_rss_mb_ru_maxrss": round(maxrss, 1),
        "peak_rss_mb_sampled": round(peak_sampled[0], 1),
        "baseline_rss_mb": round(base, 1),
        "limit_mb": 2048,
        "within_limit": bool(maxrss < 2048),
        "seconds": round(elapsed, 1),
        "seconds_per_flat": round(elapsed / max(args.flats, 1), 2),
        "g_relative_error": cal.params.g / g - 1,
        "prnu_rms_error": float(np.sqrt(np.mean((cal.prnu - prnu / prnu.mean()) ** 2))),
    }
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
