"""Batch reprocessing: many runs merged on dask.distributed into one run archive.

:func:`find_runs` turns the folders given into :class:`RunSource` (file paths only: capture
run folders through their ``manifest.jsonl``, or folders of raw brackets); :func:`merge_run` is
the task a worker runs for one run: it reads the frames itself, merges them with
:func:`pipeline.merge.files.merge_files` exactly as ``hdrcap merge`` does, and writes the run's
chunk files straight into the archive at a slot of its own (:func:`hdrcap.batch.archive.write_run`);
:func:`run_batch` sends one task per run to a local cluster or a scheduler and commits the runs
as they are reported (the runs reported while the previous commit was made go together into one
commit: a rewrite of a few small metadata files), records failures and skips runs already there.

Over the network go the task (a run's file paths and the merge settings, a few kB) and the
worker's report (the run's folder, slot and size, and its calibration record): the raw frames
and the merged arrays never leave the worker. Only a worker that does not see the archive's
file system sends the arrays (12 bytes per photosite) to the client, which writes them.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import hashlib
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.options import MergeOptions, as_strategy

if TYPE_CHECKING:
    from distributed import Client

    from hdrcap.batch.archive import ArchiveRun, ArchiveWriter, RunEntry, Target
    from hdrcap.pipeline.params import Calibration
    from hdrcap.pipeline.result import HdrResult

__all__ = [
    "RunSource",
    "BatchSettings",
    "RunOutcome",
    "BatchReport",
    "find_runs",
    "merge_run",
    "run_batch",
    "calibration_identity",
]


@dataclass(frozen=True)
class RunSource:
    """The files of one run (paths only; the worker reads them).

    Parameters
    ----------
    folder : str
        The run folder, absolute; the run's identity in the archive.
    frames : tuple of str
        Light frames (raw files), in capture order.
    darks : tuple of str
        Dark frames.
    start_time : str or None
        Start of the run (ISO 8601) from its manifest; None: from the first frame.
    plan : dict or None
        The planner's plan recorded in the manifest (per-exposure dark strategies, decided options).
    dark_strategy : str or None
        The capture plan's dark strategy for every exposure (None: mixed or unknown).
    """

    folder: str
    frames: tuple[str, ...]
    darks: tuple[str, ...] = ()
    start_time: str | None = None
    plan: dict[str, Any] | None = None
    dark_strategy: str | None = None


@dataclass(frozen=True)
class BatchSettings:
    """How every run is merged: the options of ``hdrcap merge``.

    Parameters
    ----------
    calibration : str or None
        Calibration file (read on the worker); or
    camera : str or None
        a simulator preset.
    options : MergeOptions
        Merge options (default: ``hdrcap merge``'s).
    given : frozenset of str
        Names of the options the user set (they win over a plan's).
    weighting : str
        ``optimal`` or a baseline of :mod:`pipeline.merge.weighting`.
    dark_strategy : str or None
        One dark strategy for every exposure (None: the run's own, else the merge's default).
    master_dark_frames : float or None
        Frames averaged into each dark file of a master exposure.
    calibration_id : dict
        Calibration identity recorded with every run (:func:`calibration_identity`).
    sigma_precision : str
        Storage precision of the uncertainty channels, as ``hdrcap merge --sigma-precision``
        (the archive holds the values an EXR of ``hdrcap merge`` would hold).
    calibration_mismatch : {"refuse", "warn"}
        A calibration made for another camera than a run's frames: the run fails (one line),
        or is merged with a warning (``hdrcap merge --calibration-mismatch``).
    """

    calibration: str | None
    camera: str | None
    options: MergeOptions = field(default_factory=lambda: MergeOptions(exposure_times="effective"))
    given: frozenset[str] = frozenset()
    weighting: str = "optimal"
    dark_strategy: str | None = None
    master_dark_frames: float | None = None
    calibration_id: dict[str, Any] = field(default_factory=dict)
    sigma_precision: str = "auto"
    calibration_mismatch: str = "refuse"


@dataclass(frozen=True)
class RunOutcome:
    """What a worker sends back for one run: where it wrote the run (None if it failed or did not
    see the archive), the run itself only when it did not write it (no shared file system, or no
    archive given), warnings, merge seconds (wall clock), the one-line error of a run that failed
    on bad input, and the worker process's CPU seconds during the task (all its threads: the
    merge kernel's too)."""

    entry: RunEntry | None
    run: ArchiveRun | None
    warnings: tuple[str, ...]
    seconds: float
    error: str | None = None
    cpu_seconds: float = 0.0


@dataclass
class BatchReport:
    """What a batch did: runs committed (folder -> run number), skipped (already in the
    archive), failed (folder -> error), warnings, wall-clock seconds, and the seconds spent
    merging (summed over the workers) and committing (on the client), the CPU seconds of the
    workers' tasks (summed), of the client process (scheduling, communication, commits; a local
    cluster's scheduler runs in it) in all and until the cluster was ready (the start-up:
    imports, finding the runs, opening the archive, starting the cluster), and of the client's
    commits alone; the number of commits; the seconds of the start-up. CPU seconds do not
    depend on what else the machine runs."""

    archive: str
    committed: dict[str, int] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    merge_seconds: float = 0.0
    commit_seconds: float = 0.0
    merge_cpu_seconds: float = 0.0
    client_cpu_seconds: float = 0.0
    startup_cpu_seconds: float = 0.0
    commit_cpu_seconds: float = 0.0
    commits: int = 0
    startup_seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "archive": self.archive,
            "committed": len(self.committed),
            "skipped": len(self.skipped),
            "failed": self.failed,
            "warnings": self.warnings,
            "seconds": round(self.seconds, 3),
            "merge_seconds": round(self.merge_seconds, 3),
            "commit_seconds": round(self.commit_seconds, 3),
            "merge_cpu_seconds": round(self.merge_cpu_seconds, 3),
            "client_cpu_seconds": round(self.client_cpu_seconds, 3),
            "startup_cpu_seconds": round(self.startup_cpu_seconds, 3),
            "commit_cpu_seconds": round(self.commit_cpu_seconds, 3),
            "commits": self.commits,
            "startup_seconds": round(self.startup_seconds, 3),
        }


# --------------------------------------------------------------------------- finding runs
def _capture_run(folder: Path) -> RunSource:
    from hdrcap.acquire.capture.manifest import Manifest

    man = Manifest(folder)
    head = man.header() or {}
    recs = sorted(man.frames().values(), key=lambda r: r.get("index", 0))
    lights = tuple(str(folder / r["file"]) for r in recs if r.get("kind") == "light")
    darks = tuple(str(folder / r["file"]) for r in recs if r.get("kind") == "dark")
    if not lights:
        raise InputError(f"{folder}: its manifest.jsonl records no light frame")
    plan = (head.get("planning") or {}).get("plan") or None
    strategy = (head.get("plan") or {}).get("dark_strategy")
    return RunSource(
        str(folder), lights, darks, head.get("time"), plan, None if strategy in (None, "mixed") else strategy
    )


def _bracket_run(folder: Path) -> RunSource:
    from hdrcap.pipeline.io.raw import RAW_EXTENSIONS

    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RAW_EXTENSIONS)
    darks = tuple(str(p) for p in files if "dark" in p.stem.lower())
    lights = tuple(str(p) for p in files if "dark" not in p.stem.lower())
    if not lights:
        raise InputError(
            f"{folder}: no manifest.jsonl and no raw file ({', '.join(sorted(RAW_EXTENSIONS))}); not a run folder"
        )
    return RunSource(str(folder), lights, darks)


