"""The camera protocol every acquisition backend implements, camera errors, and the parsing
of the cameras' own exposure-time labels.

A backend (:class:`hdrcap.acquire.camera.gphoto2.Gphoto2Camera`,
:class:`hdrcap.acquire.camera.mock.MockCamera`) is any object with the methods of :class:`Camera`.
Capture sessions (:mod:`hdrcap.acquire.capture.session`) drive it and decide what to do on a failure from the failure's
*kind* (:func:`fault_kind`): ``"busy"`` (wait and retry), ``"reconnect"`` (the connection is
gone or hung: reconnect, then retry), ``"recapture"`` (the file is bad: take it again) or
``"fatal"`` (card full, camera gone: stop with a clear message). Errors carry their kind in
the attribute ``camera_fault``. The identity, capture-result and error classes live in
:mod:`hdrcap.acquire.camera.types` and are re-exported here.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path
from typing import Protocol, runtime_checkable

from hdrcap.acquire.camera.types import (
    FAULT_KINDS,
    CameraBusyError,
    CameraDisconnectedError,
    CameraError,
    CameraGoneError,
    CameraIdentity,
    CameraTimeoutError,
    CaptureResult,
    CorruptFrameError,
    StorageFullError,
)

__all__ = [
    "Camera",
    "CameraIdentity",
    "CaptureResult",
    "CameraError",
    "CameraBusyError",
    "CameraDisconnectedError",
    "CameraTimeoutError",
    "CorruptFrameError",
    "StorageFullError",
    "CameraGoneError",
    "FAULT_KINDS",
    "fault_kind",
    "parse_exposure_label",
    "format_exposure",
    "nearest_allowed",
    "exposure_ladder",
    "BULB_MAX_S",
    "dark_level",
    "frame_is_dark",
]


@runtime_checkable
class Camera(Protocol):
    """What a capture session needs from a camera."""

    identity: CameraIdentity

    def allowed_exposure_times(self) -> list[float]:
        """Exposure times the camera accepts, s, ascending (bulb excluded)."""

    def iso_values(self) -> list[int]:
        """ISO speeds the camera accepts (empty when it has none)."""

    def set_iso(self, iso: int) -> int:
        """Set the ISO speed and return the value read back."""

    def set_exposure(self, t: float) -> float:
        """Set the exposure time (s) and return the value read back from the camera, s."""

    def capture(self, dest: Path, *, dark: bool = False, timeout: float | None = None) -> CaptureResult:
        """Expose with the current settings, download the file to ``dest`` (a new file) and
        delete it from the camera when the backend was asked to."""

    def cover(self) -> None:
        """Block the light (dark frames) when the camera can do it itself; else a no-op."""

    def uncover(self) -> None:
        """Unblock the light."""

    def temperature(self) -> float | None:
        """Sensor temperature, degrees C, or None when unknown."""

    def reconnect(self) -> None:
        """Drop the connection and open a new one (a fresh camera object)."""

    # optional: ``bulb_range() -> (shortest, longest) | None``, the bulb times (s) the camera
    # can time; see :func:`exposure_ladder`; ``watch_stop(event)``: give up a call in progress
    # once the event is set (a run stopping on SIGTERM), see
    # :func:`hdrcap.acquire.capture.session.watch_stop`

    def close(self) -> None:
        """Release the camera."""


def fault_kind(err: BaseException) -> str | None:
    """How a session should treat ``err``: one of :data:`FAULT_KINDS`, or None when ``err``
    is not a camera failure (a bug or a user error, which propagates)."""
    kind = getattr(err, "camera_fault", None)
    return kind if kind in FAULT_KINDS else None


_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)"


def parse_exposure_label(label: str | float | int) -> float | None:
    """Parse a camera's exposure-time label into seconds.

    Understands ``1/250``, ``1/250s``, ``0.1000s`` (the virtual PTP camera), ``30``, ``30s``,
    ``2.5``, Canon's ``30"`` and ``0"3`` (0.3 s, ``1"6`` = 1.6 s) and ``1/4000 s``.
    ``bulb``, ``time`` and ``auto`` are not timed: None.

    Raises
    ------
    ValueError
        For a label that is none of these (the message names the label).
    """
    if isinstance(label, (int, float)) and not isinstance(label, bool):
        t = float(label)
    else:
        text = str(label).strip().lower().replace(",", ".")
        if text in ("bulb", "b", "time", "t", "auto", "bulb/time"):
            return None
        text = re.sub(r"\s*(?:sec|secs|seconds|s)$", "", text).strip()
        if m := re.fullmatch(rf"({_NUM})\s*/\s*({_NUM})", text):
            den = float(m.group(2))
            if den == 0:
                raise ValueError(f"exposure label {label!r}: zero denominator")
            t = float(Fraction(m.group(1)) / Fraction(m.group(2)))
        elif m := re.fullmatch(r"(\d+)\"(\d*)", text):
            t = float(m.group(1) + "." + (m.group(2) or "0"))
        elif re.fullmatch(_NUM, text):
            t = float(text)
        else:
            raise ValueError(f"exposure label {label!r} is not an exposure time")
    if not (t > 0 and math.isfinite(t)):
        raise ValueError(f"exposure label {label!r} is not a positive time")
    return t


def format_exposure(t: float) -> str:
    """A readable label: ``1/250 s`` below 0.3 s when the reciprocal is round, else ``0.4 s``."""
    if t < 0.3:
        inv = 1.0 / t
        if abs(inv - round(inv)) < 1e-6 * inv:
            return f"1/{round(inv)} s"
    return f"{t:.6g} s"


def nearest_allowed(t: float, allowed: Sequence[float]) -> float:
    """The allowed exposure time closest to ``t`` on a logarithmic scale (as cameras round)."""
    if not allowed:
        raise ValueError("no allowed exposure times")
    return min(allowed, key=lambda a: (abs(math.log(a / t)), a))


#: Longest bulb exposure a plan may ask for, s (an hour: beyond it dark current and cosmic
#: rays, not the shutter, limit a frame).
BULB_MAX_S: float = 3600.0


def exposure_ladder(camera: Camera) -> list[float]:
    """Every exposure time a plan may use on ``camera``, s, ascending: its timed shutter speeds
    and, when it has bulb (``camera.bulb_range()``), a 1/3-stop ladder above the longest timed
    speed up to the longest bulb time (each bulb time is timed around the release).

    Parameters
    ----------
    camera : Camera
        The camera (``allowed_exposure_times()``; ``bulb_range()`` optional).

    Returns
    -------
    list of float
        Exposure times, s.
    """
    allowed = sorted(float(t) for t in camera.allowed_exposure_times())
    bulb = getattr(camera, "bulb_range", lambda: None)()
    if not allowed or not bulb:
        return allowed
    lo, hi = bulb
    out, k = list(allowed), 1
    while (t := round(allowed[-1] * 2 ** (k / 3), 1)) <= hi * (1 + 1e-9):
        if t >= lo:
            out.append(t)
        k += 1
    return out


def dark_level(path: str | os.PathLike[str]) -> float:
    """How much light a frame saw: its median above black as a fraction of the range
    (raw files via :func:`pipeline.io.raw.read_frame`, JPEG/PNG previews via Pillow)."""
    import numpy as np

    path = Path(path)
    if path.suffix.lower() in (".jpg", ".jpeg"):
        from PIL import Image

        with Image.open(path) as im:
            data = np.asarray(im.convert("L"), dtype=np.float64)
        return float(np.median(data) / 255.0)
    from hdrcap.pipeline.io.raw import read_frame

    fr = read_frame(path)
    black = fr.black_level or 0.0
    white = fr.white_level or float(np.iinfo(np.uint16).max)
    return float((np.median(fr.data) - black) / max(white - black, 1.0))


def frame_is_dark(path: str | os.PathLike[str], threshold: float = 0.05) -> bool:
    """Cover detection: True when the frame's median is below ``threshold`` of the range,
    i.e. the light was blocked (a frame of a scene lit for the exposure is far above it)."""
    return dark_level(path) < threshold
