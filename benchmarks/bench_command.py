"""Whole-command benchmark: `hdrcap merge` against HDRMerge on simulated brackets; prints one JSON object.

Both tools run as commands from the DNG files to their output file, alternating, in the same
run (quote ratios from one run: the machine may be shared), after one warm-up run each; each
case reports the best and the median wall time of ``--repeats`` runs, and the user and system
CPU time of each command (``os.wait4``) separately:

* ``large_exr``: hdrcap, the installed ``hdrcap merge`` console script on 6 frames + 6 matched
  dark frames of ``--mpix`` megapixels with a calibration file that has the sensor's PRNU and
  dark-current maps, default options and default EXR settings; HDRMerge ``hdrmerge -o out.dng
  frame_*.dng`` on the 6 bright frames (``QT_QPA_PLATFORM=offscreen``).
* ``large_dng``: the same hdrcap command writing ``-o out.dng`` (float DNG), same HDRMerge run.
* ``small``: 1.2 Mpixel, 3 frames + 3 dark frames, EXR (hdrcap's start-up against HDRMerge's),
  each command in its own process (``HDRCAP_SERVER=0``).
* ``small_server``: the same command with a command server running (``hdrcap server start``
  before the runs, ``hdrcap server stop`` after, in a folder of the benchmark's own): each
  command is forked from the warm server; the same HDRMerge runs. Its CPU times and peak RSS
  are the client's only (the command's process is the server's child, not the launcher's).
* ``cold`` (unless ``--no-cold``): the first ``hdrcap merge`` after an install, 64x48 pixels, on
  an empty numba cache (``NUMBA_CACHE_DIR`` in a new folder): the kernels' compilation, and the
  line it prints.

The hdrcap commands run without ``PYTHONDONTWRITEBYTECODE`` (an installed package has its
bytecode written: the warm-up run writes it). Peak memory is each process's maximum resident
set. The same run also times, in this process, the parts of hdrcap's command: reading the 12
files (direct DNG decoding, and LibRaw for comparison), ``check_frames``, the merge kernel on
the frames in memory, and the EXR write; ``--exr-table`` adds the size and write time of every
EXR compression and channel precision.

Usage::

    python benchmarks/bench_command.py --setup        # apt-get install -y hdrmerge
    python benchmarks/bench_command.py [--mpix 24] [--repeats 3] [--exr-table] [--no-cold]
    python benchmarks/bench_command.py --cases small,small_server --no-cold   # the small cases only
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

TIMES = (1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0)
CAMERA = "camera-A"


def shape_for(mpix: float) -> tuple[int, int]:
    """(height, width) of a 3:2 mosaic of about ``mpix`` megapixels, even sides."""
    w = round(np.sqrt(mpix * 1e6 * 3 / 2) / 2) * 2
    h = round(mpix * 1e6 / w / 2) * 2
    return h, w


#: Runs a command and reports its wall time and its own peak RSS. A child forked from a large
#: process inherits that process's RSS high-water mark (Linux keeps it across exec), so the
#: command is started from this small launcher, never from the benchmark process itself.
_LAUNCHER = r"""
import json, os, subprocess, sys, time
cmd, env = json.loads(sys.argv[1]), json.loads(sys.argv[2])
t0 = time.perf_counter()
proc = subprocess.Popen(cmd, env=env)
_, status, usage = os.wait4(proc.pid, 0)
wall = time.perf_counter() - t0
print(json.dumps({"returncode": os.waitstatus_to_exitcode(status), "wall_seconds": wall,
                  "cpu_seconds": usage.ru_utime + usage.ru_stime, "user_seconds": usage.ru_utime,
                  "sys_seconds": usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024.0}),
      file=open(sys.argv[3], "w"))
