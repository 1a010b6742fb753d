"""Plain data and exception types shared by every camera backend: the real one
(:mod:`hdrcap.acquire.gphoto2_camera`) and the simulated one (:mod:`hdrcap.mock_camera.camera`).

Types only, no camera code: who a camera is (:class:`CameraIdentity`), what a capture
delivered (:class:`CaptureResult`) and how it failed (:class:`CameraError` and its kinds), and
the one normalisation of camera model names (:func:`normalise_model`, :func:`same_model`) that
the compatibility check, the dark library and the camera locks share.
Every error carries its *kind* in the class attribute ``camera_fault``, one of
:data:`FAULT_KINDS`: ``"busy"`` (wait and retry), ``"reconnect"`` (the connection is gone or
hung: reconnect, then retry), ``"recapture"`` (the file is bad: take it again) or ``"fatal"``
(card full, camera gone: stop with a clear message). Capture sessions act on that attribute
(:func:`hdrcap.acquire.camera.fault_kind`), so a backend may also raise its own exceptions
that carry it. :mod:`hdrcap.acquire.camera` re-exports these names.
"""

from __future__ import annotations

import re
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
    "normalise_model",
    "same_model",
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


#: Words of camera names that are not part of the model: company suffixes, libgphoto2's labels
#: and the brands (EXIF writes the brand twice: Make "NIKON CORPORATION", Model "NIKON D750").
_NOISE_WORDS = {
    "CORPORATION",
    "CORP",
    "INC",
    "CO",
    "LTD",
    "COMPANY",
    "GMBH",
    "AG",
    "KK",
    "IMAGING",
    "OPTICAL",
    "ELECTRIC",
    "DIGITAL",
    "CAMERA",
    "DSC",
    "PTP",
    "MODE",
    "CONTROL",
    "PC",
    "USB",
    "NIKON",
    "CANON",
    "SONY",
    "FUJIFILM",
    "FUJI",
    "OLYMPUS",
    "OM",
    "PENTAX",
    "RICOH",
    "PANASONIC",
    "LEICA",
    "SIGMA",
    "HASSELBLAD",
    "KODAK",
    "EASTMAN",
    "SAMSUNG",
    "HDRCAP",
    "ZWO",
    "QHY",
}


def normalise_model(name: str | None) -> tuple[str, ...]:
    """The words of a camera name that name the model, upper case.

    Parameters
    ----------
    name : str or None
        A camera name as libgphoto2, EXIF (make + model) or a user wrote it.

    Returns
    -------
    tuple of str
        ``("D750",)`` for ``Nikon DSC D750`` and ``NIKON CORPORATION NIKON D750``; ``()`` for
        an unknown name.
    """
    words = re.findall(r"[A-Z0-9]+", (name or "").upper())
    return tuple(w for w in words if w not in _NOISE_WORDS)


def same_model(a: str | None, b: str | None) -> bool:
    """Whether two camera names denote the same model: equal normalised words, or one's are
    the end of the other's (a make written in front); an unknown name matches any. So
    libgphoto2's "Nikon DSC D750" and the EXIF "NIKON CORPORATION NIKON D750" match, while
    "Nikon D750" and "Nikon D7500" do not (whole words, never substrings). The dark library
    (:func:`pipeline.darklibrary.same_camera`) and the compatibility check both use it.

    Parameters
    ----------
    a, b : str or None
        Camera names.

    Returns
    -------
    bool
    """
    x, y = normalise_model(a), normalise_model(b)
    if not x or not y:
        return True
    short, long_ = sorted((x, y), key=len)
    return long_[len(long_) - len(short) :] == short
