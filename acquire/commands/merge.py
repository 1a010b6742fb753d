"""``hdrcap merge``: raw bracket (+ dark frames) -> EXR with irradiance, sigma and nexp."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import numpy as np

from hdrcap.acquire.cliutil import echo_json, many_values, resolve_calibration
from hdrcap.pipeline.errors import InputError


def read_frames(paths, times=None, what="frame", progress=False):
    """Read raw files / 16-bit images; ``times`` (seconds, one per path) override EXIF."""
    return list(_read_parallel(paths, times, what, progress))


def build_hdr_image(result, frames, calibration, extra=None):
    """The EXR content of a merge: channels and header attributes."""
    from hdrcap import __version__
    from hdrcap.pipeline.io import HdrImage

    attrs = {
        "unit": "electrons per second per photosite",
        "sigma": "standard deviation of irradiance, same unit",
        "nexp": "number of unsaturated exposures used (0: saturated everywhere, irradiance is a lower bound)",
        "cfa_pattern": frames[0].cfa_pattern or "none",
        "exposure_times": [fr.exposure_time for fr in frames],
        "source_files": [fr.path for fr in frames],
        "calibration": {"params": calibration.params.to_dict(), "provenance": calibration.provenance},
        "hdrcap_version": __version__,
        "merge": result.info,
    }
    if extra:
        attrs.update(extra)
    return HdrImage({"irradiance": result.irradiance, "sigma": result.sigma, "nexp": result.nexp}, attrs)


def _median_relative_sigma(irr, sig, ok, max_samples=1_000_000):
    """Median of sigma/|irradiance| over usable photosites (a regular subsample of at most
    ``max_samples`` of them on large images)."""
    step = max(1, irr.size // max_samples)
    i, s, o = irr.ravel()[::step], sig.ravel()[::step], ok.ravel()[::step]
    if not o.any():
        return None
    return float(np.median(s[o] / np.maximum(np.abs(i[o]), 1e-30)))


def summary(result) -> dict:
    irr, sig, nexp = result.irradiance, result.sigma, result.nexp
    ok = nexp > 0
    return {
        "shape": list(irr.shape),
        "irradiance_min": float(irr.min()),
        "irradiance_max": float(irr.max()),
        "median_relative_sigma": _median_relative_sigma(irr, sig, ok),
        "saturated_everywhere": int((~ok).sum()),
        "finite": bool(np.isfinite(irr).all() and np.isfinite(sig).all()),
    }


def _read_parallel(paths, times, what, progress):
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
        futures = [pool.submit(read_frame, p, t) for p, t in zip(paths, times)]
        for fut in tqdm(futures, desc=f"read {what}s", unit="file", disable=None if progress else True, leave=False):
            yield fut.result()


def merge_options(iterations, tolerance, saturation, prnu, dark_strategy, master_dark_frames, saturation_sigmas):
    """Keyword options of :func:`pipeline.merge.merge_arrays` from the command-line knobs."""
    opts = {"iterations": iterations, "tolerance": tolerance, "saturation": saturation, "prnu": prnu,
            "saturation_sigmas": saturation_sigmas}
    if dark_strategy:
        opts["dark_strategy"] = dark_strategy
    if master_dark_frames is not None:
        opts["n_dark"] = master_dark_frames
    return opts


# --------------------------------------------------------------------------- plans
#: Merge options a plan may decide, and the command-line option that overrides each.
PLAN_OPTIONS = ("iterations", "tolerance", "saturation", "saturation_sigmas", "prnu")
_STRATEGIES = ("matched", "master", "model")
_REL_TOL = 1e-3  # exposure times match within 0.1 %


@dataclass
class PlanFile:
    """A plan written by ``hdrcap plan --json``: its exposure times grouped (within 0.1 %)
    with their dark strategy, planned frame count N of a master dark, and number of frames."""

    path: str | None
    data: dict
    sha256: str | None
    times: list[float] = field(default_factory=list)
    strategies: list[str] = field(default_factory=list)
    n_dark: list[float] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)

    def group(self, t: float) -> int | None:
        """Index of the plan's exposure time ``t`` (s) matches within 0.1 %, or None."""
        for i, pt in enumerate(self.times):
            if math.isclose(pt, t, rel_tol=_REL_TOL):
                return i
        return None

    def merge_options(self) -> dict[str, Any]:
        """The merge options the plan decided: its ``merge_options``, or (older plans) the ones
        :meth:`planner.plan.Plan.merge_options` derives from its decisions."""
        mo = self.data.get("merge_options")
        if mo is None:
            try:
                mo = plan_from_dict(self.data).merge_options()
            except (KeyError, TypeError, ValueError, AttributeError) as err:
                raise InputError(f"{self.path}: the plan's decisions are malformed "
                                 f"({type(err).__name__}: {err})") from None
        if not isinstance(mo, dict):
            raise InputError(f"{self.path}: merge_options must be a JSON object")
        return {k: v for k, v in mo.items() if k not in ("dark_strategy", "n_dark")}