"""


def run_measured(cmd, env=None, cwd=None) -> dict:
    """Run ``cmd``; return wall time, CPU time (user + system, and each) in s, peak RSS (MB,
    os.wait4), return code, stdout/stderr tails."""
    with tempfile.TemporaryDirectory(prefix="bench_run_") as tmp:
        report = Path(tmp) / "report.json"
        out, err = Path(tmp) / "out", Path(tmp) / "err"
        with open(out, "w") as fo, open(err, "w") as fe:
            subprocess.run(
                [
                    sys.executable,
                    "-c",
                    _LAUNCHER,
                    json.dumps([str(c) for c in cmd]),
                    json.dumps(dict(os.environ if env is None else env)),
                    str(report),
                ],
                stdout=fo,
                stderr=fe,
                cwd=cwd,
                check=False,
            )
        stdout, stderr = out.read_text().strip(), err.read_text().strip()
        res = (
            json.loads(report.read_text())
            if report.exists()
            else {"returncode": -1, "wall_seconds": None, "cpu_seconds": None, "peak_rss_mb": None}
        )
    return res | {"stdout": stdout.splitlines()[-1] if stdout else "", "stderr": stderr[-400:]}


def ensure_hdrmerge() -> bool:
    """Install HDRMerge with apt-get when it is missing; whether it is on PATH."""
    if shutil.which("hdrmerge") is None:
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        if subprocess.call(["apt-get", "install", "-y", "hdrmerge"], env=env) != 0:
            subprocess.call(["apt-get", "update", "-qq"], env=env)
            subprocess.call(["apt-get", "install", "-y", "hdrmerge"], env=env)
    return shutil.which("hdrmerge") is not None


def simulate(work: Path, shape, times=TIMES) -> dict:
    """Write the bracket of ``times`` with one dark frame each (6 + 6 by default) and a
    calibration file with PRNU and dark-current maps."""
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.pipeline.calibration import save_calibration
    from hdrcap.pipeline.params import Calibration

    spec = PRESETS[CAMERA]
    for i in range(len(times)):  # a --work folder of an earlier run: simulated afresh (same seed)
        for name in (f"frame_{i}.dng", f"dark_{i}.dng"):
            (work / name).unlink(missing_ok=True)
    cam = SimulatedCamera(spec, make_scene("hdr", shape, 4.0, 2e5), seed=1)
    frames = [cam.capture_to(work / f"frame_{i}.dng", t) for i, t in enumerate(times)]
    darks = [cam.capture_to(work / f"dark_{i}.dng", t, dark=True) for i, t in enumerate(times)]
    cal = Calibration(
        spec.nominal_params(),
        prnu=cam.sensor.prnu.astype(np.float32),
        dark_current_map=cam.sensor.dark_current_map().astype(np.float32),
    )
    cal_path = save_calibration(work / "calibration.npz", cal, force=True)
    return {"frames": frames, "darks": darks, "calibration": cal_path}


def hdrcap_exe() -> str:
    """The ``hdrcap`` console script of this interpreter's environment."""
    exe = Path(sys.executable).with_name("hdrcap")
    return str(exe) if exe.exists() else "hdrcap"


def hdrcap_cmd(sim: dict, out: Path) -> list:
    return [
        hdrcap_exe(),
        "merge",
        *sim["frames"],
        "--darks",
        *sim["darks"],
        "--calibration",
        sim["calibration"],
        "-o",
        out,
        "--force",
        "--json",
    ]


