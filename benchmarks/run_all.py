"""Run every benchmark in this folder, one after another, and print one JSON object.

Each benchmark is its own script that prints JSON; this runner starts each in a subprocess
(the interpreter running this file), collects the JSON it printed (the last JSON object on its
standard output) and reports it under the benchmark's name together with its exit status and
wall time. A benchmark that fails is reported with the tail of its error output; the others
still run.

    python benchmarks/run_all.py            # quick sizes (a few minutes on 2 cores)
    python benchmarks/run_all.py --full     # the sizes quoted in README and docs (tens of minutes)
    python benchmarks/run_all.py --only bench_merge bench_denoise

Benchmarks that compare with peers install the peers themselves (HDRMerge with apt-get, the
Python peers in their own virtual environment): see each script's docstring.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: name -> (arguments for a quick run, arguments for the full run)
BENCHMARKS: dict[str, tuple[list[str], list[str]]] = {
    "bench_merge": (["--mpix", "2"], []),
    "bench_command": (["--mpix", "2"], []),
    "bench_denoise": (["--width", "1500", "--height", "1000", "--runs", "2"], []),
    "bench_trade": (["--cameras", "camera-B", "--size", "256x128", "--reps", "1", "--timing-runs", "1"], []),
    "bench_peers": (["--size", "256x192"], []),
    "merge_accuracy": (["--seeds", "1"], []),
    "bench_realistic": (["--size", "128", "--seeds", "1,2"], []),
    "calibration_memory": (["--mpix", "2", "--flats", "10"], []),
    "planner_sec8": (["--quick"], ["--quick"]),
    "session_overhead": ([], []),
    "hdrmerge_smoke": (["--size", "256x192"], []),
}
#: Benchmarks skipped in quick mode (they need system packages installed by apt-get).
NEEDS_APT = {"hdrmerge_smoke", "bench_command"}


def last_json(text: str):
    """The last line of ``text`` that parses as a JSON object, else the whole text if it does."""
    try:
        return json.loads(text)
    except ValueError:
        pass
    for line in reversed(text.splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                continue
    return None


def run(name: str, args: list[str], timeout: float) -> dict:
    """Run one benchmark script; return its JSON result with exit status and wall time."""
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(HERE / f"{name}.py"), *args], capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "seconds": round(time.perf_counter() - t0, 1), "args": args}
    out = {"status": proc.returncode, "seconds": round(time.perf_counter() - t0, 1), "args": args}
    if proc.returncode == 0:
        out["result"] = last_json(proc.stdout)
    else:
        out["error"] = proc.stderr.strip().splitlines()[-5:]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true", help="the full sizes (README figures); default: quick sizes")
    ap.add_argument("--only", nargs="+", choices=sorted(BENCHMARKS), help="run only these benchmarks")
    ap.add_argument("--timeout", type=float, default=3600, help="seconds per benchmark (default 3600)")
    args = ap.parse_args(argv)
    names = args.only or [n for n in BENCHMARKS if args.full or n not in NEEDS_APT]
    results = {}
    for name in names:
        print(f"run_all: {name} ...", file=sys.stderr, flush=True)
        results[name] = run(name, BENCHMARKS[name][1 if args.full else 0], args.timeout)
    print(json.dumps({"mode": "full" if args.full else "quick", "benchmarks": results}, indent=1))
    return 0 if all(r["status"] == 0 for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
