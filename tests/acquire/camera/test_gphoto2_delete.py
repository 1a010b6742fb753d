"""The real-camera backend around a good download: a failed delete on the camera costs the frame
nothing (a warning), and a constructor that fails leaves the camera released."""

from __future__ import annotations

import logging

import pytest

from hdrcap.acquire.camera import CameraDisconnectedError
from hdrcap.acquire.camera.gphoto2 import GphotoError
from tests.helpers.fake_gphoto2 import FakeBody, fake_camera


class _NoDelete(FakeBody):
    """A body whose card refuses deletes (libgphoto2 ``code``) while ``failing`` is set."""

    def __init__(self, code: int, **kw):
        super().__init__(**kw)
        self.code, self.failing, self.deleted = code, True, []

    def op_delete(self, folder, name):
        if self.failing:
            raise GphotoError(self.code, "injected delete failure")
        self.deleted.append(name)


@pytest.mark.parametrize("code", [-110, -1, -7])  # busy (after its retries), generic, I/O
def test_a_failed_delete_after_a_good_download_is_a_warning(tmp_path, caplog, code):
    body = _NoDelete(code, fmt="RAW")
    cam = fake_camera(body, pair_wait_s=0.0, backoff_s=0.0)
    cam.set_exposure(0.01)
    with caplog.at_level(logging.WARNING, logger="hdrcap"):
        res = cam.capture(tmp_path / "a.dng")
    assert res.path.read_text() == "DSC_0001.NEF"  # the frame is kept
    failed = [d for kind, d in cam.events if kind == "delete_failed"]
    assert sorted(d.split(":")[0] for d in failed) == ["/store/DCIM/DSC_0001.JPG", "/store/DCIM/DSC_0001.NEF"]
    assert any("could not delete" in r.message and r.levelno == logging.WARNING for r in caplog.records)
    body.failing = False  # the camera goes on: the next frame is downloaded and deleted
    assert cam.capture(tmp_path / "b.dng").path.read_text() == "DSC_0002.NEF"
    assert sorted(body.deleted) == ["DSC_0002.JPG", "DSC_0002.NEF"]
    assert sum(kind == "delete_failed" for kind, _d in cam.events) == len(failed)  # no new warning


class _NoOpen(FakeBody):
    def op_open(self, model, port):
        raise GphotoError(-53, "could not claim the USB device")  # another process holds it


class _NoSpeeds(FakeBody):
    def op_describe(self, names):
        raise GphotoError(-7, "I/O problem while reading the configuration")


@pytest.mark.parametrize("body_cls, err", [(_NoOpen, CameraDisconnectedError), (_NoSpeeds, CameraDisconnectedError)])
def test_a_failed_constructor_leaves_the_worker_stopped(body_cls, err):
    body = body_cls()
    with pytest.raises(err):
        fake_camera(body, backoff_s=0.0)
    assert body.dead  # the worker process that holds the camera was ended
