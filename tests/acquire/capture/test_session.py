"""Capture sessions on the MockCamera: manifest, verification, retries, resume, locks, merge."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hdrcap.acquire.camera.mock import MockCamera, MockFaults
from hdrcap.acquire.capture.manifest import Manifest
from hdrcap.acquire.capture.session import CapturePlan, CaptureSession, LightBlocker, SessionError
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import sha256_file
from hdrcap.pipeline.io.raw import read_frame
from tests.helpers.jobs import FAST

REPO = Path(__file__).resolve().parents[3]
TIMES = [1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0]


def _scene(shape=(32, 32), seed=0):
    from hdrcap.mock_camera.scenes import make_scene

    return make_scene("hdr", shape, decades=3.0, x_max=2e4)


def _camera(seed=0, faults=None, shape=(32, 32)):
    return MockCamera("camera-B", _scene(shape), seed=seed, faults=faults)


def _check_run(run_dir: Path, plan: CapturePlan) -> dict:
    """Every planned frame exactly once, every file hashed right, no stray file."""
    m = Manifest(run_dir)
    recs = m.records()
    frames = m.frames()
    assert set(frames) == {f.key for f in plan.frames}
    voided = {r["key"] for r in recs if r["type"] == "void"}
    for key in frames:
        live = [r for r in recs if r["type"] == "frame" and r["key"] == key]
        assert len(live) == 1 or key in voided, key
    files = sorted(p.name for p in (run_dir / "frames").iterdir())
    assert files == sorted(Path(r["file"]).name for r in frames.values())
    for rec in frames.values():
        assert sha256_file(run_dir / rec["file"]) == rec["sha256"]
        assert rec["applied_exposure_s"] == pytest.approx(rec["file_exposure_s"], rel=1e-6)
    return frames


def test_session_records_verified_frames_and_merges(tmp_path):
    from hdrcap.acquire.camera.model import camera_model

    plan = CapturePlan.bracket(TIMES, _camera().allowed_exposure_times(), "matched")
    cam = _camera()
    res = CaptureSession(
        cam,
        tmp_path / "run",
        plan,
        calibration=camera_model(camera="camera-B"),
        retry=FAST,
        progress=False,
        meta={"seed": 0},
    ).run()
    frames = _check_run(tmp_path / "run", plan)
    assert res.captured == len(plan.frames) == 2 * len(TIMES)
    darks = [r for r in frames.values() if r["kind"] == "dark"]
    lights = [r for r in frames.values() if r["kind"] == "light"]
    # the dark frames really are dark: their mean is near the bias level at every time
    for r in darks:
        assert np.mean(read_frame(tmp_path / "run" / r["file"]).data) < 32 + 0.92 * 1.0 * r["file_exposure_s"] * 3 + 3
    assert len(lights) == len(TIMES)
    head = Manifest(tmp_path / "run").header()
    assert head["camera"]["backend"] == "mock" and head["seed"] == 0
    # the merge: error against the simulator's truth within the stated sigma (robust spread)
    m = res.merge
    ok = m.nexp > 0
    z = (m.irradiance[ok] - cam.sim.scene[ok]) / m.sigma[ok]
    spread = 1.4826 * np.median(np.abs(z - np.median(z)))
    assert 0.75 < spread < 1.3 and abs(np.median(z)) < 0.2


def test_session_survives_faults_and_counts_retries(tmp_path):
    faults = MockFaults(
        seed=3,
        busy_first=2,
        busy_rate=0.3,
        disconnect_rate=0.1,
        corrupt_rate=0.1,
        truncate_rate=0.05,
        hang_rate=0.05,
        hang_s=0.01,
    )
    plan = CapturePlan.bracket(TIMES, None, "master", n_dark=2)
    cam = _camera(faults=faults)
    res = CaptureSession(cam, tmp_path / "run", plan, retry=FAST, progress=False).run()
    _check_run(tmp_path / "run", plan)
    assert res.retries.get("busy", 0) >= 2
    assert set(cam.fault_log) >= {"busy", "disconnect", "corrupt"}
    assert cam.reconnects >= 1
    events = [json.loads(l)["event"] for l in (tmp_path / "run" / "events.jsonl").read_text().splitlines()]
    assert events[0] == "start" and events[-1] == "done" and "fault" in events and "reconnect" in events


def test_card_full_stops_cleanly_then_resume_completes(tmp_path):
    plan = CapturePlan.bracket(TIMES, None, "matched")
    with pytest.raises(SessionError, match="card full"):
        CaptureSession(
            _camera(faults=MockFaults(card_full_after=5)), tmp_path / "run", plan, retry=FAST, progress=False
        ).run()
    assert len(Manifest(tmp_path / "run").frames()) == 5
    with pytest.raises(SessionError, match="--resume"):
        CaptureSession(_camera(), tmp_path / "run", plan, retry=FAST, progress=False).run()
    res = CaptureSession(_camera(), tmp_path / "run", plan, retry=FAST, progress=False, resume=True).run()
    assert res.resumed == 5 and res.captured == len(plan.frames) - 5
    _check_run(tmp_path / "run", plan)


def test_resume_adopts_landed_frame_and_voids_tampered_one(tmp_path):
    plan = CapturePlan.bracket(TIMES, None, "model")
    CaptureSession(_camera(), tmp_path / "run", plan, retry=FAST, progress=False).run()
    mpath = tmp_path / "run" / "manifest.jsonl"
    lines = mpath.read_text().splitlines(keepends=True)
    # crash between the file landing and its manifest line; and a torn half line
    mpath.write_text("".join(lines[:-1]) + lines[-1][: len(lines[-1]) // 2])
    first = json.loads(lines[1])
    (tmp_path / "run" / first["file"]).write_bytes(b"tampered")
    res = CaptureSession(_camera(), tmp_path / "run", plan, retry=FAST, progress=False, resume=True).run()
    assert res.adopted == 1 and res.captured == 1  # the tampered one was taken again
    _check_run(tmp_path / "run", plan)
    assert (tmp_path / "run" / "rejected").is_dir()


def test_resume_rejects_a_different_plan(tmp_path):
    CaptureSession(_camera(), tmp_path / "run", CapturePlan.bracket(TIMES[:2]), retry=FAST, progress=False).run()
    with pytest.raises(SessionError, match="different plan"):
        CaptureSession(
            _camera(), tmp_path / "run", CapturePlan.bracket(TIMES[:3]), retry=FAST, progress=False, resume=True
        ).run()


def test_lock_prevents_two_sessions(tmp_path, monkeypatch):
    from filelock import FileLock

    monkeypatch.setenv("HDRCAP_LOCK_DIR", str(tmp_path / "locks"))
    (tmp_path / "run").mkdir()
    with FileLock(str(tmp_path / "run" / ".hdrcap.lock")):
        with pytest.raises(SessionError, match="another hdrcap session"):
            CaptureSession(_camera(), tmp_path / "run", CapturePlan.bracket(TIMES[:1]), progress=False).run()
    # the same camera from another run folder
    from hdrcap.acquire.capture.session import _identity, _lock_key

    cam = _camera()
    with FileLock(str(tmp_path / "locks" / (_lock_key(_identity(cam)) + ".lock"))):
        with pytest.raises(SessionError, match="in use"):
            CaptureSession(cam, tmp_path / "run2", CapturePlan.bracket(TIMES[:1]), progress=False).run()


def test_light_blocking_by_command(tmp_path):
    log = tmp_path / "light.log"
    blocker = LightBlocker("command", cover_command=f"echo cover >> {log}", uncover_command=f"echo open >> {log}")
    CaptureSession(
        _camera(), tmp_path / "run", CapturePlan.bracket(TIMES[:3]), light=blocker, retry=FAST, progress=False
    ).run()
    assert log.read_text().split() == ["cover", "open"]  # blocked once for all dark frames
    bad = LightBlocker("command", cover_command="exit 3", uncover_command="true")
    with pytest.raises(SessionError, match="cover command"):
        CaptureSession(_camera(), tmp_path / "run2", CapturePlan.bracket(TIMES[:1]), light=bad, progress=False).run()


SOAK = r"""
import sys, json
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from hdrcap.acquire.camera.mock import MockCamera, MockFaults
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.acquire.capture.session import CapturePlan, CaptureSession, RetryPolicy
from hdrcap.acquire.camera.model import camera_model
run, seed, kill = Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
faults = MockFaults(seed=seed, busy_rate=0.20, disconnect_rate=0.02, corrupt_rate=0.01, truncate_rate=0.005,
                    hang_rate=0.005, hang_s=0.01, kill_after=kill or None)
