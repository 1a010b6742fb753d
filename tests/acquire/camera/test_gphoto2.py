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

from tests.helpers.fake_gphoto2 import FakeBody
from tests.helpers.fake_gphoto2 import fake_camera as _fake_camera

REPO = Path(__file__).resolve().parents[3]
pytestmark = pytest.mark.gphoto2

PRELUDE = """
import json, os, sys, threading, time
from pathlib import Path
sys.path.insert(0, {repo!r})
from hdrcap.acquire.camera.gphoto2 import Gphoto2Camera, list_cameras
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
        write_dng(
            f,
            data,
            exposure_time=t,
            iso=200,
            black_level=32,
            white_level=1023,
            cfa="RGGB",
            make="hdrcap",
            model="vcam test",
            serial="7",
            timestamp=datetime.datetime(2026, 1, 1),
            description="",
        )


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
    r = run_vcam(
        tmp_path,
        """
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
    """,
    )
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
    r = run_vcam(
        tmp_path,
        """
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
    """,
        vdir,
    )
    got = Path(r["path"])
    assert got.suffix == ".jpg"  # the suffix is the camera file's
    assert got.read_bytes() == (vdir / "scene.jpg").read_bytes()  # the virtual camera returns its .jpg
    assert r["applied"] == pytest.approx(0.01)
    assert r["camera_file"] not in r["after"] and r["kept"]
    from hdrcap.pipeline.io.raw import read_frame

    fr = read_frame(r["dng"])
    assert fr.exposure_time == pytest.approx(1 / 125) and fr.shape == (32, 32)
    assert Path(r["dng"]).read_bytes() == (vdir / "frame.dng").read_bytes()


def test_long_exposure_uses_trigger_and_events(tmp_path):
    r = run_vcam(
        tmp_path,
        """
        cam = Gphoto2Camera(long_exposure_s=0.5)
        cam.set_exposure(1.0)
        res = cam.capture(OUT / "long.dng")
        RESULT["events"] = cam.events
        RESULT["file"] = res.camera_file
        RESULT["exists"] = res.path.exists()
        cam.close()
    """,
    )
    kinds = [k for k, _v in r["events"]]
    assert "file_added" in kinds and r["exists"]
    assert dict(r["events"])["file_added"] == r["file"]


def test_store_full_stops_with_a_clear_message(tmp_path):
    r = run_vcam(
        tmp_path,
        """
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
    """,
    )
    assert r["n"] == 26  # the virtual camera's store holds 26 captures
    assert r["kind"] == "fatal" and "storage is full" in r["error"]


def test_busy_is_retried_and_two_threads_are_serialised(tmp_path):
    r = run_vcam(
        tmp_path,
        """
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
    """,
    )
    assert r["t"] == pytest.approx(0.01) and r["busy"] == 2
    assert r["gave_up"] == "busy"
    assert r["errors"] == [] and len(set(r["paths"])) == 6
    assert all(Path(p).stat().st_size > 0 for p in r["paths"])


def test_reconnect_builds_a_new_worker_and_reapplies_settings(tmp_path):
    r = run_vcam(
        tmp_path,
        """
        cam = Gphoto2Camera()
        cam.set_exposure(0.05)
        first = cam.worker_pid
        cam.capture(OUT / "a.dng")
        cam._inject = [-53]   # GP_ERROR_IO_USB_CLAIM: another process holds the device
        try:
            cam.capture(OUT / "b.dng")
        except CameraDisconnectedError as e:
            RESULT["kind"] = fault_kind(e)
        cam.reconnect()
        RESULT["new_worker"] = cam.worker_pid != first
        RESULT["t_after"] = cam.applied["shutterspeed"]
        RESULT["ok"] = cam.capture(OUT / "c.dng").path.exists()
        RESULT["reconnects"] = cam.reconnects
        RESULT["events"] = cam.events
        cam.close()
    """,
    )
    assert r["kind"] == "reconnect" and r["new_worker"] and r["ok"] and r["reconnects"] == 1
    assert r["t_after"] == "0.0500s"  # settings re-applied on the new connection
    assert ["port_reset", "usb:001,001"] in r["events"]


def test_a_hung_call_kills_the_worker_and_reconnect_starts_a_new_one(tmp_path):
    """A call that never answers (a USB transfer stuck in the kernel does not cooperate with
    any timeout): the worker process that holds the device is killed, not abandoned."""
    r = run_vcam(
        tmp_path,
        """
        cam = Gphoto2Camera(reconnect_backoff_s=0.05)
        cam.set_exposure(0.01)
        pid = cam.worker_pid
        t0 = time.monotonic()
        try:
            cam._call("sleep", 30.0, timeout=0.3)
        except Exception as e:
            RESULT["hang"] = [type(e).__name__, fault_kind(e)]
        RESULT["hang_s"] = time.monotonic() - t0
        try:
            os.kill(pid, 0); RESULT["old_alive"] = True
        except ProcessLookupError:
            RESULT["old_alive"] = False
        try:
            cam.set_exposure(0.02)
        except Exception as e:
            RESULT["before_reconnect"] = [type(e).__name__, fault_kind(e)]
        cam.reconnect()
        RESULT["new_pid"] = cam.worker_pid not in (None, pid)
        RESULT["ok"] = cam.capture(OUT / "c.dng").path.exists()
        cam.close()
    """,
    )
    assert r["hang"] == ["CameraTimeoutError", "reconnect"] and r["hang_s"] < 5
    assert r["old_alive"] is False  # the USB claim went with the process
    assert r["before_reconnect"] == ["CameraDisconnectedError", "reconnect"]  # not AttributeError
    assert r["new_pid"] and r["ok"]


def test_failed_reconnect_leaves_a_disconnected_camera_not_an_empty_one(tmp_path):
    r = run_vcam(
        tmp_path,
        """
        cam = Gphoto2Camera(reconnect_deadline_s=3.0, reconnect_backoff_s=0.05)
        cam.set_exposure(0.01)
        cam._inject = [("open", -53)] * 100   # gvfs holds the camera for longer than the deadline
        t0 = time.monotonic()
        try:
            cam.reconnect()
        except Exception as e:
            RESULT["reconnect"] = [type(e).__name__, fault_kind(e)]
        RESULT["polled_s"] = time.monotonic() - t0
        try:
            cam.set_exposure(0.02)
        except Exception as e:
            RESULT["next_call"] = [type(e).__name__, fault_kind(e)]
        RESULT["attempts"] = cam.reconnect_attempts
        cam._inject = [("open", -53)] * 2     # ... and lets it go after two more tries
        cam.reconnect_deadline_s = 30.0
        cam.reconnect()
        RESULT["attempts_after"] = cam.reconnect_attempts
        RESULT["ok"] = cam.capture(OUT / "c.dng").path.exists()
        RESULT["t"] = cam.applied["shutterspeed"]
        cam.close()
    """,
    )
    assert r["reconnect"] == ["CameraDisconnectedError", "reconnect"]
    assert r["next_call"] == ["CameraDisconnectedError", "reconnect"]
    assert r["attempts"] >= 2 and r["polled_s"] >= 2.5  # polled with backoff until the deadline, not tried once
    assert r["attempts_after"] - r["attempts"] == 3 and r["ok"] and r["t"] == "0.0100s"


def test_reconnect_finds_the_camera_by_serial_on_a_new_port(tmp_path):
    r = run_vcam(
        tmp_path,
        """
        import dataclasses
        cam = Gphoto2Camera(serial="0.1")   # what the virtual camera reports
        RESULT["serial"] = cam.identity.serial
        cam.identity = dataclasses.replace(cam.identity, port="usb:003,017")   # where it was before a re-plug
        cam.reconnect()
        RESULT["port"] = cam.identity.port
        RESULT["events"] = cam.events
        RESULT["ok"] = cam.capture(OUT / "c.dng").path.exists()
        cam.close()
        try:
            Gphoto2Camera(serial="0815")
        except CameraGoneError as e:
            RESULT["other"] = str(e)
        RESULT["cameras"] = list_cameras(serials=True)
    """,
    )
    assert r["serial"] == "0.1" and r["port"] == "usb:001,001" and r["ok"]
    assert ["port_changed", "usb:003,017 -> usb:001,001"] in r["events"]
    assert "serial '0815'" in r["other"] and "serial 0.1" in r["other"]
    assert r["cameras"] == [["Nikon DSC D750", "usb:001,001", "0.1"]]


def test_a_failed_constructor_releases_the_camera(tmp_path):
    r = run_vcam(
        tmp_path,
        """
        from hdrcap.acquire.camera import gphoto2 as g
        made = []
        class Spy(g._Worker):
            def __init__(self, *a, **k):
                super().__init__(*a, **k); made.append(self)
        g.Gphoto2Camera.worker_factory = Spy
        try:
            Gphoto2Camera(settings={"aperture": "f/5.6", "no-such-setting": 1})
        except Exception as e:
            RESULT["error"] = [type(e).__name__, str(e)]
        RESULT["ended"] = [w.proc.poll() is not None for w in made]
        cam = Gphoto2Camera()   # the device is free again
        RESULT["ok"] = cam.capture(OUT / "c.dng").path.exists()
        cam.close()
        RESULT["closed"] = made[-1].proc.poll() is not None
    """,
    )
    assert r["error"][0] == "InputError" and "no-such-setting" in r["error"][1]
    assert r["ended"] and all(r["ended"]) and r["ok"] and r["closed"]


@pytest.mark.parametrize("shade, dark", [(0, True), (200, False)])
def test_cover_detection(tmp_path, shade, dark):
    r = run_vcam(
        tmp_path,
        """
        cam = Gphoto2Camera()
        cam.set_exposure(0.01)
        RESULT["dark"] = frame_is_dark(cam.capture(OUT / "x.dng").path)
        cam.close()
    """,
        _vcam_dir(tmp_path, shade),
    )
    assert r["dark"] is dark


def test_job_check_against_the_virtual_camera(tmp_path, cli):
    vdir = _vcam_dir(tmp_path)
    job = tmp_path / "job.toml"
    text = (
        '[camera]\nbackend = "gphoto2"\nmodel = "D750"\nsettings = { autofocus = "Off" }\n\n'
        "[exposure]\ntimes = [0.01, 0.1, 1.0]\n\n"
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
    assert f"{job}:7: exposure.times: exposure 30 s is outside the camera's range 0.0001 .. 1 s" in bad.stderr
    job.write_text(text.replace('model = "D750"', 'model = "EOS R5"'))
    gone = cli("run", job, "--check", env=env)
    assert gone.returncode != 0 and "no camera model 'EOS R5'" in gone.stderr and "Traceback" not in gone.stderr


def test_session_on_the_virtual_camera_refuses_jpeg(tmp_path, cli):
    """The whole chain (job -> Gphoto2Camera -> session) on the virtual camera, which only
    delivers JPEG: the session stops at once with a clear message instead of merging JPEGs."""
    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.pipeline.calibration import save_calibration

    # a calibration of this camera (the compatibility check refuses a simulator preset's)
    cal = camera_model(camera="camera-B")
    save_calibration(tmp_path / "cal.json", cal.replace(provenance={"camera": "NIKON CORPORATION NIKON D750"}))
    job = tmp_path / "job.toml"
    job.write_text(
        '[camera]\nbackend = "gphoto2"\nenforce = true\n\n[exposure]\ntimes = [0.01]\n\n'
        '[darks]\nstrategy = "model"\nblock_light = "none"\n\n'
        '[calibration]\nfile = "cal.json"\n\n[output]\nfolder = "runs/x"\n'
    )
    env = {
        "VCAMERADIR": str(_vcam_dir(tmp_path)),
        "XDG_CONFIG_HOME": str(tmp_path / "xdg"),
        "HDRCAP_LOCK_DIR": str(tmp_path / "locks"),
    }
    proc = cli("run", job, "--no-progress", env=env)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr  # a configuration error
    assert "delivers .jpg files, not raw" in proc.stderr and "imageformat" in proc.stderr
    events = [json.loads(l) for l in (tmp_path / "runs" / "x" / "events.jsonl").read_text().splitlines()]
    assert events[0]["camera"]["model"] == "Nikon DSC D750" and events[-1]["event"] == "stop"


def test_cameras_command_shows_serials_and_a_job_selects_by_serial(tmp_path, cli):
    env = {"VCAMERADIR": str(_vcam_dir(tmp_path)), "XDG_CONFIG_HOME": str(tmp_path / "xdg")}
    listed = cli("cameras", "--json", env=env)
    assert listed.returncode == 0, listed.stderr
    assert json.loads(listed.stdout)["gphoto2"] == [{"model": "Nikon DSC D750", "port": "usb:001,001", "serial": "0.1"}]
    text = cli("cameras", env=env)
    assert "usb:001,001" in text.stdout and "serial 0.1" in text.stdout
    job = tmp_path / "job.toml"
    body = (
        '[exposure]\ntimes = [0.01]\n\n[darks]\nstrategy = "model"\nblock_light = "none"\n\n'
        '[calibration]\npreset = "camera-B"\n\n[output]\nfolder = "runs/x"\n'
    )
    job.write_text('[camera]\nbackend = "gphoto2"\nserial = "0.1"\nsettings = { autofocus = "Off" }\n\n' + body)
    ok = cli("run", job, "--check", env=env)
    assert ok.returncode == 0, ok.stderr
    job.write_text('[camera]\nbackend = "gphoto2"\nserial = "X42"\n\n' + body)
    other = cli("run", job, "--check", env=env)
    assert other.returncode != 0 and "no camera serial 'X42'" in other.stderr and "Traceback" not in other.stderr


def test_a_late_raw_partner_never_becomes_the_next_frames_file(tmp_path):
    """The RAW of a RAW+JPEG pair comes 4 event waits after the JPEG (longer than pair_wait):
    each frame still gets its own RAW, and the late one is never taken for the next frame."""
    body = FakeBody(raw_delay=4)
    cam = _fake_camera(body, pair_wait_s=0.05, long_exposure_s=0.5)
    got = []
    for k, t in enumerate([0.01, 0.01, 1.0, 1.0]):  # capture() path, then the trigger path
        cam.set_exposure(t)
        got.append(Path(cam.capture(tmp_path / f"f{k}.nef").path).read_text())
    assert got == ["DSC_0001.NEF", "DSC_0002.NEF", "DSC_0003.NEF", "DSC_0004.NEF"]


def test_stale_files_are_drained_before_the_release(tmp_path):
    body = FakeBody(fmt="RAW")
    cam = _fake_camera(body, pair_wait_s=0.0, long_exposure_s=0.5)
    body._shoot(announce_jpeg=False)  # a file announced before this capture (a stray release)
    cam.set_exposure(1.0)
    res = cam.capture(tmp_path / "a.nef")
    assert Path(res.path).read_text() == "DSC_0002.NEF" and res.camera_file.endswith("DSC_0002.NEF")
    assert ("stale_file", "/store/DCIM/DSC_0001.NEF") in cam.events


@pytest.mark.parametrize(
    "storages, full",
    [
        ([{"freeimages": 0, "access": "rw"}], True),
        ([{"freekbytes": 0, "access": "rw"}], False),  # no valid image count: unknown, not full
        ([{"access": "rw"}], False),  # nothing valid at all
        ([{"freeimages": 0, "access": "rw"}, {"freeimages": 12, "access": "rw"}], False),  # second card
        ([{"freeimages": 0, "access": "rw"}, {"freeimages": 50, "access": "ro"}], True),  # read-only card
    ],
)
def test_storage_full_only_from_valid_fields_of_every_storage(tmp_path, storages, full):
    from hdrcap.acquire.camera import StorageFullError

    cam = _fake_camera(FakeBody(fmt="RAW", storages=storages), pair_wait_s=0.0)
    cam.set_exposure(0.01)
    if full:
        with pytest.raises(StorageFullError):
            cam.capture(tmp_path / "a.nef")
    else:
        assert cam.capture(tmp_path / "a.nef").path.exists()


def test_worker_reads_only_the_storage_fields_marked_valid():
    """libgphoto2 leaves ``freeimages`` at 0 when the camera does not report it (its bit in
    ``fields`` is clear): that must not read as a full card."""
    import types

    gp = pytest.importorskip("gphoto2")
    from hdrcap.acquire.camera.gphoto2 import _WorkerState, free_images

    def info(fields, **kw):
        base = dict(
            basedir="/store_1", freeimages=0, freekbytes=0, access=gp.GP_STORAGEINFO_AC_READWRITE, description="SD"
        )
        return types.SimpleNamespace(fields=fields, **{**base, **kw})

    st = _WorkerState.__new__(_WorkerState)
    st.gp = gp
    bits = gp.GP_STORAGEINFO_ACCESS | gp.GP_STORAGEINFO_FREESPACEKBYTES
    st.cam = types.SimpleNamespace(get_storageinfo=lambda: [info(bits, freekbytes=900000)])
    assert st.op_storage() == [{"base": "/store_1", "freekbytes": 900000, "access": "rw"}]
    assert free_images(st.op_storage()) is None
    st.cam = types.SimpleNamespace(
        get_storageinfo=lambda: [
            info(bits | gp.GP_STORAGEINFO_FREESPACEIMAGES, freeimages=0),
            info(gp.GP_STORAGEINFO_FREESPACEIMAGES, freeimages=40, basedir="/store_2"),
        ]
    )
    assert free_images(st.op_storage()) == 40  # the second storage still has room


def test_no_full_config_tree_read_per_frame(tmp_path):
    """The configuration tree is read once per connection; a frame writes and reads back one
    widget (the shutter speed). The code this replaced read the whole tree five times a frame."""
    r = run_vcam(
        tmp_path,
        """
        cam = Gphoto2Camera(pair_wait_s=0)
        cam.set_exposure(0.01)
        before = cam.tree_reads()
        for i in range(4):
            RESULT.setdefault("t", []).append(cam.set_exposure([0.02, 0.05][i % 2]))
            cam.capture(OUT / f"f{i}.jpg")
        after = cam.tree_reads()
        RESULT["per_frame"] = {k: (after[k] - before[k]) / 4 for k in after}
        RESULT["label"] = cam.get_setting("shutterspeed", fresh=True)
        cam.close()
    """,
    )
    assert r["per_frame"] == {"tree": 0, "single": 1, "set": 1}
    assert r["t"] == [0.02, 0.05, 0.02, 0.05] and r["label"] == "0.0500s"


@pytest.mark.parametrize("canon", [False, True])
def test_bulb_is_one_press_sleep_release_and_records_the_measured_open_time(tmp_path, canon):
    from hdrcap.acquire.camera import exposure_ladder

    body = FakeBody(fmt="RAW", canon=canon)
    cam = _fake_camera(body, pair_wait_s=0.0)
    assert cam.bulb_range() == (pytest.approx(36.0), 3600.0)
    ladder = exposure_ladder(cam)
    assert ladder[:4] == [0.01, 0.1, 1.0, 30.0] and ladder[4:7] == [37.8, 47.6, 60.0] and max(ladder) <= 3600
    assert cam.set_exposure(60.0) == 60.0 and cam.applied["shutterspeed"] == "Bulb"
    body.log.clear()
    res = cam.capture(tmp_path / "b.nef")
    name, press, release = ("eosremoterelease", "Press Full", "Release Full") if canon else ("bulb", 1, 0)
    bulb_calls = [x for x in body.log if isinstance(x, tuple)]
    assert bulb_calls == [("bulb", name, press, release)]
    # nothing but the one worker request between press and release
    assert body.log[body.log.index("bulb") + 1] == bulb_calls[0]
    assert res.bulb and res.applied_exposure_s == pytest.approx(60.0 - 0.006)  # release start - press end
    assert res.requested_exposure_s == 60.0 and res.settings["bulb_open_s"] == "59.9940"
    cam.set_exposure(1.0)
    assert not cam.capture(tmp_path / "t.nef").bulb


def test_no_bulb_without_a_bulb_speed(tmp_path):
    from hdrcap.acquire.camera import exposure_ladder

    body = FakeBody(fmt="RAW")
    body.widgets["shutterspeed"] = ("radio", "1/100", ["1/100", "1", "30"])
    cam = _fake_camera(body)
    assert cam.bulb_range() is None and exposure_ladder(cam) == [0.01, 1.0, 30.0]
    assert cam.set_exposure(60.0) == 30.0


def _canon_like_body(dial_readonly=False):
    body = FakeBody(fmt="Large Fine JPEG", canon=True)
    body.widgets.update(
        {
            "imageformat": ("radio", "Large Fine JPEG", ["Large Fine JPEG", "RAW + Large Fine JPEG", "RAW"]),
            "autoexposuremode": ("radio", "AV", ["P", "TV", "AV", "Manual", "Bulb"]),
            "focusmode": ("radio", "One Shot", ["One Shot", "AI Servo", "Manual"]),
            "iso": ("radio", "Auto", ["Auto", "100", "200", "400", "800"]),
            "longexpnr": ("radio", "On", ["Off", "Auto", "On"]),
        }
    )
    del body.widgets["imagequality"]
    if dial_readonly:
        real = body.op_describe
        body.op_describe = lambda names: (lambda d: d and dict(d, readonly=d["name"] == "autoexposuremode"))(
            real(names)
        )
    return body


def test_preflight_reports_every_wrong_setting_and_changes_nothing(tmp_path):
    from hdrcap.pipeline.errors import InputError

    body = _canon_like_body()
    cam = _fake_camera(body)
    before = {k: v[1] for k, v in body.widgets.items()}
    with pytest.raises(InputError) as e:
        cam.preflight()
    msg = str(e.value)
    assert "\n" not in msg and "enforce = true" in msg
    for words in (
        "autoexposuremode is 'AV'",
        "focusmode is 'One Shot'",
        "imageformat is 'Large Fine JPEG'",
        "iso is 'Auto'",
        "longexpnr is 'On'",
    ):
        assert words in msg
    assert {k: v[1] for k, v in body.widgets.items()} == before  # nothing changed


def test_preflight_enforce_sets_allowed_values_and_the_jobs_iso(tmp_path):
    from hdrcap.pipeline.errors import InputError

    body = _canon_like_body()
    cam = _fake_camera(body)
    found = {f["setting"]: f for f in cam.preflight(enforce=True, iso=400)}
    assert {k: f["changed"] for k, f in found.items()} == {
        "exposureprogram": "Manual",
        "focusmode": "Manual",
        "imageformat": "RAW + Large Fine JPEG",
        "iso": "400",
        "longexposurenr": "Off",
    }
    assert all(f["ok"] for f in found.values())
    assert all(f["changed"] is None for f in cam.preflight())  # a second check finds nothing to do
    dial = _fake_camera(_canon_like_body(dial_readonly=True))
    with pytest.raises(InputError, match="autoexposuremode is 'AV', needs manual"):
        dial.preflight(enforce=True)  # a mode dial cannot be turned over USB


def test_preflight_on_the_virtual_camera(tmp_path, cli):
    vdir = _vcam_dir(tmp_path)
    env = {"VCAMERADIR": str(vdir), "XDG_CONFIG_HOME": str(tmp_path / "xdg")}
    job = tmp_path / "job.toml"
    body = (
        '\n[exposure]\ntimes = [0.01]\n\n[darks]\nstrategy = "model"\nblock_light = "none"\n\n'
        '[calibration]\npreset = "camera-B"\n\n[output]\nfolder = "runs/x"\n'
    )
    job.write_text('[camera]\nbackend = "gphoto2"\n' + body)
    refused = cli("run", job, "--check", env=env)
    assert refused.returncode != 0 and "Traceback" not in refused.stderr
    assert "autofocus is 'On', needs manual focus" in refused.stderr
    job.write_text('[camera]\nbackend = "gphoto2"\nenforce = true\n' + body)
    ok = cli("run", job, "--check", env=env)
    assert ok.returncode == 0, ok.stderr


def test_capture_command_sets_iso_and_enforces_on_the_virtual_camera(tmp_path, cli):
    """`hdrcap capture --enforce` switches autofocus off on the virtual camera (which has no
    ISO setting: --iso is refused there with the camera's own words)."""
    env = {
        "VCAMERADIR": str(_vcam_dir(tmp_path)),
        "XDG_CONFIG_HOME": str(tmp_path / "xdg"),
        "HDRCAP_LOCK_DIR": str(tmp_path / "locks"),
    }
    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.pipeline.calibration.archive import save_calibration

    # a calibration of this camera (the compatibility check refuses a simulator preset's)
    calib = save_calibration(
        tmp_path / "calib.npz",
        camera_model(camera="camera-B").replace(provenance={"camera": "NIKON CORPORATION NIKON D750"}),
    )
    base = [
        "capture",
        "--camera",
        "gphoto2",
        "--times",
        "0.01",
        "--darks",
        "model",
        "--block-light",
        "none",
        "--calibration",
        calib,
        "--out",
        tmp_path / "run",
        "--no-progress",
    ]
    refused = cli(*base, env=env)
    assert refused.returncode != 0 and "autofocus is 'On'" in refused.stderr and "Traceback" not in refused.stderr
    enforced = cli(*base, "--enforce", env=env)
    assert "autofocus" not in enforced.stderr and "delivers .jpg files, not raw" in enforced.stderr
    iso = cli(*base, "--enforce", "--iso", "400", env=env)
    assert iso.returncode != 0 and "has no setting 'iso'" in iso.stderr and "Traceback" not in iso.stderr


def test_gphoto2_success_path_raw_frames_through_the_virtual_camera(tmp_path):
    """Raw file -> verification -> manifest -> merge, every camera call through libgphoto2.

    The virtual camera returns, for every capture, the bytes of the first ``.jpg`` in
    VCAMERADIR under the name ``GPH_nnnn.JPG``, and reads them when the file is downloaded
    (with the size the file had at ``init``). So the test keeps a DNG of the simulated sensor
    there, rewritten before each release with the frame's exposure (same size every time), and
    renames each download to ``.dng``: the only step that is not the real path."""
    from hdrcap.mock_camera.dng import write_dng

    vdir = tmp_path / "vcamera"
    vdir.mkdir()
    # a placeholder DNG of the final size, so init records the size the frames will have
    placeholder = np.zeros((32, 48), np.uint16)
    with open(vdir / "scene.jpg", "wb") as f:
        import datetime

        write_dng(
            f,
            placeholder,
            exposure_time=0.01,
            iso=200,
            black_level=32,
            white_level=4095,
            cfa="RGGB",
            make="hdrcap",
            model="sim",
            serial="1",
            timestamp=datetime.datetime(2026, 1, 1),
            description="x",
        )
    r = run_vcam(
        tmp_path,
        """
        import datetime, dataclasses
        import numpy as np
        from hdrcap.mock_camera.backend import SimulatedCamera
        from hdrcap.mock_camera.dng import write_dng
        from hdrcap.mock_camera.scenes import make_scene
        from hdrcap.mock_camera.sensor import PRESETS
        from hdrcap.acquire.capture.session import CapturePlan, CaptureSession, LightBlocker, RetryPolicy
        from hdrcap.acquire.capture.manifest import Manifest
        from hdrcap.acquire.camera.model import camera_model
        VDIR = Path(os.environ["VCAMERADIR"])
        spec = PRESETS["camera-B"]
        sim = SimulatedCamera(spec, make_scene("hdr", (32, 48), decades=2.0, x_max=3e4), seed=4)
        size = (VDIR / "scene.jpg").stat().st_size

        class RawThroughVcam:
            def __init__(self, cam):
                self.cam, self.identity = cam, cam.identity
            def __getattr__(self, name):
                return getattr(self.cam, name)
            def capture(self, dest, *, dark=False, timeout=None):
                t = self.cam._t
                mosaic = sim.capture_array(t, dark=dark)
                tmp = VDIR / ".next"
                with open(tmp, "wb") as f:
                    write_dng(f, mosaic, exposure_time=t, iso=spec.iso, black_level=spec.mu_R,
                              white_level=spec.white_level, cfa=spec.cfa, make="hdrcap", model="sim", serial="1",
                              timestamp=datetime.datetime(2026, 1, 1), description="x")
                assert tmp.stat().st_size == size
                os.replace(tmp, VDIR / "scene.jpg")
                res = self.cam.capture(dest, dark=dark, timeout=timeout)
                raw = Path(res.path).with_suffix(".dng")
                os.replace(res.path, raw)
                return dataclasses.replace(res, path=raw)

        cam = Gphoto2Camera(pair_wait_s=0)
        plan = CapturePlan.bracket([0.0025, 0.01, 0.05], cam.allowed_exposure_times(), "matched")
        cal = camera_model(camera="camera-B")
        res = CaptureSession(RawThroughVcam(cam), OUT / "run", plan, calibration=cal,
                             light=LightBlocker("command", "true", "true"),
                             retry=RetryPolicy(max_attempts=3, backoff_s=0.01, max_backoff_s=0.02, timeout_s=20),
                             progress=False).run()
        frames = Manifest(OUT / "run").frames()
        RESULT["captured"] = res.captured
        RESULT["frames"] = {k: [r["camera_file"], r["file_exposure_s"], r["applied_exposure_s"]]
                            for k, r in frames.items()}
        m = res.merge
        ok = m.nexp > 0
        z = (m.irradiance[ok] - sim.scene[ok]) / m.sigma[ok]
        RESULT["z_median"] = float(np.median(z))
        RESULT["z_spread"] = float(1.4826 * np.median(np.abs(z - np.median(z))))
        RESULT["covered"] = float(ok.mean())
        cam.close()
    """,
        vdir,
    )
    assert r["captured"] == 6 and len(r["frames"]) == 6
    for cam_file, file_t, applied in r["frames"].values():
        assert cam_file.startswith("/store_00010001/DCIM/") and cam_file.endswith(".JPG")
        assert file_t == pytest.approx(applied, rel=1e-3)
    assert sorted({round(v[1], 4) for v in r["frames"].values()}) == [0.0025, 0.01, 0.05]
    # the merge of what came through libgphoto2 agrees with the simulator's truth
    assert r["covered"] > 0.9 and abs(r["z_median"]) < 0.3 and 0.7 < r["z_spread"] < 1.4
