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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.noise import DarkStrategy

from .camera import exposure_ladder, nearest_allowed

__all__ = ["Job", "JobError", "SCHEMA", "load_job", "job_from_dict", "open_camera", "run_job", "run_schedule",
           "check_job_against_camera"]


class JobError(InputError):
    """A bad job file; the message names the file and line."""


# section -> key -> (type(s), description). A key "*" accepts any key (free-form tables).
SCHEMA: dict[str, dict[str, tuple]] = {
    "job": {"name": (str,), "description": (str,)},
    "camera": {
        "backend": (str,), "preset": (str,), "size": (str,), "seed": (int,), "temperature": ((int, float),),
        "model": (str,), "port": (str,), "serial": (str,), "enforce": (bool,), "delete_after_download": (bool,),
        "iso": (int,),
        "long_exposure_s": ((int, float),), "settings": (dict,), "faults": (dict,),
        "allowed_times": (list,), "bulb_max_s": ((int, float),),
    },
    "scene": {"name": (str,), "decades": ((int, float),), "x_max": ((int, float),)},
    "exposure": {
        "mode": (str,), "times": (list,), "target_snr_db": ((int, float),), "max_exposures": (int,),
        "time_budget_s": ((int, float),), "repeats": (int,), "quantile": ((int, float),),
    },
    "darks": {"strategy": (str,), "count": (int,), "block_light": (str,), "cover_command": (str,),
              "uncover_command": (str,), "check": ((int, float),)},
    "calibration": {"file": (str,), "preset": (str,), "series": (list,), "dark_library": (str,)},
    "output": {"folder": (str,), "exr": (str,), "png": (str,), "force": (bool,)},
    "schedule": {"repeat": (int,), "every_s": ((int, float),)},
    "session": {"max_attempts": (int,), "backoff_s": ((int, float),), "max_backoff_s": ((int, float),),
                "timeout_s": ((int, float),)},
}

