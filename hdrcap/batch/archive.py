"""The run archive: many merged runs in one zarr store that xarray opens as a Dataset.

Layout (zarr format 2, consolidated metadata; ``xarray.open_zarr(ARCHIVE)``)::

    irradiance (run, y, x) float32   photo-electrons per second per photosite (the paper's X)
    sigma      (run, y, x) float32   standard deviation of irradiance, same unit
    nexp       (run, y, x) float32   unsaturated exposures used (0: irradiance is a lower bound)
    quality, sigma_calibration (run, y, x) float32   as in the EXR of ``hdrcap merge``
    run        (run)       int64     0, 1, 2, ... in the order the runs were committed
    start_time (run)       datetime64[us]  start of the run (UTC)
    folder     (run)       str       the run folder (absolute path): the run's identity
    exposure_times (run)   str       JSON list of the bracket's exposure times, s
    n_frames   (run)       int64     light frames merged
    plan       (run)       str       JSON of the plan the merge followed ("null": none)
    merge_options (run)    str       JSON of the merge options (and the merge's own record)
    calibration (run)      str       id of the run's calibration in the attribute hdrcap_calibrations
    header     (run)       str       JSON of the attributes ``hdrcap merge`` writes in its EXR header
                                     (its ``calibration`` entry: the calibration id)

Global attributes: ``hdrcap_calibrations`` (JSON: calibration id -> file sha256 or preset,
parameters, provenance; each distinct calibration once), ``hdrcap_failed_runs`` (JSON: folder
-> error and time), ``hdrcap_archive_format``.

Every array is chunked one run per chunk, so a run is one chunk file in each array and no two
runs share a file. Who writes what (:class:`ArchiveWriter`, one writer session at a time under
the lock file ``ARCHIVE.zarr.lock``):

- **Slots.** A run's chunk files are written at a *slot*: a run index at or beyond the committed
  length, taken by an exclusive file create (``O_CREAT | O_EXCL``) in the session's staging
  folder ``ARCHIVE.zarr.staging/TOKEN/slots/`` (:func:`write_run`), so concurrent writers never
  take the same slot and never write the same file. The files are encoded in a temporary folder
  first and then hard-linked into place, which never replaces a file: a writer that lost its
  slot (a task Dask ran twice) cannot overwrite another run.
- **Workers** (:func:`write_run`) write every array's chunk file of their run at their slot,
  coordinates included, and return a :class:`RunEntry` (folder, slot, size, calibration).
- **The client** (:meth:`ArchiveWriter.commit`) commits: readers see the runs listed in the
  consolidated metadata (``.zmetadata``), which is replaced atomically (temporary file, then
  rename) as the last step; before it, the arrays' ``.zarray`` grow to the new length. Runs are
  committed in slot order; a slot whose run will never come (its run failed after taking it,
  landed at another slot, or was a ``--force`` rewrite, moved onto its committed index) is
  filled by renaming the chunk files of the last finished run into it. Nothing the client does
  is proportional to the pixels.

So the archive never shows a partial run: a chunk beyond the committed length is invisible, and
a writer that dies leaves at most ``.zarray`` files longer than the consolidated metadata and
chunk files beyond it, which the next writer cuts back and removes. Readers take no lock; a
Dataset opened before a commit keeps reading its runs undisturbed (a commit never rewrites a
committed chunk, except ``--force`` rewriting a run in place).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import secrets
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hdrcap.batch import zarrv2
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import CHANNEL_NAMES

if TYPE_CHECKING:
    import xarray as xr

__all__ = [
    "ArchiveRun",
    "RunEntry",
    "Target",
    "Archive",
    "ArchiveWriter",
    "CHANNELS",
    "OPTIONAL_FILL",
    "RUN_COORDS",
    "ARRAYS",
    "calibration_id",
    "complete_channels",
    "read_run",
    "open_archive",
    "write_run",
]

#: The per-photosite variables, as in the EXR of ``hdrcap merge``.
CHANNELS = CHANNEL_NAMES
#: Channels a merge may leave out, and the value that stands for "not given" in the archive
#: (quality 0: no flag; sigma_calibration NaN: not computed). :func:`read_run` leaves
#: sigma_calibration out again when it is NaN everywhere, so an exported EXR has the merge's
#: own channels (every merge writes quality).
OPTIONAL_FILL = {"quality": 0.0, "sigma_calibration": float("nan")}
#: Coordinates along ``run`` that hold JSON text.
_JSON_COORDS = ("exposure_times", "plan", "merge_options", "header")
#: Every coordinate along ``run`` (besides ``run`` itself).
RUN_COORDS = ("start_time", "folder", "n_frames", "exposure_times", "plan", "merge_options", "calibration", "header")
#: Every array of an archive: one chunk file per run in each.
ARRAYS = ("run", *RUN_COORDS, *CHANNELS)
_DTYPES = {
    "run": "<i8",
    "start_time": "<i8",
    "n_frames": "<i8",
    "folder": "|O",
    "calibration": "|O",
    **{n: "|O" for n in _JSON_COORDS},
    **{n: "<f4" for n in CHANNELS},
}
#: Version of the archive's content (2: calibrations stored once, referenced by id).
FORMAT = 2
_FORMAT_ATTR = "hdrcap_archive_format"
_TIME_UNITS = "microseconds since 1970-01-01"
_FAILED_ATTR = "hdrcap_failed_runs"
_CALIBRATIONS_ATTR = "hdrcap_calibrations"
_CONSOLIDATED = ".zmetadata"
#: Seconds between updates of the per-array metadata files during a writer session (readers
#: without consolidated metadata see the runs committed up to then).
SYNC_SECONDS = 30.0

_VAR_ATTRS = {
    "irradiance": {
        "long_name": "irradiance: photo-electrons per second per photosite (scaled irradiance X, "
        "maximum-likelihood estimate)",
        "units": "count s-1",
        "ancillary_variables": "sigma nexp",
        "comment": "raw CFA mosaic, not demosaiced",
    },
    "sigma": {"long_name": "standard deviation of irradiance", "units": "count s-1"},
    "nexp": {
        "long_name": "number of unsaturated exposures used",
        "units": "1",
        "comment": "0: saturated in every exposure; irradiance is then a lower bound",
    },
    "quality": {
        "long_name": "quality flags (bit field)",
        "units": "1",
        "comment": "0: trusted; 1 dead, 2 weak, 4 hot, 8 stuck photosite, 16 saturated in every exposure",
    },
    "sigma_calibration": {
        "long_name": "calibration part of sigma (systematic; averaging does not reduce it)",
        "units": "count s-1",
        "comment": "NaN: not computed for this run",
    },
}

_COORD_ATTRS = {
    "run": {"long_name": "run number in the archive (commit order)"},
    "start_time": {
        "long_name": "start of the run (UTC)",
        "standard_name": "time",
        "units": _TIME_UNITS,
        "calendar": "proleptic_gregorian",
    },
    "folder": {"long_name": "run folder (absolute path); identifies the run"},
    "exposure_times": {"long_name": "exposure times of the merged frames, s (JSON list)"},
    "n_frames": {"long_name": "number of light frames merged", "units": "1"},
    "plan": {"long_name": "plan the merge followed (JSON; null: none)"},
    "merge_options": {"long_name": "merge options and the merge's record (JSON)"},
    "calibration": {
        "long_name": "calibration id: key of the global attribute hdrcap_calibrations (JSON: file sha256 "
        "or preset, parameters, provenance)"
    },
    "header": {
        "long_name": "attributes of the EXR header hdrcap merge writes for this run (JSON; its calibration "
        "entry is the calibration id)"
    },
}


def complete_channels(channels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every archive channel of a merge's channels as float32, the optional ones filled where
    the merge left them out (:data:`OPTIONAL_FILL`).

    Parameters
    ----------
    channels : dict of str to numpy.ndarray
        At least ``irradiance``, ``sigma`` and ``nexp`` (2-D, one shape).

    Returns
    -------
    dict of str to numpy.ndarray
        One contiguous float32 array per name of :data:`CHANNELS`.
    """
    shape = np.shape(channels["irradiance"])
    return {
        name: np.ascontiguousarray(channels[name], dtype=np.float32)
        if name in channels
        else np.full(shape, OPTIONAL_FILL[name], dtype=np.float32)
        for name in CHANNELS
    }


