"""The simulated sensor against the physics it claims (Eq. 3, Eq. 5, PRNU, dark current,
clipping). Expected values are computed from the spec, never from the estimator."""

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS, SimulatedSensor, preset
from hdrcap.mock_camera.scenes import SCENES, make_scene


def _moments(frames):
    st = np.stack(frames).astype(np.float64)
    return st.mean(0), st.var(0, ddof=1)


@pytest.mark.parametrize("name", ["camera-A", "camera-B"])
def test_mean_and_variance_follow_eq3(name):
    spec = preset(name, prnu=0.0, dcnu=0.0)
    sensor = SimulatedSensor(spec, (64, 64), seed=3)
    X, t = 2000.0, 0.1  # 200 electrons: far from saturation for both cameras
    frames = [sensor.expose(X, t) for _ in range(200)]
    mean, var = _moments(frames)
    e = t * (X + spec.dark_current)
    exp_mean = spec.g * e + spec.mu_R
    exp_var = spec.g**2 * e + spec.sigma2_R  # Eq. 3
    n = 200 * 64 * 64
    # pooled over photosites: sampling error of the mean ~ sqrt(var/n); of the variance ~ var*sqrt(2/(k-1))
    assert mean.mean() == pytest.approx(exp_mean, abs=5 * np.sqrt(exp_var / n))
    assert var.mean() == pytest.approx(exp_var, rel=5 * np.sqrt(2 / 199) / 64)


@pytest.mark.parametrize("name", ["camera-A", "camera-B"])
def test_dark_frame_follows_eq5(name):
    spec = preset(name, dcnu=0.0, dark_current=50.0)
    sensor = SimulatedSensor(spec, (64, 64), seed=4)
    t = 2.0
    frames = [sensor.expose(1e6, t, dark=True) for _ in range(200)]  # light blocked: X ignored
    mean, var = _moments(frames)
    exp_mean = spec.g * t * 50.0 + spec.mu_R
    exp_var = spec.g**2 * t * 50.0 + spec.sigma2_R  # Eq. 5
    assert mean.mean() == pytest.approx(exp_mean, abs=5 * np.sqrt(exp_var / (200 * 4096)))
    assert var.mean() == pytest.approx(exp_var, rel=5 * np.sqrt(2 / 199) / 64)


def test_prnu_pattern_has_configured_spread_and_shows_in_flats():
    spec = preset("camera-A", prnu=0.02, dcnu=0.0)
    sensor = SimulatedSensor(spec, (128, 128), seed=5)
    assert sensor.prnu.mean() == pytest.approx(1.0, abs=0.002)
    assert sensor.prnu.std() == pytest.approx(0.02, rel=0.05)
    X, t = 1e5, 0.1  # 10^4 e-
    flat = np.mean([sensor.expose(X, t).astype(float) for _ in range(16)], axis=0)
    signal = (flat - spec.mu_R) / (spec.g * X * t)
    assert np.corrcoef(signal.ravel(), sensor.prnu.ravel())[0, 1] > 0.95


def test_dark_current_doubles_with_temperature_and_has_dcnu():
    spec = preset("camera-B", dark_current=2.0, dcnu=0.3, temperature_ref=20.0, doubling_temperature=6.0)
    assert spec.dark_current_at(26.0) == pytest.approx(4.0)
    assert spec.dark_current_at(14.0) == pytest.approx(1.0)
    sensor = SimulatedSensor(spec, (128, 128), seed=6)
    d = sensor.dark_current_map(20.0)
    assert d.mean() == pytest.approx(2.0, rel=0.02)
    assert d.std() / d.mean() == pytest.approx(0.3, rel=0.05)
    frames = [sensor.expose(0.0, 10.0, dark=True, temperature=32.0) for _ in range(20)]
    mean = np.mean(frames, axis=0).mean()
    assert mean == pytest.approx(spec.mu_R + spec.g * 10.0 * 8.0, rel=0.01)


def test_hot_pixels():
    spec = preset("camera-B", hot_pixel_fraction=0.01, hot_pixel_factor=100.0, dcnu=0.0)
    sensor = SimulatedSensor(spec, (100, 100), seed=7)
    hot = sensor.dark_pattern == 100.0
    assert 50 < hot.sum() < 150


def test_clipping_at_full_well_and_adc():
    a = PRESETS["camera-A"]  # full well clips before the ADC
    sa = SimulatedSensor(a, (64, 64), seed=8)
    v = sa.expose(1e9, 1.0)
    assert v.max() < a.white_level
    assert v.mean() == pytest.approx(a.mu_R + a.g * a.full_well, abs=0.2)
    # mean - 3 std of a saturation frame is the published v_sat (Table 2)
    assert v.mean() - 3 * v.std() == pytest.approx(3709.0, rel=0.01)
    b = PRESETS["camera-B"]  # the ADC clips first
    vb = SimulatedSensor(b, (64, 64), seed=9).expose(1e9, 1.0)
    assert np.all(vb == b.white_level)
    # values are never negative: clipped at 0 too
    low = SimulatedSensor(preset("camera-B", mu_R=0.0), (64, 64), seed=1).expose(0.0, 1e-3)
    assert low.min() == 0 and low.dtype == np.uint16


def test_seeded_reproducible():
    spec = PRESETS["camera-B"]
    a = SimulatedSensor(spec, (16, 16), seed=11).expose(100.0, 0.1)
    b = SimulatedSensor(spec, (16, 16), seed=11).expose(100.0, 0.1)
    c = SimulatedSensor(spec, (16, 16), seed=12).expose(100.0, 0.1)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@pytest.mark.parametrize("name", SCENES)
def test_scenes_span_requested_range(name):
    X = make_scene(name, (96, 128), decades=3.0, x_max=1e4)
    assert X.shape == (96, 128) and np.all(np.isfinite(X))
    assert X.max() == pytest.approx(1e4)
    if name != "flat":
        assert X.min() >= 10.0 * (1 - 1e-9) and X.max() / X.min() <= 1e3 * (1 + 1e-9)
    with pytest.raises(ValueError):
        make_scene("nope")


@pytest.mark.parametrize(
    "options, digest",
    [
        ({}, "c871365578517b488e7d8abe9db286d153f2fb767c74e11032534cb5a4845f89"),
        (
            {"description": "dark frame", "cfa": "BGGR", "f_number": 2.8, "serial": "S1"},
            "74e80a1029ab5ec7295eb40427a290e96a30ec6c859cb70d86ff8d2e2482a499",
        ),
    ],
)
def test_dng_bytes_are_stable(options, digest):
    """The DNG writer's output, byte for byte (seeded mosaic, fixed timestamp)."""
    import datetime as dt
    import hashlib
    import io

    from hdrcap.mock_camera.dng import write_dng

    mosaic = np.random.default_rng(1).integers(0, 4096, (30, 40), dtype=np.uint16)
    buf = io.BytesIO()
    write_dng(
        buf,
        mosaic,
        exposure_time=1 / 3,
        iso=200,
        black_level=64.5,
        white_level=4095,
        timestamp=dt.datetime(2024, 1, 2, 3, 4, 5),
        **options,
    )
    assert hashlib.sha256(buf.getvalue()).hexdigest() == digest
