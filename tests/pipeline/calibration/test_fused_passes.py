"""The fused passes of the calibration (no full-size temporaries) against the numpy expressions
they replace: a flat's level and clipped count, the stack of dark-corrected flats, the pair
statistics and the counted medians. Bit for bit where the order of the sums is unchanged."""

from __future__ import annotations

import numpy as np
import pytest

# Private names on purpose: each fused pass is checked against the numpy expression it replaces.
from hdrcap.pipeline.calibration import flats as fl
from hdrcap.pipeline.calibration.stats import (
    _MAD_TO_SIGMA,
    BATCH,
    CENSOR_SIGMA,
    PixelStack,
    _censor_limit,
    _float_median_mad,
    _int_median_mad,
    _subsample,
    as_correction_map,
    pair_statistics,
    robust_mean_std,
)

SHAPE = (300, 700)  # 210 000 photosites: the clip bounds come from a subsample


def _frames(seed: int, n: int = 4, level: float = 2000.0):
    """Flats (uint16) with hot pixels and a few clipped photosites, a float32 bias map and rate."""
    rng = np.random.default_rng(seed)
    bias = (128 + rng.normal(0, 2, SHAPE)).astype(np.float32)
    rate = rng.gamma(2.0, 0.3, SHAPE).astype(np.float32)
    frames = []
    for _ in range(n):
        x = bias + level * (1 + rng.normal(0, 0.01, SHAPE)) + rng.normal(0, 20, SHAPE)
        x[rng.random(SHAPE) < 1e-3] = 4095
        frames.append(np.clip(np.round(x), 0, 4095).astype(np.uint16))
    return frames, bias, rate


def _image(data, bias, rate, t):
    """The dark-corrected float32 image as the flats' numpy code made it."""
    corr = data.astype(np.float32)
    corr -= bias
    corr -= rate * t
    return corr


@pytest.mark.parametrize("scalar_bias", [False, True])
def test_flat_level_matches_the_image(scalar_bias):
    frames, bias, rate = _frames(0)
    ref = 128.0 if scalar_bias else bias
    corr = _image(frames[0], ref, rate, 0.3)
    mean, _sd, keep = robust_mean_std(corr, 5.0)
    level, n_clip = fl._flat_level(
        frames[0], as_correction_map(ref, SHAPE), as_correction_map(rate, SHAPE), 0.3, 4000.0, 5.0, "f"
    )
    assert n_clip == int(np.count_nonzero(frames[0] >= 4000.0))
    assert level == pytest.approx(mean, rel=1e-13)  # the same photosites; sums in another order
    assert keep.sum() < keep.size  # the clip did reject the hot photosites


