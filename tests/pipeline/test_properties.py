"""Laws the mathematics of the merge guarantees, checked with hypothesis over the documented
parameter ranges (gains 1e-3 to 1e3 DN/e-, read-noise variance 1/12 to 1e4 DN^2, 8 to 16
bits, exposure times 1e-6 to 1e4 s).

The frames come from a few lines of independent physics (Poisson electrons, Gaussian read
noise, rounding, clipping at the ADC maximum), never from the estimator's formulas. Every run
is derandomised: the same examples in every run of the suite.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from hdrcap.pipeline.merge.accumulator import MergeAccumulator, merge_arrays
from hdrcap.pipeline.params import Calibration, SensorParams

SETTINGS = settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
SHAPE = (12, 16)


@st.composite
def cameras(draw):
    """A scalar camera model anywhere in the documented ranges."""
    bits = draw(st.integers(8, 16))
    white = float(2**bits - 1)
    g = 10 ** draw(st.floats(-3, 3))
    sigma2 = 10 ** draw(st.floats(np.log10(1 / 12), 4))
    mu = draw(st.floats(0.0, 0.1)) * white
    # v_sat: at least a few read-noise sigmas above the bias, at most the ADC maximum.
    lo = min(mu + 4 * np.sqrt(sigma2), white * 0.9)
    v_sat = draw(st.floats(lo, white)) if lo < white else white
    v_sat = max(v_sat, mu + 1.0)
    return SensorParams(g=g, mu_R=mu, sigma2_R=sigma2, v_sat=v_sat, white_level=white)


@st.composite
def brackets(draw, n_min=2, n_max=5):
    """Exposure times (s) within 1e-6 to 1e4, and a scene spanning the bracket's range."""
    n = draw(st.integers(n_min, n_max))
    log_t = sorted(draw(st.lists(st.floats(-6, 4), min_size=n, max_size=n)))
    times = [10.0**x for x in log_t]
    seed = draw(st.integers(0, 2**31 - 1))
    return times, seed


def _simulate(p: SensorParams, X: np.ndarray, times, rng) -> list[np.ndarray]:
    """Independent physics: V = round(g Poisson(t X) + N(mu_R, sigma2_R)), clipped to [0, white]."""
    frames = []
    for t in times:
        electrons = rng.poisson(np.minimum(t * X, 1e15)).astype(np.float64)
        v = np.round(p.g * electrons + rng.normal(p.mu_R, np.sqrt(p.sigma2_R), X.shape))
        frames.append(np.clip(v, 0, p.white_level).astype(np.float32))
    return frames


def _scene(p: SensorParams, times, rng) -> np.ndarray:
    """Irradiance (e-/s) log-uniform from below the shortest exposure's read noise to above the
    longest exposure's noise floor: every sample type occurs (dark, well exposed, saturated)."""
    full = (p.v_sat - p.mu_R) / p.g  # electrons to saturation
    hi = full / min(times) * 4
    lo = max(np.sqrt(p.sigma2_R) / p.g / max(times) * 0.1, 1e-12)
    return np.exp(rng.uniform(np.log(lo), np.log(hi), SHAPE))


def _assert_same_merge(a, b, *, bound_may_rise: bool = False) -> None:
    """Same nexp; estimates within 1e-3 sigma where used; sigma within 1e-4 relative. Where
    saturated everywhere the irradiance is a lower bound: the same within 1e-5 relative, or
    with ``bound_may_rise`` at least as high (a saturated shorter exposure tightens it)."""
    np.testing.assert_array_equal(a.nexp, b.nexp)
    used = a.nexp > 0
    diff = np.abs(a.irradiance.astype(np.float64) - b.irradiance)
    assert (diff[used] <= 1e-3 * a.sigma[used].astype(np.float64)).all()
    if bound_may_rise:
        assert (b.irradiance[~used] >= a.irradiance[~used] * (1 - 1e-5)).all()
    else:
        np.testing.assert_allclose(b.irradiance[~used], a.irradiance[~used], rtol=1e-5)
    np.testing.assert_allclose(b.sigma, a.sigma, rtol=1e-4)


@SETTINGS
@given(cameras(), brackets(), st.booleans())
def test_finite_estimate_and_positive_sigma_everywhere(p, bracket, as_uint16):
    """For any camera in range, raw frames as uint16 (the float32-weight path where its bounds
    allow) or float32: no NaN or inf, and sigma > 0 wherever an exposure was used."""
    times, seed = bracket
    rng = np.random.default_rng(seed)
    frames = _simulate(p, _scene(p, times, rng), times, rng)
    if as_uint16:
        frames = [f.astype(np.uint16) for f in frames]
    r = merge_arrays(frames, times, Calibration(p))
    assert np.isfinite(r.irradiance).all()
    assert np.isfinite(r.sigma).all()
    assert (r.sigma[r.nexp > 0] > 0).all()
    assert ((r.nexp >= 0) & (r.nexp <= len(times))).all()


