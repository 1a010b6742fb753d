"""Whole-command times of `hdrcap calibrate`, `denoise` and `plan` at 24 Mpixel; prints one JSON object.

The inputs are simulated once into ``--work`` (kept there for the next run; ``--clean``
deletes them at the end):

* calibrate: a lab's calibration set written as DNG by the simulated camera
  (:func:`hdrcap.mock_camera.simulation.simulate_calibration_set`): 2 bias frames, 1 saturation
  frame, 100 flats (``--flats``; 12 photon-transfer pairs from 3 % to 85 % of saturation and
  the rest at 75 %) and 2 dark frames at each of 6 exposure times.
* denoise and plan: a 24 Mpixel merged EXR from ``hdrcap merge`` of a simulated 6 + 6 bracket
  of an HDR scene, with the calibration the calibrate command wrote.

Each command runs as a subprocess (the installed ``hdrcap`` console script), one warm-up run
(page cache, numba cache) then best of ``--repeats``; peak memory is the process's maximum
resident set (``os.wait4``). The reference for calibrate is reading the same frame files once
with :func:`hdrcap.pipeline.io.raw.read_raw` and touching every pixel (in this process; alternated
with the command runs), so that ``calibrate_to_read`` is the whole command's time over the
time of reading its inputs once. The parts of denoise and plan (EXR read, filter, EXR write;
map read, planning) are timed in this process.

    python benchmarks/bench_commands24.py [--mpix 24] [--repeats 3] [--only calibrate,denoise,plan] [--clean]
        [--baseline /tmp/hdrcap-bench-speed2/main-src/pkg]   # before/after in one run
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_command import TIMES, _best, hdrcap_exe, run_measured, shape_for  # noqa: E402

CAMERA = "camera-A"
WORK = Path("/tmp/hdrcap-bench-speed2")
#: Plans timed: (target SNR in dB, --quantile or None for the default). The first is a typical
#: request; the second (every eligible pixel at 30 dB) is infeasible on this scene, so the greedy
#: search runs to the 64-exposure limit: the slowest case.
PLAN_CASES = {"20dB_q0.99": (20.0, 0.99), "30dB_default": (30.0, None)}


def simulate(work: Path, shape, n_flats: int) -> dict:
    """Write the calibration set, calibrate it once, merge a bracket with that calibration."""
    from hdrcap.mock_camera.simulation import CALIBRATION_SET, simulate_bracket, simulate_calibration_set

    desc_path = work / "inputs.json"
    if desc_path.exists():
        desc = json.loads(desc_path.read_text())
        if desc["shape"] == list(shape) and desc["n_flats"] == n_flats:
            return desc
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    n_ptc = 2 * len(CALIBRATION_SET["ptc_fractions"])
    cal_set = simulate_calibration_set(
        CAMERA, work / "calset", shape, 3, None, False, progress=False, plan={"n_flats": n_flats - n_ptc}
    )
    cal_path = work / "calibration.npz"
    res = run_measured([hdrcap_exe(), "calibrate", *calibrate_args(cal_set["files"]), "-o", cal_path, "--force"])
    if res["returncode"] != 0:
        raise RuntimeError(f"calibrate failed: {res['stderr']}")
    br = simulate_bracket(CAMERA, "hdr", TIMES, work / "bracket", True, shape, 4.0, 2e5, 1, None, False, False)
    merged = work / "merged.exr"
    cmd = [hdrcap_exe(), "merge", *br["frames"], "--darks", *br["darks"], "--calibration", cal_path, "-o", merged]
    res = run_measured([*cmd, "--force"])
    if res["returncode"] != 0:
        raise RuntimeError(f"merge failed: {res['stderr']}")
    desc = {
        "shape": list(shape),
        "n_flats": n_flats,
        "files": cal_set["files"],
        "calibration": str(cal_path),
        "merged": str(merged),
    }
    desc_path.write_text(json.dumps(desc))
    return desc


def calibrate_args(files: dict) -> list[str]:
    """The frame options of `hdrcap calibrate` for the calibration set's file lists."""
    args: list[str] = []
    for kind in ("bias", "saturation", "flat", "dark"):
        if files.get(kind):
            args += [f"--{kind}", *files[kind]]
    return args


