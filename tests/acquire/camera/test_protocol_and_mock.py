"""Camera protocol: exposure labels, nearest allowed time, fault kinds; MockCamera faults."""

from __future__ import annotations

import numpy as np
import pytest

from hdrcap.acquire.camera import (
    Camera,
    CameraBusyError,
    StorageFullError,
    fault_kind,
    format_exposure,
    nearest_allowed,
    parse_exposure_label,
)
from hdrcap.acquire.camera.mock import MockCamera, MockFaults


@pytest.mark.parametrize(
    "label, seconds",
    [
        ("1/250", 0.004),
        ("1/250s", 0.004),
        ("1/4000 s", 0.00025),
        ("0.1000s", 0.1),
        ("0.0012s", 0.0012),
        ("30", 30.0),
        ("30s", 30.0),
        ('30"', 30.0),
        ('0"3', 0.3),
        ('1"6', 1.6),
        ("2.5", 2.5),
        ("1/3", 1 / 3),
        (0.5, 0.5),
    ],
)
def test_parse_exposure_label(label, seconds):
    assert parse_exposure_label(label) == pytest.approx(seconds, rel=1e-12)


@pytest.mark.parametrize("label", ["bulb", "Bulb", "BULB", "time", "auto"])
def test_bulb_is_not_a_time(label):
    assert parse_exposure_label(label) is None


@pytest.mark.parametrize("label", ["", "fast", "1/0", "-1/250", "0", "1/250x", "f/2.8"])
def test_bad_labels_raise(label):
    with pytest.raises(ValueError):
        parse_exposure_label(label)


def test_format_and_nearest():
    assert format_exposure(0.004) == "1/250 s"
    assert format_exposure(2.5) == "2.5 s"
    allowed = [1 / 250, 1 / 125, 1 / 60, 1 / 30]
    assert nearest_allowed(0.0105, allowed) == 1 / 125  # log-nearest: 0.0105 is closer to 1/125 than 1/60
    assert nearest_allowed(1.0, allowed) == 1 / 30
    assert nearest_allowed(1e-6, allowed) == 1 / 250


def test_fault_kinds():
    assert fault_kind(CameraBusyError("x")) == "busy"
    assert fault_kind(StorageFullError("x")) == "fatal"
    assert fault_kind(ValueError("x")) is None


def _scene(shape=(24, 24)):
    return np.full(shape, 1000.0)


def test_mock_camera_protocol_and_coercion(tmp_path):
    cam = MockCamera("camera-B", _scene(), seed=1)
    assert isinstance(cam, Camera)
    times = cam.allowed_exposure_times()
    assert times == sorted(times) and times[0] == pytest.approx(1 / 8000) and times[-1] == 30
    # 0.011 s is not allowed: the camera applies the log-nearest standard speed, 1/100 s
    assert cam.set_exposure(0.011) == pytest.approx(1 / 100)
    res = cam.capture(tmp_path / "a.dng")
    from hdrcap.pipeline.io.raw import read_frame

    fr = read_frame(res.path)
    assert fr.exposure_time == pytest.approx(1 / 100, rel=1e-9)
    assert res.applied_exposure_s == pytest.approx(1 / 100)
    # light frame of 1000 e-/s for 10 ms at g=0.92: ~9.2 DN above the bias level 32
    assert np.mean(fr.data) - 32 == pytest.approx(0.92 * 1000 * 0.01, abs=1.5)
    cam.cover()
    cam.set_exposure(1.0)
    dark = read_frame(cam.capture(tmp_path / "d.dng").path)
    assert np.mean(dark.data) - 32 < 3  # dark current 1 e-/s * 1 s * 0.92


def test_mock_camera_faults(tmp_path):
    cam = MockCamera("camera-B", _scene(), seed=1, faults=MockFaults(busy_first=2, card_full_after=3))
    for k in range(2):
        with pytest.raises(Exception) as e:
            cam.capture(tmp_path / f"b{k}.dng")
        assert fault_kind(e.value) == "busy"
    for k in range(3):
        cam.capture(tmp_path / f"ok{k}.dng")
    with pytest.raises(Exception) as e:
        cam.capture(tmp_path / "full.dng")
    assert fault_kind(e.value) == "fatal"


