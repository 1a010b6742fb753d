"""Every variance term of the merge is floored: a dark-current map with negative values (a raw
regression, or any map a user supplies) can no longer make a variance negative, a photosite with
no usable sample is reported as such (nexp = 0, sigma = 0), never with a placeholder sigma.

Checked on a completely dark scene at 100-300 s with calibrations estimated from simulated
camera-R frames, against the simulator's truth (the irradiance is 0)."""

import numpy as np
import pytest

from hdrcap.experiments.calibrated import calibrated_sensor
from hdrcap.mock_camera import preset
from hdrcap.pipeline.merge.accumulator import merge_arrays
from hdrcap.pipeline.params import Calibration, SensorParams

SHAPE = (96, 96)
TIMES = (100.0, 200.0, 300.0)


@pytest.fixture(scope="module")
def dark_scene():
    masters = []
    sensor, cal = calibrated_sensor(preset("camera-R"), seed=3, shape=SHAPE, dark_sink=masters.append)
    # the raw per-photosite regression of the master darks (before the shrinkage): partly negative
    t = np.array([m.exposure_time for m in masters])
    y = np.stack([m.data.astype(np.float64).ravel() for m in masters])
    raw = (np.polyfit(t, y, 1)[0] / cal.params.g).reshape(SHAPE)
    rng = np.random.default_rng([3, 11])
    lights = [sensor.expose(0.0, t, dark=True, rng=rng) for t in TIMES]
    darks = [sensor.expose(0.0, t, dark=True, rng=rng) for t in TIMES]
    normal = ~np.logical_or.reduce([sensor.defects[k] for k in sensor.defects])
    return sensor, cal, raw, lights, darks, normal


def _no_placeholder(res, normal):
    """Every photosite has a finite irradiance; nexp > 0 comes with a finite sigma > 0, nexp = 0
    with sigma = 0; no normal photosite of a dark scene is reported as saturated."""
    assert np.all(np.isfinite(res.irradiance)) and np.all(np.isfinite(res.sigma))
    used = res.nexp > 0
    assert np.all(res.sigma[used] > 0)
    assert np.all(res.sigma[~used] == 0)
    assert not np.any(~used & normal), int((~used & normal).sum())


@pytest.mark.parametrize("which", ["estimated", "raw regression"])
def test_dark_scene_matched_darks(dark_scene, which):
    sensor, cal, raw, lights, darks, normal = dark_scene
    if which == "raw regression":
        assert raw.min() < -0.4  # enough to make g^2 t (u + D) + 2 sigma_R^2 negative at 300 s
        cal = cal.replace(dark_current_map=raw.astype(np.float32))
    res = merge_arrays(lights, TIMES, cal, darks=darks)
    _no_placeholder(res, normal)
    # matched darks: no systematic term, z = (estimate - 0) / sigma against the truth (the raw
    # map's floored photosites understate their dark shot noise: a few z near 6, not hundreds)
    z = res.irradiance[normal] / res.sigma[normal]
    assert np.max(np.abs(z)) < (6.0 if which == "estimated" else 10.0), float(np.max(np.abs(z)))
    assert 0.85 < np.std(z) < 1.15, float(np.std(z))


@pytest.mark.parametrize("which", ["estimated", "raw regression"])
def test_dark_scene_model_strategy(dark_scene, which):
    sensor, cal, raw, lights, _darks, normal = dark_scene
    if which == "raw regression":
        cal = cal.replace(dark_current_map=raw.astype(np.float32))
    res = merge_arrays(lights, TIMES, cal)
    _no_placeholder(res, normal)
    # the dark-current map's own error is the whole error here: within a few e-/s, never thousands
    err = np.abs(res.irradiance[normal] - 0.0)
    assert np.max(err) < 5.0, float(np.max(err))


@pytest.mark.parametrize("dark_strategy", ["matched", "model"])
def test_negative_dark_current_map_gives_the_read_noise_floor(dark_strategy):
    """D = -5 e-/s everywhere: the variance terms in D are floored at 0, so each sample's
    variance is (g^2 t a max(mu, 0) + (1 + k) sigma_R^2) / (t g a)^2, computed here from the
    model's definition (Eq. 3, 5, 6, 12)."""
    p = SensorParams(g=0.5, mu_R=100.0, sigma2_R=4.0, v_sat=4000.0, white_level=4095.0, dark_current=0.0)
    cal = Calibration(p, dark_current_map=np.full((8, 8), -5.0, np.float32))
    rng = np.random.default_rng(5)
    times = (50.0, 100.0, 300.0)
    vals = [np.rint(100.0 + rng.normal(0, 2.0, (8, 8))).astype(np.uint16) for _ in times]
    darks = (
        [np.rint(100.0 + rng.normal(0, 2.0, (8, 8))).astype(np.uint16) for _ in times]
        if dark_strategy == "matched"
        else None
    )
    res = merge_arrays(vals, times, cal, darks=darks, dark_strategy=dark_strategy)
    assert np.all(res.nexp == 3)
    k = 1.0 if dark_strategy == "matched" else 0.0
    mu = np.maximum(res.irradiance.astype(np.float64), 0.0)
    w = sum((t * p.g) ** 2 / (p.g**2 * t * mu + (1 + k) * p.sigma2_R) for t in times)
    np.testing.assert_allclose(res.sigma, 1.0 / np.sqrt(w), rtol=2e-3)
