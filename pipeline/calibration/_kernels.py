"""Fused numba kernels for the streamed calibration (one pass, no full-size temporaries).

Private to :mod:`hdrcap.pipeline.calibration`; every accumulation is float64.
"""

from __future__ import annotations

import numpy as np

from .._numba_target import numba  # numba, its compile target set (512-bit vectors on AVX-512)

__all__ = ["stack_add", "stack_add_equal", "masked_moments", "pair_keep", "pair_moments"]


@numba.njit(cache=True, nogil=True)
def stack_add(values, ref, w, s, q, mx, mn, wmx, wmn):  # pragma: no cover - compiled
    """s += w d, q += w d^2, track max/min of d and their weights, d = values - ref."""
    v = values.ravel()
    r = ref.ravel()
    s_, q_, mx_, mn_, wx_, wn_ = s.ravel(), q.ravel(), mx.ravel(), mn.ravel(), wmx.ravel(), wmn.ravel()
    for i in range(v.size):
        d = np.float64(v[i]) - np.float64(r[i])
        s_[i] += w * d
        q_[i] += w * d * d
        if d > mx_[i]:
            mx_[i] = d
            wx_[i] = w
        if d < mn_[i]:
            mn_[i] = d
            wn_[i] = w


@numba.njit(cache=True, nogil=True)
def stack_add_equal(values, ref, w, s, q, mx, mn):  # pragma: no cover - compiled
    """:func:`stack_add` when every frame has the same weight (no weight maps needed)."""
    v = values.ravel()
    r = ref.ravel()
    s_, q_, mx_, mn_ = s.ravel(), q.ravel(), mx.ravel(), mn.ravel()
    for i in range(v.size):
        d = np.float64(v[i]) - np.float64(r[i])
        s_[i] += w * d
        q_[i] += w * d * d
        if d > mx_[i]:
            mx_[i] = d
        if d < mn_[i]:
            mn_[i] = d


@numba.njit(cache=True, nogil=True)
def masked_moments(x, keep, shift):  # pragma: no cover - compiled
    """Count, mean and sum of squared deviations of x[keep] (shifted sums for stability)."""
    xv = x.ravel()
    kv = keep.ravel()
    n = 0
    s1 = 0.0
    s2 = 0.0
    for i in range(xv.size):
        if kv[i]:
            d = np.float64(xv[i]) - shift
            n += 1
            s1 += d
            s2 += d * d
    if n == 0:
        return 0, 0.0, 0.0
    m = s1 / n
    return n, m + shift, s2 - n * m * m


@numba.njit(cache=True, nogil=True)
def pair_keep(a, b, lo_a, hi_a, lo_b, hi_b, lo_d, hi_d):  # pragma: no cover - compiled
    """Photosites where a, b and a - b all lie within their clip intervals."""
    av = a.ravel()
    bv = b.ravel()
    keep = np.empty(av.size, np.bool_)
    for i in range(av.size):
        x = np.float64(av[i])
        y = np.float64(bv[i])
        d = x - y
        keep[i] = lo_a <= x <= hi_a and lo_b <= y <= hi_b and lo_d <= d <= hi_d
    return keep.reshape(a.shape)


@numba.njit(cache=True, nogil=True)
def pair_moments(a, b, keep):  # pragma: no cover - compiled
    """n, mean(a), mean(b), mean of c^2 and of c^4 with c = a - b - (mean a - mean b), over keep."""
    av = a.ravel()
    bv = b.ravel()
    kv = keep.ravel()
    n = 0
    sa = 0.0
    sb = 0.0
    a0 = np.float64(av[0])
    b0 = np.float64(bv[0])
    for i in range(av.size):
        if kv[i]:
            n += 1
            sa += np.float64(av[i]) - a0
            sb += np.float64(bv[i]) - b0
    if n == 0:
        return 0, 0.0, 0.0, 0.0, 0.0
    mu_a = sa / n + a0
    mu_b = sb / n + b0
    delta = mu_a - mu_b
    s2 = 0.0
    s4 = 0.0
    for i in range(av.size):
        if kv[i]:
            c = np.float64(av[i]) - np.float64(bv[i]) - delta
            c2 = c * c
            s2 += c2
            s4 += c2 * c2
    return n, mu_a, mu_b, s2 / n, s4 / n
