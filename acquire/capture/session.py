"""Capture sessions: run a plan of exposures (with dark frames and calibration series) on a
:class:`acquire.camera.Camera`, survive its faults, and leave a verified, hashed, resumable
record of every frame.

Guarantees
----------
* Every planned frame ends up in the run folder exactly once, under a name derived from its
  unique plan key (``frames/0007_light_0.004s.dng``); a file is never overwritten.
* A frame is recorded in the manifest only after it was verified: it opens with
  :func:`pipeline.io.raw.read_frame`, its size is the camera's and the exposure time in the file
  is the one the camera reported applying. Its sha256 is recorded. A camera that applies
  another exposure time than the one it was given (beyond its own rounding) stops the run.
* Busy cameras are retried with exponential backoff; disconnects and hangs cause a reconnect
  (a new camera object) and a retry; bad files are captured again; card full and camera gone
  stop the session with a one-line message. The manifest is left consistent in every case.
* ``resume=True`` continues an interrupted run: frames in the manifest are kept (after their
  hash is checked), a frame whose file landed but was not yet recorded is verified and
  adopted, unfinished downloads are discarded, and only the missing frames are captured; those
  missing under recorded frames (a voided dark frame) first, before anything is merged again.
* A lock on the run folder and one on the camera stop two sessions from colliding; the lock
  files are removed again.
* Each verified light frame is handed to the merge (``pipeline.merge.accumulator.MergeAccumulator``) as
  it lands, with the dark strategy the plan gives its exposure time.
* A run that stops logs a ``stop`` event with its exit status, after unblocking the light (or
  recording that it could not); a stop (SIGTERM) also ends a cover/uncover command and, on a
  camera that can (``watch_stop``), a hung camera call.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

import numpy as np

from hdrcap.acquire.camera import Camera, CameraError, CorruptFrameError, fault_kind, nearest_allowed
from hdrcap.acquire.capture.manifest import EventLog, Manifest, jsonable, utc_now
from hdrcap.pipeline.compat import CameraProfile, CompatibilityError, check_compatible
from hdrcap.pipeline.errors import HdrcapError, InputError
from hdrcap.pipeline.merge.darks import DarkResolver
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.times import ExposureMap, find_exposure, same_bulb_exposure, same_exposure

if TYPE_CHECKING:
    from hdrcap.acquire.camera import CaptureResult
    from hdrcap.pipeline.io.raw import RawFrame
    from hdrcap.pipeline.params import Calibration, SensorParams
    from hdrcap.pipeline.result import HdrResult

__all__ = [
    "FrameSpec",
    "CapturePlan",
    "RetryPolicy",
    "LightBlocker",
    "SessionError",
    "RunConflictError",
    "LocalIOError",
    "VerificationError",
    "RunInterrupted",
    "EXIT_CODES",
    "SessionResult",
    "CaptureSession",
    "StreamingMerge",
    "frame_stem",
    "lock_dir",
    "stop_on_signals",
    "hold_run_locks",
    "run_lock_files",
    "held_locks",
    "lock_is_held",
    "SESSION_LOCK_NAME",
    "PathLock",
    "run_command",
    "check_applied_exposure",
    "watch_stop",
    "emit_stop",
]

_log = logging.getLogger("hdrcap.run")

#: Frame kinds; the first two feed the HDR merge, the rest are calibration series.
LIGHT_KINDS = ("light", "flat", "saturation")
DARK_KINDS = ("dark", "bias", "darkseries")
KINDS = ("light", "dark", "bias", "flat", "saturation", "darkseries")


#: Exit statuses of ``hdrcap run``/``capture`` (documented in docs/acquisition.md): what stopped a run.
EXIT_CODES = {
    0: "done (or --resume on a finished run: nothing to do)",
    2: "bad input or configuration (job file, options, calibration of another camera); fix it first",
    3: "an output file exists; use --force or another run folder",
    4: "the camera stopped the run (card full, camera gone, gave up retrying); resumable with --resume",
    5: "conflict: the run folder or camera is locked by another session, or holds another run",
    6: "local I/O error (disk full, permissions, read-only file system); free space, then --resume",
    7: "verification failed (a dark frame saw light, a file does not match the plan); fix it, then --resume",
    130: "interrupted (SIGINT); resumable with --resume",
    143: "terminated (SIGTERM); resumable with --resume",
}


class SessionError(HdrcapError):
    """The session stopped on the camera's side (camera gone, card full, gave up retrying):
    resumable with ``--resume``."""

    exit_code = 4


class RunConflictError(SessionError):
    """The run folder or the camera is locked by another session, or the folder holds another run."""

    exit_code = 5


class LocalIOError(SessionError):
    """Our side failed: disk full, permissions, a read-only or vanished file system."""

    exit_code = 6


class VerificationError(SessionError):
    """A frame or the run folder does not match what was planned (light not blocked, wrong file)."""

    exit_code = 7


class RunInterrupted(SessionError):
    """SIGINT or SIGTERM stopped the run between two frames; the run folder is consistent and
    resumable. ``exit_code`` is 128 + the signal number."""

    def __init__(self, message: str, signum: int = 2):
        super().__init__(message)
        self.exit_code = 128 + int(signum)


@dataclass(frozen=True)
class FrameSpec:
    """One planned frame.

    Attributes
    ----------
    key : str
        Unique in the plan; names the file.
    kind : str
        ``light``, ``dark`` (dark frames for the merge), ``bias``, ``flat``, ``saturation`` or
        ``darkseries`` (calibration series).
    exposure_s : float
        Requested exposure time, s (already one of the camera's allowed times).
    job_exposure_s : float or None
        The time the job (or the caller) asked for when it is not one of the camera's and was
        snapped to ``exposure_s``, s; None when it was one of them.
    """

    key: str
    kind: str
    exposure_s: float
    job_exposure_s: float | None = None

    @property
    def dark(self) -> bool:
        return self.kind in DARK_KINDS


def frame_stem(index: int, spec: FrameSpec) -> str:
    return f"{index:04d}_{spec.kind}_{spec.exposure_s:.6g}s"


def _strategies_by_time(times: list[float], dark_strategy: str | Sequence[str]) -> ExposureMap[DarkStrategy]:
    """Exposure time (s) -> its dark strategy, from one strategy for all or one per time."""
    per = [dark_strategy] * len(times) if isinstance(dark_strategy, str) else list(dark_strategy)
    if len(per) != len(times):
        raise InputError(f"{len(per)} dark strategies for {len(times)} exposure times")
    by_time: ExposureMap[DarkStrategy] = ExposureMap()
    for t, s in zip(times, per):
        s = _strategy(s)
        if by_time.setdefault(t, s) is not s:
            raise InputError(f"exposure {t:g} s has two dark strategies ({by_time[t]} and {s})")
    return by_time


def _frame_specs(frames: list[tuple[str, float, int]], asked: ExposureMap[float]) -> tuple[FrameSpec, ...]:
    """FrameSpecs of (kind, exposure time, repetition) in order, keyed ``kind-time-n``;
    ``asked``: the time given for each snapped time."""
    out: list[FrameSpec] = []
    seen: dict[str, int] = {}
    for kind, t, _j in frames:
        base = f"{kind}-{t:.6g}"
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.append(FrameSpec(key=f"{base}-{n}", kind=kind, exposure_s=t, job_exposure_s=asked.get(t)))
    return tuple(out)


def _strategy(value: str) -> DarkStrategy:
    try:
        return DarkStrategy(value)
    except ValueError:
        raise InputError(f"dark strategy must be matched, master or model, got {value!r}") from None


#: Camera events (``camera.events`` kinds) that are not copied into ``events.jsonl``: every
#: capture has them.
ROUTINE_CAMERA_EVENTS = frozenset({"file_added", "capture_complete", "folder_added", "other"})

#: Dark frames captured per exposure time for each dark strategy (master: ``n_dark``).
_DARK_FRAMES = {DarkStrategy.MATCHED: 1, DarkStrategy.MODEL: 0}


@dataclass(frozen=True)
class CapturePlan:
    """The frames of a run in capture order, and how dark frames are used by the merge.

    The dark strategy of an exposure time is ``matched`` (one dark frame of that time),
    ``master`` (``n_dark`` dark frames of that time averaged, or a master dark of the dark
    library for the ``library_times``) or ``model`` (no dark frame: bias level and calibrated
    dark current). ``dark_strategy`` is the strategy of every exposure time, or ``"mixed"``;
    then ``time_strategies`` holds (time, strategy) pairs for every exposure time.
    """

    frames: tuple[FrameSpec, ...]
    dark_strategy: str = DarkStrategy.MATCHED.value
    n_dark: int = 1
    library_times: tuple[float, ...] = ()
    time_strategies: tuple[tuple[float, str], ...] = ()

    @classmethod
    def bracket(
        cls,
        times: Sequence[float],
        allowed: Sequence[float] | None = None,
        dark_strategy: str | Sequence[str] = DarkStrategy.MATCHED,
        n_dark: int = 1,
        repeats: int = 1,
        series: Sequence[dict[str, Any]] = (),
        library_times: Sequence[float] = (),
    ) -> CapturePlan:
        """A bracket of ``times`` (each snapped to the nearest ``allowed`` time), ``repeats``
        frames per time, dark frames per dark strategy and calibration ``series`` (dicts with
        ``kind``, ``times``, ``count``). ``dark_strategy`` is one strategy for all exposures or
        one per entry of ``times`` (a planner's per-exposure choice). Frames needing the light
        blocked come first, so the light is blocked once; a time that was snapped keeps the
        time given as the frames' ``job_exposure_s``. ``library_times``: exposure times
        whose master dark comes from the dark library (no dark frames are captured for them;
        only ``master`` times qualify)."""
        asked: ExposureMap[float] = ExposureMap()

        def snap(t: float) -> float:
            got = nearest_allowed(float(t), allowed) if allowed else float(t)
            if not same_exposure(got, t):
                asked.setdefault(got, float(t))
            return got

        times = [snap(float(t)) for t in times]
        by_time = _strategies_by_time(times, dark_strategy)
        uniq = sorted(by_time)
        lib = [t for t in uniq if by_time[t] is DarkStrategy.MASTER and find_exposure(t, library_times) is not None]
        per_time = {**_DARK_FRAMES, DarkStrategy.MASTER: max(1, int(n_dark))}
        dark_frames = [("dark", t, j) for t in uniq if t not in lib for j in range(per_time[by_time[t]])]
        light_frames = [("light", t, j) for j in range(max(1, int(repeats))) for t in times]
        for sr in series:
            kind = sr["kind"]
            if kind not in KINDS[2:]:
                raise InputError(f"calibration series kind must be one of {', '.join(KINDS[2:])}, got {kind!r}")
            for t in sr["times"]:
                for j in range(int(sr.get("count", 1))):
                    (dark_frames if kind in DARK_KINDS else light_frames).append((kind, snap(float(t)), j))
        used = {_strategy(dark_strategy)} if isinstance(dark_strategy, str) else set(by_time.values())
        used = used or {DarkStrategy.MATCHED}
        uniform = used.pop().value if len(used) == 1 else "mixed"
        pairs = () if uniform != "mixed" else tuple((t, by_time[t].value) for t in uniq)
        master = DarkStrategy.MASTER in by_time.values() or uniform == DarkStrategy.MASTER
        return cls(
            frames=_frame_specs(dark_frames + light_frames, asked),
            dark_strategy=uniform,
            n_dark=max(1, int(n_dark)) if master else 1,
            library_times=tuple(lib),
            time_strategies=pairs,
        )

    def strategy_for(self, t: float) -> DarkStrategy:
        """The dark strategy of exposure time ``t`` (s)."""
        if not self.time_strategies:
            return DarkStrategy(self.dark_strategy)
        i = find_exposure(t, [pt for pt, _s in self.time_strategies])
        if i is None:
            raise SessionError(f"exposure {t:g} s is not in the plan")
        return DarkStrategy(self.time_strategies[i][1])

    def strategies(self) -> dict[float, DarkStrategy]:
        """Exposure time (s) -> dark strategy, for every exposure time of the light frames."""
        return {f.exposure_s: self.strategy_for(f.exposure_s) for f in self.frames if f.kind == "light"}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CapturePlan:
        """The plan recorded in a manifest (:meth:`to_dict`; also manifests written before
        per-exposure strategies)."""
        return cls(
            tuple(FrameSpec(**f) for f in d["frames"]),
            d["dark_strategy"],
            d["n_dark"],
            tuple(d.get("library_times", ())),
            tuple((float(t), str(s)) for t, s in d.get("time_strategies", ())),
        )

    def fingerprint(self) -> str:
        blob = json.dumps(
            [[f.key, f.kind, f.exposure_s] for f in self.frames]
            + [self.dark_strategy, self.n_dark]
            + ([list(self.library_times)] if self.library_times else [])
            + ([[list(p) for p in self.time_strategies]] if self.time_strategies else [])
        )
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "dark_strategy": self.dark_strategy,
            "n_dark": self.n_dark,
            "library_times": list(self.library_times),
            "frames": [asdict(f) for f in self.frames],
            "fingerprint": self.fingerprint(),
        }
        if self.time_strategies:
            out["time_strategies"] = [list(p) for p in self.time_strategies]
        return out


@dataclass(frozen=True)
class RetryPolicy:
    """How hard to try for each frame.

    Attributes
    ----------
    max_attempts : int
        Attempts per frame before the session gives up.
    backoff_s : float
        First wait after a busy/disconnect, s; doubles each time up to ``max_backoff_s``.
    max_backoff_s : float
        Longest wait, s.
    timeout_s : float or None
        Longest a capture may take beyond its exposure time, s (passed to the camera).
    """

    max_attempts: int = 12
    backoff_s: float = 0.5
    max_backoff_s: float = 30.0
    timeout_s: float | None = 60.0

    def wait(self, attempt: int) -> float:
        return min(self.max_backoff_s, self.backoff_s * 2 ** max(0, attempt - 1))


class LightBlocker:
    """Blocks the light for dark frames.

    ``method``: ``mock`` (the simulated camera covers itself), ``prompt`` (ask the person at
    the terminal and wait for Enter), ``command`` (run ``cover_command`` / ``uncover_command``
    with the shell, e.g. closing a shutter or switching the light source off; a non-zero exit
    stops the session) or ``none`` (the light is already blocked, e.g. a lens cap on).
    The camera's own :meth:`cover`/:meth:`uncover` are always called too.

    A command runs in a process group of its own: one that outlasts ``command_timeout_s``, or
    is still running when ``stop`` is set (SIGTERM/SIGINT), is killed with every process it
    started, and the session stops (:class:`SessionError`, or :class:`RunInterrupted` for a
    stop).
    """

    def __init__(
        self,
        method: str = "mock",
        cover_command: str | None = None,
        uncover_command: str | None = None,
        prompt: Callable[[str], Any] | None = None,
        settle_s: float = 0.0,
        command_timeout_s: float = 60.0,
        stop: threading.Event | None = None,
    ) -> None:
        if method not in ("mock", "prompt", "command", "none"):
            raise InputError(f"light blocking must be mock, prompt, command or none, got {method!r}")
        if method == "command" and not (cover_command and uncover_command):
            raise InputError("light blocking by command needs cover_command and uncover_command")
        if not command_timeout_s > 0:
            raise InputError(f"the light command timeout must be > 0 s, got {command_timeout_s!r}")
        self.method = method
        self.cover_command = cover_command
        self.uncover_command = uncover_command
        self.prompt = prompt or _default_prompt
        self.settle_s = settle_s
        self.command_timeout_s = float(command_timeout_s)
        self.stop = stop
        self.covered: bool | None = None

    def set(self, camera: Camera, covered: bool, log: EventLog | None = None) -> None:
        """Block (``covered``) or unblock the light, unless it already is; a ``light`` event."""
        if self.covered is covered:
            return
        if self.method == "prompt":
            self.prompt(
                "Block the light for dark frames (cap the lens), then press Enter"
                if covered
                else "Unblock the light (remove the cap), then press Enter"
            )
        elif self.method == "command":
            cmd = self.cover_command if covered else self.uncover_command
            assert cmd is not None  # __init__ refuses the command method without both commands
            run_command(cmd, f"light {'cover' if covered else 'uncover'} command", self.command_timeout_s, self.stop)
        (camera.cover if covered else camera.uncover)()
        if self.settle_s:
            time.sleep(self.settle_s)
        self.covered = covered
        if log:
            log.emit("light", covered=covered, method=self.method)

    def restore(self, camera: Camera, log: EventLog | None = None) -> None:
        """Unblock the light after a run stopped with it blocked (a stop must not leave the
        next run metering in the dark): the uncover command runs (with its timeout, whatever
        the stop event says); when that fails, or nobody is there to remove a cap (``prompt``),
        a ``light`` event with ``ok`` false and the ``error`` records that it is still blocked."""
        if not self.covered:
            return
        try:
            if self.method == "prompt":
                raise SessionError("the light was blocked by hand (prompt); unblock it before the next run")
            if self.method == "command":
                assert self.uncover_command is not None
                run_command(self.uncover_command, "light uncover command", self.command_timeout_s, None)
            camera.uncover()
        except Exception as err:  # the stop that brought us here is what the run reports
            _log.warning("the light is still blocked: %s", err)
            if log:
                _emit_quietly(log, "light", covered=True, method=self.method, ok=False, error=str(err))
            return
        self.covered = False
        if log:
            _emit_quietly(log, "light", covered=False, method=self.method)


#: How often a waiting command or camera call looks at the stop event, s.
STOP_POLL_S = 0.05


def run_command(command: str, what: str, timeout_s: float, stop: threading.Event | None = None) -> None:
    """Run ``command`` with the shell in a process group of its own and wait for it.

    Parameters
    ----------
    command : str
        The shell command.
    what : str
        What it is, for messages (``light cover command``).
    timeout_s : float
        Longest it may run, s.
    stop : threading.Event, optional
        A set event (SIGTERM/SIGINT, :func:`stop_on_signals`) ends the wait.

    Raises
    ------
    SessionError
        The command failed (non-zero exit) or outlasted ``timeout_s``.
    RunInterrupted
        ``stop`` was set while it ran.

    On a timeout, a stop or any exception while waiting (a second signal), the command's
    whole process group is killed and reaped: nothing it started is left running.
    """
    with tempfile.TemporaryFile() as errors:  # a file, not a pipe: nothing waits for a reader
        proc = subprocess.Popen(
            command,
            shell=True,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=errors,
            start_new_session=True,
        )
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                try:
                    proc.wait(timeout=min(STOP_POLL_S, max(0.0, deadline - time.monotonic())))
                    break
                except subprocess.TimeoutExpired:
                    pass
                if stop is not None and stop.is_set():
                    signum = int(getattr(stop, "signum", signal.SIGTERM))
                    raise RunInterrupted(
                        f"stopped by signal {signum} while the {what} ran; run again with --resume", signum
                    )
                if time.monotonic() >= deadline:
                    raise SessionError(
                        f"{what} {command!r} did not end within {timeout_s:g} s ([darks] command_timeout_s); "
                        "it was stopped. Fix it, then run again with --resume"
                    )
        except BaseException:
            _kill_group(proc)
            raise
        if proc.returncode != 0:
            errors.seek(0)
            text = errors.read(4096).decode(errors="replace").strip()[:200]
            raise SessionError(f"{what} {command!r} failed (exit {proc.returncode}): {text}")


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    """Kill the process group of ``proc`` (it leads one: ``start_new_session``) and reap it."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:  # pragma: no cover - a process in uninterruptible sleep
        pass


def _default_prompt(message: str) -> None:
    if not sys.stdin or not sys.stdin.isatty():
        raise InputError(
            f'light blocking needs a person at a terminal ({message}); use block_light = "command" for unattended runs'
        )
    input(message + " ")


class StopEvent(threading.Event):
    """A :class:`threading.Event` that remembers the signal that set it (``signum``) and, for a
    stop that is not a signal (a Bluesky RunEngine's), who asked (``by``)."""

    signum: int = 15
    by: str = ""

    def stop(self, signum: int, by: str = "") -> None:
        self.signum = int(signum)
        self.by = by
        self.set()

    @property
    def reason(self) -> str:
        """``stopped by signal N``, or ``stopped by`` whoever asked."""
        return f"stopped by {self.by}" if self.by else f"stopped by signal {self.signum}"


@contextmanager
def stop_on_signals(signals: Sequence[int] = (signal.SIGTERM, signal.SIGINT)) -> Iterator[StopEvent]:
    """Turn SIGTERM and SIGINT into a clean stop while the block runs.

    The first signal sets the yielded :class:`StopEvent`: a :class:`CaptureSession` given it
    (``stop=``) ends before the next frame or retry with :class:`RunInterrupted` (exit status
    128 + the signal number) after logging a ``stop`` event, and the caller closes the camera;
    the run folder stays resumable. A second signal raises :class:`RunInterrupted` at once.
    Outside the main thread (where Python cannot install handlers) the event is only yielded.

    Yields
    ------
    StopEvent
        Set by the first signal.
    """
    event = StopEvent()
    if threading.current_thread() is not threading.main_thread():
        yield event
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        if event.is_set():
            raise RunInterrupted(f"stopped by signal {signum} (second signal); run again with --resume", signum)
        event.stop(signum)

    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield event
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def lock_dir(create: bool = True) -> Path:
    """Folder of the lock files: ``$HDRCAP_LOCK_DIR``, else ``$XDG_RUNTIME_DIR/hdrcap/locks``
    (per user, emptied at boot), else the user's state folder
    (``${XDG_STATE_HOME:-~/.local/state}/hdrcap/locks``). Not the shared /tmp: another user's
    lock there would be unwritable, and systemd's PrivateTmp gives each service its own /tmp.

    Parameters
    ----------
    create : bool
        Create the folder (False: only name it, for a reader that must not write).

    Returns
    -------
    Path
        The folder (created, private to the user, unless ``create`` is false).
    """
    if os.environ.get("HDRCAP_LOCK_DIR"):
        d = Path(os.environ["HDRCAP_LOCK_DIR"])
    elif os.environ.get("XDG_RUNTIME_DIR") and Path(os.environ["XDG_RUNTIME_DIR"]).is_dir():
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "hdrcap" / "locks"
    else:
        state = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
        d = Path(state) / "hdrcap" / "locks"
    if not create:
        return d
    try:
        d.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as err:
        raise InputError(f"{d}: cannot create the lock folder ({err.strerror}); set HDRCAP_LOCK_DIR") from None
    return d


class PathLock:
    """An exclusive, non-blocking lock on a file path (``flock``) whose file is removed when
    it is released, so that lock folders do not fill up with one file per run folder and
    camera (filelock keeps the path on Unix).

    Removing the file is safe because the lock counts only when the file locked is still the
    one at the path: a contender that opened the file before its holder removed it finds,
    once it gets the flock, another file (or none) at the path and tries the new one.
    Compatible with :class:`filelock.FileLock` on the same path (both use ``flock``).

    Parameters
    ----------
    path : path
        The lock file (created when needed).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self) -> bool:
        """Take the lock if nobody holds it; returns whether it was taken."""
        import fcntl

        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                os.close(fd)
                if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    return False
                raise
            try:
                current = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                current = False
            if current:
                self._fd = fd
                return True
            os.close(fd)  # its holder removed it meanwhile: lock the file at the path now

    def release(self) -> None:
        """Remove the lock file (while still holding it) and unlock."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            self.path.unlink()
        except OSError:  # a read-only folder: the file stays, the lock goes
            pass
        finally:
            os.close(fd)


@contextmanager
def hold_run_locks(run_dir: str | os.PathLike[str], camera_key: str | None = None) -> Iterator[None]:
    """Locks taken before the camera is opened and metering runs: one for the run folder and,
    when ``camera_key`` is given (a real camera named by the job), one for that camera. Both
    live in :func:`lock_dir` (the run folder need not exist yet; the lock files are removed
    again, :class:`PathLock`); a held one is a :class:`RunConflictError` (exit 5) before
    anything touches the camera.

    Parameters
    ----------
    run_dir : path
        The run folder.
    camera_key : str, optional
        Names the camera the job asks for (``gphoto2-SERIAL``, ``gphoto2-MODEL``, ...).
    """
    wanted = [(_run_lock_name(run_dir), f"{run_dir}: another hdrcap session is using this run folder")]
    if camera_key:
        wanted.append((f"open-{_safe(camera_key)}", f"camera {camera_key} is in use by another hdrcap session"))
    held: list[PathLock] = []
    try:
        for name, message in wanted:
            lock = PathLock(lock_dir() / f"{name}.lock")
            if not lock.acquire():
                raise RunConflictError(message)
            held.append(lock)
        yield
    finally:
        for lock in reversed(held):
            lock.release()


def _run_lock_name(run_dir: str | os.PathLike[str]) -> str:
    """Name of the run folder's lock in :func:`lock_dir` (from its absolute path)."""
    return "run-" + hashlib.sha256(str(Path(run_dir).resolve()).encode()).hexdigest()[:16]


#: The lock file a session holds inside its run folder while it captures.
SESSION_LOCK_NAME = ".hdrcap.lock"


def run_lock_files(run_dir: str | os.PathLike[str]) -> list[Path]:
    """The lock files held while a run is going on in ``run_dir``: the one in the run folder
    (held by the session while it captures) and the one in :func:`lock_dir` (held by ``hdrcap
    run``/``capture`` from before metering until the outputs are written). Nothing is created.

    Parameters
    ----------
    run_dir : path
        The run folder.

    Returns
    -------
    list of Path
    """
    return [Path(run_dir) / SESSION_LOCK_NAME, lock_dir(create=False) / f"{_run_lock_name(run_dir)}.lock"]


def held_locks() -> frozenset[tuple[int, int, int]] | None:
    """The files some process holds a lock on, as (device major, device minor, inode), read from
    Linux's ``/proc/locks``: a look that takes no lock itself, so it can never make a starting
    run fail on a held lock.

    Returns
    -------
    frozenset of (int, int, int) or None
        None where ``/proc/locks`` cannot be read (not Linux).
    """
    try:
        text = Path("/proc/locks").read_text()
    except OSError:
        return None
    out = set()
    for line in text.splitlines():
        fields = line.replace("->", " ").split()
        for word in fields[4:7]:  # "MAJ:MIN:INODE" (hex, hex, decimal) after the pid
            parts = word.split(":")
            if len(parts) == 3:
                try:
                    out.add((int(parts[0], 16), int(parts[1], 16), int(parts[2])))
                except ValueError:
                    pass
                break
    return frozenset(out)


def lock_is_held(path: Path, held: frozenset[tuple[int, int, int]]) -> bool:
    """Whether some process holds a lock on the file ``path`` (``held``: :func:`held_locks`)."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino) in held


def _safe(text: str) -> str:
    import re

    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text)


def _identity(camera: Camera) -> dict[str, str]:
    ident = getattr(camera, "identity", None)
    if ident is None:
        return {"backend": type(camera).__name__, "model": "", "serial": "", "port": ""}
    return {k: str(getattr(ident, k, "")) for k in ("backend", "model", "serial", "port")}


class StreamingMerge:
    """Feeds verified frames to the merge as they land.

    Uses ``pipeline.merge.accumulator.MergeAccumulator``; each light frame is added with the dark
    strategy of its exposure time (``strategy_for``) and the dark level that
    :class:`pipeline.merge.darks.DarkResolver` serves it: ``matched`` the dark frame of that time,
    ``master`` the average of the dark frames of that time (N = their number) or the library's
    master dark (its N), ``model`` none. Dark frames come before the light frames in a plan,
    so each light frame has its dark frame(s) when it lands.

    Parameters
    ----------
    calibration : pipeline.params.Calibration
    shape : (int, int)
    strategy_for : callable or str
        Exposure time (s) -> DarkStrategy (or its name); a string: one for all.
    options : dict, optional
        Further :class:`pipeline.merge.accumulator.MergeOptions` fields (iterations, saturation, prnu, ...).
        ``exposure_times`` defaults to ``"effective"``: :meth:`result` estimates each frame's
        effective exposure time from the frames (``pipeline.exposure_ratio``) before the
        iterations.
    """

    def __init__(
        self,
        calibration: Calibration,
        shape: Sequence[int],
        strategy_for: Callable[[float], str] | str = DarkStrategy.MATCHED,
        options: dict[str, Any] | None = None,
    ) -> None:
        from hdrcap.pipeline.merge.accumulator import MergeAccumulator

        self.calibration = calibration
        self.shape = tuple(shape)
        self.strategy_for = (lambda _t, s=strategy_for: s) if isinstance(strategy_for, str) else strategy_for
        self._darks = DarkResolver()
        self.streamed = True
        opts = {k: v for k, v in (options or {}).items() if k not in ("dark_strategy", "n_dark")}
        opts.setdefault("exposure_times", "effective")  # estimated by the accumulator at the end
        uniform = strategy_for if isinstance(strategy_for, str) and strategy_for != "mixed" else None
        self._acc = MergeAccumulator(calibration, self.shape, dark_strategy=uniform, **opts)
        self.dark_sources: list[str] = []  # per light frame, what served its dark level (as merge_files says)

    def add_dark(self, values: np.ndarray, t: float, name: str = "") -> None:
        """A dark frame (DN) of exposure ``t`` (s); ``name``: its file, for the header."""
        try:
            self._darks.add_dark(values, t, name)
        except InputError as err:  # after its light frames
            raise SessionError(str(err)) from None

    def add_master(self, values: np.ndarray, t: float, n_frames: int = 1, name: str = "") -> None:
        """A master dark (DN) for exposure ``t`` from the dark library, averaged from ``n_frames``."""
        self._darks.add_master(values, t, int(n_frames), name)

    def add_light(self, values: np.ndarray, t: float) -> None:
        """A light frame (DN) of exposure ``t`` (s), merged with the dark level that serves it."""
        strategy = DarkStrategy(self.strategy_for(t))
        src = self._darks.resolve(t, strategy)
        if src is None:
            raise SessionError(f"no dark frame for exposure {t:g} s ({strategy} dark strategy) before its light frame")
        self._acc.add(
            values, t, src.data, strategy=strategy, n_dark=src.n_frames if strategy is DarkStrategy.MASTER else None
        )
        self.dark_sources.append("model" if strategy is DarkStrategy.MODEL else f"{strategy}: {src.source}")

    def result(self) -> HdrResult:
        """The :class:`pipeline.result.HdrResult` of everything added; its header also names the
        dark level of every light frame (``dark_sources``)."""
        if not len(self._acc):
            raise SessionError("no light frames to merge")
        res = self._acc.result()
        return res.replace(header={**res.header, "dark_sources": list(self.dark_sources)})


@dataclass
class SessionResult:
    """What a session produced."""

    run_dir: Path
    frames: dict[str, dict[str, Any]]
    captured: int
    resumed: int
    adopted: int
    retries: dict[str, int] = field(default_factory=dict)
    merge: HdrResult | None = None
    elapsed_s: float = 0.0


class CaptureSession:
    """Run a :class:`CapturePlan` on a camera into ``run_dir``.

    Parameters
    ----------
    camera : Camera
        Any object with the :class:`acquire.camera.Camera` methods.
    run_dir : path
        The run folder (created); holds ``frames/``, ``manifest.jsonl``, ``events.jsonl``.
    plan : CapturePlan
    calibration : pipeline.params.Calibration, optional
        Given: the light frames are merged (streamed) and the result is in ``result.merge``.
    light : LightBlocker, optional
        How to block the light for dark frames (default ``mock``).
    retry : RetryPolicy, optional
    resume : bool
        Continue the run recorded in ``run_dir`` (else ``run_dir`` must hold no manifest).
    progress : bool or None
        tqdm progress bar; None shows it when stderr is a terminal.
    meta : dict
        Extra fields for the manifest's run record (job file, seed, ...).
    master_darks : dict, optional
        Exposure time (s) -> (master dark array in DN, its frame count N) from the dark
        library, for the plan's ``library_times``.
    check_dark : float
        A dark frame whose median lies above this fraction of the raw range stops the session
        (the light was not blocked); 0 disables the check.
    merge_options : dict, optional
        Options of the merge (:class:`pipeline.merge.accumulator.MergeOptions` fields such as iterations,
        saturation, prnu), e.g. the planner's decisions.
    stop : threading.Event, optional
        Set (by a SIGTERM/SIGINT handler, :func:`stop_on_signals`) to end the run cleanly before
        the next frame, retry or reconnect: :class:`RunInterrupted`, the run folder resumable.
        It also ends a light command in progress and is handed to the camera
        (:func:`watch_stop`), which gives up a hung call.
    expect : pipeline.compat.CameraProfile, optional
        The camera and ISO every frame must come from (:func:`pipeline.compat.check_compatible`
        on its EXIF make/model and ISO; a mismatch stops the run with :class:`VerificationError`).
        Without an ISO the first frame's ISO (or the recorded frames' on resume) is the run's.
        On resume the camera must be the one recorded in the manifest.
    """

    def __init__(
        self,
        camera: Camera,
        run_dir: str | os.PathLike[str],
        plan: CapturePlan,
        calibration: Calibration | None = None,
        light: LightBlocker | None = None,
        retry: RetryPolicy | None = None,
        resume: bool = False,
        progress: bool | None = None,
        meta: dict[str, Any] | None = None,
        sleep: Callable[[float], object] = time.sleep,
        check_dark: float = 0.05,
        master_darks: dict[float, tuple[np.ndarray, int]] | None = None,
        merge_options: dict[str, Any] | None = None,
        stop: threading.Event | None = None,
        expect: CameraProfile | None = None,
    ) -> None:
        self.camera = camera
        self.stop = stop
        self.expect = expect
        self.run_dir = Path(run_dir)
        self.plan = plan
        self.calibration = calibration
        self.light = light or LightBlocker("mock")
        if self.light.stop is None:  # a stop also ends a cover/uncover command that hangs
            self.light.stop = stop
        self.retry = retry or RetryPolicy()
        self.resume = resume
        self.progress = progress
        self.meta = meta or {}
        self.sleep: Callable[[float], object] = stop.wait if stop is not None and sleep is time.sleep else sleep
        self.check_dark = check_dark
        self.master_darks: ExposureMap[tuple[np.ndarray, int]] = ExposureMap(
            (float(t), v) for t, v in (master_darks or {}).items()
        )
        self.merge_options = dict(merge_options or {})
        missing = [t for t in plan.library_times if t not in self.master_darks]
        if missing:
            raise InputError(f"no master dark for {missing[0]:g} s in the dark library the plan relies on")
        self.retries: dict[str, int] = {}
        self.shape: tuple[int, ...] | None = tuple(getattr(camera, "shape", ()) or ()) or None
        self._frame_bytes = 0
        self._camera_events_seen = len(getattr(camera, "events", None) or [])  # earlier runs' events: not ours

    # ------------------------------------------------------------------ public
    def run(self) -> SessionResult:
        t0 = time.monotonic()
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            what = f"{self.run_dir}: cannot create the run folder ({err.strerror or err})"
            if err.errno in LOCAL_IO_ERRNOS:
                raise LocalIOError(f"{what}; fix it, then run again with --resume") from None
            raise InputError(what) from None
        if not os.access(self.run_dir, os.W_OK):
            raise LocalIOError(f"{self.run_dir}: the run folder is not writable (read-only or permissions)")
        ident = _identity(self.camera)
        run_lock = PathLock(self.run_dir / SESSION_LOCK_NAME)
        cam_lock = PathLock(lock_dir() / (_lock_key(ident) + ".lock"))
        if not run_lock.acquire():
            raise RunConflictError(f"{self.run_dir}: another hdrcap session is using this run folder")
        try:
            if not cam_lock.acquire():
                raise RunConflictError(
                    f"camera {ident['model']} ({ident['serial'] or ident['port']}) is in use by another hdrcap session"
                )
            try:
                watch_stop(self.camera, self.stop)
                return self._run_locked(ident, t0)
            finally:
                cam_lock.release()
        finally:
            run_lock.release()

    # ------------------------------------------------------------------ internals
    def _run_locked(self, ident: dict[str, str], t0: float) -> SessionResult:
        manifest = Manifest(self.run_dir)
        log = EventLog(self.run_dir)
        frames_dir = self.run_dir / "frames"
        partial_dir = self.run_dir / ".partial"
        frames_dir.mkdir(exist_ok=True)
        done, resumed = self._open_manifest(manifest, log, ident)
        if partial_dir.exists():  # downloads that never finished
            shutil.rmtree(partial_dir)
        partial_dir.mkdir()
        run = _RunFiles(ident, manifest, log, partial_dir, frames_dir)
        try:
            adopted = self._adopt_landed(done, run)
            self._check_free_space(done)
            captured, merger = self._capture_missing(done, run)
            if self.light.covered:
                self.light.set(self.camera, False, log)
            result = SessionResult(self.run_dir, done, captured, resumed, adopted, dict(self.retries))
            if merger is not None:
                result.merge = merger.result()
                log.emit("merged", streamed=merger.streamed, info=jsonable(result.merge.info))
        except OSError as err:  # our side: disk full, permissions
            stop = LocalIOError(
                f"{err.filename or self.run_dir}: {err.strerror or err}; free space or fix "
                "permissions, then run again with --resume"
            )
            self._stopped(log, stop, kind="local_io")
            raise stop from None
        except CameraError as err:
            self._stopped(log, err, kind=fault_kind(err))
            raise
        except BaseException as err:
            self._stopped(log, err)
            raise
        shutil.rmtree(partial_dir, ignore_errors=True)
        result.elapsed_s = time.monotonic() - t0
        log.emit(
            "done",
            captured=captured,
            resumed=resumed,
            adopted=adopted,
            retries=self.retries,
            elapsed_s=round(result.elapsed_s, 3),
        )
        return result

    def _stopped(self, log: EventLog, err: BaseException, kind: str | None = None) -> None:
        """A run that stops: the light unblocked again (or recorded as still blocked), then the
        ``stop`` event with the reason and exit code."""
        self.light.restore(self.camera, log)
        emit_stop(log, err, kind=kind)

    def _open_manifest(
        self, manifest: Manifest, log: EventLog, ident: dict[str, str]
    ) -> tuple[dict[str, dict[str, Any]], int]:
        """Start the manifest, or (resume) check it was made from this plan and void the frames
        whose file is missing or changed. Returns (frames recorded by key, their number)."""
        fp = self.plan.fingerprint()
        head = manifest.header() if manifest.exists() else None
        if head is None and manifest.exists() and (not self.resume or manifest.frames()):
            # a torn or unreadable header: the plan cannot be checked, so frames are not trusted
            raise VerificationError(
                f"{manifest.path}: the run record (first line) is unreadable, so the plan of the "
                "frames there cannot be checked; move the run folder aside and start again"
            )
        if head is None:  # a new run, or a crash while its first line was written
            manifest.append(
                {
                    "type": "run",
                    "time": utc_now(),
                    "plan_fingerprint": fp,
                    "camera": ident,
                    "plan": self.plan.to_dict(),
                    **self.meta,
                }
            )
            log.emit("start", frames=len(self.plan.frames), camera=ident, run_dir=str(self.run_dir))
            return {}, 0
        if not self.resume:
            raise RunConflictError(
                f"{self.run_dir}: holds an earlier run (manifest.jsonl); use --resume "
                "to continue it or choose another run folder"
            )
        if head.get("camera"):
            try:
                check_compatible(
                    CameraProfile.from_record(head["camera"], f"the run in {self.run_dir}"),
                    CameraProfile.from_record(ident, "the connected camera"),
                )
            except CompatibilityError as err:
                raise RunConflictError(f"{err}; resume it with its own camera") from None
        if head.get("plan_fingerprint") != fp:
            raise RunConflictError(
                f"{self.run_dir}: the run there was made from a different plan; "
                "resume with the same job or choose another run folder"
            )
        done = manifest.frames()
        bad = manifest.verify_hashes()
        for key in bad:
            rec = done.pop(key)
            self._quarantine(self.run_dir / rec["file"], "hash mismatch or missing")
            manifest.append({"type": "void", "key": key, "reason": "file missing or hash mismatch", "time": utc_now()})
            log.emit("void", key=key, file=rec["file"])
        log.emit("resume", frames_done=len(done), torn_manifest_lines=manifest.torn_lines, voided=len(bad))
        isos = {float(r["iso"]) for r in done.values() if r.get("iso") is not None}
        if self.expect is not None and self.expect.iso is None and len(isos) == 1:
            self.expect = replace(self.expect, iso=isos.pop())
        return done, len(done)

    def _adopt_landed(self, done: dict[str, dict[str, Any]], run: _RunFiles) -> int:
        """Verify and record the frames whose file landed but whose manifest line was never
        written (bad ones are quarantined); returns how many were adopted."""
        adopted = 0
        for i, spec in enumerate(self.plan.frames):
            if spec.key in done:
                continue
            for f in sorted(run.frames_dir.glob(frame_stem(i, spec) + ".*")):
                try:
                    rec = self._verify_and_record(f, i, spec, None, run.ident, run.manifest, adopted=True)
                except CorruptFrameError as err:
                    self._quarantine(f, str(err))
                    run.log.emit("reject", key=spec.key, file=f.name, reason=str(err))
                    continue
                done[spec.key] = rec
                adopted += 1
                run.log.emit("adopt", key=spec.key, file=rec["file"])
        return adopted

    def _replay(self, done: dict[str, dict[str, Any]]) -> StreamingMerge | None:
        """The merge of the frames recorded before a resume, in capture order."""
        from hdrcap.pipeline.io.raw import read_frame

        merger = None
        if self.calibration is not None:
            for rec in sorted(done.values(), key=lambda r: r["index"]):
                if rec["kind"] in ("light", "dark"):
                    merger = self._feed(self.calibration, merger, rec, read_frame(self.run_dir / rec["file"]).data)
        return merger

    def _capture_missing(self, done: dict[str, dict[str, Any]], run: _RunFiles) -> tuple[int, StreamingMerge | None]:
        """Capture every planned frame not yet done (light blocked as each needs), feeding the
        merge; a ``frame`` event follows each frame. Frames missing under recorded ones (voided
        on resume: a changed or lost file) are taken first, before the recorded frames are
        merged again, so that a light frame never reaches the merge before its dark frame.
        Returns (frames captured, the merge)."""
        from tqdm import tqdm

        todo = [(i, s) for i, s in enumerate(self.plan.frames) if s.key not in done]
        last = max((int(r["index"]) for r in done.values()), default=-1)
        holes = [(i, s) for i, s in todo if i < last]
        show = self.progress if self.progress is not None else sys.stderr.isatty()
        bar = tqdm(
            total=len(self.plan.frames),
            initial=len(self.plan.frames) - len(todo),
            desc="capture",
            unit="frame",
            disable=not show,
            dynamic_ncols=True,
        )
        eta = _Eta([s.exposure_s for _i, s in todo])
        try:
            captured, _ = self._capture_frames(holes, done, None, run, bar, eta, merge=False)
            merger = self._replay(done)
            rest = [(i, s) for i, s in todo if i >= last]
            more, merger = self._capture_frames(rest, done, merger, run, bar, eta)
        finally:
            bar.close()
        return captured + more, merger

    def _capture_frames(
        self,
        frames: list[tuple[int, FrameSpec]],
        done: dict[str, dict[str, Any]],
        merger: StreamingMerge | None,
        run: _RunFiles,
        bar: Any,
        eta: _Eta,
        merge: bool = True,
    ) -> tuple[int, StreamingMerge | None]:
        """Capture ``frames`` (plan index, spec) in order into ``done``, each handed to the merge
        (``merger``, created with the first frame) unless ``merge`` is false; returns (frames
        captured, the merge)."""
        captured = 0
        for i, spec in frames:
            self._check_stop()
            self.light.set(self.camera, spec.dark, run.log)
            rec, values = self._capture_one(i, spec, run.ident, run.manifest, run.log, run.partial_dir, run.frames_dir)
            done[spec.key] = rec
            captured += 1
            if merge and self.calibration is not None:
                merger = self._feed(self.calibration, merger, rec, values)
            eta.frame_done(spec.exposure_s)
            run.log.emit(
                "frame",
                key=spec.key,
                index=i,
                done=len(done),
                total=len(self.plan.frames),
                eta_s=eta.remaining_s(),
                temperature_c=rec.get("temperature_c"),
            )
            bar.update(1)
        return captured, merger

    def _check_stop(self) -> None:
        """Raise :class:`RunInterrupted` when the stop event is set (SIGTERM/SIGINT)."""
        if self.stop is not None and self.stop.is_set():
            signum = getattr(self.stop, "signum", 15)
            reason = getattr(self.stop, "reason", f"stopped by signal {signum}")
            raise RunInterrupted(f"{self.run_dir}: {reason} between two frames; run again with --resume", signum)

    def _feed(
        self, calibration: Calibration, merger: StreamingMerge | None, rec: dict[str, Any], values: np.ndarray
    ) -> StreamingMerge | None:
        """Hand a verified frame to the merge (created with the first frame: its size, and the
        session's ``calibration``)."""
        if rec["kind"] not in ("light", "dark"):
            return merger
        if merger is None:
            strategy = self.plan.dark_strategy if not self.plan.time_strategies else self.plan.strategy_for
            merger = StreamingMerge(calibration, values.shape, strategy, self.merge_options)
            for t, (data, n) in self.master_darks.items():
                merger.add_master(data, t, n)
        if rec["kind"] == "dark":
            merger.add_dark(values, rec["file_exposure_s"], rec["file"])
        else:
            merger.add_light(values, rec["file_exposure_s"])
        return merger

    def _capture_one(
        self,
        i: int,
        spec: FrameSpec,
        ident: dict[str, str],
        manifest: Manifest,
        log: EventLog,
        partial_dir: Path,
        frames_dir: Path,
    ) -> tuple[dict[str, Any], np.ndarray]:
        last = ""
        for attempt in range(1, self.retry.max_attempts + 1):
            self._check_stop()
            tmp = partial_dir / f"{frame_stem(i, spec)}.try{attempt}.dng"
            try:
                started = utc_now()
                applied = float(self.camera.set_exposure(spec.exposure_s))
                check_applied_exposure(spec.exposure_s, applied, f"frame {spec.key}")
                timeout = None if self.retry.timeout_s is None else applied + self.retry.timeout_s
                res = self.camera.capture(tmp, dark=spec.dark, timeout=timeout)
                if getattr(res, "bulb", False):  # timed around the release: the measured open time
                    applied = float(res.applied_exposure_s)
                    check_applied_exposure(spec.exposure_s, applied, f"frame {spec.key}", bulb=True)
                path = Path(res.path)
                final = frames_dir / (frame_stem(i, spec) + path.suffix.lower())
                rec, values = self._verify(path, spec, applied, res)
                rec.update(started=started, finished=utc_now(), attempts=attempt)
                _link_new(path, final)
                rec.update(self._record_fields(final, i, spec, ident))
                manifest.append(rec)
                path.unlink(missing_ok=True)
                if attempt > 1:
                    log.emit("recovered", key=spec.key, attempts=attempt)
                return rec, values
            except Exception as err:  # classify; anything that is not a camera fault propagates
                _raise_if_local_io(err, partial_dir, self._frame_bytes)
                kind = fault_kind(err)
                if kind is None:
                    raise
                last = str(err)  # not the error: its traceback would keep the attempt's frames (open files) alive
                self.retries[kind] = self.retries.get(kind, 0) + 1
                log.emit("fault", key=spec.key, attempt=attempt, kind=kind, error=f"{type(err).__name__}: {err}")
                for f in partial_dir.glob(f"{frame_stem(i, spec)}.try{attempt}*"):
                    f.unlink(missing_ok=True)
                if kind == "fatal":
                    raise SessionError(
                        f"camera stopped the session at frame {spec.key}: {err} "
                        f"({len(manifest.frames())} frames are safe; fix it and run again with --resume)"
                    ) from None
                if attempt == self.retry.max_attempts:
                    break
                wait = self.retry.wait(attempt)
                if kind in ("busy", "reconnect"):
                    self.sleep(wait)
                self._check_stop()  # a stop during the fault: no reconnect, no retry
                if kind == "reconnect":
                    self._reconnect(log)
            finally:
                self._forward_camera_events(log)
        raise SessionError(
            f"frame {spec.key}: gave up after {self.retry.max_attempts} attempts "
            f"(last: {last}); run again with --resume"
        )

    def _forward_camera_events(self, log: EventLog) -> None:
        """Copy the camera's new events (``camera.events``: (kind, detail) pairs, e.g. a frame it
        could not delete from the card, a stale file, a changed port) into ``events.jsonl`` as
        ``camera`` events; the routine ones (file added, capture complete) stay out."""
        events = getattr(self.camera, "events", None)
        if not isinstance(events, list):
            return
        self._camera_events_seen = min(self._camera_events_seen, len(events))  # a camera that cleared its list
        for kind, detail in events[self._camera_events_seen :]:
            if kind not in ROUTINE_CAMERA_EVENTS:
                log.emit("camera", kind=str(kind), detail=str(detail))
        self._camera_events_seen = len(events)

    def _reconnect(self, log: EventLog) -> None:
        try:
            self.camera.reconnect()
            log.emit("reconnect", ok=True, port=str(getattr(getattr(self.camera, "identity", None), "port", "")))
        except Exception as err:
            if fault_kind(err) is None:
                raise
            log.emit("reconnect", ok=False, error=str(err))
            if fault_kind(err) == "fatal":
                raise SessionError(f"camera lost: {err}") from None

    def _verify(
        self, path: Path, spec: FrameSpec, applied: float, res: CaptureResult | None
    ) -> tuple[dict[str, Any], np.ndarray]:
        """Open the file and check its size and exposure time (CorruptFrameError if not)."""
        from hdrcap.pipeline.io.raw import IMAGE_EXTENSIONS, RAW_EXTENSIONS, read_frame

        if path.suffix.lower() not in RAW_EXTENSIONS | IMAGE_EXTENSIONS:
            raise InputError(
                f"{spec.key}: the camera delivers {path.suffix or 'unnamed'} files, not raw; set its "
                'image format to RAW (job: [camera] settings = {{ imageformat = "RAW" }})'
            )
        try:
            frame = read_frame(path)
        except (InputError, OSError, ValueError) as err:
            raise CorruptFrameError(f"{path.name}: {err}") from None
        if self.shape is None:
            self.shape = frame.shape
        if frame.shape != self.shape:
            raise CorruptFrameError(f"{path.name}: size {frame.shape} differs from the camera's {self.shape}")
        if spec.dark and self.check_dark:
            self._check_dark(spec, frame)
        self._check_frame_camera(path, frame)
        bulb = bool(getattr(res, "bulb", False))
        if not (same_bulb_exposure if bulb else same_exposure)(frame.exposure_time, applied):
            raise CorruptFrameError(
                f"{path.name}: exposure {frame.exposure_time:g} s in the file, camera reported {applied:g} s"
            )
        rec = {
            "type": "frame",
            "key": spec.key,
            "kind": spec.kind,
            "dark": spec.dark,
            "job_exposure_s": spec.exposure_s if spec.job_exposure_s is None else spec.job_exposure_s,
            "requested_exposure_s": spec.exposure_s,
            "applied_exposure_s": applied,
            "file_exposure_s": frame.exposure_time,
            "iso": frame.iso,
            "shape": list(frame.shape),
            "temperature_c": getattr(res, "temperature_c", None) if res is not None else _temp(self.camera),
            "settings": jsonable(getattr(res, "settings", {}) if res is not None else {}),
            "camera_file": getattr(res, "camera_file", "") if res is not None else "",
        }
        return rec, frame.data

    def _check_dark(self, spec: FrameSpec, frame: RawFrame) -> None:
        """A dark frame must be dark: its median below ``check_dark`` of the raw range and, with a
        calibration, within :func:`dark_excess_limit` of the level the calibration predicts
        (which catches a light leak at short exposures, far below a fraction of the range)."""
        black = frame.black_level or 0.0
        white = frame.white_level or 65535.0
        median = float(np.median(frame.data))
        level = (median - black) / max(white - black, 1.0)
        why = f"dark frame median at {level:.1%} of the range" if level > self.check_dark else ""
        if not why and self.calibration is not None:
            p = self.calibration.params
            expected = p.mu_R + p.g * p.dark_current * frame.exposure_time
            limit = dark_excess_limit(p, frame.exposure_time, frame.data.size)
            if median - expected > limit:
                why = (
                    f"dark frame median {median - expected:.1f} DN above the calibrated dark level "
                    f"{expected:.1f} DN, more than {limit:.1f} DN"
                )
        if why:
            raise VerificationError(
                f"{spec.key}: the light is not blocked ({why}); check the light blocking "
                f"({self.light.method}) and run again with --resume"
            )

    def _check_frame_camera(self, path: Path, frame: RawFrame) -> None:
        """The frame's EXIF camera and ISO against :attr:`expect` (the first frame fixes the
        run's ISO when nothing else did); VerificationError on a mismatch."""
        if self.expect is None:
            return
        got = CameraProfile(f"frame {path.name}", frame.camera or "", "", frame.iso)
        try:
            check_compatible(replace(self.expect, temperature_c=None), got)
        except CompatibilityError as err:
            raise VerificationError(
                f"{err}; check the camera's settings (fixed ISO), then run again with --resume"
            ) from None
        if self.expect.iso is None and frame.iso is not None:
            self.expect = replace(self.expect, iso=float(frame.iso))

    def _check_free_space(self, done: dict[str, dict[str, Any]]) -> None:
        """Refuse to start (LocalIOError, exit 6) when the run folder's file system has no room
        for the frames still to take and the outputs (:func:`estimate_run_bytes`)."""
        todo = sum(1 for f in self.plan.frames if f.key not in done)
        if not todo:
            return
        self._frame_bytes = max([self._frame_bytes] + [int(r.get("bytes") or 0) for r in done.values()])
        need = estimate_run_bytes(todo, self.shape, self._frame_bytes or None, merge=self.calibration is not None)
        free = shutil.disk_usage(self.run_dir).free
        if free < need:
            raise LocalIOError(
                f"{self.run_dir}: {free / 1e6:.0f} MB free, the {todo} frames still to take and the "
                f"outputs need about {need / 1e6:.0f} MB; free space, then run again with --resume"
            )

    def _record_fields(self, final: Path, i: int, spec: FrameSpec, ident: dict[str, str]) -> dict[str, Any]:
        from hdrcap.pipeline.io.files import sha256_file

        self._frame_bytes = max(self._frame_bytes, final.stat().st_size)
        return {
            "file": str(final.relative_to(self.run_dir)),
            "sha256": sha256_file(final),
            "bytes": final.stat().st_size,
            "index": i,
            "camera": ident,
        }

    def _verify_and_record(
        self,
        path: Path,
        i: int,
        spec: FrameSpec,
        res: CaptureResult | None,
        ident: dict[str, str],
        manifest: Manifest,
        adopted: bool = False,
    ) -> dict[str, Any]:
        rec, _values = self._verify(path, spec, spec.exposure_s, res)
        now = utc_now()
        rec.update(started=None, finished=now, attempts=None, adopted=adopted)
        rec.update(self._record_fields(path, i, spec, ident))
        manifest.append(rec)
        return rec

    def _quarantine(self, path: Path, reason: str) -> None:
        if not path.exists():
            return
        q = self.run_dir / "rejected"
        q.mkdir(exist_ok=True)
        target = q / f"{path.name}.{int(time.time() * 1e6)}"
        os.replace(path, target)


@dataclass(frozen=True)
class _RunFiles:
    """Where a session records: the camera's identity, manifest, event log and folders."""

    ident: dict[str, str]
    manifest: Manifest
    log: EventLog
    partial_dir: Path
    frames_dir: Path


class _Eta:
    """Time left in a run: the exposures still to take plus the mean overhead per frame so far, s."""

    def __init__(self, exposures: list[float]) -> None:
        self.left = float(sum(exposures))
        self.t0 = time.monotonic()
        self.n = 0
        self.exposed = 0.0
        self.frames_left = len(exposures)

    def frame_done(self, exposure_s: float) -> None:
        self.n += 1
        self.frames_left -= 1
        self.exposed += exposure_s
        self.left -= exposure_s

    def remaining_s(self) -> float:
        overhead = max(0.0, (time.monotonic() - self.t0 - self.exposed) / max(self.n, 1))
        return round(max(0.0, self.left) + overhead * self.frames_left, 3)


#: Bytes of a raw file when neither an earlier frame nor the sensor size tells (a 24 MP raw is
#: 25-50 MB).
UNKNOWN_FRAME_BYTES = 50_000_000
#: Room kept free besides the run's files (manifest, events, file-system slack), bytes.
FREE_SPACE_MARGIN = 16_000_000
#: errno values that mean our side failed, not the camera: full disk or quota, read-only or
#: vanished file system, permissions.
LOCAL_IO_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.ENODEV})


