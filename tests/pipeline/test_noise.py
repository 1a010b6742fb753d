"""The variance function against hand-computed values of Eq. 3, 5, 6 and 13."""

import numpy as np
import pytest

from hdrcap.pipeline.noise import cramer_rao_bound, exposure_variance, exposure_weight, merged_variance, snr


def test_matched_dark_equals_eq13():
    g, s2, D, a, t, mu = 0.92, 18.0, 1.0, 1.02, 0.05, 3000.0
    w13 = t**2 * g**2 * a**2 / (g**2 * t * (a * mu + 2 * D) + 2 * s2)  # Eq. 13 as printed
    assert exposure_weight(mu, t, g, s2, D, a, "matched") == pytest.approx(w13, rel=1e-12)


def test_dark_strategies_order_and_values():
    g, s2, D, t, mu = 0.23, 6.5, 0.2, 0.01, 100.0
    m = exposure_variance(mu, t, g, s2, D, 1.0, "matched")
    n8 = exposure_variance(mu, t, g, s2, D, 1.0, "master", n_dark=8)
    mod = exposure_variance(mu, t, g, s2, D, 1.0, "model")
    base = (g * g * t * (mu + D) + s2) / (t * g) ** 2
    dark = (g * g * t * D + s2) / (t * g) ** 2
    assert mod == pytest.approx(base)
    assert n8 == pytest.approx(base + dark / 8)
    assert m == pytest.approx(base + dark)
    with pytest.raises(ValueError):
        exposure_variance(mu, t, g, s2, D, 1.0, "master", n_dark=0)


def test_negative_estimate_uses_zero_in_variance():
    assert exposure_variance(-50.0, 0.1, 1.0, 4.0) == exposure_variance(0.0, 0.1, 1.0, 4.0)


def test_merged_variance_and_snr_and_bound():
    times = np.array([0.01, 0.1, 1.0])
    mu = np.array([10.0, 1000.0])
    var = merged_variance(mu, times, 0.5, 10.0, 0.0, 1.0, "model")
    w = 1.0 / ((0.25 * times[:, None] * mu[None] + 10.0) / (times[:, None] * 0.5) ** 2)
    assert np.allclose(var, 1.0 / w.sum(0))
    assert np.allclose(snr(mu, times, 0.5, 10.0, dark="model"), mu / np.sqrt(var))
    # The exact CRB is below the practical bound 1/sum w, within a few per cent.
    crb = cramer_rao_bound(mu, times, 0.5, 10.0)
    assert np.all(crb <= var) and np.all(crb > 0.9 * var)
    none = merged_variance(mu, times, 0.5, 10.0, usable=np.zeros((3, 2), bool))
    assert np.all(np.isinf(none))
