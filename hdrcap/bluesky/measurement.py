"""One hdrcap measurement after another with one open camera, each a complete run in its own
folder: the device-free core of :class:`hdrcap.bluesky.HdrDetector`.

A measurement is exactly what ``hdrcap capture`` does (the job of
:func:`hdrcap.acquire.capture.job.capture_job` run by :func:`hdrcap.acquire.capture.run.run_job`):
metering and planning for a target SNR or a fixed bracket, dark frames, verified and hashed
frames in a manifest, retries, the streamed optimal merge and ``RUN/hdr.exr``. This module adds
only the figures a Bluesky event reports (:data:`READINGS`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hdrcap.acquire.capture.job import Job, capture_job
from hdrcap.acquire.capture.session import StopEvent
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.result import HdrResult

__all__ = ["READINGS", "Reading", "Measurement", "Measurer"]

log = logging.getLogger("hdrcap.bluesky")


@dataclass(frozen=True)
class Reading:
    """A scalar a measurement reports (one per Bluesky event).

    Attributes
    ----------
    name : str
        The key (the event's data key is ``DETECTOR-name``).
    dtype : type
        ``float``, ``int`` or ``str``.
    units : str or None
        Engineering units.
    description : str
        What it is.
    """

    name: str
    dtype: type
    units: str | None
    description: str


#: The scalars of every measurement, in the order the events list them (``scene_scale`` only
#: for the simulated camera).
READINGS: tuple[Reading, ...] = (
    Reading("snr_median_db", float, "dB", "achieved SNR of the irradiance: 20 log10 of the median of irradiance/sigma"),
    Reading("snr_target_db", float, "dB", "the target SNR the exposures were planned for (NaN: a fixed bracket)"),
    Reading("saturated_fraction", float, None, "fraction of photosites saturated in every exposure (nexp = 0)"),
    Reading("n_exposures", int, None, "light frames merged"),
    Reading("capture_s", float, "s", "wall-clock time of the measurement: metering, frames, merge, outputs"),
    Reading("scene_scale", float, None, "simulated camera: the factor on the scene's irradiance"),
    Reading("run_dir", str, None, "the run folder: frames, manifest.jsonl, events.jsonl, hdr.exr"),
)


@dataclass(frozen=True)
class Measurement:
    """What one measurement produced.

    Attributes
    ----------
    run_dir : Path
        Its run folder (a complete ``hdrcap capture`` run).
    result : HdrResult
        The merge, as ``RUN/hdr.exr`` holds it.
    readings : dict
        :data:`READINGS` by name.
    """

    run_dir: Path
    result: HdrResult
    readings: dict[str, Any]


class Measurer:
    """Takes hdrcap measurements with one camera, each into a new run folder.

    Parameters
    ----------
    camera : str
        ``mock:PRESET`` (the simulator) or ``gphoto2[:MODEL]`` (a real camera).
    times : sequence of float
        Exposure times of a fixed bracket, s.
    target_snr_db : float, optional
        Default target SNR, dB (a measurement may ask for another).
    calibration : str or path-like, optional
        A calibration file or a simulator preset (default: the simulator's preset; a real
        camera needs one).
    size : str, optional
        Simulated camera only: mosaic ``WIDTHxHEIGHT`` (default 256x192).
    folder : str or path-like
        Where the run folders will be (checked now: it must be, or be creatable in, a writable folder).
    **options
        Further options of :func:`hdrcap.acquire.capture.job.capture_job` (``dark_strategy``,
        ``dark_count``, ``block_light``, ``cover_command``, ``uncover_command``, ``max_exposures``,
        ``scene``, ``seed``, ``faults``, ``port``, ``serial``, ``iso``, ``enforce``).

    Raises
    ------
    InputError
        A bad option (the job's one-line message), ``size`` for a real camera.
    """

    def __init__(
        self,
        camera: str = "mock:camera-B",
        *,
        times: Sequence[float] = (),
        target_snr_db: float | None = None,
        calibration: str | os.PathLike[str] | None = None,
        size: str | None = None,
        folder: str | os.PathLike[str] = ".",
        **options: Any,
    ) -> None:
        from hdrcap.acquire.capture.camera_setup import job_calibration

        self.camera_name = camera
        self.times = tuple(float(t) for t in times)
        self.target_snr_db = target_snr_db
        self._options: dict[str, Any] = dict(options, calibration=calibration, png=False)
        if size is not None:
            self._options["size"] = size
        self.job = self.job_for(Path(folder), target_snr_db)
        self.simulated = self.job["camera"]["backend"] == "mock"
        if size is not None and not self.simulated:
            raise InputError("size is for the simulated camera; a real camera's mosaic is its own")
        self.calibration = job_calibration(self.job)
        self._camera: Any = None
        self._opened = 0
        self.count = 0

    @property
    def shape(self) -> tuple[int, int] | None:
        """(rows, columns) of the maps: the simulator's size; a real camera's once it measured."""
        if self.simulated:
            from hdrcap.mock_camera.scenes import parse_size

            return parse_size(self.job["camera"]["size"])
        shape = getattr(self._camera, "shape", None)
        return (int(shape[0]), int(shape[1])) if shape else None

    def job_for(self, run_dir: Path, target_snr_db: float | None) -> Job:
        """The job of one measurement into ``run_dir``: the fixed bracket, or planned for
        ``target_snr_db`` (dB) when it is a number.

        Parameters
        ----------
        run_dir : Path
        target_snr_db : float or None

        Returns
        -------
        Job
        """
        target = None if target_snr_db is None or math.isnan(target_snr_db) else float(target_snr_db)
        return capture_job(self.camera_name, run_dir, times=self.times, target_snr_db=target, **self._options)

    def settings(self) -> dict[str, Any]:
        """What stays the same from one measurement to the next, for the descriptor's
        configuration: the camera, the plan's settings, the calibration and the merge options.

        Returns
        -------
        dict
            ``camera`` (str), ``plan``, ``calibration``, ``merge_options`` (dicts of JSON types).
        """
        from hdrcap.acquire.capture.manifest import jsonable
        from hdrcap.pipeline.merge.accumulator import MergeOptions

        cal = self.calibration
        options = dataclasses.asdict(MergeOptions(exposure_times="effective"))  # the capture's streamed merge
        for key in ("dark_strategy", "n_dark", "master_dark_time"):  # per exposure, from the plan
            options.pop(key)
        # a measurement planned for a target SNR takes the planner's choices instead (its hdr.exr says)
        options["planned_measurements"] = "the planner's saturation, prnu and iterations (RUN/hdr.exr: planner)"
        return jsonable(
            {
                "camera": self.camera_name,
                "plan": {"exposure": self.job["exposure"], "darks": self.job["darks"]},
                "calibration": {
                    "source": self.job["calibration"],
                    "params": cal.params.to_dict(),
                    "provenance": cal.provenance,
                },
                "merge_options": options,
            }
        )

    def open(self) -> None:
        """Open the camera (once; the simulator's seed is offset by the number of openings)."""
        if self._camera is None:
            from hdrcap.acquire.capture.camera_setup import open_camera

            self._camera = open_camera(self.job, self._opened)
            self._opened += 1

    def close(self) -> None:
        """Close the camera (a later measurement opens it again)."""
        camera, self._camera = self._camera, None
        if camera is not None:
            camera.close()

    def measure(
        self,
        run_dir: str | os.PathLike[str],
        *,
        target_snr_db: float | None = None,
        scene_scale: float = 1.0,
        stop: StopEvent | None = None,
    ) -> Measurement:
        """One measurement into the new run folder ``run_dir``.

        Parameters
        ----------
        run_dir : str or path-like
            Must not hold a run.
        target_snr_db : float or None
            Plan for this SNR, dB; None or NaN: the fixed bracket.
        scene_scale : float
            Simulated camera: the factor on the scene's irradiance (1 for a real camera).
        stop : hdrcap.acquire.capture.session.StopEvent, optional
            Set to stop before the next frame (:class:`hdrcap.acquire.capture.session.RunInterrupted`;
            the run folder stays resumable).

        Returns
        -------
        Measurement

        Raises
        ------
        HdrcapError
            What stopped the run, with the session's one-line message.
        """
        from hdrcap.acquire.capture.run import run_job

        if scene_scale != 1.0 and not self.simulated:
            raise InputError("scene_scale is for the simulated camera")
        run_dir = Path(run_dir)
        job = self.job_for(run_dir, target_snr_db)
        self.open()
        if self.simulated:
            self._camera.set_scene_scale(scene_scale)
        t0 = time.monotonic()
        _summary, session = run_job(
            job,
            run_dir=run_dir,
            camera=self._camera,
            n=self.count,
            progress=False,
            echo=log.info,
            stop=stop,
            return_result=True,
        )
        if session is None or session.merge is None:  # not for a new run with a calibration
            raise RuntimeError(f"{run_dir}: the run produced no merge")
        self.count += 1
        result = session.merge
        readings = self._readings(session, result, job, time.monotonic() - t0, scene_scale, run_dir)
        return Measurement(run_dir, result, readings)

    @staticmethod
    def _readings(session: Any, result: HdrResult, job: Job, elapsed: float, scale: float, run_dir: Path) -> dict:
        from hdrcap.pipeline.result import summarise

        figures = summarise(result)
        rel = figures["median_relative_sigma"]
        h, w = result.shape
        exp = job["exposure"]
        return {
            "snr_median_db": 20 * math.log10(1 / rel) if rel else math.nan,
            "snr_target_db": float(exp["target_snr_db"]) if exp["mode"] == "snr" else math.nan,
            "saturated_fraction": figures["saturated_everywhere"] / (h * w),
            "n_exposures": sum(1 for r in session.frames.values() if r["kind"] == "light"),
            "capture_s": elapsed,
            "scene_scale": scale,
            "run_dir": str(run_dir),
        }
