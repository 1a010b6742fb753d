"""The merge's sigma is the variance model: 1/sqrt(sum of the exposure weights) at the estimate.

The expected weights are written out here from the paper (Eq. 3, 5, 6, 13), independently of
:mod:`pipeline.noise`, so that a wrong dark term in the one variance function (or in the
kernel that compiles it) fails. Dark currents are large (D t far above the read noise), maps
are used for the bias, the dark current and the PRNU, and the dark strategies are mixed.
"""

from __future__ import annotations

import numpy as np
import pytest

from hdrcap.mock_camera.sensor import PRESETS, SimulatedSensor
from hdrcap.pipeline.merge import accumulator as pm
from hdrcap.pipeline.params import Calibration

TIMES = [0.002, 0.01, 0.05, 0.25, 1.0, 0.5]
STRATEGIES = ["model", "master", "matched", "model", "master", "matched"]
N_MASTER = 4


def _setup(seed=0, shape=(48, 64)):
    spec = PRESETS["camera-A"].replace(dark_current=150.0, dcnu=0.5, offset_fpn=2.0)
    sensor = SimulatedSensor(spec, shape, seed=seed)
    rng = np.random.default_rng([seed, 5])
    X = 10 ** rng.uniform(-0.5, 4.5, shape)
    values = [sensor.expose(X, t) for t in TIMES]
    darks = []
    for s, t in zip(STRATEGIES, TIMES):
        if s == "matched":
            darks.append(sensor.expose(X, t, dark=True))
        elif s == "master":
            darks.append(np.mean([sensor.expose(X, t, dark=True) for _ in range(N_MASTER)], axis=0).astype(np.float32))
        else:
            darks.append(None)
    p = spec.nominal_params()
    bias = (spec.mu_R + sensor.offset).astype(np.float32)
    cal = Calibration(
        p,
        prnu=sensor.prnu.astype(np.float32),
        bias_map=bias,
        dark_current_map=sensor.dark_current_map().astype(np.float32),
    )
    return spec, p, cal, values, darks


def _expected(p, cal, values, darks, mu):
    """Samples x_i (Eq. 6), usable flags (Eq. 11) and weights at ``mu`` written out from the
    paper: w = (t g a)^2 / (g^2 t (a mu + D) + s_R^2 + k (g^2 t D + s_R^2)), k = 1 matched,
    1/N master, 0 model (Eq. 3, 5, 13)."""
    a = cal.prnu.astype(np.float64)
    D = cal.dark_current_map.astype(np.float64)
    bias = cal.bias_map.astype(np.float64)
    m = np.maximum(mu, 0.0)
    xs, ws, oks = [], [], []
    for v, d, s, t in zip(values, darks, STRATEGIES, TIMES):
        b = bias + p.g * t * D if d is None else d.astype(np.float64)
        k = {"model": 0.0, "master": 1.0 / N_MASTER, "matched": 1.0}[s]
        x = (v.astype(np.float64) - b) / (t * p.g * a)
        var_v = p.g**2 * t * (a * m + D) + p.sigma2_R
        var_b = p.g**2 * t * D + p.sigma2_R
        w = (t * p.g * a) ** 2 / (var_v + k * var_b)
        xs.append(x)
        ws.append(w)
        oks.append((v < p.v_sat) & (b < p.v_sat))
    return np.array(xs), np.array(ws), np.array(oks)


@pytest.mark.parametrize("single", [False, True])
def test_sigma_is_inverse_root_of_weight_sum_at_the_estimate(single, monkeypatch):
    """Deterministic: with the near-saturation rule and the clip rule off (camera-A's slipped
    values are then kept, as the expected weights here keep them), the merge's sigma equals
    1/sqrt(sum w_i(mu)) over the usable samples and its estimate equals sum w x / sum w, both at
    the merge's own estimate, to 1e-6 (float64 weights; 1e-5 with float32 weights)."""
    monkeypatch.setattr(pm, "SINGLE_PRECISION_WEIGHTS", single)
    spec, p, cal, values, darks = _setup()
    res = pm.merge_arrays(
        values,
        TIMES,
        cal,
        darks,
        dark_strategies=STRATEGIES,
        n_darks=[N_MASTER if s == "master" else None for s in STRATEGIES],
        saturation_sigmas=0.0,
        clip_sigmas=0.0,
        iterations=60,
        tolerance=1e-12,
    )
    assert res.info["weights_precision"] == ("float32" if single else "float64")
    mu = res.irradiance.astype(np.float64)
    x, w, ok = _expected(p, cal, values, darks, mu)
    used = ok.sum(axis=0)
    np.testing.assert_array_equal(res.nexp, used)
    sel = used > 0
    assert sel.mean() > 0.9
    sw = np.where(ok, w, 0.0).sum(axis=0)
    sigma = 1.0 / np.sqrt(sw[sel])
    rtol = 1e-5 if single else 1e-6
    np.testing.assert_allclose(res.sigma[sel], sigma, rtol=rtol)
    mu_exp = np.where(ok, w * np.nan_to_num(x), 0.0).sum(axis=0)[sel] / sw[sel]
    assert np.max(np.abs(mu[sel] - mu_exp) / sigma) < 10 * rtol
    # The dark term matters here: D t exceeds the read noise variance (in e-^2).
    D_t = cal.dark_current_map.mean() * max(TIMES)
    assert D_t > p.sigma2_R / p.g**2


def test_master_dark_at_t_ref_honest_per_decade():
    """One master dark of N frames at t_ref, extrapolated to each exposure: its variance is
    (g^2 t_ref D + s_R^2)/N (Eq. 5 at t_ref), not that at the light frame's time. Large dark
    current (40 e-/s), t_ref = 4 s, exposures 0.1 s and 0.25 s (true calibration): z spread per
    decade 0.95-1.05 against the simulator's truth (with the light frame's time: about 1.5-2)."""
    spec = PRESETS["camera-B"].replace(dark_current=40.0, dcnu=0.3)
    zs = {}
    for seed in (1, 2):
        sensor = SimulatedSensor(spec, (128, 128), seed=seed)
        rng = np.random.default_rng([seed, 8])
        X = 10 ** rng.uniform(0.5, 3.0, (128, 128))
        times = [0.1, 0.25]
        values = [sensor.expose(X, t, rng=rng) for t in times]
        master = np.mean([sensor.expose(X, 4.0, dark=True, rng=rng) for _ in range(4)], axis=0).astype(np.float32)
        cal = Calibration(
            spec.nominal_params(),
            prnu=sensor.prnu.astype(np.float32),
            dark_current_map=sensor.dark_current_map().astype(np.float32),
        )
        res = pm.merge_arrays(values, times, cal, master, n_dark=4, master_dark_time=4.0)
        z = (res.irradiance.astype(np.float64) - X) / res.sigma
        lx = np.log10(X)
        for lo in (0.5, 1, 2):
            m = (res.nexp > 0) & (lx >= lo) & (lx < np.floor(lo) + 1)
            zs.setdefault(lo, []).append(z[m])
    for lo, parts in zs.items():
        z = np.concatenate(parts)
        assert z.size > 3000
        assert 0.95 < z.std() < 1.05, (lo, z.std())
        assert abs(z.mean()) < 0.05, (lo, z.mean())
