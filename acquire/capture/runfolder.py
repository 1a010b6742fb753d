"""Run folders of a job: the folder of a new run (``[output] folder`` with ``{job}``, ``{n}``,
``{date}`` filled in), the run ``--resume`` continues, whether a run is complete, and the state
of any run folder (running, complete, stopped, failed) for those who watch it."""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

from hdrcap.acquire.capture.job import Job, JobError
from hdrcap.acquire.capture.manifest import EventLog, ManifestScan

__all__ = [
    "run_folder",
    "resume_folder",
    "run_state",
    "run_status",
    "run_is_active",
    "is_run_folder",
    "RunStatus",
    "RUN_STATES",
    "STOP_EXIT_CODES",
    "NothingToResume",
]


class NothingToResume(JobError):
    """``--resume`` found no earlier run of the job (a no-op for ``hdrcap run``)."""


def run_folder(job: Job, n: int = 0, resume: bool = False) -> Path:
    """The run folder of repetition ``n`` (``{job}``, ``{n}``, ``{date}`` are filled in).

    A new run with ``{date}`` in the pattern gets a folder that does not exist yet: when the
    name is taken (two starts within one second, as ``--repeat N`` does), the date gets a
    suffix ``-2``, ``-3``, ... (two processes racing for one name collide on the run folder's
    lock and the second stops with exit status 5). With ``resume`` the
    folder of the newest incomplete run, else of the newest complete one (:func:`resume_folder`).

    Parameters
    ----------
    job : Job
    n : int
        Repetition number (0-based).
    resume : bool
        Find the run to continue instead of a new folder.

    Returns
    -------
    Path
        The run folder.

    Raises
    ------
    NothingToResume
        With ``resume``, when no earlier run of the job exists.
    """
    pattern = job["output"]["folder"]
    base = str(job.resolve(pattern))
    if resume:
        found = resume_folder(job, n)
        if found is None:
            raise NothingToResume(
                f"{job.where('output', 'folder')}: --resume: no earlier run folder matches "
                f"{base.format(job=job.name, n=n, date='*')}"
            )
        return found
    if "{date}" not in pattern:
        return Path(base.format(job=job.name, n=n, date=""))
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    for k in range(1, 10000):
        folder = Path(base.format(job=job.name, n=n, date=stamp if k == 1 else f"{stamp}-{k}"))
        if not folder.exists():
            return folder
    raise JobError(f"{job.where('output', 'folder')}: no free run folder name for {base}")


def resume_folder(job: Job, n: int = 0) -> Path | None:
    """The run folder ``--resume`` continues: the newest run of the job whose manifest has no
    ``complete`` record (or that was stopped while metering: ``meter/`` but no manifest), else
    the newest complete one (resuming it re-reports its summary), else None. Newest by the
    start time in the manifest header, then by the folder's modification time.

    Parameters
    ----------
    job : Job
    n : int
        Repetition number filled into ``{n}``.

    Returns
    -------
    Path or None
    """
    glob = str(job.resolve(job["output"]["folder"])).format(job=job.name, n=n, date="*")
    root = Path("/") if glob.startswith("/") else Path(".")
    found = [f for f in root.glob(glob.lstrip("/")) if (f / "manifest.jsonl").is_file() or (f / "meter").is_dir()]
    if not found:
        return None
    states = {f: run_state(job, f) for f in found}
    for wanted in ("incomplete", "complete"):
        runs = [f for f in found if states[f][0] == wanted]
        if runs:
            return max(runs, key=lambda f: (states[f][1], f.stat().st_mtime, str(f)))
    return None


