"""Benchmark of ``hdrcap batch``: N runs of MPIX-megapixel brackets on 1, 2, 4, 8 workers; prints JSON.

One bracket (3 exposures with matching dark frames, camera-B, DNG) is simulated and hard-linked
into N run folders (distinct runs to the archive, the same bytes, so every run has the same
merge work). Each configuration runs the whole ``run_batch`` (the local workers' start-up
included) into a fresh archive, ``--repeats`` times, the configurations interleaved (1x1, 2x1,
1x1, 2x1, ...: a slow spell of a shared machine hits every configuration). For each
configuration the JSON gives the median over the repeats (every repeat's figures are under
``repeats``) of:

- wall-clock seconds, with and without the start-up (until every local worker has loaded the
  merge kernels), and the speed-up over 1x1 (the ratio of the medians, and each repeat's own);
- the merge's CPU seconds (the workers' tasks, summed, and per run) against the client's (the
  process that runs ``run_batch``: the pool's threads and the commits; in all, after the
  start-up, per run, and as a fraction of the merge's), the commits' own CPU seconds (the
  client's main thread) and how many commits were made;
- whether every run of the archive is bit-identical to the in-process merge of that bracket;
- the machine's 1-minute load average sampled every second while the configuration ran (the
  machine may be shared: wall-clock figures depend on it, CPU seconds do not).

``done_when`` checks the figures of issue #32 (client CPU <= 10 % of the merge's in every
configuration of every repeat, 2 workers >= 1.6x one worker after start-up by the medians, every
run bit-identical) where the configurations allow.

With ``--server`` each configuration is the ``hdrcap batch`` command instead (``--workers W
--threads T --json``; its report gives the same figures), forked from a command server the
benchmark starts first (``hdrcap server start``, docs/merge.md): the client's process then
starts with the batch's modules imported, once, by the server, as it does for a user who runs a
server.

Usage: python benchmarks/bench_batch.py [--runs 16] [--mpix 2] [--repeats 3] [--configs 1x1 2x1 4x1 8x1] [--server]

A configuration WxT is W local workers with T merge-kernel threads each (the merge kernel is
itself parallel: 1x2 is what ``--workers 1`` gives on 2 cores, 2x1 what ``--workers 2`` gives).
By default 1x1, 2x1, 4x1, 8x1 as far as the machine has the cores.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_command import hdrcap_exe, server_command  # noqa: E402  (after the path set-up above)

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


class _Load:
    """Samples the 1-minute load average every second while it runs."""

    def __init__(self) -> None:
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(os.getloadavg()[0])
            self._stop.wait(1.0)

    def __enter__(self) -> _Load:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def summary(self) -> dict:
        s = self.samples or [os.getloadavg()[0]]
        return {"min": round(min(s), 2), "mean": round(float(np.mean(s)), 2), "max": round(max(s), 2)}


@contextmanager
def _server(root: Path, wanted: bool) -> Iterator[dict | None]:
    """With ``wanted``, a command server of its own (a state folder in ``root``) for the length of
    the block, and the environment that reaches it; else None."""
    if not wanted:
        yield None
        return
    env = dict(os.environ, XDG_RUNTIME_DIR=str(root / "rt"))
    (root / "rt").mkdir()
    started = server_command("start", env)
    if not any("listening at" in line for line in started):
        raise RuntimeError(f"hdrcap server start: {started}")
    try:
        yield env
    finally:
        server_command("stop", env)


def _command(runs: list[Path], archive: Path, workers: int, threads: int, env: dict) -> dict:
    """``hdrcap batch`` of ``runs`` (camera-B) into ``archive``: its JSON report (BatchReport.to_dict)."""
    cmd = [hdrcap_exe(), "batch", *map(str, runs), "-o", str(archive), "--camera", "camera-B", "--json"]
    cmd += ["--workers", str(workers), "--threads", str(threads)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _configuration(cfg: str, runs: list[Path], archive: Path, env: dict | None, ref: dict, settings) -> dict:
    """One configuration WxT of the batch into a fresh ``archive``: its figures."""
    import xarray as xr

    from hdrcap.batch.driver import run_batch

    w, th = (int(v) for v in cfg.split("x"))
    t0 = time.perf_counter()
    with _Load() as load:
        if env is None:
            report = run_batch(runs, archive, settings, workers=w, threads=th, progress=False).to_dict()
        else:
            report = _command(runs, archive, w, th, env)
    wall = time.perf_counter() - t0
    ds = xr.open_zarr(archive)
    identical = ds.sizes["run"] == len(runs) and all(
        np.array_equal(ds[k].isel(run=i).values, ref[k], equal_nan=True) for i in range(ds.sizes["run"]) for k in ref
    )
    ds.close()
    shutil.rmtree(archive)  # before the kernel writes it back: no disk traffic left to the next configuration
    n = max(report["committed"], 1)
    merge_cpu = report["merge_cpu_seconds"]
    startup_cpu = report["startup_cpu_seconds"]
    after = report["client_cpu_seconds"] - startup_cpu
    return {
        "workers": w,
        "threads_per_worker": th,
        "seconds": round(wall, 2),
        "startup_s": round(report["startup_seconds"], 2),
        "seconds_after_startup": round(wall - report["startup_seconds"], 2),
        "runs_per_s_after_startup": round(len(runs) / max(wall - report["startup_seconds"], 1e-9), 3),
        "committed": report["committed"],
        "failed": len(report["failed"]),
        "merge_cpu_s_summed": round(merge_cpu, 3),
        "merge_cpu_s_per_run": round(merge_cpu / n, 4),
        "client_cpu_s": round(report["client_cpu_seconds"], 3),
        "client_cpu_s_startup": round(startup_cpu, 3),
        "client_cpu_s_after_startup": round(after, 3),
        "client_cpu_s_per_run": round(report["client_cpu_seconds"] / n, 4),
        "client_cpu_over_merge_cpu": round(report["client_cpu_seconds"] / merge_cpu, 4),
        "client_cpu_after_startup_over_merge_cpu": round(after / merge_cpu, 4),
        "commit_cpu_s": report["commit_cpu_seconds"],
        "commits": report["commits"],
        "commit_s": round(report["commit_seconds"], 3),
        "load_average_1min": load.summary(),
        "bit_identical": bool(identical),
    }


def _median_of(reps: list[dict]) -> dict:
    """The median over repeats of each number of one configuration (integers stay integers
    where every repeat agrees); ``bit_identical`` only if every repeat was, the load's extremes."""
    out: dict = {}
    for k in reps[0]:
        vals = [r[k] for r in reps]
        if k == "bit_identical":
            out[k] = all(vals)
        elif k == "load_average_1min":
            out[k] = {"min": min(x["min"] for x in vals), "max": max(x["max"] for x in vals)}
        elif all(x == vals[0] for x in vals):
            out[k] = vals[0]
        else:
            out[k] = round(float(np.median(vals)), 4)
    return out