def find_runs(paths: Sequence[Path]) -> list[RunSource]:
    """The runs of ``paths``: capture run folders (with ``manifest.jsonl``: its light and dark
    frames, start time and plan) or folders of raw files (files whose name holds ``dark`` are
    the dark frames). Each folder once, in the order given.

    Parameters
    ----------
    paths : sequence of Path
        Folders.

    Returns
    -------
    list of RunSource
    """
    from hdrcap.acquire.capture.manifest import MANIFEST_NAME

    out: list[RunSource] = []
    seen: set[str] = set()
    for p in paths:
        folder = Path(p).resolve()
        if not folder.is_dir():
            raise InputError(f"{p}: not a folder (give run folders or folders of raw brackets)")
        if str(folder) in seen:
            continue
        seen.add(str(folder))
        out.append(_capture_run(folder) if (folder / MANIFEST_NAME).is_file() else _bracket_run(folder))
    if not out:
        raise InputError("no run folder given")
    return out


def calibration_identity(calibration: str | None, camera: str | None) -> dict[str, Any]:
    """The calibration identity recorded with every run: its file and the file's sha256, or
    the preset's name."""
    if calibration:
        from hdrcap.pipeline.io.files import sha256_file

        path = Path(calibration)
        if not path.is_file():
            raise InputError(f"{calibration}: no such calibration file")
        return {"file": str(path.resolve()), "sha256": sha256_file(path)}
    return {"preset": camera}