def read_all(paths) -> int:
    """Read every frame file once with read_raw and touch every pixel (the calibrate reference)."""
    from hdrcap.pipeline.io.raw import read_raw

    total = 0
    for p in paths:
        total += int(read_raw(p).data.max())
    return total


def summarise(runs: list[dict]) -> dict:
    """Best wall time, every wall time and the peak RSS of a command's runs."""
    ok = [r for r in runs if r["returncode"] == 0]
    if not ok:
        return {"returncode": runs[-1]["returncode"], "stderr": runs[-1]["stderr"]}
    return {
        "best_seconds": round(min(r["wall_seconds"] for r in ok), 3),
        "all_seconds": [round(r["wall_seconds"], 3) for r in runs],
        "best_cpu_seconds": round(min(r["cpu_seconds"] for r in ok), 3),
        "peak_rss_mb": round(max(r["peak_rss_mb"] for r in ok), 1),
    }


def variants(baseline: Path | None) -> dict[str, dict | None]:
    """The code versions to time: this environment's (``current``) and, with ``baseline``, the
    hdrcap package found at that folder first on PYTHONPATH (``baseline``)."""
    out: dict[str, dict | None] = {"current": None}
    if baseline is not None:
        out["baseline"] = dict(os.environ, PYTHONPATH=str(baseline))
    return out


def time_alternating(cmd, envs: dict, repeats: int, warmup_cmd=None, between=None) -> dict:
    """Each variant's run of ``cmd`` alternating, after one warm-up run each (``warmup_cmd``, by
    default ``cmd`` itself: page cache, numba cache); ``between()`` runs before each round."""
    for env in envs.values():
        run_measured(warmup_cmd or cmd, env=env)
    runs: dict[str, list] = {name: [] for name in envs}
    for _ in range(repeats):
        if between is not None:
            between()
        for name, env in envs.items():
            runs[name].append(run_measured(cmd, env=env))
    out = {name: summarise(r) for name, r in runs.items()}
    if all("best_seconds" in v for v in out.values()) and "baseline" in out:
        out["speedup"] = round(out["baseline"]["best_seconds"] / out["current"]["best_seconds"], 2)
    out["last_stdout"] = runs["current"][-1]["stdout"]
    return out


def bench_calibrate(desc: dict, work: Path, repeats: int, envs: dict) -> dict:
    """The calibrate command (each variant) and the read-once reference, alternating; the warm-up
    runs calibrate a short set (bias, saturation, 6 flats, the darks) to load the numba caches."""
    files = desc["files"]
    paths = [p for k in ("bias", "saturation", "flat", "dark") for p in files.get(k, [])]
    cmd = [hdrcap_exe(), "calibrate", *calibrate_args(files), "-o", work / "cal_out.npz", "--force"]
    short = dict(files, flat=files["flat"][:6])
    warm = [hdrcap_exe(), "calibrate", *calibrate_args(short), "-o", work / "cal_warm.npz", "--force"]
    reads: list[float] = []

    def read_once():
        t0 = time.perf_counter()
        read_all(paths)
        reads.append(time.perf_counter() - t0)

    out = {"n_frames": len(paths), "n_flats": len(files["flat"])}
    out["command"] = time_alternating(cmd, envs, repeats, warm, read_once)
    out["command"].pop("last_stdout")
    out["read_once_best_seconds"] = round(min(reads), 3)
    out["read_once_all_seconds"] = [round(s, 3) for s in reads]
    for name in envs:
        if "best_seconds" in out["command"][name]:
            out[f"{name}_to_read"] = round(out["command"][name]["best_seconds"] / min(reads), 2)
    return out


