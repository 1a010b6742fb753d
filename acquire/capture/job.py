"""Job files: a TOML file that describes a measurement end to end (camera, scene or metering,
target SNR or fixed bracket, dark frames, calibration, outputs, repetition), read and checked
before any frame is taken; the first problem is reported in one line,
``FILE:LINE: section.key: message``.

The tables and keys are declared in :mod:`acquire.capture.schema`; a job is run by
:func:`acquire.capture.run.run_job` (one run) and :func:`acquire.capture.schedule.run_schedule`
(repetitions). See docs/acquisition.md for the format.
"""

from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from hdrcap.acquire.capture.schema import JobFile, Problem
from hdrcap.pipeline.errors import InputError

__all__ = ["Job", "JobError", "load_job", "job_from_dict", "capture_job"]


class JobError(InputError):
    """A bad job file; the message names the file and line."""


@dataclass
class Job:
    """A validated job: ``job[section][key]`` with defaults filled in (keys without a default
    are present only when given), ``job.spec`` the typed :class:`acquire.capture.schema.JobFile`."""

    spec: JobFile
    path: Path | None = None
    lines: dict[tuple[str, str], int] = field(default_factory=dict)
    sections: dict[str, dict[str, Any]] = field(init=False)

    def __post_init__(self) -> None:
        self.sections = {name: getattr(self.spec, name).model_dump(exclude_none=True) for name in JobFile.model_fields}

    def __getitem__(self, section: str) -> dict[str, Any]:
        return self.sections[section]

    @property
    def name(self) -> str:
        return self.spec.job.name or (self.path.stem if self.path else "job")

    def where(self, section: str, key: str | None = None) -> str:
        """``file:line`` of a key (or its section) for messages."""
        return _where(self.path, self.lines, section, key)

    def error(self, section: str, key: str | None, message: str) -> JobError:
        """A :class:`JobError` ``file:line: section.key: message``."""
        return _error(self.path, self.lines, section, key, message)

    def resolve(self, name: str) -> Path:
        """A path of the job file (``~`` expanded, relative to the job file's folder)."""
        p = Path(os.path.expanduser(name))
        if not p.is_absolute() and self.path is not None:
            p = self.path.parent / p
        return p


def _line(lines: dict[tuple[str, str], int], section: str, key: str | None) -> int | None:
    """The line of ``key`` in ``[section]``, else of the section's header, else None."""
    return lines.get((section, key or "")) or lines.get((section, ""))


def _where(path: Path | None, lines: dict[tuple[str, str], int], section: str, key: str | None) -> str:
    name = str(path) if path else "<job>"
    line = _line(lines, section, key)
    return f"{name}:{line}" if line else name


def _error(
    path: Path | None, lines: dict[tuple[str, str], int], section: str, key: str | None, message: str
) -> JobError:
    label = f"{section}.{key}" if key else f"[{section}]"
    return JobError(f"{_where(path, lines, section, key)}: {label}: {message}")


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
                if not section:  # a key before any table stands where a table would
                    out.setdefault((key, ""), n)
    return out


