"""The public Python API of hdrcap: a small, flat set of functions for notebooks and programs.

Arrays in, arrays out; files only where asked (paths may be given instead of arrays, and
:meth:`HdrResult.write` writes an EXR). Everything here is a thin layer over the library
(:mod:`hdrcap.pipeline`, :mod:`hdrcap.planner`, :mod:`hdrcap.mock_camera`)::

    sim = simulate("camera-B", times=[0.001, 0.01, 0.1, 1.0], seed=1)   # raw frames + truth
    hdr = merge(sim.frames, sim.times, calibration=sim.calibration)      # irradiance, sigma, nexp
    p = plan("camera-B", hdr.irradiance, target_snr_db=30)               # exposures for 30 dB
    smooth = denoise(hdr)                                                # Sec. 9 bilateral filter
    smooth.write("scene.exr")

Units (the paper's): irradiance X in electrons per second per photosite (e-/s), exposure
times t in seconds, raw values and dark frames in DN, gain g in DN per electron, read-noise
variance sigma2_R in DN^2, dark current D in e-/s. Raw frames are CFA mosaics (2-D arrays,
uint16 or float), never demosaiced.

Every problem with the caller's input raises :class:`InputError` (a :class:`HdrcapError`)
whose ``str()`` is a one-line message naming the frame, file or value at fault.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Union

import numpy as np

from hdrcap.pipeline.errors import HdrcapError, InputError
from hdrcap.pipeline.io.raw import RawFrame
from hdrcap.pipeline.merge.accumulator import MergeOptions
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.result import HdrResult

if TYPE_CHECKING:  # imported lazily at run time (numba, the planner, the simulator)
    from hdrcap.pipeline.planfile import PlanFile
    from hdrcap.planner.plan import Plan

__all__ = [
    "HdrResult",
    "HdrcapError",
    "InputError",
    "MergeOptions",
    "Simulation",
    "calibrate",
    "camera_calibration",
    "denoise",
    "load_calibration",
    "merge",
    "plan",
    "read_exr",
    "save_calibration",
    "simulate",
    "write_exr",
]

#: A frame given to the API: a file path (raw file, or 16-bit PNG/TIFF with its exposure
#: time), a 2-D array of raw values in DN, or a :class:`~hdrcap.pipeline.io.raw.RawFrame`.
FrameLike = Union[str, "os.PathLike[str]", np.ndarray, RawFrame]

#: A camera model: a :class:`Calibration`, a calibration file written by :func:`save_calibration`
#: (``hdrcap calibrate``), or the name of a simulator preset (``"camera-A"``, ``"camera-B"``).
CalibrationLike = Union[Calibration, str, "os.PathLike[str]"]

#: Exposure times of :func:`simulate` when none are given, s.
DEFAULT_SIMULATION_TIMES: tuple[float, ...] = (0.001, 0.004, 0.016, 0.064, 0.25, 1.0)

# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class Simulation:
    """A bracket of the simulated camera, with the truth behind it.

    Attributes
    ----------
    frames : tuple of numpy.ndarray
        uint16 (H, W) raw mosaics, DN, one per exposure time.
    times : tuple of float
        Exposure times actually used, s (the rational a camera writes into its files).
    truth : numpy.ndarray
        float64 (H, W) true irradiance of the scene, e-/s per photosite.
    calibration : Calibration
        The sensor's true model: its nominal scalars (Table 2) with its PRNU and dark-current
        maps (what a perfect calibration would find).
    darks : tuple of numpy.ndarray or None
        uint16 dark frames, DN, one per exposure time (same order), when asked for.
    camera : str
        Preset name.
    cfa_pattern : str
        Bayer tile of the mosaic, e.g. ``"RGGB"``.
    seed : int
        Seed of the fixed patterns and the noise.
    """

    frames: tuple[np.ndarray, ...]
    times: tuple[float, ...]
    truth: np.ndarray
    calibration: Calibration
    darks: tuple[np.ndarray, ...] | None
    camera: str
    cfa_pattern: str
    seed: int


# --------------------------------------------------------------------------- inputs


def _is_single(x: Any) -> bool:
    return isinstance(x, (str, os.PathLike, RawFrame)) or (isinstance(x, np.ndarray) and x.ndim == 2)


def _items(x: Any, what: str) -> list:
    """A list of frame-likes from one frame-like or a sequence (a 3-D array is a stack)."""
    if x is None:
        return []
    if _is_single(x):
        return [x]
    try:
        return list(x)
    except TypeError:
        raise InputError(f"{what}: expected file paths or 2-D arrays, got {type(x).__name__}") from None


def _times(times: Sequence[float | None] | None, n: int, what: str) -> list[float | None]:
    if times is None:
        return [None] * n
    if isinstance(times, (int, float)):
        times = [times]
    times = list(times)
    if len(times) != n:
        raise InputError(f"{len(times)} exposure times for {n} {what}s")
    return times


def _frame(item: Any, t: float | None, what: str, index: int, *, need_time: bool = True) -> RawFrame:
    """Read or wrap one frame; ``t`` (s) overrides the file's exposure time."""
    from hdrcap.pipeline.io.raw import check_exposure_time, read_frame

    name = f"{what} {index + 1}"
    if isinstance(item, RawFrame):
        if t is None:
            return item
        return dataclasses.replace(item, exposure_time=check_exposure_time(t, item.path or name))
    if isinstance(item, (str, os.PathLike)):
        return read_frame(Path(item), t)
    data = np.asarray(item)
    if data.ndim != 2:
        raise InputError(f"{name}: expected a 2-D raw mosaic (DN), got shape {data.shape}")
    if data.dtype.kind not in "uif":
        raise InputError(f"{name}: pixel type {data.dtype} is not numeric")
    if t is None:
        if need_time:
            raise InputError(f"{name}: an array needs its exposure time; give times=[...] in seconds")
        return RawFrame(data=data, exposure_time=0.0)
    return RawFrame(data=data, exposure_time=check_exposure_time(t, name))


