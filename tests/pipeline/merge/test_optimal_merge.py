"""The optimal merge against the simulator's truth, the practical bound, extremes and real data.

Expectations are independent of the merge: the simulator's true irradiance (physics in
mock_camera, which never calls pipeline.noise), the practical bound 1/sum w evaluated at the
TRUE irradiance, and the EMVA 1288 reference data set (a real camera).
"""

from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from hdrcap.mock_camera.sensor import PRESETS, SimulatedSensor
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.accumulator import MergeAccumulator, merge_arrays
from hdrcap.pipeline.noise import exposure_variance
from hdrcap.pipeline.params import Calibration, SensorParams

TIMES = np.array([1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0])
MARGIN = 3.0  # the merge's default saturation_sigmas


def _truth_calibration(sensor, params):
    return Calibration(
        params, prnu=sensor.prnu.astype(np.float32), dark_current_map=sensor.dark_current_map().astype(np.float32)
    )


def _bound(X, a, D, p, times, dark, n_dark=1):
    """Practical bound 1/sum w at the TRUE irradiance over the exposures whose mean raw value
    lies more than MARGIN of its standard deviation below v_sat (inf where none). ``dark``: one
    strategy, or one per exposure."""
    t = np.asarray(times)[:, None, None]
    darks = [dark] * len(times) if isinstance(dark, str) else list(dark)
    var = np.stack([exposure_variance(X, ti, p.g, p.sigma2_R, D, a, d, n_dark) for ti, d in zip(times, darks)])
    var_v = exposure_variance(X[None], t, p.g, p.sigma2_R, D[None], a[None], "model") * (t * p.g * a) ** 2
    usable = (p.v_sat - (p.mu_R + p.g * t * (a * X + D))) > MARGIN * np.sqrt(var_v)
    sw = np.where(usable, 1.0 / var, 0.0).sum(axis=0)
    return np.where(sw > 0, 1.0 / np.where(sw > 0, sw, 1.0), np.inf)


def _clip_levels(spec, times):
    """Irradiance at which each exposure reaches saturation (e-/s)."""
    p = spec.nominal_params()
    return [(min(spec.g * spec.full_well, p.v_sat - spec.mu_R)) / (spec.g * t) for t in times]


def _scene(spec, shape, rng):
    """Log-uniform over 5.5 decades plus a quarter of the photosites just above or below
    each exposure's saturation."""
    X = 10 ** rng.uniform(0.0, 5.5, shape)
    near = rng.random(shape) < 0.25
    clips = np.array(_clip_levels(spec, TIMES))
    pick = clips[rng.integers(0, len(clips), shape)] * (1 + rng.uniform(-0.03, 0.05, shape))
    return np.where(near, pick, X)


def _monte_carlo(cam, dark="matched", seeds=(0, 1, 2), shape=(256, 256), n_dark=8, spec=None, **options):
    spec = PRESETS[cam] if spec is None else spec
    p = spec.nominal_params()
    out = {k: [] for k in ("X", "err", "sigma", "nexp", "bound")}
    for seed in seeds:
        sensor = SimulatedSensor(spec, shape, seed=seed)
        rng = np.random.default_rng([seed, 77])
        X = _scene(spec, shape, rng)
        cal = _truth_calibration(sensor, p)
        values = [sensor.expose(X, t) for t in TIMES]
        kw = dict(options)
        if dark == "matched":
            darks = [sensor.expose(X, t, dark=True) for t in TIMES]
        elif dark == "master":
            darks = [
                np.mean([sensor.expose(X, t, dark=True) for _ in range(n_dark)], axis=0).astype(np.float32)
                for t in TIMES
            ]
            kw.update(dark_strategy="master", n_dark=n_dark)
        elif dark == "model":
            darks = None
        else:  # one strategy per exposure
            darks = [
                None
                if d == "model"
                else sensor.expose(X, t, dark=True)
                if d == "matched"
                else np.mean([sensor.expose(X, t, dark=True) for _ in range(n_dark)], axis=0).astype(np.float32)
                for d, t in zip(dark, TIMES)
            ]
            kw.update(dark_strategies=list(dark), n_darks=[n_dark if d == "master" else None for d in dark])
        res = merge_arrays(values, TIMES, cal, darks, **kw)
        if not isinstance(dark, str):
            assert res.info["dark_strategy"] == "mixed" and res.info["dark_strategies"] == list(dark)
            assert res.info["n_dark_per_frame"] == [{"model": 0, "matched": 1, "master": n_dark}[d] for d in dark]
        assert np.isfinite(res.irradiance).all() and np.isfinite(res.sigma).all()
        out["X"].append(X.ravel())
        out["err"].append((res.irradiance.astype(np.float64) - X).ravel())
        out["sigma"].append(res.sigma.ravel().astype(np.float64))
        out["nexp"].append(res.nexp.ravel())
        out["bound"].append(_bound(X, sensor.prnu, sensor.dark_current_map(), p, TIMES, dark, n_dark).ravel())
    return {k: np.concatenate(v) for k, v in out.items()} | {"clip_shortest": _clip_levels(spec, TIMES)[0]}


