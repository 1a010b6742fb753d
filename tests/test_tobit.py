"""The censored (Tobit) likelihood of ``saturation="probabilistic"`` against independent expectations.

* The estimate and its sigma equal an independent maximisation (scipy) of the same censored
  likelihood: unsaturated samples contribute their Gaussian density, saturated ones
  (v >= v_sat) their survival probability 1 - Phi((v_sat - E v)/sd); the variance of the
  model g^2 t (a X + D) + sigma_R^2 written here again, held at the estimate (Eq. 13); sigma =
  1/sqrt(observed information).
* Monte Carlo against the simulator's truth, per band of k = (E v - v_sat)/sigma_v around the
  clip level of every exposure that has a shorter one (above the shortest exposure's clip only
  a lower bound exists): z mean and z spread per band, against the truncated likelihood this
  replaced (z mean -0.26..-0.32 in -1..+1).
* Photosites saturated in every exposure stay flagged (nexp = 0, sigma = 0, a lower bound).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import log_ndtr

from hdrcap.mock_camera.sensor import PRESETS, SimulatedSensor
from hdrcap.pipeline.merge import merge_arrays
from hdrcap.pipeline.params import Calibration

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_honesty import estimated_calibration  # noqa: E402

TIMES = np.array([1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0])
K_EDGES = np.arange(-3.0, 3.01, 0.5)


def _truth_calibration(sensor):
    return Calibration(
        sensor.spec.nominal_params(),
        prnu=sensor.prnu.astype(np.float32),
        dark_current_map=sensor.dark_current_map().astype(np.float32),
    )


def _electrons_at_k(spec, v_sat, k):
    """Electrons E with mu_R + g E = v_sat + k sqrt(g^2 E + sigma_R^2) (fixed point)."""
    e = (v_sat - spec.mu_R) / spec.g
    for _ in range(10):
        e = (v_sat + k * np.sqrt(spec.g**2 * e + spec.sigma2_R) - spec.mu_R) / spec.g
    return e


def _clip_scene(sensor, rng, times=TIMES):
    """Every photosite at k ~ U(-3.5, 3.5) of the clip level of an exposure that has a shorter
    one (PRNU and dark-current map of the truth), and that k."""
    spec = sensor.spec
    shape = sensor.prnu.shape
    t = np.asarray(times)[rng.integers(1, len(times), shape)]
    k = rng.uniform(-3.5, 3.5, shape)
    e = _electrons_at_k(spec, spec.nominal_params().v_sat, k)
    return (e / t - sensor.dark_current_map()) / sensor.prnu, k


def _monte_carlo(cam, seeds, shape=(128, 128)):
    """z = (estimate - truth)/sigma and the true k of every photosite, matched dark frames."""
    spec = PRESETS[cam]
    zs, ks, flagged = [], [], []
    for seed in seeds:
        sensor = SimulatedSensor(spec, shape, seed=seed)
        rng = np.random.default_rng([seed, 5])
        X, k = _clip_scene(sensor, rng)
        values = [sensor.expose(X, t, rng=rng) for t in TIMES]
        darks = [sensor.expose(X, t, dark=True, rng=rng) for t in TIMES]
        res = merge_arrays(values, TIMES, _truth_calibration(sensor), darks, saturation="probabilistic")
        assert np.isfinite(res.irradiance).all() and np.isfinite(res.sigma).all()
        ok = res.nexp > 0
        assert np.all(res.sigma[ok] > 0)
        zs.append(((res.irradiance.astype(np.float64) - X) / np.where(ok, res.sigma, 1.0))[ok])
        ks.append(k[ok])
        flagged.append(np.count_nonzero(~ok))
    return np.concatenate(zs), np.concatenate(ks), sum(flagged)


@pytest.fixture(scope="module", params=["camera-A", "camera-B"])
def bands(request):
    """Per band of k (width 0.5, -3..+3): (n, z mean, z spread); and the photosites flagged."""
    z, k, flagged = _monte_carlo(request.param, seeds=(1, 2, 3))
    assert np.mean(np.abs(z) > 6) == 0  # no gross errors near any clip level (full well or ADC)
    out = []
    for lo, hi in zip(K_EDGES[:-1], K_EDGES[1:]):
        m = (k >= lo) & (k < hi)
        out.append((int(m.sum()), float(z[m].mean()), float(z[m].std())))
    return request.param, out, flagged


def test_censored_likelihood_near_every_clip_level(bands):
    """The censored likelihood removes the truncation's bias: |z mean| <= 0.13 in every band
    (the truncated likelihood: -0.26..-0.32 in -1..+1), within 0.05 from -3 to -0.5, z spread
    0.88-1.05. What remains (+0.04..+0.12 for k in 0..+2.5, spread 0.91-0.95) is the
    finite-sample bias of the maximum-likelihood estimate of a censored sample with the
    information of the shorter exposures (about a third of its own): an independent scipy
    model of exactly that (one censored Gaussian sample plus a Gaussian one with 0.32 of its
    information) gives +0.05 / +0.09 / +0.10 / +0.10 / +0.07 / +0.03 at k = 0 / 0.5 / 1 / 1.5 /
    2 / 2.5, spread 0.93-0.99; not yet the issue's target, so the planner does not choose this
    model by itself."""
    cam, rows, flagged = bands
    assert flagged == 0, cam  # every photosite has an unsaturated shorter exposure
    for (n, mean, std), lo in zip(rows, K_EDGES):
        assert n > 3000, (cam, lo, n)
        assert abs(mean) < 0.13, (cam, lo, mean)
        assert 0.88 < std < 1.05, (cam, lo, std)
        if lo < -0.5:
            assert abs(mean) < 0.05, (cam, lo, mean)


@pytest.mark.xfail(strict=True, reason="ML of a censored sample: finite-sample bias up to +0.12 sigma for k in 0..2.5")
def test_censored_likelihood_meets_the_target(bands):
    """The issue's target: |z mean| < 0.05 and z spread 0.95-1.05 in every band of k."""
    cam, rows, _ = bands
    for (_, mean, std), lo in zip(rows, K_EDGES):
        assert abs(mean) < 0.05 and 0.95 < std < 1.05, (cam, lo, mean, std)


