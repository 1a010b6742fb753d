"""Soak: many simulated runs of one job in one process (as ``hdrcap run --repeat N`` does), with
busy, disconnect, corrupt-file and hang faults (each repetition draws its own), sampling the
process's resident memory and open files; prints JSON with the slope of both against the run
number (after a warm-up) and the fault counts. A plateau, not a slope, is the pass.

    python benchmarks/soak.py                       # 10 000 runs
    python benchmarks/soak.py --runs 2000 --minutes 20 --every 50

Each run takes 4 frames (2 exposure times, matched dark frames) on a 32x24 simulated camera,
merges them and writes the EXR and the preview, then its folder is removed (the disk stays
flat); the lock folder must stay empty.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hdrcap.acquire.capture.job import job_from_dict  # noqa: E402
from hdrcap.acquire.capture.manifest import EventLog  # noqa: E402
from hdrcap.acquire.capture.run import run_job  # noqa: E402
from hdrcap.pipeline.errors import HdrcapError  # noqa: E402

FAULTS = {
    "busy_rate": 0.2,
    "disconnect_rate": 0.05,
    "corrupt_rate": 0.05,
    "hang_rate": 0.02,
    "hang_s": 0.002,
    "hang_ignores_timeout": True,
    "reconnect_fail_rate": 0.3,
    "reconnect_failures": 2,
    "renumber_rate": 0.3,
}

# the session's fault kinds (what it does) named by the fault injected (what happened)
FAULT_NAMES = {"busy": "busy", "reconnect": "disconnect", "recapture": "corrupt"}


def _job(root: Path) -> Any:
    return job_from_dict(
        {
            "job": {"name": "soak"},
            "camera": {"backend": "mock", "size": "32x24", "seed": 7, "faults": FAULTS},
            "scene": {"decades": 3.0, "x_max": 2e4},
            "exposure": {"mode": "bracket", "times": [0.004, 0.0666667]},
            "darks": {"strategy": "matched"},
            "session": {"backoff_s": 1e-4, "max_backoff_s": 1e-4, "timeout_s": 0.01, "max_attempts": 60},
            "output": {"folder": str(root / "runs" / "{job}-{n}")},
        },
        path=root / "soak.toml",
    )


def _rss_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def _open_files() -> int:
    return len(os.listdir("/proc/self/fd"))


def _slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys against xs."""
    n = len(xs)
    if n < 2:
        return 0.0
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10_000)
    ap.add_argument("--minutes", type=float, default=None, help="stop after this long (report the runs done)")
    ap.add_argument("--every", type=int, default=100, help="sample RSS and open files every N runs")
    ap.add_argument("--warm-up", type=int, default=None, help="runs left out of the slope (default: a tenth)")
    args = ap.parse_args()
    logging.getLogger("hdrcap").addHandler(logging.NullHandler())
    logging.getLogger("hdrcap").propagate = False
    root = Path(tempfile.mkdtemp(prefix="hdrcap-soak-"))
    os.environ["HDRCAP_LOCK_DIR"] = str(root / "locks")
    job = _job(root)
    faults: Counter[str] = Counter()
    failures: Counter[int] = Counter()
    samples: list[tuple[int, int, int]] = [(0, _rss_bytes(), _open_files())]
    t0 = time.monotonic()
    done = 0
    try:
        for n in range(args.runs):
            if args.minutes is not None and time.monotonic() - t0 > 60 * args.minutes:
                break
            run_dir = root / "runs" / f"soak-{n}"
            try:
                run_job(job, n=n, progress=False, echo=lambda _s: None)
            except HdrcapError as err:
                failures[err.exit_code] += 1
            for e in EventLog(run_dir).events():
                if e["event"] == "fault":
                    faults["hang" if "timeout" in e.get("error", "") else FAULT_NAMES.get(e["kind"], e["kind"])] += 1
            shutil.rmtree(run_dir, ignore_errors=True)
            done = n + 1
            if done % args.every == 0:
                samples.append((done, _rss_bytes(), _open_files()))
        elapsed = time.monotonic() - t0
        locks_left = len(list((root / "locks").iterdir())) if (root / "locks").exists() else 0
    finally:
        shutil.rmtree(root, ignore_errors=True)
    warm = args.warm_up if args.warm_up is not None else done // 10
    tail = [s for s in samples if s[0] >= warm]
    xs = [float(s[0]) for s in tail]
    rss_slope = _slope(xs, [float(s[1]) for s in tail])
    fd_slope = _slope(xs, [float(s[2]) for s in tail])
    half = [s for s in samples if s[0] >= done // 2]
    middle = min(samples, key=lambda s: abs(s[0] - done // 2))
    print(
        json.dumps(
            {
                "benchmark": "soak",
                "runs": done,
                "runs_asked": args.runs,
                "elapsed_s": round(elapsed, 1),
                "s_per_run": round(elapsed / max(done, 1), 4),
                "extrapolated_s_for_runs_asked": round(elapsed / max(done, 1) * args.runs, 0),
                "failed_runs": dict(failures),
                "faults": dict(faults),
                "lock_files_left": locks_left,
                "rss_start_mb": round(samples[0][1] / 1e6, 1),
                "rss_after_warm_up_mb": round(tail[0][1] / 1e6, 1) if tail else None,
                "rss_middle_mb": round(middle[1] / 1e6, 1),
                "rss_middle_run": middle[0],
                "rss_end_mb": round(samples[-1][1] / 1e6, 1),
                "rss_slope_kb_per_1000_runs": round(rss_slope * 1000 / 1e3, 1),
                "rss_second_half_slope_kb_per_1000_runs": round(
                    _slope([float(s[0]) for s in half], [float(s[1]) for s in half]) * 1000 / 1e3, 1
                ),
                "open_files_min_max": [min(s[2] for s in samples), max(s[2] for s in samples)],
                "open_files_slope_per_1000_runs": round(fd_slope * 1000, 3),
                "warm_up_runs": warm,
                "samples": [[s[0], s[1], s[2]] for s in samples],
            }
        )
    )


if __name__ == "__main__":
    main()
