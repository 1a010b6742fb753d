"""Jobs: a TOML file that describes a measurement end to end (camera, scene or metering,
target SNR or fixed bracket, dark frames, calibration, outputs, repetition), validated before
any frame is taken, and :func:`run_job` that runs it (meter -> plan -> capture -> merge ->
outputs). See docs/acquisition.md for the format.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import re
import sys
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdrcap.acquire.camera import exposure_ladder, nearest_allowed
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.noise import DarkStrategy

__all__ = [
    "Job",
    "JobError",
    "SCHEMA",
    "load_job",
    "job_from_dict",
    "open_camera",
    "run_job",
    "run_schedule",
    "check_job_against_camera",
    "run_folder",
    "resume_folder",
    "run_state",
    "error_summary",
    "notify",
    "NothingToResume",
    "ScheduleError",
]


class JobError(InputError):
    """A bad job file; the message names the file and line."""


# section -> key -> (type(s), description). A key "*" accepts any key (free-form tables).
SCHEMA: dict[str, dict[str, tuple]] = {
    "job": {"name": (str,), "description": (str,)},
    "camera": {
        "backend": (str,),
        "preset": (str,),
        "size": (str,),
        "seed": (int,),
        "temperature": ((int, float),),
        "model": (str,),
        "port": (str,),
        "serial": (str,),
        "enforce": (bool,),
        "delete_after_download": (bool,),
        "iso": (int,),
        "long_exposure_s": ((int, float),),
        "settings": (dict,),
        "faults": (dict,),
        "allowed_times": (list,),
        "bulb_max_s": ((int, float),),
    },
    "scene": {"name": (str,), "decades": ((int, float),), "x_max": ((int, float),)},
    "exposure": {
        "mode": (str,),
        "times": (list,),
        "target_snr_db": ((int, float),),
        "max_exposures": (int,),
        "time_budget_s": ((int, float),),
        "repeats": (int,),
        "quantile": ((int, float),),
    },
    "darks": {
        "strategy": (str,),
        "count": (int,),
        "block_light": (str,),
        "cover_command": (str,),
        "uncover_command": (str,),
        "check": ((int, float),),
    },
    "calibration": {"file": (str,), "preset": (str,), "series": (list,), "dark_library": (str,)},
    "output": {"folder": (str,), "exr": (str,), "png": (str,), "force": (bool,)},
    "schedule": {"repeat": (int,), "every_s": ((int, float),)},
    "notify": {"on_done": (str,), "on_failure": (str,), "timeout_s": ((int, float),)},
    "session": {
        "max_attempts": (int,),
        "backoff_s": ((int, float),),
        "max_backoff_s": ((int, float),),
        "timeout_s": ((int, float),),
    },
}

DEFAULTS: dict[str, dict[str, Any]] = {
    "job": {"name": ""},
    "camera": {
        "backend": "mock",
        "preset": "camera-B",
        "size": "256x192",
        "seed": 0,
        "delete_after_download": True,
        "long_exposure_s": 1.0,
    },
    "scene": {"name": "hdr", "decades": 4.0, "x_max": 2e5},
    "exposure": {"mode": "bracket", "times": [], "repeats": 1},
    "darks": {"strategy": DarkStrategy.MATCHED.value, "count": 1, "block_light": "mock", "check": 0.05},
    "calibration": {"series": []},
    "output": {"folder": "runs/{job}-{date}", "exr": "hdr.exr", "png": "preview.png", "force": False},
    "schedule": {"repeat": 1, "every_s": 0.0},
    "notify": {"timeout_s": 60.0},
    "session": {"max_attempts": 12, "backoff_s": 0.5, "max_backoff_s": 30.0, "timeout_s": 60.0},
}


@dataclass
class Job:
    """A validated job: ``sections[section][key]`` with defaults filled in."""

    sections: dict[str, dict[str, Any]]
    path: Path | None = None
    text: str = ""
    lines: dict[tuple[str, str], int] = field(default_factory=dict)
    given: dict[str, set] = field(default_factory=dict)

    def __getitem__(self, section: str) -> dict[str, Any]:
        return self.sections[section]

    @property
    def name(self) -> str:
        return self.sections["job"].get("name") or (self.path.stem if self.path else "job")

    def where(self, section: str, key: str | None = None) -> str:
        """``file:line`` of a key (or its section) for messages."""
        name = str(self.path) if self.path else "<job>"
        line = self.lines.get((section, key or "")) or self.lines.get((section, ""))
        return f"{name}:{line}" if line else name

    def error(self, section: str, key: str | None, message: str) -> JobError:
        label = f"{section}.{key}" if key else f"[{section}]"
        return JobError(f"{self.where(section, key)}: {label}: {message}")


#: The most frames one run may plan (light and dark frames, or a calibration series): a job
#: beyond it is a typing error (a run of 100 000 frames already takes more than a day at one
#: frame per second), refused when the job is read instead of planned frame by frame.
MAX_FRAMES_PER_RUN = 100_000


def _check_frame_counts(job, exp: dict, darks: dict) -> None:
    """Refuse frame counts no run can take (see :data:`MAX_FRAMES_PER_RUN`), naming the key."""
    limit = MAX_FRAMES_PER_RUN
    for section, key, value in (
        ("exposure", "repeats", exp["repeats"]),
        ("exposure", "max_exposures", exp.get("max_exposures") or 1),
        ("darks", "count", darks["count"]),
    ):
        if value > limit:
            raise job.error(section, key, f"{value} is more frames than a run takes ({limit})")
    per_repeat = len(exp["times"]) if exp["mode"] == "bracket" else (exp.get("max_exposures") or 1)
    light = per_repeat * exp["repeats"]
    if light > limit:
        raise job.error("exposure", "repeats", f"{light} light frames per run, more than a run takes ({limit})")


def _key_lines(text: str) -> dict[tuple[str, str], int]:
    """Line numbers of ``[section]`` headers and ``key =`` lines (first occurrence)."""
    out: dict[tuple[str, str], int] = {}
    section = ""
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if m := re.match(r"^\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?", s):
            section = m.group(1)
            out.setdefault((section, ""), n)
            continue
        if m := re.match(r"^([A-Za-z0-9_\-]+|\"[^\"]+\")\s*(?:\.\s*([A-Za-z0-9_\-]+))?\s*=", s):
            key = m.group(1).strip('"')
            if m.group(2):  # dotted key: camera.preset = ...
                out.setdefault((key, m.group(2)), n)
                out.setdefault((key, ""), n)
            else:
                out.setdefault((section, key), n)
    return out


def load_job(path) -> Job:
    """Read and validate a job file (syntax, keys, types and values that need no camera)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise JobError(f"{path}: no such job file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise JobError(f"{path}: cannot read the job file ({err})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise JobError(f"{path}: not valid TOML: {err}") from None
    return job_from_dict(data, path=path, text=text)


def job_from_dict(data: dict, path: Path | None = None, text: str = "") -> Job:
    """Validate a job given as a dict (``hdrcap capture`` builds one from its options)."""
    job = Job({}, path, text, _key_lines(text))
    for section in data:
        if section not in SCHEMA:
            raise job.error(section, None, f"unknown section; known: {', '.join(SCHEMA)}")
        if not isinstance(data[section], dict):
            raise job.error(section, None, "must be a table")
    for section, schema in SCHEMA.items():
        given = data.get(section, {})
        merged = dict(DEFAULTS.get(section, {}))
        for key, value in given.items():
            if key not in schema:
                raise job.error(section, key, f"unknown key; known: {', '.join(sorted(schema))}")
            types = schema[key][0]
            if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
                raise job.error(section, key, f"expected {_tname(types)}, got {value!r}")
            if not isinstance(value, types):
                raise job.error(section, key, f"expected {_tname(types)}, got {value!r}")
            merged[key] = value
        job.sections[section] = merged
        job.given[section] = set(given)
    _check_values(job)
    return job


def _tname(types) -> str:
    types = types if isinstance(types, tuple) else (types,)
    names = {
        str: "a string",
        int: "an integer",
        float: "a number",
        bool: "true or false",
        list: "a list",
        dict: "a table",
    }
    return " or ".join(names.get(t, t.__name__) for t in types)


def _check_values(job: Job) -> None:
    cam, exp, darks, cal, out = job["camera"], job["exposure"], job["darks"], job["calibration"], job["output"]
    if cam["backend"] not in ("mock", "gphoto2"):
        raise job.error("camera", "backend", f'must be "mock" or "gphoto2", got {cam["backend"]!r}')
    if cam["backend"] == "mock":
        from hdrcap.mock_camera import PRESETS

        if cam["preset"] not in PRESETS:
            raise job.error(
                "camera", "preset", f"unknown simulator preset {cam['preset']!r}; choose from {', '.join(PRESETS)}"
            )
        from hdrcap.mock_camera.scenes import parse_size

        try:
            parse_size(cam["size"])
        except InputError as err:
            raise job.error("camera", "size", str(err)) from None
        try:
            from hdrcap.acquire.camera.mock import MockFaults

            MockFaults.from_dict(cam.get("faults", {}))
        except (TypeError, ValueError) as err:
            raise job.error("camera", "faults", str(err)) from None
        from hdrcap.mock_camera.scenes import SCENES

        scene = job["scene"]["name"]
        if scene not in SCENES and not scene.lower().endswith(".exr"):
            raise job.error("scene", "name", f"unknown scene {scene!r}; choose from {', '.join(SCENES)} or an .exr")
        if cam["seed"] < 0:
            raise job.error("camera", "seed", f"must be >= 0, got {cam['seed']!r}")
        for key in ("decades", "x_max"):
            value = job["scene"][key]
            if not (value > 0 and math.isfinite(value)):
                raise job.error("scene", key, f"must be a positive number, got {value!r}")
        lowest = job["scene"]["x_max"] * 10.0 ** -min(job["scene"]["decades"], 400.0)
        if not lowest > sys.float_info.min:  # the darkest irradiance must be a number, not 0
            raise job.error("scene", "decades", "spans more decades below x_max than a float holds")
    elif "faults" in cam:
        raise job.error("camera", "faults", "fault injection is for the mock camera only")
    if exp["mode"] not in ("bracket", "snr"):
        raise job.error("exposure", "mode", f'must be "bracket" or "snr", got {exp["mode"]!r}')
    for t in exp["times"]:
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (t > 0 and math.isfinite(t)):
            raise job.error("exposure", "times", f"exposure times are positive seconds, got {t!r}")
    if exp["mode"] == "bracket" and not exp["times"]:
        raise job.error("exposure", "times", "a fixed bracket needs times = [...] (seconds)")
    if exp["mode"] == "snr" and "target_snr_db" not in exp:
        raise job.error("exposure", "target_snr_db", 'mode = "snr" needs target_snr_db')
    if exp["repeats"] < 1:
        raise job.error("exposure", "repeats", "must be >= 1")
    if darks["strategy"] not in set(DarkStrategy):
        raise job.error("darks", "strategy", f"must be matched, master or model, got {darks['strategy']!r}")
    if darks["count"] < 1:
        raise job.error("darks", "count", "must be >= 1")
    _check_frame_counts(job, exp, darks)
    if darks["block_light"] not in ("mock", "prompt", "command", "none"):
        raise job.error("darks", "block_light", f"must be mock, prompt, command or none, got {darks['block_light']!r}")
    if darks["block_light"] == "mock" and cam["backend"] != "mock" and darks["strategy"] != DarkStrategy.MODEL:
        raise job.error(
            "darks",
            "block_light",
            "a real camera cannot block its light itself: use prompt, command (cover_command/uncover_command) or none",
        )
    if darks["block_light"] == "command":
        for k in ("cover_command", "uncover_command"):
            if not darks.get(k):
                raise job.error("darks", k, 'block_light = "command" needs cover_command and uncover_command')
    if "file" in cal:
        f = _resolve(job, cal["file"])
        if not f.is_file():
            raise job.error("calibration", "file", f"calibration file {f} does not exist")
    elif "preset" not in cal and cam["backend"] != "mock":
        raise job.error(
            "calibration", None, 'a real camera needs a calibration: file = "calib..." (from `hdrcap calibrate`)'
        )
    if "dark_library" in cal and not _resolve(job, cal["dark_library"]).is_dir():
        raise job.error(
            "calibration", "dark_library", f"dark library folder {_resolve(job, cal['dark_library'])} does not exist"
        )
    for i, s in enumerate(cal["series"]):
        if not isinstance(s, dict) or set(s) - {"kind", "times", "count"} or "kind" not in s or "times" not in s:
            raise job.error("calibration", "series", f"series {i + 1}: needs kind, times (and count), nothing else")
        count, times = s.get("count", 1), s["times"]
        n = count * len(times) if isinstance(count, int) and isinstance(times, list) else 0
        if n > MAX_FRAMES_PER_RUN:
            raise job.error(
                "calibration", "series", f"series {i + 1}: {n} frames, more than a run takes ({MAX_FRAMES_PER_RUN})"
            )
        if s["kind"] not in ("bias", "flat", "saturation", "darkseries"):
            raise job.error(
                "calibration",
                "series",
                f"series {i + 1}: kind must be bias, flat, saturation or darkseries, got {s['kind']!r}",
            )
    for k in ("exr", "png"):
        if out[k] and (Path(out[k]).is_absolute() or ".." in Path(out[k]).parts):
            raise job.error("output", k, "must be a file name inside the run folder")
    try:
        str(out["folder"]).format(job="", n=0, date="")
    except (ValueError, KeyError, IndexError, AttributeError) as err:
        raise job.error(
            "output", "folder", f"not a valid pattern ({type(err).__name__}: {err}); fields: {{job}} {{n}} {{date}}"
        ) from None
    _check_writable(job, out["folder"])
    sched = job["schedule"]
    if sched["repeat"] < 1 or sched["every_s"] < 0:
        raise job.error("schedule", "repeat" if sched["repeat"] < 1 else "every_s", "must be >= 1 / >= 0")
    if not job["notify"]["timeout_s"] > 0:
        raise job.error("notify", "timeout_s", "must be > 0 seconds")


def _resolve(job: Job, name: str) -> Path:
    p = Path(os.path.expanduser(name))
    if not p.is_absolute() and job.path is not None:
        p = job.path.parent / p
    return p


def _check_writable(job: Job, folder: str) -> None:
    p = _resolve(job, folder.split("{")[0] or ".")
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and (not probe.is_dir() or not os.access(probe, os.W_OK)):
        raise job.error("output", "folder", f"{probe} is not a writable folder")


def run_folder(job: Job, n: int = 0, resume: bool = False) -> Path:
    """The run folder of repetition ``n`` (``{job}``, ``{n}``, ``{date}`` are filled in).

    A new run with ``{date}`` in the pattern gets a folder that does not exist yet: when the
    name is taken (two starts within one second, as ``--repeat N`` does), the date gets a
    suffix ``-2``, ``-3``, ... (two processes racing for one name collide on the run folder's
    lock and the second stops with exit status 5). With ``resume`` the
    folder of the newest incomplete run, else of the newest complete one (:func:`resume_folder`).

    Parameters
    ----------
    job : Job
    n : int
        Repetition number (0-based).
    resume : bool
        Find the run to continue instead of a new folder.

    Returns
    -------
    Path
        The run folder.
    """
    pattern = job["output"]["folder"]
    base = str(_resolve(job, pattern))
    if resume:
        found = resume_folder(job, n)
        if found is None:
            raise NothingToResume(
                f"{job.where('output', 'folder')}: --resume: no earlier run folder matches "
                f"{base.format(job=job.name, n=n, date='*')}"
            )
        return found
    if "{date}" not in pattern:
        return Path(base.format(job=job.name, n=n, date=""))
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    for k in range(1, 10000):
        folder = Path(base.format(job=job.name, n=n, date=stamp if k == 1 else f"{stamp}-{k}"))
        if not folder.exists():
            return folder
    raise JobError(f"{job.where('output', 'folder')}: no free run folder name for {base}")


class NothingToResume(JobError):
    """``--resume`` found no earlier run of the job (a no-op for ``hdrcap run``)."""


def resume_folder(job: Job, n: int = 0) -> Path | None:
    """The run folder ``--resume`` continues: the newest run of the job whose manifest has no
    ``complete`` record (or that was stopped while metering: ``meter/`` but no manifest), else
    the newest complete one (resuming it re-reports its summary), else None. Newest by the
    start time in the manifest header, then by the folder's modification time.

    Parameters
    ----------
    job : Job
    n : int
        Repetition number filled into ``{n}``.

    Returns
    -------
    Path or None
    """
    glob = str(_resolve(job, job["output"]["folder"])).format(job=job.name, n=n, date="*")
    root = Path("/") if glob.startswith("/") else Path(".")
    found = [f for f in root.glob(glob.lstrip("/")) if (f / "manifest.jsonl").is_file() or (f / "meter").is_dir()]
    if not found:
        return None
    states = {f: run_state(job, f) for f in found}
    for wanted in ("incomplete", "complete"):
        runs = [f for f in found if states[f][0] == wanted]
        if runs:
            return max(runs, key=lambda f: (states[f][1], f.stat().st_mtime, str(f)))
    return None


def run_state(job: Job, run_dir: Path) -> tuple[str, str]:
    """(``"complete"`` or ``"incomplete"``, start time) of the run in ``run_dir``. Complete: the
    manifest has a ``complete`` record, or (runs recorded before it existed) every planned
    frame is recorded and the job's EXR output exists."""
    from hdrcap.acquire.capture.manifest import Manifest

    m = Manifest(run_dir)
    head = m.header() or {}
    started = str(head.get("time") or _dt.datetime.fromtimestamp(run_dir.stat().st_mtime, _dt.UTC).isoformat())
    if m.completion() is not None:
        return "complete", started
    planned = {f["key"] for f in head.get("plan", {}).get("frames", [])}
    exr = job["output"]["exr"]
    if planned and planned <= set(m.frames()) and exr and (run_dir / exr).is_file():
        return "complete", started
    return "incomplete", started


# --------------------------------------------------------------------------- camera and checks
def open_camera(job: Job, n: int = 0):
    """The job's camera (for the mock backend: with the job's scene; seed + n per repetition)."""
    cam = job["camera"]
    if cam["backend"] == "mock":
        from hdrcap.acquire.camera.mock import MockCamera, MockFaults
        from hdrcap.mock_camera.scenes import load_scene, parse_size

        sc = job["scene"]
        shape = parse_size(cam["size"])
        scene = load_scene(_scene_path(job, sc["name"]), shape, sc["decades"], sc["x_max"])
        camera = MockCamera(
            cam["preset"],
            scene,
            seed=cam["seed"] + n,
            allowed_times=cam.get("allowed_times"),
            bulb_max_s=cam.get("bulb_max_s"),
            faults=MockFaults.from_dict(cam.get("faults", {})),
            temperature=cam.get("temperature"),
        )
        try:
            return _apply_iso(job, camera)
        except BaseException:
            camera.close()
            raise
    from hdrcap.acquire.camera.gphoto2 import Gphoto2Camera

    camera = Gphoto2Camera(
        cam.get("model"),
        cam.get("port"),
        serial=cam.get("serial"),
        delete_after_download=cam["delete_after_download"],
        long_exposure_s=cam["long_exposure_s"],
        settings=cam.get("settings"),
    )
    try:
        _apply_iso(job, camera)
        camera.preflight(enforce=cam.get("enforce", False), iso=cam.get("iso"))  # changes nothing unless enforce
    except BaseException:
        camera.close()
        raise
    return camera


def _apply_iso(job: Job, camera):
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


def _scene_path(job: Job, name: str) -> str:
    return str(_resolve(job, name)) if name.lower().endswith(".exr") else name


def check_job_against_camera(job: Job, camera) -> None:
    """Checks that need the camera (still before any frame): exposure times in its range."""
    allowed = exposure_ladder(camera)  # timed speeds, and bulb times where the camera has bulb
    if not allowed:
        raise job.error("camera", None, "the camera offers no exposure times")
    lo, hi = min(allowed), max(allowed)
    bad = [t for t in job["exposure"]["times"] if t < lo / 1.26 or t > hi * 1.26]
    for s in job["calibration"]["series"]:
        bad += [t for t in s["times"] if t < lo / 1.26 or t > hi * 1.26]
    if bad:
        raise job.error("exposure", "times", f"exposure {bad[0]:g} s is outside the camera's range {lo:g} .. {hi:g} s")


def check_free_space(job: Job, camera, run_dir: Path, repetitions: int = 1) -> dict:
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

    from hdrcap.acquire.capture.session import CapturePlan, LocalIOError, estimate_run_bytes

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
        frames: int | None = len(plan.frames)
    elif exp.get("max_exposures"):
        per_dark = {"matched": 1, "master": darks["count"]}.get(darks.get("strategy"), darks["count"])
        frames = int(exp["max_exposures"]) * (exp["repeats"] + per_dark)
    else:
        frames = None
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


def job_calibration(job: Job):
    from hdrcap.acquire.camera.model import camera_model

    cal = job["calibration"]
    if "file" in cal:
        return camera_model(_resolve(job, cal["file"]))
    preset = cal.get("preset") or (job["camera"]["preset"] if job["camera"]["backend"] == "mock" else None)
    return camera_model(camera=preset, temperature=job["camera"].get("temperature"))


# --------------------------------------------------------------------------- planning
def plan_for(job: Job, camera, calibration, run_dir: Path, echo: Callable[[str], None], retry=None, stop=None):
    """The capture plan: a fixed bracket, or meter + planner for a target SNR.

    The planner's dark strategy per exposure is kept (unless the job sets ``[darks] strategy``):
    dark frames are captured only for matched and master exposures, and not for master
    exposures whose master dark the dark library holds. ``info`` (recorded in the manifest)
    carries the planner's decisions and merge options for the merge and the EXR header."""
    from hdrcap.acquire.capture.session import CapturePlan

    exp, darks = job["exposure"], job["darks"]
    allowed = exposure_ladder(camera)
    times = list(exp["times"])
    strategy: str | list[str] = darks["strategy"]
    info: dict[str, Any] = {"mode": exp["mode"]}
    if exp["mode"] == "snr":
        from hdrcap import planner

        irradiance = planner.meter(_meter_fn(camera, run_dir, retry, stop), calibration, allowed)
        root = _library_root(job, calibration)
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
        times = list(plan.exposures)
        info.update(
            planner=True,
            predicted_min_snr_db=plan.predicted_min_snr_db,
            feasible=plan.feasible,
            message=plan.message,
            plan=_plan_record(plan),
        )
        if plan.darks:
            if "strategy" not in job.given.get("darks", ()):
                strategy = list(plan.darks)
            elif set(plan.darks) != {strategy}:
                info["plan_overridden"] = {"darks": {"plan": list(plan.darks), "used": strategy}}
        echo(f"plan: {plan.message}")
    snapped = [nearest_allowed(t, allowed) for t in times]
    per = [strategy] * len(snapped) if isinstance(strategy, str) else strategy
    master_times = [t for t, s in zip(snapped, per) if s == DarkStrategy.MASTER]
    masters = (
        library_masters(
            _library_root(job, calibration),
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
        snapped,
        allowed,
        strategy,
        n_dark=darks["count"],
        repeats=exp["repeats"],
        series=job["calibration"]["series"],
        library_times=list(masters),
    )
    return plan, info


def _plan_record(plan) -> dict:
    """What the manifest keeps of a planner's plan (JSON): the plan without its SNR curve, and
    the merge options that follow its decisions."""
    d = plan.to_dict()
    d.pop("curve", None)
    d.setdefault("merge_options", plan.merge_options())
    return _json_safe(d)


def _json_safe(obj):
    import json

    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def _library_root(job: Job, calibration) -> str | None:
    if "dark_library" in job["calibration"]:
        return str(_resolve(job, job["calibration"]["dark_library"]))
    return getattr(calibration, "dark_library", None)


def library_masters(
    root,
    camera,
    times,
    load: bool = True,
    iso: float | None = None,
    strict: bool = False,
    echo: Callable[[str], None] | None = None,
) -> dict[float, tuple]:
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
    times : iterable of float
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
    from hdrcap.pipeline.times import same_exposure

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
        for t in times:
            at_t = [e for e in mine if same_exposure(e.exposure_time, t)]
            if at_t and all(e.iso is not None and abs(e.iso - iso) > 0.5 for e in at_t):
                isos = ", ".join(sorted({f"{e.iso:g}" for e in at_t}))
                raise CompatibilityError(
                    f"dark library {root}: the master darks for {t:g} s are at ISO {isos}, "
                    f"the run is at ISO {iso:g}; add masters at ISO {iso:g} or use "
                    '[darks] strategy = "matched"'
                )
    name = Counter(e.camera for e in mine).most_common(1)[0][0]
    temp = camera.temperature() if hasattr(camera, "temperature") else None
    found = lib.masters(times, camera=name, iso=iso, temperature=temp, load=load)
    if echo is not None and temp is None and any(e.temperature is not None for _d, _n, e in found.values()):
        echo(
            "hdrcap: warning: the camera reports no temperature; master darks of the dark library are matched at "
            "any temperature (their dark current may differ)"
        )
    return {t: (data, n) for t, (data, n, _e) in found.items()}


def run_iso(job: Job, calibration) -> float | None:
    """The run's ISO speed: the job's ``[camera] iso``, else the calibration's, else None (then
    the first frame's ISO is the run's)."""
    from hdrcap.pipeline.compat import CameraProfile

    if "iso" in job["camera"]:
        return float(job["camera"]["iso"])
    return CameraProfile.from_calibration(calibration).iso


def check_compatibility(job: Job, camera, calibration, echo: Callable[[str], None]):
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


def _meter_fn(camera, run_dir: Path, retry=None, stop=None, sleep=time.sleep):
    """``capture_fn(t)`` for :func:`planner.meter`: one metering frame into ``RUN/meter/``, with
    the session's retries (busy: wait; disconnect or hang: reconnect; a bad file: capture again).
    Files of an earlier, interrupted metering stay; new ones never reuse their names."""
    from hdrcap.acquire.camera import fault_kind
    from hdrcap.acquire.capture.session import RetryPolicy, SessionError
    from hdrcap.pipeline.io.raw import read_frame

    retry = retry or RetryPolicy()
    meter_dir = run_dir / "meter"
    meter_dir.mkdir(parents=True, exist_ok=True)
    counter = [0]

    def capture(t: float):
        counter[0] += 1
        last = None
        for attempt in range(1, retry.max_attempts + 1):
            if stop is not None and stop.is_set():
                from hdrcap.acquire.capture.session import RunInterrupted

                raise RunInterrupted(
                    f"{run_dir}: stopped by signal {stop.signum} while metering; run again with --resume", stop.signum
                )
            dest = _free_name(meter_dir, f"meter_{counter[0]:02d}_{t:.6g}s", ".dng")
            try:
                applied = float(camera.set_exposure(t))
                timeout = None if retry.timeout_s is None else applied + retry.timeout_s
                res = camera.capture(dest, timeout=timeout)
                try:
                    return read_frame(res.path).data
                except (InputError, ValueError) as err:
                    from hdrcap.acquire.camera import CorruptFrameError

                    raise CorruptFrameError(f"metering frame {Path(res.path).name}: {err}") from None
            except Exception as err:
                kind = fault_kind(err)
                if kind is None or kind == "fatal":
                    raise
                last = err
                if attempt == retry.max_attempts:
                    break
                if kind in ("busy", "reconnect"):
                    sleep(retry.wait(attempt))
                if kind == "reconnect":
                    _reconnect_quietly(camera)
        raise SessionError(
            f"metering at {t:g} s: gave up after {retry.max_attempts} attempts (last: {last}); run again with --resume"
        )

    return capture


def _reconnect_quietly(camera) -> None:
    """Reconnect after a metering fault; a failed reconnect is one more fault for the retry loop
    (a fatal one stops)."""
    from hdrcap.acquire.camera import fault_kind

    try:
        camera.reconnect()
    except Exception as err:
        if fault_kind(err) in (None, "fatal"):
            raise


def _free_name(folder: Path, stem: str, suffix: str) -> Path:
    """``folder/stem+suffix``, or ``stem.2+suffix``, ... : the first name that does not exist."""
    path = folder / f"{stem}{suffix}"
    k = 1
    while path.exists():
        k += 1
        path = folder / f"{stem}.{k}{suffix}"
    return path


# --------------------------------------------------------------------------- running
def run_job(
    job: Job,
    *,
    resume: bool = False,
    n: int = 0,
    run_dir: Path | None = None,
    progress: bool | None = None,
    echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr),
    camera=None,
    force: bool = False,
    exr_path: Path | None = None,
    png_path: Path | None = None,
    return_result: bool = False,
    stop=None,
):
    """Run one repetition of ``job``.

    With ``resume`` the newest incomplete run of the job is continued; on a complete run
    nothing is done and its recorded summary is returned (``status`` ``"already_complete"``),
    with no run at all ``status`` is ``"nothing_to_resume"``.

    Parameters
    ----------
    job : Job
    resume : bool
        Continue an interrupted run (see :func:`resume_folder`).
    n : int
        Repetition number (seed offset of the simulated camera, ``{n}`` of the folder).
    run_dir : Path, optional
        The run folder (default: the job's ``[output] folder``).
    camera : Camera, optional
        An open camera (default: :func:`open_camera`, closed at the end).
    exr_path, png_path : Path, optional
        Override the job's outputs (which lie inside the run folder).
    return_result : bool
        Also return the :class:`acquire.capture.session.SessionResult` (None for a no-op).
    stop : threading.Event, optional
        Ends the capture cleanly when set (:func:`acquire.capture.session.stop_on_signals`).

    Returns
    -------
    dict
        Summary: ``status``, run folder, frames, captured/resumed/adopted counts, retries,
        outputs (and the SessionResult when ``return_result``).

    Raises
    ------
    HdrcapError
        With the exit status of what stopped the run; ``err.run_dir`` names the run folder.
    """
    from hdrcap.acquire.capture.manifest import Manifest
    from hdrcap.acquire.capture.session import LocalIOError
    from hdrcap.pipeline.errors import HdrcapError

    try:
        run_dir = Path(run_dir) if run_dir else run_folder(job, n, resume)
    except NothingToResume as err:
        echo(f"hdrcap: {err}; nothing to do")
        summary = {"status": "nothing_to_resume", "run_dir": None, "message": str(err)}
        return (summary, None) if return_result else summary
    if resume and Manifest(run_dir).exists() and run_state(job, run_dir)[0] == "complete":
        done = Manifest(run_dir).completion()
        summary = dict(done["summary"]) if done else {"run_dir": str(run_dir)}
        summary["status"] = "already_complete"
        echo(f"hdrcap: {run_dir}: the run is complete; nothing to resume")
        return (summary, None) if return_result else summary
    from hdrcap.acquire.capture.session import hold_run_locks

    try:
        with hold_run_locks(run_dir, job_camera_key(job) if camera is None else None):
            summary, result = _run_one(job, resume, n, run_dir, progress, echo, camera, force, exr_path, png_path, stop)
    except HdrcapError as err:
        err.run_dir = str(run_dir)
        raise
    except OSError as err:  # our side outside the session: metering files, outputs, disk full
        stop_err = LocalIOError(
            f"{err.filename or run_dir}: {err.strerror or err}; free space or fix permissions, "
            "then run again with --resume"
        )
        stop_err.run_dir = str(run_dir)
        raise stop_err from None
    try:
        Manifest(run_dir).append(
            {"type": "complete", "time": _dt.datetime.now(_dt.UTC).isoformat(), "summary": _json_safe(summary)}
        )
    except OSError as err:
        echo(f"hdrcap: warning: {run_dir}: could not record the run as complete ({err.strerror or err})")
    return (summary, result) if return_result else summary


def _run_one(
    job: Job, resume: bool, n: int, run_dir: Path, progress, echo, camera, force, exr_path, png_path, stop
) -> tuple[dict, Any]:
    """Open the camera, plan (or read the plan of the run resumed), capture, merge and write the
    outputs; returns (summary, SessionResult)."""
    from hdrcap.acquire.capture.manifest import Manifest
    from hdrcap.acquire.capture.session import CapturePlan, CaptureSession, LightBlocker, RetryPolicy, RunConflictError
    from hdrcap.pipeline.errors import OutputExistsError

    own = camera is None
    camera = camera or open_camera(job, n)
    try:
        check_job_against_camera(job, camera)
        calibration = job_calibration(job)
        expect = check_compatibility(job, camera, calibration, echo)
        sess = job["session"]
        retry = RetryPolicy(sess["max_attempts"], sess["backoff_s"], sess["max_backoff_s"], sess["timeout_s"])
        force = force or job["output"]["force"]
        if exr_path is None and job["output"]["exr"]:
            exr_path = run_dir / job["output"]["exr"]
        if png_path is None and job["output"]["png"]:
            png_path = run_dir / job["output"]["png"]
        if not resume and Manifest(run_dir).exists():
            raise RunConflictError(
                f"{run_dir}: holds an earlier run (manifest.jsonl); use --resume to continue it "
                "or choose another run folder"
            )
        for p in (exr_path, png_path):
            if p is not None and p.exists() and not force:
                raise OutputExistsError(f"{p}: exists; use --force to overwrite (or another run folder)")
        head = Manifest(run_dir).header() if resume else None
        masters = None
        if head is not None:  # resume: the plan recorded at the start, not a new one
            pd = head["plan"]
            plan = CapturePlan.from_dict(pd)
            info = head.get("planning", {})
        else:
            if resume and Manifest(run_dir).exists() is False and run_dir.exists():
                echo(f"hdrcap: {run_dir}: stopped before its plan was recorded; starting the run again")
            plan, info = plan_for(job, camera, calibration, run_dir, echo, retry, stop)
        if plan.library_times:
            masters = library_masters(
                _library_root(job, calibration), camera, plan.library_times, iso=run_iso(job, calibration), strict=True
            )
        d = job["darks"]
        light = LightBlocker(d["block_light"], d.get("cover_command"), d.get("uncover_command"))
        meta = {
            "job": str(job.path) if job.path else None,
            "job_name": job.name,
            "repetition": n,
            "planning": info,
            "calibration": calibration.provenance,
        }
        planned = info.get("plan") or {}
        options = _plan_merge_options(planned)
        session = CaptureSession(
            camera,
            run_dir,
            plan,
            calibration=calibration,
            light=light,
            retry=retry,
            resume=resume,
            progress=progress,
            meta=meta,
            check_dark=d["check"],
            master_darks=masters,
            merge_options=options,
            stop=stop,
            expect=expect,
        )
        result = session.run()
        header = None
        if planned:
            from hdrcap.pipeline.planfile import planner_attribute

            header = planner_attribute(
                planned, None, None, options, info.get("plan_overridden"), source="hdrcap run (planned from metering)"
            )
        outputs = _write_outputs(job, run_dir, result, calibration, camera, exr_path, png_path, force, header)
    finally:
        if own:
            try:
                camera.close()
            except Exception:
                pass
    summary = {
        "status": "done",
        "run_dir": str(run_dir),
        "frames": len(result.frames),
        "captured": result.captured,
        "resumed": result.resumed,
        "adopted": result.adopted,
        "retries": result.retries,
        "elapsed_s": round(result.elapsed_s, 3),
        "streamed_merge": result.merge is not None,
        **outputs,
    }
    return summary, result


def _plan_merge_options(planned: dict) -> dict:
    """The merge options the planner decided (recorded in the manifest's planning record)."""
    if not planned:
        return {}
    from hdrcap.pipeline.planfile import PLAN_OPTIONS, check_plan

    decided = check_plan(planned, "planner").merge_options()
    return {k: v for k, v in decided.items() if k in PLAN_OPTIONS}


def _write_outputs(
    job: Job, run_dir: Path, result, calibration, camera, exr_path, png_path, force, planner_header: dict | None = None
) -> dict:
    """The run's outputs: the merge's EXR (the one header builder and writer every door uses),
    the preview PNG, and the error against the truth when the camera is simulated."""
    from hdrcap.pipeline.header import with_merge_header
    from hdrcap.pipeline.io.raw import RawFrame
    from hdrcap.pipeline.io.results import write_result
    from hdrcap.pipeline.preview import write_preview_png

    out: dict[str, Any] = {}
    merge = result.merge
    if merge is None:
        return out
    lights = sorted((r for r in result.frames.values() if r["kind"] == "light"), key=lambda r: r["index"])
    cfa = getattr(getattr(camera, "spec", None), "cfa", None)
    # the files by their path (the colour metadata is read from the first one); the header lists
    # them relative to the run folder, as the manifest does
    frames = [
        RawFrame(data=None, exposure_time=r["file_exposure_s"], path=str(run_dir / r["file"]), cfa_pattern=cfa)
        for r in lights
    ]
    run = {
        "run_dir": str(run_dir),
        "job": job.name,
        "camera": lights[0]["camera"] if lights else {},
        "manifest": "manifest.jsonl",
    }
    merge = with_merge_header(
        merge, frames, calibration, source_files=[r["file"] for r in lights], run=run, planner=planner_header
    )
    if exr_path is not None:
        write_result(merge, exr_path, format="exr", force=force)
        out["exr"] = str(exr_path)
    if png_path is not None:
        write_preview_png(png_path, merge.irradiance, cfa, force=force)
        out["png"] = str(png_path)
    truth = getattr(getattr(camera, "sim", None), "scene", None)
    if truth is not None:  # the simulator knows the truth: report the error against it
        from hdrcap.pipeline.evaluation import error_against_truth

        out["error_vs_truth"] = error_against_truth(merge.irradiance, merge.sigma, merge.nexp, truth)
    return out


def run_schedule(
    job: Job,
    *,
    repeat: int | None = None,
    every_s: float | None = None,
    resume: bool = False,
    progress: bool | None = None,
    echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr),
    run_dir: Path | None = None,
    force: bool = False,
    sleep=time.sleep,
    keep_going: bool = False,
    on_result: Callable[[dict], None] | None = None,
    stop=None,
) -> list[dict]:
    """Run the job ``repeat`` times, starting one every ``every_s`` seconds (a slow run delays
    the next start rather than overlapping it).

    Parameters
    ----------
    job : Job
    repeat : int, optional
        Repetitions (default: the job's ``[schedule] repeat``).
    every_s : float, optional
        Seconds between starts (default: the job's ``[schedule] every_s``).
    resume : bool
        Each repetition continues its newest incomplete run (see :func:`run_job`).
    run_dir : Path, optional
        Folder pattern overriding ``[output] folder`` (needs ``{n}`` with ``repeat > 1``).
    keep_going : bool
        A failed repetition is reported (``status`` ``"failed"``) and the schedule goes on;
        at the end :class:`ScheduleError` carries the first failure's exit status.
    on_result : callable, optional
        Called with each repetition's summary (or error summary, :func:`error_summary`) as it ends.
    stop : threading.Event, optional
        Set by SIGTERM/SIGINT: the running repetition ends cleanly and no further one starts.

    Returns
    -------
    list of dict
        The summaries, in order.

    Raises
    ------
    HdrcapError
        The first failure (without ``keep_going``), or :class:`ScheduleError`.
    """
    from hdrcap.acquire.capture.session import RunInterrupted
    from hdrcap.pipeline.errors import HdrcapError

    repeat = repeat if repeat is not None else job["schedule"]["repeat"]
    every_s = every_s if every_s is not None else job["schedule"]["every_s"]
    if repeat > 1 and run_dir is not None and "{n" not in str(run_dir):
        raise JobError("--run-dir with --repeat needs {n} in the folder name")
    wait = stop.wait if stop is not None and sleep is time.sleep else sleep
    t0 = time.monotonic()
    results: list[dict] = []
    failures: list[HdrcapError] = []
    for n in range(repeat):
        delay = t0 + n * every_s - time.monotonic()
        if delay > 0:
            wait(delay)
        if stop is not None and stop.is_set():
            raise RunInterrupted(f"stopped by signal {stop.signum} before repetition {n + 1} of {repeat}", stop.signum)
        rd = Path(str(run_dir).format(n=n, job=job.name)) if run_dir else None
        try:
            res = run_job(job, resume=resume, n=n, run_dir=rd, progress=progress, echo=echo, force=force, stop=stop)
        except HdrcapError as err:
            err.repetition = n
            res = error_summary(err, n)
            notify(job, res, echo)
            if on_result is not None and keep_going:
                on_result(res)
            if not keep_going or isinstance(err, RunInterrupted):
                raise
            failures.append(err)
            results.append(res)
            continue
        res["repetition"] = n
        notify(job, res, echo)
        results.append(res)
        if on_result is not None:
            on_result(res)
    if failures:
        raise ScheduleError(
            f"{len(failures)} of {repeat} repetitions failed (first: {failures[0]})", failures[0].exit_code
        )
    return results