def _check_statistics(mc, mse_tol=0.05):
    X, err, sig, nexp, bound = mc["X"], mc["err"], mc["sigma"], mc["nexp"], mc["bound"]
    with np.errstate(divide="ignore"):
        snr_db = 20 * np.log10(np.maximum(X, 1e-300) / np.sqrt(bound))
    sel = np.isfinite(bound) & (snr_db > 3.0)
    assert sel.sum() > 20000
    # Photosites with some unsaturated exposure are flagged saturated-everywhere only at the
    # edge of the shortest exposure's range (the near-saturation rule's few-sigma band).
    flagged = sel & (nexp == 0)
    assert flagged.mean() < 5e-3
    assert np.all(X[flagged] > 0.9 * mc["clip_shortest"]), X[flagged].min()
    use = sel & (nexp > 0)
    z = err[use] / sig[use]
    # Honest sigma, and no gross errors (also just above each exposure's saturation).
    assert 0.95 < z.std() < 1.05, z.std()
    assert np.mean(np.abs(z) > 6) < 1e-4
    # Per decade of irradiance: unbiased and at the practical bound.
    lx = np.log10(X)
    for lo in range(0, 6):
        m = use & (lx >= lo) & (lx < lo + 1)
        if m.sum() < 2000:
            continue
        zb = err[m] / np.sqrt(bound[m])
        assert abs(zb.mean()) < 0.1, (lo, zb.mean())
        ratio = np.mean(zb**2)
        assert abs(ratio - 1) < mse_tol, (lo, ratio)


@pytest.mark.parametrize("cam", ["camera-A", "camera-B"])
def test_matched_darks_unbiased_at_bound_honest_sigma(cam):
    _check_statistics(_monte_carlo(cam, "matched"))


@pytest.mark.parametrize("dark", ["master", "model"])
def test_dark_strategies_reach_their_bound_and_beat_matched_when_dark(dark):
    mc = _monte_carlo("camera-A", dark, seeds=(3, 4, 5))
    _check_statistics(mc)
    ref = _monte_carlo("camera-A", "matched", seeds=(3, 4, 5))
    low = (mc["X"] < 30) & np.isfinite(mc["bound"])
    assert low.sum() > 1000
    # Observed MSE at low irradiance: the strategy's own is clearly below matched darks'.
    mse, mse_ref = np.mean(mc["err"][low] ** 2), np.mean(ref["err"][low] ** 2)
    expected = np.mean(mc["bound"][low]) / np.mean(ref["bound"][low])
    assert expected < 0.85
    assert mse / mse_ref == pytest.approx(expected, rel=0.08)


