"""One run of a job: meter -> plan -> capture -> merge -> outputs, in its run folder under
its locks, resumable after any interruption (:func:`run_job`)."""

from __future__ import annotations

import datetime as _dt
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, overload

from hdrcap.acquire.capture.camera_setup import (
    check_compatibility,
    check_job_against_camera,
    job_calibration,
    job_camera_key,
    open_camera,
    run_iso,
)
from hdrcap.acquire.capture.job import Job
from hdrcap.acquire.capture.manifest import Manifest, jsonable
from hdrcap.acquire.capture.outputs import _plan_merge_options, _write_outputs
from hdrcap.acquire.capture.planning import library_masters, library_root, plan_for
from hdrcap.acquire.capture.runfolder import NothingToResume, run_folder, run_state

if TYPE_CHECKING:
    from hdrcap.acquire.camera import Camera
    from hdrcap.acquire.capture.session import (
        CapturePlan,
        LocalIOError,
        RetryPolicy,
        SessionResult,
        StopEvent,
    )
    from hdrcap.pipeline.compat import CameraProfile
    from hdrcap.pipeline.params import Calibration

__all__ = ["run_job"]


@overload
def run_job(
    job: Job,
    *,
    resume: bool = ...,
    n: int = ...,
    run_dir: Path | None = ...,
    progress: bool | None = ...,
    echo: Callable[[str], None] = ...,
    camera: Camera | None = ...,
    force: bool = ...,
    exr_path: Path | None = ...,
    png_path: Path | None = ...,
    return_result: Literal[False] = ...,
    stop: StopEvent | None = ...,
) -> dict[str, Any]: ...


@overload
def run_job(
    job: Job,
    *,
    resume: bool = ...,
    n: int = ...,
    run_dir: Path | None = ...,
    progress: bool | None = ...,
    echo: Callable[[str], None] = ...,
    camera: Camera | None = ...,
    force: bool = ...,
    exr_path: Path | None = ...,
    png_path: Path | None = ...,
    return_result: Literal[True],
    stop: StopEvent | None = ...,
) -> tuple[dict[str, Any], SessionResult | None]: ...


def run_job(
    job: Job,
    *,
    resume: bool = False,
    n: int = 0,
    run_dir: Path | None = None,
    progress: bool | None = None,
    echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr),
    camera: Camera | None = None,
    force: bool = False,
    exr_path: Path | None = None,
    png_path: Path | None = None,
    return_result: bool = False,
    stop: StopEvent | None = None,
) -> dict[str, Any] | tuple[dict[str, Any], SessionResult | None]:
    """Run one repetition of ``job``.

    With ``resume`` the newest incomplete run of the job is continued (one whose frames are
    all recorded but whose outputs or completion record are missing gets them: the recorded
    frames are merged again); on a complete run nothing is done and its recorded summary is
    returned (``status`` ``"already_complete"``), with no run at all ``status`` is
    ``"nothing_to_resume"``.

    Parameters
    ----------
    job : Job
    resume : bool
        Continue an interrupted run (see :func:`acquire.capture.runfolder.resume_folder`).
    n : int
        Repetition number (seed offset of the simulated camera, ``{n}`` of the folder).
    run_dir : Path, optional
        The run folder (default: the job's ``[output] folder``).
    camera : Camera, optional
        An open camera (default: :func:`acquire.capture.camera_setup.open_camera`, closed at
        the end).
    exr_path, png_path : Path, optional
        Override the job's outputs (which lie inside the run folder).
    return_result : bool
        Also return the :class:`acquire.capture.session.SessionResult` (None for a no-op).
    stop : threading.Event, optional
        Ends the capture cleanly when set (:func:`acquire.capture.session.stop_on_signals`).

    Returns
    -------
    dict
        Summary: ``status``, run folder, frames, captured/resumed/adopted counts, retries,
        outputs (and the SessionResult when ``return_result``).

    Raises
    ------
    HdrcapError
        With the exit status of what stopped the run; ``err.run_dir`` names the run folder.
    """
    from hdrcap.acquire.capture.session import hold_run_locks
    from hdrcap.pipeline.errors import HdrcapError

    try:
        run_dir = Path(run_dir) if run_dir else run_folder(job, n, resume)
    except NothingToResume as err:
        echo(f"hdrcap: {err}; nothing to do")
        summary: dict[str, Any] = {"status": "nothing_to_resume", "run_dir": None, "message": str(err)}
        return (summary, None) if return_result else summary
    if resume and Manifest(run_dir).exists() and run_state(job, run_dir)[0] == "complete":
        done = Manifest(run_dir).completion()
        summary = dict(done["summary"]) if done else {"run_dir": str(run_dir)}
        summary["status"] = "already_complete"
        echo(f"hdrcap: {run_dir}: the run is complete; nothing to resume")
        return (summary, None) if return_result else summary
    try:
        with hold_run_locks(run_dir, job_camera_key(job) if camera is None else None):
            summary, result = _run_one(job, resume, n, run_dir, progress, echo, camera, force, exr_path, png_path, stop)
    except HdrcapError as err:
        err.run_dir = str(run_dir)
        raise
    except OSError as err:  # our side outside the session: metering files, outputs, disk full
        raise _local_io_error(err, run_dir) from None
    _record_complete(run_dir, summary, echo)
    return (summary, result) if return_result else summary