def camera_calibration(camera: str, temperature: float | None = None) -> Calibration:
    """The nominal calibration of a simulator preset (scalars only, no maps).

    Parameters
    ----------
    camera : str
        Preset name, ``"camera-A"`` (12 bit) or ``"camera-B"`` (10 bit), Table 2 of the paper.
    temperature : float, optional
        Sensor temperature, degrees C (the dark current doubles every 6.3 C).

    Returns
    -------
    Calibration
        g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), dark current (e-/s).

    Examples
    --------
    >>> cal = camera_calibration("camera-B")
    >>> cal.params.g, cal.params.v_sat  # DN/e-, DN
    (0.92, 1023.0)
    """
    from hdrcap.mock_camera.sensor import preset_calibration

    return preset_calibration(camera, temperature)


def _as_calibration(calibration: CalibrationLike | None) -> Calibration:
    if isinstance(calibration, Calibration):
        return calibration
    if calibration is None:
        raise InputError("no camera model: give calibration=<Calibration>, a calibration file or a preset name")
    from hdrcap.mock_camera import PRESETS

    if isinstance(calibration, str) and calibration in PRESETS:
        return camera_calibration(calibration)
    if isinstance(calibration, (str, os.PathLike)):
        if not Path(calibration).exists():
            raise InputError(f"{calibration}: no such calibration file, and not a camera preset ({', '.join(PRESETS)})")
        return load_calibration(calibration)
    raise InputError(f"calibration: expected a Calibration, a file or a preset name, got {type(calibration).__name__}")


