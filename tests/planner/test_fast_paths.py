"""The planner's and the file layer's fast paths equal what they replace, bit for bit.

* ``eligible_mask`` on a large map (a bisection for the rule's limit, the rule itself only in
  a narrow band around it) equals the rule evaluated on every photosite, also with photosites
  placed within a few ulps of the limit, zeros, negative values and NaN;
* ``irradiance_histogram`` in blocks equals the same histogram computed on the whole array at
  once (written here again), over maps that span many blocks;
* ``read_exr(path, channels=...)`` returns exactly the requested channels, equal to a full read;
* loading a calibration file does not import the estimators' numba kernels, and every public
  name of ``hdrcap.pipeline.calibration`` still resolves.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdrcap.pipeline import calibration as calpkg
from hdrcap.pipeline.io.exr import read_exr, write_exr
from hdrcap.pipeline.params import Calibration, SensorParams
from hdrcap.planner.plan import (  # the private block sizes on purpose: inputs must span several blocks
    _ELIGIBLE_DIRECT,
    _HIST_BLOCK,
    eligible_mask,
    irradiance_histogram,
)
from hdrcap.planner.predict import usable_fraction


def _calibration(g=0.23, mu_R=128.0, sigma2_R=6.5, v_sat=3709.0, white=4095.0, dark=3.0):
    return Calibration(
        SensorParams(g=g, mu_R=mu_R, sigma2_R=sigma2_R, v_sat=v_sat, white_level=white, dark_current=dark)
    )


def _rule(X, t, cal, k):
    return (X > 0) & (usable_fraction(X, t, cal, "threshold", k) > 0)


@pytest.mark.parametrize("k_sigma", [0.0, 3.0])
@pytest.mark.parametrize("t_min", [1e-4, 1 / 60, 30.0])
def test_eligible_mask_equals_the_rule_on_every_photosite(t_min, k_sigma):
    cal = _calibration()
    rng = np.random.default_rng([int(t_min * 1e4), int(k_sigma)])
    n = 4 * _ELIGIBLE_DIRECT
    X = 10 ** rng.uniform(-2, 9, n)
    # the limit itself, by a dense scan of the rule: photosites within a few ulps of it
    grid = np.geomspace(1e-3, 1e10, 20001)
    ok = _rule(grid, t_min, cal, k_sigma)
    edge = grid[np.argmin(ok)] if not ok.all() else grid[-1]
    fine = np.geomspace(edge / 1.01, edge * 1.01, 200001)
    limit = fine[np.argmin(_rule(fine, t_min, cal, k_sigma))]
    X[:400] = limit * (1 + np.arange(-200, 200) * np.finfo(float).eps)
    X[400:410] = [0.0, -1.0, -limit, np.nan, np.inf, -np.inf, 1e-300, 1e300, limit, np.nextafter(limit, 0)]
    rng.shuffle(X)
    got = eligible_mask(X, t_min, cal, k_sigma)
    with np.errstate(invalid="ignore"):  # the rule itself on +-inf (0 * inf in its sigma)
        want = _rule(X, t_min, cal, k_sigma)
    assert got.dtype == bool and got.shape == X.shape
    assert np.array_equal(got, want)
    assert 0 < want.sum() < n  # both sides of the limit are present
    assert np.array_equal(eligible_mask(X.reshape(64, -1), t_min, cal, k_sigma), want.reshape(64, -1))


def test_eligible_mask_with_a_negative_margin_takes_the_rule_itself():
    """k < 0 (accepted by the planner's API, refused by the merge) need not be monotone in X."""
    cal = _calibration(sigma2_R=400.0)
    X = np.geomspace(1e-3, 1e7, 2 * _ELIGIBLE_DIRECT)
    assert np.array_equal(eligible_mask(X, 1e-3, cal, -5.0), _rule(X, 1e-3, cal, -5.0))


def test_eligible_mask_where_the_rule_has_no_limit():
    """v_sat below the bias: nothing is usable; a huge v_sat: everything with signal is."""
    X = np.geomspace(1e-3, 1e12, 2 * _ELIGIBLE_DIRECT)
    none = _calibration(mu_R=128.0, v_sat=100.0)
    assert not eligible_mask(X, 1e-3, none).any()
    every = _calibration(v_sat=1e308, white=1e308)
    assert eligible_mask(X, 1e-3, every).all()


def _histogram_whole(x, bins=256):
    """The histogram on the whole array at once, its per-bin extremes found another way (the
    values sorted, each bin's first and last): a point of weight n for a bin of one value,
    else its smallest and largest value with n/2 each, in increasing order."""
    x = np.asarray(x, dtype=np.float64).ravel()
    pos = np.sort(x[x > 0])
    lx = np.log10(pos)
    lo, hi = lx.min(), lx.max()
    idx = np.minimum(((lx - lo) / (hi - lo) * bins).astype(np.int64), bins - 1)
    _, first, n = np.unique(idx, return_index=True, return_counts=True)
    points = []
    for f, c in zip(first, n):
        small, large = pos[f], pos[f + c - 1]
        points += [(small, float(c))] if small == large else [(small, c / 2), (large, c / 2)]
    X, w = (np.array(v) for v in zip(*sorted(points)))
    return X, w, x.size, x.size - pos.size


@pytest.mark.parametrize("seed", [1, 2])
def test_histogram_in_blocks_equals_the_whole_array(seed):
    rng = np.random.default_rng(seed)
    n = 5 * _HIST_BLOCK + 12345
    x = rng.lognormal(4, 3, n)
    x[rng.random(n) < 0.1] = 0.0
    x[rng.random(n) < 0.05] *= -1
    x[: _HIST_BLOCK + 7] = 0.0  # a whole block without signal
    h = irradiance_histogram(x.astype(np.float32) if seed == 2 else x)
    X, w, n_pix, n_no = _histogram_whole(x.astype(np.float32) if seed == 2 else x)
    assert np.array_equal(h.X, X) and np.array_equal(h.weight, w)
    assert (h.n_pixels, h.n_nosignal) == (n_pix, n_no)


def test_histogram_refuses_non_finite_values_in_any_block():
    x = np.ones(3 * _HIST_BLOCK)
    x[-1] = np.nan
    with pytest.raises(Exception, match="NaN or infinite"):
        irradiance_histogram(x)


def test_read_exr_keeps_only_the_requested_channels(tmp_path):
    rng = np.random.default_rng(4)
    ch = {
        "irradiance": rng.lognormal(3, 1, (20, 30)).astype(np.float32),
        "sigma": rng.random((20, 30)).astype(np.float32) + 0.5,
        "nexp": rng.integers(0, 6, (20, 30)).astype(np.float32),
    }
    path = write_exr(tmp_path / "m.exr", ch, {"unit": "e-/s"}, precision={"sigma": "half", "nexp": "uint"})
    full = read_exr(path)
    part = read_exr(path, channels=["irradiance", "nexp", "Y"])
    assert set(part.channels) == {"irradiance", "nexp"}
    for name, arr in part.channels.items():
        assert arr.dtype == np.float32 and np.array_equal(arr, full.channels[name])
    assert part.header == full.header
    assert read_exr(path, channels=[]).channels == {}


def test_loading_a_calibration_does_not_import_numba():
    code = (
        "import sys\n"
        "from hdrcap.pipeline.calibration import load_calibration, save_calibration\n"
        "from hdrcap.planner.meter import read_irradiance_map\n"
        "assert 'numba' not in sys.modules, 'numba imported'\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_every_public_name_of_the_calibration_package_resolves():
    assert set(calpkg.__all__) == set(calpkg._HOME)  # private on purpose: the lazy-export table
    for name in calpkg.__all__:
        assert getattr(calpkg, name) is not None
        assert name in dir(calpkg)
    with pytest.raises(AttributeError):
        calpkg.no_such_name  # noqa: B018


@settings(max_examples=25, deadline=None, derandomize=True)
@given(
    g=st.floats(1e-3, 1e3),
    sigma2_R=st.floats(1 / 12, 1e4),
    bits=st.integers(8, 16),
    dark=st.floats(0.0, 1e4),
    t=st.floats(1e-6, 1e4),
    k=st.floats(0.0, 6.0),
)
def test_eligible_mask_equals_the_rule_for_any_camera(g, sigma2_R, bits, dark, t, k):
    """A law: the fast path and the rule agree on every photosite, for cameras across the
    documented ranges (gains 1e-3..1e3, sigma_R^2 1/12..1e4, 8-16 bits, times 1e-6..1e4 s)."""
    white = 2.0**bits - 1
    cal = _calibration(g=g, mu_R=0.05 * white, sigma2_R=sigma2_R, v_sat=0.9 * white, white=white, dark=dark)
    rng = np.random.default_rng(7)
    X = 10 ** rng.uniform(-8, 12, _ELIGIBLE_DIRECT + 1)
    assert np.array_equal(eligible_mask(X, t, cal, k), _rule(X, t, cal, k))
