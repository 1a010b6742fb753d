"""A dark library: master darks keyed by camera, ISO, exposure time and temperature.

A folder holding one compressed ``.npz`` file per master dark (float32 ``data`` in DN, bias
included, plus a JSON ``metadata`` entry) and ``index.json`` listing every entry with its key
and its frame count N (the merge divides the dark variance by N). Writes are atomic and the
index is updated under a file lock, so several calibration runs can fill one library.
"""

from __future__ import annotations

import io as _io
import json
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrcap.pipeline.compat import same_model as same_camera
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import atomic_output
from hdrcap.pipeline.times import EXPOSURE_RTOL, same_exposure, unique_exposures

__all__ = ["DarkEntry", "DarkLibrary", "LIBRARY_FORMAT", "LIBRARY_VERSION", "same_camera"]

LIBRARY_FORMAT = "hdrcap-dark-library"
LIBRARY_VERSION = 1


@dataclass(frozen=True)
class DarkEntry:
    """One master dark of the library.

    Attributes
    ----------
    camera : str
    iso : float or None
    exposure_time : float
        Seconds.
    temperature : float or None
        Sensor temperature, degrees C.
    n_frames : int
        Number of dark frames averaged.
    file : str
        File name inside the library folder.
    level : float
        Spatial mean of the master dark, DN.
    created : str
    """

    camera: str
    iso: float | None
    exposure_time: float
    temperature: float | None
    n_frames: int
    file: str
    level: float = float("nan")
    created: str = ""


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.-]+", "-", text).strip("-")[:40] or "camera"