def _local_io_error(err: OSError, run_dir: Path) -> LocalIOError:
    """The LocalIOError (exit status 6) of a failure on our side of the run."""
    from hdrcap.acquire.capture.session import LocalIOError

    stop_err = LocalIOError(
        f"{err.filename or run_dir}: {err.strerror or err}; free space or fix permissions, then run again with --resume"
    )
    stop_err.run_dir = str(run_dir)
    return stop_err


def _record_complete(run_dir: Path, summary: dict[str, Any], echo: Callable[[str], None]) -> None:
    """The manifest's last record, ``complete`` with the summary and the outputs the run wrote
    (relative to the run folder when inside it: :func:`acquire.capture.runfolder.run_state`
    checks that they still exist); a failure is a warning."""
    outputs = [output_name(Path(summary[k]), run_dir) for k in ("exr", "png") if summary.get(k)]
    try:
        Manifest(run_dir).append(
            {
                "type": "complete",
                "time": _dt.datetime.now(_dt.UTC).isoformat(),
                "summary": jsonable(summary),
                "outputs": outputs,
            }
        )
    except OSError as err:
        echo(f"hdrcap: warning: {run_dir}: could not record the run as complete ({err.strerror or err})")


def _run_one(
    job: Job,
    resume: bool,
    n: int,
    run_dir: Path,
    progress: bool | None,
    echo: Callable[[str], None],
    camera: Camera | None,
    force: bool,
    exr_path: Path | None,
    png_path: Path | None,
    stop: StopEvent | None,
) -> tuple[dict[str, Any], SessionResult]:
    """Open the camera, plan (or read the plan of the run resumed), capture, merge and write the
    outputs; returns (summary, SessionResult)."""
    own = camera is None
    cam = camera or open_camera(job, n)
    try:
        check_job_against_camera(job, cam, echo)
        calibration = job_calibration(job)
        expect = check_compatibility(job, cam, calibration, echo)
        retry = _retry_policy(job)
        force = force or job["output"]["force"]
        exr_path, png_path = _output_paths(job, run_dir, exr_path, png_path)
        replace = _replaceable(run_dir, resume, force, (exr_path, png_path))
        _refuse_to_overwrite(run_dir, resume, replace)
        try:
            plan, info = _recorded_or_new_plan(job, cam, calibration, run_dir, resume, echo, retry, stop)
            planned = info.get("plan") or {}
            options = _plan_merge_options(planned)
            result = _capture(
                job, cam, calibration, run_dir, plan, info, options, n, resume, progress, retry, stop, expect
            )
            header = _planner_header(planned, options, info)
            outputs = _write_outputs(job, run_dir, result, calibration, cam, exr_path, png_path, replace, header)
        except BaseException as err:  # the session logs its own stops; metering and outputs here
            _log_stop(run_dir, err)
            raise
    finally:
        if own:
            try:
                cam.close()
            except Exception:
                pass
    return _summary(run_dir, result, outputs), result


def _log_stop(run_dir: Path, err: BaseException) -> None:
    """The ``stop`` event of a run that failed outside its capture session (metering, the
    merge's outputs), once the run folder exists; a local I/O error with exit status 6."""
    from hdrcap.acquire.capture.manifest import EventLog
    from hdrcap.acquire.capture.session import emit_stop

    if getattr(err, "stop_logged", False) or not run_dir.is_dir():
        return
    if isinstance(err, OSError):
        emit_stop(EventLog(run_dir), _local_io_error(err, run_dir))
        err.stop_logged = True  # type: ignore[attr-defined]
    else:
        emit_stop(EventLog(run_dir), err)


def _retry_policy(job: Job) -> RetryPolicy:
    from hdrcap.acquire.capture.session import RetryPolicy

    sess = job["session"]
    return RetryPolicy(sess["max_attempts"], sess["backoff_s"], sess["max_backoff_s"], sess["timeout_s"])


def _output_paths(
    job: Job, run_dir: Path, exr_path: Path | None, png_path: Path | None
) -> tuple[Path | None, Path | None]:
    """The EXR and PNG outputs: as given, else the job's inside the run folder (None: none)."""
    if exr_path is None and job["output"]["exr"]:
        exr_path = run_dir / job["output"]["exr"]
    if png_path is None and job["output"]["png"]:
        png_path = run_dir / job["output"]["png"]
    return exr_path, png_path