@dataclass(frozen=True)
class ArchiveRun:
    """One merged run, ready to be written to an archive.

    Parameters
    ----------
    folder : str
        The run folder (absolute path); the run's identity in the archive.
    start_time : str
        Start of the run, ISO 8601 (UTC if no zone is given).
    channels : dict of str to numpy.ndarray
        ``irradiance``, ``sigma`` (e-/s per photosite) and ``nexp`` (and ``quality``,
        ``sigma_calibration`` if the merge has them), 2-D, as the EXR stores them.
    header : dict
        The EXR header attributes of ``hdrcap merge`` for this run.
    exposure_times : list of float
        Exposure times of the merged light frames, s.
    plan : dict or None
        The plan the merge followed.
    merge_options : dict
        The merge options used.
    calibration : dict
        The calibration: its identity (file sha256, or preset), parameters, provenance.
    """

    folder: str
    start_time: str
    channels: dict[str, np.ndarray]
    header: dict[str, Any]
    exposure_times: list[float]
    plan: dict[str, Any] | None = None
    merge_options: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", complete_channels(self.channels))  # frozen dataclass

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.channels["irradiance"].shape
        return h, w


@dataclass(frozen=True)
class RunEntry:
    """A run written at its slot, as a worker reports it to the client (a few hundred bytes, plus
    the calibration record).

    Parameters
    ----------
    folder : str
        The run's folder (its identity).
    slot : int
        Run index its chunk files were written at.
    shape : (int, int)
        Its size, rows and columns.
    calibration_id : str
        Key of its calibration in the archive's ``hdrcap_calibrations``.
    calibration : dict
        That calibration (identity, parameters, provenance), stored once per archive.
    """

    folder: str
    slot: int
    shape: tuple[int, int]
    calibration_id: str
    calibration: dict[str, Any]