def run_state(job: Job, run_dir: Path) -> tuple[str, str]:
    """(``"complete"`` or ``"incomplete"``, start time) of the run in ``run_dir``. Complete: the
    manifest has a ``complete`` record (written once every output was) and every output it
    names still exists (records written before they named theirs: the job's EXR and PNG in
    the run folder). A run killed between its outputs, or whose preview was deleted, is
    incomplete: ``--resume`` writes what is missing.

    Parameters
    ----------
    job : Job
    run_dir : Path

    Returns
    -------
    tuple of str
        The state and the run's start time (ISO 8601).
    """
    from hdrcap.acquire.capture.manifest import Manifest

    scan = Manifest(run_dir).scan()
    head = scan.header or {}
    started = str(head.get("time") or _dt.datetime.fromtimestamp(run_dir.stat().st_mtime, _dt.UTC).isoformat())
    outputs = [job["output"][k] for k in ("exr", "png") if job["output"][k]]
    return ("complete" if _is_complete(scan, run_dir, outputs) else "incomplete"), started


def _is_complete(scan: ManifestScan, run_dir: Path, outputs: list[str]) -> bool:
    """Complete: a ``complete`` record and every output it declares (``outputs``, names in the
    run folder, for a record that declares none) there; an interrupted output step is not."""
    done = scan.completion
    if done is None:
        return False
    declared = done.get("outputs")
    names = outputs if declared is None else declared
    return all((Path(run_dir) / name).is_file() for name in names)  # an absolute name stays absolute


#: The states of :class:`RunStatus`.
RUN_STATES = ("running", "complete", "stopped", "failed")
#: Exit statuses of a stop someone asked for (SIGINT, SIGTERM): such a run is "stopped".
STOP_EXIT_CODES = (130, 143)


@dataclass(frozen=True)
class RunStatus:
    """What a run folder tells about its run, read without its frames (:func:`run_status`).

    Attributes
    ----------
    state : str
        ``running`` (a process holds the run's lock), ``complete`` (outputs written),
        ``stopped`` (by SIGINT/SIGTERM, exit status 130/143: ``--resume`` continues it) or
        ``failed`` (stopped by an error, with its exit status; or ended without a stop event:
        killed, power lost; ``exit_code`` None then).
    started : str or None
        Start of the run, ISO 8601 (the manifest's run record; else the folder's time).
    updated : str or None
        Time of the last event (or of the completion), ISO 8601.
    frames_done, frames_planned : int, int or None
        Frames recorded in the manifest, and planned (None before the plan is recorded).
    exit_code : int or None
        Exit status of the stop (``acquire.capture.session.EXIT_CODES``).
    message : str or None
        Why the run stopped or failed, or what it is doing.
    job : str or None
        The job's name.
    camera : str or None
        The camera model.
    target_snr_db, predicted_snr_db : float or None
        The planner's target SNR and the minimum it predicted (dB, 20 log10); None for a
        fixed bracket.
    eta_s : float or None
        Capture time left after the last frame, s (a running run's).
    last_event : dict or None
        The last event of ``events.jsonl``.
    """

    state: str
    started: str | None
    updated: str | None
    frames_done: int
    frames_planned: int | None
    exit_code: int | None
    message: str | None
    job: str | None
    camera: str | None
    target_snr_db: float | None
    predicted_snr_db: float | None
    eta_s: float | None
    last_event: dict | None


def is_run_folder(path: Path) -> bool:
    """Whether ``path`` is a run folder: it has a manifest, an event log, or metering frames
    (a run stopped before its plan was recorded).

    Parameters
    ----------
    path : Path

    Returns
    -------
    bool
    """
    from hdrcap.acquire.capture.manifest import EVENTS_NAME, MANIFEST_NAME

    return (path / MANIFEST_NAME).is_file() or (path / EVENTS_NAME).is_file() or (path / "meter").is_dir()


