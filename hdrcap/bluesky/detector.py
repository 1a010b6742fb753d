"""``HdrDetector``: an hdrcap measurement as an ophyd-async ``StandardDetector``.

ophyd-async (0.21) builds a detector from logics: a trigger logic (what a trigger may ask for),
an acquire logic (the controller: starts and stops acquiring) and data logics (the writers:
the files and the documents that point into them). Here one trigger is one hdrcap measurement
(:class:`hdrcap.bluesky.measurement.Measurer`, the same run as ``hdrcap capture``):

* :class:`HdrAcquireLogic` runs it in a worker thread in a new run folder, appends its maps to
  the HDF5 file and sets the scalar readings; a camera fault fails the trigger's status with
  the session's message; a pause (``HdrDetector.pause``) or unstaging (``RE.stop()``,
  ``RE.abort()``) stops a measurement before its next frame, leaving a resumable run folder, and
  ends its trigger without data.
* :class:`HdrMapsLogic` writes ``DIR/NAME-DATE.h5`` (:class:`hdrcap.bluesky.hdf5.MapFile`) and
  emits its ``stream_resource`` / ``stream_datum`` documents; run folders are ``DIR/NAME-DATE/0000``, ...
* :class:`HdrReadingsLogic` puts the scalars (:data:`hdrcap.bluesky.measurement.READINGS`) in
  every event.
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import functools
import json
import math
import os
import signal
import tempfile
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any

from bluesky.protocols import Reading, StreamAsset
from event_model import ComposeStreamResource, ComposeStreamResourceBundle, DataKey, StreamRange
from ophyd_async.core import (
    DetectorAcquireLogic,
    DetectorDataLogic,
    DetectorTriggerLogic,
    PathInfo,
    PathProvider,
    ReadableDataProvider,
    SignalR,
    StandardDetector,
    StreamableDataProvider,
    TriggerInfo,
    merge_gathered_dicts,
    soft_signal_r_and_setter,
    soft_signal_rw,
)

from hdrcap.acquire.capture.session import RunInterrupted, StopEvent
from hdrcap.bluesky.hdf5 import MAPS, MapFile
from hdrcap.bluesky.measurement import READINGS, Measurer, log
from hdrcap.pipeline.errors import InputError

__all__ = [
    "HdrDetector",
    "FolderPathProvider",
    "HdrTriggerLogic",
    "HdrAcquireLogic",
    "HdrMapsLogic",
    "HdrReadingsLogic",
]

#: The axes of each map in an event (the HDF5 datasets have the measurement index before them).
MAP_DIMS = ["row", "column"]


class FolderPathProvider(PathProvider):
    """Files in one folder, named ``NAME-YYYYMMDDTHHMMSSZ`` (``-2``, ``-3``, ... when taken)."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder).absolute()

    def __call__(self, datakey_name: str | None = None) -> PathInfo:
        stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
        base = f"{datakey_name or 'hdr'}-{stamp}"
        stem, k = base, 1
        while (self.folder / f"{stem}.h5").exists() or (self.folder / stem).exists():
            k += 1
            stem = f"{base}-{k}"
        return PathInfo(directory_path=self.folder, filename=stem)


