"""``Gphoto2Camera``: the :class:`acquire.camera.Camera` protocol over python-gphoto2
(the ``gphoto2`` wheel, which bundles libgphoto2).

What it does about libgphoto2's known failure modes
---------------------------------------------------
* **A child process owns the camera** (as INDI drivers do). libgphoto2 objects are not
  thread-safe and a USB call can hang for good; every call is a request to one worker process
  (:class:`_Worker`), answered within a timeout. A call that does not answer in time gets the
  worker **killed** (the kernel releases its USB claim) and raises
  :class:`~acquire.camera.CameraTimeoutError`; the session then reconnects, which starts a new
  worker. Nothing is ever left running that still holds the device.
* **Reconnect finds the camera again**, by serial number (model as the fallback), on whatever
  port it comes back (a re-plugged, power-cycled or woken camera gets a new USB address),
  polling with exponential backoff until ``reconnect_deadline_s``. A failed reconnect leaves a
  disconnected camera whose every call raises a ``reconnect`` fault, never an empty object.
* **Settings are coerced silently** (the camera picks the nearest allowed value): every
  setting is read back after writing, and the applied value is what is recorded
  (:attr:`Gphoto2Camera.applied`). The configuration tree is read once per connection and
  cached in the worker; a write sends only the changed widget (``set_single_config``) and
  reads back only that widget (``get_single_config``).
* **Busy** (``GP_ERROR_CAMERA_BUSY``, -110, "PTP Device Busy" after a capture on Nikons):
  retried in place with exponential backoff, then reported as busy to the session.
* **I/O errors** (-7, -34/-35, -53 ``GP_ERROR_IO_USB_CLAIM`` when another process holds the
  device, -10 timeout): reported as disconnects; the session reconnects.
* **Card or camera memory full** (-115 ``GP_ERROR_NO_SPACE``; -3 on capture, which is what the
  virtual camera and some PTP cameras give when their object store is exhausted) and **camera
  gone** (-105 model not found, -52 USB device not found, or no camera found again before the
  reconnect deadline) stop the session with a clear message. Free space is judged from every
  writable storage and only from the fields the camera marks valid.
* **Stale events and late partners.** Pending events are drained before every release; a file
  announced before the release, or one sharing its name stem with an earlier frame's file (the
  late RAW of a RAW+JPEG pair), never becomes this frame's file.
* **Long exposures** time out inside ``gp_camera_capture`` on several models (Nikon after
  20-30 s, Sony after 35 s): above ``long_exposure_s`` the camera is triggered
  (``trigger_capture``) and ``wait_for_event`` waits for ``GP_EVENT_FILE_ADDED``. Times
  longer than the camera's longest timed speed use bulb: the worker presses and releases the
  bulb widget (``bulb`` on Nikon and most PTP bodies, ``eosremoterelease`` on Canon) with
  nothing but a sleep in between, and the open time it measured is recorded.

Settings are addressed by a generic name with per-brand aliases (:data:`ALIASES`):
``aperture`` is ``f-number`` on Nikon, ``imageformat`` is ``imagequality`` on Nikon, and so on.
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Self

from hdrcap.acquire.camera import (
    BULB_MAX_S,
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
from hdrcap.pipeline.errors import InputError

__all__ = [
    "Gphoto2Camera",
    "ALIASES",
    "PREFLIGHT",
    "list_cameras",
    "classify_gphoto2_error",
    "RAW_SUFFIXES",
    "choose_camera",
    "free_images",
    "GphotoError",
]

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
    "serialnumber": ("serialnumber", "eos-serialnumber"),
    "exposureprogram": ("expprogram", "exposureprogram", "autoexposuremode", "autoexposuremodedial", "exposuremode"),
    "autoiso": ("autoiso", "isoauto"),
    "longexposurenr": ("longexpnr", "longexposurenr", "longexposurenoisereduction", "eos-longexposurenr"),
}

_LOG = logging.getLogger("hdrcap.camera")

_RAW_WORDS = ("raw", "nef", "cr2", "cr3", "arw", "dng", "orf", "rw2", "raf", "pef")
_OFF_WORDS = ("off", "0", "false", "disable", "disabled", "no")


def _is_manual_program(v: str) -> bool:
    return v.strip().lower() in ("m", "manual", "1") or v.strip().lower().startswith("manual")


def _is_manual_focus(v: str) -> bool:
    s = v.strip().lower()
    return s in _OFF_WORDS or s in ("mf", "manual", "manual focus") or s.startswith("manual") or "(mf)" in s


def _has_raw(v: str) -> bool:
    return any(k in v.lower() for k in _RAW_WORDS)


def _is_fixed_iso(v: str) -> bool:
    try:
        return float(v) > 0
    except ValueError:
        return False


def _is_off(v: str) -> bool:
    return v.strip().lower() in _OFF_WORDS


#: Pre-flight rules: generic setting, test of its value, what it must be and why.
PREFLIGHT: tuple[tuple[str, Callable[[str], bool], str, str], ...] = (
    ("exposureprogram", _is_manual_program, "manual (M)", "the camera must not choose the exposure"),
    ("focusmode", _is_manual_focus, "manual focus", "autofocus may refocus between frames or refuse to release"),
    ("imageformat", _has_raw, "RAW", "the merge needs linear raw data"),
    ("iso", _is_fixed_iso, "a fixed ISO", "one gain for every frame"),
    ("autoiso", _is_off, "off", "one gain for every frame"),
    ("longexposurenr", _is_off, "off", "in-camera dark subtraction doubles the time and alters the noise"),
)

RAW_SUFFIXES = (".dng", ".nef", ".nrw", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw")

_BUSY = (-110,)
_IO = (-7, -10, -31, -34, -35, -37, -51, -53, -60)
_GONE = (-105, -52, -5)


class GphotoError(Exception):
    """A libgphoto2 error code carried back from the worker process (``code``, ``string``)."""

    def __init__(self, code: int, string: str = ""):
        super().__init__(f"[{code}] {string}")
        self.code = code
        self.string = string


def classify_gphoto2_error(err: Exception, during: str = "") -> CameraError:
    """Map a libgphoto2 error to the session's camera errors by its code.

    Parameters
    ----------
    err : Exception
        A ``gphoto2.GPhoto2Error`` or :class:`GphotoError` (anything with ``code``).
    during : str
        What was being done (``"capture"``, ``"set iso"``), for the message.

    Returns
    -------
    CameraError
        The camera error of the code's kind (busy, disconnect, timeout, storage full, gone).
    """
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


# ====================================================================== the worker process
class _WorkerState:
    """Child-process side: owns the ``gp.Camera`` and its cached configuration tree. Each
    ``op_*`` method answers one request; libgphoto2 errors travel back by code."""

    WIDGET_TYPES = {2: "text", 3: "range", 4: "toggle", 5: "radio", 6: "menu", 8: "date"}

    def __init__(self):
        import gphoto2 as gp  # VCAMERADIR (tests) is in the environment this process inherited

        self.gp = gp
        self.cam: Any = None  # a gp.Camera once op_open ran (gphoto2 ships no type information)
        self.tree: Any = None
        self.reads = {"tree": 0, "single": 0, "set": 0}

    # --- connection
    def op_detect(self) -> list[tuple[str, str]]:
        found = self.gp.Camera.autodetect()
        return [(found.get_name(i), found.get_value(i)) for i in range(found.count())]

    def op_open(self, model: str, port: str) -> None:
        self.op_exit()
        gp = self.gp
        cam = gp.Camera()
        abilities = gp.CameraAbilitiesList()
        abilities.load()
        cam.set_abilities(abilities[abilities.lookup_model(model)])
        ports = gp.PortInfoList()
        ports.load()
        cam.set_port_info(ports[ports.lookup_path(port)])
        cam.init()
        self.cam, self.tree = cam, None

    def op_exit(self) -> None:
        cam, self.cam, self.tree = self.cam, None, None
        if cam is not None:
            cam.exit()

    def op_reset_port(self, path: str) -> None:
        gp = self.gp
        ports = gp.PortInfoList()
        ports.load()
        port = gp.GPPort()
        port.set_info(ports[ports.lookup_path(path)])
        port.open()
        try:
            port.reset()
        finally:
            port.close()

    def op_sleep(self, seconds: float) -> None:
        """A call that does not answer (tests: a hung USB transfer)."""
        time.sleep(seconds)

    def op_stats(self) -> dict[str, int]:
        return dict(self.reads)

    # --- settings
    def _tree(self):
        if self.tree is None:
            self.tree = self.cam.get_config()
            self.reads["tree"] += 1
        return self.tree

    def _widget(self, names: Sequence[str]):
        tree = self._tree()
        for cand in names:
            try:
                return tree.get_child_by_name(cand)
            except self.gp.GPhoto2Error:
                continue
        return None

    def op_describe(self, names: Sequence[str]) -> dict | None:
        w = self._widget(names)
        if w is None:
            return None
        try:
            choices = [w.get_choice(i) for i in range(w.count_choices())]
        except self.gp.GPhoto2Error:
            choices = []
        return {
            "name": w.get_name(),
            "type": self.WIDGET_TYPES.get(w.get_type(), "other"),
            "value": w.get_value(),
            "choices": choices,
            "readonly": bool(w.get_readonly()),
        }

    def op_read(self, names: Sequence[str]):
        """The current value of one widget, read from the camera (not the cache)."""
        w = self._widget(names)
        if w is None:
            return None
        value = self._read_back(w)
        return value

    def _read_back(self, w):
        name = w.get_name()
        try:
            fresh = self.cam.get_single_config(name)
            self.reads["single"] += 1
        except self.gp.GPhoto2Error as err:
            if err.code != self.gp.GP_ERROR_NOT_SUPPORTED:
                raise
            self.tree = None
            fresh = self._widget([name])
        value = fresh.get_value()
        if fresh is not w:
            w.set_value(value)  # keep the cached tree in step
        return value

    def op_set(self, name: str, value) -> Any:
        """Write one widget (only that one) and return the value the camera reports back."""
        w = self._widget([name])
        w.set_value(value)
        self.reads["set"] += 1
        try:
            self.cam.set_single_config(name, w)
        except self.gp.GPhoto2Error as err:
            if err.code != self.gp.GP_ERROR_NOT_SUPPORTED:
                raise
            self.cam.set_config(self._tree())
        return self._read_back(w)

    def op_bulb(self, name: str, press, release, seconds: float) -> dict[str, float]:
        """Open the shutter with ``name = press``, sleep, close with ``name = release``: nothing
        else happens inside the open interval. Returns the monotonic times of the four edges."""
        w = self._widget([name])
        w.set_value(press)
        t0 = time.monotonic()
        self.cam.set_single_config(name, w)
        t1 = time.monotonic()
        try:
            time.sleep(max(0.0, seconds - (t1 - t0)))
        finally:
            w.set_value(release)
            t2 = time.monotonic()
            self.cam.set_single_config(name, w)
            t3 = time.monotonic()
        return {"press_start": t0, "press_end": t1, "release_start": t2, "release_end": t3}

    # --- capture, files, storage
    def op_capture(self) -> tuple[str, str]:
        p = self.cam.capture(self.gp.GP_CAPTURE_IMAGE)
        return p.folder, p.name

    def op_trigger(self) -> None:
        self.cam.trigger_capture()

    def op_event(self, ms: int) -> tuple[str, Any]:
        gp = self.gp
        typ, data = self.cam.wait_for_event(ms)
        if typ == gp.GP_EVENT_FILE_ADDED:
            return "file", (data.folder, data.name)
        if typ == gp.GP_EVENT_FOLDER_ADDED:
            return "folder", (data.folder, data.name)
        if typ == gp.GP_EVENT_CAPTURE_COMPLETE:
            return "complete", ""
        if typ == gp.GP_EVENT_TIMEOUT:
            return "timeout", ""
        return "other", str(data)

    def op_drain(self, ms: int, limit: int = 200) -> list[tuple[str, Any]]:
        """Every pending event (until a wait of ``ms`` ends in a timeout)."""
        out = []
        for _ in range(limit):
            kind, data = self.op_event(ms)
            if kind == "timeout":
                break
            out.append((kind, data))
        return out

    def op_download(self, folder: str, name: str, path: str) -> None:
        self.cam.file_get(folder or "/", name, self.gp.GP_FILE_TYPE_NORMAL).save(path)

    def op_delete(self, folder: str, name: str) -> None:
        self.cam.file_delete(folder, name)

    def op_list_files(self, folder: str) -> list[str]:
        out = []
        files = self.cam.folder_list_files(folder)
        out += [folder.rstrip("/") + "/" + files.get_name(i) for i in range(files.count())]
        subs = self.cam.folder_list_folders(folder)
        for i in range(subs.count()):
            out += self.op_list_files(folder.rstrip("/") + "/" + subs.get_name(i))
        return out

    def op_storage(self) -> list[dict[str, Any]]:
        """Each storage's fields that the camera marks valid (the ``fields`` bits)."""
        gp = self.gp
        access = {
            gp.GP_STORAGEINFO_AC_READWRITE: "rw",
            gp.GP_STORAGEINFO_AC_READONLY: "ro",
            gp.GP_STORAGEINFO_AC_READONLY_WITH_DELETE: "ro+delete",
        }
        out = []
        for s in self.cam.get_storageinfo():
            d: dict[str, Any] = {"base": s.basedir}
            if s.fields & gp.GP_STORAGEINFO_FREESPACEIMAGES:
                d["freeimages"] = int(s.freeimages)
            if s.fields & gp.GP_STORAGEINFO_FREESPACEKBYTES:
                d["freekbytes"] = int(s.freekbytes)
            if s.fields & gp.GP_STORAGEINFO_ACCESS:
                d["access"] = access.get(s.access, "other")
            if s.fields & gp.GP_STORAGEINFO_DESCRIPTION:
                d["description"] = s.description
            out.append(d)
        return out


