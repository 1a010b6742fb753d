"""What a finished run tells the outside: its JSON error object (:func:`error_summary`) and the
job's ``[notify]`` hooks (:func:`notify`)."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from hdrcap.acquire.capture.job import Job
from hdrcap.acquire.capture.manifest import jsonable

__all__ = ["error_summary", "notify"]


def error_summary(err: BaseException, n: int | None = None) -> dict:
    """The JSON error object of a failed run: ``status`` ``"failed"``, ``error`` (the one-line
    message), ``exit_code``, ``error_type``, ``run_dir`` (when known) and ``repetition``.

    Parameters
    ----------
    err : BaseException
        What stopped the run.
    n : int, optional
        Repetition number.

    Returns
    -------
    dict
    """
    out = {
        "status": "failed",
        "error": str(err),
        "exit_code": int(getattr(err, "exit_code", 70)),
        "error_type": type(err).__name__,
        "run_dir": getattr(err, "run_dir", None),
    }
    n = n if n is not None else getattr(err, "repetition", None)
    if n is not None:
        out["repetition"] = n
    return out


def notify(job: Job, summary: dict, echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr)) -> None:
    """Run the job's notification hook: ``[notify] on_done`` after a run that ended well (also a
    no-op resume), ``on_failure`` after one that failed. The command runs with the shell, the
    summary as JSON on its stdin and ``HDRCAP_STATUS``, ``HDRCAP_EXIT_CODE``, ``HDRCAP_RUN_DIR``,
    ``HDRCAP_JOB`` and ``HDRCAP_MESSAGE`` in its environment; a hook that fails or outlasts
    ``timeout_s`` is reported as a warning and changes nothing else.

    Parameters
    ----------
    job : Job
    summary : dict
        The run's summary (:func:`acquire.capture.run.run_job`) or error summary
        (:func:`error_summary`).
    echo : callable
        Where warnings go.
    """
    import json
    import subprocess

    hooks = job["notify"]
    failed = summary.get("status") == "failed"
    cmd = hooks.get("on_failure" if failed else "on_done")
    if not cmd:
        return
    try:
        proc = subprocess.run(
            cmd,
            shell=True,
            input=json.dumps(jsonable(summary)),
            text=True,
            env=_hook_environment(job, summary),
            capture_output=True,
            timeout=hooks["timeout_s"],
        )
    except subprocess.TimeoutExpired:
        echo(f"hdrcap: warning: notification hook {cmd!r} took longer than {hooks['timeout_s']:g} s; stopped")
        return
    except OSError as err:
        echo(f"hdrcap: warning: notification hook {cmd!r} could not run: {err}")
        return
    if proc.returncode != 0:
        echo(f"hdrcap: warning: notification hook {cmd!r} failed (exit {proc.returncode}): {proc.stderr.strip()[:200]}")


def _hook_environment(job: Job, summary: dict) -> dict[str, str]:
    return dict(
        os.environ,
        HDRCAP_STATUS=str(summary.get("status", "")),
        HDRCAP_JOB=job.name,
        HDRCAP_EXIT_CODE=str(summary.get("exit_code", 0)),
        HDRCAP_RUN_DIR=str(summary.get("run_dir") or ""),
        HDRCAP_MESSAGE=str(summary.get("error") or summary.get("message") or ""),
    )
