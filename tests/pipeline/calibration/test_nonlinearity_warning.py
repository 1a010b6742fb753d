"""The photon-transfer non-linearity warning on flats simulated by the camera-R preset: its soft
loss of response near full well (E' = E (1 - n (E/FW)^p), n = 0.2 %, p = 8) switched on fires the
warning at the level where the variance departs by more than the threshold, switched off it
does not (the rest of camera-R's realism, defects, shutter errors, bias drift, stays on)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hdrcap.experiments.calibrated import simulated_frames
from hdrcap.mock_camera import SimulatedSensor, preset
from hdrcap.pipeline.calibration import calibrate

SHAPE = (384, 384)
#: Flat levels, fraction of the range above bias: the photon-transfer series up to 97 %.
LEVELS = (0.05, 0.15, 0.3, 0.45, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97)


def _calibrate(nonlinearity: float):
    """Camera-R with the given non-linearity: bias pair, a saturation frame and one flat pair per
    level (the level set by the exposure time at a fixed irradiance)."""
    spec = preset("camera-R", nonlinearity=nonlinearity)
    sensor = SimulatedSensor(spec, SHAPE, seed=11)
    rng = np.random.default_rng(11)
    span = spec.nominal_params().v_sat - spec.mu_R
    X = span / spec.g / 0.1  # e-/s: the full range at 0.1 s

    def flats():
        for k, f in enumerate(LEVELS):
            yield from simulated_frames(sensor, X, 0.1 * f, 2, rng, f"flat{k:02d}")

    return spec, calibrate(
        simulated_frames(sensor, 0.0, 1e-4, 2, rng, "bias", dark=True),
        simulated_frames(sensor, X, 0.2, 1, rng, "sat"),
        flats(),
        white_level=spec.white_level,
    )


def _expected_departure(spec, level: float) -> float:
    """Relative departure of the variance from g mu at ``level`` of full well under the
    simulator's response: slope^2 / (1 - n x^p) - 1 ~ -(2p + 1) n x^p."""
    n, p = spec.nonlinearity, spec.nonlinearity_power
    return -(2 * p + 1) * n * level**p


def test_warning_fires_near_full_well_with_the_level_and_not_without_it():
    spec, on = _calibrate(preset("camera-R").nonlinearity)
    warnings = [w for w in on.provenance["calibration"]["warnings"] if "not linear" in w]
    print(warnings)
    assert len(warnings) == 1
    m = re.search(r"from (\d+) % of saturation .* variance ([+-][\d.]+) % from g mu", warnings[0])
    level, departure = int(m.group(1)) / 100, float(m.group(2)) / 100
    # the variance departs by more than the 1 % threshold from 86 % of full well (about the same
    # fraction of v_sat - mu_R); the warning names the first level where it is also 4 sigma out
    assert _expected_departure(spec, 0.86) == pytest.approx(-0.01, abs=0.002)
    assert 0.85 <= level <= 0.97 and departure < -0.01
    assert departure == pytest.approx(_expected_departure(spec, level), abs=0.006)  # measured: within 0.35 %
    assert on.params.g == pytest.approx(spec.g, rel=0.01)  # the 0-70 % fit is not affected
    _spec, off = _calibrate(0.0)
    assert not [w for w in off.provenance["calibration"]["warnings"] if "not linear" in w]
    assert off.params.g == pytest.approx(spec.g, rel=0.01)
