"""The simulator's realistic effects (defects, shutter errors, row/column noise, bias drift,
black-level clipping, non-linearity) against the values configured in the spec.

Expected values come from the spec (binomial counts, uniform and normal moments), never from
the estimator; every effect is off in the presets camera-A and camera-B."""

import dataclasses

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS, SimulatedSensor, preset
from hdrcap.mock_camera.sensor import DEFECT_KINDS, REALISTIC, SensorSpec

SHAPE = (256, 256)
N = SHAPE[0] * SHAPE[1]


@pytest.mark.parametrize("name", ["camera-A", "camera-B"])
def test_ideal_presets_have_every_effect_off(name):
    spec = PRESETS[name]
    defaults = {f.name: f.default for f in dataclasses.fields(SensorSpec)}
    for key in REALISTIC:
        if key not in ("dark_current", "dcnu"):
            assert getattr(spec, key) == defaults[key], key
    sensor = SimulatedSensor(spec, (32, 32), seed=1)
    assert not any(sensor.defects[k].any() for k in DEFECT_KINDS)
    assert sensor.shutter_factor(1 / 125) == 1.0


def test_realistic_preset_and_option_agree():
    r = preset("camera-A", realistic=True)
    assert preset("camera-R").replace(name=r.name, model=r.model) == r
    assert r.hot_pixel_fraction == 1e-3 and r.dead_fraction == 5e-4 and r.shutter_error == 0.03
    assert preset("camera-B", realistic=True, dark_current=7.0).dark_current == 7.0


def test_defect_fractions_are_binomial_and_disjoint():
    spec = preset("camera-B", realistic=True, stuck_fraction=1e-3)
    s = SimulatedSensor(spec, SHAPE, seed=21)
    d = s.defects
    total = sum(d[k].astype(int) for k in DEFECT_KINDS)
    assert total.max() == 1  # disjoint
    for kind, f in (
        ("dead", spec.dead_fraction),
        ("weak", spec.weak_fraction),
        ("stuck", spec.stuck_fraction),
        ("hot", spec.hot_pixel_fraction * (1 - spec.dead_fraction - spec.weak_fraction - 1e-3)),
    ):
        mean = f * N
        assert abs(d[kind].sum() - mean) < 5 * np.sqrt(mean), kind
    # truth maps: dead a = 0, weak a = weak_factor x (1 + PRNU), hot dark current factor x mean
    assert np.all(s.prnu[d["dead"]] == 0)
    assert np.mean(s.prnu[d["weak"]]) == pytest.approx(spec.weak_factor, rel=0.01)
    assert np.all(s.dark_pattern[d["hot"]] == spec.hot_pixel_factor)
    assert np.array_equal(SimulatedSensor(spec, SHAPE, seed=21).defects["hot"], d["hot"])


def test_defects_show_in_frames():
    spec = preset(
        "camera-A",
        realistic=True,
        dead_fraction=0.01,
        weak_fraction=0.01,
        stuck_fraction=0.01,
        hot_pixel_fraction=0.01,
        shutter_error=0.0,
        shutter_jitter=0.0,
        bias_drift=0.0,
        nonlinearity=0.0,
    )
    s = SimulatedSensor(spec, (128, 128), seed=22)
    d = s.defects
    good = ~(d["dead"] | d["weak"] | d["stuck"] | d["hot"])
    X, t = 1e5, 0.05  # 5000 e-
    flats = np.stack([s.expose(X, t) for _ in range(8)]).astype(float)
    darks = np.stack([s.expose(0.0, 10.0, dark=True) for _ in range(8)]).astype(float)
    sig = flats.mean(0) - spec.mu_R
    good_sig = sig[good].mean()
    assert good_sig == pytest.approx(spec.g * X * t, rel=0.01)
    # dead: only the dark signal (2 e-/s x 0.05 s): below a percent of the good signal
    assert abs(sig[d["dead"]].mean()) < 0.01 * good_sig
    assert sig[d["weak"]].mean() / good_sig == pytest.approx(spec.weak_factor, rel=0.01)
    # stuck: the drawn constant, whatever the light and the time, without noise
    assert np.all(flats[:, d["stuck"]] == s.stuck_values) and np.all(darks[:, d["stuck"]] == s.stuck_values)
    # hot: 100 x the mean dark current (lognormal DCNU of the others has mean 1)
    dark_sig = darks.mean(0) - spec.mu_R
    expect_hot = spec.g * 10.0 * spec.dark_current * spec.hot_pixel_factor
    assert dark_sig[d["hot"]].mean() == pytest.approx(expect_hot, rel=0.01)
    assert dark_sig[good].mean() == pytest.approx(spec.g * 10.0 * spec.dark_current, rel=0.02)


def test_shutter_error_is_systematic_uniform_and_seeded():
    spec = preset("camera-B", shutter_error=0.03)
    s = SimulatedSensor(spec, (8, 8), seed=23)
    times = [2.0**k for k in np.arange(-13, 5, 1 / 3)]
    e = np.array([s.shutter_factor(t) - 1 for t in times])
    assert np.all(np.abs(e) <= 0.03)
    assert np.std(e) == pytest.approx(0.03 / np.sqrt(3), rel=0.3)  # uniform in +-3 %: sd 1.73 %
    assert abs(np.mean(e)) < 4 * 0.03 / np.sqrt(3 * e.size)
    assert (
        s.shutter_factor(1 / 125) == s.shutter_factor(0.008) == SimulatedSensor(spec, (8, 8), 23).shutter_factor(0.008)
    )
    assert SimulatedSensor(spec, (8, 8), seed=24).shutter_factor(0.008) != s.shutter_factor(0.008)
    # the frames carry it: signal ratio between two times = ratio of the actual times
    flat = preset("camera-A", shutter_error=0.03, prnu=0.0, dcnu=0.0, dark_current=0.0)
    fs = SimulatedSensor(flat, (64, 64), seed=25)
    X = 2e4
    for t in (1 / 125, 1 / 60, 0.1):
        m = fs.expose(X, t).astype(float).mean() - flat.mu_R
        assert m / (flat.g * X * t) == pytest.approx(fs.shutter_factor(t), abs=4 * np.sqrt(1 / (X * t * 4096)))