# --------------------------------------------------------------------------- the task
@functools.lru_cache(maxsize=4)
def _calibration(calibration: str | None, camera: str | None) -> Calibration:
    """The calibration, loaded once per worker process."""
    from hdrcap.acquire.camera.model import camera_model

    return camera_model(calibration, camera)


def _start_time(source: RunSource, result: HdrResult) -> str:
    if source.start_time:
        return source.start_time
    stamps = result.header.get("capture_times") or [None]
    stamp = stamps[0]
    if stamp:  # EXIF writes 2024:05:01 12:00:00
        date, _, clock = str(stamp).strip().partition(" ")
        iso = f"{date.replace(':', '-')}T{clock}" if clock else date.replace(":", "-")
        try:
            _dt.datetime.fromisoformat(iso)
            return iso
        except ValueError:
            pass
    first = min(os.stat(p).st_mtime for p in source.frames)
    return _dt.datetime.fromtimestamp(first, _dt.UTC).isoformat()


def merge_run(source: RunSource, settings: BatchSettings, target: Target | None = None) -> RunOutcome:
    """Merge one run on the worker, as ``hdrcap merge`` would (the same
    :func:`pipeline.merge.files.merge_files` and EXR content, the run's recorded plan and dark
    strategy unless the settings override them), and write it into the archive.

    Parameters
    ----------
    source : RunSource
        The run's files.
    settings : BatchSettings
        The merge settings.
    target : Target or None
        The archive's writer session: if this worker sees it, the run's chunk files are written
        there (:func:`hdrcap.batch.archive.write_run`) and only their entry is sent back.

    Returns
    -------
    RunOutcome
        The run's entry (or the run itself, float32 channels as in the EXR, when it was not
        written), warnings, seconds; or the one-line error of a run that failed on bad input
        (other exceptions propagate).
    """
    from hdrcap.pipeline.errors import HdrcapError

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        out = _merge_run(source, settings, target, t0)
    except HdrcapError as err:  # bad input: a one-line error, no worker traceback in the log
        out = RunOutcome(None, None, (), time.perf_counter() - t0, _describe(err))
    return dataclasses.replace(out, cpu_seconds=time.process_time() - c0)


def _merge_run(source: RunSource, settings: BatchSettings, target: Target | None, t0: float) -> RunOutcome:
    from hdrcap.batch.archive import ArchiveRun, write_run
    from hdrcap.pipeline.io.exr import as_stored
    from hdrcap.pipeline.merge.files import MergeRequest, library_root, merge_files
    from hdrcap.pipeline.schema import storage_precision

    calib = _calibration(settings.calibration, settings.camera)
    plan = None
    if source.plan is not None and settings.weighting == "optimal":
        from hdrcap.pipeline.planfile import check_plan

        plan = check_plan(source.plan, f"{source.folder}/manifest.jsonl")
    strategy = settings.dark_strategy or (None if plan is not None else source.dark_strategy)
    options, given = settings.options, settings.given
    if strategy and options.dark_strategy is None:
        options = dataclasses.replace(options, dark_strategy=as_strategy(strategy))
        given = given | {"dark_strategy"} if settings.dark_strategy else given
    warnings: list[str] = []
    result = merge_files(
        MergeRequest(
            frames=[Path(f) for f in source.frames],
            calibration=calib,
            dark_library=library_root(calib, settings.calibration),
            options=options,
            darks=[Path(d) for d in source.darks],
            master_dark_frames=settings.master_dark_frames,
            plan=plan,
            given=given,
            weighting=settings.weighting,
            tiling=None,
            calibration_mismatch=settings.calibration_mismatch,
        ),
        warn=warnings.append,
    )
    stored = as_stored(result.channels(), storage_precision(result.channels(), settings.sigma_precision))
    run = ArchiveRun(
        folder=source.folder,
        start_time=_start_time(source, result),
        channels=stored,
        header=result.header,
        exposure_times=list(result.header.get("exposure_times") or []),
        plan=source.plan,
        merge_options={"weighting": settings.weighting, "merge": result.header.get("merge")},
        calibration=dict(settings.calibration_id, params=calib.params.to_dict(), provenance=calib.provenance),
    )
    entry = None if target is None else write_run(target, run)
    return RunOutcome(entry, run if entry is None else None, tuple(warnings), time.perf_counter() - t0)