def estimate_run_bytes(
    n_frames: int, shape: tuple[int, ...] | None = None, frame_bytes: int | None = None, merge: bool = True
) -> int:
    """Disk space a run still needs, bytes: its raw files and (``merge``) the EXR and PNG outputs.

    Parameters
    ----------
    n_frames : int
        Frames still to take.
    shape : (int, int), optional
        Raw mosaic size, photosites.
    frame_bytes : int, optional
        Size of one raw file, bytes (an earlier frame's); else 2 bytes per photosite plus 1 MB,
        else :data:`UNKNOWN_FRAME_BYTES`.
    merge : bool
        The run writes the merged EXR (4 float32 channels) and a preview PNG.

    Returns
    -------
    int
        Bytes, with :data:`FREE_SPACE_MARGIN`.
    """
    pixels = int(np.prod(shape)) if shape else 0
    per = frame_bytes or (2 * pixels + 1_000_000 if pixels else UNKNOWN_FRAME_BYTES)
    outputs = (4 * 4 + 3) * pixels if merge else 0
    return int(n_frames * per + outputs + FREE_SPACE_MARGIN)


def dark_excess_limit(params: SensorParams, t: float, n_pixels: int) -> float:
    """How far a dark frame's median may lie above the calibrated dark level ``mu_R + g D t``
    before the light counts as not blocked, DN: 2 DN (bias drift, quantisation of the median),
    plus the dark signal itself (the dark current may double with a few degrees C), plus five
    standard errors of the median, 1.25 sigma / sqrt(N), with the noise of Eq. (5)
    sigma^2 = sigma2_R + g^2 D t.

    Parameters
    ----------
    params : pipeline.params.SensorParams
    t : float
        Exposure time, s.
    n_pixels : int
        Photosites in the frame.

    Returns
    -------
    float
        DN.
    """
    dark_dn = params.g * params.dark_current * t
    sigma = float(np.sqrt(params.sigma2_R + params.g * dark_dn))
    return 2.0 + dark_dn + 5 * 1.25 * sigma / np.sqrt(max(int(n_pixels), 1))


