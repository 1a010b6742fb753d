"""Benchmark of ``hdrcap batch``: N runs of MPIX-megapixel brackets, 1 worker vs 2; prints JSON.

One bracket (3 exposures with matching dark frames, camera-B, DNG) is simulated and hard-linked
into N run folders (distinct runs to the archive, the same bytes, so every run has the same
merge work). Each configuration runs the whole ``run_batch`` (local cluster start-up included)
into a fresh archive; the JSON gives wall-clock seconds, runs per second, seconds merging
(summed over the workers) and committing (on the client), the speed-ups of 2 workers, whether
every run of every archive is bit-identical to the in-process merge of that bracket, and the
machine's load average before and after (the machine may be shared).

Usage: python benchmarks/bench_batch.py [--runs 16] [--mpix 4] [--configs 1x2 1x1 2x1]

A configuration WxT is W local workers with T merge-kernel threads each (the merge kernel is
itself parallel: 1x2 is what ``--workers 1`` gives on 2 cores, 2x1 what ``--workers 2`` gives);
a trailing ``s`` (e.g. 2x1s) commits the runs one at a time instead of the finished ones
together. CPU seconds (the workers' tasks summed, the client process) do not depend on the
machine's load; wall-clock seconds do.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TIMES = [0.001, 0.01, 0.1]


def _shape(mpix: float) -> tuple[int, int]:
    w = int(round(np.sqrt(mpix * 1e6 * 3 / 2) / 2)) * 2
    h = int(round(mpix * 1e6 / w / 2)) * 2
    return h, w


def _runs(root: Path, n: int, mpix: float) -> list[Path]:
    from hdrcap.mock_camera.simulation import simulate_bracket

    first = root / "run_000"
    simulate_bracket("camera-B", "hdr", TIMES, first, True, _shape(mpix), 4.0, 2e5, 1, None, False, progress=False)
    runs = [first]
    for i in range(1, n):
        d = root / f"run_{i:03d}"
        d.mkdir()
        for f in first.glob("*.dng"):
            os.link(f, d / f.name)
        runs.append(d)
    return runs


@contextlib.contextmanager
def _one_by_one(single: bool):
    """With ``single``, the archive commits the runs of a batch one at a time (the old client)."""
    from hdrcap.batch.archive import Archive

    if not single:
        yield
        return
    many = Archive.commit_many
    Archive.commit_many = lambda self, runs, replace=False: [self.commit(r, replace) for r in runs]
    try:
        yield
    finally:
        Archive.commit_many = many


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=16)
    ap.add_argument("--mpix", type=float, default=4.0)
    ap.add_argument(
        "--configs",
        nargs="+",
        default=["1x2", "1x1", "2x1"],
        help="WORKERSxTHREADS: local workers and merge-kernel threads per worker",
    )
    args = ap.parse_args(argv)

    import xarray as xr

    from hdrcap.batch.driver import BatchSettings, calibration_identity, find_runs, merge_run, run_batch

    settings = BatchSettings(calibration=None, camera="camera-B", calibration_id=calibration_identity(None, "camera-B"))
    out: dict = {
        "runs": args.runs,
        "mpix": args.mpix,
        "shape": list(_shape(args.mpix)),
        "cpus": os.cpu_count(),
        "load_before": [round(x, 2) for x in os.getloadavg()],
        "configs": {},
    }
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        runs = _runs(root, args.runs, args.mpix)
        out["simulate_s"] = round(time.perf_counter() - t0, 2)
        ref = merge_run(find_runs(runs[:1])[0], settings).run.channels
        for cfg in args.configs:
            single = cfg.endswith("s")  # commits one run at a time, as before commit_many
            w, th = (int(v) for v in cfg.rstrip("s").split("x"))
            archive = root / f"w{cfg}.zarr"
            t0 = time.perf_counter()
            with _one_by_one(single):
                report = run_batch(runs, archive, settings, workers=w, threads=th, progress=False)
            wall = time.perf_counter() - t0
            ds = xr.open_zarr(archive)
            identical = ds.sizes["run"] == args.runs and all(
                np.array_equal(ds[k].isel(run=i).values, ref[k], equal_nan=True)
                for i in range(ds.sizes["run"])
                for k in ref
            )
            out["configs"][cfg] = {
                "workers": w,
                "threads_per_worker": th,
                "numba_threads_per_worker": th,
                "commits": "one run at a time" if single else "finished runs together",
                "seconds": round(wall, 2),
                "runs_per_s": round(args.runs / wall, 3),
                "committed": len(report.committed),
                "failed": len(report.failed),
                "merge_s_summed": round(report.merge_seconds, 2),
                "merge_cpu_s_summed": round(report.merge_cpu_seconds, 2),
                "merge_cpu_s_per_run": round(report.merge_cpu_seconds / max(len(report.committed), 1), 3),
                "client_cpu_s": round(report.client_cpu_seconds, 2),
                "startup_s": round(report.startup_seconds, 2),
                "seconds_after_startup": round(wall - report.startup_seconds, 2),
                "commit_s": round(report.commit_seconds, 2),
                "bit_identical": bool(identical),
            }
    sec = {k: v["seconds"] for k, v in out["configs"].items()}
    run_sec = {k: v["seconds_after_startup"] for k, v in out["configs"].items()}
    if {"1x1", "2x1"} <= set(sec):  # the same without the local cluster's start-up
        out["speedup_2x1_over_1x1_after_startup"] = round(run_sec["1x1"] / run_sec["2x1"], 3)
    cpu = {k: v["merge_cpu_s_summed"] + v["client_cpu_s"] for k, v in out["configs"].items()}
    if {"1x1", "2x1"} <= set(cpu):  # CPU seconds of 2 workers against 1 (1.0: no overhead of a second worker)
        out["cpu_ratio_2x1_over_1x1"] = round(cpu["2x1"] / cpu["1x1"], 3)
    if {"2x1", "2x1s"} <= set(sec):
        out["speedup_commit_together_2x1"] = round(sec["2x1s"] / sec["2x1"], 3)
    if {"1x1", "2x1"} <= set(sec):  # scaling: one run per core at a time, 1 worker vs 2
        out["speedup_2x1_over_1x1"] = round(sec["1x1"] / sec["2x1"], 3)
    if {"1x2", "2x1"} <= set(sec):  # the defaults on 2 cores: 1 worker with 2 kernel threads vs 2 workers
        out["speedup_2x1_over_1x2"] = round(sec["1x2"] / sec["2x1"], 3)
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