class _MapsProvider(StreamableDataProvider):
    """The maps in one HDF5 file: their data keys, ``stream_resource`` and ``stream_datum``.

    ``collections_written_signal`` counts finished triggers, the rows of the file only those
    whose measurement is in it: a trigger the RunEngine gave up on (a pause, a stop) finishes
    without a row, and every event's ``stream_datum`` points at the one row written for it.
    """

    def __init__(self, name: str, file: MapFile, uri: str, shape: Callable[[], tuple[int, int] | None]) -> None:
        self.collections_written_signal, self._set_triggers = soft_signal_r_and_setter(int, 0)
        self.name, self.file, self.uri, self._shape = name, file, uri, shape
        self.rows = 0
        self._triggers = 0
        self._bundles: list[ComposeStreamResourceBundle] = []
        self._emitted = 0

    def finish_trigger(self, row: bool) -> None:
        """A trigger finished, with a new row in the file or (abandoned) without one."""
        self.rows += int(row)
        self._triggers += 1
        self._set_triggers(self._triggers)

    def key(self, map_name: str) -> str:
        return f"{self.name}-{map_name}"

    async def make_datakeys(self, collections_per_event: int) -> dict[str, DataKey]:
        if collections_per_event != 1:
            raise ValueError(f"{self.name}: one measurement per event (collections_per_event=1)")
        shape = self.file.shape or self._shape()
        if shape is None:
            raise RuntimeError(f"{self.name}: a real camera's map size is known after its first measurement")
        keys: dict[str, DataKey] = {}
        for m in MAPS:
            key = DataKey(
                source=self.uri,
                shape=list(shape),
                dtype="array",
                dtype_numpy=m.dtype.str,
                external="STREAM:",
                dims=list(MAP_DIMS),
            )
            if m.units:
                key["units"] = m.units
            keys[self.key(m.name)] = key
        return keys

    async def make_stream_docs(
        self, collections_written: int, collections_per_event: int
    ) -> AsyncIterator[StreamAsset]:
        # the rows written since the last event (one per event in a step scan), whatever the
        # count of triggers says (collections_written)
        if self.rows and not self._bundles:
            compose = ComposeStreamResource()
            h, w = self.file.shape or (0, 0)
            self._bundles = [
                compose(
                    mimetype="application/x-hdf5",
                    uri=self.uri,
                    data_key=self.key(m.name),
                    # one measurement per event: stacked along a new first axis (the datasets' own)
                    parameters={
                        "dataset": f"/{m.name}",
                        "chunk_shape": (1, h, w),
                        "join_method": "stack",
                        "swmr": True,
                    },
                    uid=None,
                    validate=True,
                )
                for m in MAPS
            ]
            for bundle in self._bundles:
                yield "stream_resource", bundle.stream_resource_doc
        if self.rows > self._emitted:
            span: StreamRange = {"start": self._emitted, "stop": self.rows}
            self._emitted = self.rows
            for bundle in self._bundles:
                yield "stream_datum", bundle.compose_stream_datum(span)


class HdrMapsLogic(DetectorDataLogic):
    """The writer: one HDF5 file of maps per prepared plan (:class:`hdrcap.bluesky.hdf5.MapFile`),
    the run folders of its measurements beside it."""

    def __init__(self, paths: PathProvider, measurer: Measurer, attrs: dict[str, Any]) -> None:
        self.paths, self.measurer, self.attrs = paths, measurer, attrs
        self.provider: _MapsProvider | None = None
        self.runs: Path | None = None
        self._attempts = 0

    async def prepare_unbounded(self, datakey_name: str) -> StreamableDataProvider:
        info = self.paths(datakey_name)
        folder = Path(str(info.directory_path))
        folder.mkdir(parents=True, exist_ok=True)
        file = MapFile(folder / f"{info.filename}.h5", self.attrs)
        self.provider = _MapsProvider(
            datakey_name, file, f"{info.directory_uri}{info.filename}.h5", lambda: self.measurer.shape
        )
        self.runs, self._attempts = folder / info.filename, 0
        return self.provider

    def next_run_dir(self) -> Path:
        """The run folder of the next measurement (``RUNS/0000``, ``0001``, ... in the order
        they are started: a failed one keeps its number)."""
        if self.runs is None:
            raise RuntimeError("the detector was not prepared")
        folder = self.runs / f"{self._attempts:04d}"
        self._attempts += 1
        return folder

    async def stop(self) -> None:
        if self.provider is not None:
            self.provider.file.close()


class _SignalsProvider(ReadableDataProvider):
    def __init__(self, signals: Sequence[SignalR]) -> None:
        self.signals = list(signals)

    async def make_datakeys(self) -> dict[str, DataKey]:
        return await merge_gathered_dicts(s.describe() for s in self.signals)

    async def make_readings(self) -> dict[str, Reading]:
        return await merge_gathered_dicts(s.read(cached=False) for s in self.signals)


class HdrReadingsLogic(DetectorDataLogic):
    """The scalars of each measurement, read into its event; the achieved SNR is hinted."""

    datakey_suffix = "-readings"

    def __init__(self, signals: Sequence[SignalR]) -> None:
        self.signals = list(signals)

    async def prepare_single(self, datakey_name: str) -> ReadableDataProvider:
        return _SignalsProvider(self.signals)

    def get_hinted_fields(self, datakey_name: str) -> Sequence[str]:
        return [self.signals[0].name]