def _worker_main(read_fd: int, write_fd: int) -> None:
    """Entry point of the worker process: answer ``(op, args)`` requests until ``None`` or
    the parent goes away (end of file), then release the camera."""
    inbox, outbox = Connection(read_fd, writable=False), Connection(write_fd, readable=False)
    state = _WorkerState()
    try:
        while True:
            try:
                req = inbox.recv()
            except (EOFError, OSError):
                break
            if req is None:
                break
            op, args = req
            reply: tuple[Any, ...]
            try:
                reply = ("ok", getattr(state, "op_" + op)(*args))
            except Exception as err:
                code = getattr(err, "code", None)
                reply = (
                    ("gp", code, str(getattr(err, "string", err)))
                    if isinstance(code, int)
                    else ("err", type(err).__name__, str(err))
                )
            outbox.send(reply)
    finally:
        try:
            state.op_exit()
        except Exception:
            pass


#: How long a camera call in progress may still take once the run is asked to stop
#: (SIGTERM), s: a call that answers normally finishes well within it, a hung one is given up.
STOP_GRACE_S = 2.0
#: How often a waiting call looks at the stop event, s.
STOP_POLL_S = 0.05


class _Worker:
    """Parent side of the worker process; :meth:`call` sends one request and waits for its answer.

    Parameters
    ----------
    name : str
        For messages.
    """

    def __init__(self, name: str = "gphoto2"):
        self.name = name
        p_read, c_write = os.pipe()
        c_read, p_write = os.pipe()
        code = f"from hdrcap.acquire.camera.gphoto2 import _worker_main; _worker_main({c_read}, {c_write})"
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code], pass_fds=(c_read, c_write), env=env, stdin=subprocess.DEVNULL, close_fds=True
        )
        os.close(c_read)
        os.close(c_write)
        self.inbox, self.outbox = Connection(p_read, writable=False), Connection(p_write, readable=False)
        self.lock = threading.Lock()
        self.dead = False

    @property
    def pid(self) -> int:
        return self.proc.pid

    def call(
        self,
        op: str,
        *args,
        timeout: float | None = None,
        abort: threading.Event | None = None,
        grace_s: float = STOP_GRACE_S,
    ) -> Any:
        """Run ``op`` in the worker and return its result.

        Parameters
        ----------
        op : str
            The worker operation (``op_<name>`` of the worker).
        *args
            Its arguments.
        timeout : float, optional
            Longest wait for the answer, s (None: no limit).
        abort : threading.Event, optional
            The run is stopping when set (SIGTERM): the call gets ``grace_s`` more to answer,
            then the worker is killed, whatever ``timeout`` says.
        grace_s : float
            See ``abort``, s.

        Raises
        ------
        CameraTimeoutError
            No answer within ``timeout`` s, or within ``grace_s`` of ``abort``: the worker was
            killed.
        CameraDisconnectedError
            The worker is gone (killed earlier or crashed).
        GphotoError
            libgphoto2 returned an error code.
        """
        with self.lock:
            if self.dead:
                raise CameraDisconnectedError(f"{self.name}: not connected (the camera process was stopped); reconnect")
            try:
                self.outbox.send((op, args))
                ready, why = self._wait(timeout, abort, grace_s)
                reply = self.inbox.recv() if ready else None
            except (EOFError, OSError, BrokenPipeError):
                self._kill()
                raise CameraDisconnectedError(f"{self.name}: the camera process ended during {op}") from None
            if reply is None:
                self._kill()
                raise CameraTimeoutError(f"{self.name}: {op} {why}; the camera process was killed")
        if reply[0] == "ok":
            return reply[1]
        if reply[0] == "gp":
            raise GphotoError(reply[1], reply[2])
        raise CameraError(f"{self.name}: {op} failed in the camera process: {reply[1]}: {reply[2]}")

    def _wait(self, timeout: float | None, abort: threading.Event | None, grace_s: float) -> tuple[bool, str]:
        """Wait for the worker's answer: (ready, why not)."""
        if abort is None:
            ready = self.inbox.poll(timeout)
            return ready, "" if ready else f"did not answer within {timeout:.3g} s"
        deadline = None if timeout is None else time.monotonic() + timeout
        give_up = None
        while True:
            now = time.monotonic()
            if abort.is_set() and give_up is None:
                give_up = now + grace_s
            ends = [t for t in (deadline, give_up) if t is not None]
            if self.inbox.poll(max(0.0, min([now + STOP_POLL_S, *ends]) - now)):
                return True, ""
            now = time.monotonic()
            if give_up is not None and now >= give_up:
                return False, f"was given up {grace_s:g} s after the run was asked to stop (the run is stopping)"
            if deadline is not None and now >= deadline:
                return False, f"did not answer within {timeout:.3g} s"

    def _kill(self) -> None:
        self.dead = True
        if self.proc.poll() is None:
            self.proc.kill()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:  # pragma: no cover - a process in uninterruptible sleep
            pass
        for c in (self.inbox, self.outbox):
            c.close()

    def stop(self, timeout: float = 5.0) -> None:
        """Release the camera and end the worker (killed when it does not end in ``timeout`` s)."""
        if self.dead:
            return
        with self.lock:
            try:
                self.outbox.send(None)
                self.proc.wait(timeout)
            except (OSError, subprocess.TimeoutExpired):
                pass
            self._kill()