@pytest.mark.parametrize("dark", ["matched", "master", "model", ("model", "master", "matched") * 2])
def test_dark_current_comparable_to_read_noise_honest_per_decade(dark):
    """D t of 15-150 e- at the two longest exposures against 21 e-^2 of read noise (camera-B with
    100 e-/s and a strong DCNU): a wrong dark term in the variance shows as a z spread far from 1
    in the low decades (without the matched dark's term, about 1.4 at 1-10 e-/s)."""
    spec = PRESETS["camera-B"].replace(dark_current=100.0, dcnu=0.5)
    mc = _monte_carlo("camera-B", dark, seeds=(11, 12), shape=(192, 192), n_dark=4, spec=spec)
    _check_statistics(mc, mse_tol=0.06)
    use = np.isfinite(mc["bound"]) & (mc["nexp"] > 0)
    z = mc["err"][use] / mc["sigma"][use]
    lx = np.log10(mc["X"][use])
    for lo in range(0, 5):
        m = (lx >= lo) & (lx < lo + 1)
        assert m.sum() > 2000, lo
        assert 0.95 < z[m].std() < 1.05, (lo, z[m].std())
        assert abs(z[m].mean()) < 0.05, (lo, z[m].mean())


def test_mixed_dark_strategies_per_exposure_reach_their_bound():
    """A plan may mix strategies: no dark frame for the short exposures (read noise dominates
    nothing there), master darks in the middle, matched darks for the longest."""
    mixed = ("model", "model", "master", "master", "matched", "matched")
    mc = _monte_carlo("camera-B", mixed, seeds=(6, 7))
    _check_statistics(mc)
    # Streaming with per-frame strategies equals the batch merge.
    spec = PRESETS["camera-B"]
    sensor = SimulatedSensor(spec, (32, 48), seed=1)
    X = _scene(spec, (32, 48), np.random.default_rng(2))
    cal = _truth_calibration(sensor, spec.nominal_params())
    values = [sensor.expose(X, t) for t in TIMES]
    darks = [None if d == "model" else sensor.expose(X, t, dark=True) for d, t in zip(mixed, TIMES)]
    batch = merge_arrays(values, TIMES, cal, darks, dark_strategies=mixed, n_darks=[1] * 6)
    acc = MergeAccumulator(cal, X.shape, n_dark=1)
    for v, t, d, s in zip(values, TIMES, darks, mixed):
        acc.add(v, t, d, strategy=s)
    np.testing.assert_array_equal(acc.result().irradiance, batch.irradiance)
    with pytest.raises(InputError, match="no dark frame for the matched"):
        merge_arrays(values, TIMES, cal, [None] * 6, dark_strategies=["matched"] * 6)
    with pytest.raises(InputError, match="6 dark strategies for 5 frames|5 exposure times"):
        merge_arrays(values[:5], TIMES[:5], cal, None, dark_strategies=mixed)


@pytest.mark.parametrize("cam", ["camera-A", "camera-B"])
def test_probabilistic_saturation_honest_and_no_gross_errors(cam):
    mc = _monte_carlo(cam, "matched", seeds=(5,), saturation="probabilistic")
    sel = np.isfinite(mc["bound"]) & (mc["X"] / np.sqrt(mc["bound"]) > 1.41) & (mc["nexp"] > 0)
    z = mc["err"][sel] / mc["sigma"][sel]
    assert 0.95 < z.std() < 1.05, z.std()
    assert np.mean(np.abs(z) > 6) < 1e-4
    zb = mc["err"][sel] / np.sqrt(mc["bound"][sel])
    # The threshold model's bound leaves out the samples near saturation; the blended
    # likelihood uses part of them, so its MSE is at or below that bound.
    assert abs(zb.mean()) < 0.1 and np.mean(zb**2) < 1.02


def test_probabilistic_saturation_just_above_each_clip_camera_a():
    """Camera-A's full well clips before the ADC, so saturated samples slip under v_sat on
    read noise; irradiances from 0.9x to 1.5x each exposure's clip level: no gross errors."""
    spec = PRESETS["camera-A"]
    p = spec.nominal_params()
    shape = (64, 128)
    sensor = SimulatedSensor(spec, shape, seed=9)
    cal = _truth_calibration(sensor, p)
    beyond = []
    for clip in _clip_levels(spec, TIMES):
        X = clip * np.linspace(0.9, 1.5, shape[0] * shape[1]).reshape(shape)
        values = [sensor.expose(X, t) for t in TIMES]
        darks = [sensor.expose(X, t, dark=True) for t in TIMES]
        res = merge_arrays(values, TIMES, cal, darks, saturation="probabilistic")
        ok = res.nexp > 0
        beyond.append(int(np.sum(np.abs(res.irradiance[ok] - X[ok]) > 6 * res.sigma[ok])))
    assert sum(beyond) == 0, beyond


