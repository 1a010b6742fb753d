"""From a bracket of files (or frames) to a merge result: the one path every door takes.

:func:`merge_files` is what ``hdrcap merge``, ``hdrcap batch``, the capture jobs and the Python
API call: it resolves the camera model (the one given, else the calibration library's, else a
self-calibration from the bracket, :func:`bracket_calibration`), applies a plan file's
per-exposure dark strategies and decided options, gives every frame the dark level
:class:`pipeline.merge.darks.DarkResolver` serves its exposure, and merges in memory (frames
streamed into a :class:`pipeline.merge.accumulator.MergeAccumulator` as they are decoded) or
tile by tile (:mod:`pipeline.merge.tiled`) when the frames are larger than the memory budget,
or with a baseline weighting of Table 1. The result carries the complete header
(:func:`pipeline.header.with_merge_header`); :func:`pipeline.io.results.write_result` writes
it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.frameformat import FrameFormat
from hdrcap.pipeline.io.raw import IMAGE_EXTENSIONS, RawFrame
from hdrcap.pipeline.merge.accumulator import MergeOptions
from hdrcap.pipeline.merge.darks import DarkResolver, DarkSource, default_strategy
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.planfile import PlanFile
from hdrcap.pipeline.result import HdrResult

__all__ = [
    "CALIBRATION_MISMATCH",
    "FrameSource",
    "MergeRequest",
    "WEIGHTINGS",
    "bracket_calibration",
    "check_camera_model",
    "library_root",
    "merge_files",
    "read_frames",
    "start_warm_up",
]

#: A frame of a request: a file (raw, or 16-bit PNG/TIFF with its time) or a frame in memory.
FrameSource = Union[str, "os.PathLike[str]", RawFrame]

#: The optimal weighting; the baselines of Table 1 are :data:`pipeline.merge.weighting.WEIGHTING_METHODS`.
WEIGHTINGS = ("optimal",)

#: What a merge does with a calibration (or preset) made for another camera than the frames':
#: ``refuse`` (a one-line error) or ``warn`` (deliberate use: merged, with a warning).
CALIBRATION_MISMATCH = ("refuse", "warn")


def _warn(message: str) -> None:
    print(f"hdrcap: warning: {message}", file=sys.stderr)


# --------------------------------------------------------------------------- the request
@dataclass(frozen=True)
class MergeRequest:
    """Everything a merge of a bracket needs, whichever door it comes in by.

    Attributes
    ----------
    frames : sequence of path or RawFrame
        The bracket, any order.
    calibration : Calibration, path or None
        The camera model, or its calibration file (a relative dark library in it is found
        from the file's folder too). None: the calibration library's entry for the frames'
        camera, ISO and size, else a self-calibration from the bracket.
    options : MergeOptions
        Merge options (the defaults use the effective exposure times).
    darks : sequence of path or RawFrame
        Dark frames, matched to the frames by exposure time (``matched``), or master darks of
        their time (``master``, each of ``master_dark_frames`` frames).
    times : sequence of float, optional
        Exposure times of ``frames``, s, overriding the files' (needed for PNG/TIFF).
    master_dark : path or RawFrame, optional
        One master dark for every ``master`` exposure (a PNG/TIFF is used as is, a raw file
        with its exposure time: the calibrated dark current over the difference is added).
    master_dark_frames : float, optional
        Frames averaged into each master dark given here (N); library masters carry theirs.
    plan : PlanFile, optional
        A plan (``hdrcap plan --json``): its per-exposure dark strategies and decided options
        apply, except options named in ``given``.
    given : frozenset of str
        Fields of ``options`` the user set (they win over the plan's); ``dark_strategy`` here
        means one strategy for every exposure.
    weighting : str
        ``optimal`` (Eq. 6-13) or a baseline of :mod:`pipeline.merge.weighting`.
    dark_library : str, optional
        The dark library folder (default: the calibration's, see :func:`library_root`).
    bad_values : {"refuse", "mask"}
        Impossible raw values: refuse the file, or mask them (left out of that frame, quality
        bit ``masked``; needs a calibration given and the in-memory optimal merge).
    tiling : int, "auto" or None
        Rows per tile (even); ``auto``: tiles when the in-memory merge would exceed
        ``memory_budget``; None: in memory.
    memory_budget : int, optional
        Bytes (default: half of the machine's memory).
    scratch_dir : path, optional
        Where a tiled merge spills decoded frames and its outputs (default: the system's
        temporary folder).
    header : mapping
        Further header entries of the door (``run``; ``source_files``, ``cfa_pattern`` to
        override what the frames say).
    frame_format : FrameFormat, optional
        What the files do not say, or say wrongly: CFA pattern, black and white level, significant
        bits (applied to every frame and dark frame, files and frames in memory alike).
    calibration_mismatch : {"refuse", "warn"}
        A calibration or preset whose camera, ISO, white level, size or CFA pattern contradicts
        the frames' (:func:`check_camera_model`): refuse (default), or merge with a warning.
    """

    frames: Sequence[FrameSource]
    calibration: Calibration | str | os.PathLike[str] | None = None
    options: MergeOptions = field(default_factory=lambda: MergeOptions(exposure_times="effective"))
    darks: Sequence[FrameSource] = ()
    times: Sequence[float | None] | None = None
    master_dark: FrameSource | None = None
    master_dark_frames: float | None = None
    plan: PlanFile | None = None
    given: frozenset[str] = frozenset()
    weighting: str = "optimal"
    dark_library: str | None = None
    bad_values: str = "refuse"
    tiling: int | str | None = "auto"
    memory_budget: int | None = None
    scratch_dir: str | os.PathLike[str] | None = None
    header: Mapping[str, Any] = field(default_factory=dict)
    frame_format: FrameFormat | None = None
    calibration_mismatch: str = "refuse"

    def __post_init__(self) -> None:
        if not self.frames:
            raise InputError("no frames to merge")
        if self.calibration_mismatch not in CALIBRATION_MISMATCH:
            raise InputError(
                f"calibration mismatch must be refused or warned about (refuse, warn), not {self.calibration_mismatch!r}"
            )
        if self.times is not None and len(self.times) != len(self.frames):
            raise InputError(f"--times gives {len(self.times)} exposure times for {len(self.frames)} frames")
        if self.bad_values not in ("refuse", "mask"):
            raise InputError(f"bad values must be refused or masked, not {self.bad_values!r}")
        if self.tiling not in ("auto", None) and not (isinstance(self.tiling, int) and self.tiling >= 2):
            raise InputError(f"tiling must be auto, None or a number of rows >= 2, got {self.tiling!r}")
        self._check_darks()
        self._check_other_weighting()
        _check_weighting(self.weighting)

    def _check_darks(self) -> None:
        strategy = self.options.dark_strategy
        if strategy is DarkStrategy.MATCHED and not self.darks:
            raise InputError("--dark-strategy matched needs dark frames (--darks)")
        if self.master_dark is not None and self.darks and self.plan is None:
            raise InputError("give either --darks or --master-dark, not both (both only with --plan)")
        if self.master_dark is not None and strategy not in (None, DarkStrategy.MASTER):
            raise InputError(f"--master-dark needs --dark-strategy master, not {strategy.value}")

    def _check_other_weighting(self) -> None:
        if self.bad_values == "mask":
            if self.calibration is None:
                raise InputError(
                    "--bad-values mask needs --calibration or --camera (the self-calibration would read the masked "
                    "values)"
                )
            if self.weighting != "optimal":
                raise InputError(f"--bad-values mask works with --weighting optimal, not {self.weighting}")
        if self.plan is not None and self.weighting != "optimal":
            raise InputError(f"--plan works with --weighting optimal, not {self.weighting}")


def _check_weighting(weighting: str) -> None:
    if weighting == "optimal":
        return
    from hdrcap.pipeline.merge.weighting import WEIGHTING_METHODS

    if weighting not in WEIGHTING_METHODS:
        raise InputError(f"--weighting {weighting!r}: choose from optimal, {', '.join(WEIGHTING_METHODS)}")


# --------------------------------------------------------------------------- warm-up, frames
def _warm_up(work: Callable[[], None]) -> None:
    """``work`` in the background thread; a failure is left to the command itself to report."""
    try:
        work()
    except Exception:  # noqa: BLE001, S110  (the command reports its own errors)
        pass


_WARM_UP: list[threading.Thread] = []  # the process's warm-up thread, once started
_WARM_UP_LOCK = threading.Lock()  # batch workers start merges from several threads


def start_warm_up(work: Callable[[], None] | None = None) -> threading.Thread:
    """Start numba's set-up in a thread, once per process (it overlaps loading the calibration
    and reading the frames, or the EXR a denoise reads).

    The calling thread imports numba and the merge kernels first, so that the thread never
    imports a module the calling thread may be importing: two threads importing numba at once
    can be handed a half-initialised numba or stopped by CPython's import-lock deadlock error,
    and a numba import that fails half-way leaves the process a numba without ``core``.

    Parameters
    ----------
    work : callable, optional
        What to run; it must not import what the calling thread may import (default: numba's
        CPU target initialised under its compiler lock, which imports only numba's own
        modules: :func:`pipeline.merge.accumulator.import_kernels`).

    Returns
    -------
    threading.Thread
        The process's warm-up thread (later calls return the same one).
    """
    with _WARM_UP_LOCK:
        if _WARM_UP:
            return _WARM_UP[0]
        if work is None:
            from hdrcap.pipeline.merge.accumulator import import_kernels

            work = import_kernels()
        thread = threading.Thread(target=_warm_up, args=(work,), name="hdrcap-kernel-warm-up")
        _WARM_UP.append(thread)
        thread.start()
    return thread


def _frames_in(
    items: Sequence[FrameSource],
    times: Sequence[float | None] | None,
    what: str,
    progress: bool,
    bad_values: str = "refuse",
    fmt: FrameFormat | None = None,
    on_frame: Callable[[RawFrame], None] | None = None,
) -> Iterator[RawFrame]:
    """The frames in order: files decoded two at a time (LibRaw releases the GIL), frames in
    memory as they are (``times`` overriding their exposure time), ``fmt`` applied to both;
    ``on_frame`` sees each frame before it is yielded."""
    from concurrent.futures import ThreadPoolExecutor

    from hdrcap.pipeline.io.raw import check_exposure_time, read_frame, with_format

    items = list(items)
    ts = list(times) if times else [None] * len(items)
    if len(ts) != len(items):
        raise InputError(f"--times gives {len(ts)} exposure times for {len(items)} {what}s")
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = [
            None if isinstance(it, RawFrame) else pool.submit(read_frame, Path(it), t, bad_values=bad_values, fmt=fmt)
            for it, t in zip(items, ts)
        ]
        with _progress_bar(len(items), f"read {what}s", progress) as bar:
            for it, t, fut in zip(items, ts, futures):
                if fut is not None:
                    fr = fut.result()
                else:
                    assert isinstance(it, RawFrame)  # no future: a frame in memory
                    fr = with_format(
                        it
                        if t is None
                        else dataclasses.replace(it, exposure_time=check_exposure_time(t, it.path or what)),
                        fmt,
                    )
                if on_frame is not None:
                    on_frame(fr)
                yield fr
                bar.update()


class _NoBar(contextlib.AbstractContextManager):
    """A progress bar that shows nothing."""

    def __exit__(self, *exc: object) -> None:
        return None

    def update(self, n: int = 1) -> None:
        """Count ``n`` more files (nothing shown)."""


def _progress_bar(total: int, desc: str, progress: bool) -> Any:
    """tqdm's bar of ``total`` files when ``progress`` and stderr is a terminal (tqdm shows
    none elsewhere; its import costs 40 ms), else one that shows nothing."""
    if not (progress and sys.stderr.isatty()):
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="file", leave=False)


def read_frames(
    paths: Iterable[FrameSource],
    times: Sequence[float | None] | None = None,
    what: str = "frame",
    progress: bool = False,
    bad_values: str = "refuse",
    fmt: FrameFormat | None = None,
    on_frame: Callable[[RawFrame], None] | None = None,
) -> list[RawFrame]:
    """Read raw files or PNG/TIFF images, two at a time.

    Parameters
    ----------
    paths : sequence of path or RawFrame
        The files (frames already read are kept).
    times : sequence of float, optional
        Exposure times, s, one per path; they override EXIF.
    what : str
        What the files are, for messages and the progress bar.
    progress : bool
        Show a progress bar.
    bad_values : {"refuse", "mask"}
        As :func:`pipeline.io.raw.read_raw`.
    fmt : FrameFormat, optional
        What the files do not say (CFA, levels, bits), applied to every frame.
    on_frame : callable, optional
        Called with each frame as it is read.

    Returns
    -------
    list of RawFrame
        In the order of ``paths``.
    """
    return list(_frames_in(list(paths), times, what, progress, bad_values, fmt, on_frame))


def library_root(calib: Calibration, calibration_path: str | os.PathLike[str] | None = None) -> str | None:
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
    root = calib.dark_library
    if not root:
        return None
    p = Path(root)
    if not p.is_absolute() and not p.exists() and calibration_path:
        alt = Path(calibration_path).parent / p
        if alt.exists():
            p = alt
    return str(p)


# --------------------------------------------------------------------------- calibration
def bracket_calibration(
    calibration: Calibration | None,
    frame_paths: Sequence[FrameSource],
    times: Sequence[float | None] | None = None,
    *,
    darks: bool = False,
    warn: Callable[[str], None] | None = None,
    say: Callable[[str], None] | None = None,
    exposure_times: str = "effective",
    fmt: FrameFormat | None = None,
    on_frame: Callable[[RawFrame], None] | None = None,
) -> tuple[Calibration, list[float | None] | None, Any]:
    """The camera model of a merge: ``calibration`` when given, else the calibration library's
    entry for the frames' camera model, ISO and size (:mod:`pipeline.calibration.library`),
    else a self-calibration from the bracket (:mod:`pipeline.calibration.selfcal`).

    Parameters
    ----------
    calibration : Calibration or None
        The camera model when the user gave one (a file or a preset's).
    frame_paths : sequence of path or RawFrame
        The bracket.
    times : sequence of float, optional
        Exposure times (s) overriding the files'.
    darks : bool
        Dark frames are given: they are matched to the frames by nominal exposure time, so a
        self-calibration hands the merge the nominal times where an effective one differs by more
        than the matching tolerance (the merge then estimates the effective times itself, after
        matching the dark frames; it says so where they differ beyond their standard errors).
    warn : callable, optional
        Called with one-line messages on what was assumed.
    say : callable, optional
        Called with one line saying which calibration is used when none was given.
    exposure_times : {"effective", "nominal"}
        ``nominal``: a self-calibration hands the merge the nominal times, not its effective ones.
    fmt : FrameFormat, optional
        What the files do not say (CFA, levels, bits), applied to the frames read here.
    on_frame : callable, optional
        Called with each frame read here (the self-calibration reads the bracket).

    Returns
    -------
    (Calibration, list of float or None, SelfCalibration or None)
        The calibration, the exposure times to merge with (None: the files'), and the
        self-calibration when one was made.
    """
    if calibration is not None:
        return calibration, (list(times) if times else None), None
    if any(isinstance(f, RawFrame) and f.path is None for f in frame_paths):
        raise InputError(
            "no camera model: give a calibration (a Calibration, a calibration file or a preset name); a "
            "self-calibration needs the raw files, with their black and white levels"
        )
    from hdrcap.pipeline.calibration.library import find_calibration, library_dir
    from hdrcap.pipeline.calibration.selfcal import self_calibrate

    frames = read_frames(frame_paths, times or None, fmt=fmt, on_frame=on_frame)
    first = frames[0]
    found = find_calibration(first.camera, first.iso, first.shape)
    if found is not None:
        if say is not None:
            say(f"no --calibration: using {found[0].path} from the calibration library")
        return found[1], (list(times) if times else None), None
    sc = self_calibrate(frames, warn=warn)
    if say is not None:
        which = f"for {first.camera} at ISO {first.iso:g}" if first.camera and first.iso else "for these frames"
        say(f"no --calibration and none in the library {library_dir()} {which}: {sc.calibration.provenance['source']}")
    if exposure_times == "nominal":
        return sc.calibration, list(sc.nominal_times), sc
    if darks and not sc.times_match_nominal():
        beyond = sc.times_beyond_errors()
        if beyond and warn is not None:
            warn(
                f"effective exposure times differ from the nominal ones beyond their standard errors (up to "
                f"{beyond:.1f} standard errors), but dark frames are matched by nominal time: the merge uses the "
                "nominal times and estimates the effective ones itself after matching them"
            )
        return sc.calibration, list(sc.nominal_times), sc
    return sc.calibration, list(sc.effective_times), sc


def check_camera_model(
    calibration: Calibration,
    frame: RawFrame,
    *,
    name: str = "the calibration",
    mismatch: str = "refuse",
    warn: Callable[[str], None] | None = None,
) -> None:
    """Refuse a camera model made for another camera than ``frame``'s: another model or serial,
    ISO, white level (ADC range), size or CFA pattern (:func:`pipeline.compat.check_compatible`,
    the rule the capture runs use; what either side does not know is not compared).

    Parameters
    ----------
    calibration : Calibration
        The model (a calibration file's, a preset's, the library's).
    frame : RawFrame
        A frame of the bracket (its metadata).
    name : str
        The model in messages (``calibration cam.cal``, ``preset camera-B``).
    mismatch : {"refuse", "warn"}
        ``warn``: a mismatch is a warning (deliberate use), not an error.
    warn : callable, optional
        Called with the warning (``mismatch="warn"``).

    Raises
    ------
    pipeline.compat.CompatibilityError
        A mismatch, with ``mismatch="refuse"``: one line naming what differs.
    """
    from hdrcap.pipeline.compat import CameraProfile, CompatibilityError, check_compatible

    expected = dataclasses.replace(CameraProfile.from_calibration(calibration, name), temperature_c=None)
    try:
        check_compatible(expected, CameraProfile.from_frame(frame))
    except CompatibilityError as err:
        if mismatch != "warn":
            raise CompatibilityError(
                f"{err}; merge with this camera's calibration (--calibration-mismatch warn merges anyway)"
            ) from None
        if warn is not None:
            warn(f"{err} (--calibration-mismatch warn: merged with it anyway)")


def _model_name(calib: Calibration, calibration_file: Any) -> str:
    """The camera model in messages: its file, a preset's name, or "the calibration"."""
    if calibration_file is not None:
        return f"calibration {calibration_file}"
    source = str((calib.provenance or {}).get("source") or "")
    if source.startswith("preset "):
        return source.split(" (")[0]
    return "the calibration"


@dataclass
class _FirstFrame:
    """What a merge does once, with the first frame it reads (in whichever pass): say what was
    assumed about the files (one warning for the bracket) and check the camera model given."""

    warn: Callable[[str], None]
    check: Callable[[RawFrame], None] | None = None
    seen: bool = False

    def __call__(self, fr: RawFrame) -> None:
        if self.seen:
            return
        self.seen = True
        if fr.assumed:
            from hdrcap.pipeline.io.frameformat import describe_assumed

            high = int(np.max(fr.data)) if "white_level_unknown" in fr.assumed else None
            what = describe_assumed(fr.assumed, fr.bits, fr.quantisation_step, fr.white_level, high)
            self.warn(
                f"{fr.path or 'frame'} (and the bracket's other frames): the file does not say its format; assumed "
                f"{what} (--cfa, --black-level, --white-level, --bits say otherwise)"
            )
        if self.check is not None:
            self.check(fr)


def _camera_model(calibration: Calibration | str | os.PathLike[str] | None) -> tuple[Calibration | None, Any]:
    """The request's calibration and the file it came from (None for an object)."""
    if calibration is None or isinstance(calibration, Calibration):
        return calibration, None
    from hdrcap.pipeline.calibration import load_calibration

    return load_calibration(calibration), calibration


# --------------------------------------------------------------------------- preparation
@dataclass
class Prepared:
    """What both merge engines (in memory, tiled) take from a request: the options with the
    plan's applied, each frame's dark strategy, the dark resolver's settings and the header
    entries of the merge."""

    options: dict[str, Any]
    strategy_for: Callable[[RawFrame], tuple[DarkStrategy, float | None]]
    resolver_args: dict[str, Any]
    master_dark: FrameSource | None
    master_plain: bool
    plan: PlanFile | None
    entries: dict[str, Any]

    def master_dark_time(self, master: RawFrame) -> None:
        """Record the master dark's exposure time unless one is set (a PNG/TIFF or an array
        without one: used as is)."""
        self.options["dark_strategy"] = DarkStrategy.MASTER
        if self.options.get("master_dark_time") is None and not self.master_plain:
            self.options["master_dark_time"] = master.exposure_time


def _option_dict(options: MergeOptions) -> dict[str, Any]:
    """The merge options as keywords of :class:`pipeline.merge.accumulator.MergeAccumulator`."""
    out = {f.name: getattr(options, f.name) for f in dataclasses.fields(options)}
    if out["dark_strategy"] is None:
        del out["dark_strategy"]
    return out


def prepare(
    req: MergeRequest, calib: Calibration, options: MergeOptions, library: str | None, warn: Callable[[str], None]
) -> Prepared:
    """The plan, dark strategies and header entries of a request (both engines take them).

    Parameters
    ----------
    req : MergeRequest
        The request.
    calib : Calibration
        The camera model resolved.
    options : MergeOptions
        The options to merge with (the request's, exposure times possibly set by a
        self-calibration).
    library : str or None
        The dark library folder.
    warn : callable
        Called with one-line warnings.

    Returns
    -------
    Prepared
    """
    opts = _option_dict(options)
    if req.master_dark_frames is not None:
        opts["n_dark"] = req.master_dark_frames
    one = options.dark_strategy if (req.plan is None or "dark_strategy" in req.given) else None
    entries: dict[str, Any] = {"weighting": "optimal"}
    if req.plan is not None:
        from hdrcap.pipeline.planfile import apply_plan_options, planner_attribute

        opts, taken, overridden, ignored = apply_plan_options(req.plan, opts, lambda name: name in req.given)
        for name in ignored:
            warn(f"{req.plan.path}: merge option {name!r} is not one hdrcap merge knows; ignored")
        if one is not None:
            overridden["darks"] = {"plan": req.plan.data["darks"], "used": one.value}
        entries["planner"] = planner_attribute(
            req.plan.data, req.plan.path, req.plan.sha256, taken, overridden, options_ignored=ignored
        )
        strategy_for = _plan_strategies(req.plan, one)
    else:
        only = one or default_strategy(bool(req.darks), req.master_dark is not None)

        def strategy_for(_fr: RawFrame) -> tuple[DarkStrategy, float | None]:
            return only, None

    master = req.master_dark
    plain = master is not None and _without_time(master)
    if plain and "master_dark_time" not in req.given:
        opts["master_dark_time"] = None  # no exposure time: used as is
    if master is not None:
        entries["master_dark_file"] = str(master.path if isinstance(master, RawFrame) else master)
    if (
        opts.get("dark_strategy") is DarkStrategy.MASTER
        and "dark_strategy" in req.given
        and not (req.darks or master is not None or library)
    ):
        raise InputError(
            "--dark-strategy master needs --master-dark FILE, per-exposure master darks (--darks) "
            "or a calibration with a dark library (--calibration)"
        )
    resolver_args = {
        "frames_per_dark": req.master_dark_frames,
        "master_dark": None if master is None else entries["master_dark_file"],
        "library": library,
        "temperature": (calib.provenance or {}).get("temperature"),
    }
    return Prepared(opts, strategy_for, resolver_args, master, plain, req.plan, entries)


def _without_time(frame: FrameSource) -> bool:
    """Whether a master dark has no exposure time of its own (PNG/TIFF, or an array)."""
    if isinstance(frame, RawFrame):
        return frame.path is None or Path(frame.path).suffix.lower() in IMAGE_EXTENSIONS
    return Path(frame).suffix.lower() in IMAGE_EXTENSIONS


def _plan_strategies(
    plan: PlanFile, dark_strategy: DarkStrategy | None
) -> Callable[[RawFrame], tuple[DarkStrategy, float | None]]:
    """Frame -> (dark strategy, planned master-dark frame count) from the plan (or the one
    strategy the user gave for every exposure)."""

    def strategy_for(fr: RawFrame) -> tuple[DarkStrategy, float | None]:
        i = plan.group(fr.exposure_time)
        if i is None:
            raise InputError(
                f"{fr.path}: exposure {fr.exposure_time:g} s is not in the plan {plan.path} "
                f"({', '.join(f'{t:g}' for t in plan.times)} s); leave the frame out or "
                "merge without --plan"
            )
        return (dark_strategy, None) if dark_strategy else (plan.strategies[i], plan.n_dark[i])

    return strategy_for


def missing_dark(fr: RawFrame, strategy: DarkStrategy, resolver: DarkResolver) -> InputError:
    """The error for a frame no dark level serves.

    Parameters
    ----------
    fr : RawFrame
        The frame.
    strategy : DarkStrategy
        Its dark strategy.
    resolver : DarkResolver
        What was searched.

    Returns
    -------
    InputError
        A one-line message naming the frame, its time and where a dark frame could come from.
    """
    t = fr.exposure_time
    if strategy is DarkStrategy.MATCHED:
        return InputError(
            f"{fr.path}: no dark frame with exposure time {t:g} s for its matched dark strategy; give one with --darks"
        )
    root = None if resolver.library is None else resolver.library.root
    where = f"the dark library {root} holds none for this camera" if root else "the calibration has no dark library"
    return InputError(f"{fr.path}: no master dark for exposure {t:g} s: none in --darks, no --master-dark, and {where}")


def warn_short_master(
    src: DarkSource,
    strategy: DarkStrategy,
    n_planned: float | None,
    t: float,
    warned: set[str],
    warn: Callable[[str], None],
) -> None:
    """Warn once per master dark that averages fewer frames than the plan expects.

    Parameters
    ----------
    src : DarkSource
        What serves the exposure.
    strategy : DarkStrategy
        The exposure's strategy.
    n_planned : float or None
        Frames the plan expects in its master dark.
    t : float
        The exposure time, s.
    warned : set
        Sources already warned about (updated).
    warn : callable
        Called with the warning.
    """
    short = (
        src.origin == "frames"
        and strategy is DarkStrategy.MASTER
        and n_planned
        and src.n_frames is not None
        and src.n_frames < n_planned
    )
    if short and src.source not in warned:
        warned.add(src.source)
        warn(
            f"the plan expects a master dark of {n_planned:g} frames at {t:g} s; --darks gives "
            f"one of {src.n_frames:g} (set --master-dark-frames if a file averages more)"
        )


def check_plan_covered(plan: PlanFile, frames: Sequence[RawFrame], warn: Callable[[str], None]) -> None:
    """Every planned exposure time must be among the frames; fewer frames than planned warn.

    Parameters
    ----------
    plan : PlanFile
        The plan.
    frames : sequence of RawFrame
        The bracket.
    warn : callable
        Called with a warning for each time with fewer frames than planned.

    Raises
    ------
    InputError
        A planned time matches no frame.
    """
    seen = [0] * len(plan.times)
    for fr in frames:
        i = plan.group(fr.exposure_time)
        if i is not None:
            seen[i] += 1
    missing = [t for t, k in zip(plan.times, seen) if k == 0]
    if missing:
        raise InputError(f"{plan.path}: planned exposure {missing[0]:g} s matches no frame (within 0.1 %)")
    for t, c, k in zip(plan.times, plan.counts, seen):
        if k < c:
            warn(f"the plan has {c} exposures of {t:g} s, the frames {k}")


# --------------------------------------------------------------------------- the merge
def merge_files(
    request: MergeRequest,
    *,
    progress: bool = False,
    warn: Callable[[str], None] = _warn,
    say: Callable[[str], None] | None = None,
) -> HdrResult:
    """Merge a bracket into irradiance and its uncertainty, with the complete header (Eq. 6,
    8-13, Fig. 3; the baselines of Table 1).

    Parameters
    ----------
    request : MergeRequest
        The bracket, camera model, options and plan.
    progress : bool
        Progress bars on stderr.
    warn : callable
        Called with one-line warnings (what was assumed, masked values, short master darks).
    say : callable, optional
        Called with one line naming the calibration used when none was given.

    Returns
    -------
    HdrResult
        Irradiance, sigma, sigma_calibration (when the calibration has standard errors), nexp,
        quality and the header. A tiled merge's channels are memory-mapped files (read them
        block by block; :func:`pipeline.io.results.write_result` does).

    Raises
    ------
    InputError
        Unreadable or inconsistent frames, a missing dark frame, a bad option or plan.
    """
    req = request
    calib, calibration_file = _camera_model(req.calibration)
    if req.weighting == "optimal":
        start_warm_up()  # numba's set-up while the calibration loads and the frames are read
    first = _FirstFrame(warn)
    if calib is not None:
        given, name = calib, _model_name(calib, calibration_file)
        first.check = lambda fr: check_camera_model(given, fr, name=name, mismatch=req.calibration_mismatch, warn=warn)
    options = req.options
    times_applied = options.exposure_times == "effective"  # as asked (a self-calibration may hand them over)
    calib, times, selfcal = bracket_calibration(
        calib,
        req.frames,
        req.times,
        darks=bool(req.darks),
        warn=warn,
        say=say,
        exposure_times=options.exposure_times,
        fmt=req.frame_format,
        on_frame=first,
    )
    if selfcal is not None and times == list(selfcal.effective_times):
        # the self-calibration's pairs gave the effective times: not estimated twice
        options = dataclasses.replace(options, exposure_times="nominal")
    rows = _tile_rows(req, calib)
    if req.weighting != "optimal":
        return _merge_baseline(req, calib, times, progress, first)
    prep = prepare(req, calib, options, req.dark_library or library_root(calib, calibration_file), warn)
    if rows:
        from hdrcap.pipeline.merge.tiled import merge_tiled

        return merge_tiled(
            req, prep, calib, times, rows, selfcal, times_applied, progress=progress, warn=warn, on_frame=first
        )
    result, frames, darks, used = _merge_in_memory(req, prep, calib, times, progress, warn, first)
    entries = dict(prep.entries, dark_sources=used)
    if req.bad_values == "mask":
        entries["masked_values"] = {str(f.path): f.n_masked for f in frames}
    result = _finish(result, frames, calib, entries, req.header, selfcal, times_applied, warn)
    return result


def _finish(
    result: HdrResult,
    frames: Sequence[RawFrame],
    calib: Calibration,
    entries: dict[str, Any],
    door: Mapping[str, Any],
    selfcal: Any,
    times_applied: bool,
    warn: Callable[[str], None],
) -> HdrResult:
    """The merge with its header (the door's entries last) and its self-calibration stated."""
    from hdrcap.pipeline.header import with_merge_header

    result = with_merge_header(result, frames, calib, warn=warn, **entries, **dict(door))
    if selfcal is not None:
        from hdrcap.pipeline.calibration.selfcal import apply_self_calibration

        result = apply_self_calibration(result, selfcal, times_applied=times_applied)
    return result


def _merge_in_memory(
    req: MergeRequest,
    prep: Prepared,
    calib: Calibration,
    times: Sequence[float | None] | None,
    progress: bool,
    warn: Callable[[str], None],
    on_frame: Callable[[RawFrame], None] | None = None,
) -> tuple[HdrResult, list[RawFrame], list[RawFrame], list[str]]:
    """Read the bracket (in parallel threads) and feed each frame to a
    :class:`pipeline.merge.accumulator.MergeAccumulator` as soon as it is decoded, with the
    dark strategy and dark level it is served (``on_frame`` sees each frame first). Returns
    (result, frames, darks, per-frame dark sources)."""
    from hdrcap.pipeline.io.files import release_mapped_pages
    from hdrcap.pipeline.io.raw import check_frames, read_frame
    from hdrcap.pipeline.merge.accumulator import MergeAccumulator

    darks = read_frames(req.darks, None, "dark frame", progress, fmt=req.frame_format) if req.darks else []
    if darks:
        darks = check_frames(darks, "dark frame")
    master = prep.master_dark
    if master is not None and not isinstance(master, RawFrame):
        master = read_frame(Path(master), 1.0 if prep.master_plain else None)
    if master is not None:
        prep.master_dark_time(master)
    resolver = DarkResolver(**prep.resolver_args)
    for d in darks:
        resolver.add_dark(d.data, d.exposure_time, str(d.path))
    acc = None
    frames: list[RawFrame] = []
    used: list[str] = []
    warned: set[str] = set()
    for fr in _frames_in(req.frames, times, "frame", progress, req.bad_values, req.frame_format, on_frame):
        if fr.n_masked:
            warn(
                f"{fr.path}: {fr.n_masked} photosites with impossible raw values (above the white level's ADC range) "
                "masked: merged from the other frames there"
            )
        if acc is None:
            if master is not None and master.shape != fr.shape:
                raise InputError(f"{master.path}: master dark size differs from the bracket's")
            # stream=False: the frames are all read here anyway, so the merge does its single
            # pass at the end (less memory than the first-pass sums of a live capture).
            acc = MergeAccumulator(
                calib, fr.shape, master_dark=None if master is None else master.data, stream=False, **prep.options
            )
        strategy, n_planned = prep.strategy_for(fr)
        src = resolver.resolve(fr.exposure_time, strategy, camera=fr.camera, iso=fr.iso)
        if src is None:
            raise missing_dark(fr, strategy, resolver)
        if src.data is not None and np.shape(src.data) != fr.shape:
            raise InputError(f"{src.source}: dark frame size differs from the bracket's")
        warn_short_master(src, strategy, n_planned, fr.exposure_time, warned, warn)
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
    if prep.plan is not None:
        check_plan_covered(prep.plan, frames, warn)
    # Once merged, memory-mapped frames stop counting in memory (still readable).
    mapped = [fr.data for fr in (*frames, *darks)]
    assert acc is not None  # the request has frames
    result = acc.result(release_frames=lambda: release_mapped_pages(mapped))
    return result, frames, darks, used


def _merge_baseline(
    req: MergeRequest,
    calib: Calibration,
    times: Sequence[float | None] | None,
    progress: bool,
    on_frame: Callable[[RawFrame], None] | None = None,
) -> HdrResult:
    """A weighted average of Table 1 (:func:`pipeline.merge.weighting.merge_weighted`)."""
    from hdrcap.pipeline.header import with_merge_header
    from hdrcap.pipeline.merge.weighting import merge_weighted

    fr = read_frames(req.frames, times, "frame", progress, fmt=req.frame_format, on_frame=on_frame)
    dk = read_frames(req.darks, None, "dark frame", progress, fmt=req.frame_format) if req.darks else []
    result = merge_weighted(
        [f.data for f in fr],
        [f.exposure_time for f in fr],
        calib,
        [d.data for d in dk] if dk else None,
        method=req.weighting,
    )
    return with_merge_header(result, fr, calib, weighting=req.weighting, **dict(req.header))


def _tile_rows(req: MergeRequest, calib: Calibration) -> int | None:
    """Rows per tile (the request's, or chosen when the merge would exceed the memory budget),
    or None for the in-memory merge."""
    if req.tiling is None:
        return None
    files = [f for f in req.frames if not isinstance(f, RawFrame)]
    if len(files) < len(req.frames):  # frames already in memory
        if req.tiling == "auto":
            return None
        raise InputError("a tiled merge reads files: give file paths, not frames in memory")
    from hdrcap.pipeline.merge.tiled import default_memory_budget, tiling_rows

    budget = req.memory_budget or default_memory_budget()
    chunks = None if req.tiling == "auto" else int(req.tiling)
    rows = tiling_rows([Path(f) for f in files], len(req.darks), calib, chunks=chunks, budget=budget)
    if rows is None:
        return None
    why = f"--chunks {chunks}" if chunks else f"the merge would need more than --memory-budget {budget / 2**30:.2f} GiB"
    if req.weighting != "optimal":
        raise InputError(f"{why}: tiled merges use --weighting optimal, not {req.weighting}")
    if req.bad_values == "mask":
        raise InputError(f"{why}: tiled merges refuse bad values; --bad-values mask needs the in-memory merge")
    if any(isinstance(d, RawFrame) for d in req.darks) or isinstance(req.master_dark, RawFrame):
        raise InputError(f"{why}: a tiled merge reads its dark frames from files")
    return rows