def _raise_if_local_io(err: BaseException, folder: Path, frame_bytes: int) -> None:
    """A failed download whose cause is our disk (ENOSPC and its kin anywhere in the exception
    chain, or less room left than one frame) is a LocalIOError, not the camera's fault."""
    seen: set[int] = set()
    e: BaseException | None = err
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in LOCAL_IO_ERRNOS:
            raise LocalIOError(
                f"{e.filename or folder}: {e.strerror or e}; free space or fix permissions, then "
                "run again with --resume"
            ) from None
        e = e.__cause__ or e.__context__
    if fault_kind(err) is not None and frame_bytes:
        try:
            free = shutil.disk_usage(folder).free
        except OSError:
            return
        if free < frame_bytes:
            raise LocalIOError(
                f"{folder}: {free / 1e6:.1f} MB free, less than one frame ({frame_bytes / 1e6:.1f} MB):"
                f" the download failed on this computer's disk ({err}); free space, then run again "
                "with --resume"
            ) from None


def emit_stop(log: EventLog, err: BaseException, kind: str | None = None) -> None:
    """The ``stop`` event: reason and exit code, once per error (``err.stop_logged``). A
    failing event log (disk full) does not hide the error that stopped the run."""
    if getattr(err, "stop_logged", False):
        return
    fields: dict[str, Any] = {
        "reason": f"{err}" if isinstance(err, HdrcapError) else f"{type(err).__name__}: {err}",
        "exit_code": getattr(err, "exit_code", 70 if not isinstance(err, KeyboardInterrupt) else 130),
    }
    kind = kind or ("local_io" if isinstance(err, LocalIOError) else None)
    if kind:
        fields["kind"] = kind
    _emit_quietly(log, "stop", **fields)
    try:
        err.stop_logged = True  # type: ignore[attr-defined]
    except AttributeError:  # pragma: no cover - an exception type with __slots__
        pass


