"""Capture sessions: run a plan of exposures (with dark frames and calibration series) on a
:class:`acquire.camera.Camera`, survive its faults, and leave a verified, hashed, resumable
record of every frame.

Guarantees
----------
* Every planned frame ends up in the run folder exactly once, under a name derived from its
  unique plan key (``frames/0007_light_0.004s.dng``); a file is never overwritten.
* A frame is recorded in the manifest only after it was verified: it opens with
  :func:`pipeline.io.read_frame`, its size is the camera's and the exposure time in the file
  is the one the camera reported applying. Its sha256 is recorded.
* Busy cameras are retried with exponential backoff; disconnects and hangs cause a reconnect
  (a new camera object) and a retry; bad files are captured again; card full and camera gone
  stop the session with a one-line message. The manifest is left consistent in every case.
* ``resume=True`` continues an interrupted run: frames in the manifest are kept (after their
  hash is checked), a frame whose file landed but was not yet recorded is verified and
  adopted, unfinished downloads are discarded, and only the missing frames are captured.
* A lock on the run folder and one on the camera stop two sessions from colliding.
* Each verified light frame is handed to the merge (``pipeline.merge.MergeAccumulator``) as
  it lands, with the dark strategy the plan gives its exposure time.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from hdrcap.pipeline.darks import DarkResolver
from hdrcap.pipeline.errors import HdrcapError, InputError
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.times import ExposureMap, find_exposure, same_bulb_exposure, same_exposure

from .camera import CameraError, CorruptFrameError, fault_kind, nearest_allowed
from .manifest import EventLog, Manifest, utc_now

__all__ = [
    "FrameSpec",
    "CapturePlan",
    "RetryPolicy",
    "LightBlocker",
    "SessionError",
    "SessionResult",
    "CaptureSession",
    "StreamingMerge",
    "frame_stem",
    "lock_dir",
]

#: Frame kinds; the first two feed the HDR merge, the rest are calibration series.
LIGHT_KINDS = ("light", "flat", "saturation")
DARK_KINDS = ("dark", "bias", "darkseries")
KINDS = ("light", "dark", "bias", "flat", "saturation", "darkseries")


class SessionError(HdrcapError):
    """The session stopped (camera gone, card full, gave up retrying, locked run folder)."""

    exit_code = 4


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
    """

    key: str
    kind: str
    exposure_s: float

    @property
    def dark(self) -> bool:
        return self.kind in DARK_KINDS


def frame_stem(index: int, spec: FrameSpec) -> str:
    return f"{index:04d}_{spec.kind}_{spec.exposure_s:.6g}s"


def _strategies_by_time(times: list[float], dark_strategy) -> ExposureMap[DarkStrategy]:
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


def _frame_specs(frames: list[tuple[str, float, int]]) -> tuple[FrameSpec, ...]:
    """FrameSpecs of (kind, exposure time, repetition) in order, keyed ``kind-time-n``."""
    out, seen = [], {}
    for kind, t, _j in frames:
        base = f"{kind}-{t:.6g}"
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.append(FrameSpec(key=f"{base}-{n}", kind=kind, exposure_s=t))
    return tuple(out)