def test_near_saturation_rule_is_needed_for_camera_a():
    """Camera-A's full well clips before the ADC: without the near-saturation rule (and the
    clip rule), samples that slip under v_sat produce gross errors; with it, none."""
    spec = PRESETS["camera-A"]
    p = spec.nominal_params()
    shape = (128, 128)
    sensor = SimulatedSensor(spec, shape, seed=9)
    clip = _clip_levels(spec, TIMES)[-1]
    X = clip * np.linspace(1.05, 3.0, shape[0] * shape[1]).reshape(shape)
    cal = _truth_calibration(sensor, p)
    values = [sensor.expose(X, t) for t in TIMES]
    darks = [sensor.expose(X, t, dark=True) for t in TIMES]
    with_rule = merge_arrays(values, TIMES, cal, darks)
    without = merge_arrays(values, TIMES, cal, darks, saturation_sigmas=0.0, clip_sigmas=0.0)
    clip_only = merge_arrays(values, TIMES, cal, darks, saturation_sigmas=0.0)
    z_with = (with_rule.irradiance - X) / with_rule.sigma
    z_without = (without.irradiance - X) / without.sigma
    assert np.sum(np.abs(z_without) > 6) >= 3  # the hazard is real in the simulator
    assert np.sum(np.abs(z_with) > 6) == 0
    # the clip rule alone (leave-one-out, after the iterations) catches them too
    assert np.sum(np.abs((clip_only.irradiance - X) / clip_only.sigma) > 6) == 0


def test_streaming_equals_batch():
    spec = PRESETS["camera-B"]
    p = spec.nominal_params()
    sensor = SimulatedSensor(spec, (64, 96), seed=2)
    X = _scene(spec, (64, 96), np.random.default_rng(1))
    cal = _truth_calibration(sensor, p)
    values = [sensor.expose(X, t) for t in TIMES]
    darks = [sensor.expose(X, t, dark=True) for t in TIMES]
    batch = merge_arrays(values, TIMES, cal, darks)
    acc = MergeAccumulator(cal, X.shape)
    for v, t, d in zip(values, TIMES, darks):
        acc.add(v, t, d)
    stream = acc.result()
    for name in ("irradiance", "sigma", "nexp"):
        np.testing.assert_array_equal(getattr(stream, name), getattr(batch, name))
    # Another arrival order converges to the same estimate (within the tolerance).
    acc = MergeAccumulator(cal, X.shape, tolerance=1e-10)
    for i in [3, 0, 5, 1, 4, 2]:
        acc.add(values[i], TIMES[i], darks[i])
    other = acc.result()
    np.testing.assert_allclose(other.irradiance, batch.irradiance, rtol=1e-4, atol=1e-3 * batch.sigma.max())
    np.testing.assert_array_equal(other.nexp, batch.nexp)


def test_master_dark_single_array_and_info():
    spec = PRESETS["camera-B"]
    p = spec.nominal_params()
    sensor = SimulatedSensor(spec, (64, 64), seed=4)
    X = np.full((64, 64), 200.0)
    times = [0.01, 0.1]
    values = [sensor.expose(X, t) for t in times]
    master = np.mean([sensor.expose(X, 0.1, dark=True) for _ in range(16)], axis=0)
    res = merge_arrays(
        values,
        times,
        _truth_calibration(sensor, p),
        master,
        n_dark=16,
        master_dark_time=0.1,
        iterations=5,
        tolerance=1e-3,
        prnu="scalar",
    )
    assert res.info["dark_strategy"] == "master" and res.info["n_dark"] == 16
    assert res.info["iterations"] == 5 and res.info["prnu"] == "scalar"
    z = (res.irradiance - X * sensor.prnu) / res.sigma  # scalar PRNU estimates a*X
    assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1