@dataclass(frozen=True)
class Target:
    """Where the writers of one session write runs (sent with every batch task).

    Parameters
    ----------
    archive : str
        The ``.zarr`` folder.
    staging : str
        The session's staging folder (slot reservations, temporary files).
    token : str
        The session's token: a worker writes only if the staging folder holds it (it sees the
        archive's file system, and the session is still open).
    base : int
        The committed length when the session began: the first slot.
    shape : (int, int) or None
        The size of the archive's runs (None: no run yet).
    """

    archive: str
    staging: str
    token: str
    base: int
    shape: tuple[int, int] | None

    def sees(self) -> bool:
        """Whether this process sees the session's staging folder (a shared file system)."""
        try:
            return (Path(self.staging) / "token").read_text() == self.token
        except OSError:
            return False


def _json(obj: Any) -> str:
    from hdrcap.pipeline.io.exr import _json_default

    return json.dumps(obj, sort_keys=True, default=_json_default)


def calibration_id(calibration: dict[str, Any]) -> str:
    """The id of a calibration record: the first 16 hex digits of the sha256 of its JSON.

    Parameters
    ----------
    calibration : dict
        Identity (file sha256, or preset), parameters, provenance.

    Returns
    -------
    str
    """
    return hashlib.sha256(_json(calibration).encode()).hexdigest()[:16]


def _header_calibration(calibration: dict[str, Any]) -> dict[str, Any]:
    """The header's ``calibration`` entry that a calibration record stands for."""
    return {"params": calibration.get("params"), "provenance": calibration.get("provenance")}


def _utc_microseconds(iso: str) -> int:
    t = _dt.datetime.fromisoformat(iso)
    if t.tzinfo is not None:
        t = t.astimezone(_dt.UTC).replace(tzinfo=None)
    return int(np.datetime64(t, "us").astype(np.int64))


def _coordinates(run: ArchiveRun, cid: str) -> dict[str, Any]:
    """The values of ``run``'s coordinates (all but ``run``): the header's calibration entry
    replaced by the calibration id when the calibration record holds it."""
    header = dict(run.header)
    if "calibration" in header and _json(header["calibration"]) == _json(_header_calibration(run.calibration)):
        header["calibration"] = cid
    return {
        "start_time": _utc_microseconds(run.start_time),
        "folder": run.folder,
        "n_frames": len(run.exposure_times),
        "exposure_times": _json(list(run.exposure_times)),
        "plan": _json(run.plan),
        "merge_options": _json(run.merge_options),
        "calibration": cid,
        "header": _json(header),
    }


def _metadata(name: str, shape: tuple[int, int], length: int = 0) -> dict[str, Any]:
    """The ``.zarray`` of array ``name`` for runs of ``shape``."""
    return zarrv2.array_metadata((length, *shape) if name in CHANNELS else (length,), _DTYPES[name])


def _array_attrs(name: str) -> dict[str, Any]:
    """The ``.zattrs`` of array ``name`` (dimensions as xarray names them, CF attributes)."""
    if name in CHANNELS:
        return {**_VAR_ATTRS[name], "coordinates": " ".join(sorted(RUN_COORDS)), "_ARRAY_DIMENSIONS": ["run", "y", "x"]}
    return {**_COORD_ATTRS[name], "_ARRAY_DIMENSIONS": ["run"]}


def _global_attrs() -> dict[str, Any]:
    from hdrcap import __version__

    return {
        "Conventions": "CF-1.10",
        "title": "hdrcap run archive: merged HDR runs, one per index of the run dimension",
        "source": f"hdrcap {__version__}",
        "references": "Granados et al., Optimal HDR Reconstruction with Linear Digital Cameras, CVPR 2010",
        "comment": "open with xarray.open_zarr; runs appear when committed (consolidated metadata)",
        _FORMAT_ATTR: FORMAT,
        _FAILED_ATTR: "{}",
        _CALIBRATIONS_ATTR: "{}",
    }