def _default_configs() -> list[str]:
    cpus = os.cpu_count() or 1
    return [f"{w}x1" for w in (1, 2, 4, 8) if w <= cpus] or ["1x1"]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=16)
    ap.add_argument("--mpix", type=float, default=2.0)
    ap.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="repeats of every configuration, interleaved (default 3): the figures are their medians",
    )
    ap.add_argument(
        "--configs",
        nargs="+",
        default=None,
        help="WORKERSxTHREADS: local workers and merge-kernel threads per worker (default: 1x1 2x1 4x1 8x1 as far "
        "as the machine has the cores)",
    )
    ap.add_argument(
        "--server",
        action="store_true",
        help="run each configuration as the `hdrcap batch` command forked from a command server started first "
        "(`hdrcap server start`: the client's imports paid once, by the server) instead of run_batch in this process",
    )
    args = ap.parse_args(argv)
    configs = args.configs or _default_configs()

    from hdrcap.batch.driver import BatchSettings, calibration_identity, find_runs, merge_run

    settings = BatchSettings(calibration=None, camera="camera-B", calibration_id=calibration_identity(None, "camera-B"))
    out: dict = {
        "runs": args.runs,
        "mpix": args.mpix,
        "shape": list(_shape(args.mpix)),
        "cpus": os.cpu_count(),
        "load_before": [round(x, 2) for x in os.getloadavg()],
        "client": "hdrcap batch, forked from a command server" if args.server else "run_batch in this process",
        "configs": {},
    }
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp, _server(Path(tmp), args.server) as env:
        root = Path(tmp)
        t0 = time.perf_counter()
        runs = _runs(root, args.runs, args.mpix)
        out["simulate_s"] = round(time.perf_counter() - t0, 2)
        ref = merge_run(find_runs(runs[:1])[0], settings).run.channels
        every: list[dict] = []
        for r in range(args.repeats):  # the configurations interleaved: a slow spell of the machine hits all
            every.append(
                {cfg: _configuration(cfg, runs, root / f"r{r}-{cfg}.zarr", env, ref, settings) for cfg in configs}
            )
    out["configs"] = {cfg: _median_of([rep[cfg] for rep in every]) for cfg in configs}
    out["repeats"] = every
    after = {k: v["seconds_after_startup"] for k, v in out["configs"].items()}
    if "1x1" in after:  # ratios of the medians, and of each repeat's own pair
        out["speedup_over_1x1_after_startup"] = {k: round(after["1x1"] / v, 3) for k, v in after.items()}
        out["speedup_over_1x1_after_startup_each_repeat"] = {
            k: [round(rep["1x1"]["seconds_after_startup"] / rep[k]["seconds_after_startup"], 3) for rep in every]
            for k in after
        }
    cpu = {k: v["merge_cpu_s_summed"] + v["client_cpu_s"] for k, v in out["configs"].items()}
    if {"1x1", "2x1"} <= set(cpu):  # CPU seconds of 2 workers against 1 (1.0: no overhead of a second worker)
        out["cpu_ratio_2x1_over_1x1"] = round(cpu["2x1"] / cpu["1x1"], 3)
    done: dict = {"every_run_bit_identical": all(c["bit_identical"] for rep in every for c in rep.values())}
    ratios = [c["client_cpu_over_merge_cpu"] for rep in every for c in rep.values()]
    done["client_cpu_le_10pct_of_merge_cpu"] = {
        "worst": max(ratios),  # of every configuration of every repeat
        "worst_after_startup": max(c["client_cpu_after_startup_over_merge_cpu"] for rep in every for c in rep.values()),
        "ok": max(ratios) <= 0.10,
    }
    if "speedup_over_1x1_after_startup" in out and "2x1" in after:
        s = out["speedup_over_1x1_after_startup"]["2x1"]
        done["2x1_ge_1.6x_1x1_after_startup"] = {
            "speedup_of_medians": s,
            "each_repeat": out["speedup_over_1x1_after_startup_each_repeat"]["2x1"],
            "ok": s >= 1.6,
        }
    out["done_when"] = done
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