# ------------------------------------------------------------------------------ extremes


def _params(**kw):
    base = dict(g=0.5, mu_R=64.0, sigma2_R=4.0, v_sat=4000.0, white_level=4095.0, dark_current=0.5)
    base.update(kw)
    return SensorParams(**base)


def _simulate_plain(p, X, times, rng, dark=True):
    """Small independent simulator for arbitrary parameters (Poisson, Gaussian, rounding,
    clipping at white level), float64 values (not restricted to uint16)."""
    out, darks = [], []
    for t in times:
        e = rng.poisson(np.full(X.shape, (X + p.dark_current) * t))
        v = np.clip(
            np.rint(p.g * e + p.mu_R + math.sqrt(max(p.sigma2_R - 1 / 12, 0)) * rng.standard_normal(X.shape)),
            0,
            p.white_level,
        )
        out.append(v.astype(np.float32))
        e = rng.poisson(np.full(X.shape, p.dark_current * t))
        darks.append(
            np.clip(
                np.rint(p.g * e + p.mu_R + math.sqrt(max(p.sigma2_R - 1 / 12, 0)) * rng.standard_normal(X.shape)),
                0,
                p.white_level,
            ).astype(np.float32)
        )
    return out, (darks if dark else None)


EXTREMES = [
    # name, params, times, irradiance
    ("zero irradiance", _params(), [0.01, 0.1, 1.0], 0.0),
    ("single exposure", _params(), [0.1], 1000.0),
    ("fifty exposures", _params(), list(np.geomspace(1e-3, 1.0, 50)), 3000.0),
    ("times 1e-6..1e3 s", _params(), [1e-6, 1e-3, 1.0, 1e3], 2.0),
    ("sigma_R -> quantisation only", _params(sigma2_R=1 / 12), [0.01, 0.1, 1.0], 500.0),
    ("huge gain", _params(g=100.0, white_level=65535.0, v_sat=65000.0), [1e-3, 1e-2], 3000.0),
    ("tiny gain", _params(g=1e-4, white_level=65535.0, v_sat=65000.0), [1.0, 10.0], 1e6),
    ("dark pixel, negative x", _params(dark_current=0.0), [0.001, 0.01], 0.5),
]


@pytest.mark.parametrize("dtype", [np.float32, np.uint16])
@pytest.mark.parametrize("name,p,times,level", EXTREMES, ids=[e[0] for e in EXTREMES])
def test_extremes_finite_and_within_uncertainty(name, p, times, level, dtype):
    """Float frames take float64 weights; the same frames as integers (as read from raw files)
    take float32 weights where the bounds allow: either way finite and within uncertainty."""
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    X = np.full((32, 32), float(level))
    values, darks = _simulate_plain(p, X, times, rng)
    values, darks = [v.astype(dtype) for v in values], [d.astype(dtype) for d in darks]
    res = merge_arrays(values, times, Calibration(p), darks)
    assert res.info["weights_precision"] == ("float32" if dtype == np.uint16 else "float64")
    assert np.isfinite(res.irradiance).all() and np.isfinite(res.sigma).all()
    ok = res.nexp > 0
    assert ok.all()
    z = (res.irradiance[ok] - level) / res.sigma[ok]
    assert np.all(np.abs(z) < 6)
    assert abs(z.mean()) < 0.25
    if name.startswith("dark pixel"):
        assert (res.irradiance < 0).any()  # the estimate is never clipped at 0