def _emit_quietly(log: EventLog, event: str, **fields: Any) -> None:
    """``log.emit`` on the way out of a failed run: a full disk must not hide the failure."""
    try:
        log.emit(event, **fields)
    except OSError:
        pass


#: Largest difference between the exposure time a frame asked for (already one of the camera's
#: own times) and the one the camera reports applying, as a ratio: 1/6 stop. A camera rounds to
#: its own list (a label such as 0.3 s for 1/3 s is 10 % off); one that is not in manual
#: exposure, or has its shutter setting locked, applies some other time.
APPLIED_EXPOSURE_TOLERANCE = 2 ** (1 / 6)


def check_applied_exposure(requested_s: float, applied_s: float, what: str, bulb: bool = False) -> None:
    """Stop the run when the camera did not apply the exposure time it was given.

    Parameters
    ----------
    requested_s : float
        The time set, s (one of the camera's times).
    applied_s : float
        The time the camera reports applying (read back), or for bulb the measured open time, s.
    what : str
        The frame, for the message.
    bulb : bool
        A bulb exposure (:func:`pipeline.times.same_bulb_exposure` decides).

    Raises
    ------
    SessionError
        ``applied_s`` differs from ``requested_s`` by more than :data:`APPLIED_EXPOSURE_TOLERANCE`
        (exit status 4: the camera stopped the run).
    """
    if bulb:
        ok = same_bulb_exposure(applied_s, requested_s)
    else:
        ok = requested_s > 0 and 1 / APPLIED_EXPOSURE_TOLERANCE <= applied_s / requested_s <= APPLIED_EXPOSURE_TOLERANCE
    if not ok:
        raise SessionError(
            f"{what}: the camera applied {applied_s:g} s, requested {requested_s:g} s: it does not take the "
            "exposure time it is given (not in manual exposure, or its shutter setting locked); fix it, then "
            "run again with --resume"
        )