DEFAULTS: dict[str, dict[str, Any]] = {
    "job": {"name": ""},
    "camera": {"backend": "mock", "preset": "camera-B", "size": "256x192", "seed": 0, "delete_after_download": True,
               "long_exposure_s": 1.0},
    "scene": {"name": "hdr", "decades": 4.0, "x_max": 2e5},
    "exposure": {"mode": "bracket", "times": [], "repeats": 1},
    "darks": {"strategy": DarkStrategy.MATCHED.value, "count": 1, "block_light": "mock", "check": 0.05},
    "calibration": {"series": []},
    "output": {"folder": "runs/{job}-{date}", "exr": "hdr.exr", "png": "preview.png", "force": False},
    "schedule": {"repeat": 1, "every_s": 0.0},
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
    names = {str: "a string", int: "an integer", float: "a number", bool: "true or false", list: "a list",
             dict: "a table"}
    return " or ".join(names.get(t, t.__name__) for t in types)


def _check_values(job: Job) -> None:
    cam, exp, darks, cal, out = job["camera"], job["exposure"], job["darks"], job["calibration"], job["output"]
    if cam["backend"] not in ("mock", "gphoto2"):
        raise job.error("camera", "backend", f"must be \"mock\" or \"gphoto2\", got {cam['backend']!r}")
    if cam["backend"] == "mock":
        from hdrcap.mock_camera import PRESETS

        if cam["preset"] not in PRESETS:
            raise job.error("camera", "preset", f"unknown simulator preset {cam['preset']!r}; choose from "
                                               f"{', '.join(PRESETS)}")
        from hdrcap.mock_camera.scenes import parse_size

        try:
            parse_size(cam["size"])
        except InputError as err:
            raise job.error("camera", "size", str(err)) from None
        try:
            from hdrcap.mock_camera.camera import MockFaults

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
    elif "faults" in cam:
        raise job.error("camera", "faults", "fault injection is for the mock camera only")
    if exp["mode"] not in ("bracket", "snr"):
        raise job.error("exposure", "mode", f"must be \"bracket\" or \"snr\", got {exp['mode']!r}")
    for t in exp["times"]:
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (t > 0 and math.isfinite(t)):
            raise job.error("exposure", "times", f"exposure times are positive seconds, got {t!r}")
    if exp["mode"] == "bracket" and not exp["times"]:
        raise job.error("exposure", "times", "a fixed bracket needs times = [...] (seconds)")
    if exp["mode"] == "snr" and "target_snr_db" not in exp:
        raise job.error("exposure", "target_snr_db", "mode = \"snr\" needs target_snr_db")
    if exp["repeats"] < 1:
        raise job.error("exposure", "repeats", "must be >= 1")
    if darks["strategy"] not in set(DarkStrategy):
        raise job.error("darks", "strategy", f"must be matched, master or model, got {darks['strategy']!r}")
    if darks["count"] < 1:
        raise job.error("darks", "count", "must be >= 1")
    if darks["block_light"] not in ("mock", "prompt", "command", "none"):
        raise job.error("darks", "block_light", f"must be mock, prompt, command or none, got {darks['block_light']!r}")
    if darks["block_light"] == "mock" and cam["backend"] != "mock" and darks["strategy"] != DarkStrategy.MODEL:
        raise job.error("darks", "block_light", "a real camera cannot block its light itself: use prompt, "
                                                "command (cover_command/uncover_command) or none")
    if darks["block_light"] == "command":
        for k in ("cover_command", "uncover_command"):
            if not darks.get(k):
                raise job.error("darks", k, "block_light = \"command\" needs cover_command and uncover_command")
    if "file" in cal:
        f = _resolve(job, cal["file"])
        if not f.is_file():
            raise job.error("calibration", "file", f"calibration file {f} does not exist")
    elif "preset" not in cal and cam["backend"] != "mock":
        raise job.error("calibration", None, "a real camera needs a calibration: file = \"calib...\" "
                                             "(from `hdrcap calibrate`)")
    if "dark_library" in cal and not _resolve(job, cal["dark_library"]).is_dir():
        raise job.error("calibration", "dark_library", f"dark library folder {_resolve(job, cal['dark_library'])} "
                                                       "does not exist")
    for i, s in enumerate(cal["series"]):
        if not isinstance(s, dict) or set(s) - {"kind", "times", "count"} or "kind" not in s or "times" not in s:
            raise job.error("calibration", "series", f"series {i + 1}: needs kind, times (and count), nothing else")
        if s["kind"] not in ("bias", "flat", "saturation", "darkseries"):
            raise job.error("calibration", "series", f"series {i + 1}: kind must be bias, flat, saturation or "
                                                     f"darkseries, got {s['kind']!r}")
    for k in ("exr", "png"):
        if out[k] and (Path(out[k]).is_absolute() or ".." in Path(out[k]).parts):
            raise job.error("output", k, "must be a file name inside the run folder")
    _check_writable(job, out["folder"])
    sched = job["schedule"]
    if sched["repeat"] < 1 or sched["every_s"] < 0:
        raise job.error("schedule", "repeat" if sched["repeat"] < 1 else "every_s", "must be >= 1 / >= 0")


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
    """The run folder of repetition ``n`` (``{job}``, ``{n}``, ``{date}`` are filled in); with
    ``resume`` and ``{date}`` in the pattern, the newest existing folder."""
    pattern = job["output"]["folder"]
    base = _resolve(job, pattern)
    if resume and "{date}" in pattern:
        glob = str(base).format(job=job.name, n=n, date="*")
        found = sorted(Path("/").glob(glob.lstrip("/"))) if glob.startswith("/") else sorted(Path(".").glob(glob))
        found = [f for f in found if (f / "manifest.jsonl").exists()]
        if not found:
            raise JobError(f"{job.where('output', 'folder')}: --resume: no earlier run folder matches {glob}")
        return found[-1]
    date = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    return Path(str(base).format(job=job.name, n=n, date=date))


# --------------------------------------------------------------------------- camera and checks
def open_camera(job: Job, n: int = 0):
    """The job's camera (for the mock backend: with the job's scene; seed + n per repetition)."""
    cam = job["camera"]
    if cam["backend"] == "mock":
        from hdrcap.mock_camera.scenes import load_scene, parse_size
        from hdrcap.mock_camera.camera import MockCamera, MockFaults

        sc = job["scene"]
        shape = parse_size(cam["size"])
        scene = load_scene(_scene_path(job, sc["name"]), shape, sc["decades"], sc["x_max"])
        return MockCamera(cam["preset"], scene, seed=cam["seed"] + n, allowed_times=cam.get("allowed_times"),
                          bulb_max_s=cam.get("bulb_max_s"),
                          faults=MockFaults.from_dict(cam.get("faults", {})), temperature=cam.get("temperature"))
    from hdrcap.acquire.gphoto2_camera import Gphoto2Camera

    camera = Gphoto2Camera(cam.get("model"), cam.get("port"), serial=cam.get("serial"),
                           delete_after_download=cam["delete_after_download"],
                           long_exposure_s=cam["long_exposure_s"], settings=cam.get("settings"))
    try:
        if "iso" in cam:
            camera.set_iso(cam["iso"])
        camera.preflight(enforce=cam.get("enforce", False), iso=cam.get("iso"))  # changes nothing unless enforce
    except BaseException:
        camera.close()
        raise
    return camera


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
        raise job.error("exposure", "times", f"exposure {bad[0]:g} s is outside the camera's range "
                                             f"{lo:g} .. {hi:g} s")


def job_calibration(job: Job):
    from hdrcap.acquire.cliutil import resolve_calibration

    cal = job["calibration"]
    if "file" in cal:
        return resolve_calibration(str(_resolve(job, cal["file"])), None)
    preset = cal.get("preset") or (job["camera"]["preset"] if job["camera"]["backend"] == "mock" else None)
    return resolve_calibration(None, preset, job["camera"].get("temperature"))


# --------------------------------------------------------------------------- planning
def plan_for(job: Job, camera, calibration, run_dir: Path, echo: Callable[[str], None]):
    """The capture plan: a fixed bracket, or meter + planner for a target SNR.

    The planner's dark strategy per exposure is kept (unless the job sets ``[darks] strategy``):
    dark frames are captured only for matched and master exposures, and not for master
    exposures whose master dark the dark library holds. ``info`` (recorded in the manifest)
    carries the planner's decisions and merge options for the merge and the EXR header."""
    from hdrcap.acquire.session import CapturePlan

    exp, darks = job["exposure"], job["darks"]
    allowed = exposure_ladder(camera)
    times = list(exp["times"])
    strategy: str | list[str] = darks["strategy"]
    info: dict[str, Any] = {"mode": exp["mode"]}
    if exp["mode"] == "snr":
        from hdrcap import planner

        irradiance = planner.meter(_meter_fn(camera, run_dir), calibration, allowed)
        root = _library_root(job, calibration)
        library = {t: n for t, (_d, n) in library_masters(root, camera, allowed, load=False).items()}
        plan = planner.plan_exposures(calibration, irradiance, exp["target_snr_db"], allowed,
                                      max_exposures=exp.get("max_exposures"),
                                      time_budget=exp.get("time_budget_s"), quantile=exp.get("quantile"),
                                      dark_library=library or None)
        times = list(plan.exposures)
        info.update(planner=True, predicted_min_snr_db=plan.predicted_min_snr_db, feasible=plan.feasible,
                    message=plan.message, plan=_plan_record(plan))
        if plan.darks:
            if "strategy" not in job.given.get("darks", ()):
                strategy = list(plan.darks)
            elif set(plan.darks) != {strategy}:
                info["plan_overridden"] = {"darks": {"plan": list(plan.darks), "used": strategy}}
        echo(f"plan: {plan.message}")
    snapped = [nearest_allowed(t, allowed) for t in times]
    per = [strategy] * len(snapped) if isinstance(strategy, str) else strategy
    master_times = [t for t, s in zip(snapped, per) if s == DarkStrategy.MASTER]
    masters = library_masters(_library_root(job, calibration), camera, master_times, load=False) if master_times else {}
    if masters:
        info["dark_library"] = {f"{t:g}": n for t, (_d, n) in masters.items()}
        echo(f"dark library: master darks for {len(masters)} of {len(set(master_times))} master-dark exposure times")
    plan = CapturePlan.bracket(snapped, allowed, strategy, n_dark=darks["count"], repeats=exp["repeats"],
                               series=job["calibration"]["series"], library_times=list(masters))
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


def library_masters(root, camera, times, load: bool = True) -> dict[float, tuple]:
    """Master darks of the dark library at ``root`` for ``times`` (s): t -> (data, N), matched
    by :meth:`pipeline.darklibrary.DarkLibrary.masters` to the camera's model and temperature
    (data None unless ``load``). Empty when there is no dark library."""
    if not root:
        return {}
    from hdrcap.pipeline.darklibrary import DarkLibrary

    model = str(getattr(getattr(camera, "identity", None), "model", "")) or None
    temp = camera.temperature() if hasattr(camera, "temperature") else None
    found = DarkLibrary(root).masters(times, camera=model, temperature=temp, load=load)
    return {t: (data, n) for t, (data, n, _e) in found.items()}


def _meter_fn(camera, run_dir: Path):
    from hdrcap.pipeline.io import read_frame

    meter_dir = run_dir / "meter"
    meter_dir.mkdir(parents=True, exist_ok=True)
    counter = [0]

    def capture(t: float):
        counter[0] += 1
        camera.set_exposure(t)
        res = camera.capture(meter_dir / f"meter_{counter[0]:02d}_{t:.6g}s.dng")
        return read_frame(res.path).data

    return capture


# --------------------------------------------------------------------------- running
def run_job(job: Job, *, resume: bool = False, n: int = 0, run_dir: Path | None = None, progress: bool | None = None,
            echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr), camera=None,
            force: bool = False, exr_path: Path | None = None, png_path: Path | None = None,
            return_result: bool = False):
    """Run one repetition of ``job``; returns a summary dict (run folder, frames, outputs), and
    the :class:`acquire.session.SessionResult` too when ``return_result``. ``exr_path`` and
    ``png_path`` override the job's outputs (which lie inside the run folder)."""
    from hdrcap.acquire.session import CapturePlan, CaptureSession, LightBlocker, RetryPolicy
    from hdrcap.acquire.manifest import Manifest

    run_dir = Path(run_dir) if run_dir else run_folder(job, n, resume)
    own = camera is None
    camera = camera or open_camera(job, n)
    try:
        check_job_against_camera(job, camera)
        calibration = job_calibration(job)
        sess = job["session"]
        force = force or job["output"]["force"]
        if exr_path is None and job["output"]["exr"]:
            exr_path = run_dir / job["output"]["exr"]
        if png_path is None and job["output"]["png"]:
            png_path = run_dir / job["output"]["png"]
        if not resume and Manifest(run_dir).exists():
            from hdrcap.acquire.session import SessionError

            raise SessionError(f"{run_dir}: holds an earlier run (manifest.jsonl); use --resume to continue it "
                               "or choose another run folder")
        for p in (exr_path, png_path):
            if p is not None and p.exists() and not force:
                raise JobError(f"{p}: exists; use --force to overwrite (or another run folder)")
        head = Manifest(run_dir).header() if resume else None
        masters = None
        if head is not None:  # resume: the plan recorded at the start, not a new one
            pd = head["plan"]
            plan = CapturePlan.from_dict(pd)
            info = head.get("planning", {})
        else:
            if resume and Manifest(run_dir).exists() is False and run_dir.exists():
                echo(f"hdrcap: {run_dir}: nothing to resume; starting the run")
            plan, info = plan_for(job, camera, calibration, run_dir, echo)
        if plan.library_times:
            masters = library_masters(_library_root(job, calibration), camera, plan.library_times)
        d = job["darks"]
        light = LightBlocker(d["block_light"], d.get("cover_command"), d.get("uncover_command"))
        retry = RetryPolicy(sess["max_attempts"], sess["backoff_s"], sess["max_backoff_s"], sess["timeout_s"])
        meta = {"job": str(job.path) if job.path else None, "job_name": job.name, "repetition": n,
                "planning": info, "calibration": calibration.provenance}
        planned = info.get("plan") or {}
        options = _plan_merge_options(planned)
        session = CaptureSession(camera, run_dir, plan, calibration=calibration, light=light, retry=retry,
                                 resume=resume, progress=progress, meta=meta, check_dark=d["check"],
                                 master_darks=masters, merge_options=options)
        result = session.run()
        header = None
        if planned:
            from hdrcap.planner.planfile import planner_attribute

            header = planner_attribute(planned, None, None, options, info.get("plan_overridden"),
                                       source="hdrcap run (planned from metering)")
        outputs = _write_outputs(job, run_dir, result, calibration, camera, exr_path, png_path, force, header)
    finally:
        if own:
            try:
                camera.close()
            except Exception:
                pass
    summary = {
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
    return (summary, result) if return_result else summary


def _plan_merge_options(planned: dict) -> dict:
    """The merge options the planner decided (recorded in the manifest's planning record)."""
    if not planned:
        return {}
    from hdrcap.planner.planfile import PLAN_OPTIONS, check_plan

    decided = check_plan(planned, "planner").merge_options()
    return {k: v for k, v in decided.items() if k in PLAN_OPTIONS}


def _write_outputs(job: Job, run_dir: Path, result, calibration, camera, exr_path, png_path, force,
                   planner_header: dict | None = None) -> dict:
    from hdrcap.acquire.filemerge import build_hdr_image
    from hdrcap.pipeline.io import RawFrame, write_exr
    from hdrcap.pipeline.preview import write_preview_png

    out: dict[str, Any] = {}
    merge = result.merge
    if merge is None:
        return out
    lights = sorted((r for r in result.frames.values() if r["kind"] == "light"), key=lambda r: r["index"])
    cfa = getattr(getattr(camera, "spec", None), "cfa", None)
    frames = [RawFrame(data=None, exposure_time=r["file_exposure_s"], path=r["file"], cfa_pattern=cfa)
              for r in lights]
    extra = {"run_dir": str(run_dir), "job": job.name, "camera": lights[0]["camera"] if lights else {},
             "manifest": "manifest.jsonl"}
    if planner_header:
        extra["planner"] = planner_header
    if exr_path is not None:
        write_exr(exr_path, build_hdr_image(merge, frames, calibration, extra), force=force)
        out["exr"] = str(exr_path)
    if png_path is not None:
        write_preview_png(png_path, merge.irradiance, cfa, force=force)
        out["png"] = str(png_path)
    truth = getattr(getattr(camera, "sim", None), "scene", None)
    if truth is not None:  # the simulator knows the truth: report the error against it
        from hdrcap.pipeline.evaluation import error_against_truth

        out["error_vs_truth"] = error_against_truth(merge.irradiance, merge.sigma, merge.nexp, truth)
    return out


def run_schedule(job: Job, *, repeat: int | None = None, every_s: float | None = None, resume: bool = False,
                 progress: bool | None = None, echo: Callable[[str], None] = lambda s: print(s, file=sys.stderr),
                 run_dir: Path | None = None, force: bool = False, sleep=time.sleep) -> list[dict]:
    """Run the job ``repeat`` times, starting one every ``every_s`` seconds (a slow run delays
    the next start rather than overlapping it)."""
    repeat = repeat if repeat is not None else job["schedule"]["repeat"]
    every_s = every_s if every_s is not None else job["schedule"]["every_s"]
    if repeat > 1 and run_dir is not None and "{n" not in str(run_dir):
        raise JobError("--run-dir with --repeat needs {n} in the folder name")
    t0 = time.monotonic()
    results = []
    for n in range(repeat):
        start = t0 + n * every_s
        delay = start - time.monotonic()
        if delay > 0:
            sleep(delay)
        rd = Path(str(run_dir).format(n=n, job=job.name)) if run_dir else None
        results.append(run_job(job, resume=resume, n=n, run_dir=rd, progress=progress, echo=echo, force=force))
    return results
