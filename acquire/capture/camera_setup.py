"""The job's camera and what is checked against it before the first frame: opening it (the
simulated one with the job's scene, or a real one with its settings and ISO), its exposure
range, its calibration and the disk space of the run."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdrcap.acquire.camera import Camera, exposure_ladder, nearest_allowed
from hdrcap.acquire.capture.job import Job

if TYPE_CHECKING:
    from hdrcap.acquire.camera.gphoto2 import Gphoto2Camera
    from hdrcap.acquire.camera.mock import MockCamera
    from hdrcap.pipeline.compat import CameraProfile
    from hdrcap.pipeline.params import Calibration

__all__ = [
    "open_camera",
    "job_camera_key",
    "check_job_against_camera",
    "check_free_space",
    "job_calibration",
    "run_iso",
    "check_compatibility",
]


def open_camera(job: Job, n: int = 0) -> Camera:
    """The job's camera (for the mock backend: with the job's scene; its seed and its faults'
    seed + n per repetition).

    Parameters
    ----------
    job : Job
    n : int
        Repetition number (the simulated camera's seed offset).

    Returns
    -------
    Camera
        Open, the job's ISO set (and for a real camera its settings checked, or set with
        ``[camera] enforce``); closed again when that fails.

    Raises
    ------
    JobError
        The camera applied another ISO than the job's.
    """
    camera: Camera
    if job["camera"]["backend"] == "mock":
        camera, real = _open_simulator(job, n), None
    else:
        camera = real = _open_gphoto2(job)
    try:
        _apply_iso(job, camera)
        if real is not None:  # changes nothing unless enforce
            real.preflight(enforce=job["camera"].get("enforce", False), iso=job["camera"].get("iso"))
    except BaseException:
        camera.close()
        raise
    return camera


def _open_simulator(job: Job, n: int) -> MockCamera:
    from hdrcap.acquire.camera.mock import MockCamera, MockFaults
    from hdrcap.mock_camera.scenes import load_scene, parse_size

    cam, sc = job["camera"], job["scene"]
    shape = parse_size(cam["size"])
    scene = load_scene(_scene_path(job, sc["name"]), shape, sc["decades"], sc["x_max"])
    faults = MockFaults.from_dict(cam.get("faults", {}))
    return MockCamera(
        cam["preset"],
        scene,
        seed=cam["seed"] + n,
        allowed_times=cam.get("allowed_times"),
        bulb_max_s=cam.get("bulb_max_s"),
        faults=dataclasses.replace(faults, seed=faults.seed + n),  # each repetition its own fault draws
        temperature=cam.get("temperature"),
    )


def _open_gphoto2(job: Job) -> Gphoto2Camera:
    from hdrcap.acquire.camera.gphoto2 import Gphoto2Camera

    cam = job["camera"]
    return Gphoto2Camera(
        cam.get("model"),
        cam.get("port"),
        serial=cam.get("serial"),
        delete_after_download=cam["delete_after_download"],
        long_exposure_s=cam["long_exposure_s"],
        settings=cam.get("settings"),
    )


def _apply_iso(job: Job, camera: Camera) -> Camera:
    """Set the job's ``[camera] iso`` and refuse (JobError) a camera that silently applies
    another one; returns the camera."""
    cam = job["camera"]
    if "iso" in cam:
        applied = camera.set_iso(cam["iso"])
        if applied is not None and abs(float(applied) - cam["iso"]) > 0.5:  # a silent substitution
            raise job.error(
                "camera", "iso", f"the camera applied ISO {applied:g}, not {cam['iso']}; choose one of its ISO speeds"
            )
    return camera


def _scene_path(job: Job, name: str) -> str:
    return str(job.resolve(name)) if name.lower().endswith(".exr") else name


def job_camera_key(job: Job) -> str | None:
    """What names the job's real camera before it is opened, for its lock: ``gphoto2-`` and the
    serial, else the model, else the port, else ``any`` (the first camera found); None for the
    simulated camera (one object per process).

    Parameters
    ----------
    job : Job

    Returns
    -------
    str or None
    """
    cam = job["camera"]
    if cam["backend"] == "mock":
        return None
    from hdrcap.pipeline.compat import normalise_model

    if cam.get("serial"):
        return f"gphoto2-serial-{cam['serial']}"
    if cam.get("model"):
        return "gphoto2-model-" + "-".join(normalise_model(cam["model"]) or (cam["model"],))
    return f"gphoto2-port-{cam['port']}" if cam.get("port") else "gphoto2-any"


def check_job_against_camera(job: Job, camera: Camera, echo: Callable[[str], None] | None = None) -> None:
    """Checks that need the camera (still before any frame): exposure times in its range, and
    each time of a fixed bracket one of the camera's (a time that is not is taken at the
    camera's nearest, with a warning; two that would become one are refused).

    Parameters
    ----------
    job : Job
    camera : Camera
    echo : callable, optional
        Where the warnings about snapped times go.

    Raises
    ------
    JobError
        An exposure time (of the bracket or a calibration series) outside the camera's range
        (by more than a third of a stop), a camera without exposure times, or two bracket
        times the camera would take at one time (``repeats`` asks for several frames per time).
    """
    allowed = exposure_ladder(camera)  # timed speeds, and bulb times where the camera has bulb
    if not allowed:
        raise job.error("camera", None, "the camera offers no exposure times")
    lo, hi = min(allowed), max(allowed)
    bad = [t for t in job["exposure"]["times"] if t < lo / 1.26 or t > hi * 1.26]
    for s in job["calibration"]["series"]:
        bad += [t for t in s["times"] if t < lo / 1.26 or t > hi * 1.26]
    if bad:
        raise job.error("exposure", "times", f"exposure {bad[0]:g} s is outside the camera's range {lo:g} .. {hi:g} s")
    if job["exposure"]["mode"] == "bracket":
        _check_snapped_times(job, allowed, echo)


def _check_snapped_times(job: Job, allowed: list[float], echo: Callable[[str], None] | None) -> None:
    """Warn about each bracket time that is not one of the camera's; JobError when two become one."""
    from hdrcap.pipeline.times import ExposureMap, same_exposure

    taken: ExposureMap[float] = ExposureMap()
    for t in job["exposure"]["times"]:
        got = nearest_allowed(t, allowed)
        if got in taken:
            was = taken[got]
            both = f"{t:g} s is given twice" if same_exposure(was, t) else f"{was:g} s and {t:g} s"
            raise job.error(
                "exposure",
                "times",
                f"{both}: the camera takes {'it' if same_exposure(was, t) else 'both'} at {got:g} s; give each "
                "time once (repeats = N takes N frames of every time)",
            )
        taken[got] = t
        if echo is not None and not same_exposure(got, t):
            echo(
                f"hdrcap: warning: {job.where('exposure', 'times')}: exposure.times: {t:g} s is not one of the "
                f"camera's exposure times; taken at its nearest, {got:g} s (the manifest records both)"
            )