def run_status(run_dir: Path, held: frozenset[tuple[int, int, int]] | None = None, exr: str = "hdr.exr") -> RunStatus:
    """The state of the run in ``run_dir`` from its manifest, its event log and its locks, read
    one line at a time (memory bounded by the number of frame keys, never the frames).

    Parameters
    ----------
    run_dir : Path
        The run folder.
    held : frozenset, optional
        The locks held (:func:`acquire.capture.session.held_locks`; read here when not given).
        Where they cannot be read (not Linux) a run that is neither complete nor stopped counts
        as running.
    exr : str
        Name of the EXR output, for a ``complete`` record that does not list its outputs.

    Returns
    -------
    RunStatus
    """
    from hdrcap.acquire.capture.manifest import EventLog, Manifest

    run_dir = Path(run_dir)
    scan = Manifest(run_dir).scan()
    head = scan.header or {}
    ev = _scan_events(EventLog(run_dir))
    active = run_is_active(run_dir, held)
    planned = len(head["plan"]["frames"]) if isinstance(head.get("plan"), dict) and "frames" in head["plan"] else None
    exit_code, message, updated = None, None, ev["time"]
    if _is_complete(scan, run_dir, [exr]):
        state = "complete"
        updated = (scan.completion or {}).get("time") or updated
    elif active:
        state = "running"
        message = "capturing" if scan.header else "metering and planning"
    elif ev["stop"] is not None:
        exit_code = ev["stop"].get("exit_code")
        state = "stopped" if exit_code in STOP_EXIT_CODES else "failed"
        message = ev["stop"].get("reason")
    elif active is None:  # no lock information: neither complete nor stopped
        state = "running"
        message = "no stop event (whether a process still runs it cannot be told on this system)"
    else:
        state = "failed"
        captured_all = ev["done"] or (planned is not None and len(scan.keys) >= planned)
        message = (
            "stopped before its plan was recorded (metering or planning failed, or the process was killed)"
            if scan.header is None
            else "every frame captured, but the run ended before its outputs were written (no stop event: "
            "hdrcap's own output tells why)"
            if captured_all
            else "ended without a stop event (the process was killed or the machine lost power)"
        )
    planning = head.get("planning") or {}
    plan = planning.get("plan") or {}
    started = head.get("time")
    if started is None and run_dir.exists():
        started = _dt.datetime.fromtimestamp(run_dir.stat().st_mtime, _dt.UTC).isoformat()
    return RunStatus(
        state=state,
        started=started,
        updated=updated,
        frames_done=len(scan.keys),
        frames_planned=planned,
        exit_code=exit_code,
        message=message,
        job=head.get("job_name"),
        camera=(head.get("camera") or {}).get("model"),
        target_snr_db=plan.get("target_snr_db"),
        predicted_snr_db=planning.get("predicted_min_snr_db"),
        eta_s=ev["eta_s"] if state == "running" else None,
        last_event=ev["last"],
    )


def run_is_active(run_dir: Path, held: frozenset[tuple[int, int, int]] | None = None) -> bool | None:
    """Whether a process is running the run in ``run_dir``: it holds one of the run's locks
    (:func:`acquire.capture.session.run_lock_files`), seen without taking a lock.

    Parameters
    ----------
    run_dir : Path
    held : frozenset, optional
        :func:`acquire.capture.session.held_locks` (read here when not given).

    Returns
    -------
    bool or None
        None where the locks held cannot be read (not Linux).
    """
    from hdrcap.acquire.capture.session import held_locks, lock_is_held, run_lock_files

    held = held_locks() if held is None else held
    if held is None:
        return None
    return any(lock_is_held(f, held) for f in run_lock_files(run_dir))


def _scan_events(log: EventLog) -> dict:
    """One pass over the event log: the last event, its time, and (since the last start or
    resume) the stop event, whether the session finished, and the last frame's ETA."""
    out: dict = {"last": None, "time": None, "stop": None, "done": False, "eta_s": None}
    for _pos, rec in log.read_from(0):
        if rec is None:
            continue
        kind = rec.get("event")
        if kind in ("start", "resume"):
            out.update(stop=None, done=False, eta_s=None)
        elif kind == "stop":
            out["stop"] = rec
        elif kind == "done":
            out["done"] = True
        elif kind == "frame":
            out["eta_s"] = rec.get("eta_s")
        out["last"], out["time"] = rec, rec.get("time")
    return out
