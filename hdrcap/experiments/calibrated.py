"""Calibrations estimated from simulated frames, for the end-to-end tests of the merge: bias
pairs, one saturation frame, flats at about 75 % (or a given fraction) of the range above bias
and the documented dark series at six times (hdrcap simulate --calibration-set)."""

from __future__ import annotations

import numpy as np

from hdrcap.mock_camera import SimulatedSensor
from hdrcap.pipeline.calibration import calibrate
from hdrcap.pipeline.io.raw import RawFrame

DARK_TIMES = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)


def shots(sensor, X, t, n, rng, kind, dark=False):
    """``n`` simulated frames of irradiance ``X`` (e-/s) at ``t`` s as RawFrames."""
    for i in range(n):
        yield RawFrame(
            sensor.expose(X, t, dark=dark, rng=rng), t, path=f"{kind}_{i:03d}.dng", white_level=sensor.spec.white_level
        )


def calibrated_sensor(
    spec, seed, shape, *, flat_level=0.75, n_flats=16, n_darks=2, dark_sink=None, ptc_levels=(), ptc_pairs=1
):
    """A :class:`SimulatedSensor` and the calibration estimated from its frames (flats at
    ``flat_level`` of the range above bias, the dark series at :data:`DARK_TIMES`), and
    ``ptc_pairs`` flat pairs at each fraction of ``ptc_levels`` (a photon-transfer series at the
    flats' irradiance, varying the exposure time, as ``hdrcap simulate --calibration-set``)."""
    sensor = SimulatedSensor(spec, shape, seed=seed)
    rng = np.random.default_rng([seed, 53])
    t_flat = 0.01
    X = flat_level * (spec.nominal_params().v_sat - spec.mu_R) / spec.g / t_flat

    def darks():
        for t in DARK_TIMES:
            yield from shots(sensor, 0.0, t, n_darks, rng, f"dark{t:g}", dark=True)

    def flats():
        yield from shots(sensor, X, t_flat, n_flats, rng, "flat")
        for f in ptc_levels:
            yield from shots(sensor, X, t_flat * f / flat_level, 2 * ptc_pairs, rng, f"ptc{f:g}")

    cal = calibrate(
        shots(sensor, 0.0, 1e-4, 2, rng, "bias", dark=True),
        shots(sensor, X, 0.1, 1, rng, "sat"),
        flats(),
        darks(),
        white_level=spec.white_level,
        dark_sink=dark_sink,
    )
    return sensor, cal


def bracket(sensor, X, times, seed):
    """A bracket of ``X`` (e-/s) at ``times`` (s) and a matched dark frame per time, as
    RawFrames (seeded)."""
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
