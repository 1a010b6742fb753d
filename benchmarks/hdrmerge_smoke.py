"""Does HDRMerge (a LibRaw-based peer) open hdrcap's simulated DNG brackets?

Installs HDRMerge with apt-get when it is missing (root needed), simulates a bracket with
`hdrcap simulate`, runs `hdrmerge -o out.dng frame_*.dng` headless, opens the result with
rawpy and prints one JSON object: exit status, time, whether the output is finite, and the
output's size and value range.

Usage: python benchmarks/hdrmerge_smoke.py [--camera camera-B] [--size 1024x768]
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def ensure_hdrmerge() -> str:
    exe = shutil.which("hdrmerge")
    if exe:
        return exe
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    subprocess.run(["apt-get", "update", "-qq"], check=True, env=env)
    subprocess.run(["apt-get", "install", "-y", "-qq", "hdrmerge"], check=True, env=env)
    return shutil.which("hdrmerge")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera", default="camera-B")
    ap.add_argument("--size", default="1024x768")
    args = ap.parse_args()
    exe = ensure_hdrmerge()
    import numpy as np
    import rawpy

    with tempfile.TemporaryDirectory() as tmp:
        sim = Path(tmp) / "sim"
        subprocess.run(
            [
                sys.executable,
                "-m",
                "hdrcap",
                "simulate",
                "--camera",
                args.camera,
                "--size",
                args.size,
                "--out",
                str(sim),
                "--json",
            ],
            check=True,
            cwd=REPO,
            capture_output=True,
            env=dict(os.environ, PYTHONPATH=str(REPO)),
        )
        frames = sorted(glob.glob(str(sim / "frame_*.dng")))
        out = Path(tmp) / "hdrmerge.dng"
        t0 = time.perf_counter()
        proc = subprocess.run(
            [exe, "-o", str(out), *frames],
            capture_output=True,
            text=True,
            env=dict(os.environ, QT_QPA_PLATFORM="offscreen"),
        )
        seconds = time.perf_counter() - t0
        result = {
            "peer": "hdrmerge",
            "camera": args.camera,
            "size": args.size,
            "n_frames": len(frames),
            "exit_status": proc.returncode,
            "seconds": round(seconds, 3),
            "output_exists": out.is_file(),
            "stderr_tail": proc.stderr.strip().splitlines()[-3:],
        }
        if out.is_file():
            with rawpy.imread(str(out)) as raw:
                data = np.asarray(raw.raw_image_visible, dtype=np.float64)
                result.update(
                    {
                        "opens_in_rawpy": True,
                        "shape": list(data.shape),
                        "finite": bool(np.isfinite(data).all()),
                        "min": float(data.min()),
                        "max": float(data.max()),
                        "white_level": int(raw.white_level),
                    }
                )
    print(json.dumps(result))
    return 0 if result.get("opens_in_rawpy") else 1


if __name__ == "__main__":
    sys.exit(main())
