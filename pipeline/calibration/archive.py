"""The calibration file: a NumPy archive of float32 maps and JSON metadata.

Format (docs/calibration.md): a ``.npz`` archive with the float32 maps ``prnu``,
``prnu_stderr``, ``bias_map``, ``bias_map_stderr``, ``dark_current_map``,
``dark_current_map_stderr``, ``saturation_map``, the uint8 ``defect_map`` (each optional) and a
``metadata`` entry holding UTF-8 JSON: ``format``, ``version``, ``shape``, ``params``,
``stderr``, ``provenance``, ``maps``, ``dark_library`` and ``shutter`` (the per-time shutter
corrections, a table, or null). Files written before the standard-error and defect maps and
the shutter table existed load with those fields ``None``.

The maps are stored uncompressed (``np.savez``): per-photosite maps are noise-like and zlib
saved only about 24 % of their size while costing 15 s to write and 1.3 s to read per 24 Mpixel
map. Stored members are memory-mapped on load (copy-on-write: the file is never modified, and
writing to a loaded map changes only this process's copy), so a merge reads only the pages it
uses. Compressed files written by earlier versions still load (read into memory).
"""

from __future__ import annotations

import json
import math
import os
import struct
import tokenize
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import atomic_output, release_mapped_pages
from hdrcap.pipeline.params import Calibration, SensorParams, ShutterTable

__all__ = ["FORMAT", "FORMAT_VERSION", "save_calibration", "load_calibration"]

#: Identifier and version of the calibration file format (see docs/calibration.md).
FORMAT = "hdrcap-calibration"
FORMAT_VERSION = 1

_MAP_FIELDS = (
    "prnu",
    "prnu_stderr",
    "bias_map",
    "bias_map_stderr",
    "dark_current_map",
    "dark_current_map_stderr",
    "saturation_map",
)
#: Maps stored with their own integer type instead of float32.
_INT_MAPS = {"defect_map": np.uint8}


def _jsonable(obj):
    """JSON form of the numpy scalars, arrays and paths found in the provenance."""
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in calibration metadata")


def save_calibration(path: str | os.PathLike[str], calibration: Calibration, force: bool = False) -> Path:
    """Write ``calibration`` to ``path`` atomically (never overwriting without ``force``).

    Parameters
    ----------
    path : str or path-like
        Output file (any name; the format is described in the module docstring).
    calibration : Calibration
        The camera model: scalars in DN, DN^2, DN/e-, e-/s; float32 maps of one shape.
    force : bool
        Replace an existing file.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``force`` is not given.
    ValueError
        Maps of different shapes.
    """
    from hdrcap import __version__

    arrays = {}
    shape = None
    for name in (*_MAP_FIELDS, *_INT_MAPS):
        arr = getattr(calibration, name, None)
        if arr is None:
            continue
        arr = np.ascontiguousarray(arr, dtype=_INT_MAPS.get(name, np.float32))
        if shape is not None and arr.shape != shape:
            raise ValueError(f"calibration map {name} has shape {arr.shape}, expected {shape}")
        shape = arr.shape
        arrays[name] = arr
    prov = dict(calibration.provenance)
    prov.setdefault("hdrcap_version", __version__)
    meta = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "shape": list(shape) if shape else None,
        "params": calibration.params.to_dict(),
        "stderr": dict(calibration.stderr),
        "provenance": prov,
        "maps": sorted(arrays),
        "dark_library": getattr(calibration, "dark_library", None),
        "shutter": None if calibration.shutter is None else calibration.shutter.to_dict(),
    }
    text = json.dumps(meta, sort_keys=True, default=_jsonable, allow_nan=True)
    arrays["metadata"] = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)
    path = Path(path)
    with atomic_output(path, force=force, suffix=".tmp") as tmp, open(tmp, "wb") as fh:
        # a file object: no ".npz" added to the name, no copy in memory; no pickles (the reader refuses them)
        np.savez(fh, allow_pickle=False, **arrays)
    return path


