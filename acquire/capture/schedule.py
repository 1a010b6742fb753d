"""Repetitions of a job: ``[schedule] repeat`` runs, one started every ``every_s`` seconds,
each reported (and notified) as it ends (:func:`run_schedule`)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdrcap.acquire.capture.job import Job, JobError
from hdrcap.acquire.capture.notify import error_summary, notify
from hdrcap.acquire.capture.run import run_job

if TYPE_CHECKING:
    from hdrcap.acquire.capture.session import StopEvent
    from hdrcap.pipeline.errors import HdrcapError

__all__ = ["run_schedule", "ScheduleError"]


class ScheduleError(JobError):
    """Some repetitions of a ``--keep-going`` schedule failed (each already reported); the exit
    status is the first failure's."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code
        self.reported = True


def run_schedule(
    job: Job,
    *,
    repeat: int | None = None,
    every_s: float | None = None,
    resume: bool = False,
    progress: bool | None = None,
    echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr),
    run_dir: Path | None = None,
    force: bool = False,
    sleep: Callable[[float], object] = time.sleep,
    keep_going: bool = False,
    on_result: Callable[[dict[str, Any]], None] | None = None,
    stop: StopEvent | None = None,
) -> list[dict[str, Any]]:
    """Run the job ``repeat`` times, starting one every ``every_s`` seconds (a slow run delays
    the next start rather than overlapping it).

    Parameters
    ----------
    job : Job
    repeat : int, optional
        Repetitions (default: the job's ``[schedule] repeat``).
    every_s : float, optional
        Seconds between starts (default: the job's ``[schedule] every_s``).
    resume : bool
        Each repetition continues its newest incomplete run (see
        :func:`acquire.capture.run.run_job`).
    run_dir : Path, optional
        Folder pattern overriding ``[output] folder`` (needs ``{n}`` with ``repeat > 1``).
    keep_going : bool
        A failed repetition is reported (``status`` ``"failed"``) and the schedule goes on;
        at the end :class:`ScheduleError` carries the first failure's exit status.
    on_result : callable, optional
        Called with each repetition's summary (or error summary,
        :func:`acquire.capture.notify.error_summary`) as it ends.
    stop : threading.Event, optional
        Set by SIGTERM/SIGINT: the running repetition ends cleanly and no further one starts.

    Returns
    -------
    list of dict
        The summaries, in order.

    Raises
    ------
    HdrcapError
        The first failure (without ``keep_going``), or :class:`ScheduleError`.
    """
    from hdrcap.acquire.capture.session import RunInterrupted
    from hdrcap.pipeline.errors import HdrcapError

    repeat = repeat if repeat is not None else job["schedule"]["repeat"]
    every_s = every_s if every_s is not None else job["schedule"]["every_s"]
    if repeat > 1 and run_dir is not None and "{n" not in str(run_dir):
        raise JobError("--run-dir with --repeat needs {n} in the folder name")
    wait: Callable[[float], object] = stop.wait if stop is not None and sleep is time.sleep else sleep
    t0 = time.monotonic()
    results: list[dict[str, Any]] = []
    failures: list[HdrcapError] = []
    for n in range(repeat):
        _wait_for_start(t0 + n * every_s, wait, stop, f"before repetition {n + 1} of {repeat}")
        rd = Path(str(run_dir).format(n=n, job=job.name)) if run_dir else None
        try:
            res = run_job(job, resume=resume, n=n, run_dir=rd, progress=progress, echo=echo, force=force, stop=stop)
        except HdrcapError as err:
            res = _report_failure(job, err, n, echo, on_result if keep_going else None)
            if not keep_going or isinstance(err, RunInterrupted):
                raise
            failures.append(err)
            results.append(res)
            continue
        res["repetition"] = n
        notify(job, res, echo)
        results.append(res)
        if on_result is not None:
            on_result(res)
    if failures:
        raise ScheduleError(
            f"{len(failures)} of {repeat} repetitions failed (first: {failures[0]})", failures[0].exit_code
        )
    return results


def _wait_for_start(start: float, wait: Callable[[float], object], stop: StopEvent | None, when: str) -> None:
    """Wait until ``start`` (``time.monotonic``); RunInterrupted when ``stop`` is set by then."""
    from hdrcap.acquire.capture.session import RunInterrupted

    delay = start - time.monotonic()
    if delay > 0:
        wait(delay)
    if stop is not None and stop.is_set():
        raise RunInterrupted(f"stopped by signal {stop.signum} {when}", stop.signum)


def _report_failure(
    job: Job,
    err: HdrcapError,
    n: int,
    echo: Callable[[str], None],
    on_result: Callable[[dict[str, Any]], None] | None,
) -> dict[str, Any]:
    """The error summary of failed repetition ``n``, notified (and passed to ``on_result``)."""
    err.repetition = n
    res = error_summary(err, n)
    notify(job, res, echo)
    if on_result is not None:
        on_result(res)
        err.reported = True  # the caller's report was this one (no second JSON object)
    return res
