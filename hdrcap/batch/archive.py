"""The run archive: many merged runs in one zarr store that xarray opens as a Dataset.

Layout (zarr format 2, consolidated metadata; ``xarray.open_zarr(ARCHIVE)``)::

    irradiance (run, y, x) float32   photo-electrons per second per photosite (the paper's X)
    sigma      (run, y, x) float32   standard deviation of irradiance, same unit
    nexp       (run, y, x) float32   unsaturated exposures used (0: irradiance is a lower bound)
    run        (run)       int64     0, 1, 2, ... in the order the runs were committed
    start_time (run)       datetime64[us]  start of the run (UTC)
    folder     (run)       str       the run folder (absolute path): the run's identity
    exposure_times (run)   str       JSON list of the bracket's exposure times, s
    n_frames   (run)       int64     light frames merged
    plan       (run)       str       JSON of the plan the merge followed ("null": none)
    merge_options (run)    str       JSON of the merge options (and the merge's own record)
    calibration (run)      str       JSON of the calibration identity (sha256 of its file, params, provenance)
    header     (run)       str       JSON of the attributes ``hdrcap merge`` writes in its EXR header

Every array along ``run`` is chunked one run per chunk, so appending a run writes new chunk
files only and never rewrites one a reader may be reading.

Commit scheme: readers see the runs listed in the consolidated metadata (``.zmetadata``), which
is replaced atomically (temporary file, then rename) as the last step of every append. A run's
arrays are written first (the arrays' own metadata grows by one run, chunk files land), then
the consolidated metadata is rewritten: the commit. A writer that dies in between leaves
arrays one run longer than the consolidated metadata says; readers do not see that run, and
the next writer cuts the arrays back to the committed length before appending. So the archive
never shows a partial run. Writers take a lock file ``ARCHIVE.zarr.lock`` (one writer at a
time); readers take no lock and may read while a batch appends.

Staging: batch workers may write a run's chunk files themselves (:func:`stage_channels`, encoded
exactly as the archive's chunks) into ``ARCHIVE.zarr.staging/BATCH/``; the commit then renames
them into place instead of compressing and writing the arrays.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import CHANNEL_NAMES

if TYPE_CHECKING:
    import xarray as xr
    import zarr
    from numcodecs import Blosc

__all__ = [
    "ArchiveRun",
    "Archive",
    "CHANNELS",
    "OPTIONAL_FILL",
    "RUN_COORDS",
    "complete_channels",
    "read_run",
    "open_archive",
    "stage_channels",
]

#: The per-photosite variables, as in the EXR of ``hdrcap merge``.
CHANNELS = CHANNEL_NAMES
#: Channels a merge may leave out, and the value that stands for "not given" in the archive
#: (quality 0: no flag; sigma_calibration NaN: not computed). :func:`read_run` leaves
#: sigma_calibration out again when it is NaN everywhere, so an exported EXR has the merge's
#: own channels (every merge writes quality).
OPTIONAL_FILL = {"quality": 0.0, "sigma_calibration": float("nan")}
#: Coordinates along ``run`` that hold JSON text.
_JSON_COORDS = ("exposure_times", "plan", "merge_options", "calibration", "header")
#: Every coordinate along ``run`` (besides ``run`` itself).
RUN_COORDS = ("start_time", "folder", "n_frames") + _JSON_COORDS
_FORMAT: Literal[2] = 2
_TIME_UNITS = "microseconds since 1970-01-01T00:00:00"
_FAILED_ATTR = "hdrcap_failed_runs"

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


_COORD_ATTRS = {
    "run": {"long_name": "run number in the archive (commit order)"},
    "start_time": {"long_name": "start of the run (UTC)", "standard_name": "time"},
    "folder": {"long_name": "run folder (absolute path); identifies the run"},
    "exposure_times": {"long_name": "exposure times of the merged frames, s (JSON list)"},
    "n_frames": {"long_name": "number of light frames merged", "units": "1"},
    "plan": {"long_name": "plan the merge followed (JSON; null: none)"},
    "merge_options": {"long_name": "merge options and the merge's record (JSON)"},
    "calibration": {"long_name": "calibration identity: file sha256, parameters, provenance (JSON)"},
    "header": {"long_name": "attributes of the EXR header hdrcap merge writes for this run (JSON)"},
}


@dataclass(frozen=True)
class ArchiveRun:
    """One merged run, ready to be committed to an archive.

    Parameters
    ----------
    folder : str
        The run folder (absolute path); the run's identity in the archive.
    start_time : str
        Start of the run, ISO 8601 (UTC if no zone is given).
    channels : dict of str to numpy.ndarray
        ``irradiance``, ``sigma`` (e-/s per photosite) and ``nexp``, 2-D, as float32 (the EXR's).
    header : dict
        The EXR header attributes of ``hdrcap merge`` for this run.
    exposure_times : list of float
        Exposure times of the merged light frames, s.
    plan : dict or None
        The plan the merge followed.
    merge_options : dict
        The merge options used.
    calibration : dict
        Calibration identity (file sha256, parameters, provenance).
    """

    folder: str
    start_time: str
    channels: dict[str, np.ndarray]
    header: dict[str, Any]
    exposure_times: list[float]
    plan: dict[str, Any] | None = None
    merge_options: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    staged: dict[str, str] = field(default_factory=dict)
    staged_shape: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        if self.channels:
            object.__setattr__(self, "channels", complete_channels(self.channels))  # frozen dataclass

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.staged_shape if self.staged else self.channels["irradiance"].shape
        return h, w

    def arrays(self) -> dict[str, np.ndarray]:
        """The channels, decoded from the staged chunk files if the run was staged."""
        if not self.staged:
            return self.channels
        codec = _codec()
        return {
            name: np.frombuffer(codec.decode(Path(f).read_bytes()), dtype=np.float32).reshape(self.shape)
            for name, f in self.staged.items()
        }


def _json(obj: Any) -> str:
    from hdrcap.pipeline.io.exr import _json_default

    return json.dumps(obj, sort_keys=True, default=_json_default)


def _utc_datetime64(iso: str) -> np.datetime64:
    t = _dt.datetime.fromisoformat(iso)
    if t.tzinfo is not None:
        t = t.astimezone(_dt.UTC).replace(tzinfo=None)
    return np.datetime64(t, "us")


def _coords(run: ArchiveRun, index: int) -> dict[str, tuple[str, np.ndarray, dict[str, str]]]:
    """The coordinates along ``run`` of ``run`` at position ``index``."""
    values = {
        "run": np.array([index], dtype=np.int64),
        "start_time": np.array([_utc_datetime64(run.start_time)], dtype="datetime64[us]"),
        "folder": np.array([run.folder], dtype=object),
        "n_frames": np.array([len(run.exposure_times)], dtype=np.int64),
        "exposure_times": np.array([_json(list(run.exposure_times))], dtype=object),
        "plan": np.array([_json(run.plan)], dtype=object),
        "merge_options": np.array([_json(run.merge_options)], dtype=object),
        "calibration": np.array([_json(run.calibration)], dtype=object),
        "header": np.array([_json(run.header)], dtype=object),
    }
    return {name: ("run", v, _COORD_ATTRS[name]) for name, v in values.items()}


def _dataset(run: ArchiveRun, index: int) -> xr.Dataset:
    """The one-run xarray Dataset of ``run`` at position ``index``."""
    import xarray as xr

    arrays = run.arrays()
    data = {
        name: (("run", "y", "x"), np.asarray(arrays[name], dtype=np.float32)[None], _VAR_ATTRS[name])
        for name in CHANNELS
    }
    return xr.Dataset(data, coords=_coords(run, index))


def _dataset_coords(run: ArchiveRun, index: int) -> xr.Dataset:
    """The one-run Dataset of ``run``'s coordinates only (its arrays are staged), as variables:
    the per-photosite arrays' ``coordinates`` attribute already makes them coordinates."""
    import xarray as xr

    return xr.Dataset(coords=_coords(run, index)).reset_coords()


def _codec() -> Blosc:
    """The compressor of the per-photosite chunks (workers encode staged chunks with it)."""
    from numcodecs import Blosc

    return Blosc(cname="lz4", clevel=5, shuffle=Blosc.SHUFFLE)


def _encoding(shape: tuple[int, int]) -> dict[str, dict[str, Any]]:
    enc: dict[str, dict[str, Any]] = {name: {"chunks": (1, *shape), "compressors": (_codec(),)} for name in CHANNELS}
    enc.update({name: {"chunks": (1,)} for name in ("run", *RUN_COORDS)})
    enc["start_time"].update(units=_TIME_UNITS, dtype="int64")
    return enc


def _global_attrs() -> dict[str, str]:
    from hdrcap import __version__

    return {
        "Conventions": "CF-1.10",
        "title": "hdrcap run archive: merged HDR runs, one per index of the run dimension",
        "source": f"hdrcap {__version__}",
        "references": "Granados et al., Optimal HDR Reconstruction with Linear Digital Cameras, CVPR 2010",
        "comment": "open with xarray.open_zarr; runs appear when committed (consolidated metadata)",
        _FAILED_ATTR: "{}",
    }


def _array(group: zarr.Group, name: str) -> zarr.Array:
    """The array ``name`` of an archive's zarr group (InputError when it is a group: not an archive)."""
    import zarr

    arr = group[name]
    if not isinstance(arr, zarr.Array):
        raise InputError(f"{group.store_path}: {name} is a group, not an array; not an hdrcap archive")
    return arr


def _folders(group: zarr.Group) -> list[str]:
    """The ``folder`` coordinate of an archive's zarr group: the run folders, in run order."""
    return [str(f) for f in np.asarray(_array(group, "folder")[:])]


def open_archive(path: str | os.PathLike[str]) -> xr.Dataset:
    """The archive at ``path`` as an xarray Dataset of its committed runs (lazy, dask-backed).

    Parameters
    ----------
    path : str or Path
        The ``.zarr`` folder.

    Returns
    -------
    xarray.Dataset
        Variables ``irradiance``, ``sigma``, ``nexp`` (run, y, x) and the run coordinates.
    """
    import xarray as xr

    folder = Path(path)
    if not (folder / ".zmetadata").is_file():
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
        and the run's header. ``sigma_calibration`` and ``quality`` are left out where the
        merge had none.

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
    """Writer of a run archive (see the module notes for the layout and the commit scheme).

    Parameters
    ----------
    path : str or Path
        The ``.zarr`` folder; created by the first :meth:`commit`.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.lock_path = self.path.with_name(self.path.name + ".lock")

    # ------------------------------------------------------------------ reading
    def exists(self) -> bool:
        return (self.path / ".zmetadata").is_file()

    def folders(self) -> dict[str, int]:
        """Folder -> run number of every committed run."""
        if not self.exists():
            return {}
        ds = open_archive(self.path)
        if "folder" not in ds:  # failures only, no run yet
            return {}
        return {str(f): int(r) for f, r in zip(ds["folder"].values, ds["run"].values)}

    def failed(self) -> dict[str, dict[str, str]]:
        """Folder -> {"error", "time"} of the runs whose last attempt failed."""
        if not self.exists():
            return {}
        return json.loads(open_archive(self.path).attrs.get(_FAILED_ATTR, "{}"))

    # ------------------------------------------------------------------ writing
    @contextmanager
    def _locked(self) -> Iterator[None]:
        from filelock import FileLock

        if self.path.exists() and not self.path.is_dir():
            raise InputError(f"{self.path}: exists and is not a zarr folder")
        with FileLock(str(self.lock_path)):
            yield

    def _repair(self) -> int:
        """Cut every array back to the committed number of runs (an append that died before its
        commit left them longer); returns that number."""
        import zarr

        committed = zarr.open_group(self.path, mode="r", use_consolidated=True, zarr_format=_FORMAT)
        n = _array(committed, "run").shape[0]
        group = zarr.open_group(self.path, mode="r+", use_consolidated=False, zarr_format=_FORMAT)
        for _name, arr in group.arrays():
            if arr.shape[0] > n:
                arr.resize((n, *arr.shape[1:]))
        return n

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
        with self._locked():
            i = self._commit(run, replace)
        for f in run.staged.values():  # decoded rather than renamed (first run, rewrite): not needed any more
            Path(f).unlink(missing_ok=True)
        return i

    def commit_many(self, runs: Sequence[ArchiveRun], replace: bool = False) -> list[int]:
        """Commit several runs at once; returns their run numbers.

        New runs whose chunks were staged are appended together: one append of their
        coordinates, one resize of every array and one commit (consolidated metadata) for all
        of them, which is what a commit costs on the client whatever the number of runs. Any
        other case (a rewrite, arrays sent back, the first run) commits the runs one by one.
        Either every run of the call is committed or, if an error is raised, none of the ones
        appended together.

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
        import zarr

        runs = list(runs)
        with self._locked():
            group = None
            if self.exists():
                self._repair()
                group = zarr.open_group(self.path, mode="r", use_consolidated=True, zarr_format=_FORMAT)
            together = (
                len(runs) > 1
                and group is not None
                and "irradiance" in group
                and len({r.folder for r in runs}) == len(runs)
                and all(r.staged for r in runs)
                and all(tuple(r.shape) == tuple(_array(group, "irradiance").shape[1:]) for r in runs)
                and not {r.folder for r in runs} & set(_folders(group))
                and self._chunks_compatible(group)
            )
            if together and group is not None:
                attrs = dict(group.attrs)
                attrs.pop("coordinates", None)
                failed = json.loads(str(attrs.get(_FAILED_ATTR, "{}")))
                for r in runs:
                    failed.pop(r.folder, None)
                attrs[_FAILED_ATTR] = json.dumps(failed, sort_keys=True)
                numbers = self._append_staged_many(runs, _array(group, "run").shape[0], attrs)
            else:
                numbers = [self._commit(r, replace) for r in runs]
        for r in runs:
            for f in r.staged.values():  # decoded rather than renamed (first run, rewrite): not needed any more
                Path(f).unlink(missing_ok=True)
        return numbers

    def _commit(self, run: ArchiveRun, replace: bool) -> int:
        """:meth:`commit` under the writer's lock."""
        import zarr

        group = None
        if self.exists():
            self._repair()
            group = zarr.open_group(self.path, mode="r", use_consolidated=True, zarr_format=_FORMAT)
        attrs: dict[str, Any] = _global_attrs() if group is None else dict(group.attrs)
        attrs.pop("coordinates", None)
        failed = json.loads(str(attrs.get(_FAILED_ATTR, "{}")))
        failed.pop(run.folder, None)
        attrs[_FAILED_ATTR] = json.dumps(failed, sort_keys=True)
        if group is None or "irradiance" not in group:  # the first run (perhaps after failures only)
            ds = _dataset(run, 0)
            ds.attrs.update(attrs)
            ds.to_zarr(self.path, mode="w", consolidated=True, zarr_format=_FORMAT, encoding=_encoding(run.shape))
            return 0
        n = _array(group, "run").shape[0]
        shape = tuple(_array(group, "irradiance").shape[1:])
        if tuple(run.shape) != shape:
            raise InputError(
                f"{run.folder}: merged size {run.shape[1]}x{run.shape[0]} differs from the "
                f"archive's {shape[1]}x{shape[0]}"
            )
        folders = _folders(group)
        if run.folder in folders:
            if not replace:
                raise InputError(f"{run.folder}: already in {self.path} as run {folders.index(run.folder)}")
            i = folders.index(run.folder)
            ds = _dataset(run, i)
            ds.attrs.update(attrs)
            ds.to_zarr(self.path, mode="r+", region={"run": slice(i, i + 1)}, consolidated=True, zarr_format=_FORMAT)
            return i
        if run.staged and self._chunks_compatible(group):
            return self._append_staged(run, n, attrs)
        ds = _dataset(run, n)
        ds.attrs.update(attrs)  # xarray replaces the root attributes on append
        ds.to_zarr(self.path, mode="a", append_dim="run", consolidated=True, zarr_format=_FORMAT)
        return n

    @staticmethod
    def _chunks_compatible(group: zarr.Group) -> bool:
        """Whether staged chunk files can be moved in as they are (same codec, dtype, layout)."""
        from zarr.core.metadata import ArrayV2Metadata

        for name in CHANNELS:
            meta = _array(group, name).metadata
            if not isinstance(meta, ArrayV2Metadata):  # the archive is zarr format 2
                return False
            if (
                meta.compressor != _codec()
                or meta.filters
                or meta.order != "C"
                or meta.dtype.to_native_dtype() != np.dtype("<f4")
                or meta.dimension_separator != "."
            ):
                return False
        return True

    def _append_staged(self, run: ArchiveRun, n: int, attrs: dict[str, Any]) -> int:
        """Append a staged run (:meth:`_append_staged_many` of one run)."""
        return self._append_staged_many([run], n, attrs)[0]

    def _append_staged_many(self, runs: list[ArchiveRun], n: int, attrs: dict[str, Any]) -> list[int]:
        """Append staged runs as runs n, n+1, ...: their coordinates (xarray, one append), the
        per-photosite arrays grown by that many runs and the chunk files renamed into place,
        then the commit (consolidated metadata)."""
        import xarray as xr
        import zarr

        parts = [_dataset_coords(run, n + i) for i, run in enumerate(runs)]
        ds = parts[0] if len(parts) == 1 else xr.concat(parts, dim="run")
        ds.attrs.update(attrs)
        ds.to_zarr(self.path, mode="a", append_dim="run", consolidated=False, zarr_format=_FORMAT)
        group = zarr.open_group(self.path, mode="r+", use_consolidated=False, zarr_format=_FORMAT)
        for name in CHANNELS:
            arr = _array(group, name)
            arr.resize((n + len(runs), *arr.shape[1:]))
            for i, run in enumerate(runs):
                os.replace(run.staged[name], self.path / name / arr.metadata.encode_chunk_key((n + i, 0, 0)))
        zarr.consolidate_metadata(self.path, zarr_format=_FORMAT)
        return list(range(n, n + len(runs)))

    # ------------------------------------------------------------------ staging
    def open_staging(self) -> tuple[str, str]:
        """A staging folder for this batch (``ARCHIVE.zarr.staging/TOKEN``, on the archive's file
        system) where workers that see it write their runs' encoded chunks; returns (folder, token)."""
        import secrets

        token = secrets.token_hex(8)
        folder = self.path.with_name(self.path.name + ".staging") / token
        folder.mkdir(parents=True)
        (folder / "token").write_text(token)
        return str(folder), token

    def close_staging(self, staging: tuple[str, str]) -> None:
        """Remove this batch's staging folder (and the staging root once empty)."""
        import shutil

        folder = Path(staging[0])
        shutil.rmtree(folder, ignore_errors=True)
        try:
            folder.parent.rmdir()
        except OSError:
            pass

    def record_failure(self, folder: str, error: str) -> None:
        """Record that merging ``folder`` failed with ``error`` (kept in the archive's
        ``hdrcap_failed_runs`` attribute, JSON, until the run lands)."""
        with self._locked():
            if not self.exists():
                import zarr

                root = zarr.open_group(self.path, mode="w", zarr_format=_FORMAT)
                root.attrs.update(_global_attrs())
                # an empty archive: the run dimension exists with no run yet
                self._init_empty(root)
            else:
                self._repair()
            self._set_failed(folder, error)

    def _init_empty(self, root: zarr.Group) -> None:
        import zarr

        arr = root.create_array("run", shape=(0,), chunks=(1,), dtype="int64")
        arr.attrs.update({"_ARRAY_DIMENSIONS": ["run"], **_COORD_ATTRS["run"]})
        zarr.consolidate_metadata(self.path, zarr_format=_FORMAT)

    def _set_failed(self, folder: str, error: str | None, consolidate: bool = True) -> None:
        import zarr

        root = zarr.open_group(self.path, mode="r+", use_consolidated=False, zarr_format=_FORMAT)
        failed = json.loads(str(root.attrs.get(_FAILED_ATTR, "{}")))
        if error is None:
            if folder not in failed:
                return
            failed.pop(folder)
        else:
            failed[folder] = {"error": error, "time": _dt.datetime.now(_dt.UTC).isoformat()}
        root.attrs[_FAILED_ATTR] = json.dumps(failed, sort_keys=True)
        if consolidate:
            zarr.consolidate_metadata(self.path, zarr_format=_FORMAT)


def stage_channels(staging: tuple[str, str] | None, key: str, channels: dict[str, np.ndarray]) -> dict[str, str]:
    """On a worker: write each channel as the archive's chunk file (float32, C order, encoded with
    the archive's compressor) into the batch's staging folder, so that the client commits the
    run by renaming files instead of receiving and compressing the arrays.

    Parameters
    ----------
    staging : (str, str) or None
        The staging folder and its token (:meth:`Archive.open_staging`).
    key : str
        A name unique to the run in this batch.
    channels : dict of str to numpy.ndarray
        ``irradiance``, ``sigma``, ``nexp``.

    Returns
    -------
    dict of str to str
        Channel name -> staged file; empty when the worker does not see the staging folder
        (no shared file system): then the arrays go to the client.
    """
    if staging is None:
        return {}
    folder, token = Path(staging[0]), staging[1]
    try:
        if (folder / "token").read_text() != token:
            return {}
    except OSError:
        return {}
    codec, out = _codec(), {}
    channels = complete_channels(channels)
    for name in CHANNELS:
        final = folder / f"{key}.{name}"
        tmp = folder / f".{key}.{name}.{os.getpid()}.partial"
        tmp.write_bytes(codec.encode(np.ascontiguousarray(channels[name], dtype=np.float32)))
        os.replace(tmp, final)
        out[name] = str(final)
    return out
