"""PixelStack (the streamed, sigma-clipped per-photosite mean of the calibration) against a direct
evaluation on the whole stack of frames: censored samples, unequal weights and cosmic rays."""

from __future__ import annotations

import numpy as np

from hdrcap.pipeline.calibration.stats import PixelStack


def _stack(seed: int, n_frames: int = 8, shape=(60, 70), equal_weights: bool = False):
    """Frames (truth + unit noise / sqrt(weight)), weights, censor masks and injected cosmic rays."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(100.0, 200.0, shape)
    weights = np.ones(n_frames) if equal_weights else rng.choice([0.5, 1.0, 2.0, 4.0], n_frames)
    frames = truth + rng.standard_normal((n_frames, *shape)) / np.sqrt(weights)[:, None, None]
    censor = rng.random((n_frames, *shape)) < 0.15
    censor[:, 0, 0] = True  # one photosite censored in every frame
    n_kept = (~censor).sum(0)
    # one cosmic ray (+1000 DN) in an uncensored sample of 5 % of the photosites with >= 4 samples
    hit = (rng.random(shape) < 0.05) & (n_kept >= 4)
    ray = np.zeros((n_frames, *shape), bool)
    for i, j in zip(*np.nonzero(hit)):
        k = rng.choice(np.flatnonzero(~censor[:, i, j]))
        ray[k, i, j] = True
    frames = (frames + 1000.0 * ray).astype(np.float32)
    return frames, weights, censor, ray, n_kept


def test_clipped_mean_is_the_weighted_mean_without_the_cosmic_rays():
    frames, weights, censor, ray, n_kept = _stack(3)
    stack = PixelStack(frames.shape[1:])
    for f, w, c in zip(frames, weights, censor):
        stack.add(f, w, c)
    mean, err, rejected = stack.result(5.0)
    keep = ~censor & ~ray
    w = weights[:, None, None] * keep
    expected = (w * frames.astype(np.float64)).sum(0) / np.maximum(w.sum(0), 1e-300)
    ok = n_kept >= 3
    ok[0, 0] = False
    # every ray is rejected; a good sample very rarely (the variance floor is the median of the
    # photosites' own variances, which with a few samples lies below their mean)
    same = np.isclose(mean, expected, rtol=1e-6, atol=0)[ok]
    assert same.mean() > 0.999, same.mean()
    assert int(ray.sum()) <= rejected <= int(ray.sum()) + (~same).sum()
    # every sample censored: the first frame's value with a 100 % error
    assert mean[0, 0] == frames[0, 0, 0] and err[0, 0] == abs(frames[0, 0, 0])
    assert np.all(np.isfinite(err)) and np.all(err[ok] > 0)
    # the standard error of a weighted mean of unit-variance-per-weight samples is 1/sqrt(sum w)
    z = err[ok] * np.sqrt(w.sum(0)[ok])
    assert 0.8 < float(np.median(z)) < 1.2


def test_equal_weights_without_censoring():
    frames, weights, _, ray, _ = _stack(4, equal_weights=True)
    frames = frames - 1000.0 * ray  # no rays: nothing may be rejected at 5 sigma
    stack = PixelStack(frames.shape[1:])
    for f in frames:
        stack.add(f)
    mean, err, rejected = stack.result(5.0)
    np.testing.assert_allclose(mean, frames.astype(np.float64).mean(0), rtol=1e-6)
    assert rejected == 0
    np.testing.assert_allclose(float(np.median(err)), 1.0 / np.sqrt(len(frames)), rtol=0.1)
