"""Calibration of frame files (what ``hdrcap calibrate`` runs): paths in, a Calibration out.

Frame files are read one at a time while the estimators stream them; the camera, ISO, white
level and capture dates the files record go into the provenance, and master darks can be
stored in a dark library as they are made. Frames of a static scene at the camera's exposure
times add the per-time shutter corrections (:func:`add_shutter_table`, ``--shutter``).
"""

from __future__ import annotations

import datetime as _dt
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from hdrcap.pipeline.calibration.dark import MasterDark
from hdrcap.pipeline.calibration.shutter import estimate_shutter_table
from hdrcap.pipeline.calibration.stats import DEFAULT_CLIP
from hdrcap.pipeline.calibration.workflow import calibrate, with_file_metadata
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.raw import RawFrame, read_frame
from hdrcap.pipeline.params import Calibration

__all__ = ["FileFrames", "calibrate_files", "add_shutter_table"]

PathLike = str | os.PathLike[str]

#: The kinds of calibration frames, in the order their exposure times are given.
_KINDS = ("bias", "saturation", "flat", "dark", "shutter")


class FileFrames:
    """Frame files read one at a time (memory-bounded streaming), noting what they record.

    Parameters
    ----------
    paths : sequence of path
        The files.
    times : sequence of float, optional
        Exposure times, s, one per file (None: from the file).
    meta : dict
        Filled with the ``camera``, ``iso`` and ``white_level`` (DN) of the first file that
        has them, and the ``first_timestamp``/``last_timestamp`` of the files.
    """

    def __init__(self, paths: Sequence[PathLike], times: Sequence[float | None] | None, meta: dict[str, Any]):
        self.paths = list(paths)
        self.times = list(times) if times else [None] * len(self.paths)
        self.meta = meta

    def __iter__(self) -> Iterator[RawFrame]:
        for p, t in zip(self.paths, self.times):
            fr = read_frame(p, t)
            m = self.meta
            m.setdefault("camera", fr.camera)
            m.setdefault("iso", fr.iso)
            m.setdefault("white_level", fr.white_level)
            if fr.timestamp:
                m["first_timestamp"] = min(m.get("first_timestamp") or fr.timestamp, fr.timestamp)
                m["last_timestamp"] = max(m.get("last_timestamp") or fr.timestamp, fr.timestamp)
            yield fr


def _check_paths(paths: Sequence[PathLike], what: str) -> None:
    """Refuse a file given twice or missing."""
    seen = {}
    for p in paths:
        key = str(Path(p).resolve())
        if key in seen:
            raise InputError(f"{p}: the same {what} file is given twice")
        seen[key] = p
        if not Path(p).exists():
            raise InputError(f"{p}: no such {what} file")


def _split_times(groups: Mapping[str, list], times: Sequence[float] | None) -> dict[str, list | None]:
    """One exposure time per frame, in the order bias, saturation, flat, dark, shutter, split by
    kind."""
    total = sum(len(v) for v in groups.values())
    if times and len(times) != total:
        raise InputError(
            f"--times gives {len(times)} exposure times for {total} frames "
            f"(one per frame, in the order {', '.join(k for k in _KINDS if k in groups)})"
        )
    tl = list(times) if times else None
    split, i = {}, 0
    for what, paths in groups.items():
        split[what] = tl[i : i + len(paths)] if tl else None
        i += len(paths)
    return split


def _dark_library_sink(folder: PathLike, meta: Mapping[str, Any], provenance: Mapping[str, Any], force: bool):
    """A ``dark_sink`` that stores each master dark in the dark library at ``folder``."""
    from hdrcap.pipeline.calibration.darklibrary import DarkLibrary

    lib = DarkLibrary(folder)

    def sink(master: MasterDark) -> None:
        lib.add(
            master.data,
            master.n_frames,
            camera=str(meta.get("camera") or provenance.get("camera") or "unknown"),
            iso=meta.get("iso"),
            exposure_time=master.exposure_time,
            temperature=provenance.get("temperature"),
            force=force,
            created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        )

    return sink


