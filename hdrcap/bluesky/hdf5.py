"""The HDF5 file an :class:`hdrcap.bluesky.HdrDetector` writes: one dataset per map, the
measurement index first, each measurement appended whole or not at all."""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import UNIT_ELECTRONS, channel

__all__ = ["MapSpec", "MAPS", "MapFile"]

#: numpy type of each storage kind of :mod:`hdrcap.pipeline.schema` (sigma at full float32).
_DTYPES = {"float": np.dtype("<f4"), "sigma": np.dtype("<f4"), "uint": np.dtype("<u4")}


@dataclass(frozen=True)
class MapSpec:
    """One map of a measurement in the HDF5 file.

    Attributes
    ----------
    name : str
        Channel of :mod:`hdrcap.pipeline.schema` and dataset ``/name``.
    dtype : numpy.dtype
        Stored type (little-endian).
    units : str or None
    description : str
    """

    name: str
    dtype: np.dtype
    units: str | None
    description: str


def _spec(name: str, units: str | None) -> MapSpec:
    ch = channel(name)
    return MapSpec(name, _DTYPES[ch.storage], units, ch.description)


#: The maps every measurement writes, in order.
MAPS: tuple[MapSpec, ...] = (
    _spec("irradiance", UNIT_ELECTRONS),
    _spec("sigma", UNIT_ELECTRONS),
    _spec("nexp", "exposures"),
    _spec("quality", None),
)


class MapFile:
    """An HDF5 file of measurements: datasets ``/irradiance``, ``/sigma``, ``/nexp``,
    ``/quality`` of shape (N, rows, columns), chunked one measurement per chunk, written in
    SWMR mode (readers may open it while measurements are added). Created with the first
    measurement (a real camera's size is known only then).

    Parameters
    ----------
    path : Path
        The file (must not exist).
    attrs : dict, optional
        JSON-ready file attributes (the detector's settings), stored as JSON strings.
    """

    def __init__(self, path: Path, attrs: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.attrs = dict(attrs or {})
        self.shape: tuple[int, int] | None = None
        self._file: Any = None
        self._closed = False
        self._lock = threading.Lock()  # append (a worker thread) and close (the event loop)

    def append(self, result: HdrResult, index: int) -> None:
        """Write ``result``'s maps as measurement ``index`` (a row from ``index`` on that was left
        by an earlier failure is replaced). On any failure the file is left with ``index``
        measurements.

        Parameters
        ----------
        result : HdrResult
        index : int
            Measurements already in the file (and in the documents).

        Raises
        ------
        ValueError
            A result of another size than the file's, or whose nexp or quality is missing.
        """
        with self._lock:
            self._append(result, index)

    def _append(self, result: HdrResult, index: int) -> None:
        maps = {m.name: getattr(result, m.name) for m in MAPS}
        missing = [name for name, arr in maps.items() if arr is None]
        if missing:
            raise ValueError(f"the merge has no {', '.join(missing)} map")
        if self._closed:
            raise ValueError(f"{self.path}: closed")
        if self._file is None:
            self._create(result.shape)
        if result.shape != self.shape:
            raise ValueError(f"a measurement of size {result.shape}, the file holds {self.shape}")
        data = {m.name: np.asarray(maps[m.name]).astype(m.dtype, copy=False) for m in MAPS}
        try:
            for m in MAPS:
                dset = self._file[m.name]
                dset.resize(index + 1, axis=0)
                dset[index] = data[m.name]
            self._flush()
        except BaseException:
            for m in MAPS:
                self._file[m.name].resize(index, axis=0)
            self._flush()
            raise

    def __len__(self) -> int:
        return 0 if self._file is None else int(self._file[MAPS[0].name].shape[0])

    def _create(self, shape: tuple[int, int]) -> None:
        import h5py

        h, w = shape
        f = h5py.File(self.path, "x", libver="latest")
        try:
            for m in MAPS:
                dset = f.create_dataset(
                    m.name,
                    shape=(0, h, w),
                    maxshape=(None, h, w),
                    dtype=m.dtype,
                    chunks=(1, h, w),
                    compression="gzip",
                    compression_opts=1,
                    shuffle=True,
                )
                dset.attrs["description"] = m.description
                dset.attrs["dims"] = ["measurement", "row", "column"]
                if m.units:
                    dset.attrs["units"] = m.units
            for key, value in self.attrs.items():
                f.attrs[key] = json.dumps(value)
            f.swmr_mode = True  # from here on readers may open the file while it grows
        except BaseException:
            f.close()
            self.path.unlink(missing_ok=True)
            raise
        self._file, self.shape = f, (int(h), int(w))

    def _flush(self) -> None:
        for m in MAPS:
            self._file[m.name].flush()
        self._file.flush()

    def close(self) -> None:
        """Close the file (after an append in progress; nothing to do before the first measurement)."""
        with self._lock:
            f, self._file = self._file, None
            self._closed = True
            if f is not None:
                f.close()
