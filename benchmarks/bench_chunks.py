"""Benchmark of ``hdrcap merge --chunks``: peak memory and time of the tiled merge of a huge frame
against the in-memory merge; prints JSON.

A bracket of FRAMES exposures with a matched dark frame each (realistic camera-A: hot
photosites, dark current) and a calibration estimated from simulated frames (PRNU, bias,
dark-current and defect maps with their standard errors) are simulated at a base size and
repeated (``numpy.tile``) to MPIX megapixels, written as uncompressed DNGs and a calibration
archive under the temporary folder (deleted after). Each merge runs as its own ``hdrcap merge``
process; its peak resident memory is the ``ru_maxrss`` that ``os.wait4`` reports for it (the
data are written by a child process: Linux carries a parent's peak RSS into a child it forks,
so the benchmark's own process stays small).

* ``tiled``: the whole size with ``--memory-budget BUDGET`` (tiles chosen automatically);
* at the comparison size COMPARE_MPIX (one that fits in memory): the in-memory merge and the
  tiled one, with whether their EXRs are bit-identical (every channel and the header).

Usage: python benchmarks/bench_chunks.py [--mpix 100] [--compare-mpix 16] [--frames 4]
[--budget 2GB] [--tmp DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BASE = 1250  # side of the simulated base tile, photosites (even)
TIMES = (0.001, 0.004, 0.016, 0.064, 0.25, 1.0)


def _reps(mpix: float) -> tuple[int, int]:
    """Repetitions (down, across) of the base tile for about ``mpix`` megapixels."""
    n = max(1, round(np.sqrt(mpix * 1e6) / BASE))
    return n, n


def _simulate(root: Path, n_frames: int, seed: int = 5):
    """Base-size sensor, calibration, frames and dark frames (seeded)."""
    from hdrcap.experiments.calibrated import calibrated_sensor
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.mock_camera.sensor import preset

    spec = preset("camera-A", realistic=True)
    sensor, cal = calibrated_sensor(spec, seed, (BASE, BASE))
    X = make_scene("hdr", (BASE, BASE), 4.0, 1e5)
    rng = np.random.default_rng(seed)
    times = TIMES[:n_frames]
    frames = [sensor.expose(X, t, rng=rng) for t in times]
    darks = [sensor.expose(X, t, dark=True, rng=rng) for t in times]
    return spec, cal, times, frames, darks


def _write(root: Path, reps, spec, cal, times, frames, darks) -> tuple[list[Path], list[Path], Path]:
    """The base data repeated ``reps`` times, as DNGs and a calibration archive in ``root``."""
    from hdrcap.mock_camera.dng import write_dng
    from hdrcap.pipeline.calibration import save_calibration

    root.mkdir(parents=True, exist_ok=True)
    out = {"frame": [], "dark": []}
    for kind, data in (("frame", frames), ("dark", darks)):
        for i, (t, d) in enumerate(zip(times, data)):
            p = root / f"{kind}_{i}.dng"
            with open(p, "wb") as fh:
                write_dng(
                    fh,
                    np.tile(d, reps),
                    exposure_time=t,
                    iso=100,
                    black_level=spec.mu_R,
                    white_level=spec.white_level,
                    model="Simulated camera-A",
                )
            out[kind].append(p)
    maps = {
        f.name: np.tile(getattr(cal, f.name), reps)
        for f in dataclasses.fields(cal)
        if isinstance(getattr(cal, f.name), np.ndarray)
    }
    save_calibration(root / "cal.npz", cal.replace(**maps))
    return out["frame"], out["dark"], root / "cal.npz"


def _merge(frames, darks, cal, out: Path, extra=()) -> dict:
    """One ``hdrcap merge`` process: wall time, CPU seconds, peak RSS (os.wait4), its JSON."""
    cmd = [sys.executable, "-c", "import sys; from hdrcap.cli import main; sys.exit(main())", "merge"]
    cmd += [*map(str, frames), "--darks", *map(str, darks), "--calibration", str(cal), "-o", str(out), "--json"]
    cmd += list(extra)
    log = out.with_suffix(".log")
    with open(log, "w+") as so, open(log.with_suffix(".err"), "w+") as se:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=so, stderr=se)
        _pid, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        so.seek(0)
        se.seek(0)
        if proc.returncode != 0:
            raise RuntimeError(f"merge failed ({proc.returncode}): {se.read()[-2000:]}")
        info = json.loads(so.read().strip().splitlines()[-1])
    return {
        "seconds": round(wall, 2),
        "cpu_seconds": round(usage.ru_utime + usage.ru_stime, 2),
        "peak_rss_MB": round(usage.ru_maxrss / 1024, 1),
        "chunk_rows": info.get("chunk_rows"),
        "tiles": info.get("tiles"),
        "shape": info["shape"],
    }


def _identical(a: Path, b: Path) -> bool:
    from hdrcap.pipeline.io.exr import read_exr

    x, y = read_exr(a), read_exr(b)
    for head in (x.header, y.header):
        head["merge"].pop("tiling", None)  # how a tiled merge was cut, its only difference
    return (
        set(x.channels) == set(y.channels)
        and all(x.channels[k].tobytes() == y.channels[k].tobytes() for k in x.channels)
        and x.header == y.header
    )


def _generate(root: Path, n_frames: int, reps: list[tuple[int, int]]) -> None:
    """Write the data sets (one folder per repetition count) in a child process: a process's
    peak RSS as ``wait4`` reports it includes its parent's at the fork, so the parent stays small."""
    base = _simulate(root, n_frames)
    for r in reps:
        _write(root / f"x{r[0]}", r, *base)