def plan_from_dict(d: dict):
    """A :class:`planner.plan.Plan` from its JSON form (the fields a merge needs)."""
    from hdrcap.planner.plan import Plan

    if hasattr(Plan, "from_dict"):
        return Plan.from_dict(d)
    return Plan(exposures=list(d.get("exposures", [])), darks=list(d.get("darks", [])),
                predicted_min_snr_db=d.get("predicted_min_snr_db"), total_time_s=d.get("total_time_s"),
                decisions=dict(d.get("decisions") or {}), feasible=bool(d.get("feasible", True)),
                message=str(d.get("message", "")))


def read_plan(path) -> PlanFile:
    """Read and check a plan JSON (``hdrcap plan --json``); InputError naming the file."""
    import hashlib
    import json

    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read the plan ({err.strerror or err})") from None
    try:
        d = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: not a plan (invalid JSON: {err})") from None
    return check_plan(d, str(path), hashlib.sha256(raw).hexdigest())


def check_plan(d, where: str | None = None, sha256: str | None = None) -> PlanFile:
    """A :class:`PlanFile` from a plan's dict, with one-line errors naming ``where``."""
    where = where or "plan"
    if not isinstance(d, dict):
        raise InputError(f"{where}: not a plan (expected a JSON object from `hdrcap plan --json`)")
    exp = d.get("exposures")
    if not isinstance(exp, list) or not exp:
        raise InputError(f"{where}: the plan has no exposures (key 'exposures': a list of seconds)")
    for t in exp:
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (math.isfinite(t) and t > 0):
            raise InputError(f"{where}: exposure time {t!r} is not a positive number of seconds")
    darks = d.get("darks")
    if not isinstance(darks, list) or len(darks) != len(exp):
        raise InputError(f"{where}: 'darks' must list one dark strategy per exposure ({len(exp)})")
    for s in darks:
        if s not in _STRATEGIES:
            raise InputError(f"{where}: dark strategy {s!r} is not matched, master or model")
    nd = d.get("n_dark")
    if nd is None:
        nd = [1] * len(exp)
    if not isinstance(nd, list) or len(nd) != len(exp) or not all(
            isinstance(n, (int, float)) and not isinstance(n, bool) and n >= 0 for n in nd):
        raise InputError(f"{where}: 'n_dark' must list one frame count >= 0 per exposure ({len(exp)})")
    for key in ("decisions", "merge_options"):
        if d.get(key) is not None and not isinstance(d[key], dict):
            raise InputError(f"{where}: {key!r} must be a JSON object")
    plan = PlanFile(where, d, sha256)
    for t, s, n in zip(exp, darks, nd):
        i = plan.group(float(t))
        if i is None:
            plan.times.append(float(t))
            plan.strategies.append(s)
            plan.n_dark.append(float(n))
            plan.counts.append(1)
        elif plan.strategies[i] != s:
            raise InputError(f"{where}: exposure {t:g} s is planned with two dark strategies "
                             f"({plan.strategies[i]} and {s})")
        else:
            plan.counts[i] += 1
            plan.n_dark[i] = max(plan.n_dark[i], float(n))
    return plan