@pytest.mark.parametrize("where", ["below", "above"])
def test_just_below_and_above_saturation_everywhere(where):
    p = _params(v_sat=4095.0)
    times = [0.5, 1.0]
    clip = (p.v_sat - p.mu_R) / (p.g * times[0])
    level = clip * (0.995 if where == "below" else 1.05)
    X = np.full((32, 32), level)
    values, darks = _simulate_plain(p, X, times, np.random.default_rng(11))
    res = merge_arrays(values, times, Calibration(p), darks)
    assert np.isfinite(res.irradiance).all() and np.isfinite(res.sigma).all()
    flagged = res.nexp == 0
    # Too close to saturation to trust: flagged, with a lower bound no higher than the truth
    # (allowing the few-sigma band of the near-saturation rule when below); the rare sample
    # far enough below v_sat is used, within its uncertainty.
    assert flagged.mean() > (0.95 if where == "below" else 0.999)
    assert np.all(res.sigma[flagged] == 0)
    z = (res.irradiance[~flagged] - level) / res.sigma[~flagged]
    assert np.all(np.abs(z) < 6)
    assert np.all(res.irradiance <= level * (1.0 if where == "above" else 1.01))
    assert np.all(res.irradiance > 0.9 * clip)


def test_float32_huge_values_and_nan_inputs_stay_finite():
    p = _params(v_sat=3.0e38, white_level=3.4e38, g=1.0)
    v = np.full((8, 8), 3.0e38, np.float32)
    v[0, 0] = np.nan
    v[1, 1] = np.inf
    v[2, 2] = -3.0e38
    res = merge_arrays([v, v * np.float32(0.5)], [1e-6, 1e-6 * 0.5], Calibration(p), iterations=3)
    for arr in (res.irradiance, res.sigma, res.nexp):
        assert np.isfinite(arr).all()


def test_bad_input_raises_input_error():
    p = _params()
    v = np.zeros((4, 4), np.uint16)
    with pytest.raises(InputError):
        merge_arrays([v], [0.0], Calibration(p))
    with pytest.raises(InputError):
        merge_arrays([v, np.zeros((4, 5), np.uint16)], [1.0, 2.0], Calibration(p))
    with pytest.raises(InputError):
        merge_arrays([v], [1.0], Calibration(p), [v, v])
    with pytest.raises(InputError):
        merge_arrays([v], [1.0], Calibration(p), saturation="magic")
    with pytest.raises(InputError):
        merge_arrays([v], [1.0], Calibration(p), dark_strategy="matched")


# ------------------------------------------------------------------------------ real data


def _emva_steps(emva_dir):
    from hdrcap.pipeline.io.emva_descriptor import read_emva_descriptor
    from hdrcap.pipeline.io.raw import read_image16

    ds = read_emva_descriptor(emva_dir / "EMVA1288_Data.txt")
    darks = {round(s.exposure_time, 9): s for s in ds.dark()}
    steps = [s for s in ds.bright()[:50] if round(s.exposure_time, 9) in darks]

    def load(step, k):
        d = darks[round(step.exposure_time, 9)]
        return (
            read_image16(step.images[k], step.exposure_time).data,
            read_image16(d.images[k], step.exposure_time).data,
        )

    return ds, steps, load


def _photon_transfer(steps, load):
    """Gain (DN/e-) as the slope of temporal variance vs mean (EMVA 1288) on two steps, bias
    and read variance from the dark pair; independent of the merge."""
    pts = []
    for s in steps:
        (b1, d1), (b2, d2) = load(s, 0), load(s, 1)
        b1, b2, d1, d2 = (x.astype(np.float64) for x in (b1, b2, d1, d2))
        mean = 0.5 * (b1.mean() + b2.mean()) - 0.5 * (d1.mean() + d2.mean())
        var = np.var(b1 - b2) / 2 - np.var(d1 - d2) / 2
        pts.append((mean, var, d1.mean(), np.var(d1 - d2) / 2))
    (m1, v1, *_), (m2, v2, mu_R, s2) = pts
    return (v2 - v1) / (m2 - m1), mu_R, s2