def bench_denoise(desc: dict, work: Path, repeats: int, envs: dict) -> dict:
    """The denoise command (each variant), then its parts in this process (EXR read, filter, EXR write
    by the one writer's storage rules)."""
    from hdrcap.pipeline.denoise.files import denoise_result
    from hdrcap.pipeline.io.results import read_result, write_result

    cmd = [hdrcap_exe(), "denoise", desc["merged"], "-o", work / "denoised.exr", "--force"]
    out = {"command": time_alternating(cmd, envs, repeats)}
    out["command"].pop("last_stdout")
    read_s, image = _best(lambda: read_result(desc["merged"]), repeats)
    filt_s, res = _best(lambda: denoise_result(image), repeats)
    write_s = {}
    for comp in ("zip", "zstd", "rle"):  # the default first; the others are --exr-compression
        write_s[comp], _ = _best(
            lambda: write_result(res, work / "parts.exr", force=True, compression=comp),  # noqa: B023
            repeats,
        )
    (work / "parts.exr").unlink(missing_ok=True)
    out["parts_best_seconds"] = {
        "read_exr": round(read_s, 3),
        "denoise": round(filt_s, 3),
        "write_exr": round(write_s["zip"], 3),
        "write_exr_zstd": round(write_s["zstd"], 3),
        "write_exr_rle": round(write_s["rle"], 3),
    }
    return out


def bench_plan(desc: dict, repeats: int, envs: dict) -> dict:
    """The plan command on the merged map for each of PLAN_CASES (each variant), then its parts
    in this process (map read, planning)."""
    from hdrcap.pipeline.calibration import load_calibration
    from hdrcap.planner import plan_exposures
    from hdrcap.planner.ladder import parse_times
    from hdrcap.planner.meter import read_irradiance_map

    out: dict = {}
    read_s, X = _best(lambda: read_irradiance_map(desc["merged"]), repeats)
    out["read_map_best_seconds"] = round(read_s, 3)
    cal = load_calibration(desc["calibration"])
    for name, (snr_db, quantile) in PLAN_CASES.items():
        args = ["--calibration", desc["calibration"], "--irradiance", desc["merged"], "--target-snr-db", snr_db]
        cmd = [hdrcap_exe(), "plan", *args, "--json"] + ([] if quantile is None else ["--quantile", quantile])
        case = {"command": time_alternating(cmd, envs, repeats)}
        try:
            plan = json.loads(case["command"].pop("last_stdout"))
            case["plan"] = {k: plan.get(k) for k in ("exposures", "feasible", "predicted_min_snr_db")}
        except (ValueError, KeyError):
            pass
        kw = {} if quantile is None else {"quantile": quantile}
        plan_s, _ = _best(lambda: plan_exposures(cal, X, snr_db, parse_times(()), **kw), repeats)  # noqa: B023
        case["plan_exposures_best_seconds"] = round(plan_s, 3)
        out[name] = case
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mpix", type=float, default=24.0, help="megapixels per frame (default 24)")
    ap.add_argument("--flats", type=int, default=100, help="flat fields in the calibration set (default 100)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each command (best is reported)")
    ap.add_argument("--only", default="calibrate,denoise,plan", help="commands to time, comma-separated")
    ap.add_argument("--work", type=Path, default=WORK, help=f"folder of the simulated inputs (default {WORK})")
    ap.add_argument(
        "--baseline",
        type=Path,
        help="also time the hdrcap package found in this folder (e.g. an export of main with the package "
        "folders linked under hdrcap/), alternating with this environment's",
    )
    ap.add_argument("--clean", action="store_true", help="delete the simulated inputs at the end")
    args = ap.parse_args(argv)
    shape = shape_for(args.mpix)
    t0 = time.perf_counter()
    desc = simulate(args.work, shape, args.flats)
    report = {
        "mpix": args.mpix,
        "shape": list(shape),
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "simulate_seconds": round(time.perf_counter() - t0, 1),
        "git": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent
        ).stdout.strip(),
    }
    envs = variants(args.baseline)
    only = set(args.only.split(","))
    if "calibrate" in only:
        report["calibrate"] = bench_calibrate(desc, args.work, args.repeats, envs)
    if "denoise" in only:
        report["denoise"] = bench_denoise(desc, args.work, args.repeats, envs)
    if "plan" in only:
        report["plan"] = bench_plan(desc, args.repeats, envs)
    report["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(report, indent=1))
    if args.clean:
        shutil.rmtree(args.work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
