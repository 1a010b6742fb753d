"""Full disks and file systems without hard links: a local I/O error (exit 6) never blamed on
the camera, an error path that does not write to the full disk, a free-space check before the
run, whole manifest records, and run folders on exFAT/FAT (no os.link)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

import hdrcap.acquire.capture.manifest as manifest_mod
import hdrcap.acquire.capture.session as session_mod
from hdrcap.acquire.camera.mock import MockCamera
from hdrcap.acquire.camera.types import CameraDisconnectedError
from hdrcap.acquire.capture.manifest import EventLog, Manifest
from hdrcap.acquire.capture.session import CapturePlan, CaptureSession, LocalIOError, estimate_run_bytes
from hdrcap.pipeline.errors import OutputExistsError
from hdrcap.pipeline.io.files import atomic_output, sha256_file
from tests.helpers.jobs import FAST

TIMES = [0.001, 0.004, 0.016, 0.064]


def _scene(shape=(24, 32)):
    from hdrcap.mock_camera.scenes import make_scene

    return make_scene("hdr", shape, decades=3.0, x_max=2e4)


def _plan():
    return CapturePlan.bracket(TIMES, None, "matched")


class _FullDiskCamera(MockCamera):
    """Writing the download fails from capture number ``at`` on: ENOSPC as a plain OSError (the
    simulated camera writing to our disk), or wrapped in a camera error (as a camera backend
    that reports every failed download as a disconnect would)."""

    def __init__(self, *a, at=3, wrapped=False, **kw):
        super().__init__(*a, **kw)
        self.at, self.wrapped = at, wrapped

    def capture(self, dest, **kw):
        if self.calls + 1 >= self.at:
            self.calls += 1
            full = OSError(errno.ENOSPC, "No space left on device", str(dest))
            if self.wrapped:
                raise CameraDisconnectedError("download failed [-7 I/O]") from full
            raise full
        return super().capture(dest, **kw)


def _frames_once(run_dir: Path, plan: CapturePlan) -> None:
    frames = Manifest(run_dir).frames()
    assert set(frames) == {f.key for f in plan.frames}
    for rec in frames.values():
        assert sha256_file(run_dir / rec["file"]) == rec["sha256"]
    assert len(list((run_dir / "frames").iterdir())) == len(plan.frames)


@pytest.mark.parametrize("wrapped", [False, True])
def test_a_full_host_disk_is_a_local_io_error_not_the_cameras_fault(tmp_path, wrapped):
    cam = _FullDiskCamera("camera-B", _scene(), at=3, wrapped=wrapped)
    with pytest.raises(LocalIOError, match="No space left") as info:
        CaptureSession(cam, tmp_path / "r", _plan(), retry=FAST, progress=False).run()
    assert info.value.exit_code == 6
    assert cam.calls == 3  # no retries, no reconnects: the camera is fine
    stop = [e for e in EventLog(tmp_path / "r").events() if e["event"] == "stop"]
    assert stop[-1]["exit_code"] == 6 and stop[-1]["kind"] == "local_io"
    res = CaptureSession(
        MockCamera("camera-B", _scene()), tmp_path / "r", _plan(), retry=FAST, progress=False, resume=True
    ).run()
    assert res.resumed == 2 and res.captured == len(_plan().frames) - 2
    _frames_once(tmp_path / "r", _plan())


def test_the_error_path_does_not_write_to_the_full_disk_again(tmp_path, monkeypatch):
    """The whole disk fills: the download and every later write (events, manifest) fail."""
    cam = _FullDiskCamera("camera-B", _scene(), at=3)
    real_write = os.write
    full = {"on": False}

    def write(fd, data):
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    orig_capture = cam.capture

    def capture(dest, **kw):
        if cam.calls + 1 >= cam.at:
            full["on"] = True
        return orig_capture(dest, **kw)

    cam.capture = capture
    monkeypatch.setattr(manifest_mod.os, "write", write)
    with pytest.raises(LocalIOError) as info:
        CaptureSession(cam, tmp_path / "r", _plan(), retry=FAST, progress=False).run()
    assert info.value.exit_code == 6 and "No space left" in str(info.value)
    full["on"] = False
    assert len(Manifest(tmp_path / "r").frames()) == 2 and Manifest(tmp_path / "r").torn_lines == 0


def test_free_space_is_checked_before_the_first_frame(tmp_path, monkeypatch):
    cam = MockCamera("camera-B", _scene())
    need = estimate_run_bytes(len(_plan().frames), cam.shape, merge=False)
    assert need > len(_plan().frames) * 2 * 24 * 32  # the raw files at least
    usage = session_mod.shutil.disk_usage(tmp_path)
    monkeypatch.setattr(session_mod.shutil, "disk_usage", lambda p: usage._replace(free=need - 1))
    with pytest.raises(LocalIOError, match="MB free") as info:
        CaptureSession(cam, tmp_path / "r", _plan(), retry=FAST, progress=False).run()
    assert info.value.exit_code == 6 and cam.calls == 0
    monkeypatch.setattr(session_mod.shutil, "disk_usage", lambda p: usage._replace(free=need + 1))
    CaptureSession(
        MockCamera("camera-B", _scene()), tmp_path / "r", _plan(), retry=FAST, progress=False, resume=True
    ).run()
    _frames_once(tmp_path / "r", _plan())


def test_short_writes_are_continued_and_a_failed_one_tears_no_record(tmp_path, monkeypatch):
    real_write = os.write
    monkeypatch.setattr(manifest_mod.os, "write", lambda fd, data: real_write(fd, bytes(data[:7])))
    m = Manifest(tmp_path)
    m.append({"type": "run", "note": "x" * 100})
    m.append({"type": "frame", "key": "a", "file": "f"})
    assert [r["type"] for r in m.records()] == ["run", "frame"] and m.torn_lines == 0

    def half_then_full(fd, data):
        if len(data) > 20:
            return real_write(fd, bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(manifest_mod.os, "write", half_then_full)
    size = m.path.stat().st_size
    with pytest.raises(OSError):
        m.append({"type": "frame", "key": "b", "file": "g" * 50})
    assert m.path.stat().st_size == size and m.torn_lines == 0 and len(m.records()) == 2


@pytest.fixture
def no_hard_links(monkeypatch):
    """A file system without hard links (exFAT/FAT): os.link fails with EPERM."""

    def link(src, dst, *a, **kw):
        raise OSError(errno.EPERM, "Operation not permitted", str(src), None, str(dst))

    monkeypatch.setattr(os, "link", link)


def test_run_folders_without_hard_links(tmp_path, no_hard_links):
    from hdrcap.acquire.camera.model import camera_model

    res = CaptureSession(
        MockCamera("camera-B", _scene()),
        tmp_path / "r",
        _plan(),
        retry=FAST,
        progress=False,
        calibration=camera_model(camera="camera-B"),
    ).run()
    assert res.captured == len(_plan().frames) and res.merge is not None
    _frames_once(tmp_path / "r", _plan())
    assert not list((tmp_path / "r").glob(".partial/*"))


def test_atomic_output_without_hard_links_never_replaces(tmp_path, no_hard_links):
    target = tmp_path / "out.txt"
    with atomic_output(target) as tmp:
        tmp.write_text("one")
    assert target.read_text() == "one"
    with pytest.raises(OutputExistsError):
        with atomic_output(target) as tmp:
            tmp.write_text("two")
    # a file that appears while writing is not clobbered either
    other = tmp_path / "late.txt"
    with pytest.raises(OutputExistsError, match="appeared"):
        with atomic_output(other) as tmp:
            tmp.write_text("mine")
            other.write_text("theirs")
    assert other.read_text() == "theirs" and not list(tmp_path.glob(".late*"))
