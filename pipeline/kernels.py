"""Compiled per-photosite kernels of the optimal merge (numba, parallel over rows).

The whole estimator of :mod:`pipeline.merge` runs here, one photosite at a time, with all of
that photosite's samples in registers/cache: one pass over the input frames, no full-size
per-frame temporaries (only a buffer of one row per frame and thread), float64 arithmetic,
float32 outputs. The variance is :func:`pipeline.noise.variance_core`, compiled as is (the
formula is written only there).

Conventions shared by the kernels
---------------------------------
``values``/``darks``
    numba typed lists of 2-D arrays (DN). With ``has_darks`` the dark level of frame i is
    ``darks[i]``; otherwise it is ``base + base_shift * g * D * (t_i - t_ref)`` (``base`` the bias map or
    ``mu_R`` for the model strategy, a master dark taken at ``t_ref`` otherwise).
maps
    ``(array, is_map, scalar)``: a float32 map of the image's shape when ``is_map``, else the
    float64 ``scalar`` (PRNU gain a, dark current D in e-/s, bias in DN, dark base in DN).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from .noise import variance_core

__all__ = ["merge_kernel", "first_pass_kernel", "FLOAT32_MAX"]

FLOAT32_MAX = float(np.finfo(np.float32).max)

_vcore = numba.njit(inline="always", cache=True)(variance_core)

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@numba.njit(inline="always", cache=True)
def _pick(arr, is_map, scalar, r, c):
    if is_map:
        return float(arr[r, c])
    return scalar


@numba.njit(inline="always", cache=True)
def _sample(v, b, tga, v_sat):
    """x_i of Eq. 6 and whether the sample is usable under Eq. 11 (observed value)."""
    x = (v - b) / tga
    ok = (v < v_sat) and (b < v_sat) and math.isfinite(x)
    return x, ok


@numba.njit(inline="always", cache=True)
def _clamp32(x):
    if not math.isfinite(x):
        return 0.0 if math.isnan(x) else (FLOAT32_MAX if x > 0 else -FLOAT32_MAX)
    return min(max(x, -FLOAT32_MAX), FLOAT32_MAX)


@numba.njit(parallel=True, cache=True)
def first_pass_kernel(v_arr, d_arr, has_dark, base, base_is_map, base_scalar, t_ref, base_shift, t, g, v_sat,
                      D_map, D_is_map, D_scalar, a_map, a_is_map, init_sum, init_cnt):
    """Streaming first pass: add one frame's usable x_i to the non-saturated average.

    Computes x_i exactly as :func:`merge_kernel` does, so that a merge started from these
    sums equals the batch merge bit for bit when the frames come in the same order.
    """
    H, W = v_arr.shape
    for r in prange(H):
        for c in range(W):
            a = _pick(a_map, a_is_map, 1.0, r, c)
            D = _pick(D_map, D_is_map, D_scalar, r, c)
            if has_dark:
                b = float(d_arr[r, c])
            else:
                b = _pick(base, base_is_map, base_scalar, r, c) + base_shift * g * D * (t - t_ref)
            x, ok = _sample(float(v_arr[r, c]), b, t * g * a, v_sat)
            if ok:
                init_sum[r, c] += x
                init_cnt[r, c] += 1


@numba.njit(parallel=True, cache=True)
def merge_kernel(values, darks, has_darks, times, k, g, sigma2_R, v_sat, white,
                 base, base_is_map, base_scalar, t_ref, base_shift,
                 bias, bias_is_map, bias_scalar,
                 D_map, D_is_map, D_scalar, a_map, a_is_map,
                 init_sum, init_cnt, use_init,
                 max_iter, tol, sat_sigmas, probabilistic,
                 out_irr, out_sig, out_nexp, out_iter):
    """The ML merge of every photosite (Eq. 6, 8-13, Fig. 3); results into ``out_*``.

    Per photosite: x_i (Eq. 6); start from the non-saturated average (Eq. 11 usable set);
    iterate w_i = 1/Var(x_i) at max(mu, 0) (Eq. 13) and mu = sum w x / sum w, sigma^2 =
    1/sum w (Eq. 12) until |change| <= tol * max(|mu|, sigma) or ``max_iter`` steps. From the
    second step on, a sample whose raw value predicted from the current estimate lies within
    ``sat_sigmas`` of its own standard deviation of ``v_sat`` is dropped for good (saturated
    samples that slip under v_sat on read noise). With ``probabilistic``, Newton steps on the
    blended likelihood of Eq. 8-10 follow (damped to one sigma), started from that estimate. Photosites with no
    usable sample get ``nexp = 0``, ``sigma = 0`` and a lower bound of the irradiance.
    """
    n = len(values)
    H, W = values[0].shape
    tmin = times[0]
    for i in range(n):
        tmin = min(tmin, times[i])
    sat2 = sat_sigmas * sat_sigmas
    sigma_R = math.sqrt(sigma2_R)
    for r in prange(H):
        X = np.empty((n, W))
        V = np.empty((n, W))
        OK = np.empty((n, W), dtype=np.uint8)
        for i in range(n):
            vi = values[i]
            di = darks[i if has_darks else 0]
            t = times[i]
            for c in range(W):
                a = _pick(a_map, a_is_map, 1.0, r, c)
                D = _pick(D_map, D_is_map, D_scalar, r, c)
                if has_darks:
                    b = float(di[r, c])
                else:
                    b = _pick(base, base_is_map, base_scalar, r, c) + base_shift * g * D * (t - t_ref)
                v = float(vi[r, c])
                x, ok = _sample(v, b, t * g * a, v_sat)
                X[i, c] = x
                V[i, c] = v
                OK[i, c] = 1 if ok else 0
        for c in range(W):
            a = _pick(a_map, a_is_map, 1.0, r, c)
            D = _pick(D_map, D_is_map, D_scalar, r, c)
            bl = _pick(bias, bias_is_map, bias_scalar, r, c)
            if use_init:
                s = init_sum[r, c]
                cnt = init_cnt[r, c]
            else:
                s = 0.0
                cnt = 0
                for i in range(n):
                    if OK[i, c]:
                        s += X[i, c]
                        cnt += 1
            # Lower bound for a photosite saturated in every exposure (shortest exposure at v_sat).
            lb = ((v_sat - bl) / (g * tmin) - D) / a
            if cnt == 0:
                out_irr[r, c] = _clamp32(lb)
                out_sig[r, c] = 0.0
                out_nexp[r, c] = 0.0
                out_iter[r, c] = 0
                continue
            mu = s / cnt
            sig = 0.0
            nu = 0
            iters = 0
            flagged = False
            for it in range(max_iter):
                m = mu if mu > 0.0 else 0.0
                sw = 0.0
                swx = 0.0
                nu = 0
                for i in range(n):
                    if OK[i, c] == 0:
                        continue
                    t = times[i]
                    if it > 0 and sat_sigmas > 0.0:
                        tga = t * g * a
                        varv = _vcore(m, t, g, sigma2_R, D, a, 0.0) * tga * tga
                        gap = v_sat - (bl + g * t * D + tga * m)
                        if gap <= 0.0 or gap * gap <= sat2 * varv:
                            OK[i, c] = 0  # sticky: the usable set only shrinks
                            continue
                    w = 1.0 / _vcore(m, t, g, sigma2_R, D, a, k)
                    sw += w
                    swx += w * X[i, c]
                    nu += 1
                iters = it + 1
                if nu == 0:
                    flagged = True
                    break
                new = swx / sw
                sig = math.sqrt(1.0 / sw)
                delta = abs(new - mu)
                mu = new
                if it > 0 and delta <= tol * max(abs(new), sig):
                    break
            if probabilistic and not flagged:
                # Eq. 8-10: blend of the unclipped Gaussian and a uniform density by
                # P_nsat(v); Newton steps on the log-likelihood (EM step where not concave).
                for it2 in range(max_iter):
                    m = mu if mu > 0.0 else 0.0
                    L1 = 0.0
                    L2 = 0.0
                    swr = 0.0
                    nr = 0
                    for i in range(n):
                        v = V[i, c]
                        x = X[i, c]
                        if not (v < white) or not math.isfinite(x):
                            continue
                        p = 0.5 * math.erfc((v - v_sat) / (_SQRT2 * sigma_R))
                        if p <= 0.0:
                            continue
                        t = times[i]
                        tga = t * g * a
                        w = 1.0 / _vcore(m, t, g, sigma2_R, D, a, k)
                        d = x - mu
                        num = p * math.sqrt(w) * _INV_SQRT_2PI * math.exp(-0.5 * w * d * d)
                        den = (1.0 - p) * tga / max(white - bl, 1.0) + num
                        rr = num / den if den > 0.0 else 0.0
                        L1 += rr * w * d
                        L2 += w * (rr * (1.0 - rr) * w * d * d - rr)
                        swr += rr * w
                        if rr > 0.5:
                            nr += 1
                    iters += 1
                    if swr <= 0.0 or nr == 0:
                        flagged = True
                        break
                    sig = math.sqrt(1.0 / swr)
                    # Newton step, damped to one standard deviation (the blended likelihood
                    # has flat stretches where the bare Newton step overshoots).
                    step = -L1 / L2 if L2 < 0.0 else L1 / swr
                    step = min(max(step, -sig), sig)
                    mu += step
                    nu = nr
                    if abs(step) <= tol * max(abs(mu), sig):
                        break
            if flagged:
                est = mu if mu < lb else lb
                out_irr[r, c] = _clamp32(est)
                out_sig[r, c] = 0.0
                out_nexp[r, c] = 0.0
            else:
                out_irr[r, c] = _clamp32(mu)
                out_sig[r, c] = _clamp32(sig)
                out_nexp[r, c] = nu
            out_iter[r, c] = min(iters, 255)
