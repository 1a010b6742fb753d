"""Capture faults of the audit in issue #29, each stopped at its cause: outputs an interrupted run
still owes, a voided dark frame under recorded light frames, cover/uncover commands that hang,
a camera that ignores the shutter setting, job times snapped to the camera's list, the light
left blocked by a stop (and metering in the dark), and the soak's findings (faults drawn per
repetition, lock files, a second JSON report, a hung call at SIGTERM, read-only folders, stop
events of failed outputs)."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from hdrcap.acquire.camera.mock import MockCamera, MockFaults
from hdrcap.acquire.capture.job import JobError, load_job
from hdrcap.acquire.capture.manifest import EventLog, Manifest
from hdrcap.acquire.capture.run import run_job
from hdrcap.acquire.capture.schedule import run_schedule
from hdrcap.acquire.capture.session import (
    CapturePlan,
    CaptureSession,
    LightBlocker,
    LocalIOError,
    RunInterrupted,
    SessionError,
    StopEvent,
    VerificationError,
)
from hdrcap.pipeline.io.files import sha256_file
from tests.helpers.cameras import StoppingCamera
from tests.helpers.jobs import FAST, mock_job


def _run_args(job: Path) -> list[str]:
    """``hdrcap run JOB`` as a command of its own."""
    return [sys.executable, "-m", "hdrcap", "run", str(job), "--no-progress"]


def _run_env(tmp_path: Path) -> dict[str, str]:
    """The environment of such a command: its lock files in ``tmp_path/locks``."""
    return dict(os.environ, HDRCAP_LOCK_DIR=str(tmp_path / "locks"))


def _start_run(tmp_path: Path, job: Path) -> subprocess.Popen:
    """``hdrcap run JOB`` started in ``tmp_path``, its stdout and stderr piped (text)."""
    return subprocess.Popen(
        _run_args(job), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_run_env(tmp_path)
    )


def _job(
    tmp_path: Path,
    camera: str = "",
    exposure: str = 'mode = "bracket"\ntimes = [0.004, 0.064, 0.5]',
    darks: str = "",
    folder: str = "runs/{job}-{n}",
) -> Path:
    return mock_job(
        tmp_path / "job.toml",
        name="f",
        camera=camera,
        exposure=exposure,
        darks='strategy = "matched"\n' + darks,
        session="backoff_s = 0.001\nmax_backoff_s = 0.001\ntimeout_s = 0.05",
        folder=folder,
    )


def _quiet(_msg: str) -> None:
    pass


def _scene(shape=(24, 32)):
    from hdrcap.mock_camera.scenes import make_scene

    return make_scene("hdr", shape, decades=3.0, x_max=2e4)


def _frames_once(run_dir: Path) -> dict:
    m = Manifest(run_dir)
    frames = m.frames()
    assert set(frames) == {f["key"] for f in m.header()["plan"]["frames"]}
    for rec in frames.values():
        assert sha256_file(run_dir / rec["file"]) == rec["sha256"]
    return frames


def _processes(text: str) -> list[int]:
    """Process ids whose command line contains ``text`` (arguments joined by spaces)."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmd:
            found.append(int(d.name))
    return found


def _gone(text: str, within: float = 5.0) -> list[int]:
    """:func:`_processes` once they have had ``within`` seconds to go (a killed process leaves
    /proc when its parent or init reaps it, later on a loaded machine)."""
    deadline = time.monotonic() + within
    while (found := _processes(text)) and time.monotonic() < deadline:
        time.sleep(0.05)
    return found


# --------------------------------------------------------------------------- 1. outputs owed by a run
def test_resume_writes_a_deleted_preview_and_the_complete_record(tmp_path):
    job = load_job(_job(tmp_path))
    first = run_job(job, progress=False, echo=_quiet)
    run_dir = Path(first["run_dir"])
    (run_dir / "preview.png").unlink()
    res = run_job(job, resume=True, progress=False, echo=_quiet)
    assert res["status"] == "done" and Path(res["run_dir"]) == run_dir and res["captured"] == 0
    assert (run_dir / "preview.png").is_file() and (run_dir / "hdr.exr").is_file()
    assert [r["type"] for r in Manifest(run_dir).records()].count("complete") == 2
    assert run_job(job, resume=True, progress=False, echo=_quiet)["status"] == "already_complete"