# --------------------------------------------------------------------------- the driver
#: Dask settings of a local cluster. Its scheduler and the workers' nannies run in the client's
#: process: event-loop health checks (they only time warnings of a blocked loop) every second
#: rather than every 20 ms, the resource monitor (it feeds the dashboard, which a batch does not
#: start) every 2 s without disk counters, and the nannies' memory checks every second rather
#: than every 0.1 s, take most of an idle local cluster's CPU off the client. The workers run
#: no statistical profiler: its sampling every 10 ms cost about a tenth of a run's CPU seconds,
#: counted as the merge's.
_LOCAL_CLUSTER_CONFIG = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.admin.system-monitor.disk": False,
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.worker.profile.enabled": False,
}


def _prepare_worker() -> None:
    """Import the merge kernels and set numba's CPU target up in a worker before its first task
    (:func:`hdrcap.pipeline.merge.accumulator.import_kernels`): the fixed cost of a worker
    process, paid by every worker at once while the cluster starts, not in its first run."""
    from hdrcap.pipeline.merge.accumulator import import_kernels

    import_kernels()()


def _prepared(client: Client) -> Client:
    """``client`` once every worker it has has run :func:`_prepare_worker` (a worker that joins
    later pays it in its first run instead); a failure is left to the runs to report."""
    try:
        client.run(_prepare_worker)
    except Exception:  # noqa: BLE001, S110  (the merge itself reports what is wrong)
        pass
    return client