def test_emva_two_disjoint_brackets_agree_within_predicted_sigma(emva_dir):
    ds, steps, load = _emva_steps(emva_dir)
    g, mu_R, s2 = _photon_transfer([steps[10], steps[25]], load)
    assert 0.2 < g < 0.4
    p = SensorParams(g=g, mu_R=mu_R, sigma2_R=s2, v_sat=float(2**ds.bits - 1), white_level=float(2**ds.bits - 1))
    cal = Calibration(p)
    chosen = [steps[i] for i in (1, 5, 15, 30)]
    times = [s.exposure_time for s in chosen]
    merged = []
    for k in (0, 1):  # snap_001 bracket vs snap_002 bracket, each with its own darks
        pairs = [load(s, k) for s in chosen]
        merged.append(merge_arrays([b for b, _ in pairs], times, cal, [d for _, d in pairs]))
    a, b = merged
    ok = (a.nexp > 0) & (b.nexp > 0)
    assert ok.mean() > 0.99
    z = (a.irradiance[ok] - b.irradiance[ok]) / np.hypot(a.sigma[ok], b.sigma[ok])
    # (measured: mean +0.04, std 1.007; the small mean is the light's drift between snaps)
    assert abs(z.mean()) < 0.1
    assert 0.95 < z.std() < 1.05, z.std()
    # Irradiance proportional to the data set's photon counts per second: single-step merges
    # at very different exposure times give the same e-/s per photon/s (the QE).
    qe = []
    for s in (steps[3], steps[12], steps[20], steps[28]):
        bright, dark = load(s, 0)
        res = merge_arrays([bright], [s.exposure_time], cal, [dark])
        qe.append(float(np.mean(res.irradiance[res.nexp > 0])) / (s.photons / s.exposure_time))
    qe_bracket = float(np.mean(a.irradiance[ok])) / (chosen[0].photons / chosen[0].exposure_time)
    assert 0.05 < qe[0] < 1.0
    assert np.ptp(qe) / np.mean(qe) < 0.03, qe
    assert qe_bracket == pytest.approx(np.mean(qe), rel=0.03)


def test_weights_precision_choice():
    """float32 weights for integer frames with ordinary parameters; float64 for float frames
    and where a bound leaves the float32 range (tiny read noise, extreme times and gains)."""
    rng = np.random.default_rng(5)
    X = np.full((16, 16), 500.0)
    p = _params()
    values, darks = _simulate_plain(p, X, [0.01, 0.1, 1.0], rng)
    u16 = [v.astype(np.uint16) for v in values]
    d16 = [d.astype(np.uint16) for d in darks]
    assert merge_arrays(u16, [0.01, 0.1, 1.0], Calibration(p), d16).info["weights_precision"] == "float32"
    assert merge_arrays(values, [0.01, 0.1, 1.0], Calibration(p), darks).info["weights_precision"] == "float64"
    tiny = _params(sigma2_R=1e-40, dark_current=0.0)
    assert merge_arrays(u16, [0.01, 0.1, 1.0], Calibration(tiny), d16).info["weights_precision"] == "float64"
    far = merge_arrays(u16, [1e-9, 0.1, 1e3], Calibration(_params(g=1e4, white_level=65535.0, v_sat=65000.0)), d16)
    assert far.info["weights_precision"] == "float64"


@pytest.mark.parametrize("cam", ["camera-A", "camera-B"])
def test_float32_weights_agree_with_float64_weights(cam, monkeypatch):
    """The float32 weights change the estimates by a negligible fraction of their sigma (the
    Monte Carlo tests above check the float32 path against the truth and the bound)."""
    import hdrcap.pipeline.merge.accumulator as pm

    spec = PRESETS[cam]
    sensor = SimulatedSensor(spec, (128, 128), seed=3)
    X = _scene(spec, (128, 128), np.random.default_rng(3))
    cal = _truth_calibration(sensor, spec.nominal_params())
    values = [sensor.expose(X, t) for t in TIMES]
    darks = [sensor.expose(X, t, dark=True) for t in TIMES]
    single = merge_arrays(values, TIMES, cal, darks)
    monkeypatch.setattr(pm, "SINGLE_PRECISION_WEIGHTS", False)
    double = merge_arrays(values, TIMES, cal, darks)
    assert single.info["weights_precision"] == "float32" and double.info["weights_precision"] == "float64"
    np.testing.assert_array_equal(single.nexp, double.nexp)
    ok = double.nexp > 0
    assert np.max(np.abs(single.irradiance - double.irradiance)[ok] / double.sigma[ok]) < 1e-3
    assert np.max(np.abs(single.sigma[ok] / double.sigma[ok] - 1)) < 1e-5