def output_name(path: Path, run_dir: Path) -> str:
    """An output's name as the completion record keeps it: relative to the run folder when
    inside it, else absolute."""
    try:
        return str(Path(path).absolute().relative_to(Path(run_dir).absolute()))
    except ValueError:
        return str(Path(path).absolute())


def _replaceable(run_dir: Path, resume: bool, force: bool, outputs: tuple[Path | None, ...]) -> dict[Path, bool]:
    """Output path -> whether it may replace an existing file: with ``force``, and on a resume
    for the outputs inside the run folder (the run's own, written again from the same frames)."""
    return {p: force or (resume and not Path(output_name(p, run_dir)).is_absolute()) for p in outputs if p is not None}


def _refuse_to_overwrite(run_dir: Path, resume: bool, replace: dict[Path, bool]) -> None:
    """RunConflictError for a new run in a folder with a run; OutputExistsError for an output
    that exists and may not be replaced (:func:`_replaceable`)."""
    from hdrcap.acquire.capture.session import RunConflictError
    from hdrcap.pipeline.io.files import check_new_output

    if not resume and Manifest(run_dir).exists():
        raise RunConflictError(
            f"{run_dir}: holds an earlier run (manifest.jsonl); use --resume to continue it or choose another run folder"
        )
    for p, may in replace.items():
        check_new_output(p, may)


def _recorded_or_new_plan(
    job: Job,
    camera: Camera,
    calibration: Calibration,
    run_dir: Path,
    resume: bool,
    echo: Callable[[str], None],
    retry: RetryPolicy,
    stop: StopEvent | None,
) -> tuple[CapturePlan, dict[str, Any]]:
    """(plan, planning info): the plan recorded at the start of the run resumed, else a new one."""
    from hdrcap.acquire.capture.session import CapturePlan

    head = Manifest(run_dir).header() if resume else None
    if head is not None:
        return CapturePlan.from_dict(head["plan"]), head.get("planning", {})
    if resume and Manifest(run_dir).exists() is False and run_dir.exists():
        echo(f"hdrcap: {run_dir}: stopped before its plan was recorded; starting the run again")
    return plan_for(job, camera, calibration, run_dir, echo, retry, stop)


def _capture(
    job: Job,
    camera: Camera,
    calibration: Calibration,
    run_dir: Path,
    plan: CapturePlan,
    info: dict[str, Any],
    options: dict[str, Any],
    n: int,
    resume: bool,
    progress: bool | None,
    retry: RetryPolicy,
    stop: StopEvent | None,
    expect: CameraProfile,
) -> SessionResult:
    """Capture ``plan`` in a :class:`acquire.capture.session.CaptureSession` (master darks
    from the dark library, the job's light blocking and dark check); returns its result."""
    from hdrcap.acquire.capture.session import CaptureSession, LightBlocker

    masters = None
    if plan.library_times:
        found = library_masters(
            library_root(job, calibration), camera, plan.library_times, iso=run_iso(job, calibration), strict=True
        )
        masters = {t: (data, n_frames) for t, (data, n_frames) in found.items() if data is not None}  # all: loaded
    d = job["darks"]
    light = LightBlocker(
        d["block_light"], d.get("cover_command"), d.get("uncover_command"), command_timeout_s=d["command_timeout_s"]
    )
    meta = {
        "job": str(job.path) if job.path else None,
        "job_name": job.name,
        "repetition": n,
        "planning": info,
        "calibration": calibration.provenance,
    }
    session = CaptureSession(
        camera,
        run_dir,
        plan,
        calibration=calibration,
        light=light,
        retry=retry,
        resume=resume,
        progress=progress,
        meta=meta,
        check_dark=d["check"],
        master_darks=masters,
        merge_options=options,
        stop=stop,
        expect=expect,
    )
    return session.run()


def _planner_header(planned: dict[str, Any], options: dict[str, Any], info: dict[str, Any]) -> dict[str, Any] | None:
    """The EXR header's planner attribute of a planned run (None for a fixed bracket)."""
    if not planned:
        return None
    from hdrcap.pipeline.planfile import planner_attribute

    return planner_attribute(
        planned, None, None, options, info.get("plan_overridden"), source="hdrcap run (planned from metering)"
    )


def _summary(run_dir: Path, result: SessionResult, outputs: dict[str, Any]) -> dict[str, Any]:
    return {
        "status": "done",
        "run_dir": str(run_dir),
        "frames": len(result.frames),
        "captured": result.captured,
        "resumed": result.resumed,
        "adopted": result.adopted,
        "retries": result.retries,
        "elapsed_s": round(result.elapsed_s, 3),
        "streamed_merge": result.merge is not None,
        **outputs,
    }
