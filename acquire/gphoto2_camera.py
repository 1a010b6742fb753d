"""``Gphoto2Camera``: the :class:`acquire.camera.Camera` protocol over python-gphoto2
(the ``gphoto2`` wheel, which bundles libgphoto2).

What it does about libgphoto2's known failure modes
---------------------------------------------------
* **One thread owns the camera.** libgphoto2 objects are not thread-safe; every call runs on
  one worker thread, callers submit work and wait with a timeout (a hung call becomes a
  :class:`~acquire.camera.CameraTimeoutError` instead of a hung program).
* **Settings are coerced silently** (the camera picks the nearest allowed value): every
  setting is read back after writing, and the applied value is what is recorded
  (:attr:`Gphoto2Camera.applied`).
* **Busy** (``GP_ERROR_CAMERA_BUSY``, -110, "PTP Device Busy" after a capture on Nikons):
  retried in place with exponential backoff, then reported as busy to the session.
* **I/O errors** (-7, -34/-35, -53 ``GP_ERROR_IO_USB_CLAIM`` when another process holds the
  device, -10 timeout): reported as disconnects; the session reconnects, which exits the old
  camera and builds a **new** ``gp.Camera`` object (never re-initialising the old one).
* **Card or camera memory full** (-115 ``GP_ERROR_NO_SPACE``; -3 on capture, which is what the
  virtual camera and some PTP cameras give when their object store is exhausted) and **camera
  gone** (-105 model not found, -52 USB device not found, or no camera at the port on
  reconnect) stop the session with a clear message.
* **Long exposures** time out inside ``gp_camera_capture`` on several models (Nikon after
  20-30 s, Sony after 35 s): above ``long_exposure_s`` the camera is triggered
  (``trigger_capture``) and ``wait_for_event`` waits for ``GP_EVENT_FILE_ADDED``; times
  longer than the camera's longest timed speed use bulb (``bulb`` = 1, wait, ``bulb`` = 0).

Settings are addressed by a generic name with per-brand aliases (:data:`ALIASES`):
``aperture`` is ``f-number`` on Nikon, ``imageformat`` is ``imagequality`` on Nikon, and so on.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any, Callable

from hdrcap.pipeline.errors import InputError

from .camera import (
    CameraBusyError,
    CameraDisconnectedError,
    CameraError,
    CameraGoneError,
    CameraIdentity,
    CameraTimeoutError,
    CaptureResult,
    StorageFullError,
    nearest_allowed,
    parse_exposure_label,
)

__all__ = ["Gphoto2Camera", "ALIASES", "list_cameras", "classify_gphoto2_error", "RAW_SUFFIXES"]

#: Generic setting name -> names used by the brands (first found wins).
ALIASES: dict[str, tuple[str, ...]] = {
    "shutterspeed": ("shutterspeed", "shutterspeed2", "exposuretime", "eos-shutterspeed"),
    "iso": ("iso", "isospeed", "exposureisospeed"),
    "aperture": ("aperture", "f-number", "fnumber"),
    "imageformat": ("imageformat", "imagequality", "imageformatsd"),
    "capturetarget": ("capturetarget",),
    "bulb": ("bulb", "eosremoterelease"),
    "exposurecompensation": ("exposurecompensation", "exposurebiascompensation"),
    "focusmode": ("focusmode", "autofocus"),
    "temperature": ("sensortemperature", "cameratemperature", "temperature", "batterytemperature"),
}

RAW_SUFFIXES = (".dng", ".nef", ".nrw", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw")

_BUSY = (-110,)
_IO = (-7, -10, -31, -34, -35, -37, -51, -53, -60)
_GONE = (-105, -52, -5)


def _gp():
    import gphoto2 as gp  # imported late: VCAMERADIR must be set before the first import

    return gp


def classify_gphoto2_error(err: Exception, during: str = "") -> CameraError:
    """Map a ``gphoto2.GPhoto2Error`` to the session's camera errors by its code."""
    code = getattr(err, "code", None)
    what = f"{during}: " if during else ""
    msg = f"{what}libgphoto2 error {code} ({getattr(err, 'string', err)})"
    if code in _BUSY:
        return CameraBusyError(msg)
    if code == -115 or (code == -3 and during.startswith("capture")):
        return StorageFullError(f"{what}camera storage is full (libgphoto2 {code}); free the card and resume")
    if code in _GONE:
        return CameraGoneError(f"{what}camera not found any more (libgphoto2 {code}); check cable and power")
    if code == -10:
        return CameraTimeoutError(msg)
    if code in _IO:
        return CameraDisconnectedError(msg)
    return CameraError(msg)