def test_mock_camera_disconnect_leaves_partial_and_needs_reconnect(tmp_path):
    cam = MockCamera("camera-B", _scene(), seed=1, faults=MockFaults(disconnect_rate=1.0))
    with pytest.raises(Exception) as e:
        cam.capture(tmp_path / "a.dng")
    assert fault_kind(e.value) == "reconnect"
    assert (tmp_path / "a.dng").exists()  # half a file was left behind
    with pytest.raises(Exception) as e:
        cam.set_exposure(0.01)
    assert fault_kind(e.value) == "reconnect"
    cam.reconnect()
    assert cam.set_exposure(0.01) == pytest.approx(0.01)


def test_mock_camera_hang_respects_timeout(tmp_path):
    import time

    cam = MockCamera("camera-B", _scene(), seed=1, faults=MockFaults(hang_rate=1.0, hang_s=5.0))
    t0 = time.monotonic()
    with pytest.raises(Exception) as e:
        cam.capture(tmp_path / "a.dng", timeout=0.05)
    assert time.monotonic() - t0 < 1.0
    assert fault_kind(e.value) == "reconnect"


@pytest.mark.parametrize("fault", ["corrupt_rate", "truncate_rate"])
def test_mock_camera_bad_files_do_not_open(tmp_path, fault):
    from hdrcap.pipeline.errors import InputError
    from hdrcap.pipeline.io.raw import read_frame

    cam = MockCamera("camera-B", _scene(), seed=1, faults=MockFaults(**{fault: 1.0}))
    res = cam.capture(tmp_path / "a.dng")  # reported as a success, as real transfers do
    with pytest.raises(InputError):
        read_frame(res.path)


def test_mock_camera_shares_the_camera_types(tmp_path):
    """The simulator raises and returns the classes the real camera uses (one set of types)."""
    from hdrcap.acquire.camera import CameraDisconnectedError, CameraError, CameraIdentity, CaptureResult

    cam = MockCamera("camera-B", _scene(), seed=1, faults=MockFaults(busy_first=1, disconnect_rate=1.0))
    assert isinstance(cam.identity, CameraIdentity) and cam.identity.backend == "mock"
    with pytest.raises(CameraBusyError):
        cam.capture(tmp_path / "a.dng")
    with pytest.raises(CameraDisconnectedError) as e:
        cam.capture(tmp_path / "b.dng")
    assert isinstance(e.value, CameraError) and e.value.camera_fault == "reconnect"
    ok = MockCamera("camera-B", _scene(), seed=1)
    assert isinstance(ok.capture(tmp_path / "c.dng"), CaptureResult)


def test_mock_reconnect_fails_n_times_then_comes_back_on_a_new_port(tmp_path):
    faults = MockFaults(disconnect_rate=1.0, reconnect_fail_rate=1.0, reconnect_failures=2, renumber_rate=1.0)
    cam = MockCamera("camera-B", _scene(), seed=1, faults=faults)
    serial, port = cam.identity.serial, cam.identity.port
    with pytest.raises(Exception) as e:
        cam.capture(tmp_path / "a.dng")
    assert fault_kind(e.value) == "reconnect"
    for _ in range(2):  # gvfs (say) holds the device twice
        with pytest.raises(Exception) as e:
            cam.reconnect()
        assert fault_kind(e.value) == "reconnect" and "-53" in str(e.value)
        with pytest.raises(Exception) as e:
            cam.set_exposure(0.01)
        assert fault_kind(e.value) == "reconnect"
    cam.reconnect()
    assert cam.identity.port != port and cam.identity.serial == serial
    assert cam.reconnect_failures == 2 and cam.fault_log.count("renumbered") == 1
    assert cam.set_exposure(0.01) == pytest.approx(0.01)


def test_mock_reconnect_faults_are_drawn_per_disconnect():
    """Half of the disconnects (rate 0.5) are followed by failing reconnects: the draws are
    seeded and their frequency is the rate's (binomial, 400 disconnects: 3 sigma = 30)."""
    cam = MockCamera(
        "camera-B",
        _scene((8, 8)),
        seed=1,
        faults=MockFaults(seed=3, reconnect_fail_rate=0.5, reconnect_failures=2, renumber_rate=0.25),
    )
    failing = 0
    for _ in range(400):
        cam._lose_connection()
        failed = 0
        while True:
            try:
                cam.reconnect()
                break
            except Exception as err:
                assert fault_kind(err) == "reconnect"
                failed += 1
        assert failed in (0, 2)
        failing += failed == 2
    assert abs(failing - 200) < 30
    assert abs(cam.fault_log.count("renumbered") - 100) < 26  # 3 sigma of binomial(400, 0.25)