def _independent_tobit(v, b, t, g, a, D, sigma2_R, v_sat, start):
    """The root of the censored likelihood's score (variances held at the estimate, Eq. 13),
    with scipy; returns (estimate, 1/sqrt(observed information))."""

    def terms(mu):
        sd = np.sqrt(g * g * t * (a * max(mu, 0.0) + max(D, 0.0)) + sigma2_R)
        kap = t * g * a / sd
        ev = b + t * g * a * mu
        cen = v >= v_sat
        y = (v - ev) / sd
        z = (v_sat - ev) / sd
        lam = np.exp(-0.5 * z * z - 0.5 * np.log(2 * np.pi) - log_ndtr(-z))
        score = np.where(cen, lam * kap, y * kap).sum()
        info = np.where(cen, lam * (lam - z) * kap**2, kap**2).sum()
        return score, info

    lo, hi = start - 1.0, start + 1.0
    while terms(lo)[0] <= 0:
        lo -= 2 * (start - lo)
    while terms(hi)[0] >= 0:
        hi += 2 * (hi - start)
    mu = brentq(lambda m: terms(m)[0], lo, hi, xtol=1e-12, rtol=1e-13)
    return mu, 1.0 / np.sqrt(terms(mu)[1])


def test_equals_an_independent_maximisation_of_the_censored_likelihood():
    """Camera-B (the ADC clips: no full-well mixture), model darks with PRNU and dark-current
    maps: the kernel's estimate and sigma equal scipy's root of the same likelihood."""
    spec = PRESETS["camera-B"].replace(dark_current=50.0, dcnu=0.3, prnu=0.02)
    p = spec.nominal_params()
    shape = (6, 40)
    sensor = SimulatedSensor(spec, shape, seed=4)
    rng = np.random.default_rng(8)
    X, _ = _clip_scene(sensor, rng)
    values = [sensor.expose(X, t, rng=rng) for t in TIMES]
    cal = _truth_calibration(sensor)
    res = merge_arrays(values, TIMES, cal, None, saturation="probabilistic", tolerance=1e-10)
    thr = merge_arrays(values, TIMES, cal, None, tolerance=1e-10)
    a, D = cal.prnu.astype(np.float64), cal.dark_current_map.astype(np.float64)
    V = np.stack(values).astype(np.float64)
    censored = 0
    for r, c in np.ndindex(shape):
        b = p.mu_R + p.g * TIMES * D[r, c]
        v = V[:, r, c]
        censored += int(np.count_nonzero(v >= p.v_sat))
        mu, sig = _independent_tobit(
            v, b, TIMES, p.g, a[r, c], D[r, c], p.sigma2_R, p.v_sat, float(thr.irradiance[r, c])
        )
        assert res.nexp[r, c] == np.count_nonzero(v < p.v_sat)
        assert abs(res.irradiance[r, c] - mu) < 1e-4 * sig + 1e-6 * abs(mu), (r, c)
        assert res.sigma[r, c] == pytest.approx(sig, rel=1e-5), (r, c)
    assert censored > 100  # the censored terms matter in this scene