def _files(folder: Path, n_frames: int) -> tuple[list[Path], list[Path], Path]:
    return (
        [folder / f"frame_{i}.dng" for i in range(n_frames)],
        [folder / f"dark_{i}.dng" for i in range(n_frames)],
        folder / "cal.npz",
    )


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpix", type=float, default=100.0)
    ap.add_argument("--compare-mpix", type=float, default=16.0)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--budget", default="2GB")
    ap.add_argument("--tmp", default=None, help="folder for the temporary files (default: the system's)")
    ap.add_argument("--generate", default=None, help=argparse.SUPPRESS)  # internal: the child that writes data
    args = ap.parse_args(argv)
    small, big = _reps(args.compare_mpix), _reps(args.mpix)
    if args.generate:
        _generate(Path(args.generate), args.frames, [small, big])
        return {}

    out: dict = {
        "frames": args.frames,
        "darks": args.frames,
        "budget": args.budget,
        "cpus": os.cpu_count(),
        "load_before": [round(x, 2) for x in os.getloadavg()],
    }
    with tempfile.TemporaryDirectory(prefix="bench_chunks_", dir=args.tmp) as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                __file__,
                "--generate",
                str(root),
                "--mpix",
                str(args.mpix),
                "--compare-mpix",
                str(args.compare_mpix),
                "--frames",
                str(args.frames),
            ],
            check=True,
        )
        out["simulate_s"] = round(time.perf_counter() - t0, 1)
        sfiles, bfiles = _files(root / f"x{small[0]}", args.frames), _files(root / f"x{big[0]}", args.frames)
        mem = _merge(*sfiles, root / "small_mem.exr")
        tiled_small = _merge(*sfiles, root / "small_tiled.exr", ["--chunks", "500"])
        huge = _merge(*bfiles, root / "big_tiled.exr", ["--memory-budget", args.budget])
        huge["under_budget"] = huge["peak_rss_MB"] * 2**20 < _bytes(args.budget)
        out["compare"] = {
            "in_memory": mem,
            "tiled": tiled_small,
            "bit_identical": _identical(root / "small_mem.exr", root / "small_tiled.exr"),
        }
        out["huge"] = {"tiled": huge}
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out))
    return out


def _bytes(size: str) -> int:
    from hdrcap.pipeline.merge.tiled import parse_memory

    return parse_memory(size)


if __name__ == "__main__":
    main()
