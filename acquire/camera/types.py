"""Plain data and exception types shared by every camera backend: the real one
(:mod:`hdrcap.acquire.camera.gphoto2`) and the simulated one (:mod:`hdrcap.acquire.camera.mock`).

Types only, no camera code: who a camera is (:class:`CameraIdentity`), what a capture
delivered (:class:`CaptureResult`) and how it failed (:class:`CameraError` and its kinds). The
one normalisation of camera model names is :func:`hdrcap.pipeline.compat.same_model`.
Every error carries its *kind* in the class attribute ``camera_fault``, one of
:data:`FAULT_KINDS`: ``"busy"`` (wait and retry), ``"reconnect"`` (the connection is gone or
hung: reconnect, then retry), ``"recapture"`` (the file is bad: take it again) or ``"fatal"``
(card full, camera gone: stop with a clear message). Capture sessions act on that attribute
(:func:`hdrcap.acquire.camera.fault_kind`), so a backend may also raise its own exceptions
that carry it. :mod:`hdrcap.acquire.camera` re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdrcap.pipeline.errors import HdrcapError

__all__ = [
    "FAULT_KINDS",
    "CameraIdentity",
    "CaptureResult",
    "CameraError",
    "CameraBusyError",
    "CameraDisconnectedError",
    "CameraTimeoutError",
    "CorruptFrameError",
    "StorageFullError",
    "CameraGoneError",
]

#: Failure kinds a session knows how to handle, see :func:`fault_kind`.
FAULT_KINDS = ("busy", "reconnect", "recapture", "fatal")


@dataclass(frozen=True)
class CameraIdentity:
    """Who the camera is: recorded with every frame.

    Attributes
    ----------
    backend : str
        ``"gphoto2"`` or ``"mock"``.
    model : str
        Camera model as the camera reports it.
    serial : str
        Serial number ("" when the camera does not report one).
    port : str
        Where it is connected (``usb:001,004``; ``mock:`` for the simulator).
    """

    backend: str
    model: str
    serial: str = ""
    port: str = ""

    def to_dict(self) -> dict[str, str]:
        """The identity as a JSON object.

        Returns
        -------
        dict
            ``backend``, ``model``, ``serial``, ``port``.
        """
        return {"backend": self.backend, "model": self.model, "serial": self.serial, "port": self.port}


@dataclass
class CaptureResult:
    """One downloaded frame.

    Attributes
    ----------
    path : Path
        Where the file was written on this computer.
    requested_exposure_s : float
        Exposure time asked for, s.
    applied_exposure_s : float
        Exposure time the camera reported after setting it (read back), s.
    dark : bool
        Whether the light was blocked.
    settings : dict
        Every setting read back from the camera at capture (name -> applied value).
    camera_file : str
        Name of the file on the camera ("" for the simulator).
    temperature_c : float or None
        Sensor temperature when the camera reports it, degrees C.
    bulb : bool
        A bulb exposure: ``applied_exposure_s`` is the open time measured around the release
        (compare it with the file's time by :func:`hdrcap.pipeline.times.same_bulb_exposure`).
    """

    path: Path
    requested_exposure_s: float
    applied_exposure_s: float
    dark: bool = False
    settings: dict[str, Any] = field(default_factory=dict)
    camera_file: str = ""
    temperature_c: float | None = None
    bulb: bool = False


class CameraError(HdrcapError):
    """A camera failure; ``camera_fault`` says how a session handles it."""

    camera_fault = "fatal"
    exit_code = 4


class CameraBusyError(CameraError):
    """The camera is busy (libgphoto2 -110, PTP Device Busy): wait and retry."""

    camera_fault = "busy"


class CameraDisconnectedError(CameraError):
    """The connection broke (I/O error, USB claim failure, mid-download loss): reconnect."""

    camera_fault = "reconnect"


class CameraTimeoutError(CameraError):
    """The camera did not answer in time (hang): reconnect."""

    camera_fault = "reconnect"


class CorruptFrameError(CameraError):
    """The downloaded file is truncated or unreadable, or its size or exposure is wrong."""

    camera_fault = "recapture"


class StorageFullError(CameraError):
    """The camera's card (or memory) is full: the session stops."""

    camera_fault = "fatal"


class CameraGoneError(CameraError):
    """The camera cannot be found any more (unplugged, switched off): the session stops."""

    camera_fault = "fatal"