class HdrTriggerLogic(DetectorTriggerLogic):
    """Internal triggering, one measurement per trigger; its exposure times are the bracket's or
    the planner's, never a ``livetime``."""

    async def prepare_internal(self, num: int, livetime: float, deadtime: float) -> None:
        if num != 1:
            raise ValueError("one trigger is one hdrcap measurement: prepare for 1 exposure per trigger (step scans)")
        if livetime:
            raise ValueError("the exposure times come from times= or the planner (target_snr_db); livetime must be 0")

    async def default_trigger_info(self) -> TriggerInfo:
        return TriggerInfo()


class HdrAcquireLogic(DetectorAcquireLogic):
    """The controller: a trigger runs one measurement to its end (in a worker thread), then
    appends its maps and sets its readings; the trigger's status fails with the session's error."""

    def __init__(
        self,
        measurer: Measurer,
        maps: HdrMapsLogic,
        target_snr_db: SignalR[float],
        scene_scale: float | SignalR[float],
        setters: dict[str, Callable[[Any], None]],
    ) -> None:
        self.measurer, self.maps, self.target_snr_db = measurer, maps, target_snr_db
        self.scene_scale, self.setters = scene_scale, setters
        self.stop_event = StopEvent()
        self._inflight: asyncio.Future[Any] | None = None

    async def ensure_ready(self) -> None:
        await self._finish_inflight()
        await asyncio.get_running_loop().run_in_executor(None, self.measurer.open)

    async def start_acquiring(self) -> None:
        await self._finish_inflight()  # one the RunEngine gave up waiting for (a pause)
        target = await self.target_snr_db.get_value()
        scale = self.scene_scale if isinstance(self.scene_scale, float) else await self.scene_scale.get_value()
        provider = self.maps.provider
        if provider is None:
            raise RuntimeError("the detector was not prepared")
        stop = self.stop_event = StopEvent()
        measure = functools.partial(
            self.measurer.measure, self.maps.next_run_dir(), target_snr_db=target, scene_scale=float(scale), stop=stop
        )
        loop = asyncio.get_running_loop()
        self._inflight = loop.run_in_executor(None, measure)
        try:
            done = await asyncio.shield(self._inflight)
        except RunInterrupted as err:
            if not stop.is_set():
                raise
            self._abandon(provider, str(err))
            return
        self._inflight = None
        if stop.is_set():  # finished after the RunEngine paused or stopped: it re-triggers or tears down
            self._abandon(provider, f"{done.run_dir}: complete, but the RunEngine gave up on its trigger")
            return
        await loop.run_in_executor(None, provider.file.append, done.result, provider.rows)
        for name, setter in self.setters.items():
            setter(done.readings[name])
        provider.finish_trigger(row=True)

    @staticmethod
    def _abandon(provider: _MapsProvider, why: str) -> None:
        """End a trigger the RunEngine gave up on (a pause, a stop) without a row. Its status
        succeeds: a failure now would be an error of the RunEngine's cleanup, or of the run it
        resumes; no event reads it (a resumed plan triggers again, a stopped one reads nothing)."""
        log.warning("%s; not in the HDF5 file", why)
        provider.finish_trigger(row=False)

    async def wait_for_idle(self) -> None:
        return None  # a trigger returns once its measurement is written

    def interrupt(self, by: str) -> None:
        """Stop the measurement in progress before its next frame (its run folder resumable)."""
        self.stop_event.stop(signal.SIGINT, by=by)

    async def ensure_stopped(self) -> None:
        self.interrupt("the RunEngine (the detector was unstaged)")
        await self._finish_inflight()
        await asyncio.get_running_loop().run_in_executor(None, self.measurer.close)

    async def _finish_inflight(self) -> None:
        """Wait for a measurement still running (its error was the trigger's, if anyone waited)."""
        running, self._inflight = self._inflight, None
        if running is not None:
            with suppress(Exception):
                await asyncio.shield(running)