def load_job(path: str | os.PathLike[str]) -> Job:
    """Read and validate a job file (syntax, keys, types and values that need no camera).

    Parameters
    ----------
    path : str or Path
        The TOML job file.

    Returns
    -------
    Job

    Raises
    ------
    JobError
        The first problem, as ``FILE:LINE: section.key: message`` (one line).
    acquire.capture.session.LocalIOError
        The output folder is not writable (exit status 6), with its ``FILE:LINE``.
    """
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise JobError(f"{file}: no such job file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise JobError(f"{file}: cannot read the job file ({err})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise JobError(f"{file}: not valid TOML: {err}") from None
    return job_from_dict(data, path=file, text=text)


def job_from_dict(data: dict[str, Any], path: Path | None = None, text: str = "") -> Job:
    """Validate a job given as a dict (``hdrcap capture`` builds one from its options).

    Parameters
    ----------
    data : dict
        The job's tables (as TOML parses them).
    path : Path, optional
        The job file: messages name it, relative paths in the job are relative to its folder.
    text : str
        The job file's text, for the line numbers of messages.

    Returns
    -------
    Job

    Raises
    ------
    JobError
        The first problem (the one nearest the top of the file), in one line.
    """
    lines = _key_lines(text)
    try:
        spec = JobFile.model_validate(data)
    except ValidationError as err:
        problems = [_problem(e) for e in err.errors()]
        section, key, message = min(problems, key=lambda p: _line(lines, p[0], p[1]) or float("inf"))
        raise _error(path, lines, section, key, message) from None
    job = Job(spec, path, lines)
    _check_paths(job)
    return job


def capture_job(
    camera: str = "mock:camera-B",
    run_dir: str | os.PathLike[str] = ".",
    *,
    times: Sequence[float] = (),
    target_snr_db: float | None = None,
    max_exposures: int | None = None,
    dark_strategy: str | None = None,
    dark_count: int = 1,
    block_light: str | None = None,
    cover_command: str | None = None,
    uncover_command: str | None = None,
    calibration: str | os.PathLike[str] | None = None,
    scene: str = "hdr",
    size: str = "256x192",
    seed: int = 0,
    faults: Mapping[str, Any] | None = None,
    port: str | None = None,
    serial: str | None = None,
    iso: int | None = None,
    enforce: bool = False,
    png: bool = True,
) -> Job:
    """The job of one capture given as options (``hdrcap capture``, :mod:`hdrcap.bluesky`):
    a fixed bracket or a target SNR on the simulated or a real camera, validated like a job file.

    Parameters
    ----------
    camera : str
        ``mock:PRESET`` or ``PRESET`` (the simulator), ``gphoto2`` or ``gphoto2:MODEL`` (a real camera).
    run_dir : str or path-like
        The run folder (``[output] folder``).
    times : sequence of float
        Exposure times of a fixed bracket, s (with ``target_snr_db``: the fallback without the planner).
    target_snr_db : float, optional
        Plan the exposures for this SNR of the merged irradiance, dB (metering and the planner).
    max_exposures : int, optional
        Most exposure times the planner may choose.
    dark_strategy : {"matched", "master", "model"}, optional
        Default: matched; with ``target_snr_db`` the planner's choice per exposure.
    dark_count : int
        Dark frames averaged per exposure time (``master``).
    block_light : {"mock", "prompt", "command", "none"}, optional
        How the light is blocked for dark frames (default: mock for the simulator, prompt otherwise).
    cover_command, uncover_command : str, optional
        Shell commands that block and unblock the light (``block_light="command"``).
    calibration : str or path-like, optional
        A calibration file (``hdrcap calibrate``) or a simulator preset's name (its nominal model);
        default: the simulator's preset.
    scene, size, seed, faults
        The simulator's scene, mosaic ``WIDTHxHEIGHT``, seed and injected faults
        (:class:`acquire.camera.mock.MockFaults` fields).
    port, serial, iso, enforce
        A real camera's gphoto2 port, serial number, ISO speed and whether wrong settings are set.
    png : bool
        Write the preview PNG next to the EXR.

    Returns
    -------
    Job

    Raises
    ------
    InputError
        An unknown camera, neither ``times`` nor ``target_snr_db``.
    JobError
        What the job schema refuses (``<job>: section.key: message``).
    """
    from hdrcap.mock_camera import PRESETS

    backend, _, name = camera.partition(":") if ":" in camera or camera == "gphoto2" else ("mock", ":", camera)
    if backend not in ("mock", "gphoto2") or (backend == "mock" and name and name not in PRESETS):
        raise InputError(
            f"camera must be mock:PRESET, PRESET ({', '.join(PRESETS)}) or gphoto2[:MODEL], got {camera!r}"
        )
    if not times and target_snr_db is None:
        raise InputError("give times (a fixed bracket) or a target SNR (dB)")
    cam: dict[str, Any] = {"backend": backend}
    if backend == "mock":
        cam.update(preset=name or "camera-B", size=size, seed=seed)
        if faults:
            cam["faults"] = dict(faults)
    else:
        cam.update({k: v for k, v in (("model", name), ("port", port), ("serial", serial)) if v})
        cam["enforce"] = enforce
    if iso is not None:
        cam["iso"] = iso
    exposure: dict[str, Any] = {"mode": "snr", "target_snr_db": target_snr_db} if target_snr_db is not None else {}
    exposure.setdefault("mode", "bracket")
    if times:
        exposure["times"] = [float(t) for t in times]
    if max_exposures is not None:
        exposure["max_exposures"] = max_exposures
    darks: dict[str, Any] = {
        "count": dark_count,
        "block_light": block_light or ("mock" if backend == "mock" else "prompt"),
    }
    for key, value in (
        ("strategy", dark_strategy),
        ("cover_command", cover_command),
        ("uncover_command", uncover_command),
    ):
        if value:
            darks[key] = value
    data: dict[str, Any] = {
        "job": {"name": "capture"},
        "camera": cam,
        "exposure": exposure,
        "darks": darks,
        "output": {"folder": str(run_dir), **({} if png else {"png": ""})},
    }
    if backend == "mock":
        data["scene"] = {"name": scene}
    if calibration:
        preset = str(calibration).removeprefix("mock:")
        data["calibration"] = {"preset": preset} if preset in PRESETS else {"file": str(calibration)}
    return job_from_dict(data)


def _check_paths(job: Job) -> None:
    """The calibration file and dark library exist; the run folder can be written (a folder
    that is read-only or not ours is a local I/O error, exit status 6, as it is during a run)."""
    cal = job.spec.calibration
    if cal.file is not None and not job.resolve(cal.file).is_file():
        raise job.error("calibration", "file", f"calibration file {job.resolve(cal.file)} does not exist")
    if cal.dark_library is not None and not job.resolve(cal.dark_library).is_dir():
        raise job.error(
            "calibration", "dark_library", f"dark library folder {job.resolve(cal.dark_library)} does not exist"
        )
    probe = job.resolve(job.spec.output.folder.split("{")[0] or ".")
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise job.error("output", "folder", f"{probe} is not a writable folder")
    if probe.exists() and not os.access(probe, os.W_OK):  # local I/O (exit 6), as during a run
        from hdrcap.acquire.capture.session import LocalIOError

        raise LocalIOError(
            f"{job.where('output', 'folder')}: output.folder: {probe} is not writable (read-only or permissions); "
            "fix it or choose another folder"
        )


# --------------------------------------------------------------------------- pydantic -> one line
#: What a type error expected, by pydantic's error type.
_EXPECTED = {
    "string_type": "a string",
    "int_type": "an integer",
    "float_type": "a number",
    "bool_type": "true or false",
    "list_type": "a list",
    "dict_type": "a table",
    "model_type": "a table",
}


def _problem(error: ErrorDetails) -> tuple[str, str | None, str]:
    """(section, key, message) of one pydantic error; deeper places (a list item, a key of an
    inline table) lead the message: ``item 2: kind: ...``."""
    loc, kind, ctx = error["loc"], error["type"], error.get("ctx") or {}
    cause = ctx.get("error")
    if isinstance(cause, Problem):
        section = cause.section or str(loc[0])
        return section, cause.key, str(cause)
    section = str(loc[0])
    if len(loc) == 1:
        if kind == "extra_forbidden":
            return section, None, f"unknown section; known: {', '.join(JobFile.model_fields)}"
        return section, None, "must be a table" if kind in ("model_type", "dict_type") else _message(error)
    inner = [f"item {p + 1}" if isinstance(p, int) else str(p) for p in loc[2:]]
    if kind == "extra_forbidden":
        known = ", ".join(sorted(_model_at(loc[:-1]).model_fields))
        message = f"unknown key; known: {known}"
        if inner:  # the unknown key itself is the last place
            message = f"unknown key {inner.pop()!r}; known: {known}"
    else:
        message = _message(error)
    return section, str(loc[1]), ": ".join([*inner, message])


def _message(error: ErrorDetails) -> str:
    """The message of one pydantic error in the job file's words."""
    kind, ctx, value = error["type"], error.get("ctx") or {}, error.get("input")
    if kind in _EXPECTED:
        return f"expected {_EXPECTED[kind]}, got {value!r}"
    if kind == "literal_error":
        choices = ctx["expected"].replace("'", "")  # 'a', 'b' or 'c' -> a, b or c
        return f"must be {choices}, got {value!r}"
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in bounds:
        limit = next(iter(ctx.values()))
        return f"must be {bounds[kind]} {limit:g}, got {value!r}"
    if kind == "finite_number":
        return f"must be a finite number, got {value!r}"
    if kind == "missing":
        return "required, not given"
    if kind == "value_error" and ctx.get("error") is not None:
        return str(ctx["error"])
    return error["msg"]


def _model_at(loc: tuple[int | str, ...]) -> type[BaseModel]:
    """The table model at ``loc`` (field names and list indices from :class:`JobFile`)."""
    model: Any = JobFile
    for part in loc:
        if isinstance(part, int):
            continue
        model = model.model_fields[part].annotation
        while not (isinstance(model, type) and issubclass(model, BaseModel)):
            model = next(a for a in get_args(model) if a is not type(None))
    return model
