"""Run folders of a job: the folder of a new run (``[output] folder`` with ``{job}``, ``{n}``,
``{date}`` filled in), the run ``--resume`` continues, and whether a run is complete."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from hdrcap.acquire.capture.job import Job, JobError

__all__ = ["run_folder", "resume_folder", "run_state", "NothingToResume"]


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

    m = Manifest(run_dir)
    head = m.header() or {}
    started = str(head.get("time") or _dt.datetime.fromtimestamp(run_dir.stat().st_mtime, _dt.UTC).isoformat())
    done = m.completion()
    if done is None:
        return "incomplete", started
    outputs = done.get("outputs")
    if outputs is None:
        outputs = [job["output"][k] for k in ("exr", "png") if job["output"][k]]
    if all((run_dir / name).is_file() for name in outputs):  # an absolute name stays absolute
        return "complete", started
    return "incomplete", started