def _hdrcap_env(**extra: str) -> dict:
    """The environment of hdrcap's commands: bytecode written as in an installed package."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return env | extra


def _summary(runs: list) -> dict:
    """Best and median wall time, the CPU times of the best run and of the median, peak RSS."""
    ok = [r for r in runs if r["returncode"] == 0]
    if not ok:
        return {"best_seconds": None, "returncode": runs[-1]["returncode"], "stderr": runs[-1]["stderr"]}
    by_wall = sorted(ok, key=lambda r: r["wall_seconds"])
    best, median = by_wall[0], by_wall[len(by_wall) // 2]
    return {
        "best_seconds": round(best["wall_seconds"], 3),
        "median_seconds": round(median["wall_seconds"], 3),
        "all_seconds": [round(r["wall_seconds"], 3) for r in runs],
        "best_user_seconds": round(best["user_seconds"], 3),
        "best_sys_seconds": round(best["sys_seconds"], 3),
        "median_user_seconds": round(statistics.median(r["user_seconds"] for r in ok), 3),
        "median_sys_seconds": round(statistics.median(r["sys_seconds"] for r in ok), 3),
        "peak_rss_mb": round(max(r["peak_rss_mb"] for r in ok), 1),
        "returncode": 0,
    }


def compare_commands(cases: dict, work: Path, repeats: int) -> dict:
    """Every case's commands (``{"hdrcap": cmd, "hdrmerge": cmd or None, "env": hdrcap's
    environment (optional)}``) alternating, one warm-up run each (page cache, numba cache,
    bytecode), ``repeats`` counted runs each."""
    henv = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_RUNTIME_DIR=str(work))
    hdrmerge_runs: dict[tuple, list] = {}  # one HDRMerge command shared by cases (the same frames)
    runs: dict[str, dict[str, list]] = {name: {"hdrcap": []} for name in cases}

    def one(cmd, env, out=None):
        if out is not None:
            Path(out).unlink(missing_ok=True)
        return run_measured(cmd, env=env)

    for case in cases.values():
        one(case["hdrcap"], case.get("env") or _hdrcap_env())
        if case["hdrmerge"]:
            one(case["hdrmerge"], henv, case["hdrmerge"][2])
    for _ in range(repeats):
        for name, case in cases.items():
            runs[name]["hdrcap"].append(one(case["hdrcap"], case.get("env") or _hdrcap_env()))
            key = tuple(map(str, case["hdrmerge"] or ()))
            if key and len(hdrmerge_runs.setdefault(key, [])) < repeats:
                hdrmerge_runs[key].append(one(case["hdrmerge"], henv, case["hdrmerge"][2]))
    out = {}
    for name, case in cases.items():
        res = {"hdrcap": _summary(runs[name]["hdrcap"])}
        key = tuple(map(str, case["hdrmerge"] or ()))
        if key:
            res["hdrmerge"] = _summary(hdrmerge_runs[key])
            a, b = res["hdrcap"], res["hdrmerge"]
            if a["best_seconds"] and b["best_seconds"]:
                res["ratio_best"] = round(a["best_seconds"] / b["best_seconds"], 3)
                res["ratio_median"] = round(a["median_seconds"] / b["median_seconds"], 3)
                cpu = lambda r: r["median_user_seconds"] + r["median_sys_seconds"]  # noqa: E731
                res["ratio_median_cpu"] = round(cpu(a) / cpu(b), 3)
        out[name] = res
    return out


def server_command(action: str, env: dict) -> list:
    """``hdrcap server ACTION`` run with ``env``: its output lines."""
    cmd = [hdrcap_exe(), "server", action]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120, check=False)
    return (proc.stdout + proc.stderr).strip().splitlines()


def cold_first_merge(work: Path) -> dict:
    """The first merge after an install: 64x48 pixels, 3 frames + 3 darks, an empty numba cache."""
    from hdrcap.pipeline._numba_target import COMPILE_NOTICE

    small = work / "cold"
    small.mkdir(exist_ok=True)
    sim = simulate(small, (48, 64), TIMES[-3:])
    with tempfile.TemporaryDirectory(prefix="bench_numba_cache_") as cache:
        first = run_measured(hdrcap_cmd(sim, small / "o.exr"), env=_hdrcap_env(NUMBA_CACHE_DIR=cache))
        second = run_measured(hdrcap_cmd(sim, small / "o.exr"), env=_hdrcap_env(NUMBA_CACHE_DIR=cache))
    return {
        "cold_seconds": round(first["wall_seconds"], 2),
        "cold_user_seconds": round(first["user_seconds"], 2),
        "cold_sys_seconds": round(first["sys_seconds"], 2),
        "cold_notice_lines": first["stderr"].count(COMPILE_NOTICE),
        "warm_seconds": round(second["wall_seconds"], 2),
        "warm_notice_lines": second["stderr"].count(COMPILE_NOTICE),
        "returncodes": [first["returncode"], second["returncode"]],
    }


def _best(fn, repeats: int):
    """(best wall time in s, last result) of ``repeats`` calls of ``fn``."""
    best, res = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = fn()
        best = min(best, time.perf_counter() - t0)
    return best, res


def time_parts(sim: dict, repeats: int) -> dict:
    """hdrcap's command in parts, in this process: read, check_frames, kernel, EXR write (the
    merge's channels at the default settings)."""
    from hdrcap.pipeline.calibration import load_calibration
    from hdrcap.pipeline.io import exr as pexr
    from hdrcap.pipeline.io import raw as pio
    from hdrcap.pipeline.io.results import write_result
    from hdrcap.pipeline.merge.accumulator import merge_arrays

    paths = [*sim["frames"], *sim["darks"]]
    parts: dict[str, float] = {}
    parts["read_seconds"], frames = _best(lambda: [pio.read_frame(p) for p in paths], repeats)
    parts["read_and_touch_seconds"], _ = _best(lambda: [int(pio.read_frame(p).data.max()) for p in paths], repeats)
    parts["read_libraw_seconds"], _ = _best(lambda: [pio._libraw_decode(Path(p)) for p in paths], repeats)
    parts["check_frames_seconds"], _ = _best(
        lambda: (pio.check_frames(frames[:6]), pio.check_frames(frames[6:], "dark frame")), repeats
    )
    cal = load_calibration(sim["calibration"])
    values, darks = [f.data for f in frames[:6]], [f.data for f in frames[6:]]
    times = [f.exposure_time for f in frames[:6]]
    small = cal.replace(prnu=cal.prnu[:64], dark_current_map=cal.dark_current_map[:64])
    merge_arrays([v[:64] for v in values], times, small, darks=[d[:64] for d in darks])  # compile or load the cache
    parts["kernel_seconds"], res = _best(lambda: merge_arrays(values, times, cal, darks=darks), repeats)
    image = pexr.ExrContent({"irradiance": res.irradiance, "sigma": res.sigma, "nexp": res.nexp}, {"unit": "e-/s"})
    with tempfile.TemporaryDirectory(prefix="bench_exr_") as tmp:
        out = Path(tmp) / "o.exr"
        parts["write_seconds"], _ = _best(lambda: write_result(res, out, force=True), repeats)  # the command's EXR
    return parts, image