@SETTINGS
@given(cameras(), brackets(), st.randoms(use_true_random=False))
def test_order_of_frames_does_not_matter(p, bracket, shuffler):
    """The ML estimate is a function of the set of exposures (Eq. 12), not of their order."""
    times, seed = bracket
    rng = np.random.default_rng(seed)
    frames = _simulate(p, _scene(p, times, rng), times, rng)
    order = list(range(len(times)))
    shuffler.shuffle(order)
    a = merge_arrays(frames, times, Calibration(p))
    b = merge_arrays([frames[i] for i in order], [times[i] for i in order], Calibration(p))
    _assert_same_merge(a, b)


@SETTINGS
@given(cameras(), brackets(), st.floats(-1, 1))
def test_scaling_times_scales_irradiance_and_keeps_snr(p, bracket, log_c):
    """Without dark current, times c*t see irradiance X/c through the same raw values:
    the estimate and sigma scale by 1/c, the SNR is unchanged."""
    times, seed = bracket
    c = 10.0**log_c
    rng = np.random.default_rng(seed)
    frames = _simulate(p, _scene(p, times, rng), times, rng)
    a = merge_arrays(frames, times, Calibration(p))
    b = merge_arrays(frames, [t * c for t in times], Calibration(p))
    np.testing.assert_array_equal(a.nexp, b.nexp)
    used = a.nexp > 0
    np.testing.assert_allclose(b.irradiance[used] * c, a.irradiance[used], rtol=1e-4, atol=1e-4 * a.sigma[used].max())
    np.testing.assert_allclose(b.sigma[used] * c, a.sigma[used], rtol=1e-4)


@SETTINGS
@given(cameras(), brackets())
def test_streaming_equals_batch_bit_for_bit(p, bracket):
    """Frames added one by one as they land give exactly the batch result."""
    times, seed = bracket
    rng = np.random.default_rng(seed)
    frames = _simulate(p, _scene(p, times, rng), times, rng)
    batch = merge_arrays(frames, times, Calibration(p))
    acc = MergeAccumulator(Calibration(p), SHAPE)
    for v, t in zip(frames, times):
        acc.add(v, t)
    stream = acc.result()
    np.testing.assert_array_equal(stream.irradiance, batch.irradiance)
    np.testing.assert_array_equal(stream.sigma, batch.sigma)
    np.testing.assert_array_equal(stream.nexp, batch.nexp)


@SETTINGS
@given(cameras(), brackets(), st.floats(-6, 4))
def test_a_frame_saturated_everywhere_changes_nothing(p, bracket, log_t):
    """A sample at the ADC maximum carries no information below saturation (Eq. 11): the
    estimates and sigmas do not change; only the lower bound of photosites saturated
    everywhere may rise. (Without the clip rule, which reads a saturated shorter exposure as a
    lower bound and rejects a possibly clipped longer sample below it: a frame at the white
    level whatever the scene contradicts the longer frames, docs/merge.md item 4.)"""
    times, seed = bracket
    rng = np.random.default_rng(seed)
    frames = _simulate(p, _scene(p, times, rng), times, rng)
    a = merge_arrays(frames, times, Calibration(p), clip_sigmas=0.0)
    white = np.full(SHAPE, p.white_level, np.float32)
    b = merge_arrays([*frames, white], [*times, 10.0**log_t], Calibration(p), clip_sigmas=0.0)
    _assert_same_merge(a, b, bound_may_rise=True)


@SETTINGS
@given(cameras(), brackets(n_min=1, n_max=4), st.floats(-6, 4))
def test_an_unsaturated_frame_never_increases_sigma(p, bracket, log_t):
    """Noise-free frames (the expected raw values, so the estimate is the truth in every case):
    one more unsaturated exposure adds a positive weight, so sigma cannot grow (Eq. 12). (The
    saturation rules are off: with another sample the clip rule may judge a value just under
    v_sat more likely clipped than not, docs/merge.md item 4, and leave the new sample alone.)"""
    times, seed = bracket
    rng = np.random.default_rng(seed)
    t_new = 10.0**log_t
    X = _scene(p, [*times, t_new], rng)

    def expected(t):
        return (p.mu_R + p.g * t * X).astype(np.float64)

    frames = [expected(t) for t in times]
    a = merge_arrays(frames, times, Calibration(p), saturation_sigmas=0.0, clip_sigmas=0.0)
    b = merge_arrays(
        [*frames, expected(t_new)], [*times, t_new], Calibration(p), saturation_sigmas=0.0, clip_sigmas=0.0
    )
    both = (a.nexp > 0) & (b.nexp > 0)
    assert (b.nexp >= a.nexp).all()
    assert (b.sigma[both] <= a.sigma[both] * (1 + 1e-6)).all()