def test_mock_hang_that_ignores_the_timeout(tmp_path):
    import time

    cam = MockCamera(
        "camera-B", _scene(), seed=1, faults=MockFaults(hang_rate=1.0, hang_s=0.3, hang_ignores_timeout=True)
    )
    t0 = time.monotonic()
    with pytest.raises(Exception) as e:
        cam.capture(tmp_path / "a.dng", timeout=0.01)
    assert time.monotonic() - t0 >= 0.3  # the caller's timeout did not shorten it
    assert fault_kind(e.value) == "reconnect"


def test_session_survives_failing_reconnects_and_a_new_port(tmp_path):
    """Every disconnect is followed by two failed reconnects and a new port: the session keeps
    reconnecting (each failure is logged), and every planned frame lands once."""
    import json

    from hdrcap.acquire.capture.manifest import Manifest
    from hdrcap.acquire.capture.session import CapturePlan, CaptureSession
    from tests.helpers.jobs import FAST

    faults = MockFaults(seed=5, disconnect_rate=0.25, reconnect_fail_rate=1.0, reconnect_failures=2, renumber_rate=1.0)
    cam = MockCamera("camera-B", _scene((24, 24)), seed=2, faults=faults)
    plan = CapturePlan.bracket([1 / 250, 1 / 60, 1 / 15], None, "matched")
    res = CaptureSession(cam, tmp_path / "run", plan, retry=FAST, progress=False).run()
    disconnects = cam.fault_log.count("disconnect")
    assert disconnects >= 1 and res.captured == len(plan.frames)
    assert cam.reconnect_failures == 2 * disconnects and len(set(cam.ports)) == disconnects + 1
    assert sorted(Manifest(tmp_path / "run").frames()) == sorted(f.key for f in plan.frames)
    events = [json.loads(line) for line in (tmp_path / "run" / "events.jsonl").read_text().splitlines()]
    rec = [e for e in events if e["event"] == "reconnect"]
    assert sum(not e["ok"] for e in rec) == 2 * disconnects
    assert [e["port"] for e in rec if e["ok"]] == cam.ports[1:]


BULB_JOB = """\
[camera]
backend = "mock"
preset = "camera-B"
size = "32x32"
{bulb}

[scene]
name = "hdr"
decades = 2.0
x_max = 200.0

[exposure]
times = [1.0, 60.0]

[darks]
strategy = "matched"
block_light = "mock"
check = 0.5

[output]
folder = "runs/b"
"""


def test_bulb_exposures_beyond_30_s_are_planned_captured_and_verified(tmp_path, cli):
    """A 60 s exposure: refused on a camera without bulb, planned exactly (not snapped to 30 s)
    and captured on one with bulb; the frame's EXIF time is the bulb time."""
    import json

    from hdrcap.acquire.capture.manifest import Manifest

    job = tmp_path / "job.toml"
    job.write_text(BULB_JOB.format(bulb=""))
    no = cli("run", job, "--check")
    assert no.returncode != 0 and "exposure 60 s is outside the camera's range" in no.stderr
    job.write_text(BULB_JOB.format(bulb="bulb_max_s = 600"))
    ok = cli("run", job, "--no-progress", "--json")
    assert ok.returncode == 0, ok.stderr
    frames = Manifest(tmp_path / "runs" / "b").frames().values()
    long = [r for r in frames if r["requested_exposure_s"] > 30]
    assert len(long) == 2 and {r["kind"] for r in long} == {"dark", "light"}  # matched dark too
    for r in long:
        assert r["applied_exposure_s"] == pytest.approx(60.0) and r["file_exposure_s"] == pytest.approx(60.0)
    assert json.loads(ok.stdout.strip().splitlines()[-1])["frames"] == 4


def test_bulb_verification_tolerance():
    from hdrcap.pipeline.times import same_bulb_exposure, same_exposure

    assert same_bulb_exposure(60.0, 59.9) and not same_exposure(60.0, 59.9)  # host timing: tens of ms
    assert same_bulb_exposure(40, 40.45) and not same_bulb_exposure(40, 40.55)  # EXIF in whole seconds
    assert same_bulb_exposure(600, 605.9) and not same_bulb_exposure(600, 606.1)  # 1 % at long times
    assert not same_bulb_exposure(47.6, 60.0)  # never joins two 1/3-stop steps