def check_free_space(job: Job, camera: Camera, run_dir: Path, repetitions: int = 1) -> dict[str, Any]:
    """The disk space the job's run needs against the room on the run folder's file system
    (still before any frame): the planned frames and outputs (:func:`acquire.capture.session.estimate_run_bytes`).

    A fixed bracket's frames are counted from its plan; a target-SNR plan is known only after
    metering, so its frames are bounded by ``[exposure] max_exposures`` (light frames per
    exposure and its dark frames), and without that limit only one frame and the outputs count.
    Master darks a dark library holds are counted as captured (an upper bound).

    Parameters
    ----------
    job : Job
    camera : Camera
        The open camera (exposure ladder, mosaic size).
    run_dir : Path
        The run folder (need not exist yet; the nearest existing parent is measured).
    repetitions : int
        Runs that will share the file system (``--repeat``).

    Returns
    -------
    dict
        ``frames`` (None when metering decides), ``need_bytes``, ``free_bytes``, ``folder``.

    Raises
    ------
    acquire.capture.session.LocalIOError
        When the free space is short (exit status 6).
    """
    import shutil

    from hdrcap.acquire.capture.session import LocalIOError, estimate_run_bytes

    frames = _planned_frames(job, camera)
    shape = tuple(getattr(camera, "shape", ()) or ()) or None
    need = repetitions * estimate_run_bytes(frames or 1, shape)
    folder = Path(run_dir).absolute()
    while not folder.exists():
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if free < need:
        what = f"the {frames} planned frames and the outputs" if frames else "one frame and the outputs"
        raise LocalIOError(
            f"{folder}: {free / 1e6:.0f} MB free, {what} need about {need / 1e6:.0f} MB"
            + (f" per run x {repetitions}" if repetitions > 1 else "")
            + "; free space first"
        )
    return {"frames": frames, "need_bytes": need, "free_bytes": free, "folder": str(folder)}