def planner_attribute(plan: dict, plan_file: str | None = None, sha256: str | None = None,
                      from_plan: dict | None = None, overridden: dict | None = None, **more) -> dict:
    """The ``planner`` attribute of the EXR header: the plan's decisions, predicted minimum
    SNR and file (with its sha256), and which merge options came from the plan and which the
    user overrode."""
    return {
        "plan_file": plan_file,
        "plan_sha256": sha256,
        "decisions": plan.get("decisions") or {},
        "predicted_min_snr_db": plan.get("predicted_min_snr_db"),
        "target_snr_db": plan.get("target_snr_db"),
        "total_time_s": plan.get("total_time_s"),
        "feasible": plan.get("feasible"),
        "exposures": plan.get("exposures"),
        "darks": plan.get("darks"),
        "n_dark": plan.get("n_dark"),
        "options_from_plan": dict(from_plan or {}),
        "options_overridden": dict(overridden or {}),
        **more,
    }


def apply_plan_options(plan: PlanFile, options: dict, given) -> tuple[dict, dict, dict, list]:
    """Merge ``options`` (the command line's) with the plan's decided options; an option the
    user gave (``given(name)``) wins. Returns (options, taken from the plan, overridden as
    name -> {"plan", "used"}, names of decided options this merge does not know)."""
    decided = plan.merge_options()
    options, taken, overridden = dict(options), {}, {}
    ignored = sorted(set(decided) - set(PLAN_OPTIONS))
    for name in PLAN_OPTIONS:
        if name not in decided:
            continue
        value = decided[name]
        if given(name):
            if options.get(name) != value:
                overridden[name] = {"plan": value, "used": options.get(name)}
        else:
            options[name] = value
            taken[name] = value
    return options, taken, overridden, ignored


# --------------------------------------------------------------------------- dark frames
class DarkSources:
    """The dark level of each light frame, by its dark strategy.

    ``matched``: the dark frame of the same exposure time from ``darks``. ``master``: the
    dark frames of that time from ``darks`` (averaged when several; N = their number times
    ``master_frames``), else the single ``master_dark`` (None is returned: the accumulator
    uses its own master dark), else the master dark of that time in the calibration's dark
    library (its N). ``model``: none.
    """

    def __init__(self, master_dark=None, master_frames=None, library_root=None, temperature=None, darks=()):
        self.by_time: dict[float, list] = {}
        self.master_dark = master_dark
        self.master_frames = master_frames
        self.library_root = library_root
        self.temperature = temperature
        self._library = None
        self._cache: dict[float, tuple] = {}
        self.add_darks(darks)

    def add_darks(self, darks) -> None:
        """Dark frames (RawFrame) to draw matched and master darks from, by exposure time."""
        for d in darks or ():
            self.by_time.setdefault(round(d.exposure_time, 12), []).append(d)

    def _dark_frames(self, t: float) -> list:
        hit = self.by_time.get(round(t, 12))
        if hit:
            return hit
        for k, v in self.by_time.items():
            if math.isclose(k, t, rel_tol=_REL_TOL):
                return v
        return []

    def _from_library(self, fr):
        """The library's master dark for the frame's exposure time, camera and ISO."""
        if not self.library_root:
            return None
        from hdrcap.pipeline.darklibrary import DarkLibrary

        if self._library is None:
            self._library = DarkLibrary(self.library_root)
        found = self._library.masters([fr.exposure_time], camera=fr.camera, iso=fr.iso, temperature=self.temperature)
        return next(iter(found.values()), None)

    def for_frame(self, fr, strategy: str, n_planned: float | None = None) -> tuple[Any, float | None, str]:
        """(dark level in DN or None, frames averaged in it for ``master``, its source).
        ``n_planned``: the frame count the plan expects of the master dark (a warning when
        ``--darks`` files give fewer: they count ``master_frames``, default 1, each)."""
        t = fr.exposure_time
        if strategy == "model":
            return None, None, "model"
        if strategy == "matched":
            got = self._dark_frames(t)
            if not got:
                raise InputError(f"{fr.path}: no dark frame with exposure time {t:g} s for its matched dark "
                                 "strategy; give one with --darks")
            return got[0].data, None, str(got[0].path)
        key = round(t, 12)
        if key in self._cache:
            return self._cache[key]
        got = self._dark_frames(t)
        if got:
            data = got[0].data if len(got) == 1 else np.mean([g.data for g in got], axis=0, dtype=np.float64)
            n = (self.master_frames or 1) * len(got)
            out = (np.asarray(data, np.float32) if len(got) > 1 else data, n, ", ".join(str(g.path) for g in got))
            if n_planned and n < n_planned:
                click.echo(f"hdrcap: warning: the plan expects a master dark of {n_planned:g} frames at {t:g} s; "
                           f"--darks gives one of {n:g} (set --master-dark-frames if a file averages more)", err=True)
        elif self.master_dark is not None:
            out = (None, None, str(self.master_dark.path))
        else:
            hit = self._from_library(fr)
            if hit is None:
                where = (f"the dark library {self.library_root} holds none for this camera"
                         if self.library_root else "the calibration has no dark library")
                raise InputError(f"{fr.path}: no master dark for exposure {t:g} s: none in --darks, no --master-dark, "
                                 f"and {where}")
            data, n, entry = hit
            out = (data, float(n), str(Path(self.library_root) / entry.file))
        self._cache[key] = out
        return out


