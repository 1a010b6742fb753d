"""Calibration at the limits of its input: dark signal as large as the light, flats close to
saturation, clipped photosites.

Every expectation comes from the simulator's truth (g, the dark current, the clip levels), never
from the calibration code's own output.
"""

from __future__ import annotations

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS, SimulatedSensor
from hdrcap.pipeline.calibration import calibrate
from hdrcap.pipeline.io import RawFrame


def shots(sensor, X, t, n, rng, kind, dark=False):
    """Yield n simulated RawFrames (lazily, as a camera would deliver them)."""
    for i in range(n):
        yield RawFrame(
            sensor.expose(X, t, dark=dark, rng=rng), t, path=f"{kind}_{i:03d}.dng", white_level=sensor.spec.white_level
        )


def test_photon_transfer_gain_with_dark_signal_as_large_as_the_light():
    """Dim 1 s flats (25-230 e-) over a dark signal of 100 e-: the dark shot noise must leave
    the variance as the dark mean leaves the mean (EMVA 1288), else g comes out ~50 % high."""
    spec = PRESETS["camera-B"].replace(dark_current=100.0, dcnu=0.05)
    for seed in range(3):
        sensor = SimulatedSensor(spec, (128, 128), seed=seed)
        rng = np.random.default_rng([seed, 14])
        t = 1.0

        flats = (fr for f in np.linspace(0.03, 0.25, 8) for fr in shots(sensor, f * 1000 / spec.g / t, t, 2, rng, "f"))
        darks = (fr for td in (0.25, 0.5, 1, 1.5, 2, 3) for fr in shots(sensor, 0, td, 2, rng, "d", dark=True))
        cal = calibrate(
            shots(sensor, 0, 1e-4, 2, rng, "bias", dark=True),
            shots(sensor, 1e6, 1, 1, rng, "sat"),
            flats,
            darks,
            white_level=spec.white_level,
        )
        info = cal.provenance["calibration"]
        assert "photon-transfer" in info["gain_method"]
        assert "dark temporal variance" in info["ptc"]["dark_correction"]
        dark_e = float(sensor.dark_current_map().mean()) * t
        light_e = np.array(info["ptc"]["means"]) / spec.g
        assert 0.25 * dark_e < light_e.min() and light_e.max() < 3 * dark_e  # comparable signals
        assert cal.params.g == pytest.approx(spec.g, rel=0.03)
        assert abs(cal.params.g - spec.g) < 4 * cal.stderr["g"] < 0.05 * spec.g