def test_a_full_disk_between_the_exr_and_the_png_is_finished_by_resume(tmp_path, monkeypatch):
    import hdrcap.pipeline.preview as preview

    def full(path, *a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    job = load_job(_job(tmp_path))
    with monkeypatch.context() as m:
        m.setattr(preview, "write_preview_png", full)
        with pytest.raises(LocalIOError) as info:
            run_job(job, progress=False, echo=_quiet)
    assert info.value.exit_code == 6 and "--resume" in str(info.value)
    run_dir = Path(info.value.run_dir)
    assert (run_dir / "hdr.exr").is_file() and not (run_dir / "preview.png").exists()
    assert Manifest(run_dir).completion() is None
    # the failed output step is a stop like any other (7: output-write failures log a stop event)
    stops = [e for e in EventLog(run_dir).events() if e["event"] == "stop"]
    assert [(s["exit_code"], s.get("kind")) for s in stops] == [(6, "local_io")]
    res = run_job(job, resume=True, progress=False, echo=_quiet)
    assert res["status"] == "done" and Path(res["run_dir"]) == run_dir and res["captured"] == 0
    assert (run_dir / "preview.png").is_file() and Manifest(run_dir).completion() is not None


# --------------------------------------------------------------------------- 2. a voided dark frame
def test_a_dark_frame_truncated_after_its_light_was_recorded_is_retaken_first(tmp_path):
    job = load_job(_job(tmp_path))
    stop = StopEvent()
    cam = StoppingCamera(MockCamera("camera-B", _scene(), seed=1), stop, after=5)  # 3 darks, 2 lights
    with pytest.raises(RunInterrupted) as info:
        run_job(job, progress=False, echo=_quiet, camera=cam, stop=stop)
    run_dir = Path(info.value.run_dir)
    frames = Manifest(run_dir).frames()
    dark = next(r for r in frames.values() if r["kind"] == "dark" and r["requested_exposure_s"] == 0.004)
    assert any(r["kind"] == "light" and r["requested_exposure_s"] == 0.004 for r in frames.values())
    path = run_dir / dark["file"]
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    res = run_job(job, resume=True, progress=False, echo=_quiet)
    assert res["status"] == "done" and res["captured"] == 2 and res["frames"] == 6
    _frames_once(run_dir)
    recs = [r["type"] for r in Manifest(run_dir).records() if r.get("key") == dark["key"]]
    assert recs == ["frame", "void", "frame"]
    events = EventLog(run_dir).events()
    names = [(e["event"], e.get("key")) for e in events]
    resumed = names[names.index(("stop", None)) :]
    # voided, then taken again (the light blocked for it) before anything was merged again
    assert (
        resumed.index(("void", dark["key"])) < resumed.index(("frame", dark["key"])) < resumed.index(("merged", None))
    )
    assert [e["exit_code"] for e in events if e["event"] == "stop"] == [143]


# --------------------------------------------------------------------------- 3. cover/uncover commands
@pytest.mark.slow
def test_a_hanging_cover_command_ends_the_run_and_leaves_no_process(tmp_path):
    darks = 'block_light = "command"\ncover_command = "sleep 100017"\nuncover_command = "true"\ncommand_timeout_s = 5'
    p = _job(tmp_path, darks=darks)
    t0 = time.monotonic()
    proc = subprocess.run(
        _run_args(p), cwd=tmp_path, capture_output=True, text=True, timeout=60, env=_run_env(tmp_path)
    )
    assert proc.returncode not in (0, 2), proc.stderr
    assert time.monotonic() - t0 < 60
    assert "cover command" in proc.stderr and "5 s" in proc.stderr and "Traceback" not in proc.stderr
    assert _gone("sleep 100017") == []


def test_two_sigterms_during_a_hanging_cover_command_leave_no_process(tmp_path):
    # "&& true": the shell forks the sleep instead of becoming it, so killing the shell alone
    # (what subprocess.run does when a second signal interrupts it) would leave the sleep behind
    darks = 'block_light = "command"\ncover_command = "sleep 100021 && true"\nuncover_command = "true"'
    p = _job(tmp_path, darks=darks)
    proc = _start_run(tmp_path, p)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not _processes("sleep 100021"):
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.02)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)  # a second signal (systemd's, or an impatient user's)
        _out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    # 143, or killed by the second signal itself once the first one's stop was reported
    assert proc.returncode in (143, -signal.SIGTERM), err
    assert "stopped by signal 15" in err and "Traceback" not in err
    assert time.monotonic() - t0 < 10
    time.sleep(0.2)
    assert _gone("sleep 100021") == []