def test_shutter_jitter_per_frame():
    spec = preset("camera-A", shutter_jitter=0.01, prnu=0.0, dcnu=0.0, dark_current=0.0)
    s = SimulatedSensor(spec, (32, 32), seed=26)
    X, t = 1e5, 0.05
    m = np.array([s.expose(X, t).astype(float).mean() for _ in range(300)]) - spec.mu_R
    rel = m / (spec.g * X * t)
    # frame-mean noise from shot and read noise: sqrt(g^2 E + sigma2_R) / (g E sqrt(P)), tiny against 1 %
    assert np.std(rel, ddof=1) == pytest.approx(0.01, rel=5 * np.sqrt(1 / (2 * 299)))


def test_bias_drift_row_and_column_noise():
    spec = preset("camera-B", bias_drift=0.5, row_noise=1.0, column_noise=0.7, dark_current=0.0)
    s = SimulatedSensor(spec, (128, 128), seed=27)
    frames = np.stack([s.expose(0.0, 0.0) for _ in range(200)]).astype(float)
    pix = spec.sigma2_R  # per-photosite readout variance, DN^2
    frame_means = frames.mean(axis=(1, 2))
    # frame mean = drift + mean of rows' and columns' offsets + read noise / sqrt(P)
    exp_var = 0.5**2 + 1.0**2 / 128 + 0.7**2 / 128 + pix / 128**2
    assert np.var(frame_means, ddof=1) == pytest.approx(exp_var, rel=5 * np.sqrt(2 / 199))
    resid = frames - frame_means[:, None, None]
    rows = resid.mean(axis=2)  # row offsets (minus their mean) + column and read noise averaged
    cols = resid.mean(axis=1)
    assert np.var(rows) == pytest.approx(1.0 * (1 - 1 / 128) + pix / 128, rel=0.05)
    assert np.var(cols) == pytest.approx(0.49 * (1 - 1 / 128) + pix / 128, rel=0.05)


def test_black_level_clipping():
    spec = preset("camera-B", black_clip=32.0, dark_current=0.0)  # the bias level: half the values clip
    v = SimulatedSensor(spec, (128, 128), seed=28).expose(0.0, 0.0)
    assert v.min() == 32
    # P(round(N(32, s^2)) <= 32) = P(N < 32.5)
    from math import erf, sqrt

    p = 0.5 * (1 + erf(0.5 / sqrt(2 * (spec.sigma2_R - 1 / 12))))
    assert np.mean(v == 32) == pytest.approx(p, abs=5 * np.sqrt(p * (1 - p) / v.size))
    low = SimulatedSensor(preset("camera-B", mu_R=0.0), (64, 64), seed=1).expose(0.0, 1e-3)
    assert low.min() == 0  # below 0: clipped at the ADC's floor


def test_soft_nonlinearity_near_full_well():
    n, p = 0.01, 6.0
    spec = preset("camera-A", nonlinearity=n, nonlinearity_power=p, prnu=0.0, dcnu=0.0, dark_current=0.0)
    s = SimulatedSensor(spec, (64, 64), seed=29)
    for frac in (0.3, 0.9):
        E = frac * spec.full_well
        m = np.mean([s.expose(E, 1.0).astype(float).mean() for _ in range(4)]) - spec.mu_R
        expect = spec.g * E * (1 - n * frac**p)
        assert m == pytest.approx(expect, abs=0.05 + 1e-4 * expect)
    sat = s.expose(1e9, 1.0).astype(float)
    assert sat.mean() == pytest.approx(spec.mu_R + spec.g * spec.full_well * (1 - n), abs=0.2)
    assert spec.nominal_params().v_sat == pytest.approx(sat.mean() - 3 * sat.std(), rel=0.01)


@pytest.mark.parametrize(
    "bad",
    [
        {"dead_fraction": -0.1},
        {"dead_fraction": 0.6, "weak_fraction": 0.6},
        {"shutter_error": 1.5},
        {"nonlinearity": 0.5},
        {"row_noise": -1.0},
    ],
)
def test_invalid_effects_refused(bad):
    with pytest.raises(ValueError):
        preset("camera-A", **bad)


def test_shutter_errors_of_distinct_times_are_independent():
    """Times below and above 1 s never share a shutter error (t and 500 t once did), and one
    nominal time computed two ways keeps one error."""
    from hdrcap.mock_camera.sensor import SimulatedSensor, preset

    sensor = SimulatedSensor(preset("camera-R"), (24, 24), seed=1)
    for t in (0.08, 0.6, 0.01, 0.002):
        assert sensor.shutter_factor(t) != sensor.shutter_factor(500 * t)
    assert sensor.shutter_factor(1 / 125) == sensor.shutter_factor(0.008)
