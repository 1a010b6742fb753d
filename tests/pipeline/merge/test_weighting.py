"""Table 1 weightings (pipeline.merge.weighting): closed forms for a linear sensor and the merge."""

from __future__ import annotations

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS, SimulatedSensor
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.weighting import WEIGHTING_METHODS, merge_weighted, weights
from hdrcap.pipeline.params import Calibration, SensorParams

P = SensorParams(g=0.92, mu_R=32.0, sigma2_R=18.0, v_sat=1023.0, white_level=1023.0, dark_current=1.0)
V = np.array([0.0, 5.0, 100.0, 495.5, 900.0, 991.0])
T = np.array([0.01, 0.02, 0.1, 0.5, 1.0, 2.0])


def test_registry_has_the_papers_names():
    assert list(WEIGHTING_METHODS) == [
        "uniform",
        "mann-picard",
        "debevec-malik",
        "mitsunaga-nayar",
        "reinhard",
        "robertson",
        "tsin",
        "kirk-andersen",
        "optimal",
    ]
    for name, fn in WEIGHTING_METHODS.items():
        assert fn.__doc__ and ("Table 1" in fn.__doc__ or "Eq. 13" in fn.__doc__), name
        w = fn(V, T, P)
        assert w.shape == V.shape and np.all(np.isfinite(w)) and np.all(w >= 0), name


@pytest.mark.parametrize(
    "name, expected",
    [
        # closed forms for a linear sensor, g(v) = v/g, written independently of the module
        ("uniform", lambda v, t: np.ones_like(v)),
        ("mann-picard", lambda v, t: v),
        ("mitsunaga-nayar", lambda v, t: v),
        ("debevec-malik", lambda v, t: np.minimum(v, (1023.0 - 32.0) - v)),
        ("reinhard", lambda v, t: np.maximum(v * (1 - (v / 495.5 - 1) ** 12), 0)),
        ("robertson", lambda v, t: t**2 * v),
        ("tsin", lambda v, t: t * 0.92 / np.sqrt(0.92 * v + 18.0)),
        ("kirk-andersen", lambda v, t: t**2 * 0.92**2 / (0.92 * v + 18.0)),
        # Eq. 13 with mu at the observed value v/(t g) - D, one matched dark frame
        ("optimal", lambda v, t: t**2 * 0.92**2 / (0.92**2 * t * (np.maximum(v / (t * 0.92) - 1.0, 0) + 2.0) + 36.0)),
    ],
)
def test_closed_forms(name, expected):
    np.testing.assert_allclose(weights(name, V, T, P), expected(V, T), rtol=1e-12)


def test_robertson_grows_like_t_cubed_and_mitsunaga_like_t():
    # constant irradiance: v = g X t, so Robertson ~ t^3 and Mitsunaga-Nayar ~ t (Sec. 7, App. A)
    t = np.array([0.01, 0.02, 0.04])
    v = 0.92 * 1000.0 * t
    r = weights("robertson", v, t, P)
    m = weights("mitsunaga-nayar", v, t, P)
    np.testing.assert_allclose(r[1:] / r[:-1], 8.0)
    np.testing.assert_allclose(m[1:] / m[:-1], 2.0)


def test_unknown_method_is_an_input_error():
    with pytest.raises(InputError, match="unknown weighting 'foo'"):
        weights("foo", V, T, P)
    with pytest.raises(InputError, match="unknown weighting"):
        merge_weighted([np.zeros((2, 2))], [1.0], Calibration(P), method="foo")


def _bracket(spec, X, times, seed, darks=True):
    sensor = SimulatedSensor(spec, X.shape, seed=seed)
    rng = np.random.default_rng([seed, 5])
    frames = [sensor.expose(X, t, rng=rng) for t in times]
    dk = [sensor.expose(X, t, dark=True, rng=rng) for t in times] if darks else None
    calib = Calibration(spec.nominal_params(), prnu=sensor.prnu, dark_current_map=sensor.dark_current_map())
    return frames, dk, calib


@pytest.mark.parametrize("method", ["uniform", "kirk-andersen", "robertson", "debevec-malik"])
def test_merge_is_unbiased_and_sigma_is_honest(method):
    spec = PRESETS["camera-B"]
    X = np.full((64, 64), 3000.0)  # bright: every method is unbiased here
    times = [0.01, 0.04, 0.16]
    frames, darks, calib = _bracket(spec, X, times, seed=3)
    res = merge_weighted(frames, times, calib, darks, method=method)
    assert res.irradiance.dtype == np.float32 and res.sigma.dtype == np.float32
    z = (res.irradiance.astype(float) - X) / res.sigma
    assert abs(np.mean(res.irradiance) / 3000.0 - 1) < 0.005
    assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1, (z.mean(), z.std())
    # expected saturation pattern: 0.16 s collects 480 e- -> 474 DN, all three usable
    assert np.all(res.nexp == 3)


def test_saturated_everywhere_and_no_dark_frames():
    spec = PRESETS["camera-B"]
    X = np.array([[1e3, 1e7]])
    frames, _, calib = _bracket(spec, X, [0.01, 0.1], seed=1, darks=False)
    res = merge_weighted(frames, [0.01, 0.1], calib, None, method="tsin")
    assert res.info["dark_strategy"] == "model"
    assert res.nexp[0, 1] == 0 and res.sigma[0, 1] == 0
    assert 0 < res.irradiance[0, 1] < 1e7 and np.isfinite(res.irradiance).all()
    assert abs(res.irradiance[0, 0] / 1e3 - 1) < 0.2


def test_dark_count_must_match():
    with pytest.raises(InputError, match="1 dark frames for 2 exposures"):
        merge_weighted([np.zeros((2, 2))] * 2, [1.0, 2.0], Calibration(P), [np.zeros((2, 2))])