def test_a_light_command_is_killed_with_its_children_when_the_run_stops(tmp_path):
    stop = StopEvent()
    blocker = LightBlocker("command", "sleep 100018 & sleep 100019", "true", command_timeout_s=60, stop=stop)
    threading.Timer(0.5, stop.stop, args=(signal.SIGTERM,)).start()
    t0 = time.monotonic()
    with pytest.raises(RunInterrupted) as info:
        blocker.set(MockCamera("camera-B", _scene((8, 8))), True)
    assert info.value.exit_code == 143 and time.monotonic() - t0 < 10
    assert _gone("sleep 100018") == [] and _gone("sleep 100019") == []
    with pytest.raises(SessionError, match=r"cover command 'sleep 100020' did not end within 0.5 s"):
        LightBlocker("command", "sleep 100020", "true", command_timeout_s=0.5).set(
            MockCamera("camera-B", _scene((8, 8))), True
        )
    assert _gone("sleep 100020") == []


def test_the_command_timeout_is_in_the_schema(tmp_path):
    assert load_job(_job(tmp_path))["darks"]["command_timeout_s"] == 60
    with pytest.raises(JobError, match="darks.command_timeout_s: must be > 0"):
        load_job(_job(tmp_path, darks="command_timeout_s = 0"))


# --------------------------------------------------------------------------- 4. a camera that ignores the shutter
def test_the_mock_camera_can_ignore_the_shutter_setting(tmp_path):
    from hdrcap.pipeline.io.raw import read_frame

    cam = MockCamera("camera-B", _scene(), faults=MockFaults(stuck_exposure_s=0.01))
    assert cam.set_exposure(1.0) == 0.01
    assert read_frame(cam.capture(tmp_path / "a.dng").path).exposure_time == pytest.approx(0.01)


def test_a_camera_that_ignores_the_shutter_setting_stops_the_run(tmp_path):
    job = load_job(_job(tmp_path, camera="faults = { stuck_exposure_s = 0.01 }"))
    with pytest.raises(SessionError) as info:
        run_job(job, progress=False, echo=_quiet)
    err = info.value
    assert err.exit_code == 4
    assert "applied 0.01 s" in str(err) and "requested 0.004 s" in str(err)
    stops = [e for e in EventLog(Path(err.run_dir)).events() if e["event"] == "stop"]
    assert [s["exit_code"] for s in stops] == [4]
    assert Manifest(Path(err.run_dir)).frames() == {}


# --------------------------------------------------------------------------- 5. snapped job times
def test_snapped_times_are_warned_about_and_recorded_as_given(tmp_path):
    p = _job(
        tmp_path,
        camera="allowed_times = [0.001, 0.004, 0.016, 0.064, 0.25, 1.0]",
        exposure='mode = "bracket"\ntimes = [0.004, 0.06, 0.3]',
    )
    said: list[str] = []
    res = run_job(load_job(p), progress=False, echo=said.append)
    warned = [s for s in said if "warning" in s]
    assert len(warned) == 2 and "0.06 s" in warned[0] and "0.064 s" in warned[0] and "exposure.times" in warned[0]
    assert "0.3 s" in warned[1] and "0.25 s" in warned[1]
    lights = {r["job_exposure_s"]: r for r in _frames_once(Path(res["run_dir"])).values() if r["kind"] == "light"}
    assert sorted(lights) == [0.004, 0.06, 0.3]
    assert lights[0.06]["requested_exposure_s"] == lights[0.06]["applied_exposure_s"] == 0.064
    head = Manifest(Path(res["run_dir"])).header()
    assert head["planning"]["snapped_times"] == [[0.06, 0.064], [0.3, 0.25]]


def test_two_times_that_snap_to_one_are_refused_unless_repeats_says_so(tmp_path):
    p = _job(
        tmp_path,
        camera="allowed_times = [0.001, 0.004, 0.016, 0.064, 0.25, 1.0]",
        exposure='mode = "bracket"\ntimes = [0.004, 0.06, 0.07]',
    )
    with pytest.raises(JobError) as info:
        run_job(load_job(p), progress=False, echo=_quiet)
    assert info.value.exit_code == 2 and "exposure.times" in str(info.value)
    assert "0.06 s and 0.07 s" in str(info.value) and "repeats" in str(info.value)
    assert not (tmp_path / "runs").exists()
    # the same time twice is what repeats = 2 asks for
    p = _job(tmp_path, exposure='mode = "bracket"\ntimes = [0.004, 0.064]\nrepeats = 2')
    res = run_job(load_job(p), progress=False, echo=_quiet)
    assert res["frames"] == 2 + 4


