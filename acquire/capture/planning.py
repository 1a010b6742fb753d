"""The capture plan of a run: a fixed bracket, or metering and the planner for a target SNR,
with the master darks a dark library already holds left out of the frames to take."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hdrcap.acquire.camera import Camera, exposure_ladder, nearest_allowed
from hdrcap.acquire.capture.camera_setup import run_iso
from hdrcap.acquire.capture.job import Job
from hdrcap.acquire.capture.manifest import jsonable
from hdrcap.acquire.capture.metering import meter_fn, refuse_unlit_metering
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.times import same_exposure

if TYPE_CHECKING:
    from hdrcap.acquire.capture.session import CapturePlan, RetryPolicy, StopEvent
    from hdrcap.pipeline.calibration.darklibrary import DarkEntry
    from hdrcap.pipeline.params import Calibration
    from hdrcap.planner.plan import Plan

__all__ = ["plan_for", "library_masters", "library_root"]


def plan_for(
    job: Job,
    camera: Camera,
    calibration: Calibration,
    run_dir: Path,
    echo: Callable[[str], None],
    retry: RetryPolicy | None = None,
    stop: StopEvent | None = None,
) -> tuple[CapturePlan, dict[str, Any]]:
    """The capture plan: a fixed bracket, or meter + planner for a target SNR.

    Times that are not the camera's are snapped to its nearest (``info["snapped_times"]``:
    [given, taken] pairs; each frame keeps the given time as ``job_exposure_s``). The
    planner's dark strategy per exposure is kept (unless the job sets ``[darks] strategy``):
    dark frames are captured only for matched and master exposures, and not for master
    exposures whose master dark the dark library holds. ``info`` (recorded in the manifest)
    carries the planner's decisions and merge options for the merge and the EXR header.

    Parameters
    ----------
    job : Job
    camera : Camera
        The open camera (exposure ladder; metering frames for a target SNR).
    calibration : pipeline.params.Calibration
    run_dir : Path
        The run folder (metering frames go to its ``meter/``).
    echo : callable
        Where the plan's message goes.
    retry : acquire.capture.session.RetryPolicy, optional
        Retries of the metering frames.
    stop : threading.Event, optional
        Stops metering.

    Returns
    -------
    tuple
        (:class:`acquire.capture.session.CapturePlan`, info dict).

    Raises
    ------
    acquire.capture.session.VerificationError
        Metering saw no light (:func:`acquire.capture.metering.refuse_unlit_metering`).
    """
    from hdrcap.acquire.capture.session import CapturePlan

    exp, darks = job["exposure"], job["darks"]
    allowed = exposure_ladder(camera)
    times = list(exp["times"])
    strategy: str | list[str] = darks["strategy"]
    info: dict[str, Any] = {"mode": exp["mode"]}
    if exp["mode"] == "snr":
        times, strategy = _plan_for_snr(job, camera, calibration, run_dir, echo, retry, stop, info)
    snapped = [nearest_allowed(t, allowed) for t in times]
    moved = [[t, got] for t, got in zip(times, snapped) if not same_exposure(t, got)]
    if moved:  # the camera's times are what the frames are taken at; the job's are kept
        info["snapped_times"] = moved
    per = [strategy] * len(snapped) if isinstance(strategy, str) else strategy
    master_times = [t for t, s in zip(snapped, per) if s == DarkStrategy.MASTER]
    masters = (
        library_masters(
            library_root(job, calibration),
            camera,
            master_times,
            load=False,
            iso=run_iso(job, calibration),
            strict=True,
            echo=echo,
        )
        if master_times
        else {}
    )
    if masters:
        info["dark_library"] = {f"{t:g}": n for t, (_d, n) in masters.items()}
        echo(f"dark library: master darks for {len(masters)} of {len(set(master_times))} master-dark exposure times")
    plan = CapturePlan.bracket(
        times,
        allowed,
        strategy,
        n_dark=darks["count"],
        repeats=exp["repeats"],
        series=job["calibration"]["series"],
        library_times=list(masters),
    )
    return plan, info


def _plan_for_snr(
    job: Job,
    camera: Camera,
    calibration: Calibration,
    run_dir: Path,
    echo: Callable[[str], None],
    retry: RetryPolicy | None,
    stop: StopEvent | None,
    info: dict[str, Any],
) -> tuple[list[float], str | list[str]]:
    """Meter the scene and plan for ``[exposure] target_snr_db``: (times, dark strategy or one
    per time); the planner's decisions go into ``info``."""
    from hdrcap import planner

    exp = job["exposure"]
    strategy: str | list[str] = job["darks"]["strategy"]
    allowed = exposure_ladder(camera)
    irradiance, report = planner.meter(meter_fn(camera, run_dir, retry, stop), calibration, allowed, return_report=True)
    refuse_unlit_metering(report, run_dir)
    root = library_root(job, calibration)
    iso = run_iso(job, calibration)
    library = {t: n for t, (_d, n) in library_masters(root, camera, allowed, load=False, iso=iso).items()}
    plan = planner.plan_exposures(
        calibration,
        irradiance,
        exp["target_snr_db"],
        allowed,
        max_exposures=exp.get("max_exposures"),
        time_budget=exp.get("time_budget_s"),
        quantile=exp.get("quantile"),
        dark_library=library or None,
    )
    info.update(
        planner=True,
        predicted_min_snr_db=plan.predicted_min_snr_db,
        feasible=plan.feasible,
        message=plan.message,
        plan=_plan_record(plan),
    )
    if plan.darks:
        if "strategy" not in job.spec.darks.model_fields_set:
            strategy = list(plan.darks)
        elif set(plan.darks) != {strategy}:
            info["plan_overridden"] = {"darks": {"plan": list(plan.darks), "used": strategy}}
    echo(f"plan: {plan.message}")
    return list(plan.exposures), strategy