def _member_header(zf: zipfile.ZipFile, name: str, ndim: int = 2) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Shape, Fortran order and dtype of the ``.npy`` member ``name``, checked against the
    member's stored size before anything is allocated.

    Raises
    ------
    ValueError
        Not an ``ndim``-D array of real numbers, or the header promises more data than the
        member holds.
    """
    info = zf.getinfo(f"{name}.npy")
    with zf.open(info) as fh:
        fmt = np.lib.format
        version = fmt.read_magic(fh)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"map {name}: npy format version {version}")
        read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read_header(fh)
        header_size = fh.tell()
    if dtype.kind not in "fiub" or len(shape) != ndim:
        raise ValueError(f"member {name} is a {len(shape)}-D array of {dtype}, not {ndim}-D numbers")
    if header_size + dtype.itemsize * int(np.prod(shape, dtype=object)) > info.file_size:
        raise ValueError(f"member {name}: its header promises more data than the archive holds")
    return shape, fortran, dtype


def _memmap_member(path: Path, zf: zipfile.ZipFile, name: str) -> np.ndarray | None:
    """Copy-on-write memory map of the array ``name`` of an ``.npz`` file when it is stored
    uncompressed, else None (the caller then reads it). The header is checked first
    (:func:`_member_header`)."""
    shape, fortran, dtype = _member_header(zf, name)
    info = zf.getinfo(f"{name}.npy")
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    with open(path, "rb") as fh:
        fh.seek(info.header_offset)
        local = fh.read(30)
        if len(local) != 30 or local[:4] != b"PK\x03\x04":
            return None
        start = (
            info.header_offset + 30 + int.from_bytes(local[26:28], "little") + int.from_bytes(local[28:30], "little")
        )
        fh.seek(start)
        fmt = np.lib.format
        version = fmt.read_magic(fh)
        if version not in ((1, 0), (2, 0)):
            return None
        read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        if read_header(fh) != (shape, fortran, dtype):
            return None
        offset = fh.tell()
    if offset - start + dtype.itemsize * int(np.prod(shape)) > info.file_size:
        return None
    if offset + dtype.itemsize * int(np.prod(shape)) > path.stat().st_size:
        raise ValueError(f"map {name} runs past the end of the file")
    return np.memmap(path, dtype=dtype, mode="c", offset=offset, shape=shape, order="F" if fortran else "C")


#: What zipfile, zlib and numpy raise for a damaged archive (a corrupt member name, CRC,
#: compressed stream, npy header or JSON).
_ARCHIVE_ERRORS = (
    OSError,
    ValueError,
    KeyError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
    NotImplementedError,
    RuntimeError,
    TypeError,
    OverflowError,
    struct.error,
    SyntaxError,
    tokenize.TokenError,
)


def _read_archive(path: Path) -> tuple[Any, dict[str, np.ndarray]]:
    """The metadata (parsed JSON) and the maps of a calibration archive."""
    try:
        with np.load(path, allow_pickle=False) as z, zipfile.ZipFile(path) as zf:
            if "metadata" not in z.files:
                raise InputError(f"{path}: not an hdrcap calibration file (no metadata entry)")
            _member_header(zf, "metadata", ndim=1)
            meta = json.loads(bytes(z["metadata"]).decode("utf-8"))
            names = [name for name in (*_MAP_FIELDS, *_INT_MAPS) if name in z.files]
            mapped = {name: _memmap_member(path, zf, name) for name in names}
            maps = {name: z[name] if arr is None else arr for name, arr in mapped.items()}
    except InputError:
        raise
    except _ARCHIVE_ERRORS as err:
        detail = str(err).splitlines()[0][:200] if str(err) else ""
        raise InputError(
            f"{path}: not a readable hdrcap calibration file ({type(err).__name__}{': ' + detail if detail else ''})"
        ) from None
    return meta, maps


def _check_metadata(path: Path, meta: Any) -> tuple[int, ...] | None:
    """Refuse metadata of the wrong format, version or types; return the recorded map shape."""
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(
            f"{path}: not an hdrcap calibration file (format {meta.get('format')!r})"
            if isinstance(meta, dict)
            else f"{path}: not an hdrcap calibration file"
        )
    version = meta.get("version")
    if not isinstance(version, int) or version < 1 or version > FORMAT_VERSION:
        raise InputError(
            f"{path}: calibration format version {version!r} is not supported "
            f"(this hdrcap reads versions 1..{FORMAT_VERSION})"
        )
    shape = meta.get("shape")
    if shape is not None and not (
        isinstance(shape, list) and len(shape) == 2 and all(type(n) is int and n > 0 for n in shape)
    ):
        raise InputError(f"{path}: bad map shape {shape!r} in the metadata")
    for key in ("params", "stderr", "provenance"):
        if meta.get(key) is not None and not isinstance(meta[key], dict):
            raise InputError(f"{path}: metadata entry {key!r} is not a table")
    stderr = meta.get("stderr") or {}
    if not all(v is None or (type(v) in (int, float) and math.isfinite(v) and v >= 0) for v in stderr.values()):
        raise InputError(f"{path}: standard errors must be finite numbers >= 0")
    if meta.get("maps") is not None and not (
        isinstance(meta["maps"], list) and all(isinstance(m, str) for m in meta["maps"])
    ):
        raise InputError(f"{path}: metadata entry 'maps' is not a list of map names")
    if meta.get("dark_library") is not None and not isinstance(meta["dark_library"], str):
        raise InputError(f"{path}: dark_library must be a folder name")
    return tuple(shape) if shape else None


def _check_params(path: Path, raw: Any) -> SensorParams:
    """The scalar model, refused when a value is not a number or the levels contradict each
    other (bias level at or above the saturation limit, saturation limit above the white level)."""
    if not isinstance(raw, dict):
        raise InputError(f"{path}: no camera parameters")
    for key, value in raw.items():
        if key != "name" and (type(value) not in (int, float)):
            raise InputError(f"{path}: camera parameter {key} is {value!r}, not a number")
    try:
        params = SensorParams(**raw)
    except (TypeError, ValueError) as err:
        raise InputError(f"{path}: bad camera parameters ({err})") from None
    if not params.mu_R < params.v_sat <= params.white_level:
        raise InputError(
            f"{path}: bad camera parameters (need bias level {params.mu_R:g} < saturation limit "
            f"{params.v_sat:g} <= white level {params.white_level:g} DN)"
        )
    return params


#: Range of a PRNU gain that is a photosite's response: calibrate writes gains near 1 and sets
#: dead and weak photosites to 1 in the defect map's place; anything outside is a damaged file.
PRNU_RANGE = (1e-2, 1e2)
#: Largest dark current (or its standard error) a map may hold, e-/s: a full well of 1e6 e- filled
#: in a microsecond; the other maps have their own bounds (gains, white level).
DARK_CURRENT_MAX = 1e12


def _extremes(arr: np.ndarray) -> np.ndarray:
    """The values the checks of a map need to see: for a float map its least and largest value
    (same dtype; a NaN anywhere makes both NaN), for which every test of
    :func:`load_calibration` and :func:`_check_map_range` (finite; a bound on the value or on its
    magnitude) gives the answer it gives on the whole map, in two passes without temporaries
    (a 24 Mpixel map took 0.1 s of elementwise masks); an integer map (the defect map) or an
    empty one as it is."""
    if arr.dtype.kind != "f" or arr.size == 0:
        return arr
    return np.array([arr.min(), arr.max()], dtype=arr.dtype)


def _check_map_range(path: Path, name: str, arr: np.ndarray, params: SensorParams) -> None:
    """Refuse a map whose values no measurement gives: PRNU gains outside :data:`PRNU_RANGE`,
    negative standard errors, standard errors of a gain above 100 or of a bias above the white
    level, dark currents beyond :data:`DARK_CURRENT_MAX`, bias levels outside 0..white level (DN). A negative dark-current map
    is read as it is (files written before the map was clamped; the merge floors its variances).
    ``arr`` is the map or its :func:`_extremes`."""
    if name == "prnu" and not (np.all(arr >= PRNU_RANGE[0]) and np.all(arr <= PRNU_RANGE[1])):
        lo, hi = float(np.min(arr)), float(np.max(arr))
        raise InputError(f"{path}: PRNU map has gains {lo:.3g}..{hi:.3g}, outside {PRNU_RANGE[0]:g}..{PRNU_RANGE[1]:g}")
    if name in ("bias_map_stderr", "dark_current_map_stderr", "prnu_stderr") and np.any(arr < 0):
        raise InputError(f"{path}: map {name} has negative values")
    limit = {"prnu_stderr": PRNU_RANGE[1], "bias_map_stderr": params.white_level}.get(name, DARK_CURRENT_MAX)
    if name != "defect_map" and np.any(np.abs(arr) > limit):
        raise InputError(f"{path}: map {name} has values beyond {limit:g}, which no measurement gives")
    if name == "bias_map" and (np.any(arr < 0) or np.any(arr > params.white_level)):
        raise InputError(f"{path}: bias map has levels outside 0..{params.white_level:g} DN (the white level)")


def _check_shutter(path: Path, raw: Any) -> ShutterTable | None:
    """The shutter table of the metadata (None when absent), refused when malformed."""
    if raw is None:
        return None
    try:
        return ShutterTable.from_dict(raw)
    except ValueError as err:
        raise InputError(f"{path}: bad {err}") from None


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file written by :func:`save_calibration`.

    Checks the format name, the version (files of a newer major version are refused), the
    types of the metadata, that the levels are ordered (bias < saturation <= white level) and
    that every map is a finite 2-D array of the recorded shape; a damaged archive is refused
    before any map is allocated from its header.

    Parameters
    ----------
    path : str or path-like
        The calibration file.

    Returns
    -------
    Calibration
        Scalars g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), D (e-/s), their standard
        errors, the maps and the provenance.

    Raises
    ------
    InputError
        Missing or unreadable file, not a calibration file, unsupported version, bad shape.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such calibration file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a calibration file")
    meta, maps = _read_archive(path)
    shape = _check_metadata(path, meta)
    missing = sorted(set(meta.get("maps") or ()) - set(maps))
    if missing:
        raise InputError(f"{path}: map {missing[0]} is listed in the metadata but missing from the archive")
    params = _check_params(path, meta.get("params"))
    for name, arr in maps.items():
        if arr.ndim != 2 or (shape is not None and arr.shape != shape):
            raise InputError(f"{path}: map {name} has shape {arr.shape}, the file says {shape}")
        values = _extremes(arr)
        if not np.all(np.isfinite(values)):
            raise InputError(f"{path}: map {name} holds NaN or infinite values")
        _check_map_range(path, name, values, params)
        release_mapped_pages([arr])  # checked: a mapped map need not stay resident (huge frames)
    if "defect_map" in maps and maps["defect_map"].dtype != np.uint8:
        raise InputError(f"{path}: defect map has type {maps['defect_map'].dtype}, expected uint8")
    return Calibration(
        params=params,
        prnu=maps.get("prnu"),
        bias_map=maps.get("bias_map"),
        dark_current_map=maps.get("dark_current_map"),
        stderr={k: float(v) for k, v in (meta.get("stderr") or {}).items() if v is not None},
        provenance=dict(meta.get("provenance") or {}),
        prnu_stderr=maps.get("prnu_stderr"),
        saturation_map=maps.get("saturation_map"),
        dark_library=meta.get("dark_library"),
        bias_map_stderr=maps.get("bias_map_stderr"),
        dark_current_map_stderr=maps.get("dark_current_map_stderr"),
        defect_map=maps.get("defect_map"),
        shutter=_check_shutter(path, meta.get("shutter")),
    )