def list_cameras(serials: bool = False, timeout: float = 30.0) -> list[tuple[str, ...]]:
    """Detected cameras as (model, port) pairs, or (model, port, serial) with ``serials``
    (each camera is opened briefly to read it; "" when it reports none or is busy).

    Parameters
    ----------
    serials : bool
        Also read each camera's serial number.
    timeout : float
        Longest wait for libgphoto2, s.

    Returns
    -------
    list of tuple
        One tuple per detected camera.
    """
    worker = _Worker("gphoto2 detect")
    try:
        found = [tuple(x) for x in worker.call("detect", timeout=timeout)]
        if not serials:
            return found
        out: list[tuple[str, ...]] = []
        for model, port in found:
            try:
                worker.call("open", model, port, timeout=timeout)
                serial = _serial_text(worker.call("read", ALIASES["serialnumber"], timeout=timeout))
                worker.call("exit", timeout=timeout)
            except (GphotoError, CameraError):
                serial = ""
            out.append((model, port, serial))
        return out
    except GphotoError as err:
        raise classify_gphoto2_error(err, "autodetect") from None
    finally:
        worker.stop()


def _serial_text(value) -> str:
    return str(value or "").strip()


def choose_camera(
    found: Sequence[tuple[str, str]],
    *,
    model: str | None = None,
    port: str | None = None,
    serial: str | None = None,
    serial_of: Callable[[str, str], str] | None = None,
    prefer_port: str | None = None,
) -> tuple[str, str, str]:
    """Pick one detected camera: by serial number when one is wanted, else by model and port.

    Parameters
    ----------
    found : sequence of (model, port)
        Detected cameras.
    model : str, optional
        Text the model must contain (case-insensitive).
    port : str, optional
        The port it must be on (``usb:001,004``); None accepts any port (a re-plugged camera
        comes back on a new one).
    serial : str, optional
        The serial number it must report.
    serial_of : callable, optional
        ``(model, port) -> serial``: opens a candidate to read its serial (needed with ``serial``).
    prefer_port : str, optional
        Try the camera at this port first (the port it was on before).

    Returns
    -------
    (model, port, serial)
        The chosen camera; its serial is "" when it was not read.

    Raises
    ------
    CameraGoneError
        No camera matches.
    InputError
        Several cameras match and nothing tells them apart.
    """
    sel = [(m, p) for m, p in found if (not model or model.lower() in m.lower()) and (not port or p == port)]
    sel.sort(key=lambda mp: mp[1] != prefer_port)
    want = " ".join(
        x for x in (model and f"model {model!r}", port and f"port {port}", serial and f"serial {serial!r}") if x
    )
    listing = ", ".join(f"{m} at {p}" for m, p in found) or "none"
    if not sel:
        raise CameraGoneError(f"no camera {want or 'detected'} (found: {listing})")
    if serial:
        if serial_of is None:
            raise ValueError("choose_camera: serial given without serial_of")
        seen = []
        for m, p in sel:
            s = serial_of(m, p)
            if s == serial:
                return m, p, s
            seen.append(f"{m} at {p} (serial {s or 'unknown'})")
        raise CameraGoneError(f"no camera {want} (found: {', '.join(seen)})")
    if len(sel) > 1 and not port and not (prefer_port and sel[0][1] == prefer_port):
        raise InputError(
            "several cameras match: " + ", ".join(f"{m} at {p}" for m, p in sel) + "; choose one with serial or port"
        )
    return sel[0][0], sel[0][1], ""