@settings(max_examples=12, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(
    st.floats(-3.0, 3.0),  # log10 g
    st.floats(np.log10(1 / 12), 4.0),  # log10 sigma2_R
    st.integers(8, 16),  # bits
    st.floats(0.5, 4.0),  # decades of scene range
    st.floats(10.0, 40.0),  # target, dB
    st.integers(0, 2**31 - 1),
)
def test_plan_reaches_its_predicted_snr_under_its_own_model(log_g, log_s2, bits, decades, target, seed):
    """Sec. 8: the SNR predicted for the planned exposures, dark strategies and merge model,
    re-evaluated independently with ``predict_snr``, is the plan's stated minimum over the
    eligible pixels; a feasible plan reaches the target. Over the documented ranges wherever the
    camera can see: at least 100 electrons to saturation, read noise under 5 % of the range."""
    from hdrcap.planner import plan_exposures, predict_snr, systematic_errors_from_calibration

    white = float(2**bits - 1)
    p = SensorParams(g=10**log_g, mu_R=0.02 * white, sigma2_R=10**log_s2, v_sat=0.95 * white, white_level=white)
    assume(np.sqrt(p.sigma2_R) < 0.05 * white and (p.v_sat - p.mu_R) / p.g >= 100)  # a camera that can see
    cal = Calibration(p)
    rng = np.random.default_rng(seed)
    full = (p.v_sat - p.mu_R) / p.g
    top = full / 1e-3  # saturates at 1 ms
    X = top * 10 ** rng.uniform(-decades, 0, 4000)
    plan = plan_exposures(cal, X, target)
    curve_X = np.asarray(plan.curve["irradiance"])
    eligible = np.asarray(plan.curve["eligible"], bool)
    assert eligible.any()
    opts = plan.merge_options()
    pred = predict_snr(
        curve_X[eligible],
        plan.exposures,
        cal,
        darks=plan.darks,
        n_dark=plan.n_dark,
        errors=systematic_errors_from_calibration(cal),
        prnu=opts.get("prnu", "map"),
        saturation=opts.get("saturation", "threshold"),
        k_sigma=plan.saturation_sigmas,
    )
    if plan.quantile == 1.0:
        assert np.min(pred.snr_db) >= plan.predicted_min_snr_db - 0.01
    if plan.feasible:
        assert plan.predicted_min_snr_db >= target - 1e-6


@settings(max_examples=12, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(
    st.floats(-3.0, 3.0),  # log10 g
    st.floats(0.0, 4.0),  # log10 sigma2_R
    st.integers(8, 16),  # bits
    st.floats(0.3, 0.7),  # flat level, fraction of the range above bias
    st.integers(0, 2**31 - 1),
)
def test_calibration_recovers_its_camera_within_stated_errors(log_g, log_s2, bits, level, seed):
    """Sec. 6: g, mu_R and sigma2_R estimated from simulated bias, saturation and flat frames
    lie within 4 of their stated standard errors of the simulator's values, over the documented
    ranges wherever a camera can be calibrated at all: at least 100 electrons to saturation, the
    bias level plus 8 read-noise sigmas below half the range, and a photon variance of the flats
    at least a tenth of the read-noise variance (else the gain is refused). Read noise below 1 DN^2 is left
    out: there the rounded bias frames bias mu_R and sigma2_R by up to 170 and 80 of their stated
    standard errors (sigma2_R = 0.1 DN^2, 8-16 bits), and may be estimated as 0 (calibrate then
    raises ValueError)."""
    import dataclasses

    from hdrcap.mock_camera import PRESETS, SimulatedSensor
    from hdrcap.pipeline.calibration import calibrate
    from hdrcap.pipeline.io.raw import RawFrame

    white = float(2**bits - 1)
    g, s2 = 10**log_g, 10**log_s2
    mu = 0.03 * white + 4 * np.sqrt(s2)
    assume(mu + 8 * np.sqrt(s2) < 0.5 * white and (white - mu) / g >= 100)
    assume(g * level * (white - mu) >= s2 / 10)  # photon noise of the flats not buried in read noise
    spec = dataclasses.replace(
        PRESETS["camera-B"],
        g=g,
        sigma2_R=s2,
        mu_R=mu,
        bits=bits,
        full_well=1.1 * (white - mu) / g,
        dark_current=0.0,
        dcnu=0.0,
    )
    sensor = SimulatedSensor(spec, (96, 96), seed=seed)
    rng = np.random.default_rng([seed, 5])
    t = 0.01
    X = level * (white - mu) / g / t

    def shots(x, tt, n, kind, dark=False):
        return [
            RawFrame(sensor.expose(x, tt, dark=dark, rng=rng), tt, path=f"{kind}{i}.dng", white_level=white)
            for i in range(n)
        ]

    cal = calibrate(
        shots(0.0, 1e-4, 2, "bias", True), shots(X, 10 * t, 1, "sat"), shots(X, t, 24, "flat"), white_level=white
    )
    p, se = cal.params, cal.stderr
    assert abs(p.g - g) <= 4 * se["g"], (p.g, g, se["g"])
    assert abs(p.mu_R - mu) <= 4 * se["mu_R"] + 0.02, (p.mu_R, mu, se["mu_R"])
    assert abs(p.sigma2_R - s2) <= 4 * se["sigma2_R"] + 1 / 12, (p.sigma2_R, s2, se["sigma2_R"])
