"""Per-frame overhead of :class:`hdrcap.acquire.camera.gphoto2.Gphoto2Camera` on libgphoto2's
virtual camera: the wall time of ``set_exposure`` + ``capture`` (download and delete included)
and the number of full configuration-tree reads (``gp_camera_get_config``) per frame. Prints JSON.

    python benchmarks/gphoto2_overhead.py [FRAMES]

The virtual camera answers in microseconds; on a real body each full tree read costs tens to
hundreds of milliseconds, so the count of tree reads is the figure that carries over. The
counts come from wrapping ``gp.Camera`` in this process (a camera driven in-process) and from
the camera's own ``tree_reads()`` (a camera driven in a worker process).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = """
import json, sys, time
from pathlib import Path
sys.path.insert(0, {repo!r})
import gphoto2 as gp
count = {{"get_config": 0, "get_single_config": 0}}
class Counting(gp.Camera):
    def get_config(self, *a):
        count["get_config"] += 1
        return super().get_config(*a)
    def get_single_config(self, *a):
        count["get_single_config"] += 1
        return super().get_single_config(*a)
gp.Camera = Counting
from hdrcap.acquire.camera.gphoto2 import Gphoto2Camera
out = Path({out!r})
cam = Gphoto2Camera(pair_wait_s=0)
times = [0.01, 0.02, 0.05, 0.1]
cam.set_exposure(times[0])
stats = getattr(cam, "tree_reads", lambda: {{}})
before = dict(count, **stats())
t0 = time.perf_counter()
n = {frames}
for i in range(n):
    cam.set_exposure(times[i % len(times)])
    cam.capture(out / f"f{{i}}.jpg")
dt = time.perf_counter() - t0
after = dict(count, **stats())
reads = {{k: (after[k] - before[k]) / n for k in after}}
cam.close()
print(json.dumps({{"frames": n, "s_per_frame": dt / n, "config_reads_per_frame": reads}}))
"""


def main(frames: int = 20) -> None:
    from PIL import Image

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "v").mkdir()
        (d / "o").mkdir()
        Image.new("RGB", (64, 48), (200, 200, 200)).save(d / "v" / "scene.jpg")
        env = dict(os.environ, VCAMERADIR=str(d / "v"), XDG_CONFIG_HOME=str(d / "xdg"))
        script = textwrap.dedent(CHILD).format(repo=str(REPO), out=str(d / "o"), frames=frames)
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
        if proc.returncode:
            raise SystemExit(proc.stderr[-2000:])
        print(proc.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
