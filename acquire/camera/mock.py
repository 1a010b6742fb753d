"""``MockCamera``: the acquisition :class:`hdrcap.acquire.camera.Camera` protocol on the simulated
sensor, with injectable faults.

It behaves like a tethered raw camera: a list of allowed exposure times (1/3-stop series),
``set_exposure`` coerces to the nearest allowed value and reports what it applied, ``capture``
writes a DNG (:class:`hdrcap.mock_camera.backend.SimulatedCamera`) and hands it over. Faults
(:class:`MockFaults`) reproduce what real cameras do: busy, disconnect in the middle of a
download (a partial file is left behind), hang until the timeout (or past it: a hang that does
not cooperate), reconnects that fail several times in a row, a camera that comes back on a new
port, a corrupted or truncated file reported as a success, a full card, a camera that ignores
the shutter setting, and an abrupt process kill.

This module must not import :mod:`hdrcap.acquire` (imports point down): it raises the camera
errors of :mod:`hdrcap.acquire.camera.types` (the classes the real camera raises; their
``camera_fault`` tells a session how to react) and returns its
:class:`~hdrcap.acquire.camera.types.CaptureResult`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.acquire.camera.types import (
    CameraBusyError,
    CameraDisconnectedError,
    CameraIdentity,
    CameraTimeoutError,
    CaptureResult,
    StorageFullError,
)
from hdrcap.mock_camera.backend import SimulatedCamera
from hdrcap.mock_camera.sensor import PRESETS, SensorSpec
from hdrcap.pipeline.params import THIRD_STOP_TIMES

__all__ = ["MockCamera", "MockFaults", "STANDARD_TIMES"]

#: The usual 1/3-stop shutter speeds of a DSLR, 1/8000 s .. 30 s, ascending.
STANDARD_TIMES: tuple[float, ...] = THIRD_STOP_TIMES


@dataclass(frozen=True)
class MockFaults:
    """Faults to inject, each drawn per capture from its own seeded generator.

    Attributes
    ----------
    seed : int
        Seeds the fault draws (independent of the sensor noise).
    busy_first : int
        The first this-many capture calls fail as busy.
    busy_rate, disconnect_rate, hang_rate, corrupt_rate, truncate_rate : float
        Probability per capture call of: busy; a disconnect in the middle of the download
        (a partial file is left at the destination; every call fails until ``reconnect``);
        a hang (sleeps ``hang_s`` or the caller's timeout, then fails as a timeout and needs
        a reconnect); a corrupted file (its header overwritten with noise, reported as a
        success); a truncated file (reported as a success).
    card_full_after : int or None
        Captures that succeed before the card is full (every later capture fails).
    kill_after : int or None
        Kill the process (``os._exit(137)``) during the download of this capture number
        (1-based, counting successful downloads), after the file is written and before the
        call returns: the crash a resume must survive.
    hang_s : float
        Longest simulated hang, s.
    hang_ignores_timeout : bool
        A hang sleeps the whole ``hang_s`` whatever the caller's timeout (a USB transfer stuck
        in the driver does not cooperate); the caller must be able to give up on it.
    reconnect_fail_rate : float
        Probability that a disconnect or hang is followed by ``reconnect_failures`` failed
        reconnects (``-53``: another process, such as gvfs, claimed the device meanwhile).
    reconnect_failures : int
        How many reconnects fail in a row when they do.
    renumber_rate : float
        Probability that a reconnect finds the camera on a new port (a re-plugged,
        power-cycled or woken camera gets a new USB address); the identity's port changes,
        its serial does not.
    stuck_exposure_s : float or None
        A camera that ignores the shutter setting (not in manual exposure, the setting
        locked): every frame is exposed this many seconds, and the setting reads back as it.
    """

    seed: int = 0
    busy_first: int = 0
    busy_rate: float = 0.0
    disconnect_rate: float = 0.0
    hang_rate: float = 0.0
    corrupt_rate: float = 0.0
    truncate_rate: float = 0.0
    card_full_after: int | None = None
    kill_after: int | None = None
    hang_s: float = 0.05
    hang_ignores_timeout: bool = False
    reconnect_fail_rate: float = 0.0
    reconnect_failures: int = 2
    renumber_rate: float = 0.0
    stuck_exposure_s: float | None = None

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MockFaults:
        """Faults from a mapping of field names (a job file's ``[camera.faults]`` table).

        Raises
        ------
        ValueError
            An unknown fault name.
        """
        known = set(cls.__dataclass_fields__)
        bad = set(d) - known
        if bad:
            raise ValueError(f"unknown fault {sorted(bad)[0]!r}; known: {', '.join(sorted(known))}")
        return cls(**d)


class MockCamera:
    """A simulated tethered camera implementing :class:`hdrcap.acquire.camera.Camera`.

    Parameters
    ----------
    spec : SensorSpec or str
        Sensor physics or a preset name (``camera-A``, ``camera-B``).
    scene : numpy.ndarray
        Irradiance map, e-/s per photosite; its shape is the mosaic's.
    seed : int
        Seeds fixed patterns and temporal noise.
    allowed_times : sequence of float, optional
        Exposure times the camera accepts, s (default :data:`STANDARD_TIMES`).
    faults : MockFaults, optional
        Faults to inject (none by default).
    temperature : float, optional
        Sensor temperature, degrees C (reported by :meth:`temperature`).
    bulb_max_s : float, optional
        Longest bulb exposure, s: times above 1.2 x the longest allowed time up to this are
        exposed exactly as asked (bulb); None: no bulb.
    """

    backend = "mock"

    def __init__(
        self,
        spec: SensorSpec | str,
        scene: np.ndarray,
        seed: int = 0,
        allowed_times: Sequence[float] | None = None,
        faults: MockFaults | None = None,
        temperature: float | None = None,
        bulb_max_s: float | None = None,
    ):
        if isinstance(spec, str):
            if spec not in PRESETS:
                raise ValueError(f"unknown camera preset {spec!r}; choose from {', '.join(PRESETS)}")
            spec = PRESETS[spec]
        self.spec = spec
        self.sim = SimulatedCamera(spec, scene, seed=seed, temperature=temperature)
        self._scene = self.sim.scene  # as opened: set_scene_scale scales this one
        self.scene_scale = 1.0
        self.shape = self.sim.scene.shape
        self._allowed = sorted(float(t) for t in (allowed_times or STANDARD_TIMES))
        self.faults = faults or MockFaults()
        self._frng = np.random.default_rng([self.faults.seed, 7])
        self._rrng = np.random.default_rng([self.faults.seed, 11])  # reconnect faults: own stream
        self._t = self._allowed[len(self._allowed) // 2]
        self.bulb_max_s = bulb_max_s
        self._bulb = False
        self._iso = spec.iso
        self._covered = False
        self._connected = True
        self._card_full = False
        self.calls = 0
        self.downloads = 0
        self.reconnects = 0
        self.reconnect_failures = 0
        self.ports: list[str] = []
        self._failing_reconnects = 0
        self.fault_log: list[str] = []
        self._stop: threading.Event | None = None
        # the port names this object: two simulated cameras are never the same device
        self._port_base = f"mock:{spec.name}:{os.getpid()}.{id(self):x}"
        self.identity = CameraIdentity("mock", spec.model, self.sim.serial, self._port_base)
        self.ports.append(self.identity.port)

    # --- settings -------------------------------------------------------------------
    def allowed_exposure_times(self) -> list[float]:
        return list(self._allowed)

    def iso_values(self) -> list[int]:
        return [self.spec.iso]

    def set_iso(self, iso: int) -> int:
        self._check_connected()
        self._iso = self.spec.iso  # the simulated sensor has one ISO: coerced
        return self._iso

    def bulb_range(self) -> tuple[float, float] | None:
        """Bulb times (s) this camera exposes exactly, None without bulb."""
        return (self._allowed[-1] * 1.2, float(self.bulb_max_s)) if self.bulb_max_s else None

    def set_exposure(self, t: float) -> float:
        """Coerce ``t`` to the nearest allowed time (log scale), or take it as it is in the
        bulb range, and return what was applied (``stuck_exposure_s``: that, whatever ``t``)."""
        self._check_connected()
        if not (t > 0 and math.isfinite(t)):
            raise ValueError(f"exposure time must be positive, got {t!r}")
        if self.faults.stuck_exposure_s is not None:
            self._t, self._bulb = float(self.faults.stuck_exposure_s), False
            return self._t
        bulb = self.bulb_range()
        self._bulb = bulb is not None and bulb[0] < t <= bulb[1]
        self._t = t if self._bulb else min(self._allowed, key=lambda a: (abs(math.log(a / t)), a))
        return self._t

    # --- light, temperature, connection -------------------------------------------------
    def set_scene_scale(self, scale: float) -> None:
        """Dim or brighten the simulated light source: later frames see ``scale`` times the
        irradiance of the scene the camera was opened with (``sim.scene``, the truth, follows).

        Raises
        ------
        ValueError
            ``scale`` negative or not finite.
        """
        scale = float(scale)
        if not (math.isfinite(scale) and scale >= 0):
            raise ValueError(f"scene scale must be finite and >= 0, got {scale!r}")
        self.sim.scene = self._scene if scale == 1.0 else self._scene * scale
        self.scene_scale = scale

    def cover(self) -> None:
        self._covered = True

    def uncover(self) -> None:
        self._covered = False

    @property
    def covered(self) -> bool:
        return self._covered

    def temperature(self) -> float | None:
        return self.sim.temperature

    def reconnect(self) -> None:
        """Connect again; fails (``reconnect`` kind) while a drawn run of failed reconnects
        lasts, and may come back on a new port (:class:`MockFaults`)."""
        self.reconnects += 1
        if self._failing_reconnects > 0:
            self._failing_reconnects -= 1
            self.reconnect_failures += 1
            self.fault_log.append("reconnect_failed")
            raise CameraDisconnectedError("mock camera: could not claim the device [-53 I/O USB claim]")
        if not self._connected and self._rrng.random() < self.faults.renumber_rate:
            self.fault_log.append("renumbered")
            port = f"{self._port_base}#{len(self.ports)}"
            self.identity = dataclasses.replace(self.identity, port=port)
            self.ports.append(port)
        self._connected = True

    def _lose_connection(self) -> None:
        """The connection broke: draw whether the next reconnects fail."""
        self._connected = False
        if self._rrng.random() < self.faults.reconnect_fail_rate:
            self._failing_reconnects = self.faults.reconnect_failures

    def close(self) -> None:
        self._connected = False

    def watch_stop(self, stop: threading.Event | None) -> None:
        """A hang in progress ends when ``stop`` is set (as the real camera's worker is given
        up on: :meth:`hdrcap.acquire.camera.gphoto2.Gphoto2Camera.watch_stop`)."""
        self._stop = stop

    def _check_connected(self) -> None:
        if not self._connected:
            raise CameraDisconnectedError("mock camera: not connected (reconnect first)")

    # --- capture --------------------------------------------------------------------------
    def capture(
        self, dest: str | os.PathLike[str], *, dark: bool = False, timeout: float | None = None
    ) -> CaptureResult:
        """Expose for the applied time (light blocked when covered) and write a DNG at ``dest``.

        ``dark`` is what the caller intends; the light is blocked only by :meth:`cover`, as on
        a real camera. ``dest`` must not exist.
        """
        dest = Path(dest)
        f = self.faults
        self.calls += 1
        self._check_connected()
        if self._card_full:
            raise StorageFullError("mock camera: card full")
        u = self._frng.random(6)
        if self.calls <= f.busy_first or u[0] < f.busy_rate:
            self.fault_log.append("busy")
            raise CameraBusyError("mock camera: busy [-110]")
        if u[1] < f.hang_rate:
            self.fault_log.append("hang")
            hang = min(f.hang_s, timeout) if timeout and not f.hang_ignores_timeout else f.hang_s
            if self._stop is not None and self._stop.wait(hang):
                self._lose_connection()
                raise CameraTimeoutError("mock camera: no answer; given up because the run is stopping")
            if self._stop is None:
                time.sleep(hang)
            self._lose_connection()
            raise CameraTimeoutError("mock camera: no answer (timeout)")
        if f.card_full_after is not None and self.downloads >= f.card_full_after:
            self._card_full = True
            self.fault_log.append("card_full")
            raise StorageFullError("mock camera: card full")
        if dest.exists():
            raise FileExistsError(f"{dest}: exists")
        self.sim.capture_to(dest, self._t, dark=self._covered)
        if u[2] < f.disconnect_rate:
            self.fault_log.append("disconnect")
            size = dest.stat().st_size
            with open(dest, "r+b") as fh:  # the download stopped half-way
                fh.truncate(size // 2)
            self._lose_connection()
            raise CameraDisconnectedError("mock camera: disconnected during download [-7 I/O]")
        if u[3] < f.corrupt_rate:
            self.fault_log.append("corrupt")
            _corrupt(dest, self._frng)
        elif u[4] < f.truncate_rate:
            self.fault_log.append("truncate")
            size = dest.stat().st_size
            with open(dest, "r+b") as fh:
                fh.truncate(int(size * 0.6))
        self.downloads += 1
        if f.kill_after is not None and self.downloads == f.kill_after:
            os._exit(137)
        return CaptureResult(
            path=dest,
            requested_exposure_s=self._t,
            applied_exposure_s=self._t,
            dark=self._covered,
            settings={"shutterspeed": self._t, "iso": self._iso, "covered": self._covered},
            camera_file="",
            temperature_c=self.sim.temperature,
            bulb=self._bulb,
        )


def _corrupt(path: Path, rng: np.random.Generator) -> None:
    """Overwrite the first bytes of the file (its header) with noise, as a bad transfer would."""
    size = path.stat().st_size
    n = min(size, 512)
    with open(path, "r+b") as fh:
        fh.seek(0)
        fh.write(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