def library_root(calib, calibration_path=None) -> str | None:
    """The calibration's dark library folder (a relative path is tried from the working
    folder, then from the calibration file's folder)."""
    root = getattr(calib, "dark_library", None)
    if not root:
        return None
    p = Path(root)
    if not p.is_absolute() and not p.exists() and calibration_path:
        alt = Path(calibration_path).parent / p
        if alt.exists():
            p = alt
    return str(p)


def streamed_merge(frame_paths, dark_paths, times, calib, options, master_dark=None, progress=False, *,
                   strategy_for=None, sources: DarkSources | None = None, plan: PlanFile | None = None):
    """Read the bracket (in parallel threads) and feed each frame to a
    :class:`pipeline.merge.MergeAccumulator` as soon as it is decoded, with the dark strategy
    ``strategy_for(frame)`` gives it (a strategy, or (strategy, planned frame count of its
    master dark); default: the one of ``options``) and its dark level from
    ``sources`` (default: ``dark_paths`` matched by exposure time). With a ``plan``, every plan
    exposure time must be among the frames. Returns (result, frames without pixel data kept,
    darks, per-frame dark sources)."""
    from hdrcap.pipeline.io import check_frames
    from hdrcap.pipeline.merge import MergeAccumulator

    default = options.get("dark_strategy")
    darks = list(_read_parallel(dark_paths, None, "dark frame", progress)) if dark_paths else []
    if darks:
        darks = check_frames(darks, "dark frame")
    if sources is None:
        sources = DarkSources(master_dark, options.get("n_dark"))
    sources.add_darks(darks)
    if strategy_for is None:
        only = default or ("matched" if darks else "master" if master_dark is not None else "model")

        def strategy_for(_fr):
            return only
    acc = None
    frames, used = [], []
    for fr in _read_parallel(frame_paths, times, "frame", progress):
        if acc is None:
            opts = dict(options)
            if master_dark is not None:
                opts["dark_strategy"] = "master"
                opts.setdefault("master_dark_time", master_dark.exposure_time)
            # stream=False: the frames are all read here anyway, so the merge does its single
            # pass at the end (less memory than the first-pass sums of a live capture).
            acc = MergeAccumulator(calib, fr.shape, master_dark=None if master_dark is None else master_dark.data,
                                   stream=False, **opts)
        strategy = strategy_for(fr)
        strategy, n_planned = (strategy, None) if isinstance(strategy, str) else strategy
        dark, n, source = sources.for_frame(fr, strategy, n_planned)
        if dark is not None and np.shape(dark) != fr.shape:
            raise InputError(f"{source}: dark frame size differs from the bracket's")
        acc.add(fr.data, fr.exposure_time, dark, strategy=strategy, n_dark=n)
        frames.append(fr)
        used.append(f"{strategy}: {source}" if strategy != "model" else "model")
    check_frames(frames)
    if plan is not None:
        seen = [0] * len(plan.times)
        for fr in frames:
            seen[plan.group(fr.exposure_time)] += 1
        missing = [t for t, k in zip(plan.times, seen) if k == 0]
        if missing:
            raise InputError(f"{plan.path}: planned exposure {missing[0]:g} s matches no frame (within 0.1 %)")
        short = [(t, c, k) for t, c, k in zip(plan.times, plan.counts, seen) if k < c]
        for t, c, k in short:
            click.echo(f"hdrcap: warning: the plan has {c} exposures of {t:g} s, the frames {k}", err=True)
    return acc.result(), frames, darks, used


