"""Resident memory of `hdrcap serve` before and after reading a (large) run folder; prints JSON.

Usage: ``python benchmarks/serve_memory.py ROOT RUN [--port 8790]``: starts ``hdrcap serve ROOT``
on 127.0.0.1, reads the runs list, the run's detail and page, a page of its frames and the last
200 events, and reports the server process's resident memory (``VmRSS``) and its peak
(``VmHWM``) from ``/proc/PID/status`` after each request (Linux only).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import urllib.request


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root")
    ap.add_argument("run")
    ap.add_argument("--port", type=int, default=8790)
    args = ap.parse_args()
    proc = subprocess.Popen(
        [sys.executable, "-m", "hdrcap", "serve", args.root, "--port", str(args.port)],
        stderr=subprocess.PIPE,
        text=True,
    )
    base = f"http://127.0.0.1:{args.port}"

    def memory() -> dict:
        status = dict(line.split(":", 1) for line in open(f"/proc/{proc.pid}/status"))
        return {k: round(int(status[v].split()[0]) / 1024, 1) for k, v in (("rss_mb", "VmRSS"), ("peak_mb", "VmHWM"))}

    def get(path: str, events: int | None = None) -> dict:
        t0 = time.monotonic()
        with urllib.request.urlopen(base + path, timeout=600) as res:
            if events is None:
                n = len(res.read())
            else:  # an event stream: read until that many events came (a running run's never ends)
                n, seen = 0, 0
                while seen < events:
                    line = res.readline()
                    if not line:
                        break
                    n += len(line)
                    seen += line.startswith(b"event: event")
        return {"path": path, "bytes": n, "s": round(time.monotonic() - t0, 3), **memory()}

    try:
        proc.stderr.readline()  # "hdrcap serve: http://..." once it listens
        get("/static/style.css")
        out = {"start": memory(), "requests": []}
        run = args.run
        for path in (
            "/api/runs",
            "/",
            f"/api/runs/{run}",
            f"/runs/{run}",
            f"/api/runs/{run}/files?folder=frames&offset=4900&limit=100",
        ):
            out["requests"].append(get(path))
        out["requests"].append(get(f"/api/runs/{run}/events?tail=200", events=200))
        out["requests"].append(get("/api/runs"))
        entry = next(r for r in json.loads(urllib.request.urlopen(base + "/api/runs").read()) if r["name"] == run)
        out["run"] = {k: entry[k] for k in ("state", "frames_done", "frames_planned")}
        print(json.dumps(out))
    finally:
        proc.terminate()
        proc.wait()


if __name__ == "__main__":
    main()