def _strategy(value) -> DarkStrategy:
    try:
        return DarkStrategy(value)
    except ValueError:
        raise InputError(f"dark strategy must be matched, master or model, got {value!r}") from None


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
    def bracket(cls, times: Sequence[float], allowed: Sequence[float] | None = None,
                dark_strategy: str | Sequence[str] = DarkStrategy.MATCHED, n_dark: int = 1, repeats: int = 1,
                series: Sequence[dict] = (), library_times: Sequence[float] = ()) -> "CapturePlan":
        """A bracket of ``times`` (each snapped to the nearest ``allowed`` time), ``repeats``
        frames per time, dark frames per dark strategy and calibration ``series`` (dicts with
        ``kind``, ``times``, ``count``). ``dark_strategy`` is one strategy for all exposures or
        one per entry of ``times`` (a planner's per-exposure choice). Frames needing the light
        blocked come first, so the light is blocked once. ``library_times``: exposure times
        whose master dark comes from the dark library (no dark frames are captured for them;
        only ``master`` times qualify)."""
        snap = (lambda t: nearest_allowed(t, allowed)) if allowed else float
        times = [snap(float(t)) for t in times]
        by_time = _strategies_by_time(times, dark_strategy)
        uniq = sorted(by_time)
        lib = [t for t in uniq if by_time[t] is DarkStrategy.MASTER and find_exposure(t, library_times) is not None]
        per_time = dict(_DARK_FRAMES, **{DarkStrategy.MASTER: max(1, int(n_dark))})
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
        return cls(frames=_frame_specs(dark_frames + light_frames), dark_strategy=uniform,
                   n_dark=max(1, int(n_dark)) if master else 1, library_times=tuple(lib), time_strategies=pairs)

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
    def from_dict(cls, d: dict) -> "CapturePlan":
        """The plan recorded in a manifest (:meth:`to_dict`; also manifests written before
        per-exposure strategies)."""
        return cls(tuple(FrameSpec(**f) for f in d["frames"]), d["dark_strategy"], d["n_dark"],
                   tuple(d.get("library_times", ())),
                   tuple((float(t), str(s)) for t, s in d.get("time_strategies", ())))

    def fingerprint(self) -> str:
        blob = json.dumps([[f.key, f.kind, f.exposure_s] for f in self.frames] + [self.dark_strategy, self.n_dark]
                          + ([list(self.library_times)] if self.library_times else [])
                          + ([[list(p) for p in self.time_strategies]] if self.time_strategies else []))
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        out = {"dark_strategy": self.dark_strategy, "n_dark": self.n_dark, "library_times": list(self.library_times),
               "frames": [asdict(f) for f in self.frames], "fingerprint": self.fingerprint()}
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
    """

    def __init__(self, method: str = "mock", cover_command: str | None = None, uncover_command: str | None = None,
                 prompt: Callable[[str], Any] | None = None, settle_s: float = 0.0):
        if method not in ("mock", "prompt", "command", "none"):
            raise InputError(f"light blocking must be mock, prompt, command or none, got {method!r}")
        if method == "command" and not (cover_command and uncover_command):
            raise InputError("light blocking by command needs cover_command and uncover_command")
        self.method = method
        self.cover_command = cover_command
        self.uncover_command = uncover_command
        self.prompt = prompt or _default_prompt
        self.settle_s = settle_s
        self.covered: bool | None = None

    def set(self, camera, covered: bool, log: EventLog | None = None) -> None:
        if self.covered is covered:
            return
        if self.method == "prompt":
            self.prompt("Block the light for dark frames (cap the lens), then press Enter" if covered
                        else "Unblock the light (remove the cap), then press Enter")
        elif self.method == "command":
            cmd = self.cover_command if covered else self.uncover_command
            proc = subprocess.run(cmd, shell=True, capture_output=True, text=True)
            if proc.returncode != 0:
                raise SessionError(f"light {'cover' if covered else 'uncover'} command {cmd!r} failed "
                                   f"(exit {proc.returncode}): {proc.stderr.strip()[:200]}")
        (camera.cover if covered else camera.uncover)()
        if self.settle_s:
            time.sleep(self.settle_s)
        self.covered = covered
        if log:
            log.emit("light", covered=covered, method=self.method)


def _default_prompt(message: str) -> None:
    if not sys.stdin or not sys.stdin.isatty():
        raise SessionError(f"light blocking needs a person at a terminal ({message}); "
                           "use block_light = \"command\" for unattended runs")
    input(message + " ")


def lock_dir() -> Path:
    """Folder of the per-camera lock files (``HDRCAP_LOCK_DIR`` or the system temp folder)."""
    d = Path(os.environ.get("HDRCAP_LOCK_DIR") or Path(tempfile.gettempdir()) / "hdrcap-locks")
    d.mkdir(parents=True, exist_ok=True)
    return d


def _identity(camera) -> dict:
    ident = getattr(camera, "identity", None)
    if ident is None:
        return {"backend": type(camera).__name__, "model": "", "serial": "", "port": ""}
    return {k: str(getattr(ident, k, "")) for k in ("backend", "model", "serial", "port")}


class StreamingMerge:
    """Feeds verified frames to the merge as they land.

    Uses ``pipeline.merge.MergeAccumulator``; each light frame is added with the dark
    strategy of its exposure time (``strategy_for``) and the dark level that
    :class:`pipeline.darks.DarkResolver` serves it: ``matched`` the dark frame of that time,
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
        Further :class:`pipeline.merge.MergeOptions` fields (iterations, saturation, prnu, ...).
        ``exposure_times`` defaults to ``"effective"``: :meth:`result` estimates each frame's
        effective exposure time from the frames (``pipeline.exposure_ratio``) before the
        iterations.
    """

    def __init__(self, calibration, shape, strategy_for: Callable[[float], str] | str = DarkStrategy.MATCHED,
                 options: dict | None = None):
        from hdrcap.pipeline.merge import MergeAccumulator

        self.calibration = calibration
        self.shape = tuple(shape)
        self.strategy_for = (lambda _t, s=strategy_for: s) if isinstance(strategy_for, str) else strategy_for
        self._darks = DarkResolver()
        self.streamed = True
        opts = {k: v for k, v in (options or {}).items() if k not in ("dark_strategy", "n_dark")}
        opts.setdefault("exposure_times", "effective")  # estimated by the accumulator at the end
        uniform = strategy_for if isinstance(strategy_for, str) and strategy_for != "mixed" else None
        self._acc = MergeAccumulator(calibration, self.shape, dark_strategy=uniform, **opts)

    def add_dark(self, values: np.ndarray, t: float) -> None:
        """A dark frame (DN) of exposure ``t`` (s)."""
        try:
            self._darks.add_dark(values, t)
        except InputError as err:  # after its light frames
            raise SessionError(str(err)) from None

    def add_master(self, values: np.ndarray, t: float, n_frames: int = 1) -> None:
        """A master dark (DN) for exposure ``t`` from the dark library, averaged from ``n_frames``."""
        self._darks.add_master(values, t, int(n_frames))

    def add_light(self, values: np.ndarray, t: float) -> None:
        """A light frame (DN) of exposure ``t`` (s), merged with the dark level that serves it."""
        strategy = DarkStrategy(self.strategy_for(t))
        src = self._darks.resolve(t, strategy)
        if src is None:
            raise SessionError(f"no dark frame for exposure {t:g} s ({strategy} dark strategy) before its light frame")
        self._acc.add(values, t, src.data, strategy=strategy,
                      n_dark=src.n_frames if strategy is DarkStrategy.MASTER else None)

    def result(self):
        """The :class:`pipeline.merge.MergeResult` of everything added."""
        if not len(self._acc):
            raise SessionError("no light frames to merge")
        return self._acc.result()


@dataclass
class SessionResult:
    """What a session produced."""

    run_dir: Path
    frames: dict[str, dict]
    captured: int
    resumed: int
    adopted: int
    retries: dict[str, int] = field(default_factory=dict)
    merge: Any = None
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
        Options of the merge (:class:`pipeline.merge.MergeOptions` fields such as iterations,
        saturation, prnu), e.g. the planner's decisions.
    """

    def __init__(self, camera, run_dir, plan: CapturePlan, calibration=None, light: LightBlocker | None = None,
                 retry: RetryPolicy | None = None, resume: bool = False, progress: bool | None = None,
                 meta: dict | None = None, sleep: Callable[[float], None] = time.sleep, check_dark: float = 0.05,
                 master_darks: dict | None = None, merge_options: dict | None = None):
        self.camera = camera
        self.run_dir = Path(run_dir)
        self.plan = plan
        self.calibration = calibration
        self.light = light or LightBlocker("mock")
        self.retry = retry or RetryPolicy()
        self.resume = resume
        self.progress = progress
        self.meta = meta or {}
        self.sleep = sleep
        self.check_dark = check_dark
        self.master_darks: ExposureMap[tuple] = ExposureMap((float(t), v) for t, v in (master_darks or {}).items())
        self.merge_options = dict(merge_options or {})
        missing = [t for t in plan.library_times if t not in self.master_darks]
        if missing:
            raise SessionError(f"no master dark for {missing[0]:g} s in the dark library the plan relies on")
        self.retries: dict[str, int] = {}
        self.shape = tuple(getattr(camera, "shape", ()) or ()) or None

    # ------------------------------------------------------------------ public
    def run(self) -> SessionResult:
        from filelock import FileLock, Timeout

        t0 = time.monotonic()
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(f"{self.run_dir}: cannot create the run folder ({err.strerror})") from None
        if not os.access(self.run_dir, os.W_OK):
            raise InputError(f"{self.run_dir}: run folder is not writable")
        ident = _identity(self.camera)
        run_lock = FileLock(str(self.run_dir / ".hdrcap.lock"))
        cam_lock = FileLock(str(lock_dir() / (_lock_key(ident) + ".lock")))
        try:
            run_lock.acquire(timeout=0)
        except Timeout:
            raise SessionError(f"{self.run_dir}: another hdrcap session is using this run folder") from None
        try:
            try:
                cam_lock.acquire(timeout=0)
            except Timeout:
                raise SessionError(f"camera {ident['model']} ({ident['serial'] or ident['port']}) is in use "
                                   "by another hdrcap session") from None
            try:
                return self._run_locked(ident, t0)
            finally:
                cam_lock.release()
        finally:
            run_lock.release()

    # ------------------------------------------------------------------ internals
    def _run_locked(self, ident: dict, t0: float) -> SessionResult:
        manifest = Manifest(self.run_dir)
        log = EventLog(self.run_dir)
        frames_dir = self.run_dir / "frames"
        partial_dir = self.run_dir / ".partial"
        frames_dir.mkdir(exist_ok=True)
        done, resumed = self._open_manifest(manifest, log, ident)
        if partial_dir.exists():  # downloads that never finished
            shutil.rmtree(partial_dir)
        partial_dir.mkdir()
        adopted = self._adopt_landed(done, frames_dir, ident, manifest, log)
        merger = self._replay(done)
        captured, merger = self._capture_missing(done, merger, ident, manifest, log, partial_dir, frames_dir)
        result = SessionResult(self.run_dir, done, captured, resumed, adopted, dict(self.retries))
        if merger is not None:
            result.merge = merger.result()
            log.emit("merged", streamed=merger.streamed, info=_jsonable(result.merge.info))
        shutil.rmtree(partial_dir, ignore_errors=True)
        result.elapsed_s = time.monotonic() - t0
        log.emit("done", captured=captured, resumed=resumed, adopted=adopted, retries=self.retries,
                 elapsed_s=round(result.elapsed_s, 3))
        return result

    def _open_manifest(self, manifest: Manifest, log: EventLog, ident: dict) -> tuple[dict[str, dict], int]:
        """Start the manifest, or (resume) check it was made from this plan and void the frames
        whose file is missing or changed. Returns (frames recorded by key, their number)."""
        fp = self.plan.fingerprint()
        if not manifest.exists():
            manifest.append({"type": "run", "time": utc_now(), "plan_fingerprint": fp, "camera": ident,
                             "plan": self.plan.to_dict(), **self.meta})
            log.emit("start", frames=len(self.plan.frames), camera=ident, run_dir=str(self.run_dir))
            return {}, 0
        if not self.resume:
            raise SessionError(f"{self.run_dir}: holds an earlier run (manifest.jsonl); use --resume "
                               "to continue it or choose another run folder")
        head = manifest.header()
        if head is not None and head.get("plan_fingerprint") != fp:
            raise SessionError(f"{self.run_dir}: the run there was made from a different plan; "
                               "resume with the same job or choose another run folder")
        done = manifest.frames()
        bad = manifest.verify_hashes()
        for key in bad:
            rec = done.pop(key)
            self._quarantine(self.run_dir / rec["file"], "hash mismatch or missing")
            manifest.append({"type": "void", "key": key, "reason": "file missing or hash mismatch",
                             "time": utc_now()})
            log.emit("void", key=key, file=rec["file"])
        log.emit("resume", frames_done=len(done), torn_manifest_lines=manifest.torn_lines, voided=len(bad))
        return done, len(done)

    def _adopt_landed(self, done: dict, frames_dir: Path, ident: dict, manifest: Manifest, log: EventLog) -> int:
        """Verify and record the frames whose file landed but whose manifest line was never
        written (bad ones are quarantined); returns how many were adopted."""
        adopted = 0
        for i, spec in enumerate(self.plan.frames):
            if spec.key in done:
                continue
            for f in sorted(frames_dir.glob(frame_stem(i, spec) + ".*")):
                try:
                    rec = self._verify_and_record(f, i, spec, None, ident, manifest, adopted=True)
                except CorruptFrameError as err:
                    self._quarantine(f, str(err))
                    log.emit("reject", key=spec.key, file=f.name, reason=str(err))
                    continue
                done[spec.key] = rec
                adopted += 1
                log.emit("adopt", key=spec.key, file=rec["file"])
        return adopted

    def _replay(self, done: dict) -> StreamingMerge | None:
        """The merge of the frames recorded before a resume, in capture order."""
        from hdrcap.pipeline.io import read_frame

        merger = None
        if self.calibration is not None:
            for rec in sorted(done.values(), key=lambda r: r["index"]):
                if rec["kind"] in ("light", "dark"):
                    merger = self._feed(merger, rec, read_frame(self.run_dir / rec["file"]).data)
        return merger

    def _capture_missing(self, done: dict, merger: StreamingMerge | None, ident: dict, manifest: Manifest,
                         log: EventLog, partial_dir: Path, frames_dir: Path) -> tuple[int, StreamingMerge | None]:
        """Capture every planned frame not yet done (light blocked as each needs), feeding the
        merge; a stop is logged with its reason. Returns (frames captured, the merge)."""
        from tqdm import tqdm

        todo = [(i, s) for i, s in enumerate(self.plan.frames) if s.key not in done]
        show = self.progress if self.progress is not None else sys.stderr.isatty()
        bar = tqdm(total=len(self.plan.frames), initial=len(self.plan.frames) - len(todo), desc="capture",
                   unit="frame", disable=not show, dynamic_ncols=True)
        captured = 0
        try:
            for i, spec in todo:
                self.light.set(self.camera, spec.dark, log)
                rec, values = self._capture_one(i, spec, ident, manifest, log, partial_dir, frames_dir)
                done[spec.key] = rec
                captured += 1
                if self.calibration is not None:
                    merger = self._feed(merger, rec, values)
                bar.update(1)
            if self.light.covered:
                self.light.set(self.camera, False, log)
        except CameraError as err:
            log.emit("stop", reason=str(err), kind=fault_kind(err))
            raise
        except SessionError as err:
            log.emit("stop", reason=str(err))
            raise
        except OSError as err:  # our side: disk full, permissions
            log.emit("stop", reason=f"{type(err).__name__}: {err}")
            raise SessionError(f"{err.filename or self.run_dir}: {err.strerror or err}; free space or fix "
                               "permissions, then run again with --resume") from None
        except BaseException as err:
            log.emit("stop", reason=f"{type(err).__name__}: {err}")
            raise
        finally:
            bar.close()
        return captured, merger

    def _feed(self, merger: StreamingMerge | None, rec: dict, values: np.ndarray) -> StreamingMerge | None:
        """Hand a verified frame to the merge (created with the first frame: its size)."""
        if rec["kind"] not in ("light", "dark"):
            return merger
        if merger is None:
            strategy = self.plan.dark_strategy if not self.plan.time_strategies else self.plan.strategy_for
            merger = StreamingMerge(self.calibration, values.shape, strategy, self.merge_options)
            for t, (data, n) in self.master_darks.items():
                merger.add_master(data, t, n)
        if rec["kind"] == "dark":
            merger.add_dark(values, rec["file_exposure_s"])
        else:
            merger.add_light(values, rec["file_exposure_s"])
        return merger

    def _capture_one(self, i: int, spec: FrameSpec, ident: dict, manifest: Manifest, log: EventLog,
                     partial_dir: Path, frames_dir: Path):
        last = None
        for attempt in range(1, self.retry.max_attempts + 1):
            tmp = partial_dir / f"{frame_stem(i, spec)}.try{attempt}.dng"
            try:
                started = utc_now()
                applied = float(self.camera.set_exposure(spec.exposure_s))
                timeout = None if self.retry.timeout_s is None else applied + self.retry.timeout_s
                res = self.camera.capture(tmp, dark=spec.dark, timeout=timeout)
                if getattr(res, "bulb", False):  # timed around the release: the measured open time
                    applied = float(res.applied_exposure_s)
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
                kind = fault_kind(err)
                if kind is None:
                    raise
                last = err
                self.retries[kind] = self.retries.get(kind, 0) + 1
                log.emit("fault", key=spec.key, attempt=attempt, kind=kind, error=f"{type(err).__name__}: {err}")
                for f in partial_dir.glob(f"{frame_stem(i, spec)}.try{attempt}*"):
                    f.unlink(missing_ok=True)
                if kind == "fatal":
                    raise SessionError(f"camera stopped the session at frame {spec.key}: {err} "
                                       f"({len(manifest.frames())} frames are safe; fix it and run again with --resume)") from None
                if attempt == self.retry.max_attempts:
                    break
                wait = self.retry.wait(attempt)
                if kind in ("busy", "reconnect"):
                    self.sleep(wait)
                if kind == "reconnect":
                    self._reconnect(log)
        raise SessionError(f"frame {spec.key}: gave up after {self.retry.max_attempts} attempts "
                           f"(last: {last}); run again with --resume")

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

    def _verify(self, path: Path, spec: FrameSpec, applied: float, res) -> tuple[dict, np.ndarray]:
        """Open the file and check its size and exposure time (CorruptFrameError if not)."""
        from hdrcap.pipeline.io import IMAGE_EXTENSIONS, RAW_EXTENSIONS, read_frame

        if path.suffix.lower() not in RAW_EXTENSIONS | IMAGE_EXTENSIONS:
            raise SessionError(f"{spec.key}: the camera delivers {path.suffix or 'unnamed'} files, not raw; set its "
                               "image format to RAW (job: [camera] settings = {{ imageformat = \"RAW\" }})")
        try:
            frame = read_frame(path)
        except (InputError, OSError, ValueError) as err:
            raise CorruptFrameError(f"{path.name}: {err}") from None
        if self.shape is None:
            self.shape = frame.shape
        if frame.shape != self.shape:
            raise CorruptFrameError(f"{path.name}: size {frame.shape} differs from the camera's {self.shape}")
        if spec.dark and self.check_dark:
            black = frame.black_level or 0.0
            white = frame.white_level or 65535.0
            level = float((np.median(frame.data) - black) / max(white - black, 1.0))
            if level > self.check_dark:
                raise SessionError(f"{spec.key}: the light is not blocked (dark frame median at {level:.1%} of the "
                                   f"range); check the light blocking ({self.light.method}) and run again with --resume")
        bulb = bool(getattr(res, "bulb", False))
        if not (same_bulb_exposure if bulb else same_exposure)(frame.exposure_time, applied):
            raise CorruptFrameError(f"{path.name}: exposure {frame.exposure_time:g} s in the file, "
                                    f"camera reported {applied:g} s")
        rec = {
            "type": "frame",
            "key": spec.key,
            "kind": spec.kind,
            "dark": spec.dark,
            "requested_exposure_s": spec.exposure_s,
            "applied_exposure_s": applied,
            "file_exposure_s": frame.exposure_time,
            "iso": frame.iso,
            "shape": list(frame.shape),
            "temperature_c": getattr(res, "temperature_c", None) if res is not None else _temp(self.camera),
            "settings": _jsonable(getattr(res, "settings", {}) if res is not None else {}),
            "camera_file": getattr(res, "camera_file", "") if res is not None else "",
        }
        return rec, frame.data

    def _record_fields(self, final: Path, i: int, spec: FrameSpec, ident: dict) -> dict:
        from hdrcap.pipeline.io import sha256_file

        return {"file": str(final.relative_to(self.run_dir)), "sha256": sha256_file(final),
                "bytes": final.stat().st_size, "index": i, "camera": ident}

    def _verify_and_record(self, path: Path, i: int, spec: FrameSpec, res, ident, manifest: Manifest,
                           adopted: bool = False) -> dict:
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


def _link_new(src: Path, dst: Path) -> None:
    """Put ``src`` at ``dst`` without ever replacing an existing file."""
    try:
        os.link(src, dst)
    except FileExistsError:
        raise SessionError(f"{dst}: exists already; the run folder is inconsistent") from None


def _temp(camera) -> float | None:
    try:
        return camera.temperature()
    except Exception:
        return None


def _lock_key(ident: dict) -> str:
    import re

    # a real camera is one device whatever port it is on (serial); a simulated one is one object (port)
    who = ident["serial"] if ident["serial"] and ident["backend"] != "mock" else ident["port"]
    key = f"{ident['backend']}-{ident['model']}-{who}"
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", key)


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