class ScheduleError(JobError):
    """Some repetitions of a ``--keep-going`` schedule failed (each already reported); the exit
    status is the first failure's."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code
        self.reported = True


def error_summary(err: BaseException, n: int | None = None) -> dict:
    """The JSON error object of a failed run: ``status`` ``"failed"``, ``error`` (the one-line
    message), ``exit_code``, ``error_type``, ``run_dir`` (when known) and ``repetition``.

    Parameters
    ----------
    err : BaseException
        What stopped the run.
    n : int, optional
        Repetition number.

    Returns
    -------
    dict
    """
    out = {
        "status": "failed",
        "error": str(err),
        "exit_code": int(getattr(err, "exit_code", 70)),
        "error_type": type(err).__name__,
        "run_dir": getattr(err, "run_dir", None),
    }
    n = n if n is not None else getattr(err, "repetition", None)
    if n is not None:
        out["repetition"] = n
    return out


def notify(job: Job, summary: dict, echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr)) -> None:
    """Run the job's notification hook: ``[notify] on_done`` after a run that ended well (also a
    no-op resume), ``on_failure`` after one that failed. The command runs with the shell, the
    summary as JSON on its stdin and ``HDRCAP_STATUS``, ``HDRCAP_EXIT_CODE``, ``HDRCAP_RUN_DIR``,
    ``HDRCAP_JOB`` and ``HDRCAP_MESSAGE`` in its environment; a hook that fails or outlasts
    ``timeout_s`` is reported as a warning and changes nothing else.

    Parameters
    ----------
    job : Job
    summary : dict
        The run's summary (:func:`run_job`) or error summary (:func:`error_summary`).
    echo : callable
        Where warnings go.
    """
    import json
    import subprocess

    hooks = job["notify"]
    failed = summary.get("status") == "failed"
    cmd = hooks.get("on_failure" if failed else "on_done")
    if not cmd:
        return
    env = dict(
        os.environ,
        HDRCAP_STATUS=str(summary.get("status", "")),
        HDRCAP_JOB=job.name,
        HDRCAP_EXIT_CODE=str(summary.get("exit_code", 0)),
        HDRCAP_RUN_DIR=str(summary.get("run_dir") or ""),
        HDRCAP_MESSAGE=str(summary.get("error") or summary.get("message") or ""),
    )
    try:
        proc = subprocess.run(
            cmd,
            shell=True,
            input=json.dumps(_json_safe(summary)),
            text=True,
            env=env,
            capture_output=True,
            timeout=hooks["timeout_s"],
        )
    except subprocess.TimeoutExpired:
        echo(f"hdrcap: warning: notification hook {cmd!r} took longer than {hooks['timeout_s']:g} s; stopped")
        return
    except OSError as err:
        echo(f"hdrcap: warning: notification hook {cmd!r} could not run: {err}")
        return
    if proc.returncode != 0:
        echo(f"hdrcap: warning: notification hook {cmd!r} failed (exit {proc.returncode}): {proc.stderr.strip()[:200]}")