def free_images(storages: Sequence[dict[str, Any]]) -> int | None:
    """Free images on the camera's writable storages, from the fields the camera marks valid.

    Parameters
    ----------
    storages : sequence of dict
        One per storage, with ``freeimages`` / ``freekbytes`` / ``access`` only when valid.

    Returns
    -------
    int or None
        The total free images; None when unknown (no storage reports a count, or one reports
        free bytes but no count): only a known 0 means full.
    """
    total, known = 0, False
    for s in storages:
        if s.get("access", "rw") != "rw":
            continue
        if "freeimages" in s:
            total += max(0, int(s["freeimages"]))
            known = True
        elif s.get("freekbytes", 0) > 0:
            return None
    return total if known else None


# ====================================================================== the camera
class Gphoto2Camera:
    """A camera driven through libgphoto2, in a worker process.

    Parameters
    ----------
    model : str, optional
        Choose the camera whose model contains this text (case-insensitive).
    port : str, optional
        Choose the camera at this port (``usb:001,004``) when connecting first.
    serial : str, optional
        Choose the camera with this serial number (checked at every connection).
    delete_after_download : bool
        Delete each frame from the camera after it was downloaded.
    long_exposure_s : float
        Exposures at or above this use trigger + wait_for_event instead of ``capture``, s.
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
    reconnect_deadline_s : float
        How long :meth:`reconnect` keeps looking for the camera, s.
    reconnect_backoff_s : float
        First wait between reconnect attempts, s (doubles, at most 10 s).
    """

    backend = "gphoto2"
    #: makes the worker that owns the camera (name -> object with call/stop/pid/dead); tests
    #: substitute a simulated body here
    worker_factory: Callable[[str], Any] = _Worker

    def __init__(
        self,
        model: str | None = None,
        port: str | None = None,
        *,
        serial: str | None = None,
        delete_after_download: bool = True,
        long_exposure_s: float = 1.0,
        call_timeout_s: float = 30.0,
        busy_retries: int = 5,
        backoff_s: float = 0.2,
        pair_wait_s: float = 0.2,
        settings: dict[str, Any] | None = None,
        reconnect_deadline_s: float = 60.0,
        reconnect_backoff_s: float = 0.5,
    ):
        self.want_model = model
        self.want_port = port
        self.want_serial = serial or None
        self.delete_after_download = delete_after_download
        self.long_exposure_s = long_exposure_s
        self.call_timeout_s = call_timeout_s
        self.busy_retries = busy_retries
        self.backoff_s = backoff_s
        self.pair_wait_s = pair_wait_s
        self.reconnect_deadline_s = reconnect_deadline_s
        self.reconnect_backoff_s = reconnect_backoff_s
        self.initial_settings = dict(settings or {})
        self.applied: dict[str, str] = {}
        self.events: list[tuple[str, str]] = []
        self.busy_count = 0
        self.reconnects = 0
        self.reconnect_attempts = 0
        self.bulb_open_s: float | None = None
        #: tests: libgphoto2 codes to raise instead of the next calls; an int fails the next
        #: call, an (op, code) pair the next call of that worker op
        self._inject: list = []
        self._worker: Any = None
        self._stop: threading.Event | None = None
        self._bulb_time: float | None = None
        self._t: float | None = None
        self._labels: dict[float, str] = {}
        self._bulb_label: str | None = None
        self._stems: set[str] = set()  # name stems of the previous frame's files (late partners)
        self.identity = CameraIdentity("gphoto2", model or "", serial or "", port or "")
        try:
            self._connect(port=port, model=model, serial=self.want_serial, prefer_port=port)
            for name, value in self.initial_settings.items():
                self.set_setting(name, value)
        except BaseException:
            self.close()  # a failed constructor leaves nothing claimed
            raise

    # ------------------------------------------------------------------ connection
    @property
    def connected(self) -> bool:
        return self._worker is not None and not self._worker.dead

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker that owns the camera (None when disconnected)."""
        return self._worker.pid if self.connected else None

    def _connect(self, *, port: str | None, model: str | None, serial: str | None, prefer_port: str | None) -> None:
        """Start a worker, find the camera (by serial when known), open it and read its
        exposure times; on failure the worker is stopped and the camera stays disconnected."""
        self._worker = self.worker_factory(f"camera {model or ''}".strip())
        try:
            found = [tuple(x) for x in self._call("detect", during="autodetect")]
            opened: list[str] = []

            def serial_of(m: str, p: str) -> str:
                if opened:
                    self._call("exit", during="close")
                self._call("open", m, p, during="connect")
                opened[:] = [p]
                return _serial_text(self._call("read", ALIASES["serialnumber"], during="get serialnumber"))

            m, p, s = choose_camera(
                found, model=model, port=port, serial=serial, serial_of=serial_of, prefer_port=prefer_port
            )
            if opened != [p]:
                if opened:
                    self._call("exit", during="close")
                self._call("open", m, p, during="connect")
                s = _serial_text(self._call("read", ALIASES["serialnumber"], during="get serialnumber"))
            old = self.identity.port
            self.identity = CameraIdentity("gphoto2", m, s, p)
            self._stems = set()  # a new connection may restart the camera's file numbering
            if old and old != p:
                self.events.append(("port_changed", f"{old} -> {p}"))
            self._read_exposures()
        except BaseException:
            self._drop_worker()
            raise

    def _drop_worker(self) -> None:
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.stop(timeout=2.0)

    def reconnect(self) -> None:
        """Stop the worker (killed if it hangs), then look for the camera again until
        ``reconnect_deadline_s``: by serial number when it reported one (else by model), on any
        port, polling with exponential backoff; then re-apply the settings.

        Raises
        ------
        CameraError
            The camera was not found again in time (its kind says whether the session may
            retry). The camera stays disconnected (every call raises a ``reconnect`` fault)
            until a later reconnect succeeds.
        """
        self.reconnects += 1
        old_port = self.identity.port
        self._drop_worker()
        deadline = time.monotonic() + self.reconnect_deadline_s
        delay = self.reconnect_backoff_s
        reset = False
        while True:
            self.reconnect_attempts += 1
            try:
                if not reset and old_port:
                    reset = True
                    self._reset_port(old_port)
                self._connect(
                    port=None, model=self.identity.model, serial=self.identity.serial or None, prefer_port=old_port
                )
                break
            except (CameraError, InputError) as err:
                self.events.append(("reconnect_failed", f"{type(err).__name__}: {err}"))
                if self._stop is not None and self._stop.is_set():  # the run is stopping: no more polling
                    raise CameraDisconnectedError(f"reconnect given up, the run is stopping ({err})") from None
                left = deadline - time.monotonic()
                if left <= 0:  # tried at the deadline too: give up
                    if isinstance(err, InputError):
                        raise CameraGoneError(f"reconnect: {err}") from None
                    raise
                time.sleep(min(delay, left))  # the last wait ends at the deadline, then one more try
                delay = min(2 * delay, 10.0)
        self.events.append(("reconnected", self.identity.port))
        for name, value in self.applied.items():
            if name != "shutterspeed":
                self.set_setting(name, value)
        if self._t is not None:
            self.set_exposure(self._t)

    def _reset_port(self, port: str) -> None:
        """USB reset of the old port in a short-lived worker (best effort)."""
        worker = self.worker_factory("port reset")
        try:
            worker.call("reset_port", port, timeout=10.0)
            self.events.append(("port_reset", port))
        except Exception as err:  # a port that cannot be reset may still reopen
            self.events.append(("port_reset_failed", f"{type(err).__name__}: {err}"))
        finally:
            worker.stop(timeout=2.0)

    def close(self) -> None:
        """Release the camera and end its worker process."""
        self._drop_worker()

    def watch_stop(self, stop: threading.Event | None) -> None:
        """Give up a call in progress :data:`STOP_GRACE_S` after ``stop`` is set (SIGTERM,
        :func:`hdrcap.acquire.capture.session.stop_on_signals`) instead of waiting for its
        timeout: the worker is killed (the kernel releases the USB claim with it) and the call
        fails as a timeout; a stopping session then neither retries nor reconnects, and a
        reconnect in progress stops polling. None: no stop to watch."""
        self._stop = stop

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ low level
    def _call(self, op: str, *args, during: str = "", timeout: float | None = None) -> Any:
        """Run a worker op; retry busy with backoff; map libgphoto2 errors to camera errors."""
        timeout = self.call_timeout_s if timeout is None else timeout
        during = during or op
        for attempt in range(self.busy_retries + 1):
            worker = self._worker
            if worker is None:
                raise CameraDisconnectedError(f"{during}: camera not connected (a reconnect failed); reconnect")
            try:
                self._injected(op)
                if self._stop is None:
                    return worker.call(op, *args, timeout=timeout)
                return worker.call(op, *args, timeout=timeout, abort=self._stop)
            except GphotoError as err:
                mapped = classify_gphoto2_error(err, during)
                if isinstance(mapped, CameraBusyError):
                    self.busy_count += 1
                    if attempt < self.busy_retries:
                        time.sleep(self.backoff_s * 2**attempt)
                        continue
                raise mapped from None
        raise AssertionError("unreachable")

    def _injected(self, op: str) -> None:
        for k, item in enumerate(self._inject):
            if isinstance(item, tuple) and item[0] != op:
                continue
            del self._inject[k]
            raise GphotoError(item[1] if isinstance(item, tuple) else item, "injected")

    def tree_reads(self) -> dict[str, int]:
        """Configuration reads by the current worker: full trees, single widgets, writes."""
        return dict(self._call("stats")) if self.connected else {}

    def _describe(self, name: str) -> dict | None:
        """A setting as plain data (name, type, value, choices) from the cached tree."""
        return self._call("describe", ALIASES.get(name, ()) + (name,), during=f"get {name}")

    # ------------------------------------------------------------------ settings
    def get_setting(self, name: str, fresh: bool = False) -> str | None:
        """A setting's value (generic name or the camera's), None if absent.

        Parameters
        ----------
        name : str
            Generic or camera name.
        fresh : bool
            Read it from the camera instead of the cached tree (values that change by
            themselves: temperature, a dial turned by hand).
        """
        names = ALIASES.get(name, ()) + (name,)
        if fresh:
            v = self._call("read", names, during=f"get {name}")
            return None if v is None else str(v)
        d = self._describe(name)
        return None if d is None else str(d["value"])

    def set_setting(self, name: str, value: Any) -> str:
        """Set a setting, read it back and return (and record) the applied value.

        For a choice setting whose value is not offered, the nearest numeric choice is used
        (the camera would do it silently); a value that matches nothing raises InputError.
        Only this widget is written and read back.
        """
        d = self._describe(name)
        if d is None:
            raise InputError(f"camera {self.identity.model} has no setting {name!r}")
        real, choices = d["name"], d["choices"]
        val = value
        if choices and str(value) not in choices:
            val = _nearest_choice(value, choices)
            if val is None:
                raise InputError(f"setting {name!r}: {value!r} is not one of {', '.join(choices[:12])}")
        val = _typed(val, d["type"])
        applied = str(self._call("set", real, val, during=f"set {real}"))
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
        """Timed shutter speeds, s, ascending (bulb excluded)."""
        return sorted(self._labels)

    def bulb_range(self) -> tuple[float, float] | None:
        """Times (s) reachable by bulb: above 1.2 x the longest timed speed up to
        :data:`~acquire.camera.BULB_MAX_S`; None when the camera has no bulb speed or no bulb
        release widget."""
        if not self._labels or not self._bulb_label or self._describe("bulb") is None:
            return None
        return max(self._labels) * 1.2, BULB_MAX_S

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
        if self._bulb_label and t > longest * 1.2:
            self.set_setting("shutterspeed", self._bulb_label)
            self._t, self._bulb_time = t, t
            return t
        target = nearest_allowed(t, list(self._labels))
        applied = self.set_setting("shutterspeed", self._labels[target])
        seconds = parse_exposure_label(applied)
        if seconds is None:
            raise CameraError(f"camera reports shutter speed {applied!r} after setting {self._labels[target]!r}")
        self._t, self._bulb_time = t, None  # re-applied after a reconnect
        return seconds

    # ------------------------------------------------------------------ light, temperature
    def cover(self) -> None:
        """A tethered camera cannot block its own light; the session's light blocker does it."""

    def uncover(self) -> None:
        """See :meth:`cover`."""

    def temperature(self) -> float | None:
        """Sensor (or camera) temperature read fresh from the camera, degrees C; None if unknown."""
        try:
            v = self.get_setting("temperature", fresh=True)
        except CameraError:
            return None
        if v is None:
            return None
        try:
            return float(str(v).replace("°C", "").replace("C", "").strip())
        except ValueError:
            return None

    def preflight(self, *, enforce: bool = False, iso: int | None = None) -> list[dict[str, Any]]:
        """Check the settings an HDR capture needs (:data:`PREFLIGHT`): manual exposure program,
        manual focus, a RAW image format, a fixed ISO (``iso`` when given), no auto ISO, no
        long-exposure noise reduction. Nothing is changed unless ``enforce``.

        Parameters
        ----------
        enforce : bool
            Set each wrong setting to an allowed value (read back).
        iso : int, optional
            The ISO the job asks for.

        Returns
        -------
        list of dict
            One finding per setting the camera has: ``setting``, ``widget``, ``value``, ``want``,
            ``ok`` and ``changed`` (the value set, or None).

        Raises
        ------
        InputError
            A setting is wrong and ``enforce`` is off, or it cannot be changed (a mode dial,
            a read-only widget, no allowed value); the message names every such setting.
        """
        findings, bad = [], []
        for name, good, want, why in PREFLIGHT:
            d = self._describe(name)
            if d is None:
                continue
            value = str(d["value"])
            ok = good(value)
            if name == "iso" and iso is not None and ok:
                ok, want = _is_fixed_iso(value) and int(float(value)) == int(iso), f"ISO {iso}"
            f = {"setting": name, "widget": d["name"], "value": value, "want": want, "ok": ok, "changed": None}
            if not ok and enforce:
                target = (
                    str(iso) if name == "iso" and iso is not None else next((c for c in d["choices"] if good(c)), None)
                )
                if target is not None and not d["readonly"]:
                    applied = self.set_setting(name, target)
                    f.update(
                        changed=applied,
                        ok=good(applied) and (name != "iso" or iso is None or int(float(applied)) == int(iso)),
                    )
            findings.append(f)
            if not f["ok"]:
                bad.append(f"{d['name']} is {value!r}, needs {want} ({why})")
        if bad:
            hint = "" if enforce else "; set it on the camera or add enforce = true to the job's [camera]"
            raise InputError(f"camera {self.identity.model}: " + "; ".join(bad) + hint)
        return findings

    def storage_free_images(self) -> int | None:
        """Free images on the writable storages (:func:`free_images`), None when unknown
        (only meaningful when the camera captures to its card)."""
        try:
            storages = self._call("storage", during="storageinfo")
        except (CameraBusyError, CameraDisconnectedError, CameraTimeoutError, CameraGoneError):
            raise
        except CameraError:  # storage information not supported
            return None
        return free_images(storages)

    # ------------------------------------------------------------------ capture
    def capture(
        self, dest: str | os.PathLike[str], *, dark: bool = False, timeout: float | None = None
    ) -> CaptureResult:
        """Expose, download to ``dest`` (suffix taken from the camera's file) and delete the
        file from the camera when ``delete_after_download``."""
        dest = Path(dest)
        t = self._bulb_time or self._t or 0.0
        wait = timeout or (t + self.call_timeout_s)
        target = (self.applied.get("capturetarget") or self.get_setting("capturetarget") or "").lower()
        if "ram" not in target and self.storage_free_images() == 0:
            raise StorageFullError("camera storage is full (0 free images); free the card and resume")
        stale = self._drain_stale()
        if self._bulb_time is not None:
            files = self._capture_bulb(self._bulb_time, wait)
        elif t >= self.long_exposure_s:
            self._call("trigger", during="capture (trigger)")
            files = self._wait_files(wait, stale)
        else:
            first = tuple(self._call("capture", during="capture", timeout=wait))
            if first in stale or _stem(first[1]) in self._stems:
                self.events.append(("stale_file", "/".join(first)))
                files = self._wait_files(wait, stale | {first})
            else:
                files = [first] + self._partners(first, wait)
        if not files:
            raise CameraTimeoutError(f"no file from the camera within {wait:.0f} s")
        folder, name = _prefer_raw(files)
        out = self.download(f"{folder}/{name}", dest.with_suffix(Path(name).suffix.lower() or dest.suffix), wait)
        self._stems = {_stem(na) for _fo, na in files}
        if self.delete_after_download:
            self._delete_from_camera(files)
        bulb = self._bulb_time is not None
        applied = (
            self.bulb_open_s
            if bulb
            else parse_exposure_label(self.applied.get("shutterspeed", "") or self.get_setting("shutterspeed") or "")
        )
        settings = dict(self.applied, **({"bulb_open_s": f"{self.bulb_open_s:.4f}"} if bulb else {}))
        return CaptureResult(
            path=out,
            requested_exposure_s=t,
            applied_exposure_s=applied or t,
            dark=dark,
            settings=settings,
            camera_file=f"{folder}/{name}",
            temperature_c=self.temperature(),
            bulb=bulb,
        )

    def _delete_from_camera(self, files: Sequence[tuple[str, str]]) -> None:
        """Delete the frame's files from the camera after a good download. A failure there
        (busy, a hang, a read-only card) costs the frame nothing: it is a ``delete_failed``
        warning in :attr:`events` and on the ``hdrcap`` logger, and the file stays on the card
        (a card that fills up stops a later capture with :class:`StorageFullError`)."""
        for fo, na in files:
            try:
                self._call("delete", fo, na, during=f"delete {na}")
            except CameraError as err:
                self.events.append(("delete_failed", f"{fo}/{na}: {err}"))
                _LOG.warning(
                    "camera: could not delete %s/%s after the download (%s); it stays on the card", fo, na, err
                )

    def download(self, camera_path: str, dest: str | os.PathLike[str], timeout: float | None = None) -> Path:
        """Download a file already on the camera (``/store_00010001/DCIM/x.NEF``) to ``dest``."""
        folder, name = camera_path.rsplit("/", 1)
        dest = Path(dest)
        if dest.exists():
            raise FileExistsError(f"{dest}: exists")
        tmp = dest.with_name(f".{dest.name}.download")
        try:
            self._call("download", folder or "/", name, str(tmp), during=f"download {name}", timeout=timeout)
            os.replace(tmp, dest)
        finally:
            if tmp.exists():
                tmp.unlink()
        return dest

    def list_files(self, folder: str = "/") -> list[str]:
        """Every file on the camera under ``folder`` (recursive)."""
        return self._call("list_files", folder, during="list files")

    def _capture_bulb(self, t: float, wait: float) -> list[tuple[str, str]]:
        """Press, sleep ``t`` s and release in the worker (one request: no other camera call
        inside the open interval); the open time is measured from the end of the press call
        to the start of the release call (both edges: :attr:`events`)."""
        d = self._describe("bulb")
        if d is None:
            raise InputError(f"camera {self.identity.model} has no bulb release widget (bulb, eosremoterelease)")
        press, release = _bulb_values(d)
        self.bulb_open_s = None
        edges = self._call("bulb", d["name"], press, release, float(t), during="bulb exposure", timeout=t + wait)
        self.bulb_open_s = edges["release_start"] - edges["press_end"]
        slack = (edges["press_end"] - edges["press_start"]) + (edges["release_end"] - edges["release_start"])
        self.events.append(("bulb", f"open {self.bulb_open_s:.4f} s (press/release calls {slack:.4f} s)"))
        return self._wait_files(wait, set())

    def _drain_stale(self) -> set[tuple[str, str]]:
        """Consume the events pending before a release; the files they announce are stale."""
        stale = set()
        for kind, data in self._call("drain", 10, during="drain events"):
            if kind == "file":
                stale.add(tuple(data))
                self.events.append(("stale_file", "/".join(data)))
        return stale

    def _is_new(self, f: tuple[str, str], stale: set) -> bool:
        return f not in stale and _stem(f[1]) not in self._stems

    def _wait_files(self, wait: float, stale: set) -> list[tuple[str, str]]:
        """Wait for GP_EVENT_FILE_ADDED of a new file (then a little more for its partner)."""
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            kind, data = self._next_event(500)
            if kind == "file":
                f = tuple(data)
                if self._is_new(f, stale):
                    return [f] + self._partners(f, deadline - time.monotonic())
                self.events.append(("late_partner" if _stem(f[1]) in self._stems else "stale_file", "/".join(f)))
        return []

    def _partners(self, first: tuple[str, str], wait: float) -> list[tuple[str, str]]:
        """Files with the stem of ``first`` (RAW+JPEG): listened for ``pair_wait_s``; when
        ``first`` is not raw but the image format includes raw, up to ``wait`` s for the raw."""
        need_raw = not _is_raw(first[1]) and self._format_has_raw()
        span = max(self.pair_wait_s, wait if need_raw else 0.0)
        if span <= 0:
            return []
        end = time.monotonic() + span
        files = []
        while time.monotonic() < end:
            kind, data = self._next_event(50)
            if kind == "timeout" and not need_raw:
                break
            if kind == "file":
                f = tuple(data)
                if _stem(f[1]) == _stem(first[1]):
                    files.append(f)
                    need_raw = need_raw and not _is_raw(f[1])
                else:
                    self.events.append(("unmatched_file", "/".join(f)))
        return files

    def _format_has_raw(self) -> bool:
        """Whether the camera's image format setting includes a raw file (RAW, NEF+Fine...)."""
        return _has_raw(self.applied.get("imageformat") or self.get_setting("imageformat") or "")

    def _next_event(self, ms: int) -> tuple[str, Any]:
        kind, data = self._call("event", ms, during="wait_for_event", timeout=ms / 1000 + 10)
        if kind == "file":
            self.events.append(("file_added", "/".join(data)))
        elif kind == "complete":
            self.events.append(("capture_complete", ""))
        elif kind == "folder":
            self.events.append(("folder_added", "/".join(data)))
        elif kind == "other":
            self.events.append(("other", data))
        return kind, data


def _stem(name: str) -> str:
    return Path(name).stem.lower()


def _typed(value: Any, kind: str) -> Any:
    if kind == "toggle":
        return int(value)
    if kind == "range":
        return float(value)
    return str(value)


def _bulb_values(d: dict) -> tuple[Any, Any]:
    """Press and release values of a bulb widget: 1/0 for a toggle, Canon's
    ``Press Full``/``Release Full`` (or the nearest offered) for ``eosremoterelease``."""
    if d["type"] == "toggle":
        return 1, 0
    choices = d["choices"]
    press = next((c for c in choices if c.lower() == "press full"), None) or next(
        (c for c in choices if c.lower().startswith("press")), None
    )
    release = next((c for c in choices if c.lower() == "release full"), None) or next(
        (c for c in choices if c.lower().startswith("release")), None
    )
    if press is None or release is None:
        raise InputError(f"bulb widget {d['name']!r} offers no press/release values ({', '.join(choices)})")
    return press, release


def _is_raw(name: str) -> bool:
    return Path(name).suffix.lower() in RAW_SUFFIXES


def _prefer_raw(files: list[tuple[str, str]]) -> tuple[str, str]:
    for folder, name in files:
        if _is_raw(name):
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
