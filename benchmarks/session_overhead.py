"""Time the capture session's overhead per frame (verify with rawpy, sha256, manifest and event
log with fsync) against the simulated camera alone. Prints JSON.

    python benchmarks/session_overhead.py
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hdrcap.acquire.camera.mock import MockCamera  # noqa: E402
from hdrcap.acquire.capture.session import CapturePlan, CaptureSession  # noqa: E402
from hdrcap.mock_camera.scenes import make_scene  # noqa: E402

TIMES = [0.001, 0.004, 0.016, 0.064, 0.25, 1.0]


def main() -> None:
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for shape in [(32, 32), (768, 1024)]:
            cam = MockCamera("camera-B", make_scene("hdr", shape), seed=0)
            plan = CapturePlan.bracket(TIMES, cam.allowed_exposure_times(), "matched")
            t0 = time.perf_counter()
            for i, f in enumerate(plan.frames):
                cam.set_exposure(f.exposure_s)
                cam.capture(d / f"raw{shape[0]}_{i}.dng")
            camera_only = (time.perf_counter() - t0) / len(plan.frames)
            t0 = time.perf_counter()
            CaptureSession(
                MockCamera("camera-B", make_scene("hdr", shape), seed=0), d / f"run{shape[0]}", plan, progress=False
            ).run()
            session = (time.perf_counter() - t0) / len(plan.frames)
            out.append(
                {
                    "shape": list(shape),
                    "frames": len(plan.frames),
                    "camera_only_ms": round(camera_only * 1e3, 1),
                    "session_ms": round(session * 1e3, 1),
                    "overhead_ms": round((session - camera_only) * 1e3, 1),
                }
            )
    print(json.dumps({"benchmark": "session_overhead", "results": out}))


if __name__ == "__main__":
    main()