def _plan_record(plan: Plan) -> dict[str, Any]:
    """What the manifest keeps of a planner's plan (JSON): the plan without its SNR curve, and
    the merge options that follow its decisions."""
    d = plan.to_dict()
    d.pop("curve", None)
    d.setdefault("merge_options", plan.merge_options())
    return jsonable(d)


def library_root(job: Job, calibration: Calibration) -> str | None:
    """The dark library of the run: ``[calibration] dark_library``, else the calibration's.

    Parameters
    ----------
    job : Job
    calibration : pipeline.params.Calibration

    Returns
    -------
    str or None
    """
    if "dark_library" in job["calibration"]:
        return str(job.resolve(job["calibration"]["dark_library"]))
    return getattr(calibration, "dark_library", None)


def library_masters(
    root: str | None,
    camera: Camera,
    times: Sequence[float],
    load: bool = True,
    iso: float | None = None,
    strict: bool = False,
    echo: Callable[[str], None] | None = None,
) -> dict[float, tuple[np.ndarray | None, int]]:
    """Master darks of the dark library at ``root`` for ``times`` (s): t -> (data, N), matched
    by :meth:`pipeline.calibration.darklibrary.DarkLibrary.masters` to the camera's model (normalised,
    :func:`pipeline.compat.same_model`), ``iso`` and temperature (data None unless ``load``).
    Empty when there is no dark library.

    Parameters
    ----------
    root : str or None
        The dark library folder.
    camera : Camera
        The connected camera (identity, temperature).
    times : sequence of float
        Exposure times, s.
    load : bool
        Load the master darks.
    iso : float, optional
        The run's ISO speed.
    strict : bool
        Refuse (CompatibilityError) a library that holds no master of this camera, or whose
        masters for one of ``times`` are all of another ISO, instead of using none.
    echo : callable, optional
        Where a warning goes when the camera reports no temperature (the masters are then
        matched at any temperature).

    Returns
    -------
    dict
        t -> (master dark in DN or None, its frame count N).
    """
    if not root:
        return {}
    from collections import Counter

    from hdrcap.pipeline.calibration.darklibrary import DarkLibrary
    from hdrcap.pipeline.compat import CompatibilityError, same_model

    lib = DarkLibrary(root)
    entries = lib.entries()
    model = str(getattr(getattr(camera, "identity", None), "model", "")) or None
    mine = [e for e in entries if same_model(model, e.camera)]
    if not mine:
        if strict and entries:
            names = ", ".join(sorted({e.camera for e in entries}))
            raise CompatibilityError(f"dark library {root} holds master darks of {names}, not of the camera {model!r}")
        return {}
    if strict and iso is not None:
        _refuse_other_iso(root, mine, times, iso)
    name = Counter(e.camera for e in mine).most_common(1)[0][0]
    temp = camera.temperature() if hasattr(camera, "temperature") else None
    found = lib.masters(times, camera=name, iso=iso, temperature=temp, load=load)
    if echo is not None and temp is None and any(e.temperature is not None for _d, _n, e in found.values()):
        echo(
            "hdrcap: warning: the camera reports no temperature; master darks of the dark library are matched at "
            "any temperature (their dark current may differ)"
        )
    return {t: (data, n) for t, (data, n, _e) in found.items()}


def _refuse_other_iso(root: str, entries: list[DarkEntry], times: Sequence[float], iso: float) -> None:
    """CompatibilityError when the library's masters for one of ``times`` are all of another ISO."""
    from hdrcap.pipeline.compat import CompatibilityError
    from hdrcap.pipeline.times import same_exposure

    for t in times:
        at_t = [e for e in entries if same_exposure(e.exposure_time, t)]
        if at_t and all(e.iso is not None and abs(e.iso - iso) > 0.5 for e in at_t):
            isos = ", ".join(sorted({f"{e.iso:g}" for e in at_t}))
            raise CompatibilityError(
                f"dark library {root}: the master darks for {t:g} s are at ISO {isos}, "
                f"the run is at ISO {iso:g}; add masters at ISO {iso:g} or use "
                '[darks] strategy = "matched"'
            )