# --------------------------------------------------------------------------- calibration


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file (written by :func:`save_calibration` or ``hdrcap calibrate``).

    Parameters
    ----------
    path : str or path-like
        The file (``.npz`` format, any name).

    Returns
    -------
    Calibration
        Scalars g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), D (e-/s), their standard
        errors, the per-photosite maps and the provenance.

    Raises
    ------
    InputError
        Missing, unreadable or not a calibration file; unsupported version; bad map shape.

    Examples
    --------
    >>> import tempfile
    >>> path = save_calibration(Path(tempfile.mkdtemp()) / "cam.cal", camera_calibration("camera-A"))
    >>> load_calibration(path).params == camera_calibration("camera-A").params
    True
    """
    from hdrcap.pipeline.calibration import load_calibration as _load

    return _load(path)


def save_calibration(path: str | os.PathLike[str], calibration: Calibration, *, force: bool = False) -> Path:
    """Write ``calibration`` to ``path`` (atomically; an existing file is kept unless ``force``).

    Parameters
    ----------
    path : str or path-like
        Output file (``.npz`` format, any name).
    calibration : Calibration
        The camera model.
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
    """
    from hdrcap.pipeline.calibration import save_calibration as _save

    return _save(path, calibration, force=force)


def _stream(items: list, times: list[float | None], what: str, meta: dict, need_time: bool) -> Iterator[RawFrame]:
    """Frames one at a time (memory-bounded), noting the camera, ISO and white level seen."""
    for i, (item, t) in enumerate(zip(items, times)):
        fr = _frame(item, t, what, i, need_time=need_time)
        for key, val in (("camera", fr.camera), ("iso", fr.iso), ("white_level", fr.white_level)):
            if val is not None:
                meta.setdefault(key, val)
        yield fr


def calibrate(
    bias: Iterable[FrameLike] | FrameLike,
    saturation: Iterable[FrameLike] | FrameLike | None = None,
    flats: Iterable[FrameLike] | None = None,
    darks: Iterable[FrameLike] | None = None,
    *,
    flat_times: Sequence[float | None] | None = None,
    dark_times: Sequence[float | None] | None = None,
    bias_times: Sequence[float | None] | None = None,
    saturation_times: Sequence[float | None] | None = None,
    white_level: float | None = None,
    gain_method: str = "auto",
    clip: float | None = 5.0,
    provenance: Mapping[str, Any] | None = None,
) -> Calibration:
    """Calibrate the camera noise model from bias, saturation, flat and dark frames (Sec. 6).

    mu_R and sigma2_R from the bias frames (pair difference), v_sat = mean - 3 std of the
    saturation frame(s), the PRNU map a_j (Eq. 14) and the gain g from flat pairs (Eq. 16-17)
    or the EMVA 1288 photon-transfer regression, the dark current D from dark frames at >= 6
    exposure times. Frames are read one at a time.

    Parameters
    ----------
    bias : paths or 2-D arrays
        Bias frames (zero or shortest exposure, light blocked), DN; two or more.
    saturation : paths or 2-D arrays, optional
        Saturation frame(s), DN. Without one, ``white_level`` is used as v_sat.
    flats : paths or 2-D arrays
        Flat fields, DN; consecutive frames of the same exposure time form pairs.
    darks : paths or 2-D arrays, optional
        Dark frames at >= 6 exposure times, DN, ordered by exposure time.
    flat_times, dark_times, bias_times, saturation_times : sequence of float, optional
        Exposure times, s, one per frame of that kind; required for arrays of flats and
        darks and for PNG/TIFF files, they override a raw file's EXIF. Bias and saturation
        arrays without times are taken as exposures of 0 s.
    white_level : float, optional
        ADC white level, DN (default: from the raw files).
    gain_method : {"auto", "pairs", "ptc"}
        ``ptc``: EMVA 1288 regression; ``pairs``: Eq. 16 average; ``auto``: ptc when the flats
        span >= 3 levels.
    clip : float or None
        Sigma-clipping threshold for hot pixels and cosmic rays, standard deviations; None
        disables outlier rejection.
    provenance : mapping, optional
        Camera model, serial, ISO, temperature (degrees C) ... recorded with the result.

    Returns
    -------
    Calibration
        g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), D (e-/s), each with its standard
        error in ``stderr``, the PRNU, bias and dark-current maps and the provenance.

    Raises
    ------
    InputError
        Missing or unreadable frames, arrays without exposure times, too few frames for an
        estimate, frames of the wrong kind (e.g. a bias frame with signal).
    """
    from hdrcap import __version__
    from hdrcap.pipeline.calibration import GAIN_METHODS, with_file_metadata
    from hdrcap.pipeline.calibration import calibrate as _calibrate

    if gain_method not in GAIN_METHODS:
        raise InputError(f"gain_method must be auto, pairs or ptc, got {gain_method!r}")
    meta: dict[str, Any] = {}
    groups: dict[str, Iterator[RawFrame] | None] = {}
    for what, items, times, need in (
        ("bias frame", bias, bias_times, False),
        ("saturation frame", saturation, saturation_times, False),
        ("flat", flats, flat_times, True),
        ("dark frame", darks, dark_times, True),
    ):
        lst = _items(items, what + "s")
        groups[what] = _stream(lst, _times(times, len(lst), what), what, meta, need) if lst else None
    if groups["bias frame"] is None:
        raise InputError("no bias frames given")
    if groups["flat"] is None:
        raise InputError("no flat fields given: the gain g and the PRNU map need flat fields")
    prov = {"hdrcap_version": __version__, **dict(provenance or {})}
    calib = _calibrate(
        groups["bias frame"],
        groups["saturation frame"],
        groups["flat"],
        groups["dark frame"],
        clip=clip,
        gain_method=gain_method,
        white_level=white_level,
        provenance=prov,
    )
    # What the files said (camera, ISO, white level), as `hdrcap calibrate` records it.
    return with_file_metadata(calib, meta, white_level)


# --------------------------------------------------------------------------- merge


def _plan_file(plan: Plan | PlanFile | Mapping[str, Any]) -> PlanFile:
    """A plan as the merge reads it (from :func:`plan`, a plan file read back, or its JSON)."""
    from hdrcap.pipeline.planfile import PlanFile, check_plan

    if isinstance(plan, PlanFile):
        return plan
    data = plan.to_dict() if hasattr(plan, "to_dict") else plan
    return check_plan(dict(data), "plan")


def merge(
    frames: Iterable[FrameLike] | FrameLike,
    times: Sequence[float | None] | None = None,
    calibration: CalibrationLike | None = None,
    *,
    darks: Iterable[FrameLike] | None = None,
    dark_times: Sequence[float | None] | None = None,
    master_dark: FrameLike | None = None,
    options: MergeOptions | None = None,
    plan: Plan | PlanFile | Mapping[str, Any] | None = None,
    weighting: str = "optimal",
    cfa_pattern: str | None = None,
    black_level: float | None = None,
    white_level: float | None = None,
    bits: int | None = None,
    calibration_mismatch: str = "refuse",
) -> HdrResult:
    """Merge a bracket of raw frames into irradiance and its uncertainty (Eq. 6, 8-13, Fig. 3).

    The optimal maximum-likelihood merge: per-exposure estimates x_i = (v_i - b_i)/(t_i g a)
    (Eq. 6) weighted by their inverse variance from the calibrated noise model (Eq. 13),
    iterated to convergence; sigma^2 = 1 / sum of the weights (Eq. 12). The same path as
    ``hdrcap merge`` (:func:`hdrcap.pipeline.merge.files.merge_files`): the same files give
    the same result and, written, the same EXR.

    Parameters
    ----------
    frames : paths or 2-D arrays
        The bracket, any order: raw files (DNG, NEF, ...), 8- to 16-bit PNG/TIFF files, or raw
        mosaics in DN (uint16 or float); a 3-D array is a stack of frames.
    times : sequence of float, optional
        Exposure times, s, one per frame. Required for arrays and PNG/TIFF files; for raw
        files they override EXIF (None entries: from the file).
    calibration : Calibration, path or str, optional
        The camera model: a :class:`Calibration`, a calibration file, or a simulator preset
        name (``"camera-B"``: nominal scalars). None: the calibration library's entry for the
        frames' camera, else a self-calibration from the bracket (docs/selfcal.md).
    darks : paths or 2-D arrays, optional
        Dark frames (DN), matched to the frames by exposure time: one per time for
        ``matched``, or each a master dark of ``options.n_dark`` frames for ``master``.
    dark_times : sequence of float, optional
        Exposure times of ``darks``, s. Default for arrays: the frames' ``times`` when there is
        one dark per frame (same order).
    master_dark : path or 2-D array, optional
        One master dark (DN) for every exposure, averaged from ``options.n_dark`` frames; taken
        at ``options.master_dark_time`` s (a raw file's own time by default), the calibrated
        dark current over the difference being added.
    options : MergeOptions, optional
        Iterations, tolerance, saturation model (Eq. 8-11), PRNU, dark strategy, master-dark
        frame count and time, exposure times; default ``MergeOptions(exposure_times=
        "effective")`` (each frame's effective time estimated from the bracket).
    plan : Plan, PlanFile or dict, optional
        A plan (:func:`plan`): its per-exposure dark strategies and decided options apply,
        except the fields of ``options`` that differ from their defaults.
    weighting : str
        ``"optimal"`` or a baseline of Table 1 (:data:`hdrcap.pipeline.merge.weighting.WEIGHTING_METHODS`).
    cfa_pattern : str, optional
        The frames' Bayer tile (``"RGGB"``, ``"BGGR"``, ``"GRBG"``, ``"GBRG"``) or ``"mono"``
        (default: the raw file's; PNG/TIFF files and arrays: monochrome); recorded in the
        header, :func:`denoise` filters each colour plane when one is recorded.
    black_level, white_level : float, optional
        The frames' black and white level, DN (default: the raw file's; PNG/TIFF: the white
        level from the bit depth, the black level estimated by a self-calibration).
    bits : int, optional
        Significant bits of the values: N-bit data stored LSB- or MSB-aligned in 16-bit words
        (MSB alignment sets the quantisation step 2^(16 - N) DN); default: the file's bit depth,
        MSB alignment detected.
    calibration_mismatch : {"refuse", "warn"}
        A calibration made for another camera than the frames' (model or serial, ISO, white
        level, size, CFA pattern): refuse (InputError), or merge with a warning.

    Returns
    -------
    HdrResult
        float32 irradiance (e-/s) and sigma (e-/s), nexp, quality, sigma_calibration (when the
        calibration has standard errors) and the header (exposure times, source files,
        calibration, options).

    Raises
    ------
    InputError
        Unreadable, duplicate or mismatched frames; arrays without exposure times; a missing
        dark frame; a bad option value.

    Examples
    --------
    >>> sim = simulate("camera-B", times=[0.01, 0.1, 1.0], shape=(32, 48), seed=1)
    >>> hdr = merge(sim.frames, sim.times, calibration=sim.calibration)
    >>> hdr.shape, hdr.header["unit"]
    ((32, 48), 'electrons per second per photosite')
    >>> bool(abs(hdr.irradiance[hdr.measured] / sim.truth[hdr.measured] - 1).mean() < 0.1)
    True
    """
    from hdrcap.pipeline.io.frameformat import FrameFormat
    from hdrcap.pipeline.merge.files import MergeRequest, merge_files

    fmt = FrameFormat(cfa=cfa_pattern, black_level=black_level, white_level=white_level, bits=bits)
    calib: Calibration | str | os.PathLike[str] | None = None
    if calibration is not None:
        calib = _as_calibration(calibration)
        if isinstance(calibration, (str, os.PathLike)) and Path(calibration).exists():
            calib = calibration  # its file: a dark library relative to it is found too
    items = _items(frames, "frames")
    if not items:
        raise InputError("no frames to merge")
    ts = _times(times, len(items), "frame")
    # files are read by merge_files (with the format); arrays wrapped with their times
    fr: list[str | os.PathLike[str] | RawFrame] = [
        x if isinstance(x, (str, os.PathLike)) else _frame(x, t, "frame", i) for i, (x, t) in enumerate(zip(items, ts))
    ]
    opts = MergeOptions(exposure_times="effective") if options is None else options
    if not isinstance(opts, MergeOptions):
        raise InputError(f"options: expected a MergeOptions, got {type(opts).__name__}")
    dk: list[RawFrame] = []
    if darks is not None:
        ditems = _items(darks, "darks")
        if dark_times is None and len(ditems) == len(fr):
            arrays = [not isinstance(d, (str, os.PathLike, RawFrame)) for d in ditems]
            own = _frame_times(fr, ts) if any(arrays) else [None] * len(fr)
            dts: list[float | None] = [t if a else None for a, t in zip(arrays, own)]
        else:
            dts = _times(dark_times, len(ditems), "dark frame")
        dk = [_frame(x, t, "dark frame", i) for i, (x, t) in enumerate(zip(ditems, dts))]
    md: str | os.PathLike[str] | RawFrame | None
    if master_dark is None or isinstance(master_dark, (str, os.PathLike, RawFrame)):
        md = master_dark
    else:
        md = _frame(master_dark, None, "master dark", 0, need_time=False)  # an array: no exposure time
    defaults = MergeOptions(exposure_times="effective")
    given = frozenset(f.name for f in dataclasses.fields(opts) if getattr(opts, f.name) != getattr(defaults, f.name))
    request = MergeRequest(
        frames=fr,
        calibration=calib,
        options=opts,
        darks=dk,
        master_dark=md,
        plan=None if plan is None else _plan_file(plan),
        given=given,
        weighting=weighting,
        times=ts if any(t is not None for t in ts) else None,
        tiling=None,
        frame_format=fmt if fmt.given else None,
        calibration_mismatch=calibration_mismatch,
    )
    return merge_files(request)


def _frame_times(frames: Sequence[Any], times: Sequence[float | None]) -> list[float | None]:
    """Each frame's exposure time, s: the one given, else a frame's own (a file's from its metadata)."""
    from hdrcap.pipeline.io.raw import read_frame

    out: list[float | None] = []
    for f, t in zip(frames, times):
        if t is None:
            t = f.exposure_time if isinstance(f, RawFrame) else read_frame(Path(f)).exposure_time
        out.append(t)
    return out


# --------------------------------------------------------------------------- plan


def plan(
    calibration: CalibrationLike,
    irradiance: np.ndarray | HdrResult,
    target_snr_db: float,
    allowed_times: Sequence[float] | None = None,
    **options: Any,
) -> Plan:
    """Plan the exposures (and dark frames) that reach a target SNR on a scene (Eq. 18, Sec. 8).

    Parameters
    ----------
    calibration : Calibration, path or str
        The camera model: a :class:`Calibration`, a calibration file or a preset name.
    irradiance : array_like or HdrResult
        Irradiance map of the scene (or any sample of pixel irradiances), e-/s per photosite,
        e.g. a previous merge.
    target_snr_db : float
        Required SNR of the merged estimate, dB (20 log10).
    allowed_times : sequence of float, optional
        Exposure times the camera offers, s (default: the 1/3-EV ladder 1/8000..30 s).
    **options
        Options of :func:`hdrcap.planner.plan_exposures`: ``max_exposures`` (int),
        ``time_budget`` (s), ``overhead`` (s per frame, default 1), ``quantile`` (fraction of
        pixels that must reach the target), ``highlight_fraction``, ``dark_library``
        (exposure time in s -> frame count of the available master darks),
        ``uniform_darks`` (bool), ...

    Returns
    -------
    Plan
        ``exposures`` (s, capture order), ``darks`` (dark strategy per exposure), ``n_dark``,
        ``predicted_min_snr_db``, ``total_time_s``, ``feasible``, ``decisions``, ``message``;
        ``merge_options()`` gives the options for :func:`merge`.

    Raises
    ------
    InputError
        A non-finite irradiance map or target, an impossible request.

    Examples
    --------
    >>> import numpy as np
    >>> scene = np.geomspace(300.0, 1e5, 1000)  # e-/s
    >>> p = plan("camera-B", scene, target_snr_db=20, allowed_times=[0.001, 0.01, 0.1, 1.0], overhead=0)
    >>> p.feasible, p.predicted_min_snr_db >= 20, sorted(set(p.exposures))
    (True, True, [0.001, 0.01, 0.1])
    """
    from hdrcap.planner import plan_exposures

    calib = _as_calibration(calibration)
    X = irradiance.irradiance if isinstance(irradiance, HdrResult) else irradiance
    try:
        X = np.asarray(X, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"irradiance: expected an array of e-/s, got {type(irradiance).__name__}") from None
    if X.size == 0 or not np.all(np.isfinite(X)):
        raise InputError("irradiance: the map is empty or holds NaN or infinite values")
    try:
        target = float(target_snr_db)
    except (TypeError, ValueError):
        raise InputError(f"target_snr_db must be a number of dB, got {target_snr_db!r}") from None
    if not np.isfinite(target):
        raise InputError(f"target_snr_db must be a finite number of dB, got {target_snr_db!r}")
    known = set(inspect.signature(plan_exposures).parameters) - {
        "calibration",
        "irradiance",
        "target_snr_db",
        "allowed_times",
    }
    unknown = sorted(set(options) - known)
    if unknown:
        raise InputError(f"unknown plan option {unknown[0]!r}; choose from {', '.join(sorted(known))}")
    return plan_exposures(calib, X, target, allowed_times, **options)


# --------------------------------------------------------------------------- denoise


def denoise(
    hdr: HdrResult,
    *,
    method: str = "adaptive",
    range_scale: float | None = None,
    bandwidth: float | None = None,
    radius: int | None = None,
    spatial_sigma: float | None = None,
    layout: str = "auto",
) -> HdrResult:
    """Denoise a merge with a bilateral filter whose range bandwidth follows each photosite's
    predicted sigma (Sec. 9). Returns a new result; ``hdr`` is not modified.

    Parameters
    ----------
    hdr : HdrResult
        A merge (or a read EXR) with irradiance and sigma, e-/s.
    method : {"adaptive", "constant"}
        ``adaptive``: range bandwidth ``range_scale`` x sigma per photosite; ``constant``:
        one bandwidth ``bandwidth`` for all.
    range_scale : float, optional
        K, the range bandwidth in multiples of the predicted sigma (adaptive; default 3).
    bandwidth : float, optional
        Constant range bandwidth, e-/s (constant method; ``inf``: a plain Gaussian).
    radius : int, optional
        Half-width of the square support, same-colour steps (default 2).
    spatial_sigma : float, optional
        Standard deviation of the spatial Gaussian, same-colour steps (default 1.5).
    layout : {"auto", "cfa", "mono"}
        ``cfa``: filter each colour plane of the 2x2 mosaic; ``mono``: one channel; ``auto``:
        ``cfa`` when the metadata names a CFA pattern.

    Returns
    -------
    HdrResult
        Filtered irradiance (e-/s) and its propagated sigma (e-/s; it does not include the
        bias the filter introduces); ``nexp`` and other channels unchanged (photosites with
        ``nexp == 0`` are not filtered); the settings under ``header["denoise"]``
        (:func:`hdrcap.pipeline.denoise.files.denoise_result`, which ``hdrcap denoise`` uses too).

    Raises
    ------
    InputError
        Bad settings, or sigma not finite and > 0 where nexp > 0.
    """
    from hdrcap.pipeline.denoise.files import DenoiseOptions, denoise_result

    if not isinstance(hdr, HdrResult):
        raise InputError(f"denoise: expected an HdrResult (from merge or read_exr), got {type(hdr).__name__}")
    return denoise_result(hdr, DenoiseOptions(method, range_scale, bandwidth, radius, spatial_sigma, layout))


# --------------------------------------------------------------------------- simulation


def simulate(
    camera: str = "camera-B",
    scene: str | np.ndarray = "hdr",
    times: Sequence[float] | None = None,
    *,
    seed: int = 0,
    shape: tuple[int, int] = (192, 256),
    decades: float = 4.0,
    x_max: float = 2e5,
    darks: bool = False,
    temperature: float | None = None,
) -> Simulation:
    """Simulate a bracket of the built-in camera: raw frames and the truth behind them.

    The physics (Poisson electrons, Gaussian read noise, rounding, clipping at the full well
    and the ADC) of :mod:`hdrcap.mock_camera`; the same seed gives the same mosaics as
    ``hdrcap simulate`` writes into its DNG files.

    Parameters
    ----------
    camera : str
        Preset: ``"camera-A"`` (12 bit) or ``"camera-B"`` (10 bit), Table 2 of the paper.
    scene : str or array_like
        A synthetic scene (``"hdr"``, ``"gradient"``, ``"patches"``, ``"edges"``, ``"flat"``)
        or an irradiance map, e-/s per photosite (its shape is the mosaic's).
    times : sequence of float, optional
        Exposure times, s, in capture order; repeats allowed (default: 0.001 to 1 s in 6
        steps).
    seed : int
        Seed of the fixed patterns (PRNU, dark-current non-uniformity) and the noise.
    shape : (int, int)
        Mosaic size (rows, columns) of a synthetic scene, photosites.
    decades : float
        Dynamic range of a synthetic scene, orders of magnitude.
    x_max : float
        Brightest irradiance of a synthetic scene, e-/s.
    darks : bool
        Also take one dark frame per exposure time.
    temperature : float, optional
        Sensor temperature, degrees C (the dark current doubles every 6.3 C).

    Returns
    -------
    Simulation
        ``frames`` (uint16, DN), ``times`` (s), ``truth`` (e-/s), ``calibration`` (the
        sensor's true model), ``darks``, ``cfa_pattern``.

    Raises
    ------
    InputError
        Unknown preset or scene, non-positive exposure times, a bad scene array.

    Examples
    --------
    >>> sim = simulate("camera-A", times=[0.01, 0.1], shape=(16, 24), seed=3, darks=True)
    >>> len(sim.frames), sim.frames[0].dtype, sim.frames[0].shape, sim.cfa_pattern
    (2, dtype('uint16'), (16, 24), 'RGGB')
    """
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.mock_camera.scenes import SCENES, make_scene
    from hdrcap.pipeline.io.raw import check_exposure_time

    if camera not in PRESETS:
        raise InputError(f"unknown camera preset {camera!r}; choose from {', '.join(PRESETS)}")
    ts = [check_exposure_time(t, "simulate") for t in (DEFAULT_SIMULATION_TIMES if times is None else times)]
    if not ts:
        raise InputError("simulate: give at least one exposure time")
    if isinstance(scene, str):
        if scene not in SCENES:
            raise InputError(f"unknown scene {scene!r}; choose from {', '.join(SCENES)} or give an irradiance array")
        try:
            X = make_scene(scene, shape, decades=decades, x_max=x_max)
        except ValueError as err:
            raise InputError(f"simulate: {err}") from None
    else:
        X = np.asarray(scene, dtype=np.float64)
        if X.ndim != 2 or min(X.shape) < 2:
            raise InputError(f"scene: expected a 2-D irradiance map (e-/s), got shape {X.shape}")
        if not np.all(np.isfinite(X)) or np.any(X < 0):
            raise InputError("scene: irradiance must be finite and >= 0 e-/s")
    spec = PRESETS[camera]
    cam = SimulatedCamera(spec, X, seed=seed, temperature=temperature)
    frames = tuple(cam.capture_array(t) for t in ts)
    dark = tuple(cam.capture_array(t, dark=True) for t in ts) if darks else None
    sensor = cam.sensor
    bias = None if sensor.offset is None else (spec.mu_R + sensor.offset).astype(np.float32)
    calib = Calibration(
        params=spec.nominal_params(temperature),
        prnu=sensor.prnu.astype(np.float32),
        dark_current_map=sensor.dark_current_map(temperature).astype(np.float32),
        bias_map=bias,
        provenance={
            "source": f"simulated {camera}, seed {seed}: the sensor's true model",
            "camera": f"{spec.make} {spec.model}",  # as the camera's files name it
            "iso": spec.iso,
            "temperature": temperature,
        },
    )
    return Simulation(
        frames=frames,
        times=tuple(cam.actual_time(t) for t in ts),
        truth=X,
        calibration=calib,
        darks=dark,
        camera=camera,
        cfa_pattern=spec.cfa,
        seed=int(seed),
    )


# --------------------------------------------------------------------------- files


def read_exr(path: str | os.PathLike[str]) -> HdrResult:
    """Read an EXR written by :meth:`HdrResult.write` or ``hdrcap merge``/``denoise``.

    Parameters
    ----------
    path : str or path-like
        The EXR file (channels ``irradiance`` and ``sigma`` in e-/s, optional ``nexp``,
        ``quality``, ``sigma_calibration``).

    Returns
    -------
    HdrResult

    Raises
    ------
    InputError
        Missing or unreadable file, no irradiance or sigma channel.
    """
    from hdrcap.pipeline.io.results import read_result

    return read_result(path)


def write_exr(
    path: str | os.PathLike[str],
    hdr: HdrResult,
    *,
    force: bool = False,
    compression: str = "zip",
    sigma_precision: str = "auto",
) -> Path:
    """Write a result as an EXR, atomically (an existing file is kept unless ``force``): the
    file ``hdrcap merge`` writes for the same result (:meth:`HdrResult.write`).

    Parameters
    ----------
    path : str or path-like
        Output file; its folder must exist.
    hdr : HdrResult
        The merge (or a denoised one).
    force : bool
        Replace an existing file.
    compression : str
        zip (default), zips, piz, zstd, rle or none.
    sigma_precision : {"auto", "half", "float"}
        Storage of the sigma channels (``auto``: half where they fit, at most 0.05 % lost).

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    OutputExistsError
        The file exists and ``force`` is false.
    InputError
        The output folder does not exist or is not writable; a bad option.

    Examples
    --------
    >>> import tempfile
    >>> sim = simulate("camera-B", times=[0.01, 0.1, 1.0], shape=(16, 24), seed=2)
    >>> hdr = merge(sim.frames, sim.times, calibration=sim.calibration)
    >>> path = write_exr(Path(tempfile.mkdtemp()) / "m.exr", hdr)
    >>> back = read_exr(path)
    >>> sorted(back.channels()), bool((back.irradiance == hdr.irradiance).all())
    (['irradiance', 'nexp', 'quality', 'sigma'], True)
    """
    from hdrcap.pipeline.io.results import write_result

    if not isinstance(hdr, HdrResult):
        raise InputError(f"write_exr: expected an HdrResult, got {type(hdr).__name__}")
    return write_result(hdr, path, format="exr", force=force, compression=compression, sigma_precision=sigma_precision)
