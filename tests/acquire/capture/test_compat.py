"""One compatibility check of calibration, dark library, camera and frames: at plan time, at
verification and on resume, before any frame of a mismatched run is taken."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hdrcap.acquire.camera.mock import MockCamera
from hdrcap.acquire.capture.job import load_job
from hdrcap.acquire.capture.run import run_job
from hdrcap.acquire.capture.session import CapturePlan, CaptureSession, RunConflictError, VerificationError
from hdrcap.pipeline.compat import (
    CameraProfile,
    CompatibilityError,
    check_compatible,
    normalise_model,
    same_model,
)
from tests.helpers.jobs import FAST, mock_job


def _job(tmp_path, camera="", darks='strategy = "matched"', calibration='preset = "camera-B"'):
    return mock_job(
        tmp_path / "job.toml",
        name="c",
        seed=5,
        camera=camera,
        times="[0.001, 0.004, 0.05]",
        darks=darks,
        session="",
        calibration=calibration,
    )


def _scene(shape=(24, 32)):
    from hdrcap.mock_camera.scenes import make_scene

    return make_scene("hdr", shape, decades=3.0, x_max=2e4)


# --------------------------------------------------------------------------- the check itself
@pytest.mark.parametrize(
    "a, b, same",
    [
        ("Nikon DSC D750", "NIKON CORPORATION NIKON D750", True),  # libgphoto2 vs EXIF make + model
        ("Canon EOS 5D Mark III", "Canon Canon EOS 5D Mark III", True),
        ("Canon EOS 5D Mark III", "Canon EOS 5D Mark II", False),
        ("Nikon DSC D750", "NIKON CORPORATION NIKON D7500", False),
        ("Simulated camera-A (Canon EOS 5D, Table 2)", "hdrcap Simulated camera-A (Canon EOS 5D, Table 2)", True),
        ("Simulated camera-A (Canon EOS 5D, Table 2)", "Simulated camera-B (Canon PowerShot S5, Table 2)", False),
        ("", "Nikon D750", True),  # unknown matches anything
    ],
)
def test_model_names_are_normalised(a, b, same):
    assert same_model(a, b) is same and same_model(b, a) is same


def test_normalised_nikon_name():
    assert normalise_model("Nikon DSC D750") == normalise_model("NIKON CORPORATION NIKON D750") == ("D750",)


def test_serial_decides_iso_is_an_error_temperature_a_warning():
    cal = CameraProfile("calibration", "Nikon D750", "3001234", 100.0, 20.0)
    with pytest.raises(CompatibilityError, match="serial 3009999"):
        check_compatible(cal, CameraProfile("camera", "Nikon DSC D750", "3009999"))
    with pytest.raises(CompatibilityError, match="ISO 400"):
        check_compatible(cal, CameraProfile("frame", "NIKON CORPORATION NIKON D750", "", 400.0))
    # the same serial with a differently spelled model is the same camera
    assert check_compatible(cal, CameraProfile("camera", "D750 (PTP mode)", "3001234", 100.0, 21.0)) == []
    (warning,) = check_compatible(cal, CameraProfile("camera", "Nikon DSC D750", "", 100.0, 31.0))
    assert "31 C" in warning and "20 C" in warning
    assert "unknown" in check_compatible(cal, CameraProfile("camera", "Nikon DSC D750"))[0]


# --------------------------------------------------------------------------- plan time
def test_calibration_of_another_camera_is_refused_before_any_frame(tmp_path, cli):
    proc = cli("run", _job(tmp_path, calibration='preset = "camera-A"'), "--no-progress")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "another camera" in proc.stderr and "camera-A" in proc.stderr
    assert not list(tmp_path.glob("runs/*/frames/*"))


def test_a_silent_iso_substitution_is_refused(tmp_path):
    from hdrcap.acquire.capture.job import JobError

    with pytest.raises(JobError, match="applied ISO 400, not 100"):
        run_job(load_job(_job(tmp_path, camera="iso = 100")), progress=False, echo=lambda s: None)


def _library(tmp_path, iso, model=None) -> Path:
    from hdrcap.pipeline.calibration.darklibrary import DarkLibrary
    from hdrcap.pipeline.io.raw import read_frame

    lib = DarkLibrary(tmp_path / "darks")
    cam = MockCamera("camera-B", _scene(), seed=5)
    cam.cover()
    for t in (0.001, 0.004):
        cam.set_exposure(t)
        stack = [read_frame(cam.capture(tmp_path / f"d{t:g}_{k}.dng").path).data for k in range(3)]
        lib.add(np.mean(stack, axis=0), 3, camera=model or cam.identity.model, iso=iso, exposure_time=t)
    return lib.root


def test_dark_library_master_of_another_iso_is_refused(tmp_path, cli):
    _library(tmp_path, iso=6400)
    p = _job(
        tmp_path, darks='strategy = "master"\ncount = 2', calibration='preset = "camera-B"\ndark_library = "darks"'
    )
    proc = cli("run", p, "--no-progress")
    assert proc.returncode == 2, proc.stderr
    assert "ISO 6400" in proc.stderr and "ISO 400" in proc.stderr and "Traceback" not in proc.stderr
    assert not list(tmp_path.glob("runs/*/frames/*"))


def test_dark_library_with_the_exif_spelling_is_used(tmp_path):
    # the library was built from frames (EXIF: make + model), the camera reports its model only
    _library(tmp_path, iso=400, model="hdrcap Simulated camera-B (Canon PowerShot S5, Table 2)")
    p = _job(
        tmp_path, darks='strategy = "master"\ncount = 2', calibration='preset = "camera-B"\ndark_library = "darks"'
    )
    res = run_job(load_job(p), progress=False, echo=lambda s: None)
    head = json.loads((Path(res["run_dir"]) / "manifest.jsonl").read_text().splitlines()[0])
    assert head["plan"]["library_times"] == [0.001, 0.004]


def test_dark_library_of_another_camera_is_refused(tmp_path):
    _library(tmp_path, iso=400, model="NIKON CORPORATION NIKON D750")
    p = _job(
        tmp_path, darks='strategy = "master"\ncount = 2', calibration='preset = "camera-B"\ndark_library = "darks"'
    )
    with pytest.raises(CompatibilityError, match="D750"):
        run_job(load_job(p), progress=False, echo=lambda s: None)


# --------------------------------------------------------------------------- verification and resume
def test_frames_of_another_iso_or_camera_stop_the_run(tmp_path):
    plan = CapturePlan.bracket([0.004, 0.064], None, "matched")
    with pytest.raises(VerificationError, match="ISO 400") as info:
        CaptureSession(
            MockCamera("camera-B", _scene()),
            tmp_path / "a",
            plan,
            retry=FAST,
            progress=False,
            expect=CameraProfile("the run", iso=100.0),
        ).run()
    assert info.value.exit_code == 7
    with pytest.raises(VerificationError, match="D750"):
        CaptureSession(
            MockCamera("camera-B", _scene()),
            tmp_path / "b",
            plan,
            retry=FAST,
            progress=False,
            expect=CameraProfile("the run", "Nikon DSC D750"),
        ).run()


def test_the_first_frame_fixes_the_run_iso(tmp_path):
    class AutoIso(MockCamera):
        """A camera on auto-ISO: the third frame comes out at another ISO."""

        def capture(self, dest, **kw):
            if self.downloads == 2:
                object.__setattr__(self, "spec", self.spec.__class__(**{**self.spec.__dict__, "iso": 800}))
                self.sim.spec = self.spec
            return super().capture(dest, **kw)

    plan = CapturePlan.bracket([0.004, 0.064], None, "matched")
    with pytest.raises(VerificationError, match="ISO 800.*ISO 400"):
        CaptureSession(
            AutoIso("camera-B", _scene()),
            tmp_path / "a",
            plan,
            retry=FAST,
            progress=False,
            expect=CameraProfile("the run"),
        ).run()


def test_resume_on_another_camera_is_refused_before_any_frame(tmp_path):
    plan = CapturePlan.bracket([0.004, 0.064], None, "matched")
    CaptureSession(
        MockCamera("camera-B", _scene(), seed=1, faults=None),
        tmp_path / "r",
        CapturePlan(plan.frames[:2]),
        retry=FAST,
        progress=False,
    ).run()
    other = MockCamera("camera-B", _scene(), seed=2)  # same model, another serial
    with pytest.raises(RunConflictError, match="serial") as info:
        CaptureSession(
            other, tmp_path / "r", CapturePlan(plan.frames[:2]), retry=FAST, progress=False, resume=True
        ).run()
    assert info.value.exit_code == 5 and other.calls == 0


def test_masters_at_any_temperature_are_a_warning_when_the_camera_reports_none(tmp_path):
    from hdrcap.pipeline.calibration.darklibrary import DarkLibrary

    lib = DarkLibrary(tmp_path / "darks")
    model = MockCamera("camera-B", _scene()).identity.model
    for t in (0.001, 0.004):
        lib.add(np.full((24, 32), 32.0), 4, camera=model, iso=400, exposure_time=t, temperature=35.0)
    p = _job(
        tmp_path, darks='strategy = "master"\ncount = 2', calibration='preset = "camera-B"\ndark_library = "darks"'
    )
    said = []
    run_job(load_job(p), progress=False, echo=said.append)
    assert any("no temperature" in s for s in said)