def test_shared_division_equals_one_division_per_sample():
    """The iteration pass with one division for three samples gives the weights of one
    division per sample (relative 1e-13), dropped samples included."""
    from hdrcap.pipeline.merge.kernels import _iterate

    rng = np.random.default_rng(9)
    n, W = 7, 300
    X = rng.uniform(-50, 5000, (n, W))
    X[rng.random((n, W)) < 0.1] = np.nan
    t = np.geomspace(1e-3, 1.0, n)
    g, s2, k = 2.0, 9.0, rng.choice([0.0, 0.125, 1.0], n)
    FR = np.stack([t * g, g * g * t, (t * g) ** 2, k, s2 * (1 + k)], axis=1)
    U, VSB = rng.uniform(0, 3000, W), rng.uniform(100, 4000, W)
    A2, DD = rng.uniform(0.9, 1.1, W) ** 2, rng.uniform(0, 5, W)
    out = []
    for shared in (True, False):
        Xc, SW, SWX = X.copy(), np.zeros(W), np.zeros(W)
        _iterate(Xc, FR, n, U, VSB, A2, DD, SW, SWX, s2, 9.0, True, shared, 0, W)
        out.append((Xc, SW, SWX))
    np.testing.assert_array_equal(np.isnan(out[0][0]), np.isnan(out[1][0]))
    assert np.isnan(out[0][0]).sum() > np.isnan(X).sum()  # the near-saturation rule dropped some
    np.testing.assert_allclose(out[0][1], out[1][1], rtol=1e-13)
    np.testing.assert_allclose(out[0][2], out[1][2], rtol=1e-12, atol=1e-12 * np.abs(out[1][2]).max())


def test_map_extrema_follow_in_place_changes():
    """The float32-weights check sees a map as it is now: a map changed in place gives its new
    extrema (no stale cache), non-finite maps give NaN, scalars their value."""
    from hdrcap.pipeline.merge.precision import extrema

    maps = [np.full((4, 4), float(i), np.float32) for i in range(5)]
    assert [extrema((m, True, 0.0)) for m in maps] == [(float(i), float(i)) for i in range(5)]
    maps[0][0, 0] = 100.0  # changed in place: the new extrema
    assert extrema((maps[0], True, 0.0)) == (0.0, 100.0)
    maps[0][1, 1] = -1.0
    assert extrema((maps[0], True, 0.0)) == (-1.0, 100.0)
    fresh = np.array([[np.inf]], np.float32)
    assert all(np.isnan(extrema((fresh, True, 0.0))))
    assert extrema((None, False, 2.5)) == (2.5, 2.5)


def test_weights_precision_follows_a_calibration_map_changed_in_place():
    """A PRNU map changed in place between two merges is seen by the float32-weights check."""
    from hdrcap.api import simulate

    sim = simulate("camera-A", "hdr", [0.004, 0.064, 1.0], seed=2, shape=(32, 48), darks=True)
    cal = sim.calibration
    first = merge_arrays(sim.frames, sim.times, cal, sim.darks)
    assert first.info["weights_precision"] == "float32"
    cal.prnu[0, 0] = 1e-20  # in place: float32 bounds no longer hold
    second = merge_arrays(sim.frames, sim.times, cal, sim.darks)
    assert second.info["weights_precision"] == "float64"


@pytest.mark.parametrize("bad", [np.nan, np.inf, 0.0, -0.5])
def test_prnu_map_not_finite_and_positive_is_refused(bad):
    """One photosite of the PRNU map NaN, infinite, zero or negative: refused, wherever it is."""
    spec = PRESETS["camera-A"]
    params = spec.nominal_params()
    prnu = np.ones((8, 6), np.float32)
    prnu[5, 3] = bad
    with pytest.raises(InputError, match="PRNU map must be finite and > 0"):
        MergeAccumulator(Calibration(params, prnu=prnu), (8, 6))
    prnu[5, 3] = 1.0
    MergeAccumulator(Calibration(params, prnu=prnu), (8, 6))  # the same map, valid, is accepted