@many_values("--darks", "--times")
@click.command("merge")
@click.argument("frames", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--darks", multiple=True, type=click.Path(path_type=Path), help="Dark frames, one per exposure time (several after one flag); for master exposures, the master dark of that time (several of one time are averaged).")
@click.option("--calibration", type=click.Path(path_type=Path), help="Calibration file written by `hdrcap calibrate` (its dark library serves master darks).")
@click.option("--camera", help="Use a simulator preset's nominal parameters as the calibration (camera-A, camera-B).")
@click.option("--times", multiple=True, type=float, help="Exposure times (s), one per frame; override EXIF (needed for PNG/TIFF frames).")
@click.option("--plan", "plan_file", type=click.Path(dir_okay=False, path_type=Path), help="Plan JSON from `hdrcap plan --json`: its per-exposure dark strategies and decided merge options are applied (options given here win); recorded in the EXR header.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Output EXR file.")
@click.option("--weighting", default="optimal", show_default=True, help="Weighting: 'optimal' (iterative ML merge) or a baseline name from hdrcap.pipeline.weighting.")
@click.option("--iterations", type=click.IntRange(min=1), default=20, show_default=True, help="Maximum re-weighting steps per photosite.")
@click.option("--tolerance", type=click.FloatRange(min=0), default=1e-6, show_default=True, help="Stop when the change is below this times max(|estimate|, sigma).")
@click.option("--saturation", type=click.Choice(["threshold", "probabilistic"]), default="threshold", show_default=True, help="Saturation model: Eq. 11 plus the near-saturation rule, or the blended likelihood of Eq. 8-10.")
@click.option("--saturation-sigmas", type=click.FloatRange(min=0), default=3.0, show_default=True, help="Drop samples predicted within this many sigma of v_sat (0: off).")
@click.option("--prnu", type=click.Choice(["map", "scalar"]), default="map", show_default=True, help="Per-photosite gain map from the calibration, or a = 1.")
@click.option("--dark-strategy", type=click.Choice(["matched", "master", "model"]), default=None, help="For every exposure (overrides a --plan's). Default: the plan's per exposure; else matched with --darks, master with --master-dark, model otherwise. master without --darks/--master-dark: the calibration's dark library.")
@click.option("--master-dark", type=click.Path(path_type=Path), help="One master dark frame (raw file or 16-bit image) for the master exposures.")
@click.option("--master-dark-frames", type=click.FloatRange(min=1), default=None, help="Number of frames averaged into each master dark file given here (N; library masters carry their own).")
@click.option("--exr-compression", type=click.Choice(["zip", "zips", "piz", "zstd", "rle", "none"]), default="zip", show_default=True, help="EXR compression (none/rle write fastest, zip is about a third smaller; zstd is smaller and faster but needs OpenEXR >= 3.4 to read).")
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
@click.pass_context
def command(ctx, frames, darks, calibration, camera, times, plan_file, output, weighting, iterations, tolerance,
            saturation, saturation_sigmas, prnu, dark_strategy, master_dark, master_dark_frames, exr_compression,
            force, as_json):
    """Merge raw FRAMES (DNG/raw files or 16-bit PNG/TIFF with --times) into an EXR.

    The EXR holds float32 channels irradiance (e-/s per photosite), sigma (its standard
    deviation) and nexp (unsaturated exposures used), and header attributes with the unit, CFA
    pattern, exposure times, calibration, all merge options, the dark frame of every exposure
    and, with --plan, the planner's decisions.
    """
    from click.core import ParameterSource

    from hdrcap.pipeline.io import write_exr

    def given(name):
        return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)

    if output.exists() and not force:
        raise InputError(f"{output}: exists; use --force to overwrite")
    plan = read_plan(plan_file) if plan_file else None
    if plan is not None and weighting != "optimal":
        raise InputError(f"--plan works with --weighting optimal, not {weighting}")
    if dark_strategy == "matched" and not darks:
        raise InputError("--dark-strategy matched needs dark frames (--darks)")
    if master_dark and darks and plan is None:
        raise InputError("give either --darks or --master-dark, not both (both only with --plan)")
    if master_dark and dark_strategy not in (None, "master"):
        raise InputError(f"--master-dark needs --dark-strategy master, not {dark_strategy}")
    t0 = time.perf_counter()
    calib = resolve_calibration(str(calibration) if calibration else None, camera)
    lib_root = library_root(calib, calibration)
    if dark_strategy == "master" and not (darks or master_dark or lib_root):
        raise InputError("--dark-strategy master needs --master-dark FILE, per-exposure master darks (--darks) "
                         "or a calibration with a dark library (--calibration)")
    options = merge_options(iterations, tolerance, saturation, prnu, dark_strategy, master_dark_frames,
                            saturation_sigmas)
    extra = {"weighting": weighting}
    if weighting != "optimal":
        try:
            from hdrcap.pipeline.weighting import WEIGHTING_METHODS, merge_weighted
        except ImportError:
            raise InputError(f"--weighting {weighting}: baseline weightings are not available in this build; use 'optimal'") from None
        if weighting not in WEIGHTING_METHODS:
            raise InputError(f"--weighting {weighting!r}: choose from optimal, {', '.join(WEIGHTING_METHODS)}")
        fr = read_frames(frames, times, "frame", progress=not as_json)
        dk = read_frames(darks, None, "dark frame", progress=not as_json) if darks else None
        result = merge_weighted([f.data for f in fr], [f.exposure_time for f in fr], calib,
                                [d.data for d in dk] if dk else None, method=weighting)
    else:
        md = None
        if master_dark:
            from hdrcap.pipeline.io import read_frame

            if master_dark.suffix.lower() in (".png", ".tif", ".tiff"):  # no exposure time: used as is
                md = read_frame(master_dark, 1.0)
                options["master_dark_time"] = None
            else:
                md = read_frame(master_dark)
        strategy_for = None
        if plan is not None:
            options, taken, overridden, ignored = apply_plan_options(plan, options, given)
            for name in ignored:
                click.echo(f"hdrcap: warning: {plan.path}: merge option {name!r} is not one hdrcap merge knows; "
                           "ignored", err=True)
            if dark_strategy:
                overridden["darks"] = {"plan": plan.data["darks"], "used": dark_strategy}

            def strategy_for(fr):
                i = plan.group(fr.exposure_time)
                if i is None:
                    raise InputError(f"{fr.path}: exposure {fr.exposure_time:g} s is not in the plan {plan.path} "
                                     f"({', '.join(f'{t:g}' for t in plan.times)} s); leave the frame out or "
                                     "merge without --plan")
                return (dark_strategy, None) if dark_strategy else (plan.strategies[i], plan.n_dark[i])

        sources = DarkSources(md, master_dark_frames, lib_root, (calib.provenance or {}).get("temperature"))
        result, fr, dk, used = streamed_merge(frames, darks, times, calib, options, md, progress=not as_json,
                                              strategy_for=strategy_for, sources=sources, plan=plan)
        extra["dark_sources"] = used
        if master_dark:
            extra["master_dark_file"] = str(master_dark)
        if plan is not None:
            extra["planner"] = planner_attribute(plan.data, str(plan_file), plan.sha256, taken, overridden,
                                                 options_ignored=ignored)
    write_exr(output, build_hdr_image(result, fr, calib, extra), force=force, compression=exr_compression)
    info = summary(result) | {"output": str(output), "seconds": round(time.perf_counter() - t0, 3),
                              "n_frames": len(fr), "n_darks": len(dk or [])}
    if as_json:
        echo_json(info)
    else:
        click.echo(f"wrote {output}: {info['shape'][1]}x{info['shape'][0]}, irradiance "
                   f"{info['irradiance_min']:.4g}..{info['irradiance_max']:.4g} e-/s, "
                   f"{info['saturated_everywhere']} photosites saturated everywhere, {info['seconds']:.2f} s")
