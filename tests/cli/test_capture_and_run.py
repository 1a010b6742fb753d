"""The `capture` and `run` commands: a clean stop on SIGTERM for both, the disk-space check of
``run --check``, and the options they share."""

from __future__ import annotations

import json
import signal

import pytest

import hdrcap.acquire.capture.run as run_mod
from hdrcap.acquire.capture.manifest import EventLog, Manifest
from hdrcap.cli import main
from tests.helpers.cameras import SignallingCamera


def test_capture_ends_cleanly_on_sigterm_and_resume_completes(tmp_path, monkeypatch, capsys, sigterm_guard):
    opened = []
    real_open = run_mod.open_camera

    def open_signalling(job, n=0):
        cam = SignallingCamera(real_open(job, n), after=3) if not opened else real_open(job, n)
        opened.append(cam)
        return cam

    monkeypatch.setattr(run_mod, "open_camera", open_signalling)
    out = tmp_path / "c"
    args = [
        "capture",
        "--camera",
        "mock:camera-B",
        "--size",
        "32x24",
        "--times",
        "0.004",
        "0.064",
        "0.5",
        "--out",
        str(out),
        "--no-progress",
    ]
    assert main(args) == 143  # 128 + SIGTERM, as documented
    err = capsys.readouterr().err
    assert "--resume" in err.strip().splitlines()[-1] and "Traceback" not in err
    assert opened[0].closed and opened[0].n == 3  # stopped before the next frame, camera closed
    stops = [e for e in EventLog(out).events() if e["event"] == "stop"]
    assert len(stops) == 1 and stops[0]["exit_code"] == 143
    assert len(Manifest(out).frames()) == 3 and not (out / "hdr.exr").exists()
    # the handler is gone after the command: SIGTERM reaches the test's guard again
    assert signal.getsignal(signal.SIGTERM).__name__ == "unhandled"
    assert main(args + ["--resume", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["resumed"] == 3 and res["captured"] == 3 and (out / "hdr.exr").exists()


JOB = """\
[job]
name = "d"

[camera]
backend = "mock"
preset = "camera-B"
size = "32x24"

[exposure]
mode = "bracket"
times = [0.004, 0.064, 0.5]

[darks]
strategy = "{strategy}"
count = 4

[output]
folder = "runs/{{job}}-{{date}}"
"""


def _disk(free: int):
    import collections

    usage = collections.namedtuple("usage", "total used free")
    return lambda _path: usage(10 * free, 9 * free, free)


@pytest.mark.parametrize("strategy, frames", [("matched", 3 + 3), ("master", 3 + 3 * 4), ("model", 3)])
def test_run_check_reports_the_disk_space_and_refuses_when_short(tmp_path, monkeypatch, capsys, strategy, frames):
    p = tmp_path / "job.toml"
    p.write_text(JOB.format(strategy=strategy))
    # 32x24 photosites: a raw file of 2 B/photosite + 1 MB, the EXR (4 float32) and PNG (3 B) outputs, 16 MB margin
    need = frames * (2 * 768 + 1_000_000) + 19 * 768 + 16_000_000
    monkeypatch.setattr("shutil.disk_usage", _disk(need + 1))
    assert main(["run", str(p), "--check"]) == 0
    out = capsys.readouterr().out
    assert f"{frames} frames" in out and f"about {need / 1e6:.0f} MB" in out and str(tmp_path) in out
    monkeypatch.setattr("shutil.disk_usage", _disk(need - 1))
    assert main(["run", str(p), "--check"]) == 6  # local I/O, as documented
    lines = capsys.readouterr().err.strip().splitlines()
    err = [line for line in lines if not line.startswith("hdrcap: warning:")]  # 0.064 s is taken at 1/15 s
    assert len(err) == 1 and "MB free" in err[0] and f"{frames} planned frames" in err[0]
    # three repetitions need three times the room
    monkeypatch.setattr("shutil.disk_usage", _disk(2 * need))
    assert main(["run", str(p), "--check", "--repeat", "3"]) == 6
    assert not (tmp_path / "runs").exists()  # no frame, no folder


# --------------------------------------------------------------------------- shared option names
def _capture(capsys, *args) -> dict:
    assert main(["capture", "--size", "32x24", "--seed", "3", "--no-progress", "--json", *map(str, args)]) == 0
    return json.loads(capsys.readouterr().out)


def test_capture_plan_and_merge_spell_camera_snr_darks_and_folder_alike(tmp_path, capsys):
    # the spellings of plan / merge / run ...
    new = _capture(
        capsys, "--camera", "camera-B", "--target-snr-db", 20, "--dark-strategy", "model", "--run-dir", tmp_path / "new"
    )
    # ... and the older ones of capture mean the same run: same plan, same frames
    old = _capture(
        capsys, "--camera", "mock:camera-B", "--target-snr", 20, "--darks", "model", "--out", tmp_path / "old"
    )
    assert new["run_dir"] == str(tmp_path / "new") and old["run_dir"] == str(tmp_path / "old")
    plans = [Manifest(tmp_path / d).header()["plan"] for d in ("new", "old")]
    assert plans[0] == plans[1] and plans[0]["dark_strategy"] == "model"
    assert new["frames"] == old["frames"] == sum(f["kind"] == "light" for f in plans[0]["frames"])
    # plan takes capture's camera spelling and SNR alias, with the same result
    base = ["plan", "--meter", "--size", "32x24", "--json"]
    assert main(base + ["--camera", "camera-B", "--target-snr-db", "20"]) == 0
    a = json.loads(capsys.readouterr().out)
    assert main(base + ["--camera", "mock:camera-B", "--target-snr", "20"]) == 0
    assert json.loads(capsys.readouterr().out) == a
    # merge takes it too (its calibration: the preset's nominal parameters)
    lights = sorted(
        str(tmp_path / "new" / r["file"]) for r in Manifest(tmp_path / "new").frames().values() if r["kind"] == "light"
    )
    for cam, name in (("camera-B", "a.exr"), ("mock:camera-B", "b.exr")):
        assert main(["merge", *lights, "--camera", cam, "-o", str(tmp_path / name), "--json"]) == 0
        capsys.readouterr()
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    # a real camera has no nominal parameters: one line, exit 2
    assert main(["plan", "--meter", "--camera", "gphoto2:D750", "--target-snr-db", "20"]) == 2
    assert "--calibration" in capsys.readouterr().err