def watch_stop(camera: Camera, stop: threading.Event | None) -> None:
    """Hand ``stop`` to a camera that can give up a call in progress when it is set
    (``camera.watch_stop(event)``, optional in the :class:`acquire.camera.Camera` protocol):
    a stop then does not wait for a hung camera call's own timeout.

    Parameters
    ----------
    camera : Camera
    stop : threading.Event or None
        None: no stop to watch (a camera reused by a later session forgets the earlier one's).
    """
    watch = getattr(camera, "watch_stop", None)
    if callable(watch):
        watch(stop)


def _link_new(src: Path, dst: Path) -> None:
    """Put ``src`` at ``dst`` without ever replacing an existing file (also on file systems
    without hard links, :func:`pipeline.io.files.place_new`)."""
    from hdrcap.pipeline.io.files import place_new

    try:
        place_new(src, dst)
    except FileExistsError:
        raise VerificationError(f"{dst}: exists already; the run folder is inconsistent") from None


def _temp(camera: Camera) -> float | None:
    try:
        return camera.temperature()
    except Exception:
        return None


def _lock_key(ident: dict[str, str]) -> str:
    # a real camera is one device whatever port it is on (serial); a simulated one is one object (port)
    who = ident["serial"] if ident["serial"] and ident["backend"] != "mock" else ident["port"]
    return _safe(f"{ident['backend']}-{ident['model']}-{who}")