# --------------------------------------------------------------------------- 6. the light after a stop
def test_a_stopped_run_uncovers_the_light(tmp_path):
    state = tmp_path / "light"
    blocker = LightBlocker("command", f"echo covered > {state}", f"echo open > {state}")
    stop = StopEvent()
    cam = StoppingCamera(MockCamera("camera-B", _scene(), seed=2), stop, after=1)
    plan = CapturePlan.bracket([0.004, 0.032, 0.25], cam.allowed_exposure_times())
    with pytest.raises(RunInterrupted):
        CaptureSession(cam, tmp_path / "r", plan, light=blocker, retry=FAST, progress=False, stop=stop).run()
    assert state.read_text().strip() == "open" and not cam.covered
    lights = [(e["covered"], e.get("ok", True)) for e in EventLog(tmp_path / "r").events() if e["event"] == "light"]
    assert lights == [(True, True), (False, True)]
    # an uncover that fails is recorded, and the stop keeps its own exit status
    bad = LightBlocker("command", f"echo covered > {state}", "exit 3")
    stop = StopEvent()
    cam = StoppingCamera(MockCamera("camera-B", _scene(), seed=2), stop, after=1)
    with pytest.raises(RunInterrupted):
        CaptureSession(cam, tmp_path / "r2", plan, light=bad, retry=FAST, progress=False, stop=stop).run()
    events = EventLog(tmp_path / "r2").events()
    failed = [e for e in events if e["event"] == "light" and not e.get("ok", True)]
    assert len(failed) == 1 and failed[0]["covered"] is True and "exit 3" in failed[0]["error"]
    assert [e["exit_code"] for e in events if e["event"] == "stop"] == [143]


def test_metering_refuses_frames_without_light(tmp_path):
    p = _job(tmp_path, exposure='mode = "snr"\ntarget_snr_db = 20.0\nmax_exposures = 3')
    cam = MockCamera("camera-B", _scene(), seed=1)
    cam.cover()  # the light was left blocked
    with pytest.raises(VerificationError) as info:
        run_job(load_job(p), camera=cam, progress=False, echo=_quiet)
    assert info.value.exit_code == 7 and "no light" in str(info.value)
    assert not Manifest(Path(info.value.run_dir)).exists()
    cam.uncover()
    assert run_job(load_job(p), camera=cam, progress=False, echo=_quiet, resume=True)["status"] == "done"


# --------------------------------------------------------------------------- 7. the soak's findings
def test_each_repetition_draws_its_own_faults(tmp_path):
    # fault seed 0 (the default): its first repetition meets busy only
    faults = "faults = { busy_rate = 0.15, disconnect_rate = 0.05, corrupt_rate = 0.05 }"
    job = load_job(_job(tmp_path, camera=faults))
    results = run_schedule(job, repeat=12, progress=False, echo=_quiet)
    per_run = []
    for res in results:
        events = EventLog(Path(res["run_dir"])).events()
        per_run.append(tuple((e["key"], e["kind"]) for e in events if e["event"] == "fault"))
    kinds = Counter(kind for run in per_run for _key, kind in run)
    assert {"busy", "reconnect", "recapture"} <= set(kinds), kinds
    assert len(set(per_run)) > 6  # not one fault sequence replayed 12 times


def test_lock_files_do_not_accumulate(tmp_path, monkeypatch):
    locks = tmp_path / "locks"
    monkeypatch.setenv("HDRCAP_LOCK_DIR", str(locks))
    job = load_job(_job(tmp_path))
    results = run_schedule(job, repeat=3, progress=False, echo=_quiet)
    assert sorted(p.name for p in locks.iterdir()) == []
    assert all(not (Path(r["run_dir"]) / ".hdrcap.lock").exists() for r in results)