class DarkLibrary:
    """A folder of master darks with an ``index.json`` (created on first :meth:`add`)."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    @property
    def index_path(self) -> Path:
        return self.root / "index.json"

    def entries(self) -> list[DarkEntry]:
        """All entries of the index.

        Returns
        -------
        list of DarkEntry
            Empty when the library does not exist yet.
        """
        if not self.index_path.exists():
            return []
        try:
            meta = json.loads(self.index_path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise InputError(f"{self.index_path}: unreadable dark-library index ({err})") from None
        if meta.get("format") != LIBRARY_FORMAT or meta.get("version", 0) > LIBRARY_VERSION:
            raise InputError(f"{self.index_path}: not a dark library of version <= {LIBRARY_VERSION}")
        return [DarkEntry(**e) for e in meta.get("entries", [])]

    def add(
        self,
        data: np.ndarray,
        n_frames: int,
        *,
        camera: str,
        iso: float | None,
        exposure_time: float,
        temperature: float | None = None,
        force: bool = False,
        created: str = "",
    ) -> DarkEntry:
        """Store a master dark; an entry with the same key is replaced only with ``force``.

        Parameters
        ----------
        data : numpy.ndarray
            Master dark, DN (bias included).
        n_frames : int
            Frames averaged into it, N.
        camera : str
            Camera name.
        iso : float or None
            ISO speed.
        exposure_time : float
            Exposure time, s.
        temperature : float, optional
            Sensor temperature, degrees C.
        force : bool
            Replace an entry with the same key.
        created : str
            Creation time (ISO 8601), recorded.

        Returns
        -------
        DarkEntry
        """
        from filelock import FileLock

        if n_frames < 1:
            raise ValueError("n_frames must be >= 1")
        self.root.mkdir(parents=True, exist_ok=True)
        temp = "none" if temperature is None else f"{temperature:+.1f}C"
        iso_s = "none" if iso is None else f"{iso:g}"
        fname = f"dark_{_slug(camera)}_iso{iso_s}_{exposure_time:.6g}s_{temp}.npz"
        entry = DarkEntry(
            camera=camera,
            iso=None if iso is None else float(iso),
            exposure_time=float(exposure_time),
            temperature=None if temperature is None else float(temperature),
            n_frames=int(n_frames),
            file=fname,
            level=float(np.mean(data)),
            created=created,
        )
        with FileLock(str(self.root / ".index.lock")):
            entries = [e for e in self.entries() if e.file != fname]
            if len(entries) != len(self.entries()) and not force:
                raise InputError(f"{self.root / fname}: a master dark with this key exists; use --force to replace it")
            meta = json.dumps({"format": LIBRARY_FORMAT, "version": LIBRARY_VERSION, **entry.__dict__})
            buf = _io.BytesIO()
            np.savez_compressed(buf, data=np.asarray(data, np.float32), metadata=np.frombuffer(meta.encode(), np.uint8))
            with atomic_output(self.root / fname, force=True, suffix=".tmp") as tmp:
                tmp.write_bytes(buf.getvalue())
            entries.append(entry)
            entries.sort(key=lambda e: (e.camera, e.iso or 0, e.temperature or 0, e.exposure_time))
            index = {"format": LIBRARY_FORMAT, "version": LIBRARY_VERSION, "entries": [e.__dict__ for e in entries]}
            with atomic_output(self.index_path, force=True, suffix=".tmp") as tmp:
                tmp.write_text(json.dumps(index, indent=1))
        return entry

    def find(
        self,
        *,
        camera: str | None,
        iso: float | None,
        exposure_time: float,
        temperature: float | None = None,
        temperature_tolerance: float = 1.0,
        rtol: float = EXPOSURE_RTOL,
    ) -> DarkEntry | None:
        """The entry for a camera, ISO, exposure time and temperature.

        Parameters
        ----------
        camera : str or None
            Camera name (:func:`same_camera`; None: any).
        iso : float or None
            ISO speed (compared when both are known).
        exposure_time : float
            Exposure time, s (:func:`pipeline.times.same_exposure` with ``rtol``).
        temperature : float, optional
            Sensor temperature, degrees C (any temperature when either is unknown).
        temperature_tolerance : float
            Largest temperature difference, degrees C.
        rtol : float
            Relative tolerance of the exposure time.

        Returns
        -------
        DarkEntry or None
            The closest temperature, the most frames on ties; None when none matches.
        """
        return self._find(self.entries(), camera, iso, exposure_time, temperature, temperature_tolerance, rtol)

    @staticmethod
    def _find(entries, camera, iso, exposure_time, temperature, temperature_tolerance, rtol):
        best = None
        for e in entries:
            if not same_camera(camera, e.camera) or (iso is not None and e.iso is not None and abs(e.iso - iso) > 0.5):
                continue
            if not same_exposure(e.exposure_time, exposure_time, rtol):
                continue
            dt = 0.0
            if temperature is not None and e.temperature is not None:
                dt = abs(e.temperature - temperature)
                if dt > temperature_tolerance:
                    continue
            key = (dt, -e.n_frames)
            if best is None or key < best[0]:
                best = (key, e)
        return None if best is None else best[1]

    def masters(
        self,
        times: Iterable[float],
        *,
        camera: str | None = None,
        iso: float | None = None,
        temperature: float | None = None,
        temperature_tolerance: float = 1.0,
        rtol: float = EXPOSURE_RTOL,
        load: bool = True,
    ) -> dict[float, tuple[np.ndarray | None, int, DarkEntry]]:
        """Master darks for the exposure ``times`` that the library holds, matched as in
        :meth:`find`.

        Parameters
        ----------
        times : iterable of float
            Exposure times, s.
        camera, iso, temperature, temperature_tolerance, rtol
            As :meth:`find`.
        load : bool
            Load the data (else None).

        Returns
        -------
        dict
            t (s) -> (float32 master dark in DN or None, its frame count N, its entry). Times
            without a master are absent; an absent library gives an empty dict.
        """
        entries = self.entries()
        out: dict[float, tuple[np.ndarray | None, int, DarkEntry]] = {}
        for t in sorted(unique_exposures(times, rtol)):
            e = self._find(entries, camera, iso, t, temperature, temperature_tolerance, rtol)
            if e is not None:
                out[t] = (*self.load(e), e) if load else (None, e.n_frames, e)
        return out

    def load(self, entry: DarkEntry) -> tuple[np.ndarray, int]:
        """The master dark of an entry.

        Parameters
        ----------
        entry : DarkEntry

        Returns
        -------
        (numpy.ndarray, int)
            The master dark (float32, DN) and its frame count N.
        """
        path = self.root / entry.file
        try:
            with np.load(path, allow_pickle=False) as z:
                data = z["data"]
        except (OSError, KeyError, ValueError) as err:
            raise InputError(f"{path}: unreadable master dark ({type(err).__name__})") from None
        return data, entry.n_frames
