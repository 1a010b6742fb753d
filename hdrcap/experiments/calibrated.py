"""Calibrations estimated from the simulator's own frames, and brackets as RawFrames: what the
accuracy experiments, the tests and the benchmarks merge with when the calibration must be a
user's (estimated, with its errors), never the simulator's truth.

The calibration frames (Sec. 6, through :func:`hdrcap.pipeline.calibration.calibrate`): bias
frames at 1e-4 s, one saturation frame at 0.1 s, flats at ``flat_level`` of the range above the
bias (0.01 s), optionally a photon-transfer series of flat pairs at other levels (varying the
exposure time, as ``hdrcap simulate --calibration-set`` does) and a dark series at several
times. Every frame is drawn from a seeded generator.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from hdrcap.mock_camera.sensor import SensorSpec, SimulatedSensor
from hdrcap.pipeline.calibration import calibrate
from hdrcap.pipeline.io.raw import RawFrame
from hdrcap.pipeline.params import Calibration

__all__ = [
    "DARK_SERIES",
    "DARK_TIMES",
    "FLAT_TIME",
    "bracket",
    "calibrated_sensor",
    "estimated_calibration",
    "simulated_frames",
]

#: Exposure times of the dark series of :func:`estimated_calibration`, s.
DARK_SERIES = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
#: Exposure times of the dark series of :func:`calibrated_sensor`, s (the documented series of
#: ``hdrcap simulate --calibration-set``).
DARK_TIMES = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
#: Exposure time of the flats, s (the saturation frame: ten times as long).
FLAT_TIME = 0.01


def simulated_frames(
    sensor: SimulatedSensor,
    X: float | np.ndarray,
    t: float,
    n: int,
    rng: np.random.Generator,
    kind: str,
    dark: bool = False,
) -> Iterator[RawFrame]:
    """``n`` simulated frames of irradiance ``X`` at ``t``, drawn lazily as a camera delivers them.

    Parameters
    ----------
    sensor : SimulatedSensor
        The sensor (its fixed patterns are those of every frame).
    X : float or numpy.ndarray
        Irradiance, e-/s per photosite (a scalar or a map of the sensor's shape).
    t : float
        Exposure time, s.
    n : int
        Number of frames.
    rng : numpy.random.Generator
        Temporal noise of the frames.
    kind : str
        Name stem of the frames (``<kind>_000.dng``, ...), as calibration messages show them.
    dark : bool
        Shutter closed (dark frames).

    Yields
    ------
    RawFrame
        DN frames with their exposure time and the sensor's white level.
    """
    for i in range(n):
        yield RawFrame(
            sensor.expose(X, t, dark=dark, rng=rng), t, path=f"{kind}_{i:03d}.dng", white_level=sensor.spec.white_level
        )


def estimated_calibration(
    sensor: SimulatedSensor,
    rng: np.random.Generator,
    *,
    flat_level: float = 0.75,
    n_bias: int = 2,
    n_flats: int = 16,
    dark_times: Sequence[float] = DARK_SERIES,
    n_per_dark: int = 2,
    ptc_levels: Sequence[float] = (),
    ptc_pairs: int = 1,
    dark_sink: Callable[[Any], Any] | None = None,
) -> Calibration:
    """A calibration estimated from simulated frames of ``sensor`` (Sec. 6), never its truth.

    Parameters
    ----------
    sensor : SimulatedSensor
        The sensor (its fixed patterns are those of the bracket it will calibrate).
    rng : numpy.random.Generator
        Temporal noise of the calibration frames.
    flat_level : float
        Level of the flats, fraction of the nominal range above the bias (0.75: 75 %).
    n_bias, n_flats, n_per_dark : int
        Bias frames, flat fields (at ``flat_level``, :data:`FLAT_TIME` s) and dark frames per
        time of the dark series.
    dark_times : sequence of float
        Exposure times of the dark series, s (at least 6 for the dark-current map).
    ptc_levels : sequence of float
        Further photon-transfer levels, fractions of the range (flat pairs at the flats'
        irradiance with the exposure time scaled), e.g. 10 levels from 0.05 to 0.7.
    ptc_pairs : int
        Flat pairs at each level of ``ptc_levels``.
    dark_sink : callable, optional
        Receives each master dark of the series (see :func:`~hdrcap.pipeline.calibration.calibrate`).

    Returns
    -------
    Calibration
        With the standard-error maps, the defect map and the provenance of the calibration
        workflow.
    """
    spec = sensor.spec
    X = flat_level * (spec.nominal_params().v_sat - spec.mu_R) / spec.g / FLAT_TIME

    def flats() -> Iterator[RawFrame]:
        yield from simulated_frames(sensor, X, FLAT_TIME, n_flats, rng, "flat")
        for f in ptc_levels:
            yield from simulated_frames(sensor, X, FLAT_TIME * f / flat_level, 2 * ptc_pairs, rng, f"ptc{f:g}")

    def darks() -> Iterator[RawFrame]:
        for t in dark_times:
            yield from simulated_frames(sensor, 0.0, t, n_per_dark, rng, f"dark{t:g}", dark=True)

    return calibrate(
        simulated_frames(sensor, 0.0, 1e-4, n_bias, rng, "bias", dark=True),
        simulated_frames(sensor, X, 10 * FLAT_TIME, 1, rng, "sat"),
        flats(),
        darks(),
        white_level=spec.white_level,
        dark_sink=dark_sink,
    )


def calibrated_sensor(
    spec: SensorSpec,
    seed: int,
    shape: tuple[int, int],
    *,
    flat_level: float = 0.75,
    n_flats: int = 16,
    n_darks: int = 2,
    dark_sink: Callable[[Any], Any] | None = None,
    ptc_levels: Sequence[float] = (),
    ptc_pairs: int = 1,
) -> tuple[SimulatedSensor, Calibration]:
    """A simulated sensor and the calibration estimated from its frames, both from one seed.

    The dark series is :data:`DARK_TIMES` (``hdrcap simulate --calibration-set``'s); the
    calibration frames' noise comes from ``numpy.random.default_rng([seed, 53])``.

    Parameters
    ----------
    spec : SensorSpec
        The sensor's specification (a preset, possibly changed).
    seed : int
        Seed of the sensor's fixed patterns and of the calibration frames.
    shape : tuple of int
        Photosites (rows, columns).
    flat_level, n_flats, ptc_levels, ptc_pairs, dark_sink
        As for :func:`estimated_calibration`.
    n_darks : int
        Dark frames per time of the dark series.

    Returns
    -------
    tuple of SimulatedSensor and Calibration
        The sensor and its estimated calibration.
    """
    sensor = SimulatedSensor(spec, shape, seed=seed)
    cal = estimated_calibration(
        sensor,
        np.random.default_rng([seed, 53]),
        flat_level=flat_level,
        n_flats=n_flats,
        dark_times=DARK_TIMES,
        n_per_dark=n_darks,
        ptc_levels=ptc_levels,
        ptc_pairs=ptc_pairs,
        dark_sink=dark_sink,
    )
    return sensor, cal


def bracket(
    sensor: SimulatedSensor, X: float | np.ndarray, times: Sequence[float], seed: int
) -> tuple[list[RawFrame], list[RawFrame]]:
    """A bracket of ``X`` at ``times`` and a matched dark frame per time (seeded).

    Parameters
    ----------
    sensor : SimulatedSensor
        The sensor.
    X : float or numpy.ndarray
        Irradiance, e-/s per photosite.
    times : sequence of float
        Exposure times, s.
    seed : int
        Seed of the frames' noise (``numpy.random.default_rng([seed, 59])``).

    Returns
    -------
    tuple of list of RawFrame
        The frames (``f<i>.dng``) and their dark frames (``d<i>.dng``), in the order of ``times``.
    """
    rng = np.random.default_rng([seed, 59])
    white = sensor.spec.white_level
    frames = [
        RawFrame(sensor.expose(X, t, rng=rng), t, path=f"f{i}.dng", white_level=white) for i, t in enumerate(times)
    ]
    darks = [
        RawFrame(sensor.expose(X, t, dark=True, rng=rng), t, path=f"d{i}.dng", white_level=white)
        for i, t in enumerate(times)
    ]
    return frames, darks