@contextmanager
def _client(workers: int | None, scheduler: str | None, threads: int | None = None) -> Iterator[Client]:
    """A dask.distributed client: of the scheduler at ``scheduler`` (the workers' reports, a few
    kB each, come through it: the client needs to reach the scheduler only), or of a local
    cluster of ``workers`` worker processes running one task at a time, each with ``threads``
    threads for the merge kernel (default: its share of the cores; reports fetched from the
    workers directly)."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield _prepared(client)
        return
    n = workers or max(1, (os.cpu_count() or 1))
    per_worker = str(threads or max(1, (os.cpu_count() or 1) // n))
    env = {"NUMBA_NUM_THREADS": per_worker, "OMP_NUM_THREADS": per_worker}
    with (
        dask.config.set(_LOCAL_CLUSTER_CONFIG),
        LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, env=env) as cluster,
        Client(cluster, direct_to_workers=True) as client,
    ):
        yield _prepared(client)


def _describe(err: BaseException) -> str:
    from hdrcap.pipeline.errors import HdrcapError

    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    return text if isinstance(err, HdrcapError) else f"{type(err).__name__}: {text}"


def _task_key(source: RunSource) -> str:
    return "hdrcap-merge-" + hashlib.sha256(source.folder.encode()).hexdigest()[:16]


def run_batch(
    paths: Sequence[Path],
    archive: str | os.PathLike[str],
    settings: BatchSettings,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    threads: int | None = None,
    force: bool = False,
    progress: bool | None = None,
    on_submit: Callable[[Client], None] | None = None,
) -> BatchReport:
    """Merge the runs of ``paths`` on dask.distributed into ``archive``.

    Runs already in the archive are skipped unless ``force`` (then rewritten in place). One
    task per run, which writes the run into the archive; the client commits the runs reported
    (together, in one commit, when several are). A run whose task fails is recorded in the
    archive with its error and the others go on; a task whose worker dies is re-run by Dask. The
    archive's writer lock is held for the whole batch (a second batch into it waits).

    Parameters
    ----------
    paths : sequence of Path
        Run folders or folders of raw brackets.
    archive : str or Path
        The ``.zarr`` archive (created if missing).
    settings : BatchSettings
        The merge settings.
    workers : int or None
        Worker processes of the local cluster (default: one per core).
    scheduler : str or None
        Address of a running Dask scheduler (instead of a local cluster).
    threads : int or None
        Merge-kernel threads per local worker (default: the cores divided among the workers).
    force : bool
        Merge runs already in the archive again.
    progress : bool or None
        Progress bar with ETA (default: on a terminal).
    on_submit : callable or None
        Called with the client once the tasks are submitted (tests use it to kill a worker).

    Returns
    -------
    BatchReport
    """
    from hdrcap.batch.archive import Archive

    t0, c0 = time.perf_counter(), time.process_time()
    sources = find_runs(paths)
    report = BatchReport(str(archive))
    with Archive(archive).writer() as session:
        todo = [s for s in sources if force or s.folder not in session.committed]
        report.skipped = [s.folder for s in sources if s not in todo]
        if todo:
            _run_tasks(
                todo, settings, session, report, (workers, scheduler, threads), force, progress, on_submit, (t0, c0)
            )
    report.seconds = time.perf_counter() - t0
    report.client_cpu_seconds = time.process_time() - c0
    return report


class _Committer:
    """The client's side of a batch: takes the workers' reports and commits them."""

    def __init__(self, session: ArchiveWriter, report: BatchReport, force: bool) -> None:
        self.session, self.report, self.force = session, report, force
        self.warnings: dict[str, tuple[str, ...]] = {}

    def take(self, source: RunSource, status: str, result: Any) -> None:
        """One finished task: its status and its :class:`RunOutcome`, or what
        ``as_completed(..., raise_errors=False)`` gives for a task that raised (``(type,
        exception, traceback)``) or was cancelled (the exception)."""
        try:
            if status != "finished":
                raise result[1] if isinstance(result, tuple) else result
            out: RunOutcome = result
            self.report.merge_seconds += out.seconds
            self.report.merge_cpu_seconds += out.cpu_seconds
            if out.error is not None:
                raise InputError(out.error)
            entry = out.entry
            if entry is None and out.run is not None:  # the worker did not see the archive: write it here
                entry = self.session.write(out.run)
            if entry is None:
                raise InputError("the worker returned no run")
            self.warnings[source.folder] = out.warnings
            self.session.add(entry, replace=self.force)
        except Exception as err:  # any failure of one run: recorded, the batch goes on
            message = _describe(err)
            self.session.fail(source.folder, message)
            self.report.failed[source.folder] = message

    def commit(self, final: bool = False) -> int:
        """Commit what can be; returns the number of runs committed."""
        t0, c0 = time.perf_counter(), time.thread_time()
        landed = self.session.commit(final=final)
        self.report.commit_seconds += time.perf_counter() - t0
        self.report.commit_cpu_seconds += time.thread_time() - c0
        self.report.commits = self.session.commits
        for folder, i in landed.items():
            self.report.committed[folder] = i
            self.report.warnings.extend(f"{folder}: {w}" for w in self.warnings.pop(folder, ()))
        return len(landed)


def _run_tasks(
    todo: list[RunSource],
    settings: BatchSettings,
    session: ArchiveWriter,
    report: BatchReport,
    cluster: tuple[int | None, str | None, int | None],
    force: bool,
    progress: bool | None,
    on_submit: Callable[[Client], None] | None,
    began: tuple[float, float],
) -> None:
    """Submit one task per run; commit the runs reported (or record their failure) as they come.
    ``cluster``: the workers, scheduler and threads of :func:`_client`; ``began``: the clock and
    the client's CPU seconds when the batch began (the start-up is counted from then)."""
    from distributed import as_completed
    from tqdm import tqdm

    committer = _Committer(session, report, force)
    with _client(*cluster) as client:
        report.startup_seconds = time.perf_counter() - began[0]
        report.startup_cpu_seconds = time.process_time() - began[1]
        futures = [client.submit(merge_run, s, settings, session.target, key=_task_key(s), pure=False) for s in todo]
        sources = {f.key: s for f, s in zip(futures, todo)}
        if on_submit is not None:
            on_submit(client)
        show = sys.stderr.isatty() if progress is None else progress
        with tqdm(total=len(todo), desc="batch", unit="run", disable=not show, dynamic_ncols=True) as bar:
            # the runs reported while the previous commit was made are committed together
            for done in as_completed(futures, with_results=True, raise_errors=False).batches():
                for fut, result in done:
                    committer.take(sources[fut.key], fut.status, result)
                    fut.release()
                committer.commit()
                bar.update(len(done))
        committer.commit(final=True)
