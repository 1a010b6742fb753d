"""Gphoto2Camera against libgphoto2's virtual PTP camera (shipped in the gphoto2 wheel).

Each test runs in its own interpreter: VCAMERADIR must be set before ``import gphoto2``, the
virtual camera allows 26 captures per process, and a misuse of libgphoto2 aborts the process.
XDG_CONFIG_HOME points at a temporary folder so nothing is written to the user's settings.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.gphoto2

PRELUDE = """
import json, os, sys, threading, time
from pathlib import Path
sys.path.insert(0, {repo!r})
from hdrcap.acquire.gphoto2_camera import Gphoto2Camera, list_cameras
from hdrcap.acquire.camera import (CameraBusyError, CameraDisconnectedError, CameraGoneError, StorageFullError,
                            frame_is_dark, fault_kind)
OUT = Path({out!r})
RESULT = {{}}
"""


def _vcam_dir(tmp_path: Path, shade: int = 200) -> Path:
    from PIL import Image

    d = tmp_path / "vcamera"
    d.mkdir()
    Image.new("RGB", (64, 48), (shade, shade, shade)).save(d / "scene.jpg", quality=95)
    return d


def _dng(path: Path, t: float) -> None:
    import datetime

    from hdrcap.mock_camera.dng import write_dng

    data = (np.arange(32 * 32, dtype=np.uint16).reshape(32, 32) % 900 + 40).astype(np.uint16)
    with open(path, "wb") as f:
        write_dng(f, data, exposure_time=t, iso=200, black_level=32, white_level=1023, cfa="RGGB", make="hdrcap",
                  model="vcam test", serial="7", timestamp=datetime.datetime(2026, 1, 1), description="")


def run_vcam(tmp_path: Path, body: str, vdir: Path | None = None) -> dict:
    vdir = vdir or _vcam_dir(tmp_path)
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    script = PRELUDE.format(repo=str(REPO), out=str(out)) + textwrap.dedent(body) + "\nprint(json.dumps(RESULT))\n"
    env = dict(os.environ, VCAMERADIR=str(vdir), XDG_CONFIG_HOME=str(tmp_path / "xdg"))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_detect_identity_and_settings_read_back(tmp_path):
    r = run_vcam(tmp_path, """
        RESULT["cameras"] = list_cameras()
        cam = Gphoto2Camera(model="d750")
        RESULT["identity"] = cam.identity.to_dict()
        RESULT["times"] = cam.allowed_exposure_times()
        RESULT["t_exact"] = cam.set_exposure(0.05)
        RESULT["t_coerced"] = cam.set_exposure(0.03)
        RESULT["label"] = cam.get_setting("shutterspeed")
        RESULT["aperture"] = cam.set_setting("aperture", "f/5.6")   # Nikon calls it f-number
        RESULT["aperture_near"] = cam.set_setting("aperture", "5.3")
        RESULT["applied"] = cam.applied
        try:
            Gphoto2Camera(model="Canon EOS")
        except CameraGoneError as e:
            RESULT["gone"] = str(e)
        cam.close()
    """)
    assert r["cameras"] == [["Nikon DSC D750", "usb:001,001"]]
    assert r["identity"]["model"] == "Nikon DSC D750" and r["identity"]["port"] == "usb:001,001"
    assert r["times"] == sorted(r["times"]) and 0.01 in r["times"] and 1.0 in r["times"]
    assert r["t_exact"] == pytest.approx(0.05)
    # 0.03 s is not offered: the log-nearest offered speed is 0.02 s and it is what is read back
    assert r["t_coerced"] == pytest.approx(0.02) and r["label"] == "0.0200s"
    assert r["aperture"] == "f/5.6" and r["aperture_near"] == "f/5.6"
    assert r["applied"]["shutterspeed"] == "0.0200s" and r["applied"]["aperture"] == "f/5.6"
    assert "no camera model 'Canon EOS'" in r["gone"] and "Nikon DSC D750" in r["gone"]


def test_capture_download_delete_and_dng_from_card(tmp_path):
    vdir = _vcam_dir(tmp_path)
    _dng(vdir / "frame.dng", 1 / 125)
    r = run_vcam(tmp_path, """
        cam = Gphoto2Camera()
        before = cam.list_files()
        cam.set_exposure(0.01)
        res = cam.capture(OUT / "a.dng")
        after = cam.list_files()
        RESULT.update(path=str(res.path), camera_file=res.camera_file, applied=res.applied_exposure_s,
                      before=before, after=after)
        keep = Gphoto2Camera.__new__(Gphoto2Camera)
        cam.delete_after_download = False
        res2 = cam.capture(OUT / "b.dng")
        RESULT["kept"] = res2.camera_file in cam.list_files()
        dng = [f for f in before if f.endswith(".dng")][0]
        RESULT["dng"] = str(cam.download(dng, OUT / "card.dng"))
        cam.close()
    """, vdir)
    got = Path(r["path"])
    assert got.suffix == ".jpg"  # the suffix is the camera file's
    assert got.read_bytes() == (vdir / "scene.jpg").read_bytes()  # the virtual camera returns its .jpg
    assert r["applied"] == pytest.approx(0.01)
    assert r["camera_file"] not in r["after"] and r["kept"]
    from hdrcap.pipeline.io import read_frame

    fr = read_frame(r["dng"])
    assert fr.exposure_time == pytest.approx(1 / 125) and fr.shape == (32, 32)
    assert Path(r["dng"]).read_bytes() == (vdir / "frame.dng").read_bytes()


def test_long_exposure_uses_trigger_and_events(tmp_path):
    r = run_vcam(tmp_path, """
        cam = Gphoto2Camera(long_exposure_s=0.5)
        cam.set_exposure(1.0)
        res = cam.capture(OUT / "long.dng")
        RESULT["events"] = cam.events
        RESULT["file"] = res.camera_file
        RESULT["exists"] = res.path.exists()
        cam.close()
    """)
    kinds = [k for k, _v in r["events"]]
    assert "file_added" in kinds and r["exists"]
    assert dict(r["events"])["file_added"] == r["file"]


def test_store_full_stops_with_a_clear_message(tmp_path):
    r = run_vcam(tmp_path, """
        cam = Gphoto2Camera(pair_wait_s=0)
        cam.set_exposure(0.01)
        n = 0
        try:
            for i in range(30):
                cam.capture(OUT / f"f{i}.dng")
                n += 1
        except StorageFullError as e:
            RESULT["error"] = str(e); RESULT["kind"] = fault_kind(e)
        RESULT["n"] = n
        cam.close()
    """)
    assert r["n"] == 26  # the virtual camera's store holds 26 captures
    assert r["kind"] == "fatal" and "storage is full" in r["error"]


def test_busy_is_retried_and_two_threads_are_serialised(tmp_path):
    r = run_vcam(tmp_path, """
        cam = Gphoto2Camera(backoff_s=0.01, busy_retries=3)
        cam._inject = [-110, -110]
        RESULT["t"] = cam.set_exposure(0.01)
        RESULT["busy"] = cam.busy_count
        cam._inject = [-110] * 5
        try:
            cam.set_exposure(0.01)
        except CameraBusyError as e:
            RESULT["gave_up"] = fault_kind(e)
        cam._inject = []
        paths, errors = [], []
        def shoot(k):
            try:
                for j in range(3):
                    paths.append(str(cam.capture(OUT / f"t{k}_{j}.dng").path))
            except Exception as e:
                errors.append(repr(e))
        th = [threading.Thread(target=shoot, args=(k,)) for k in range(2)]
        [t.start() for t in th]; [t.join() for t in th]
        RESULT["paths"] = paths; RESULT["errors"] = errors
        RESULT["files"] = sorted(set(cam.list_files()))
        cam.close()
    """)
    assert r["t"] == pytest.approx(0.01) and r["busy"] == 2
    assert r["gave_up"] == "busy"
    assert r["errors"] == [] and len(set(r["paths"])) == 6
    assert all(Path(p).stat().st_size > 0 for p in r["paths"])


def test_reconnect_builds_a_new_camera_object(tmp_path):
    r = run_vcam(tmp_path, """
        cam = Gphoto2Camera()
        cam.set_exposure(0.05)
        first = id(cam._cam)
        cam.capture(OUT / "a.dng")
        cam._inject = [-53]   # GP_ERROR_IO_USB_CLAIM: another process holds the device
        try:
            cam.capture(OUT / "b.dng")
        except CameraDisconnectedError as e:
            RESULT["kind"] = fault_kind(e)
        try:   # a call that hangs: the caller gets a timeout, not a hung program
            cam._run(lambda: time.sleep(1.0), "hang test", timeout=0.2)
        except Exception as e:
            RESULT["hang"] = [type(e).__name__, fault_kind(e)]
        cam.reconnect()
        RESULT["new_object"] = id(cam._cam) != first
        RESULT["t_after"] = cam.applied["shutterspeed"]
        RESULT["ok"] = cam.capture(OUT / "c.dng").path.exists()
        RESULT["reconnects"] = cam.reconnects
        RESULT["events"] = cam.events
        cam.close()
    """)
    assert r["kind"] == "reconnect" and r["new_object"] and r["ok"] and r["reconnects"] == 1
    assert r["t_after"] == "0.0500s"  # settings re-applied on the new connection
    assert ["port_reset", "usb:001,001"] in r["events"]
    assert r["hang"] == ["CameraTimeoutError", "reconnect"]


@pytest.mark.parametrize("shade, dark", [(0, True), (200, False)])
def test_cover_detection(tmp_path, shade, dark):
    r = run_vcam(tmp_path, """
        cam = Gphoto2Camera()
        cam.set_exposure(0.01)
        RESULT["dark"] = frame_is_dark(cam.capture(OUT / "x.dng").path)
        cam.close()
    """, _vcam_dir(tmp_path, shade))
    assert r["dark"] is dark


def test_job_check_against_the_virtual_camera(tmp_path, cli):
    vdir = _vcam_dir(tmp_path)
    job = tmp_path / "job.toml"
    text = (
        '[camera]\nbackend = "gphoto2"\nmodel = "D750"\n\n'
        '[exposure]\ntimes = [0.01, 0.1, 1.0]\n\n'
        '[darks]\nstrategy = "matched"\nblock_light = "command"\ncover_command = "true"\nuncover_command = "true"\n\n'
        '[calibration]\npreset = "camera-B"\n\n[output]\nfolder = "runs/x"\n'
    )
    env = {"VCAMERADIR": str(vdir), "XDG_CONFIG_HOME": str(tmp_path / "xdg")}
    job.write_text(text)
    ok = cli("run", job, "--check", env=env)
    assert ok.returncode == 0 and "ok" in ok.stdout, ok.stderr
    job.write_text(text.replace("1.0]", "1.0, 30.0]"))
    bad = cli("run", job, "--check", env=env)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr
    assert f"{job}:6: exposure.times: exposure 30 s is outside the camera's range 0.0001 .. 1 s" in bad.stderr
    job.write_text(text.replace('model = "D750"', 'model = "EOS R5"'))
    gone = cli("run", job, "--check", env=env)
    assert gone.returncode != 0 and "no camera model 'EOS R5'" in gone.stderr and "Traceback" not in gone.stderr


def test_session_on_the_virtual_camera_refuses_jpeg(tmp_path, cli):
    """The whole chain (job -> Gphoto2Camera -> session) on the virtual camera, which only
    delivers JPEG: the session stops at once with a clear message instead of merging JPEGs."""
    from hdrcap.acquire.cliutil import resolve_calibration
    from hdrcap.pipeline.calibration import save_calibration

    # a calibration of this camera (the compatibility check refuses a simulator preset's)
    cal = resolve_calibration(None, "camera-B")
    save_calibration(tmp_path / "cal.json", cal.replace(provenance={"camera": "NIKON CORPORATION NIKON D750"}))
    job = tmp_path / "job.toml"
    job.write_text('[camera]\nbackend = "gphoto2"\n\n[exposure]\ntimes = [0.01]\n\n'
                   '[darks]\nstrategy = "model"\nblock_light = "none"\n\n'
                   '[calibration]\nfile = "cal.json"\n\n[output]\nfolder = "runs/x"\n')
    env = {"VCAMERADIR": str(_vcam_dir(tmp_path)), "XDG_CONFIG_HOME": str(tmp_path / "xdg"),
           "HDRCAP_LOCK_DIR": str(tmp_path / "locks")}
    proc = cli("run", job, "--no-progress", env=env)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr  # a configuration error
    assert "delivers .jpg files, not raw" in proc.stderr and "imageformat" in proc.stderr
    events = [json.loads(l) for l in (tmp_path / "runs" / "x" / "events.jsonl").read_text().splitlines()]
    assert events[0]["camera"]["model"] == "Nikon DSC D750" and events[-1]["event"] == "stop"