def _planned_frames(job: Job, camera: Camera) -> int | None:
    """Frames of one run: counted from a fixed bracket's plan, bounded by ``max_exposures``
    for a target SNR, None when only metering can tell."""
    from hdrcap.acquire.capture.session import CapturePlan

    exp, darks = job["exposure"], job["darks"]
    if exp["mode"] == "bracket":  # master darks of a dark library would only take fewer frames
        plan = CapturePlan.bracket(
            exp["times"],
            exposure_ladder(camera),
            darks["strategy"],
            n_dark=darks["count"],
            repeats=exp["repeats"],
            series=job["calibration"]["series"],
        )
        return len(plan.frames)
    if exp.get("max_exposures"):
        per_dark = {"matched": 1, "master": darks["count"]}.get(darks["strategy"], darks["count"])
        return int(exp["max_exposures"]) * (exp["repeats"] + per_dark)
    return None


def job_calibration(job: Job) -> Calibration:
    """The job's calibration: ``[calibration] file``, else its preset, else (simulated camera)
    the camera's preset.

    Parameters
    ----------
    job : Job

    Returns
    -------
    pipeline.params.Calibration
    """
    from hdrcap.acquire.camera.model import camera_model

    cal = job["calibration"]
    if "file" in cal:
        return camera_model(job.resolve(cal["file"]))
    preset = cal.get("preset") or (job["camera"]["preset"] if job["camera"]["backend"] == "mock" else None)
    return camera_model(camera=preset, temperature=job["camera"].get("temperature"))


def run_iso(job: Job, calibration: Calibration) -> float | None:
    """The run's ISO speed: the job's ``[camera] iso``, else the calibration's, else None (then
    the first frame's ISO is the run's).

    Parameters
    ----------
    job : Job
    calibration : pipeline.params.Calibration

    Returns
    -------
    float or None
    """
    from hdrcap.pipeline.compat import CameraProfile

    if "iso" in job["camera"]:
        return float(job["camera"]["iso"])
    return CameraProfile.from_calibration(calibration).iso


def check_compatibility(
    job: Job, camera: Camera, calibration: Calibration, echo: Callable[[str], None]
) -> CameraProfile:
    """Plan-time check: the calibration must belong to the connected camera (serial, else the
    normalised model) and the run's ISO (:func:`pipeline.compat.check_compatible`); temperature
    differences are warnings. Returns the profile every frame is then checked against.

    Parameters
    ----------
    job : Job
    camera : Camera
    calibration : pipeline.params.Calibration
    echo : callable
        Where warnings go.

    Returns
    -------
    pipeline.compat.CameraProfile
        Model of the camera and the run's ISO.

    Raises
    ------
    pipeline.compat.CompatibilityError
        Calibration of another camera or ISO (exit status 2), before any frame.
    """
    from hdrcap.pipeline.compat import CameraProfile, check_compatible

    cal = job["calibration"]
    what = f"calibration {cal['file']}" if "file" in cal else f"calibration preset {cal.get('preset') or ''}".strip()
    profile = CameraProfile.from_calibration(calibration, what)
    iso = run_iso(job, calibration)
    connected = CameraProfile.from_camera(camera, iso=job["camera"].get("iso"))
    for warning in check_compatible(profile, connected):
        echo(f"hdrcap: warning: {warning}")
    return CameraProfile("the run's camera", connected.model or profile.model, "", iso)
