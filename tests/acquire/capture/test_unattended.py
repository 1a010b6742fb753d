"""Unattended rigs: --resume on finished and interrupted runs, repeat-safe folders, --keep-going,
JSON lines and JSON errors, exit codes, SIGTERM, frame events, logging, notification hooks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hdrcap.acquire.camera.mock import MockCamera
from hdrcap.acquire.capture.job import job_from_dict, load_job
from hdrcap.acquire.capture.manifest import EventLog, Manifest
from hdrcap.acquire.capture.run import run_job
from hdrcap.acquire.capture.schedule import ScheduleError, run_schedule
from hdrcap.acquire.capture.session import (
    EXIT_CODES,
    CapturePlan,
    CaptureSession,
    LocalIOError,
    RunConflictError,
    RunInterrupted,
    StopEvent,
    VerificationError,
)
from hdrcap.pipeline.io.files import sha256_file
from tests.helpers.cameras import StoppingCamera as _StoppingCamera
from tests.helpers.jobs import FAST, mock_job

REPO = Path(__file__).resolve().parents[3]


def _job(tmp_path, folder="runs/{job}-{date}", faults="", backoff=0.001, extra="", name="job.toml") -> Path:
    return mock_job(
        tmp_path / name,
        name="u",
        camera=faults,
        session=f"backoff_s = {backoff}\nmax_backoff_s = {backoff}",
        folder=folder,
        output=extra,
    )


def _quiet(_msg):
    pass


def _hdrcap(*args, env=None, **kw) -> subprocess.Popen:
    full = dict(os.environ, **(env or {}))
    return subprocess.Popen(
        [sys.executable, "-m", "hdrcap", *map(str, args)],
        cwd=kw.get("cwd", REPO),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=full,
    )


def _frames_once(run_dir: Path) -> dict:
    """Every planned frame recorded exactly once (after voids), files hashed right."""
    m = Manifest(run_dir)
    planned = {f["key"] for f in m.header()["plan"]["frames"]}
    frames = m.frames()
    assert set(frames) == planned
    for rec in frames.values():
        assert sha256_file(run_dir / rec["file"]) == rec["sha256"]
    assert sorted(p.name for p in (run_dir / "frames").iterdir()) == sorted(
        Path(r["file"]).name for r in frames.values()
    )
    return frames


# --------------------------------------------------------------------------- item: resume / repeat / JSON
def test_repeat_three_with_the_date_folder_prints_three_json_lines_and_resume_is_a_noop(tmp_path, cli):
    p = _job(tmp_path)
    proc = cli("run", p, "--repeat", "3", "--json", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(line) for line in proc.stdout.strip().splitlines()]
    assert len(lines) == 3 and [r["repetition"] for r in lines] == [0, 1, 2]
    dirs = [Path(r["run_dir"]) for r in lines]
    assert len(set(dirs)) == 3 and all((d / "hdr.exr").is_file() for d in dirs)
    for d in dirs:
        _frames_once(d)
    # --resume on a finished schedule: exit 0, the newest run's summary re-reported, nothing captured
    before = {d: (d / "manifest.jsonl").read_bytes() for d in dirs}
    again = cli("run", p, "--resume", "--json", "--no-progress")
    assert again.returncode == 0, again.stderr
    (res,) = [json.loads(line) for line in again.stdout.strip().splitlines()]
    assert res["status"] == "already_complete" and res["captured"] == 6 and Path(res["run_dir"]) in dirs
    assert {d: (d / "manifest.jsonl").read_bytes() for d in dirs} == before


def test_resume_picks_the_newest_incomplete_run_not_the_newest_folder(tmp_path):
    p = _job(tmp_path, folder="runs/{job}-{date}")
    job = load_job(p)
    first = run_job(job, progress=False, echo=_quiet)
    # an interrupted run: the plan header and one frame, no outputs (made by stopping after 1 frame)
    stop = StopEvent()
    cam = _StoppingCamera(MockCamera("camera-B", _scene((24, 32)), seed=1), stop, after=1)
    with pytest.raises(RunInterrupted) as info:
        run_job(job, progress=False, echo=_quiet, camera=cam, stop=stop)
    assert info.value.exit_code == 143
    broken = Path(info.value.run_dir)
    assert broken != Path(first["run_dir"])
    # a newer complete run must not hide the interrupted one
    third = run_job(job, progress=False, echo=_quiet)
    assert Path(third["run_dir"]).name > broken.name
    res = run_job(job, resume=True, progress=False, echo=_quiet)
    assert res["status"] == "done" and Path(res["run_dir"]) == broken
    assert res["resumed"] == 1 and res["captured"] == 5
    _frames_once(broken)
    assert run_job(job, resume=True, progress=False, echo=_quiet)["status"] == "already_complete"


def test_resume_without_any_run_is_a_noop(tmp_path):
    res = run_job(load_job(_job(tmp_path)), resume=True, progress=False, echo=_quiet)
    assert res["status"] == "nothing_to_resume" and not (tmp_path / "runs").exists()


def test_keep_going_reports_each_repetition_and_exits_with_the_first_failure(tmp_path):
    p = _job(tmp_path, folder="runs/{job}-{n}")
    job = load_job(p)
    blocked = tmp_path / "runs" / "u-1"
    blocked.mkdir(parents=True)
    (blocked / "manifest.jsonl").write_text('{"type": "run", "plan_fingerprint": "other"}\n')
    seen = []
    with pytest.raises(ScheduleError) as info:
        run_schedule(job, repeat=3, keep_going=True, on_result=seen.append, progress=False, echo=_quiet)
    assert info.value.exit_code == 5 and "1 of 3" in str(info.value)
    assert [r["status"] for r in seen] == ["done", "failed", "done"]
    assert seen[1]["exit_code"] == 5 and seen[1]["run_dir"] == str(blocked) and seen[1]["repetition"] == 1
    # without --keep-going the first failure ends the schedule
    seen.clear()
    with pytest.raises(RunConflictError):
        run_schedule(
            load_job(_job(tmp_path, folder="runs/{job}-{n}")),
            repeat=3,
            on_result=seen.append,
            progress=False,
            echo=_quiet,
            resume=False,
        )
    assert seen == []  # u-0 holds a finished run now: the first repetition conflicts


def test_json_error_object_and_exit_codes_on_the_command_line(tmp_path, cli):
    bad = _job(tmp_path).read_text().replace('strategy = "matched"', 'strategy = "sometimes"')
    (tmp_path / "bad.toml").write_text(bad)
    proc = cli("run", tmp_path / "bad.toml", "--json")
    assert proc.returncode == 2
    err = json.loads(proc.stdout)
    assert err["status"] == "failed" and err["exit_code"] == 2 and "darks.strategy" in err["error"]
    assert proc.stderr.startswith("hdrcap: error:") and "Traceback" not in proc.stderr
    # keep-going: one JSON line per repetition, the failed one as an error object, exit status 5
    p = _job(tmp_path, folder="runs/{job}-{n}")
    (tmp_path / "runs" / "u-1").mkdir(parents=True)
    (tmp_path / "runs" / "u-1" / "manifest.jsonl").write_text('{"type": "run", "plan_fingerprint": "x"}\n')
    proc = cli("run", p, "--repeat", "3", "--keep-going", "--json", "--no-progress")
    assert proc.returncode == 5, proc.stderr
    lines = [json.loads(line) for line in proc.stdout.strip().splitlines()]
    assert [r["status"] for r in lines] == ["done", "failed", "done"]


def test_exit_codes_are_distinct_and_documented():
    codes = {
        RunConflictError("x").exit_code,
        LocalIOError("x").exit_code,
        VerificationError("x").exit_code,
        RunInterrupted("x", signal.SIGTERM).exit_code,
        RunInterrupted("x", signal.SIGINT).exit_code,
    }
    assert codes == {5, 6, 7, 143, 130}
    doc = (REPO / "docs" / "acquisition.md").read_text()
    for code in EXIT_CODES:
        assert f"| {code} |" in doc, code


# --------------------------------------------------------------------------- item: signals, events, logging, hooks
def _scene(shape):
    from hdrcap.mock_camera.scenes import make_scene

    return make_scene("hdr", shape, decades=3.0, x_max=2e4)


def test_stop_event_ends_the_session_between_frames_and_resume_completes(tmp_path):
    from hdrcap.acquire.camera.model import camera_model

    cal = camera_model(camera="camera-B")
    plan = CapturePlan.bracket([0.004, 0.032, 0.25], MockCamera("camera-B", _scene((24, 32))).allowed_exposure_times())
    stop = StopEvent()
    cam = _StoppingCamera(MockCamera("camera-B", _scene((24, 32)), seed=2), stop, after=4)
    with pytest.raises(RunInterrupted) as info:
        CaptureSession(cam, tmp_path / "r", plan, calibration=cal, retry=FAST, progress=False, stop=stop).run()
    assert info.value.exit_code == 143
    events = EventLog(tmp_path / "r").events()
    assert events[-1]["event"] == "stop" and events[-1]["exit_code"] == 143
    assert len(Manifest(tmp_path / "r").frames()) == 4
    res = CaptureSession(
        MockCamera("camera-B", _scene((24, 32)), seed=2),
        tmp_path / "r",
        plan,
        calibration=cal,
        retry=FAST,
        progress=False,
        resume=True,
    ).run()
    assert res.resumed == 4 and res.captured == 2
    frames = [e for e in EventLog(tmp_path / "r").events() if e["event"] == "frame"]
    # one frame event per captured frame, with index, total, ETA and temperature; the ETA ends at 0
    assert [e["done"] for e in frames] == [1, 2, 3, 4, 5, 6]
    assert all(e["total"] == 6 and "temperature_c" in e and e["eta_s"] >= 0 for e in frames)
    assert frames[3]["eta_s"] >= 0.032 + 0.25 and frames[-1]["eta_s"] == 0


def test_sigterm_ends_a_run_cleanly_and_resume_completes(tmp_path):
    p = _job(tmp_path, faults="faults = { busy_rate = 0.6, seed = 4 }", backoff=0.15)
    proc = _hdrcap("run", p, "--no-progress", cwd=tmp_path)
    runs = tmp_path / "runs"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        ev = list(runs.glob("*/events.jsonl"))
        if ev and '"event":"frame"' in ev[0].read_text():
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and last.startswith("hdrcap: error:") and "--resume" in last
    (run_dir,) = runs.iterdir()
    stop = [e for e in EventLog(run_dir).events() if e["event"] == "stop"]
    assert len(stop) == 1 and stop[0]["exit_code"] == 143
    assert not (run_dir / "hdr.exr").exists()
    # the camera lock was released (the camera closed): the resume runs at once and completes
    again = _hdrcap("run", p, "--resume", "--json", "--no-progress", cwd=tmp_path)
    out, err = again.communicate(timeout=300)
    assert again.returncode == 0, err
    res = json.loads(out)
    assert Path(res["run_dir"]) == run_dir
    assert res["resumed"] >= 1 and res["resumed"] + res["captured"] + res["adopted"] == 6
    _frames_once(run_dir)


def test_verbose_logs_events_and_quiet_hides_them(tmp_path, cli):
    p = _job(tmp_path, folder="runs/{job}-{n}")
    loud = cli("-v", "run", p, "--no-progress")
    assert loud.returncode == 0, loud.stderr
    assert "INFO: u-0 frame" in loud.stderr and "eta_s" in loud.stderr
    quiet = cli("-q", "run", p, "--run-dir", tmp_path / "q", "--no-progress")
    assert quiet.returncode == 0 and "frame" not in quiet.stderr


def test_notification_hooks_get_the_summary(tmp_path):
    log = tmp_path / "hook.log"
    extra = (
        f'\n[notify]\non_done = "cat >> {log}; echo \\" $HDRCAP_STATUS\\" >> {log}"\n'
        f'on_failure = "echo \\"failed $HDRCAP_EXIT_CODE $HDRCAP_RUN_DIR\\" >> {log}"\n'
    )
    job = load_job(_job(tmp_path, folder="runs/{job}-{n}", extra=extra))
    blocked = tmp_path / "runs" / "u-1"
    blocked.mkdir(parents=True)
    (blocked / "manifest.jsonl").write_text('{"type": "run", "plan_fingerprint": "x"}\n')
    with pytest.raises(ScheduleError):
        run_schedule(job, repeat=2, keep_going=True, progress=False, echo=_quiet)
    text = log.read_text()
    summary = json.loads(text.splitlines()[0][: text.splitlines()[0].rindex("}") + 1])
    assert summary["status"] == "done" and summary["frames"] == 6
    assert text.splitlines()[-1] == f"failed 5 {blocked}"


def test_a_failing_hook_is_only_a_warning(tmp_path):
    warnings = []
    job = job_from_dict({"notify": {"on_done": "exit 3"}, "exposure": {"times": [0.01]}})
    from hdrcap.acquire.capture.notify import notify

    notify(job, {"status": "done"}, warnings.append)
    assert len(warnings) == 1 and "exit 3" in warnings[0]


# --------------------------------------------------------------------------- item: metering
SNR = """
[exposure]
mode = "snr"
target_snr_db = 20.0
max_exposures = 3
"""


def _snr_job(tmp_path, faults, folder="runs/{job}-{date}") -> Path:
    text = _job(tmp_path, folder=folder, faults=faults).read_text()
    text = text.replace('[exposure]\nmode = "bracket"\ntimes = [0.004, 0.064, 0.5]\n', SNR)
    p = tmp_path / "job.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("folder", ["runs/{job}-{date}", "runs/fixed"])
def test_a_kill_during_metering_leaves_a_run_that_resume_and_a_fresh_start_complete(tmp_path, cli, folder):
    p = _snr_job(tmp_path, "faults = { kill_after = 1 }", folder)
    first = cli("run", p, "--no-progress", cwd=tmp_path)
    assert first.returncode == 137
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert list((run_dir / "meter").iterdir()) and not (run_dir / "manifest.jsonl").exists()
    _snr_job(tmp_path, "", folder)
    resumed = cli("run", p, "--resume", "--json", "--no-progress", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    res = json.loads(resumed.stdout)
    assert Path(res["run_dir"]) == run_dir and res["status"] == "done" and (run_dir / "hdr.exr").is_file()
    _frames_once(run_dir)
    if folder == "runs/fixed":  # a fresh start in a folder a metering kill left behind
        (tmp_path / "runs" / "again" / "meter").mkdir(parents=True)
        for f in (run_dir / "meter").iterdir():
            (tmp_path / "runs" / "again" / "meter" / f.name).write_bytes(f.read_bytes())
        fresh = cli("run", p, "--run-dir", tmp_path / "runs" / "again", "--no-progress", cwd=tmp_path)
        assert fresh.returncode == 0, fresh.stderr


def test_metering_retries_busy_and_disconnects(tmp_path):
    p = _snr_job(tmp_path, "faults = { busy_first = 3, disconnect_rate = 0.3, seed = 2 }")
    res = run_job(load_job(p), progress=False, echo=_quiet)
    assert res["status"] == "done"
    meters = list((Path(res["run_dir"]) / "meter").iterdir())
    assert meters


# --------------------------------------------------------------------------- item: locks
def test_locks_are_taken_before_the_camera_is_opened(tmp_path, monkeypatch):
    from filelock import FileLock

    import hdrcap.acquire.capture.run as run_mod
    from hdrcap.acquire.capture.camera_setup import job_camera_key
    from hdrcap.acquire.capture.session import hold_run_locks, lock_dir

    monkeypatch.setenv("HDRCAP_LOCK_DIR", str(tmp_path / "locks"))
    opened = []
    real_open = run_mod.open_camera
    monkeypatch.setattr(run_mod, "open_camera", lambda *a, **kw: opened.append(1) or real_open(*a, **kw))
    job = load_job(_job(tmp_path, folder="runs/{job}-{n}"))
    with hold_run_locks(tmp_path / "runs" / "u-0"):
        with pytest.raises(RunConflictError, match="another hdrcap session") as info:
            run_job(job, progress=False, echo=_quiet)
    assert info.value.exit_code == 5 and opened == [] and not (tmp_path / "runs").exists()
    # a real camera named by the job: locked by its serial (else model, port) before it is opened
    gp = job_from_dict(
        {
            "camera": {"backend": "gphoto2", "model": "Nikon DSC D750", "serial": "300123"},
            "darks": {"block_light": "none"},
            "exposure": {"times": [0.01]},
            "calibration": {"preset": "camera-B"},
        }
    )
    assert job_camera_key(gp) == "gphoto2-serial-300123"
    with FileLock(str(lock_dir() / "open-gphoto2-serial-300123.lock")):
        with pytest.raises(RunConflictError, match="300123 is in use"):
            run_job(gp, run_dir=tmp_path / "gp", progress=False, echo=_quiet)
    assert opened == []


def test_the_default_lock_folder_is_per_user_not_tmp(tmp_path, monkeypatch):
    from hdrcap.acquire.capture.session import lock_dir

    monkeypatch.delenv("HDRCAP_LOCK_DIR", raising=False)
    (tmp_path / "run").mkdir()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run"))
    assert lock_dir() == tmp_path / "run" / "hdrcap" / "locks"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    assert lock_dir() == tmp_path / "state" / "hdrcap" / "locks" and lock_dir().is_dir()
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert lock_dir() == tmp_path / "home" / ".local" / "state" / "hdrcap" / "locks"
    assert oct(lock_dir().stat().st_mode & 0o777) == "0o700"


def test_capture_json_error_object_and_run_out_alias(tmp_path, cli):
    proc = cli("capture", "--camera", "mock:camera-Z", "--times", "0.01", "--out", tmp_path / "c", "--json")
    assert proc.returncode == 2 and json.loads(proc.stdout)["exit_code"] == 2, proc.stderr
    p = _job(tmp_path)
    ok = cli("run", p, "--out", tmp_path / "here", "--json", "--no-progress")
    assert ok.returncode == 0 and Path(json.loads(ok.stdout)["run_dir"]) == tmp_path / "here", ok.stderr
