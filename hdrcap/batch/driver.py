"""Batch reprocessing: many runs merged on local worker processes or dask.distributed into one run archive.

:func:`find_runs` turns the folders given into :class:`RunSource` (file paths only: capture
run folders through their ``manifest.jsonl``, or folders of raw brackets); :func:`merge_run` is
the task a worker runs for one run: it reads the frames itself, merges them with
:func:`pipeline.merge.files.merge_files` exactly as ``hdrcap merge`` does, and writes the run's
chunk files straight into the archive at a slot of its own (:func:`hdrcap.batch.archive.write_run`);
:func:`run_batch` gives one task per run to a pool of local worker processes (pebble: no Dask in
the client) or to a Dask scheduler, and commits the runs
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
import multiprocessing.context
import multiprocessing.process
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.options import MergeOptions, as_strategy

if TYPE_CHECKING:
    from multiprocessing.connection import Connection

    from distributed import Client
    from pebble import ProcessPool

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
#: Times a run is given to a worker process that then dies while merging it (killed, out of
#: memory, a crash in a library) before the run is recorded as failed.
WORKER_ATTEMPTS = 3

#: Seconds the local pool waits for its workers to be prepared before it takes the runs anyway.
_START_TIMEOUT = 600.0

#: What a finished task gives :meth:`_Committer.take`: the run, the task's status and outcome.
_Finished = tuple[RunSource, str, Any]


#: Why a local worker that imports the caller's script must not start a batch of its own.
_MAIN_GUARD = (
    'a script that calls run_batch must do so under `if __name__ == "__main__":` '
    "(each local worker imports the script as it starts)"
)


def _load_kernels() -> None:
    """Import numba and the merge kernels and set numba's CPU target up
    (:func:`hdrcap.pipeline.merge.accumulator.import_kernels`): a worker's fixed cost, paid by
    every worker at once before the runs are given out, not in the first run of each. A failure
    is left to the runs to report."""
    try:
        from hdrcap.pipeline.merge.accumulator import import_kernels

        import_kernels()()
    except Exception:  # noqa: BLE001, S110  (the merge itself reports what is wrong)
        pass


def _prepare_worker(threads: int, ready: Connection) -> None:
    """The start of a local worker process: ``threads`` merge-kernel threads (``NUMBA_NUM_THREADS``
    and ``OMP_NUM_THREADS`` before numba is imported, and numba's own setting if it already
    was), the kernels loaded (:func:`_load_kernels`), then a message on ``ready``."""
    os.environ["NUMBA_NUM_THREADS"] = os.environ["OMP_NUM_THREADS"] = str(threads)
    # A spawned worker's default start method is spawn: the locks a library makes in it (numcodecs'
    # blosc mutex, in the first chunk written) would be named semaphores left to the resource
    # tracker, which warns of them as leaked when the worker is stopped. The worker starts no process.
    multiprocessing.set_start_method("fork", force=True)
    try:
        _load_kernels()
        import numba

        numba.set_num_threads(min(threads, numba.get_num_threads()))
    finally:
        ready.send_bytes(b"ready")


class _SpawnContext(multiprocessing.context.SpawnContext):
    """multiprocessing's spawn context that keeps the processes it made (to see workers that
    end as they start)."""

    def __init__(self) -> None:
        super().__init__()
        self.made: list[multiprocessing.context.SpawnProcess] = []

    def Process(self, *args: Any, **kwargs: Any) -> multiprocessing.context.SpawnProcess:  # type: ignore[override]  # noqa: N802
        proc = multiprocessing.context.SpawnProcess(*args, **kwargs)
        self.made.append(proc)
        return proc


def _await_workers(n: int, ready: Connection, ctx: _SpawnContext) -> None:
    """Wait until ``n`` workers said they are ready on ``ready``, up to :data:`_START_TIMEOUT`
    seconds. Raises RuntimeError when ``n`` worker processes ended before any was ready."""
    deadline, got = time.monotonic() + _START_TIMEOUT, 0
    while got < n and time.monotonic() < deadline:
        if ready.poll(0.1):
            ready.recv_bytes()
            got += 1
            continue
        ended = [p.exitcode for p in ctx.made if p.exitcode is not None]
        if got == 0 and len(ended) >= n:
            raise RuntimeError(
                f"the batch's worker processes end as they start (exit status {ended[-1]}): {_MAIN_GUARD}"
            )


def _check_not_starting_a_worker() -> None:
    """Raises RuntimeError inside a local worker that is starting (importing the caller's main
    module, as spawned processes do): a script that calls :func:`run_batch` at its top level
    would otherwise start a batch in every worker (the check of ``multiprocessing`` itself
    comes only when a process is started, after the archive's lock)."""
    if getattr(multiprocessing.process.current_process(), "_inheriting", False):
        raise RuntimeError(f"run_batch called while a worker process starts: {_MAIN_GUARD}")


@contextmanager
def _local_pool(workers: int | None, threads: int | None) -> Iterator[ProcessPool]:
    """A pool of ``workers`` local worker processes (default: one per core), each a new
    interpreter (spawned, which imports the caller's main module) that merges one run at a time
    with ``threads`` merge-kernel threads (default: the cores shared among the workers), given
    once every worker is prepared (:func:`_prepare_worker`); stopped when the block ends. A
    worker that dies is replaced and the run it was merging ends with
    :class:`pebble.ProcessExpired`. Raises RuntimeError when the workers cannot start."""
    from pebble import ProcessPool

    cores = os.cpu_count() or 1
    n = workers or cores
    ctx = _SpawnContext()
    reader, writer = ctx.Pipe(duplex=False)
    pool = ProcessPool(
        max_workers=n, initializer=_prepare_worker, initargs=(threads or max(1, cores // n), writer), context=ctx
    )
    try:
        if pool.active:  # (asking starts the workers)
            _await_workers(n, reader, ctx)
        yield pool
    finally:
        pool.stop()
        pool.join()
        reader.close()
        writer.close()


def _pool_batches(
    pool: ProcessPool, todo: list[RunSource], args: tuple[Any, ...], task: Callable[..., Any] | None = None
) -> Iterator[list[_Finished]]:
    """Give each run of ``todo`` to ``pool`` now (``task(source, *args)``, default
    :func:`merge_run`) and return the runs as they finish, in batches: those that finished while
    the previous batch was taken. A run whose worker died is given again, up to
    :data:`WORKER_ATTEMPTS` times."""
    from concurrent.futures import FIRST_COMPLETED, Future, wait

    from pebble import ProcessExpired

    run = task or merge_run
    pending: dict[Future[Any], tuple[RunSource, int]] = {pool.schedule(run, (s, *args)): (s, 1) for s in todo}

    def batches() -> Iterator[list[_Finished]]:
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            batch: list[_Finished] = []
            for fut in done:
                source, attempt = pending.pop(fut)
                err = fut.exception()
                if isinstance(err, ProcessExpired) and attempt < WORKER_ATTEMPTS:
                    pending[pool.schedule(run, (source, *args))] = (source, attempt + 1)
                elif isinstance(err, ProcessExpired):
                    died = RuntimeError(
                        f"its worker process died (exit code {err.exitcode}) in each of {attempt} attempts"
                    )
                    batch.append((source, "error", (RuntimeError, died, None)))
                elif err is not None:
                    batch.append((source, "error", (type(err), err, None)))
                else:
                    batch.append((source, "finished", fut.result()))
            if batch:
                yield batch

    return batches()


@contextmanager
def _dask_client(scheduler: str) -> Iterator[Client]:
    """A dask.distributed client of the scheduler at ``scheduler``, once the workers it has
    have loaded the kernels (a worker that joins later pays it in its first run). The workers'
    reports, a few kB each, come through the scheduler: the client needs to reach it only."""
    from distributed import Client

    with Client(scheduler) as client:
        try:
            client.run(_load_kernels)
        except Exception:  # noqa: BLE001, S110  (the merge itself reports what is wrong)
            pass
        yield client


def _dask_batches(client: Client, todo: list[RunSource], args: tuple[Any, ...]) -> Iterator[list[_Finished]]:
    """Submit one :func:`merge_run` task per run of ``todo`` to ``client`` now and return the
    runs as they finish, in batches (Dask re-runs a task whose worker died)."""
    from distributed import as_completed

    futures = [client.submit(merge_run, s, *args, key=_task_key(s), pure=False) for s in todo]
    sources = {f.key: s for f, s in zip(futures, todo)}

    def batches() -> Iterator[list[_Finished]]:
        for done in as_completed(futures, with_results=True, raise_errors=False).batches():
            yield [(sources[fut.key], fut.status, result) for fut, result in done]
            for fut, _ in done:
                fut.release()

    return batches()


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
    """Merge the runs of ``paths`` into ``archive`` on local worker processes, or on the
    workers of a Dask scheduler.

    Runs already in the archive are skipped unless ``force`` (then rewritten in place). One
    task per run, which writes the run into the archive; the client commits the runs reported
    (together, in one commit, when several are). A run whose task fails is recorded in the
    archive with its error and the others go on; a run whose worker dies is merged again by
    another (a local one up to :data:`WORKER_ATTEMPTS` times, then recorded as failed; Dask
    re-runs it as its configuration allows). The archive's writer lock is held for the whole
    batch (a second batch into it waits). Local workers are spawned and import the caller's
    main module: a script must call this under ``if __name__ == "__main__":``.

    Parameters
    ----------
    paths : sequence of Path
        Run folders or folders of raw brackets.
    archive : str or Path
        The ``.zarr`` archive (created if missing).
    settings : BatchSettings
        The merge settings.
    workers : int or None
        Local worker processes (default: one per core).
    scheduler : str or None
        Address of a running Dask scheduler whose workers merge the runs (instead of local ones).
    threads : int or None
        Merge-kernel threads per local worker (default: the cores divided among the workers).
    force : bool
        Merge runs already in the archive again.
    progress : bool or None
        Progress bar with ETA (default: on a terminal).
    on_submit : callable or None
        Called once the tasks are submitted with the local pool (a :class:`pebble.ProcessPool`)
        or the Dask client (tests use it to kill a worker).

    Returns
    -------
    BatchReport

    Raises
    ------
    RuntimeError
        Called while a local worker starts (a script without a main guard), or its local
        workers end as they start.
    HdrcapError
        No run folder, or a folder that is not a run.
    """
    from hdrcap.batch.archive import Archive

    _check_not_starting_a_worker()
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
    on_submit: Callable[[Any], None] | None,
    began: tuple[float, float],
) -> None:
    """Give one task per run to the workers; commit the runs reported (or record their failure)
    as they come. ``cluster``: the local workers, the scheduler's address and the threads per
    local worker; ``began``: the clock and the client's CPU seconds when the batch began (the
    start-up is counted from then)."""
    from tqdm import tqdm

    workers, scheduler, threads = cluster
    committer = _Committer(session, report, force)
    args = (settings, session.target)
    with ExitStack() as stack:
        executor: Any
        if scheduler:
            executor = stack.enter_context(_dask_client(scheduler))
        else:
            executor = stack.enter_context(_local_pool(workers, threads))
        report.startup_seconds = time.perf_counter() - began[0]
        report.startup_cpu_seconds = time.process_time() - began[1]
        batches = _dask_batches(executor, todo, args) if scheduler else _pool_batches(executor, todo, args)
        if on_submit is not None:
            on_submit(executor)
        show = sys.stderr.isatty() if progress is None else progress
        with tqdm(total=len(todo), desc="batch", unit="run", disable=not show, dynamic_ncols=True) as bar:
            # the runs reported while the previous commit was made are committed together
            for done in batches:
                for source, status, result in done:
                    committer.take(source, status, result)
                committer.commit()
                bar.update(len(done))
        committer.commit(final=True)
