"""The unattended-rig soak: `hdrcap run` on the simulated camera through its command line, 310
frames with 20 % busy, 2 % disconnects (half of them followed by two failed reconnects, some
coming back on a new port), 1 % corrupt files, hangs that ignore the timeout, one full disk (ENOSPC) in
the middle and one SIGTERM, each followed by `--resume`: every planned frame exactly once,
hashes right, the HDR output written, every stop reported with its documented exit code."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from hdrcap.acquire.capture.manifest import EventLog, Manifest
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.io.files import sha256_file

REPO = Path(__file__).resolve().parents[2]

#: ``python -c SCRIPT ENOSPC_AT ARGS...``: `hdrcap ARGS` whose camera download finds the host
#: disk full once, at capture call ENOSPC_AT (0: never) - the fixture's ENOSPC.
SCRIPT = r"""
import errno, sys
import hdrcap.acquire.capture.run as run

at = int(sys.argv[1])
real_open = run.open_camera


class DiskFullOnce:
    def __init__(self, cam):
        self._cam, self.n = cam, 0

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def capture(self, dest, **kw):
        self.n += 1
        if self.n == at:
            raise OSError(errno.ENOSPC, "No space left on device", str(dest))
        return self._cam.capture(dest, **kw)


run.open_camera = lambda j, n=0: DiskFullOnce(real_open(j, n))
from hdrcap.cli import main

sys.exit(main(sys.argv[2:]))
"""

JOB = """\
[job]
name = "soak"

[camera]
backend = "mock"
preset = "camera-B"
size = "32x24"
seed = 21
faults = { seed = 5, busy_rate = 0.20, disconnect_rate = 0.02, corrupt_rate = 0.01, hang_rate = 0.005, hang_s = 0.05, \
           hang_ignores_timeout = true, reconnect_fail_rate = 0.5, reconnect_failures = 2, renumber_rate = 0.3 }

[scene]
name = "hdr"
decades = 3.0
x_max = 2e4

[exposure]
mode = "bracket"
times = [0.00025, 0.001, 0.004, 0.016, 0.064, 0.25, 1.0, 2.0, 4.0, 8.0]
repeats = 30

[darks]
strategy = "matched"

[session]
max_attempts = 40
backoff_s = 0.0005
max_backoff_s = 0.002
timeout_s = 0.02

[output]
folder = "runs/{job}-{date}"
"""


def _start(tmp_path, enospc_at, *args) -> subprocess.Popen:
    env = {"HDRCAP_LOCK_DIR": str(tmp_path / "locks"), "PATH": "/usr/bin:/bin"}
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(enospc_at), *map(str, args)],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _frames_in(run_dir: Path) -> int:
    p = run_dir / "manifest.jsonl"
    return p.read_bytes().count(b'"type":"frame"') if p.exists() else 0


@pytest.mark.slow
def test_soak_unattended_rig(tmp_path):
    t0 = time.monotonic()
    job = tmp_path / "soak.toml"
    job.write_text(JOB)
    # 1. the host disk fills in the middle: exit 6, a JSON error object, the run resumable
    first = _start(tmp_path, 140, "run", job, "--json", "--no-progress")
    out, err = first.communicate(timeout=300)
    assert first.returncode == 6, err
    failed = json.loads(out)
    assert failed["exit_code"] == 6 and failed["status"] == "failed" and "No space left" in failed["error"]
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert Path(failed["run_dir"]) == run_dir
    n_full = _frames_in(run_dir)
    assert 60 <= n_full < 140
    # 2. resumed, then SIGTERM (a scheduler's stop) once 80 more frames are in: exit 143
    second = _start(tmp_path, 0, "run", job, "--resume", "--no-progress")
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and second.poll() is None and _frames_in(run_dir) < n_full + 80:
        time.sleep(0.01)
    second.send_signal(signal.SIGTERM)
    _out, err = second.communicate(timeout=120)
    assert second.returncode == 143, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("hdrcap: error:")
    n_term = len(Manifest(run_dir).frames())
    assert n_full + 80 <= n_term < 310
    # 3. resumed to the end: exit 0, HDR written
    third = _start(tmp_path, 0, "run", job, "--resume", "--json", "--no-progress")
    out, err = third.communicate(timeout=300)
    assert third.returncode == 0, err
    res = json.loads(out)
    assert res["status"] == "done" and res["frames"] == 310 and Path(res["run_dir"]) == run_dir
    assert res["resumed"] + res["adopted"] + res["captured"] == 310
    # 4. --resume once more (an @reboot line after a normal run): nothing to do, exit 0
    fourth = _start(tmp_path, 0, "run", job, "--resume", "--json", "--no-progress")
    out, err = fourth.communicate(timeout=120)
    assert fourth.returncode == 0 and json.loads(out)["status"] == "already_complete", err

    # every planned frame exactly once, hashes right, no stray file
    m = Manifest(run_dir)
    planned = {f["key"] for f in m.header()["plan"]["frames"]}
    frames = m.frames()
    assert set(frames) == planned and len(planned) == 310
    live = Counter(r["key"] for r in m.records() if r["type"] == "frame")
    voided = {r["key"] for r in m.records() if r["type"] == "void"}
    assert all(n == 1 or key in voided for key, n in live.items())
    assert sorted(p.name for p in (run_dir / "frames").iterdir()) == sorted(
        Path(r["file"]).name for r in frames.values()
    )
    assert all(sha256_file(run_dir / r["file"]) == r["sha256"] for r in frames.values())
    hdr = read_exr(run_dir / "hdr.exr")
    assert hdr.shape == (24, 32)
    # every stop reported with its documented exit code; the faults met and survived
    events = EventLog(run_dir).events()
    stops = [e for e in events if e["event"] == "stop"]
    assert [(s["exit_code"], s.get("kind")) for s in stops] == [(6, "local_io"), (143, None)]
    faults = Counter(e["kind"] for e in events if e["event"] == "fault")
    hangs = sum(1 for e in events if e["event"] == "fault" and "timeout" in e["error"])
    assert faults["busy"] >= 40 and faults["reconnect"] >= 4 and faults["recapture"] >= 1 and hangs >= 1
    reconnects = [e for e in events if e["event"] == "reconnect"]
    failed_reconnects = sum(1 for e in reconnects if not e["ok"])
    ports = {e.get("port") for e in reconnects if e["ok"]}
    assert failed_reconnects >= 4 and len(ports) >= 2  # reconnects that failed twice; the port renumbered
    names = [e["event"] for e in events]
    assert names.count("resume") == 2 and names.count("done") == 1  # the 4th start did not touch the run
    print(
        f"soak: 310 frames, {sum(faults.values())} faults {dict(faults)} ({hangs} hangs), {failed_reconnects} failed "
        f"reconnects, {len(ports)} ports, stops at {n_full} (ENOSPC) and {n_term} (SIGTERM) frames, "
        f"{time.monotonic() - t0:.1f} s"
    )