def test_saturated_everywhere_stays_a_lower_bound():
    """Photosites saturated in every exposure (both camera types) keep nexp = 0, sigma = 0 and
    an irradiance at or below the shortest exposure's clip level, never a confident value."""
    for cam in ("camera-A", "camera-B"):
        spec = PRESETS[cam]
        p = spec.nominal_params()
        sensor = SimulatedSensor(spec, (8, 16), seed=2)
        clip = (p.v_sat - spec.mu_R) / (spec.g * TIMES[0])
        X = np.full((8, 16), 3.0 * clip)
        rng = np.random.default_rng(3)
        values = [sensor.expose(X, t, rng=rng) for t in TIMES]
        darks = [sensor.expose(X, t, dark=True, rng=rng) for t in TIMES]
        res = merge_arrays(values, TIMES, _truth_calibration(sensor), darks, saturation="probabilistic")
        assert np.all(res.nexp == 0) and np.all(res.sigma == 0), cam
        assert np.all(res.irradiance <= 1.1 * clip) and np.all(res.irradiance > 0.5 * clip), cam


def test_estimated_calibration_model_darks_below_the_clip():
    """camera-B, model darks (bias and dark-current maps subtracted), a calibration ESTIMATED from
    simulated frames (2 bias frames, 16 flats, a 6-time dark series), exposures 0.125-30 s:
    for k in -3..-1, z mean (the estimated gain's common error removed) within 0.05 (-1..0: 0.1,
    where the maximum-likelihood bias of the clip above begins) and z spread 0.93-1.05 per band. The calibration's part of sigma propagates with the censored
    likelihood's per-sample information; with the threshold rule's weights (which leave out
    the long exposure near its clip) the spread was 0.80-0.88 here."""
    times = np.array([0.125, 0.5, 2.0, 8.0, 30.0])
    spec = PRESETS["camera-B"]
    sensor = SimulatedSensor(spec, (128, 128), seed=6)
    rng = np.random.default_rng([6, 31])
    cal = estimated_calibration(sensor, rng)
    X, k = _clip_scene(sensor, rng, times)
    values = [sensor.expose(X, t, rng=rng) for t in times]
    res = merge_arrays(values, times, cal, None, saturation="probabilistic")
    ok = res.nexp > 0
    assert ok.all()
    assert np.any(res.sigma_calibration > 0)  # the estimated maps' errors are in sigma
    zg = (res.irradiance.astype(np.float64) - X * spec.g / cal.params.g) / res.sigma
    for lo in (-3, -2, -1):
        m = (k >= lo) & (k < lo + 1)
        assert m.sum() > 2000
        assert abs(zg[m].mean()) < (0.05 if lo < -1 else 0.1), (lo, zg[m].mean())  # -1..0: +0.07
        assert 0.93 < zg[m].std() < 1.05, (lo, zg[m].std())