class HdrDetector(StandardDetector):
    """An hdrcap measurement as a Bluesky detector: one trigger meters and plans for a target
    SNR (or takes a fixed bracket), captures the bracket and its dark frames through the capture
    session (manifest, retries, verification) into a new run folder, merges it optimally and
    writes the irradiance, sigma, nexp and quality maps to an HDF5 file as external data.

    Parameters
    ----------
    camera : str
        ``mock:PRESET`` (the simulated camera: camera-A, camera-B, camera-R) or
        ``gphoto2[:MODEL]`` (a real camera through libgphoto2).
    path : str, path-like or ophyd_async.core.PathProvider
        Folder of the HDF5 files (one per staged plan, ``NAME-DATE.h5``) and the run folders
        (``NAME-DATE/0000``, ...); or a PathProvider naming them.
    name : str
        Device name; the data keys are ``NAME-irradiance``, ``NAME-snr_median_db``, ...
    times : sequence of float
        Exposure times of a fixed bracket, s.
    target_snr_db : float, optional
        Plan each measurement for this SNR, dB (metering and the planner); ``det.target_snr_db``
        is a signal a plan may set between points (NaN: the fixed bracket).
    calibration : str or path-like, optional
        A calibration file (``hdrcap calibrate``) or a simulator preset; a real camera needs one.
    size : str, optional
        Simulated camera only: mosaic ``WIDTHxHEIGHT`` (default 256x192).
    scene_scale : float or SignalR[float]
        Simulated camera only: the factor on the scene's irradiance, or a signal read at each
        trigger (a motor's readback: its position is the light level).
    **options
        Further options of :func:`hdrcap.acquire.capture.job.capture_job`: ``dark_strategy``,
        ``dark_count``, ``block_light``, ``cover_command``, ``uncover_command``,
        ``max_exposures``, ``scene``, ``seed``, ``faults``, ``port``, ``serial``, ``iso``, ``enforce``.

    Raises
    ------
    InputError
        A bad option, with the job's one-line message.
    """

    def __init__(
        self,
        camera: str = "mock:camera-B",
        *,
        path: str | os.PathLike[str] | PathProvider,
        name: str = "hdr",
        times: Sequence[float] = (),
        target_snr_db: float | None = None,
        calibration: str | os.PathLike[str] | None = None,
        size: str | None = None,
        scene_scale: float | SignalR[float] = 1.0,
        **options: Any,
    ) -> None:
        folder = path if isinstance(path, (str, os.PathLike)) else tempfile.gettempdir()
        self.measurer = Measurer(
            camera,
            times=times,
            target_snr_db=target_snr_db,
            calibration=calibration,
            size=size,
            folder=folder,
            **options,
        )
        if not isinstance(scene_scale, SignalR):
            scene_scale = float(scene_scale)
            if scene_scale != 1.0 and not self.measurer.simulated:
                raise InputError("scene_scale is for the simulated camera")
        settings = self.measurer.settings()
        self.target_snr_db = soft_signal_rw(
            float, math.nan if target_snr_db is None else float(target_snr_db), units="dB"
        )
        setters: dict[str, Callable[[Any], None]] = {}
        readings = []
        for r in READINGS:
            if r.name == "scene_scale" and not self.measurer.simulated:
                continue
            initial = math.nan if r.dtype is float else r.dtype()
            sig, setters[r.name] = soft_signal_r_and_setter(r.dtype, initial, units=r.units)
            setattr(self, r.name, sig)
            readings.append(sig)
        config = []
        for key in ("camera", "plan", "calibration", "merge_options"):
            value = settings[key]
            sig, _set = soft_signal_r_and_setter(
                str, value if isinstance(value, str) else json.dumps(value, sort_keys=True)
            )
            setattr(self, key, sig)
            config.append(sig)
        paths = FolderPathProvider(path) if isinstance(path, (str, os.PathLike)) else path
        maps = HdrMapsLogic(paths, self.measurer, settings)
        acquire = HdrAcquireLogic(self.measurer, maps, self.target_snr_db, scene_scale, setters)
        self.add_detector_logics(
            HdrTriggerLogic(),
            acquire,
            maps,
            HdrReadingsLogic(readings),
        )
        self.add_config_signals(*config)
        self._acquire = acquire
        super().__init__(name=name)

    def pause(self) -> None:
        """The RunEngine paused (Ctrl-C): the measurement in progress stops before its next frame,
        its run folder resumable; ``RE.resume()`` triggers the point again, in a new run folder."""
        self._acquire.interrupt("the RunEngine (paused)")

    def resume(self) -> None:
        """The RunEngine resumes: the next trigger measures (nothing to restore)."""
