"""The job file's schema: one pydantic model per TOML table, each key with its type, range and
default, and the rules that tie keys together.

Pure validation of the parsed TOML: no file is read and no camera is opened (the checks that
need the job file's folder are in :mod:`acquire.capture.job`, those that need the camera in
:mod:`acquire.capture.camera_setup`). Types are strict: a string is never read as a number,
``true`` is never an integer, an integer is a number. A rule that concerns one key raises
:class:`Problem` naming it, so that the message can carry the key's line. See
docs/acquisition.md for the format.

>>> JobFile.model_validate({"exposure": {"times": [0.01, 0.1]}}).darks.strategy
'matched'
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from hdrcap.pipeline.dark_strategy import DarkStrategy
from hdrcap.pipeline.errors import InputError

__all__ = ["JobFile", "Problem", "MAX_FRAMES_PER_RUN"]

#: The most frames one run may plan (light and dark frames, or a calibration series): a job
#: beyond it is a typing error (a run of 100 000 frames already takes more than a day at one
#: frame per second), refused when the job is read instead of planned frame by frame.
MAX_FRAMES_PER_RUN = 100_000


class Problem(ValueError):
    """A rule broken by one key (or by a table when ``key`` is None) of a table: ``section``
    None means the table whose validator raised it."""

    def __init__(self, key: str | None, message: str, section: str | None = None):
        super().__init__(message)
        self.key = key
        self.section = section


def _frames(value: int) -> int:
    if value > MAX_FRAMES_PER_RUN:
        raise ValueError(f"{value} is more frames than a run takes ({MAX_FRAMES_PER_RUN})")
    return value


def _inside_run_folder(name: str) -> str:
    if name and (Path(name).is_absolute() or ".." in Path(name).parts):
        raise ValueError("must be a file name inside the run folder")
    return name


def _folder_pattern(pattern: str) -> str:
    try:
        pattern.format(job="", n=0, date="")
    except (ValueError, KeyError, IndexError, AttributeError, TypeError) as err:
        raise ValueError(f"not a valid pattern ({type(err).__name__}: {err}); fields: {{job}} {{n}} {{date}}") from None
    return pattern


#: A positive, finite number (seconds for exposure times).
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
#: A frame count a run can take (:data:`MAX_FRAMES_PER_RUN`).
FrameCount = Annotated[int, AfterValidator(_frames)]
#: The names of :class:`pipeline.dark_strategy.DarkStrategy`, in its order
#: (tests/acquire/capture/test_job.py checks that the two agree).
DarkStrategyName = Literal["matched", "master", "model"]


class Table(BaseModel):
    """One TOML table: unknown keys are refused, types are strict."""

    model_config = ConfigDict(extra="forbid", strict=True)


class JobTable(Table):
    name: str = ""
    description: str | None = None


class CameraTable(Table):
    backend: Literal["mock", "gphoto2"] = "mock"
    # the simulated camera
    preset: str = "camera-B"
    size: str = "256x192"
    seed: int = Field(0, ge=0)
    temperature: float | None = None
    faults: dict[str, Any] | None = None
    allowed_times: list[Positive] | None = None
    bulb_max_s: float | None = None
    # a real camera (gphoto2)
    model: str | None = None
    port: str | None = None
    serial: str | None = None
    enforce: bool = False
    delete_after_download: bool = True
    iso: int | None = None
    long_exposure_s: float = 1.0
    settings: dict[str, Any] | None = None


class SceneTable(Table):
    name: str = "hdr"
    decades: Positive = 4.0
    x_max: Positive = 2e5

    @model_validator(mode="after")
    def _darkest_is_a_number(self) -> SceneTable:
        if not self.x_max * 10.0 ** -min(self.decades, 400.0) > sys.float_info.min:
            raise Problem("decades", "spans more decades below x_max than a float holds")
        return self


class ExposureTable(Table):
    mode: Literal["bracket", "snr"] = "bracket"
    times: list[Positive] = []
    target_snr_db: float | None = None
    max_exposures: FrameCount | None = None
    time_budget_s: float | None = None
    repeats: Annotated[int, Field(ge=1), AfterValidator(_frames)] = 1
    quantile: float | None = None

    @model_validator(mode="after")
    def _mode_has_what_it_needs(self) -> ExposureTable:
        if self.mode == "bracket" and not self.times:
            raise Problem("times", "a fixed bracket needs times = [...] (seconds)")
        if self.mode == "snr" and self.target_snr_db is None:
            raise Problem("target_snr_db", 'mode = "snr" needs target_snr_db')
        per_repeat = len(self.times) if self.mode == "bracket" else (self.max_exposures or 1)
        light = per_repeat * self.repeats
        if light > MAX_FRAMES_PER_RUN:
            raise Problem("repeats", f"{light} light frames per run, more than a run takes ({MAX_FRAMES_PER_RUN})")
        return self


class DarksTable(Table):
    strategy: DarkStrategyName = DarkStrategy.MATCHED.value
    count: Annotated[int, Field(ge=1), AfterValidator(_frames)] = 1
    block_light: Literal["mock", "prompt", "command", "none"] = "mock"
    cover_command: str | None = None
    uncover_command: str | None = None
    command_timeout_s: float = Field(60.0, gt=0, allow_inf_nan=False)
    check: float = 0.05

    @model_validator(mode="after")
    def _commands_for_command(self) -> DarksTable:
        if self.block_light == "command":
            for key in ("cover_command", "uncover_command"):
                if not getattr(self, key):
                    raise Problem(key, 'block_light = "command" needs cover_command and uncover_command')
        return self


class Series(Table):
    """One calibration series: ``count`` frames at each of ``times``."""

    kind: Literal["bias", "flat", "saturation", "darkseries"]
    times: list[Positive]
    count: int = 1

    @model_validator(mode="after")
    def _frames_a_run_takes(self) -> Series:
        n = self.count * len(self.times)
        if n > MAX_FRAMES_PER_RUN:
            raise ValueError(f"{n} frames, more than a run takes ({MAX_FRAMES_PER_RUN})")
        return self


class CalibrationTable(Table):
    file: str | None = None
    preset: str | None = None
    series: list[Series] = []
    dark_library: str | None = None


class OutputTable(Table):
    folder: Annotated[str, AfterValidator(_folder_pattern)] = "runs/{job}-{date}"
    exr: Annotated[str, AfterValidator(_inside_run_folder)] = "hdr.exr"
    png: Annotated[str, AfterValidator(_inside_run_folder)] = "preview.png"
    force: bool = False


class ScheduleTable(Table):
    repeat: int = Field(1, ge=1)
    every_s: float = Field(0.0, ge=0)


class NotifyTable(Table):
    on_done: str | None = None
    on_failure: str | None = None
    timeout_s: float = Field(60.0, gt=0)


class SessionTable(Table):
    max_attempts: int = 12
    backoff_s: float = 0.5
    max_backoff_s: float = 30.0
    timeout_s: float = 60.0


class JobFile(Table):
    """A whole job file: its tables in the order they are documented, each one optional (a
    table not given is validated as an empty one: its defaults and rules hold)."""

    job: JobTable = Field(default={}, validate_default=True)
    camera: CameraTable = Field(default={}, validate_default=True)
    scene: SceneTable = Field(default={}, validate_default=True)
    exposure: ExposureTable = Field(default={}, validate_default=True)
    darks: DarksTable = Field(default={}, validate_default=True)
    calibration: CalibrationTable = Field(default={}, validate_default=True)
    output: OutputTable = Field(default={}, validate_default=True)
    schedule: ScheduleTable = Field(default={}, validate_default=True)
    notify: NotifyTable = Field(default={}, validate_default=True)
    session: SessionTable = Field(default={}, validate_default=True)

    @model_validator(mode="after")
    def _fits_the_camera(self) -> JobFile:
        cam, darks = self.camera, self.darks
        if cam.backend == "mock":
            _check_simulator(cam, self.scene)
        elif cam.faults is not None:
            raise Problem("faults", "fault injection is for the mock camera only", "camera")
        if darks.block_light == "mock" and cam.backend != "mock" and darks.strategy != DarkStrategy.MODEL:
            raise Problem(
                "block_light",
                "a real camera cannot block its light itself: use prompt, command (cover_command/uncover_command) "
                "or none",
                "darks",
            )
        cal = self.calibration
        if cal.file is None and cal.preset is None and cam.backend != "mock":
            raise Problem(
                None, 'a real camera needs a calibration: file = "calib..." (from `hdrcap calibrate`)', "calibration"
            )
        return self


def _check_simulator(cam: CameraTable, scene: SceneTable) -> None:
    """The simulated camera's preset, mosaic size, faults and scene exist."""
    from hdrcap.acquire.camera.mock import MockFaults
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.scenes import SCENES, parse_size

    if cam.preset not in PRESETS:
        raise Problem("preset", f"unknown simulator preset {cam.preset!r}; choose from {', '.join(PRESETS)}", "camera")
    try:
        parse_size(cam.size)
    except InputError as err:
        raise Problem("size", str(err), "camera") from None
    try:
        MockFaults.from_dict(cam.faults or {})
    except (TypeError, ValueError) as err:
        raise Problem("faults", str(err), "camera") from None
    if scene.name not in SCENES and not scene.name.lower().endswith(".exr"):
        raise Problem("name", f"unknown scene {scene.name!r}; choose from {', '.join(SCENES)} or an .exr", "scene")