# one camera (seed 11: its serial and fixed patterns) restarted with other fault draws each time
cam = MockCamera("camera-B", make_scene("hdr", (32, 32), decades=3.0, x_max=2e4), seed=11, faults=faults)
times = [1/4000, 1/1000, 1/250, 1/60, 1/15, 1/4, 1.0, 2.0, 4.0, 8.0]
plan = CapturePlan.bracket(times, cam.allowed_exposure_times(), "matched", repeats=20)
res = CaptureSession(cam, run, plan, calibration=camera_model(camera="camera-B"),
                     retry=RetryPolicy(max_attempts=40, backoff_s=0.0005, max_backoff_s=0.002, timeout_s=0.02),
                     resume=bool(kill == 0), progress=False).run()
print(json.dumps({"captured": res.captured, "resumed": res.resumed, "adopted": res.adopted, "retries": res.retries,
                  "faults": {k: cam.fault_log.count(k) for k in set(cam.fault_log)}, "n": len(plan.frames)}))
"""


@pytest.mark.slow
def test_soak_faults_kill_and_resume(tmp_path):
    """210 frames; 20 % busy, 2 % disconnects, 1 % corrupt, 0.5 % truncated, 0.5 % hangs; killed
    twice (inside a download, then by SIGKILL from outside at whatever point it is), resumed."""
    import signal
    import time

    run = tmp_path / "run"
    env = dict(os.environ, HDRCAP_LOCK_DIR=str(tmp_path / "locks"))
    first = subprocess.run(
        [sys.executable, "-c", SOAK, str(REPO), str(run), "11", "100"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert first.returncode == 137, first.stderr  # killed in the middle of a download
    assert "Traceback" not in first.stderr
    n_before = len(Manifest(run).frames())
    assert 90 <= n_before < 210
    # resume, and kill it from outside once ~40 more frames are in
    proc = subprocess.Popen(
        [sys.executable, "-c", SOAK, str(REPO), str(run), "12", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if (run / "manifest.jsonl").read_bytes().count(b'"type":"frame"') >= n_before + 40:
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.01)
    _out, err2 = proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGKILL and "Traceback" not in err2
    n_mid = len(Manifest(run).frames())
    assert n_before + 40 <= n_mid < 210
    third = subprocess.run(
        [sys.executable, "-c", SOAK, str(REPO), str(run), "13", "0"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert third.returncode == 0 and "Traceback" not in third.stderr, third.stderr
    out = json.loads(third.stdout)
    print("soak:", n_before, n_mid, out)
    assert out["n"] == 210 and out["resumed"] + out["adopted"] + out["captured"] == 210
    assert out["retries"]["busy"] >= 3
    m = Manifest(run)
    frames = m.frames()
    assert len(frames) == 210
    recs = [r for r in m.records() if r["type"] == "frame"]
    assert len(recs) == 210  # exactly once: no frame recorded twice
    files = sorted(p.name for p in (run / "frames").iterdir())
    assert files == sorted(Path(r["file"]).name for r in frames.values())
    assert all(sha256_file(run / r["file"]) == r["sha256"] for r in frames.values())
    assert not (run / ".partial").exists()
    events = [
        json.loads(line) for line in (run / "events.jsonl").read_text().splitlines() if line.strip().endswith("}")
    ]
    kinds = {e["event"] for e in events}
    assert {"fault", "reconnect", "resume", "done"} <= kinds


def test_dark_frame_with_light_stops_the_session(tmp_path):
    cam = _camera()
    cam.cover = lambda: None  # someone forgot the lens cap
    with pytest.raises(SessionError, match="light is not blocked"):
        CaptureSession(
            cam, tmp_path / "run", CapturePlan.bracket([1.0]), light=LightBlocker("none"), retry=FAST, progress=False
        ).run()
    assert Manifest(tmp_path / "run").frames() == {}


def test_calibration_series_prompt_blocking_and_temperature(tmp_path):
    asked = []
    series = [
        {"kind": "bias", "times": [1 / 8000], "count": 3},
        {"kind": "darkseries", "times": [0.5, 2.0], "count": 2},
        {"kind": "flat", "times": [1 / 60], "count": 2},
    ]
    plan = CapturePlan.bracket([1 / 250], None, "master", n_dark=2, series=series)
    cam = MockCamera("camera-B", np.full((32, 32), 2e4), seed=4, temperature=30.0)
    res = CaptureSession(
        cam, tmp_path / "run", plan, light=LightBlocker("prompt", prompt=asked.append), retry=FAST, progress=False
    ).run()
    frames = _check_run(tmp_path / "run", plan)
    kinds = sorted(r["kind"] for r in frames.values())
    assert kinds == sorted(["dark"] * 2 + ["light"] + ["bias"] * 3 + ["darkseries"] * 4 + ["flat"] * 2)
    assert len(asked) == 2 and "Block the light" in asked[0] and "Unblock" in asked[1]  # blocked once
    # every frame that needed the light blocked is dark, every other one is lit
    for r in frames.values():
        level = np.median(read_frame(tmp_path / "run" / r["file"]).data) - 32
        assert (level < 10) == r["dark"], (r["key"], level)
        assert r["temperature_c"] == 30.0 and r["camera"]["backend"] == "mock"
    assert res.captured == len(plan.frames) == 12


class _NoShape:
    """A camera that, like a real one, does not announce its mosaic size."""

    def __init__(self, cam):
        self._cam = cam
        self.identity = cam.identity

    def __getattr__(self, name):
        if name == "shape":
            raise AttributeError(name)
        return getattr(self._cam, name)


def test_session_learns_the_size_from_the_first_frame(tmp_path):
    from hdrcap.acquire.camera.model import camera_model

    plan = CapturePlan.bracket(TIMES[:3], None, "matched")
    res = CaptureSession(
        _NoShape(_camera()),
        tmp_path / "run",
        plan,
        calibration=camera_model(camera="camera-B"),
        retry=FAST,
        progress=False,
    ).run()
    assert res.merge.irradiance.shape == (32, 32)
    _check_run(tmp_path / "run", plan)


def test_master_darks_from_the_library_replace_dark_frames(tmp_path):
    from hdrcap.acquire.camera.model import camera_model

    # the library's masters: 8 dark frames per time averaged, taken earlier with the same sensor
    lib_cam = _camera()
    lib_cam.cover()
    masters = {}
    for t in TIMES[:2]:
        lib_cam.set_exposure(t)
        stack = [read_frame(lib_cam.capture(tmp_path / f"lib_{t:g}_{k}.dng").path).data.astype(float) for k in range(8)]
        masters[t] = (np.mean(stack, axis=0), 8)
    plan = CapturePlan.bracket(TIMES[:3], None, "master", n_dark=2, library_times=TIMES[:2])
    assert [f.kind for f in plan.frames].count("dark") == 2  # only the time without a library master
    cam = _camera()
    res = CaptureSession(
        cam,
        tmp_path / "run",
        plan,
        calibration=camera_model(camera="camera-B"),
        retry=FAST,
        progress=False,
        master_darks=masters,
    ).run()
    _check_run(tmp_path / "run", plan)
    m = res.merge
    ok = m.nexp > 0
    z = (m.irradiance[ok] - cam.sim.scene[ok]) / m.sigma[ok]
    assert 0.7 < 1.4826 * np.median(np.abs(z - np.median(z))) < 1.3
    with pytest.raises(InputError, match="no master dark"):
        CaptureSession(_camera(), tmp_path / "run2", plan, progress=False, master_darks={TIMES[0]: masters[TIMES[0]]})


def test_capture_plan_per_exposure_strategies_and_old_manifests():
    t = [1 / 1000, 1 / 250, 1 / 60, 1 / 250]
    plan = CapturePlan.bracket(t, None, ["model", "matched", "master", "matched"], n_dark=3, library_times=[1 / 60])
    assert [(f.kind, f.exposure_s) for f in plan.frames if f.kind == "dark"] == [("dark", 1 / 250)]
    assert plan.dark_strategy == "mixed" and plan.strategy_for(1 / 60) == "master" and plan.library_times == (1 / 60,)
    again = CapturePlan.from_dict(json.loads(json.dumps(plan.to_dict())))
    assert again == plan and again.fingerprint() == plan.fingerprint()
    with pytest.raises(InputError, match="two dark strategies"):
        CapturePlan.bracket(t, None, ["model", "matched", "master", "model"])
    # a manifest written before per-exposure strategies (fingerprint by the code before them):
    # the same plan, the same fingerprint
    old = {
        "dark_strategy": "master",
        "n_dark": 2,
        "library_times": [],
        "fingerprint": "109ac916a4f30da9",
        "frames": [
            {"key": "dark-0.001-0", "kind": "dark", "exposure_s": 0.001},
            {"key": "dark-0.001-1", "kind": "dark", "exposure_s": 0.001},
            {"key": "light-0.001-0", "kind": "light", "exposure_s": 0.001},
        ],
    }
    p = CapturePlan.from_dict(old)
    assert p == CapturePlan.bracket([0.001], None, "master", n_dark=2) and p.strategy_for(0.001) == "master"
    assert p.fingerprint() == old["fingerprint"]


def test_a_torn_manifest_header_is_not_trusted(tmp_path):
    plan = CapturePlan.bracket(TIMES[:2], None, "matched")
    CaptureSession(_camera(), tmp_path / "run", plan, retry=FAST, progress=False).run()
    mpath = tmp_path / "run" / "manifest.jsonl"
    lines = mpath.read_text().splitlines(keepends=True)
    mpath.write_text(lines[0][: len(lines[0]) // 2] + "\n" + "".join(lines[1:]))
    other = CapturePlan.bracket(TIMES[2:4], None, "matched")  # would have passed unchecked before
    from hdrcap.acquire.capture.session import VerificationError

    with pytest.raises(VerificationError, match="unreadable"):
        CaptureSession(_camera(), tmp_path / "run", other, retry=FAST, progress=False, resume=True).run()
    # a crash while the very first line was written: nothing recorded, the run starts over
    (tmp_path / "new").mkdir()
    (tmp_path / "new" / "manifest.jsonl").write_text('{"type": "run", "plan_fin')
    res = CaptureSession(_camera(), tmp_path / "new", plan, retry=FAST, progress=False, resume=True).run()
    assert res.captured == len(plan.frames)
    _check_run(tmp_path / "new", plan)


def test_a_light_leak_at_a_short_exposure_is_caught_with_a_calibration(tmp_path):
    """At 1/60 s the lit scene's median is ~1 % of the range: below the 5 % rule, yet ~10 DN
    above the calibrated dark level, far beyond the noise of a 32x32 median."""
    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.acquire.capture.session import VerificationError

    cal = camera_model(camera="camera-B")
    plan = CapturePlan.bracket([1 / 60], None, "matched")
    leaky = _camera()
    leaky.cover = lambda: None  # the lens cap fell off
    CaptureSession(leaky, tmp_path / "weak", plan, light=LightBlocker("none"), retry=FAST, progress=False).run()
    leaky = _camera()
    leaky.cover = lambda: None
    with pytest.raises(VerificationError, match="above the calibrated dark level"):
        CaptureSession(
            leaky, tmp_path / "run", plan, calibration=cal, light=LightBlocker("none"), retry=FAST, progress=False
        ).run()
    # no false alarm for real dark frames up to 30 s, also 5 C warmer than the calibration
    warm = MockCamera("camera-B", _scene((32, 32)), seed=4, temperature=25.0)
    times = [1 / 8000, 1 / 60, 1.0, 8.0, 30.0]
    CaptureSession(
        warm, tmp_path / "ok", CapturePlan.bracket(times, None, "matched"), calibration=cal, retry=FAST, progress=False
    ).run()


class _CardCamera(MockCamera):
    """A camera that reports what libgphoto2's worker reports: a delete that failed on the card
    after every second download, and the routine file-added event of every capture."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.events = [("delete_failed", "from an earlier run")]  # before the session: not its event
        self.n = 0

    def capture(self, *a, **k):
        res = super().capture(*a, **k)
        self.n += 1
        self.events.append(("file_added", f"/DCIM/{self.n}.dng"))
        if self.n % 2 == 0:
            self.events.append(("delete_failed", f"/DCIM/{self.n}.dng: read-only card"))
        return res


def test_camera_events_reach_the_event_log(tmp_path):
    plan = CapturePlan.bracket(TIMES[:2], _camera().allowed_exposure_times(), "matched")
    cam = _CardCamera("camera-B", _scene(), seed=0)
    CaptureSession(cam, tmp_path / "run", plan, retry=FAST, progress=False).run()
    lines = [json.loads(x) for x in (tmp_path / "run" / "events.jsonl").read_text().splitlines()]
    got = [(e["kind"], e["detail"]) for e in lines if e["event"] == "camera"]
    assert got == [("delete_failed", f"/DCIM/{n}.dng: read-only card") for n in (2, 4)]
