"""Benchmark of the optimal merge; prints one JSON object.

1. Kernel: 6 brackets + 6 dark frames of MPIX megapixels (uint16, in memory), merged with at
   least 3 iterations (tolerance 0, so every photosite does exactly ``--iterations`` steps),
   against one ``np.sum`` of the same 12-frame stack measured in the same run.
2. Whole command: ``hdrcap merge`` on 12 DNG files (written with mock_camera) to EXR, versus
   HDRMerge on the 6 bright DNGs (installed with ``apt-get install -y hdrmerge`` if missing),
   with peak memory (``/usr/bin/time -v``) and whether HDRMerge's output DNG is finite (rawpy).

Usage: python benchmarks/bench_merge.py [--mpix 24] [--iterations 3] [--no-hdrmerge]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TIMES = [1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0]


def _shape(mpix: float) -> tuple[int, int]:
    w = int(round(np.sqrt(mpix * 1e6 * 3 / 2) / 2)) * 2
    h = int(round(mpix * 1e6 / w / 2)) * 2
    return h, w


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
    from hdrcap.pipeline.merge import merge_arrays
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


def _time_v(cmd, env=None):
    """Run ``cmd`` under /usr/bin/time -v: (wall seconds, peak RSS MB, returncode, stderr)."""
    t0 = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-v", *map(str, cmd)], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    return wall, (int(m.group(1)) / 1024 if m else None), proc.returncode, proc.stderr[-2000:]


def _ensure_hdrmerge():
    if shutil.which("hdrmerge"):
        return True
    subprocess.run(["apt-get", "install", "-y", "hdrmerge"], capture_output=True, text=True)
    return shutil.which("hdrmerge") is not None


def bench_commands(shape, work: Path, run_hdrmerge=True):
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.mock_camera.sensor import PRESETS

    spec = PRESETS["camera-A"]
    cam = SimulatedCamera(spec, make_scene("hdr", shape, 4.0, 2e5), seed=1)
    frames, darks = [], []
    for i, t in enumerate(TIMES):
        frames.append(cam.capture_to(work / f"frame_{i}.dng", t))
        darks.append(cam.capture_to(work / f"dark_{i}.dng", t, dark=True))
    del cam
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = {}
    # Warm the numba cache (compilation is a one-off, not part of a merge).
    subprocess.run([sys.executable, "-m", "hdrcap", "merge", frames[0], "--camera", "camera-A", "-o",
                    work / "warm.exr", "--force"], env=env, capture_output=True)
    wall, rss, rc, err = _time_v([sys.executable, "-m", "hdrcap", "merge", *frames, "--darks", *darks,
                                  "--camera", "camera-A", "-o", work / "hdrcap.exr", "--force", "--json",
                                  "--iterations", "20"], env)
    out["hdrcap_merge"] = {"seconds": wall, "peak_rss_mb": rss, "returncode": rc, "inputs": 12,
                           "exr_compression": "zip (default)"}
    if rc != 0:
        out["hdrcap_merge"]["stderr"] = err
    wall, rss, rc, err = _time_v([sys.executable, "-m", "hdrcap", "merge", *frames, "--darks", *darks,
                                  "--camera", "camera-A", "-o", work / "hdrcap_rle.exr", "--force", "--json",
                                  "--iterations", "20", "--exr-compression", "rle"], env)
    out["hdrcap_merge_rle"] = {"seconds": wall, "peak_rss_mb": rss, "returncode": rc, "inputs": 12,
                               "exr_compression": "rle"}
    if run_hdrmerge:
        if _ensure_hdrmerge():
            henv = dict(os.environ, QT_QPA_PLATFORM="offscreen")
            wall, rss, rc, err = _time_v(["hdrmerge", "-o", work / "hdrmerge.dng", *frames], henv)
            res = {"seconds": wall, "peak_rss_mb": rss, "returncode": rc, "inputs": 6}
            try:
                import rawpy

                with rawpy.imread(str(work / "hdrmerge.dng")) as raw:
                    data = raw.raw_image_visible.astype(np.float64)
                    res["output_finite"] = bool(np.isfinite(data).all())
                    res["output_dtype"] = str(raw.raw_image_visible.dtype)
            except Exception as e:  # report, do not fail the benchmark
                res["output_finite"] = None
                res["output_error"] = f"{type(e).__name__}: {e}"
                res["stderr"] = err
            out["hdrmerge"] = res
            out["ratio_hdrcap_to_hdrmerge"] = out["hdrcap_merge"]["seconds"] / wall
            out["ratio_hdrcap_rle_to_hdrmerge"] = out["hdrcap_merge_rle"]["seconds"] / wall
        else:
            out["hdrmerge"] = {"error": "hdrmerge not installable here"}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpix", type=float, default=24.0, help="megapixels per frame (default 24)")
    ap.add_argument("--iterations", type=int, default=3, help="iterations per photosite (>= 3)")
    ap.add_argument("--no-hdrmerge", action="store_true", help="skip the HDRMerge comparison")
    ap.add_argument("--no-command", action="store_true", help="skip the whole-command comparison")
    args = ap.parse_args(argv)
    shape = _shape(args.mpix)
    import numba

    import hdrcap.pipeline.kernels  # noqa: F401  (sets numba's CPU features before anything compiles)
    from numba.core import config

    report = {"mpix": args.mpix, "cpu_count": os.cpu_count(), "numba_threads": numba.get_num_threads(),
              "vector_width": "512-bit (prefer-256-bit lifted)" if (config.CPU_FEATURES or "").endswith(
                  "-prefer-256-bit") else "numba default"}
    report["kernel"] = bench_kernel(shape, max(3, args.iterations))
    if not args.no_command:
        with tempfile.TemporaryDirectory(prefix="bench_merge_") as tmp:
            report["command"] = bench_commands(shape, Path(tmp), not args.no_hdrmerge)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