EXR_VARIANTS = {
    "float32 x3": {},
    "sigma half": {"sigma": "half"},
    "sigma half, nexp uint": {"sigma": "half", "nexp": "uint"},
}


def exr_table(image, repeats: int) -> dict:
    """Size (MB) and write time (s) of every compression x precision, and the loss of half sigma."""
    from hdrcap.pipeline.io import exr as pio

    table = {}
    sig = image.channels["sigma"]
    with tempfile.TemporaryDirectory(prefix="bench_exr_") as tmp:
        path = Path(tmp) / "o.exr"
        for comp in pio.EXR_COMPRESSIONS:
            for label, prec in EXR_VARIANTS.items():
                try:
                    sec, _ = _best(
                        partial(pio.write_exr, path, *image, force=True, compression=comp, precision=prec), repeats
                    )
                except ValueError as err:
                    table[f"{comp}, {label}"] = {"error": str(err)}
                    continue
                read_sec, _ = _best(partial(pio.read_exr, path), 1)
                table[f"{comp}, {label}"] = {
                    "write_seconds": round(sec, 3),
                    "read_seconds": round(read_sec, 3),
                    "megabytes": round(path.stat().st_size / 1e6, 1),
                }
        for threads in (1, 2):
            sec, _ = _best(partial(pio.write_exr, path, *image, force=True, threads=threads), repeats)
            table[f"zip, float32 x3, {threads} thread(s)"] = {"write_seconds": round(sec, 3)}
    finite = np.isfinite(sig) & (sig != 0)
    rel = np.abs(sig[finite].astype(np.float16).astype(np.float32) / sig[finite] - 1)
    table["sigma_half_max_relative_error"] = float(rel.max()) if rel.size else None
    table["sigma_range"] = [float(np.abs(sig[finite]).min()), float(np.abs(sig[finite]).max())]
    return table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--setup", action="store_true", help="install HDRMerge with apt-get, then exit")
    ap.add_argument("--mpix", type=float, default=24.0, help="megapixels per frame (default 24)")
    ap.add_argument("--small-mpix", type=float, default=1.2, help="megapixels of the small bracket (default 1.2)")
    ap.add_argument("--repeats", type=int, default=3, help="counted runs of each command")
    ap.add_argument("--no-hdrmerge", action="store_true", help="time hdrcap only")
    ap.add_argument("--no-cold", action="store_true", help="skip the first merge on an empty numba cache")
    ap.add_argument("--exr-table", action="store_true", help="also time every EXR compression and precision")
    ap.add_argument("--work", type=Path, help="keep the simulated files in this folder (default: a temporary one)")
    ap.add_argument(
        "--cases",
        default="large_exr,large_dng,small,small_server",
        help="comma-separated cases to time (default: all four)",
    )
    args = ap.parse_args(argv)
    if args.setup:
        return 0 if ensure_hdrmerge() else 1
    with_hdrmerge = not args.no_hdrmerge and shutil.which("hdrmerge") is not None
    shape = shape_for(args.mpix)
    report = {
        "mpix": args.mpix,
        "shape": list(shape),
        "small_shape": list(shape_for(args.small_mpix)),
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg(),
        "frames": len(TIMES),
        "darks": len(TIMES),
        "calibration": "PRNU and dark-current maps",
        "exr": "default (zip, float32 irradiance, half sigma where it fits, uint nexp and quality)",
    }
    if not args.no_hdrmerge and not with_hdrmerge:
        report["hdrmerge"] = "not on PATH: run with --setup"
    with tempfile.TemporaryDirectory(prefix="bench_command_") as tmp:
        work = args.work or Path(tmp)
        (work / "small").mkdir(parents=True, exist_ok=True)
        names = args.cases.split(",")
        large = any(name.startswith("large") for name in names)
        sim = simulate(work, shape) if large else {"frames": [], "darks": [], "calibration": ""}
        small = simulate(work / "small", shape_for(args.small_mpix), TIMES[-3:])

        def hdrmerge(s, folder):
            return ["hdrmerge", "-o", folder / "hdrmerge.dng", *s["frames"]] if with_hdrmerge else None

        server_env = _hdrcap_env(XDG_RUNTIME_DIR=tempfile.mkdtemp(prefix="bench_srv_"))
        small_cmd = hdrcap_cmd(small, work / "small" / "hdrcap.exr")
        cases = {
            "large_exr": {"hdrcap": hdrcap_cmd(sim, work / "hdrcap.exr"), "hdrmerge": hdrmerge(sim, work)},
            "large_dng": {"hdrcap": hdrcap_cmd(sim, work / "hdrcap.dng"), "hdrmerge": hdrmerge(sim, work)},
            "small": {
                "hdrcap": small_cmd,
                "hdrmerge": hdrmerge(small, work / "small"),
                "env": _hdrcap_env(HDRCAP_SERVER="0"),
            },
            "small_server": {"hdrcap": small_cmd, "hdrmerge": hdrmerge(small, work / "small"), "env": server_env},
        }
        cases = {name: cases[name] for name in names}
        if "small_server" in cases:
            report["server_start"] = server_command("start", server_env)
        try:
            report["commands"] = compare_commands(cases, work, args.repeats)
        finally:
            if "small_server" in cases:
                report["server_stop"] = server_command("stop", server_env)
                shutil.rmtree(server_env["XDG_RUNTIME_DIR"], ignore_errors=True)
        report["load_average_after"] = os.getloadavg()
        if not args.no_cold:
            report["first_merge"] = cold_first_merge(work)
        if large:  # the parts of the large command
            report["hdrcap_parts"], image = time_parts(sim, args.repeats)
        if large and args.exr_table:
            report["exr"] = exr_table(image, args.repeats)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