def test_a_lock_file_removed_by_its_holder_is_not_shared(tmp_path):
    from hdrcap.acquire.capture.session import PathLock

    path = tmp_path / "x.lock"
    first = PathLock(path)
    assert first.acquire()
    assert not PathLock(path).acquire()  # held
    waiting = os.open(path, os.O_RDWR)  # a contender that opened the file before it was removed
    first.release()
    assert not path.exists()
    second = PathLock(path)
    assert second.acquire()
    import fcntl

    fcntl.flock(waiting, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the old file: locking it locks nothing
    assert os.fstat(waiting).st_ino != os.stat(path).st_ino
    os.close(waiting)
    assert not PathLock(path).acquire()
    second.release()


@pytest.mark.usefixtures("sigterm_guard")
def test_an_interrupted_repetition_is_reported_once_with_keep_going(tmp_path, monkeypatch, capsys):
    import hdrcap.acquire.capture.run as run_mod
    from hdrcap.cli import main
    from tests.helpers.cameras import SignallingCamera

    real_open = run_mod.open_camera
    opened: list = []

    def open_signalling(job, n=0):
        cam = SignallingCamera(real_open(job, n), after=2) if n == 1 else real_open(job, n)
        opened.append(cam)
        return cam

    monkeypatch.setattr(run_mod, "open_camera", open_signalling)
    p = _job(tmp_path)
    code = main(["run", str(p), "--repeat", "3", "--keep-going", "--json", "--no-progress"])
    assert code == 143
    lines = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [(r["status"], r.get("repetition")) for r in lines] == [("done", 0), ("failed", 1)]


def test_sigterm_does_not_wait_for_a_hung_camera_call(tmp_path):
    faults = "faults = { hang_rate = 1.0, hang_s = 30.0, hang_ignores_timeout = true }"
    p = _job(tmp_path, camera=faults, folder="runs/hung")
    proc = _start_run(tmp_path, p)
    events = tmp_path / "runs" / "hung" / "events.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (events.exists() and '"light"' in events.read_text()):
        time.sleep(0.05)
    time.sleep(0.3)  # inside the hung capture
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert time.monotonic() - t0 < 10
    names = [e["event"] for e in EventLog(events.parent).events()]
    assert "reconnect" not in names and names[-1] == "stop"


def test_the_gphoto2_worker_gives_up_a_hung_call_when_the_run_stops():
    from hdrcap.acquire.camera.gphoto2 import _Worker
    from hdrcap.acquire.camera.types import CameraTimeoutError

    stop = threading.Event()
    worker = _Worker("test")
    try:
        threading.Timer(0.3, stop.set).start()
        t0 = time.monotonic()
        with pytest.raises(CameraTimeoutError, match="stopping"):
            worker.call("sleep", 60.0, timeout=30.0, abort=stop, grace_s=0.5)
        assert time.monotonic() - t0 < 5 and worker.dead and worker.proc.poll() is not None
    finally:
        worker.stop()


def test_a_read_only_run_folder_is_a_local_io_error_at_validation_and_during_the_run(tmp_path, monkeypatch):
    real_access = os.access
    ro = tmp_path / "ro"
    ro.mkdir()
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == ro else real_access(p, mode, **kw))
    p = _job(tmp_path, folder="ro/{job}-{n}")
    with pytest.raises(LocalIOError) as info:
        load_job(p)
    assert info.value.exit_code == 6 and "output.folder" in str(info.value)
    monkeypatch.undo()
    job = load_job(p)
    real_mkdir = Path.mkdir

    def read_only(self, *a, **kw):
        if self.parent == ro:
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real_mkdir(self, *a, **kw)

    monkeypatch.setattr(Path, "mkdir", read_only)
    with pytest.raises(LocalIOError) as info:
        run_job(job, progress=False, echo=_quiet)
    assert info.value.exit_code == 6 and "Read-only" in str(info.value)


def _open_files_under(folder: Path) -> list[str]:
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(folder)):
            out.append(target)
    return out


def test_a_retried_frame_leaves_no_file_open(tmp_path):
    """A fault kept alive with its traceback held the frames of the attempt (memory-mapped raw
    files, open until the cyclic garbage collector ran): open files and memory grew run by run."""
    import gc

    plan = CapturePlan.bracket([0.004, 0.032, 0.25], MockCamera("camera-B", _scene()).allowed_exposure_times())
    gc.collect()
    gc.disable()
    try:
        for k in range(3):
            cam = MockCamera("camera-B", _scene(), seed=k, faults=MockFaults(seed=k, busy_first=1, corrupt_rate=0.3))
            res = CaptureSession(cam, tmp_path / f"r{k}", plan, retry=FAST, progress=False).run()
            assert res.retries
            del res
        # metering retries too
        from hdrcap.acquire.capture.metering import meter_fn

        capture = meter_fn(MockCamera("camera-B", _scene(), faults=MockFaults(busy_first=1)), tmp_path / "m", FAST)
        capture(0.004)
        del capture
        assert _open_files_under(tmp_path) == []
    finally:
        gc.enable()
