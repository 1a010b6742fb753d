"""The calibration library: calibrate a camera once, merge its brackets without naming the file.

Calibration files (:func:`pipeline.calibration.save_calibration`) are kept in one folder of the
user's data directory, one file per camera model (normalised), serial number (when known) and
ISO: ``<model>__<serial or any>__iso<ISO>.cal``. The folder is ``$HDRCAP_DATA_DIR/calibrations``
when that variable is set, else ``$XDG_DATA_HOME/hdrcap/calibrations``, else
``~/.local/share/hdrcap/calibrations``.

``hdrcap merge`` without ``--calibration`` looks here first (:func:`find_calibration`: same
model and ISO, and the frame size of the calibration's maps), then calibrates itself from the
bracket.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from hdrcap.pipeline.compat import same_model
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.params import Calibration

__all__ = [
    "LibraryEntry",
    "library_dir",
    "model_slug",
    "entry_name",
    "store_calibration",
    "library_entries",
    "find_calibration",
    "remove_calibration",
]

_SUFFIX = ".cal"


def library_dir() -> Path:
    """The library folder (see module docstring); not created here.

    Returns
    -------
    pathlib.Path
    """
    root = os.environ.get("HDRCAP_DATA_DIR")
    if root:
        return Path(root) / "calibrations"
    xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(xdg) / "hdrcap" / "calibrations"


def model_slug(name: str | None) -> str:
    """A camera model as a file-name key: lower case, runs of anything but letters and digits as
    one ``-`` (``"Canon EOS 5D Mark II"`` -> ``"canon-eos-5d-mark-ii"``). Entries are matched to
    frames by :func:`pipeline.compat.same_model`, the one model rule (libgphoto2's and
    EXIF's spellings of one camera match), not by this key.

    Parameters
    ----------
    name : str or None

    Returns
    -------
    str
        ``""`` for None or a name without letters or digits.
    """
    return re.sub(r"[^a-z0-9]+", "-", (name or "").lower()).strip("-")


def entry_name(camera: str, serial: str | None, iso: float) -> str:
    """The file name of a library entry (camera model, serial or ``any``, ISO).

    Parameters
    ----------
    camera : str
        Camera model as the files or libgphoto2 name it (normalised here).
    serial : str or None
        Serial number, when known.
    iso : float
        ISO speed.

    Returns
    -------
    str
        ``<model>__<serial|any>__iso<ISO>.cal``.
    """
    model = model_slug(camera)
    if not model:
        raise InputError("a library calibration needs the camera model (--camera-name, or from the files)")
    ser = model_slug(serial) or "any"
    return f"{model}__{ser}__iso{float(iso):g}{_SUFFIX}"


@dataclass(frozen=True)
class LibraryEntry:
    """One calibration in the library.

    Attributes
    ----------
    name : str
        File name (the key).
    path : pathlib.Path
    model : str
        Normalised camera model.
    serial : str or None
        Normalised serial number, None for ``any``.
    iso : float
    """

    name: str
    path: Path
    model: str
    serial: str | None
    iso: float


def _parse(path: Path) -> LibraryEntry | None:
    m = re.fullmatch(r"(.+)__(.+)__iso([0-9.eE+-]+)" + re.escape(_SUFFIX), path.name)
    if not m:
        return None
    return LibraryEntry(path.name, path, m.group(1), None if m.group(2) == "any" else m.group(2), float(m.group(3)))


def library_entries() -> list[LibraryEntry]:
    """Every calibration in the library, sorted by name.

    Returns
    -------
    list of LibraryEntry
    """
    root = library_dir()
    if not root.is_dir():
        return []
    return [e for e in (_parse(p) for p in sorted(root.glob("*" + _SUFFIX))) if e is not None]


def store_calibration(
    calibration: Calibration,
    *,
    camera: str | None = None,
    serial: str | None = None,
    iso: float | None = None,
    force: bool = False,
) -> Path:
    """Save ``calibration`` into the library under its camera model, serial and ISO.

    Parameters
    ----------
    calibration : Calibration
    camera, serial, iso : optional
        Override the calibration's provenance (``camera``, ``serial``, ``iso``).
    force : bool
        Replace an entry with the same key.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    InputError
        No camera model or no ISO known.
    """
    from hdrcap.pipeline.calibration import save_calibration

    prov = calibration.provenance or {}
    camera = camera or prov.get("camera") or calibration.params.name
    iso = iso if iso is not None else prov.get("iso")
    if iso is None:
        raise InputError("a library calibration needs the ISO (--iso, or from the files' EXIF)")
    root = library_dir()
    root.mkdir(parents=True, exist_ok=True)
    return save_calibration(root / entry_name(camera, serial or prov.get("serial"), iso), calibration, force=force)


def _map_shape(calibration: Calibration) -> tuple[int, int] | None:
    for m in (
        calibration.prnu,
        calibration.bias_map,
        calibration.dark_current_map,
        calibration.saturation_map,
        calibration.defect_map,
    ):
        if m is not None:
            return tuple(m.shape)
    return None


def find_calibration(
    camera: str | None, iso: float | None, shape: tuple[int, int], serial: str | None = None
) -> tuple[LibraryEntry, Calibration] | None:
    """The library's calibration for frames of ``camera`` at ``iso`` and size ``shape``.

    Same normalised model and ISO (within 1 %); a calibration with maps must have the frames'
    size; an entry of the same serial is preferred to one of ``any`` serial or another.

    Parameters
    ----------
    camera : str or None
        Camera model of the frames.
    iso : float or None
    shape : (int, int)
        Frame size (rows, columns).
    serial : str, optional

    Returns
    -------
    (LibraryEntry, Calibration) or None
    """
    from hdrcap.pipeline.calibration import load_calibration

    model = model_slug(camera)
    if not model or iso is None:
        return None
    ser = model_slug(serial) or None
    cands = [
        e
        for e in library_entries()
        if same_model(e.model, camera) and abs(e.iso - float(iso)) <= 0.01 * float(iso)  # the one model rule
    ]
    cands.sort(key=lambda e: (e.serial != ser, e.serial is not None, e.name))
    for e in cands:
        calib = load_calibration(e.path)
        got = _map_shape(calib)
        if got is None or got == tuple(shape):
            return e, calib
    return None


def remove_calibration(name: str) -> Path:
    """Delete the library entry ``name`` (its file name, with or without ``.cal``).

    Parameters
    ----------
    name : str
        The entry's file name (``hdrcap calibrations list`` shows it).

    Returns
    -------
    pathlib.Path
        The file removed.

    Raises
    ------
    InputError
        No such entry.
    """
    name = name if name.endswith(_SUFFIX) else name + _SUFFIX
    path = library_dir() / Path(name).name
    if not path.is_file():
        raise InputError(f"{name}: no such calibration in the library {library_dir()} (see `hdrcap calibrations list`)")
    path.unlink()
    return path
