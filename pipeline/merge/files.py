"""Merging raw files into an EXR: the library behind ``hdrcap merge`` and ``hdrcap run``.

:func:`merge_files` reads a bracket (in parallel threads), gives every frame the dark level
that :class:`pipeline.merge.darks.DarkResolver` serves its exposure (dark frames given, one master
dark, or the calibration's dark library), applies a plan file's per-exposure dark strategies
and decided options, and merges (optimal, streamed into a ``MergeAccumulator``, or a baseline
weighting). :func:`build_hdr_image` is the EXR content of a merge, :func:`summary` its
one-line figures.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io import RawFrame
from hdrcap.pipeline.merge.darks import DarkResolver, default_strategy
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.params import Calibration

if TYPE_CHECKING:  # the planner (and scipy under it) is imported only for a merge with a plan
    from hdrcap.pipeline.planfile import PlanFile

__all__ = [
    "FileMerge",
    "merge_files",
    "streamed_merge",
    "read_frames",
    "build_hdr_image",
    "summary",
    "merge_options",
    "library_root",
]


def _warn(message: str) -> None:
    print(f"hdrcap: warning: {message}", file=sys.stderr)


def _warm_up(work: Callable[[], None] | None) -> None:
    """``work`` (default :func:`pipeline.merge.accumulator.warm_up_kernels`), in a background thread; a
    failure is left to the command itself to report."""
    try:
        if work is None:
            from hdrcap.pipeline.merge.accumulator import warm_up_kernels as work
        work()
    except Exception:  # noqa: BLE001, S110  (the command reports its own errors)
        pass


_WARM_UP: list[threading.Thread] = []  # the process's warm-up thread, once started


def start_warm_up(work: Callable[[], None] | None = None) -> threading.Thread:
    """Start :func:`_warm_up` in a thread (numba's set-up overlaps loading the calibration and
    reading the frames, or the EXR a denoise reads), once per process: later calls return the
    same thread. ``work``: what to run (default: import the merge kernels and initialise
    numba's CPU target; :func:`pipeline._numba_target.warm_up` for a module already imported)."""
    if _WARM_UP:
        return _WARM_UP[0]
    thread = threading.Thread(target=_warm_up, args=(work,), name="hdrcap-kernel-warm-up")
    _WARM_UP.append(thread)
    thread.start()
    return thread


def read_frames(paths, times=None, what="frame", progress=False, bad_values="refuse") -> list[RawFrame]:
    """Read raw files or 16-bit images, two at a time.

    Parameters
    ----------
    paths : sequence of path
        The files.
    times : sequence of float, optional
        Exposure times, s, one per path; they override EXIF.
    what : str
        What the files are, for messages and the progress bar.
    progress : bool
        Show a progress bar.
    bad_values : {"refuse", "mask"}
        As :func:`pipeline.io.read_raw`.

    Returns
    -------
    list of RawFrame
        In the order of ``paths``.
    """
    return list(_read_parallel(paths, times, what, progress, bad_values))


def _read_parallel(paths, times, what, progress, bad_values="refuse") -> Iterator[RawFrame]:
    """Decode raw files in a thread pool (LibRaw releases the GIL), yielding frames in order."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from hdrcap.pipeline.io import read_frame

    paths = list(paths)
    if times:
        if len(times) != len(paths):
            raise InputError(f"--times gives {len(times)} exposure times for {len(paths)} {what}s")
    else:
        times = [None] * len(paths)
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = [pool.submit(read_frame, p, t, bad_values=bad_values) for p, t in zip(paths, times)]
        for fut in tqdm(futures, desc=f"read {what}s", unit="file", disable=None if progress else True, leave=False):
            yield fut.result()


def _camera_colour(frames) -> dict | None:
    """The first frame's colour metadata (colour matrices, white balance) for the header, so
    that ``hdrcap develop`` works from the EXR alone; None without a file or a matrix."""
    from hdrcap.pipeline.io.dngwrite import camera_colour

    path = frames[0].path if frames else None
    if not path:
        return None
    try:
        found = camera_colour(path)
    except InputError as err:
        _warn(f"no colour matrix recorded: {err}")
        return None
    return None if found is None else found.to_attrs()


def build_hdr_image(result, frames, calibration, extra=None):
    """The EXR content of a merge: channels and header attributes.

    Parameters
    ----------
    result : MergeResult
        The merge.
    frames : list of RawFrame
        The frames merged (their files, times, CFA pattern).
    calibration : Calibration
        The camera model used.
    extra : dict, optional
        Further header attributes.

    Returns
    -------
    HdrImage
    """
    from hdrcap import __version__
    from hdrcap.pipeline.io import HdrImage

    attrs = {
        "unit": "electrons per second per photosite",
        "sigma": "total standard uncertainty of irradiance (noise plus calibration error), same unit",
        "sigma_calibration": "the calibration's part of sigma alone (systematic: more frames do not reduce it), "
        "same unit",
        "nexp": "number of unsaturated exposures used (0: saturated everywhere, irradiance is a lower bound)",
        "cfa_pattern": frames[0].cfa_pattern or "none",
        "exposure_times": [fr.exposure_time for fr in frames],
        "exposure_times_effective": result.info.get("exposure_times", [fr.exposure_time for fr in frames]),
        # after the calibration's shutter table alone (before the bracket's own estimate)
        "exposure_times_calibrated": result.info.get(
            "exposure_times_calibrated", result.info.get("exposure_times", [fr.exposure_time for fr in frames])
        ),
        "shutter_corrections": _shutter_header(calibration, result.info),
        "source_files": [fr.path for fr in frames],
        "calibration": {"params": calibration.params.to_dict(), "provenance": calibration.provenance},
        "hdrcap_version": __version__,
        "merge": result.info,
    }
    colour = _camera_colour(frames)
    if colour is not None:
        attrs["camera_colour"] = colour
    if extra:
        attrs.update(extra)
    channels = {"irradiance": result.irradiance, "sigma": result.sigma, "nexp": result.nexp}
    if getattr(result, "sigma_calibration", None) is not None:
        channels["sigma_calibration"] = result.sigma_calibration
    quality = getattr(result, "quality", None)
    if quality is not None:
        from hdrcap.pipeline.merge.accumulator import QUALITY_BITS

        channels["quality"] = quality  # uint8 bits: stored as uint (or float) without a float32 copy here
        attrs["quality"] = (
            "bit field, 0 a trusted measurement; any bit but masked: nexp = 0, not a measurement; masked (a frame's "
            "impossible raw value left out) with nexp > 0: estimated from the other frames: "
        ) + ", ".join(f"{bit} {name}" for name, bit in QUALITY_BITS.items())
    return HdrImage(channels, attrs)


def _shutter_header(calibration, info) -> dict[str, Any] | None:
    """The calibration's shutter table as the EXR header records it (None without one): the
    table (times s, factors, relative standard errors, reference s) and, per frame, whether it
    applied (``--exposure-times nominal`` or a time not in the table: not applied)."""
    table = getattr(calibration, "shutter", None)
    if table is None:
        return None
    applied = (info.get("shutter_table") or {}).get("applied")
    return {**table.to_dict(), "applied": applied}


def exr_precision(channels, sigma: str = "auto") -> dict[str, str]:
    """Storage precision of each merge channel: irradiance float32; sigma and
    sigma_calibration as ``sigma`` says (``auto``: half where the channel fits half's range, at
    most 0.05 % lost); nexp and quality as uint (whole numbers, lossless).

    Parameters
    ----------
    channels : mapping of str to array
        The image's channels (only present ones get an entry).
    sigma : {"auto", "half", "float"}
        Precision of the uncertainty channels.

    Returns
    -------
    dict of str to str
        Channel name -> precision for :func:`hdrcap.pipeline.io.write_exr`.
    """
    wanted = {"sigma": sigma, "sigma_calibration": sigma, "nexp": "uint", "quality": "uint"}
    return {name: p for name, p in wanted.items() if name in channels}


def _median_relative_sigma(irr, sig, ok, max_samples=1_000_000):
    """Median of sigma/|irradiance| over usable photosites (a regular subsample of at most
    ``max_samples`` of them on large images)."""
    step = max(1, irr.size // max_samples)
    i, s, o = irr.ravel()[::step], sig.ravel()[::step], ok.ravel()[::step]
    if not o.any():
        return None
    return float(np.median(s[o] / np.maximum(np.abs(i[o]), 1e-30)))


def summary(result) -> dict:
    """Figures of a merge for a one-line report.

    Parameters
    ----------
    result : MergeResult
        The merge.

    Returns
    -------
    dict
        Shape, irradiance range (e-/s), median relative sigma, photosites saturated everywhere
        (defects and photosites masked in every frame not counted), defective photosites
        flagged, whether everything is finite, and (when there are some) the photosites with a
        masked value.
    """
    irr, sig, nexp = result.irradiance, result.sigma, result.nexp
    ok = nexp > 0
    n_defects = int(result.info.get("defects_flagged", 0))  # nexp = 0 too, saturated or not
    n_void = int(result.info.get("masked_everywhere", 0))  # nexp = 0, no information at all
    # a float array is finite where its least and largest value are (a NaN makes both NaN):
    # no full-size masks
    extrema = (irr.min(), irr.max(), sig.min(), sig.max())
    out = {
        "shape": list(irr.shape),
        "irradiance_min": float(extrema[0]),
        "irradiance_max": float(extrema[1]),
        "median_relative_sigma": _median_relative_sigma(irr, sig, ok),
        "saturated_everywhere": ok.size - int(np.count_nonzero(ok)) - n_defects - n_void,
        "defects_flagged": n_defects,
        "finite": bool(np.isfinite(extrema).all()),
    }
    if result.info.get("masked_photosites"):  # only where a frame had masked values
        out["masked_photosites"] = int(result.info["masked_photosites"])
    return out


def merge_options(
    iterations,
    tolerance,
    saturation,
    prnu,
    dark_strategy,
    master_dark_frames,
    saturation_sigmas,
    exposure_times="effective",
):
    """Keyword options of :func:`pipeline.merge.accumulator.merge_arrays` from the command-line knobs.

    Parameters
    ----------
    iterations, tolerance, saturation, prnu, saturation_sigmas
        As :class:`pipeline.merge.accumulator.MergeOptions`.
    dark_strategy : str or None
        One dark strategy for every exposure.
    master_dark_frames : float or None
        Frames averaged into each master dark.
    exposure_times : {"effective", "nominal"}
        Effective times estimated from the bracket, or the nominal ones.

    Returns
    -------
    dict
    """
    opts = {
        "iterations": iterations,
        "tolerance": tolerance,
        "saturation": saturation,
        "prnu": prnu,
        "saturation_sigmas": saturation_sigmas,
        "exposure_times": exposure_times,
    }
    if dark_strategy:
        opts["dark_strategy"] = DarkStrategy(dark_strategy)
    if master_dark_frames is not None:
        opts["n_dark"] = master_dark_frames
    return opts


def library_root(calib, calibration_path=None) -> str | None:
    """The calibration's dark library folder.

    Parameters
    ----------
    calib : Calibration
        The camera model.
    calibration_path : path, optional
        Its file: a relative library path is tried from the working folder, then from there.

    Returns
    -------
    str or None
        The folder, or None without a dark library.
    """
    root = getattr(calib, "dark_library", None)
    if not root:
        return None
    p = Path(root)
    if not p.is_absolute() and not p.exists() and calibration_path:
        alt = Path(calibration_path).parent / p
        if alt.exists():
            p = alt
    return str(p)


def _missing_dark(fr: RawFrame, strategy: DarkStrategy, resolver: DarkResolver) -> InputError:
    t = fr.exposure_time
    if strategy is DarkStrategy.MATCHED:
        return InputError(
            f"{fr.path}: no dark frame with exposure time {t:g} s for its matched dark strategy; give one with --darks"
        )
    root = None if resolver.library is None else resolver.library.root
    where = f"the dark library {root} holds none for this camera" if root else "the calibration has no dark library"
    return InputError(f"{fr.path}: no master dark for exposure {t:g} s: none in --darks, no --master-dark, and {where}")


def _check_plan_covered(plan: PlanFile, frames: list[RawFrame], warn: Callable[[str], None]) -> None:
    """Every planned exposure time must be among the frames; fewer frames than planned warn."""
    seen = [0] * len(plan.times)
    for fr in frames:
        seen[plan.group(fr.exposure_time)] += 1
    missing = [t for t, k in zip(plan.times, seen) if k == 0]
    if missing:
        raise InputError(f"{plan.path}: planned exposure {missing[0]:g} s matches no frame (within 0.1 %)")
    for t, c, k in zip(plan.times, plan.counts, seen):
        if k < c:
            warn(f"the plan has {c} exposures of {t:g} s, the frames {k}")


def streamed_merge(
    frame_paths,
    dark_paths,
    times,
    calib,
    options,
    master_dark=None,
    progress=False,
    *,
    strategy_for=None,
    resolver: DarkResolver | None = None,
    plan: PlanFile | None = None,
    warn: Callable[[str], None] = _warn,
    bad_values: str = "refuse",
):
    """Read the bracket (in parallel threads) and feed each frame to a
    :class:`pipeline.merge.accumulator.MergeAccumulator` as soon as it is decoded, with the dark strategy
    ``strategy_for(frame)`` gives it (a strategy, or (strategy, planned frame count of its
    master dark); default: the one of ``options``) and the dark level ``resolver`` serves it
    (default: ``dark_paths`` matched by exposure time). With a ``plan``, every plan exposure
    time must be among the frames. ``bad_values="mask"``: a frame's impossible raw values are
    masked (:func:`pipeline.io.read_raw`), left out of that frame, and each file with some is
    warned about in one line (dark frames are always refused). Returns (result, frames, darks,
    per-frame dark sources).

    Parameters
    ----------
    frame_paths, dark_paths : sequence of path
        The bracket and its dark frames.
    times : sequence of float, optional
        Exposure times of the frames, s.
    calib : Calibration
        The camera model.
    options : dict
        Merge options.
    master_dark : RawFrame, optional
        One master dark for the master exposures.
    progress : bool
        Show a progress bar.

    Returns
    -------
    tuple
        (MergeResult, frames, dark frames, dark source of each frame).
    """
    from hdrcap.pipeline.io import check_frames, release_mapped_pages
    from hdrcap.pipeline.merge.accumulator import MergeAccumulator

    darks = list(_read_parallel(dark_paths, None, "dark frame", progress)) if dark_paths else []
    if darks:
        darks = check_frames(darks, "dark frame")
    if resolver is None:
        resolver = DarkResolver(
            frames_per_dark=options.get("n_dark"), master_dark=None if master_dark is None else str(master_dark.path)
        )
    for d in darks:
        resolver.add_dark(d.data, d.exposure_time, str(d.path))
    if strategy_for is None:
        only = options.get("dark_strategy") or default_strategy(bool(darks), master_dark is not None)

        def strategy_for(_fr):
            return only

    opts = dict(options)
    if master_dark is not None:
        opts["dark_strategy"] = DarkStrategy.MASTER
        opts.setdefault("master_dark_time", master_dark.exposure_time)
    acc = None
    frames, used, warned = [], [], set()
    for fr in _read_parallel(frame_paths, times, "frame", progress, bad_values):
        if fr.n_masked:
            warn(
                f"{fr.path}: {fr.n_masked} photosites with impossible raw values (above the white level's ADC range) "
                "masked: merged from the other frames there"
            )
        if acc is None:
            # stream=False: the frames are all read here anyway, so the merge does its single
            # pass at the end (less memory than the first-pass sums of a live capture).
            acc = MergeAccumulator(
                calib, fr.shape, master_dark=None if master_dark is None else master_dark.data, stream=False, **opts
            )
        strategy = strategy_for(fr)
        strategy, n_planned = (strategy, None) if isinstance(strategy, str) else strategy
        strategy = DarkStrategy(strategy)
        src = resolver.resolve(fr.exposure_time, strategy, camera=fr.camera, iso=fr.iso)
        if src is None:
            raise _missing_dark(fr, strategy, resolver)
        if src.data is not None and np.shape(src.data) != fr.shape:
            raise InputError(f"{src.source}: dark frame size differs from the bracket's")
        short = src.origin == "frames" and strategy is DarkStrategy.MASTER and n_planned and src.n_frames < n_planned
        if short and src.source not in warned:  # once per master dark
            warned.add(src.source)
            warn(
                f"the plan expects a master dark of {n_planned:g} frames at {fr.exposure_time:g} s; --darks gives "
                f"one of {src.n_frames:g} (set --master-dark-frames if a file averages more)"
            )
        acc.add(
            fr.data,
            fr.exposure_time,
            src.data,
            strategy=strategy,
            n_dark=src.n_frames if strategy is DarkStrategy.MASTER else None,
            mask=fr.masked,
        )
        frames.append(fr)
        used.append(f"{strategy}: {src.source}" if strategy is not DarkStrategy.MODEL else "model")
    check_frames(frames)
    if plan is not None:
        _check_plan_covered(plan, frames, warn)
    # Once merged, memory-mapped frames stop counting in memory (still readable).
    mapped = [fr.data for fr in (*frames, *darks)]
    result = acc.result(release_frames=lambda: release_mapped_pages(mapped))
    return result, frames, darks, used


def _read_master_dark(path: Path | None, options: dict) -> RawFrame | None:
    """The master dark file: a raw file (with its exposure time), or a PNG/TIFF used as is."""
    if not path:
        return None
    from hdrcap.pipeline.io import read_frame

    if path.suffix.lower() in (".png", ".tif", ".tiff"):  # no exposure time: used as is
        options["master_dark_time"] = None
        return read_frame(path, 1.0)
    return read_frame(path)


def _plan_strategies(plan: PlanFile, dark_strategy: DarkStrategy | None):
    """Frame -> (dark strategy, planned master-dark frame count) from the plan (or the one
    strategy the user gave for every exposure)."""

    def strategy_for(fr):
        i = plan.group(fr.exposure_time)
        if i is None:
            raise InputError(
                f"{fr.path}: exposure {fr.exposure_time:g} s is not in the plan {plan.path} "
                f"({', '.join(f'{t:g}' for t in plan.times)} s); leave the frame out or "
                "merge without --plan"
            )
        return (dark_strategy, None) if dark_strategy else (plan.strategies[i], plan.n_dark[i])

    return strategy_for


@dataclass
class FileMerge:
    """What :func:`merge_files` produced: the merge, the frames (and dark frames) read, and
    the extra EXR header attributes (weighting, dark sources, master dark file, planner)."""

    result: Any
    frames: list[RawFrame]
    darks: list[RawFrame]
    extra: dict[str, Any] = field(default_factory=dict)


def merge_files(
    frame_paths: Sequence[Path],
    calib,
    options: dict,
    *,
    dark_paths: Sequence[Path] = (),
    times: Sequence[float] | None = None,
    weighting: str = "optimal",
    plan: PlanFile | None = None,
    plan_file: str | None = None,
    dark_strategy: str | None = None,
    master_dark: Path | None = None,
    master_dark_frames: float | None = None,
    library: str | None = None,
    given: Callable[[str], bool] = lambda _name: False,
    progress: bool = False,
    warn: Callable[[str], None] = _warn,
    bad_values: str = "refuse",
) -> FileMerge:
    """Merge raw files: the work of ``hdrcap merge`` between its options and the EXR.

    ``options`` are merge options (:func:`merge_options`); ``given(name)`` tells which of them
    the user set (they win over a plan's). ``weighting`` other than ``optimal`` runs a baseline
    of :mod:`pipeline.merge.weighting`. Master darks come from ``dark_paths`` of the exposure time
    (``master_dark_frames`` frames each), else ``master_dark``, else the dark library at
    ``library``. ``bad_values="mask"`` masks impossible raw values of the frames instead of
    refusing the files (:func:`streamed_merge`; the optimal weighting only) and records the
    count per file in ``masked_values``.

    Parameters
    ----------
    frame_paths : sequence of Path
        The bracket.
    calib : Calibration
        The camera model.
    options : dict
        Merge options (:func:`merge_options`).

    Returns
    -------
    FileMerge
    """
    extra: dict[str, Any] = {"weighting": weighting}
    if bad_values == "mask" and weighting != "optimal":
        raise InputError(f"bad values are masked by the optimal merge only, not --weighting {weighting}")
    if weighting != "optimal":
        from hdrcap.pipeline.merge.weighting import merge_weighted

        fr = read_frames(frame_paths, times, "frame", progress)
        dk = read_frames(dark_paths, None, "dark frame", progress) if dark_paths else []
        result = merge_weighted(
            [f.data for f in fr],
            [f.exposure_time for f in fr],
            calib,
            [d.data for d in dk] if dk else None,
            method=weighting,
        )
        return FileMerge(result, fr, dk, extra)
    start_warm_up()
    dark_strategy = None if dark_strategy is None else DarkStrategy(dark_strategy)
    md = _read_master_dark(master_dark, options)
    strategy_for = taken = overridden = ignored = None
    if plan is not None:
        from hdrcap.pipeline.planfile import apply_plan_options

        options, taken, overridden, ignored = apply_plan_options(plan, options, given)
        for name in ignored:
            warn(f"{plan.path}: merge option {name!r} is not one hdrcap merge knows; ignored")
        if dark_strategy:
            overridden["darks"] = {"plan": plan.data["darks"], "used": dark_strategy.value}
        strategy_for = _plan_strategies(plan, dark_strategy)
    resolver = DarkResolver(
        frames_per_dark=master_dark_frames,
        master_dark=None if md is None else str(md.path),
        library=library,
        temperature=(calib.provenance or {}).get("temperature"),
    )
    result, fr, dk, used = streamed_merge(
        frame_paths,
        dark_paths,
        times,
        calib,
        options,
        md,
        progress,
        strategy_for=strategy_for,
        resolver=resolver,
        plan=plan,
        warn=warn,
        bad_values=bad_values,
    )
    extra["dark_sources"] = used
    if bad_values == "mask":
        extra["masked_values"] = {str(f.path): f.n_masked for f in fr}
    if master_dark:
        extra["master_dark_file"] = str(master_dark)
    if plan is not None:
        from hdrcap.pipeline.planfile import planner_attribute

        extra["planner"] = planner_attribute(
            plan.data, plan_file, plan.sha256, taken, overridden, options_ignored=ignored
        )
    return FileMerge(result, fr, dk, extra)


def bracket_calibration(
    calibration: Calibration | None,
    frame_paths,
    times=None,
    *,
    darks: bool = False,
    warn=None,
    say=None,
    exposure_times: str = "effective",
):
    """The camera model of a merge: ``calibration`` when given, else the calibration library's entry for the frames' camera model, ISO and size
    (:mod:`pipeline.calibration.library`), else a self-calibration from the bracket
    (:mod:`pipeline.calibration.selfcal`).

    Parameters
    ----------
    calibration : Calibration or None
        The camera model when the user gave one (a file or a preset's).
    frame_paths : sequence of path
        The bracket.
    times : sequence of float, optional
        Exposure times (s) overriding the files'.
    darks : bool
        Dark frames are given: they are matched to the frames by nominal exposure time, so a
        self-calibration hands the merge the nominal times where an effective one differs by more
        than the matching tolerance (the merge then estimates the effective times itself, after
        matching the dark frames, and says so).
    warn : callable, optional
        Called with one-line messages on what was assumed.
    say : callable, optional
        Called with one line saying which calibration is used when none was given.
    exposure_times : {"effective", "nominal"}
        ``nominal``: a self-calibration hands the merge the nominal times, not its effective ones.

    Returns
    -------
    (Calibration, list of float or None, SelfCalibration or None)
        The calibration, the exposure times to merge with (None: the files'), and the
        self-calibration when one was made.
    """
    if calibration is not None:
        return calibration, (list(times) if times else None), None
    from hdrcap.pipeline.calibration.library import find_calibration, library_dir
    from hdrcap.pipeline.calibration.selfcal import self_calibrate
    from hdrcap.pipeline.times import same_exposure

    frames = read_frames(frame_paths, times or None)
    first = frames[0]
    found = find_calibration(first.camera, first.iso, first.shape)
    if found is not None:
        if say is not None:
            say(f"no --calibration: using {found[0].path} from the calibration library")
        return found[1], (list(times) if times else None), None
    sc = self_calibrate(frames, warn=warn)
    if say is not None:
        say(
            f"no --calibration and none in the library {library_dir()} for {first.camera} at ISO {first.iso}: "
            f"{sc.calibration.provenance['source']}"
        )
    if exposure_times == "nominal":
        return sc.calibration, list(sc.nominal_times), sc
    if darks and not all(same_exposure(a, b) for a, b in zip(sc.effective_times, sc.nominal_times)):
        if warn is not None:
            warn(
                "effective exposure times differ from the nominal ones, but dark frames are matched by nominal "
                "time: the merge estimates the effective times itself after matching them"
            )
        return sc.calibration, list(sc.nominal_times), sc
    return sc.calibration, list(sc.effective_times), sc