# --------------------------------------------------------------------------- the worker's side
def _reserve(target: Target, folder: str) -> int:
    """Take the lowest free slot of the session (an exclusive create of ``slots/N``, which
    names the run) and return it. Slots are taken in order, never released within a session."""
    slots = Path(target.staging) / "slots"
    slot = target.base + len(os.listdir(slots))  # the first free slot when listed, or below it
    while True:
        try:
            fd = os.open(slots / str(slot), os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            slot += 1
            continue
        try:
            os.write(fd, folder.encode())
        finally:
            os.close(fd)
        return slot


def write_run(target: Target, run: ArchiveRun) -> RunEntry | None:
    """Write ``run``'s chunk files into the archive at a slot of its own (on a batch worker, or
    the client); the run becomes visible when the session commits it.

    Every array's chunk is encoded into the staging folder first, then the slot is taken and the
    files are hard-linked into the archive (never replacing a file).

    Parameters
    ----------
    target : Target
        The writer session's target (:attr:`ArchiveWriter.target`).
    run : ArchiveRun
        The merged run.

    Returns
    -------
    RunEntry or None
        What the session needs to commit the run; None when this process does not see the
        session's staging folder (then send the run to the client, which writes it).

    Raises
    ------
    InputError
        The run's size differs from the archive's.
    FileExistsError
        A chunk file is already at the slot (a writer of the same run that lost its slot).
    """
    from hdrcap.pipeline.io.files import place_new

    if not target.sees():
        return None
    if target.shape is not None and tuple(run.shape) != tuple(target.shape):
        raise InputError(
            f"{run.folder}: merged size {run.shape[1]}x{run.shape[0]} differs from the "
            f"archive's {target.shape[1]}x{target.shape[0]}"
        )
    record = dict(run.calibration)
    cid = calibration_id(record)
    values: dict[str, Any] = {**_coordinates(run, cid), **run.channels}
    tmp = Path(target.staging) / "tmp"
    prefix = secrets.token_hex(8)
    files: dict[str, Path] = {}
    try:
        for name in ARRAYS[1:]:
            files[name] = tmp / f"{prefix}.{name}"
            data = zarrv2.encode_chunk(_metadata(name, run.shape), np.asarray(values[name])[None])
            files[name].write_bytes(data)
        slot = _reserve(target, run.folder)
        files["run"] = tmp / f"{prefix}.run"
        files["run"].write_bytes(zarrv2.encode_chunk(_metadata("run", run.shape), [slot]))
        root = Path(target.archive)
        for name, f in files.items():
            folder = root / name
            folder.mkdir(parents=True, exist_ok=True)
            place_new(f, folder / zarrv2.chunk_name(slot, 3 if name in CHANNELS else 1))
    finally:
        for f in files.values():
            f.unlink(missing_ok=True)
    return RunEntry(run.folder, slot, run.shape, cid, record)


# --------------------------------------------------------------------------- reading
def _consolidated(path: Path) -> dict[str, Any]:
    """The consolidated metadata of the archive at ``path`` (key -> JSON; empty: none)."""
    doc = zarrv2.read_json(path / _CONSOLIDATED)
    return {} if doc is None else dict(doc["metadata"])


def _length(meta: dict[str, Any]) -> int:
    return int(meta["run/.zarray"]["shape"][0]) if "run/.zarray" in meta else 0


def _read_coordinate(path: Path, meta: dict[str, Any], name: str) -> list[Any]:
    """The committed values of the coordinate ``name`` (one chunk file per run)."""
    key = f"{name}/.zarray"
    if key not in meta:
        return []
    arr = meta[key]
    return [
        zarrv2.decode_chunk(arr, (path / name / zarrv2.chunk_name(i, 1)).read_bytes())[0]
        for i in range(int(arr["shape"][0]))
    ]


def open_archive(path: str | os.PathLike[str]) -> xr.Dataset:
    """The archive at ``path`` as an xarray Dataset of its committed runs (lazy, dask-backed).

    Parameters
    ----------
    path : str or Path
        The ``.zarr`` folder.

    Returns
    -------
    xarray.Dataset
        Variables ``irradiance``, ``sigma``, ``nexp``, ... (run, y, x) and the run coordinates.
    """
    import xarray as xr

    folder = Path(path)
    if not (folder / _CONSOLIDATED).is_file():
        raise InputError(f"{folder}: not an hdrcap archive (no consolidated zarr metadata)")
    return xr.open_zarr(folder, consolidated=True)


def read_run(path: str | Path, index: int) -> HdrResult:
    """One committed run of the archive as the result ``hdrcap merge`` gives for that run.

    Parameters
    ----------
    path : str or Path
        The ``.zarr`` folder.
    index : int
        Run number (the ``run`` coordinate), 0 for the first.

    Returns
    -------
    HdrResult
        The channels as the run's EXR stores them (read back as float32; quality as uint8),
        and the run's header (its calibration entry in full). ``sigma_calibration`` and
        ``quality`` are left out where the merge had none.

    Raises
    ------
    InputError
        Not an archive, or no such run.
    """
    ds = open_archive(path)
    n = ds.sizes["run"]
    if not 0 <= index < n:
        raise InputError(
            f"{path}: run {index} is not in the archive (it holds runs 0..{n - 1})"
            if n
            else f"{path}: the archive holds no run yet"
        )
    one = ds.isel(run=index)
    header = json.loads(str(one["header"].values))
    if isinstance(header.get("calibration"), str):  # an id of the archive's calibrations
        table = json.loads(str(ds.attrs.get(_CALIBRATIONS_ATTR, "{}")))
        if header["calibration"] not in table:
            raise InputError(
                f"{path}: run {index}'s calibration {header['calibration']} is not in {_CALIBRATIONS_ATTR}"
            )
        header["calibration"] = _header_calibration(table[header["calibration"]])
    channels = {}
    for name in CHANNELS:
        if name not in one:
            continue
        arr = np.asarray(one[name].values, dtype=np.float32)
        if name in OPTIONAL_FILL and header.get(name) is None:
            continue  # the merge had no such channel (its description is None)
        channels[name] = arr
    quality = channels.get("quality")
    return HdrResult(
        channels["irradiance"],
        channels["sigma"],
        channels["nexp"],
        quality=None if quality is None else quality.astype(np.uint8),
        sigma_calibration=channels.get("sigma_calibration"),
        header=header,
    )


class Archive:
    """A run archive on disk: what it holds, and its writer sessions (see the module notes).

    Parameters
    ----------
    path : str or Path
        The ``.zarr`` folder; created by the first commit.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.lock_path = self.path.with_name(self.path.name + ".lock")

    # ------------------------------------------------------------------ reading
    def exists(self) -> bool:
        return (self.path / _CONSOLIDATED).is_file()

    def folders(self) -> dict[str, int]:
        """Folder -> run number of every committed run."""
        meta = _consolidated(self.path)
        return {str(f): i for i, f in enumerate(_read_coordinate(self.path, meta, "folder"))}

    def failed(self) -> dict[str, dict[str, str]]:
        """Folder -> {"error", "time"} of the runs whose last attempt failed."""
        attrs = _consolidated(self.path).get(".zattrs", {})
        return dict(json.loads(str(attrs.get(_FAILED_ATTR, "{}"))))

    def calibrations(self) -> dict[str, dict[str, Any]]:
        """Calibration id -> calibration record (identity, parameters, provenance)."""
        attrs = _consolidated(self.path).get(".zattrs", {})
        return dict(json.loads(str(attrs.get(_CALIBRATIONS_ATTR, "{}"))))

    # ------------------------------------------------------------------ writing
    @contextmanager
    def writer(self) -> Iterator[ArchiveWriter]:
        """A writer session: the archive's lock held (a second session waits for it), an
        interrupted earlier session cleaned up, a staging folder for the writers. On a normal
        exit every run added is committed (:meth:`ArchiveWriter.commit` with ``final``); on an
        exception nothing more is committed. Either way the chunk files beyond the committed
        runs and the staging folder are removed.

        Yields
        ------
        ArchiveWriter
        """
        from filelock import FileLock

        if self.path.exists() and not self.path.is_dir():
            raise InputError(f"{self.path}: exists and is not a zarr folder")
        with FileLock(str(self.lock_path)):
            session = ArchiveWriter(self.path)
            ok = False
            try:
                yield session
                session.commit(final=True)
                ok = True
            finally:
                session.close(ok)

    def commit(self, run: ArchiveRun, replace: bool = False) -> int:
        """Write ``run`` and commit it; returns its run number.

        A run whose folder is already in the archive is rewritten in place when ``replace``,
        else refused. Its failure record, if any, is cleared.

        Parameters
        ----------
        run : ArchiveRun
            The merged run.
        replace : bool
            Overwrite a committed run of the same folder.

        Returns
        -------
        int
            The run number (``run`` coordinate).
        """
        return self.commit_many([run], replace)[0]

    def commit_many(self, runs: Sequence[ArchiveRun], replace: bool = False) -> list[int]:
        """Write several runs and commit them together (one commit); returns their run numbers.
        Either every run is committed or, if an error is raised, none.

        Parameters
        ----------
        runs : sequence of ArchiveRun
            The merged runs (distinct folders).
        replace : bool
            Overwrite committed runs of the same folders.

        Returns
        -------
        list of int
            The run numbers, in the order of ``runs``.
        """
        with self.writer() as session:
            for run in runs:
                session.add(session.write(run), replace)
            landed = session.commit(final=True)
        return [landed[r.folder] for r in runs]

    def record_failure(self, folder: str, error: str) -> None:
        """Record that merging ``folder`` failed with ``error`` (kept in the archive's
        ``hdrcap_failed_runs`` attribute, JSON, until the run lands)."""
        with self.writer() as session:
            session.fail(folder, error)


class ArchiveWriter:
    """The writer session of an archive (:meth:`Archive.writer`; the lock is held).

    Writers (batch workers, or :meth:`write`) write runs at slots (:func:`write_run`, with
    :attr:`target`); :meth:`add` hands a written run to the session, :meth:`fail` records a
    run that failed, :meth:`commit` makes the runs added so far visible (the ones that can be:
    slot order) with one rewrite of the metadata.

    Parameters
    ----------
    path : Path
        The ``.zarr`` folder.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._meta = _consolidated(path)
        self._synced: dict[str, Any] = {}  # key -> what the per-array metadata file holds
        self._synced_at = time.monotonic()
        self._check()
        #: Committed runs.
        self.length = _length(self._meta)
        irr = self._meta.get("irradiance/.zarray")
        #: The runs' size (None: no run yet).
        self.shape: tuple[int, int] | None = None if irr is None else (int(irr["shape"][1]), int(irr["shape"][2]))
        self._repair()
        #: Folder -> run number of the committed runs.
        self.committed = {str(f): i for i, f in enumerate(_read_coordinate(path, self._meta, "folder"))}
        self._attrs: dict[str, Any] = dict(self._meta.get(".zattrs") or _global_attrs())
        self._attrs.setdefault(_CALIBRATIONS_ATTR, "{}")
        self._attrs[_FORMAT_ATTR] = FORMAT
        self._failed_runs: dict[str, Any] = json.loads(str(self._attrs.get(_FAILED_ATTR, "{}")))
        self._calibrations: dict[str, Any] = json.loads(str(self._attrs[_CALIBRATIONS_ATTR]))
        staging_root = path.with_name(path.name + ".staging")
        token = secrets.token_hex(8)
        self._staging = staging_root / token
        (self._staging / "slots").mkdir(parents=True)
        (self._staging / "tmp").mkdir()
        (self._staging / "token").write_text(token)
        #: Where the session's writers write (sent to batch workers).
        self.target = Target(str(path), str(self._staging), token, self.length, self.shape)
        self._pending: dict[int, RunEntry] = {}  # slot -> a new run waiting for the slots before it
        self._rewrites: list[tuple[int, RunEntry]] = []  # committed index -> a run rewriting it
        self._seen: dict[str, int | None] = {}  # folder -> the slot of its run (None: failed)
        self._orphans: set[int] = set()  # slots whose run will never come
        self._failures: dict[str, dict[str, str]] = {}
        #: Commits made (metadata rewrites).
        self.commits = 0

    # ------------------------------------------------------------------ session start
    def _check(self) -> None:
        """Refuse a folder that is not an archive of this format."""
        if not self._meta:  # no archive yet: an empty folder, or what a first commit that died left
            if self.path.is_dir() and not all(_ours(p.name) for p in self.path.iterdir()):
                raise InputError(f"{self.path}: exists and is not an hdrcap archive (no consolidated zarr metadata)")
            return
        attrs = self._meta.get(".zattrs", {})
        if "irradiance/.zarray" in self._meta and attrs.get(_FORMAT_ATTR) != FORMAT:
            raise InputError(
                f"{self.path}: written by an earlier hdrcap (calibration stored with every run); "
                "batch into a new archive"
            )
        for name in ARRAYS:
            arr = self._meta.get(f"{name}/.zarray")
            if arr is not None and arr != zarrv2.array_metadata(arr["shape"], _DTYPES[name]):
                raise InputError(f"{self.path}: its array {name} is not laid out as hdrcap batch writes it")

    def _repair(self) -> None:
        """Undo what an interrupted session left: per-array metadata behind the consolidated
        metadata (brought up to it), chunk files beyond the committed runs and temporary files
        (removed), its staging folder (removed)."""
        import shutil

        self._sync(check_disk=True)
        for name in ARRAYS:
            folder = self.path / name
            if not folder.is_dir():
                continue
            with os.scandir(folder) as entries:
                for e in entries:
                    i = zarrv2.chunk_index(e.name)
                    if (i is not None and i >= self.length) or e.name.endswith(".partial"):
                        os.unlink(e.path)
        if self.path.is_dir():
            for p in self.path.glob(".*.partial"):
                p.unlink(missing_ok=True)
        root = self.path.with_name(self.path.name + ".staging")
        if root.is_dir():  # only a dead session's: the lock is held
            shutil.rmtree(root, ignore_errors=True)

    # ------------------------------------------------------------------ runs
    def write(self, run: ArchiveRun) -> RunEntry:
        """Write ``run`` at a slot from this process (:func:`write_run`).

        Parameters
        ----------
        run : ArchiveRun

        Returns
        -------
        RunEntry
        """
        entry = write_run(self.target, run)
        if entry is None:
            raise InputError(f"{self._staging}: the session's staging folder is gone")
        return entry

    def add(self, entry: RunEntry, replace: bool = False) -> None:
        """Hand a run written at its slot to the session, to be committed.

        Parameters
        ----------
        entry : RunEntry
            What :func:`write_run` returned.
        replace : bool
            A run of a committed folder rewrites it in place (else it is refused).

        Raises
        ------
        InputError
            Its size differs from the archive's, its folder is committed (without ``replace``)
            or already added. The run is then dropped (its slot is filled by another run).
        """
        try:
            if entry.folder in self._seen and self._seen[entry.folder] != entry.slot:
                raise InputError(f"{entry.folder}: given twice")
            self._seen[entry.folder] = entry.slot
            if self.shape is None:
                self.shape = (int(entry.shape[0]), int(entry.shape[1]))
            elif tuple(entry.shape) != tuple(self.shape):
                raise InputError(
                    f"{entry.folder}: merged size {entry.shape[1]}x{entry.shape[0]} differs from the "
                    f"archive's {self.shape[1]}x{self.shape[0]}"
                )
            if entry.folder in self.committed:
                if not replace:
                    raise InputError(f"{entry.folder}: already in {self.path} as run {self.committed[entry.folder]}")
                self._rewrites.append((self.committed[entry.folder], entry))
            else:
                self._pending[entry.slot] = entry
        except InputError:
            self._orphans.add(entry.slot)
            raise

    def fail(self, folder: str, error: str) -> None:
        """Record that ``folder`` failed with ``error`` (committed with the next commit; the
        record is cleared when the run lands).

        Parameters
        ----------
        folder : str
        error : str
            One line.
        """
        self._seen.setdefault(folder, None)
        self._failures[folder] = {"error": error, "time": _dt.datetime.now(_dt.UTC).isoformat()}

    def _orphaned(self, slot: int) -> bool:
        """Whether no run will come for ``slot``: its run landed at another slot, failed, or
        was moved away (from its reservation, which names the run's folder)."""
        if slot in self._orphans:
            return True
        try:
            folder = (self._staging / "slots" / str(slot)).read_text()
        except OSError:
            return False
        return folder in self._seen and self._seen[folder] != slot

    def _ready(self, final: bool) -> list[tuple[int, int, RunEntry]]:
        """The new runs that can be committed now, as (run number, slot, entry): in slot order,
        a slot whose run will never come filled with the last finished run (with ``final``,
        once no writer is left, every such slot)."""
        out: list[tuple[int, int, RunEntry]] = []
        index = self.length
        while self._pending:
            if index in self._pending:
                out.append((index, index, self._pending.pop(index)))
            elif final or self._orphaned(index):
                top = max(self._pending)
                out.append((index, top, self._pending.pop(top)))
                self._orphans.add(top)
            else:
                break
            index += 1
        return out

    def _move(self, src: int, dst: int, run_coordinate: bool) -> None:
        """Rename every chunk file of slot ``src`` onto run ``dst`` (a rename replaces a file a
        writer that lost slot ``dst`` may have left); write ``dst``'s ``run`` coordinate if asked
        (else it keeps its own)."""
        for name in ARRAYS[1:]:
            ndim = 3 if name in CHANNELS else 1
            os.replace(self.path / name / zarrv2.chunk_name(src, ndim), self.path / name / zarrv2.chunk_name(dst, ndim))
        if run_coordinate:
            data = zarrv2.encode_chunk(_metadata("run", (1, 1)), [dst])
            zarrv2.write_atomic(self.path / "run" / zarrv2.chunk_name(dst, 1), data)

    def commit(self, final: bool = False) -> dict[str, int]:
        """Commit what can be: the rewrites, the new runs in slot order, the failure records, in
        one rewrite of the consolidated metadata (the commit point; a few kB per distinct
        calibration plus the failure records, whatever the number of runs).

        Parameters
        ----------
        final : bool
            No writer is left: fill every slot whose run will never come.

        Returns
        -------
        dict of str to int
            Folder -> run number of the runs committed now.
        """
        ready = self._ready(final)
        landed: dict[str, int] = {}
        entries: list[RunEntry] = []
        for index, entry in self._rewrites:
            self._move(entry.slot, index, run_coordinate=False)
            self._orphans.add(entry.slot)
            landed[entry.folder] = index
            entries.append(entry)
        for index, slot, entry in ready:
            if slot != index:
                self._move(slot, index, run_coordinate=True)
            landed[entry.folder] = index
            entries.append(entry)
        if landed or self._failures:
            self._commit_metadata(landed, entries, len(ready))
        if final or time.monotonic() - self._synced_at >= SYNC_SECONDS:
            self._sync()
        return landed

    def _commit_metadata(self, landed: dict[str, int], entries: list[RunEntry], new: int) -> None:
        """Commit ``landed`` (``new`` of them appended) and the failure records."""
        failed, table = self._failed_runs, self._calibrations
        failed.update(self._failures)
        for folder in landed:
            failed.pop(folder, None)
        new_calibrations = {e.calibration_id: e.calibration for e in entries if e.calibration_id not in table}
        table.update(new_calibrations)
        self._attrs[_FAILED_ATTR] = json.dumps(failed, sort_keys=True)
        if new_calibrations:
            self._attrs[_CALIBRATIONS_ATTR] = _json(table)
        self._write_metadata(self.length + new)
        self._rewrites.clear()
        self._failures.clear()
        for folder, index in landed.items():
            self.committed[folder] = index

    def _write_metadata(self, length: int) -> None:
        """The commit: the consolidated metadata rewritten with the arrays grown to ``length``
        runs (and created, when the archive had no run yet) and the attributes."""
        meta = dict(self._meta)  # the session's view changes only once the commit is made
        for name in ARRAYS:
            key = f"{name}/.zarray"
            if key not in meta:
                if name != "run" and (length == 0 or self.shape is None):
                    continue  # an archive of failure records only: the run dimension, no run
                meta[key] = _metadata(name, self.shape or (1, 1), length)
                meta[f"{name}/.zattrs"] = _array_attrs(name)
            elif meta[key]["shape"][0] != length:
                meta[key] = {**meta[key], "shape": [length, *meta[key]["shape"][1:]]}
        meta[".zgroup"] = {"zarr_format": 2}
        meta[".zattrs"] = dict(self._attrs)
        self.path.mkdir(exist_ok=True)
        _write_consolidated(self.path, meta)
        self._meta = meta
        self.length = length
        self.commits += 1

    def _sync(self, check_disk: bool = False) -> None:
        """Bring the per-array metadata files (``.zarray``, ``.zattrs``, ``.zgroup``) up to the
        consolidated metadata, for readers that do not read it: after a commit, so they never
        run ahead of it (at most every :data:`SYNC_SECONDS` during a session, and at its end)."""
        for key, value in self._meta.items():
            if check_disk:
                self._synced[key] = zarrv2.read_json(self.path / key)
            if self._synced.get(key) != value:
                (self.path / key).parent.mkdir(exist_ok=True)
                zarrv2.write_json(self.path / key, value)
                self._synced[key] = value
        self._synced_at = time.monotonic()

    # ------------------------------------------------------------------ session end
    def close(self, committed: bool) -> None:
        """End the session: remove the chunk files at the slots beyond the committed runs, the
        staging folder, and the archive folder if nothing was ever committed to it."""
        import shutil

        if self._meta:
            self._sync()
        slots = self._staging / "slots"
        taken = {int(p.name) for p in slots.iterdir()} if slots.is_dir() else set()
        for slot in sorted(taken | self._orphans):
            if slot < self.length:
                continue
            for name in ARRAYS:
                (self.path / name / zarrv2.chunk_name(slot, 3 if name in CHANNELS else 1)).unlink(missing_ok=True)
        shutil.rmtree(self._staging, ignore_errors=True)
        empty = [self._staging.parent]
        if not self._meta:  # nothing ever committed: no archive
            empty += [*(self.path / n for n in ARRAYS), self.path]
        for folder in empty:
            try:
                folder.rmdir()  # only if empty
            except OSError:
                pass


def _ours(name: str) -> bool:
    """Whether ``name`` in an archive folder is something hdrcap batch writes there."""
    return name in ARRAYS or name in (".zgroup", ".zattrs") or name.endswith(".partial")


def _write_consolidated(path: Path, meta: dict[str, Any]) -> None:
    """Replace the consolidated metadata (atomically): the commit point of every write."""
    zarrv2.write_json(path / _CONSOLIDATED, {"metadata": meta, "zarr_consolidated_format": 1})