def add_shutter_table(
    calibration: Calibration,
    paths: Sequence[PathLike],
    times: Sequence[float] | None = None,
    *,
    reference: float | None = None,
) -> Calibration:
    """The calibration with the per-time shutter corrections measured from frame files
    (:func:`~hdrcap.pipeline.calibration.shutter.estimate_shutter_table`).

    Parameters
    ----------
    calibration : Calibration
        The camera's calibration (g, sigma2_R, v_sat, offset and dark-current maps, defects).
    paths : sequence of path
        Frames of a static scene at the camera's exposure times (several per time allowed).
    times : sequence of float, optional
        Exposure times, s, one per file (override EXIF).
    reference : float, optional
        Reference time, s, whose factor is 1 (default: the longest).

    Returns
    -------
    Calibration
        With ``shutter`` set, the files in ``provenance["files"]["shutter"]`` and the method in
        ``provenance["calibration"]["shutter"]``.

    Raises
    ------
    InputError
        A file missing or given twice, a wrong number of times, or the estimator's complaint.
    """
    paths = list(paths)
    if not paths:
        raise InputError("no shutter frames given (--shutter)")
    _check_paths(paths, "shutter")
    split = _split_times({"shutter": paths}, times)
    table = estimate_shutter_table(FileFrames(paths, split["shutter"], {}), calibration, reference=reference)
    prov = dict(calibration.provenance)
    prov["files"] = {**(prov.get("files") or {}), "shutter": [str(p) for p in paths]}
    prov["calibration"] = {
        **(prov.get("calibration") or {}),
        "shutter": {
            "method": "exposure-ratio pairs of a static scene (pipeline.exposure_ratio), per-time mean, "
            "anchored at the reference time",
            "reference": table.reference,
            "frames": len(paths),
        },
    }
    return calibration.replace(shutter=table, provenance=prov)


def calibrate_files(
    bias: Sequence[PathLike],
    saturation: Sequence[PathLike] = (),
    flats: Sequence[PathLike] = (),
    darks: Sequence[PathLike] = (),
    times: Sequence[float] | None = None,
    *,
    shutter: Sequence[PathLike] = (),
    shutter_reference: float | None = None,
    clip: float | None = DEFAULT_CLIP,
    gain_method: str = "auto",
    white_level: float | None = None,
    provenance: Mapping[str, Any] | None = None,
    dark_library: PathLike | None = None,
    force: bool = False,
) -> Calibration:
    """Calibrate from frame files (:func:`~hdrcap.pipeline.calibration.calibrate` on files).

    Parameters
    ----------
    bias, saturation, flats, darks : sequence of path
        Frame files of each kind (raw, or 16-bit PNG/TIFF with ``times``); darks are sorted
        by exposure time when ``times`` are given.
    times : sequence of float, optional
        Exposure times, s, one per file in the order bias, saturation, flats, darks, shutter;
        they override the files' EXIF.
    shutter : sequence of path
        Frames of a static scene at the camera's exposure times: the per-time shutter
        corrections (:func:`add_shutter_table`), measured with the calibration just made.
    shutter_reference : float, optional
        Reference time of the shutter corrections, s (default: the longest).
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables outlier rejection.
    gain_method : {"auto", "pairs", "ptc"}
        As in :func:`~hdrcap.pipeline.calibration.calibrate`.
    white_level : float, optional
        ADC white level, DN (default: from the files).
    provenance : mapping, optional
        Camera, serial, ISO, temperature (degrees C), ... recorded with the result.
    dark_library : path, optional
        Folder of a dark library that receives every master dark.
    force : bool
        Replace existing dark-library entries.

    Returns
    -------
    Calibration
        With the files' camera, ISO and dates and the file lists in its provenance.

    Raises
    ------
    InputError
        A file missing or given twice, a wrong number of times, no bias frames, or any
        estimator's complaint about the frames.
    """
    provenance = dict(provenance or {})
    groups = {
        "bias": list(bias),
        "saturation": list(saturation),
        "flat": list(flats),
        "dark": list(darks),
        "shutter": list(shutter),
    }
    for what, paths in groups.items():
        _check_paths(paths, what)
    split = _split_times(groups, times)
    dark_times = split["dark"]
    if dark_times:  # darks are streamed one exposure time after the other
        order = sorted(range(len(groups["dark"])), key=lambda k: dark_times[k])
        groups["dark"] = [groups["dark"][k] for k in order]
        split["dark"] = [dark_times[k] for k in order]
    meta: dict[str, Any] = {}
    lazy = {w: FileFrames(groups[w], split[w], meta) if groups[w] else None for w in _KINDS if w != "shutter"}
    sink = None if dark_library is None else _dark_library_sink(dark_library, meta, provenance, force)
    if lazy["bias"] is None:
        raise InputError("no bias frames given (--bias)")
    calib = calibrate(
        lazy["bias"],
        lazy["saturation"],
        lazy["flat"],
        lazy["dark"],
        clip=clip,
        gain_method=gain_method,
        white_level=white_level,
        dark_sink=sink,
        provenance=provenance,
    )
    calib = with_file_metadata(
        calib, meta, white_level, dark_library=None if dark_library is None else str(dark_library)
    )
    prov = dict(calib.provenance)
    prov["files"] = {w: [str(p) for p in v] for w, v in groups.items() if v and w != "shutter"}
    calib = calib.replace(provenance=prov)
    if groups["shutter"]:
        calib = add_shutter_table(calib, groups["shutter"], split["shutter"], reference=shutter_reference)
    return calib