def list_cameras() -> list[tuple[str, str]]:
    """Detected cameras as (model, port) pairs (``gp.Camera.autodetect``)."""
    gp = _gp()
    found = gp.Camera.autodetect()
    return [(found.get_name(i), found.get_value(i)) for i in range(found.count())]


class _Owner:
    """A worker thread that owns the gphoto2 objects; :meth:`call` runs a function on it."""

    def __init__(self, name: str):
        self.q: queue.Queue = queue.Queue()
        self.thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while True:
            item = self.q.get()
            if item is None:
                return
            fn, box, done = item
            try:
                box["value"] = fn()
            except BaseException as err:  # handed to the caller
                box["error"] = err
            done.set()

    def call(self, fn: Callable[[], Any], timeout: float | None) -> Any:
        box: dict[str, Any] = {}
        done = threading.Event()
        self.q.put((fn, box, done))
        if not done.wait(timeout):
            raise CameraTimeoutError(f"camera did not answer within {timeout:.0f} s")
        if "error" in box:
            raise box["error"]
        return box.get("value")

    def stop(self) -> None:
        self.q.put(None)


class Gphoto2Camera:
    """A camera driven through libgphoto2.

    Parameters
    ----------
    model : str, optional
        Choose the camera whose model contains this text (case-insensitive).
    port : str, optional
        Choose the camera at this port (``usb:001,004``).
    delete_after_download : bool
        Delete each frame from the camera after it was downloaded.
    long_exposure_s : float
        Exposures at or above this use trigger + wait_for_event instead of ``capture``.
    call_timeout_s : float
        Longest a camera call (other than waiting for an exposure) may take, s.
    busy_retries : int
        In-place retries of a busy camera before the session is told.
    backoff_s : float
        First wait after busy, s (doubles).
    pair_wait_s : float
        After a file arrives, how long to listen for its partner (RAW+JPEG), s.
    settings : dict, optional
        Settings to apply at connection (generic or camera names -> values), read back.
    """

    backend = "gphoto2"

    def __init__(self, model: str | None = None, port: str | None = None, *, delete_after_download: bool = True,
                 long_exposure_s: float = 1.0, call_timeout_s: float = 30.0, busy_retries: int = 5,
                 backoff_s: float = 0.2, pair_wait_s: float = 0.2, settings: dict[str, Any] | None = None):
        self.want_model = model
        self.want_port = port
        self.delete_after_download = delete_after_download
        self.long_exposure_s = long_exposure_s
        self.call_timeout_s = call_timeout_s
        self.busy_retries = busy_retries
        self.backoff_s = backoff_s
        self.pair_wait_s = pair_wait_s
        self.initial_settings = dict(settings or {})
        self.applied: dict[str, str] = {}
        self.events: list[tuple[str, str]] = []
        self.busy_count = 0
        self.reconnects = 0
        self._inject: list[int] = []  # tests: error codes to raise before the next calls
        self._cam = None
        self._owner = _Owner("gphoto2-owner")
        self._covered = False
        self._bulb_time: float | None = None
        self._t: float | None = None
        self._labels: dict[float, str] = {}
        self._bulb_label: str | None = None
        model_name, port_name = self._choose()
        self._open(model_name, port_name)
        self.identity = CameraIdentity("gphoto2", model_name, self._serial(), port_name)
        for name, value in self.initial_settings.items():
            self.set_setting(name, value)

    # ------------------------------------------------------------------ connection
    def _choose(self) -> tuple[str, str]:
        try:
            cams = self._owner.call(list_cameras, self.call_timeout_s)
        except Exception as err:
            if hasattr(err, "code"):
                raise classify_gphoto2_error(err, "autodetect") from None
            raise
        sel = [(m, p) for m, p in cams
               if (not self.want_model or self.want_model.lower() in m.lower())
               and (not self.want_port or p == self.want_port)]
        want = " ".join(x for x in (self.want_model and f"model {self.want_model!r}",
                                    self.want_port and f"port {self.want_port}") if x)
        if not sel:
            found = ", ".join(f"{m} at {p}" for m, p in cams) or "none"
            raise CameraGoneError(f"no camera {want or 'detected'} (found: {found})")
        if len(sel) > 1 and not self.want_port:
            raise InputError("several cameras match: " + ", ".join(f"{m} at {p}" for m, p in sel)
                             + "; choose one with port")
        return sel[0]

    def _open(self, model: str, port: str) -> None:
        def go():
            gp = _gp()
            cam = gp.Camera()
            abilities = gp.CameraAbilitiesList()
            abilities.load()
            cam.set_abilities(abilities[abilities.lookup_model(model)])
            ports = gp.PortInfoList()
            ports.load()
            cam.set_port_info(ports[ports.lookup_path(port)])
            cam.init()
            return cam

        self._cam = self._run(go, "connect")
        self._read_exposures()

    def reconnect(self) -> None:
        """Exit the camera, reset the port and open a new ``gp.Camera`` on it (a fresh object,
        never the old one re-initialised; a hung owner thread is abandoned for a new one)."""
        self.reconnects += 1
        old, self._cam = self._cam, None
        owner_alive = True
        try:
            self._owner.call(lambda: old.exit() if old is not None else None, 5.0)
        except CameraTimeoutError:
            owner_alive = False
        except Exception:
            pass
        if not owner_alive:
            self._owner = _Owner("gphoto2-owner")
        self.want_port = self.identity.port
        try:
            self._owner.call(lambda: _reset_port(self.identity.port), 10.0)
            self.events.append(("port_reset", self.identity.port))
        except Exception as err:  # best effort: a port that cannot be reset may still reopen
            self.events.append(("port_reset_failed", f"{type(err).__name__}: {err}"))
        model, port = self._choose()
        self._open(model, port)
        for name, value in self.applied.items():
            if name != "shutterspeed":
                self.set_setting(name, value)
        if self._t is not None:
            self.set_exposure(self._t)

    def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                self._owner.call(cam.exit, 5.0)
            except Exception:
                pass
        self._owner.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ low level
    def _run(self, fn: Callable[[], Any], during: str, timeout: float | None = None) -> Any:
        """Run ``fn`` on the owner thread; retry busy with backoff; map libgphoto2 errors."""
        timeout = self.call_timeout_s if timeout is None else timeout
        for attempt in range(self.busy_retries + 1):
            def guarded():
                if self._inject:
                    _raise_code(self._inject.pop(0))
                return fn()

            try:
                return self._owner.call(guarded, timeout)
            except CameraError:
                raise
            except Exception as err:
                if not hasattr(err, "code"):
                    raise
                mapped = classify_gphoto2_error(err, during)
                if isinstance(mapped, CameraBusyError):
                    self.busy_count += 1
                    if attempt < self.busy_retries:
                        time.sleep(self.backoff_s * 2**attempt)
                        continue
                raise mapped from None
        raise AssertionError("unreachable")

    @staticmethod
    def _find(config, name: str):
        for cand in ALIASES.get(name, ()) + (name,):
            try:
                return config.get_child_by_name(cand)
            except Exception:
                continue
        return None

    def _describe(self, name: str) -> dict | None:
        """A setting as plain data (name, type, value, choices), read on the owner thread."""
        def go():
            w = self._find(self._cam.get_config(), name)
            if w is None:
                return None
            try:
                choices = [w.get_choice(i) for i in range(w.count_choices())]
            except Exception:
                choices = []
            return {"name": w.get_name(), "type": w.get_type(), "value": w.get_value(), "choices": choices}

        return self._run(go, f"get {name}")

    # ------------------------------------------------------------------ settings
    def get_setting(self, name: str) -> str | None:
        """Current value of a setting (generic name or the camera's), None if absent."""
        d = self._describe(name)
        return None if d is None else str(d["value"])

    def set_setting(self, name: str, value: Any) -> str:
        """Set a setting, read it back and return (and record) the applied value.

        For a choice setting whose value is not offered, the nearest numeric choice is used
        (the camera would do it silently); a value that matches nothing raises InputError.
        """
        d = self._describe(name)
        if d is None:
            model = self.identity.model if hasattr(self, "identity") else "camera"
            raise InputError(f"camera {model} has no setting {name!r}")
        real, choices = d["name"], d["choices"]
        val = value
        if choices and str(value) not in choices:
            val = _nearest_choice(value, choices)
            if val is None:
                raise InputError(f"setting {name!r}: {value!r} is not one of {', '.join(choices[:12])}")
        gp = _gp()
        if d["type"] == gp.GP_WIDGET_TOGGLE:
            val = int(val)
        elif d["type"] == gp.GP_WIDGET_RANGE:
            val = float(val)
        else:
            val = str(val)

        def apply():
            config = self._cam.get_config()
            self._find(config, real).set_value(val)
            self._cam.set_config(config)

        self._run(apply, f"set {real}")
        applied = self.get_setting(real)  # read back: the camera may have chosen another value
        self.applied[name] = applied
        return applied

    def _read_exposures(self) -> None:
        d = self._describe("shutterspeed")
        self._labels, self._bulb_label = {}, None
        for label in d["choices"] if d else []:
            try:
                t = parse_exposure_label(label)
            except ValueError:
                continue
            if t is None:
                self._bulb_label = label
            else:
                self._labels.setdefault(t, label)

    def allowed_exposure_times(self) -> list[float]:
        return sorted(self._labels)

    def iso_values(self) -> list[int]:
        d = self._describe("iso")
        out = []
        for c in d["choices"] if d else []:
            try:
                out.append(int(float(c)))
            except ValueError:
                continue
        return sorted(set(out))

    def set_iso(self, iso: int) -> int:
        return int(float(self.set_setting("iso", str(iso))))

    def set_exposure(self, t: float) -> float:
        """Set the shutter speed nearest ``t`` (or bulb for longer times), read it back and
        return the applied time, s."""
        if not (t > 0 and math.isfinite(t)):
            raise InputError(f"exposure time must be positive seconds, got {t!r}")
        if not self._labels:
            raise InputError(f"camera {self.identity.model} exposes no shutter-speed setting")
        longest = max(self._labels)
        self._t = t
        if self._bulb_label and t > longest * 1.2:
            self.set_setting("shutterspeed", self._bulb_label)
            self._bulb_time = t
            return t
        self._bulb_time = None
        target = nearest_allowed(t, list(self._labels))
        applied = self.set_setting("shutterspeed", self._labels[target])
        seconds = parse_exposure_label(applied)
        if seconds is None:
            raise CameraError(f"camera reports shutter speed {applied!r} after setting {self._labels[target]!r}")
        return seconds

    # ------------------------------------------------------------------ light, temperature
    def cover(self) -> None:
        """A tethered camera cannot block its own light; the session's light blocker does it."""
        self._covered = True

    def uncover(self) -> None:
        self._covered = False

    def temperature(self) -> float | None:
        try:
            v = self.get_setting("temperature")
        except CameraError:
            return None
        if v is None:
            return None
        try:
            return float(str(v).replace("°C", "").replace("C", "").strip())
        except ValueError:
            return None

    def _serial(self) -> str:
        try:
            v = self.get_setting("serialnumber")
            return (v or "").strip()
        except CameraError:
            return ""

    def storage_free_images(self) -> int | None:
        """Free images reported by the first storage, None when unknown (only meaningful when
        the camera captures to its card: capturing to internal RAM needs no card space)."""
        def go():
            return [getattr(x, "freeimages", None) for x in self._cam.get_storageinfo()]

        try:
            free = self._run(go, "storageinfo")
        except (CameraBusyError, CameraDisconnectedError, CameraTimeoutError, CameraGoneError):
            raise
        except CameraError:  # storage information not supported
            return None
        for n in free:
            if n is not None and n >= 0:
                return int(n)
        return None

    # ------------------------------------------------------------------ capture
    def capture(self, dest, *, dark: bool = False, timeout: float | None = None) -> CaptureResult:
        """Expose, download to ``dest`` (suffix taken from the camera's file) and delete the
        file from the camera when ``delete_after_download``."""
        gp = _gp()
        dest = Path(dest)
        t = self._bulb_time or self._t or 0.0
        wait = (timeout or (t + self.call_timeout_s))
        target = (self.get_setting("capturetarget") or "").lower()
        if "ram" not in target and "sdram" not in target and self.storage_free_images() == 0:
            raise StorageFullError("camera storage is full (0 free images); free the card and resume")
        if self._bulb_time is not None:
            files = self._capture_bulb(self._bulb_time, wait)
        elif t >= self.long_exposure_s:
            self._run(lambda: self._cam.trigger_capture(), "capture (trigger)")
            files = self._wait_files(wait)
        else:
            def shoot():
                p = self._cam.capture(gp.GP_CAPTURE_IMAGE)
                return (p.folder, p.name)

            files = [self._run(shoot, "capture", timeout=wait)] + self._drain_files(self.pair_wait_s)
        if not files:
            raise CameraTimeoutError(f"no file from the camera within {wait:.0f} s")
        folder, name = _prefer_raw(files)
        out = self.download(f"{folder}/{name}", dest.with_suffix(Path(name).suffix.lower() or dest.suffix), wait)
        if self.delete_after_download:
            for fo, na in files:
                self._run(lambda fo=fo, na=na: self._cam.file_delete(fo, na), f"delete {na}")
        applied = self._bulb_time if self._bulb_time is not None else parse_exposure_label(
            self.applied.get("shutterspeed", "") or self.get_setting("shutterspeed"))
        return CaptureResult(path=out, requested_exposure_s=t, applied_exposure_s=applied or t, dark=dark,
                             settings=dict(self.applied), camera_file=f"{folder}/{name}",
                             temperature_c=self.temperature())

    def download(self, camera_path: str, dest, timeout: float | None = None) -> Path:
        """Download a file already on the camera (``/store_00010001/DCIM/x.NEF``) to ``dest``."""
        gp = _gp()
        folder, name = camera_path.rsplit("/", 1)
        dest = Path(dest)
        if dest.exists():
            raise FileExistsError(f"{dest}: exists")
        tmp = dest.with_name(f".{dest.name}.download")

        def go():
            self._cam.file_get(folder or "/", name, gp.GP_FILE_TYPE_NORMAL).save(str(tmp))

        try:
            self._run(go, f"download {name}", timeout=timeout)
            os.replace(tmp, dest)
        finally:
            if tmp.exists():
                tmp.unlink()
        return dest

    def list_files(self, folder: str = "/") -> list[str]:
        """Every file on the camera under ``folder`` (recursive)."""
        def walk(f):
            out = []
            files = self._cam.folder_list_files(f)
            out += [f.rstrip("/") + "/" + files.get_name(i) for i in range(files.count())]
            subs = self._cam.folder_list_folders(f)
            for i in range(subs.count()):
                out += walk(f.rstrip("/") + "/" + subs.get_name(i))
            return out

        return self._run(lambda: walk(folder), "list files")

    def _capture_bulb(self, t: float, wait: float) -> list[tuple[str, str]]:
        self.set_setting("bulb", 1)
        t0 = time.monotonic()
        try:
            time.sleep(t)
        finally:
            self.set_setting("bulb", 0)
        self.events.append(("bulb", f"{time.monotonic() - t0:.3f}"))
        return self._wait_files(wait)

    def _wait_files(self, wait: float) -> list[tuple[str, str]]:
        """Wait for GP_EVENT_FILE_ADDED (then a little more for a RAW+JPEG pair)."""
        deadline = time.monotonic() + wait
        files: list[tuple[str, str]] = []
        while time.monotonic() < deadline:
            got = self._next_event(500)
            if got == "complete" and files:
                break
            if isinstance(got, tuple):
                files.append(got)
                files += self._drain_files(self.pair_wait_s)
                break
        return files

    def _drain_files(self, seconds: float) -> list[tuple[str, str]]:
        if seconds <= 0:
            return []
        end = time.monotonic() + seconds
        files = []
        while time.monotonic() < end:
            got = self._next_event(50)
            if got == "timeout":
                break
            if isinstance(got, tuple):
                files.append(got)
        return files

    def _next_event(self, ms: int):
        gp = _gp()

        def wait():
            typ, data = self._cam.wait_for_event(ms)
            if typ in (gp.GP_EVENT_FILE_ADDED, gp.GP_EVENT_FOLDER_ADDED):
                return typ, (data.folder, data.name)
            return typ, str(data)

        typ, data = self._run(wait, "wait_for_event", timeout=ms / 1000 + 10)
        if typ == gp.GP_EVENT_FILE_ADDED:
            self.events.append(("file_added", f"{data[0]}/{data[1]}"))
            return data
        if typ == gp.GP_EVENT_CAPTURE_COMPLETE:
            self.events.append(("capture_complete", ""))
            return "complete"
        if typ == gp.GP_EVENT_TIMEOUT:
            return "timeout"
        if typ == gp.GP_EVENT_FOLDER_ADDED:
            self.events.append(("folder_added", f"{data[0]}/{data[1]}"))
        else:
            self.events.append(("other", data))
        return "other"


def _reset_port(path: str) -> None:
    """Open the port, reset it (USB reset) and close it, as after a hang or a disconnect."""
    gp = _gp()
    ports = gp.PortInfoList()
    ports.load()
    port = gp.GPPort()
    port.set_info(ports[ports.lookup_path(path)])
    port.open()
    try:
        port.reset()
    finally:
        port.close()


def _raise_code(code: int):
    gp = _gp()
    raise gp.GPhoto2Error(code)


def _prefer_raw(files: list[tuple[str, str]]) -> tuple[str, str]:
    for folder, name in files:
        if Path(name).suffix.lower() in RAW_SUFFIXES:
            return folder, name
    return files[0]


def _nearest_choice(value: Any, choices: list[str]) -> str | None:
    """The choice numerically nearest ``value`` (exposure labels and f-numbers understood)."""
    def num(x):
        s = str(x).strip().lower().removeprefix("f/").removeprefix("iso ")
        try:
            v = parse_exposure_label(s)
        except ValueError:
            return None
        return v

    want = num(value)
    if want is None:
        return None
    scored = [(abs(math.log(n / want)), c) for c in choices if (n := num(c))]
    return min(scored)[1] if scored else None