def test_stack_of_corrected_flats_is_bit_identical():
    frames, bias, rate = _frames(1, n=5)
    upper = 4000.0
    a, b = PixelStack(SHAPE), PixelStack(SHAPE)
    off, rt = as_correction_map(bias, SHAPE), as_correction_map(rate, SHAPE)
    for k, f in enumerate(frames):
        level, t, w = 1900.0 + 10 * k, 0.1 * (k + 1), 1.0 + (k % 2)
        corr = _image(f, bias, rate, t)
        corr /= level
        clipped = f >= upper
        a.add(corr, weight=w, censor=clipped)  # with a mask: added at once, frame by frame
        b.add_corrected(f, off, rt, t, level, w, upper, int(clipped.sum()))
    for x, y in zip(a.result(5.0), b.result(5.0)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_queued_raw_frames_and_reset_are_bit_identical(dtype):
    """Raw frames queued by add() (one pass per batch) as added one by one, also after reset()."""
    frames, _bias, _rate = _frames(5, n=BATCH + 3)
    a, b = PixelStack(SHAPE), PixelStack(SHAPE)
    for rnd in range(2):
        for k, f in enumerate(frames[rnd:]):
            f = (f * 1.001).astype(dtype) if dtype != np.uint16 else f
            w = 1.0 if k < 4 else 2.0
            a.add(f, weight=w, censor=np.zeros(SHAPE, bool))  # at once, the frame-by-frame kernels
            b.add(f, weight=w)
        for x, y in zip(a.result(5.0), b.result(5.0)):
            np.testing.assert_array_equal(x, y)
        a = PixelStack(SHAPE)
        b.reset()


def test_batched_stack_over_many_flats_is_bit_identical():
    """More flats than one batch, a flat without dark rate (t = 0) and a censored one between
    them, and a float32 frame (another batch): as the images added one by one."""
    frames, bias, rate = _frames(4, n=2 * BATCH + 3)
    frames[5] = frames[5].astype(np.float32)
    upper = 4000.0
    a, b = PixelStack(SHAPE), PixelStack(SHAPE)
    off, rt, no_rate = as_correction_map(bias, SHAPE), as_correction_map(rate, SHAPE), as_correction_map(None, ())
    for k, f in enumerate(frames):
        level, t, w = 1900.0 + 10 * k, 0.0 if k == 3 else 0.1 * (k + 1), 1.0 + (k > 6)
        corr = _image(f, bias, rate if t > 0 else 0.0, t)
        corr /= np.float32(level)
        clipped = f >= upper if k in (9, 12) else np.zeros(SHAPE, bool)
        a.add(corr, weight=w, censor=clipped)  # with a mask: added at once, frame by frame
        b.add_corrected(f, off, rt if t > 0 else no_rate, t, level, w, upper, int(clipped.sum()))
    np.testing.assert_array_equal(a.n_uncensored(), b.n_uncensored())
    for x, y in zip(a.result(5.0), b.result(5.0)):
        np.testing.assert_array_equal(x, y)


def _pair_reference(a, b, clip, upper):
    """pair_statistics as numpy expressions over masks (the code the fused kernel replaced)."""
    sa, sb = _subsample(a).astype(np.float64), _subsample(b).astype(np.float64)
    keep = np.ones(a.shape, bool)
    for x, s in ((a.astype(np.float64), sa), (b.astype(np.float64), sb), (a.astype(np.float64) - b, sa - sb)):
        med, mad = _float_median_mad(s)
        scale = _MAD_TO_SIGMA * mad or float(np.std(s))
        keep &= (x >= med - clip * scale) & (x <= med + clip * scale)
    sub = (sa - _subsample(b)) / 2.0
    scale = _MAD_TO_SIGMA * float(np.median(np.abs(sub - np.median(sub)))) or float(np.std(sub))
    total = a.astype(np.float32)
    total += b
    keep &= ~(total >= np.float32(2.0 * (upper - CENSOR_SIGMA * scale)))
    x, y = a[keep].astype(np.float64), b[keep].astype(np.float64)
    c = x - y - (x.mean() - y.mean())
    return x.mean(), y.mean(), 0.5 * np.mean(c * c), int(keep.sum())


@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_pair_statistics_match_the_masks(dtype):
    frames, _bias, _rate = _frames(2, n=2, level=3500.0)
    a, b = (f.astype(dtype) for f in frames)
    ps = pair_statistics(a, b, 5.0, 0.1, upper=3800.0)
    mu_a, mu_b, var, n = _pair_reference(a, b, 5.0, 3800.0)
    assert ps.n_used == n and ps.n_censored > 0
    assert (ps.mean_a, ps.mean_b) == pytest.approx((mu_a, mu_b), rel=1e-14)
    assert ps.variance == pytest.approx(var, rel=1e-11)
    assert _censor_limit(a, b, 4000.0) == pytest.approx(_censor_limit(a.astype(np.float64), b, 4000.0), rel=0)


def test_counted_medians_are_numpys():
    rng = np.random.default_rng(3)
    for k in range(300):
        x = rng.integers(-40, 60 + k, int(rng.integers(1, 300)))
        assert _int_median_mad(x) == _float_median_mad(x)
        assert _int_median_mad(np.abs(x).astype(np.uint16)) == _float_median_mad(np.abs(x).astype(np.uint16))


@pytest.mark.parametrize("kind", ["normal", "ties", "hot", "cauchy", "zeros", "odd"])
def test_selected_medians_are_numpys(kind):
    """The dark-current map's population limits: the medians of a float32 map's float64 values
    and of their absolute deviations, selected without a copy, equal numpy.median of them."""
    from hdrcap.pipeline.calibration._kernels import median_f32

    rng = np.random.default_rng(7)
    n = 40_000
    a = (
        {
            "normal": rng.normal(0.3, 0.05, n),
            "ties": rng.integers(-3, 4, n).astype(float),
            "hot": np.concatenate([rng.normal(0.0, 1e-3, n), rng.exponential(100.0, n // 50)]),
            "cauchy": rng.standard_cauchy(n),
            "zeros": np.where(np.arange(n) % 3 == 0, -0.0, np.where(np.arange(n) % 3 == 1, 0.0, 1e-40)),
            "odd": rng.normal(-2.0, 1.0, n + 1),
        }[kind]
        .astype(np.float32)
        .reshape(-1, 200 if kind != "odd" else 1)
    )
    med = float(np.median(a.astype(np.float64)))
    assert median_f32(a, 0.0, False) == med
    assert median_f32(a, med, True) == float(np.median(np.abs(a.astype(np.float64) - med)))
    a.flat[3] = np.nan
    assert np.isnan(median_f32(a, 0.0, False))
