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

from .noise import difference_variance

__all__ = ["merge_kernel", "first_pass_kernel", "FLOAT32_MAX"]

FLOAT32_MAX = float(np.finfo(np.float32).max)

_dvar = numba.njit(inline="always", cache=True)(difference_variance)

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@numba.njit(inline="always", cache=True)
def _pick(arr, is_map, scalar, r, c):
    if is_map:
        return float(arr[r, c])
    return scalar


@numba.njit(inline="always", cache=True)
def _sample(v, b, inv_tg, inv_a, v_sat):
    """x_i = (v - b) / (t g a) of Eq. 6 (from the reciprocals 1/(t g), 1/a: no division per
    sample) and whether the sample is usable under Eq. 11 (observed value)."""
    x = (v - b) * inv_tg * inv_a
    ok = (v < v_sat) & (b < v_sat) & ((x - x) == 0.0)  # branch-free; x - x != 0 for inf/nan
    return x, ok


@numba.njit(inline="always", cache=True)
def _clamp32(x):
    if not math.isfinite(x):
        return 0.0 if math.isnan(x) else (FLOAT32_MAX if x > 0 else -FLOAT32_MAX)
    return min(max(x, -FLOAT32_MAX), FLOAT32_MAX)


@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract", "arcp", "nsz"})
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
            x, ok = _sample(float(v_arr[r, c]), b, 1.0 / (t * g), 1.0 / a, v_sat)
            if ok:
                init_sum[r, c] += x
                init_cnt[r, c] += 1

@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract", "arcp", "nsz"})
def merge_kernel(values, darks, has_darks, times, k, g, sigma2_R, v_sat, white,
                 base, base_is_map, base_scalar, t_ref, base_shift,
                 bias, bias_is_map, bias_scalar,
                 D_map, D_is_map, D_scalar, a_map, a_is_map,
                 init_sum, init_cnt, use_init,
                 max_iter, tol, sat_sigmas, probabilistic,
                 out_irr, out_sig, out_nexp, out_iter, n_chunks):
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
    tol2 = tol * tol
    inv_gtmin = 1.0 / (g * tmin)
    sigma_R = math.sqrt(sigma2_R)
    nchunk = min(H, max(1, n_chunks))
    for ch in prange(nchunk):
        # Row buffers, allocated once per chunk of rows (not per row).
        X = np.empty((n, W))
        OK = np.empty((n, W))  # 1.0 usable, 0.0 not (float: branch-free, vectorisable loops)
        A = np.empty(W)
        DD = np.empty(W)
        BL = np.empty(W)
        BASE = np.empty(W)
        MU = np.empty(W)
        M = np.empty(W)
        IA = np.empty(W)
        SIG = np.zeros(W)
        NU = np.zeros(W)
        SW = np.empty(W)
        SWX = np.empty(W)
        ITER = np.zeros(W, dtype=np.int64)
        DONE = np.zeros(W, dtype=np.uint8)
        FLAG = np.zeros(W, dtype=np.uint8)
        LB = np.empty(W)
        S = np.empty(W)
        CNT = np.empty(W)
        for r in range(ch * H // nchunk, (ch + 1) * H // nchunk):
            for c in range(W):
                SIG[c] = 0.0
                NU[c] = 0.0
                ITER[c] = 0
                DONE[c] = 0
                FLAG[c] = 0
            for c in range(W):
                A[c] = _pick(a_map, a_is_map, 1.0, r, c)
                DD[c] = _pick(D_map, D_is_map, D_scalar, r, c)
                BL[c] = _pick(bias, bias_is_map, bias_scalar, r, c)
                BASE[c] = _pick(base, base_is_map, base_scalar, r, c)
                IA[c] = 1.0 / A[c]
            for i in range(n):
                vrow = values[i][r]
                t = times[i]
                inv_tg = 1.0 / (t * g)
                xrow = X[i]
                okrow = OK[i]
                if has_darks:
                    drow = darks[i][r]
                    for c in range(W):
                        x, ok = _sample(float(vrow[c]), float(drow[c]), inv_tg, IA[c], v_sat)
                        xrow[c] = x if ok else 0.0
                        okrow[c] = 1.0 if ok else 0.0
                else:
                    for c in range(W):
                        b = BASE[c] + base_shift * g * DD[c] * (t - t_ref)
                        x, ok = _sample(float(vrow[c]), b, inv_tg, IA[c], v_sat)
                        xrow[c] = x if ok else 0.0
                        okrow[c] = 1.0 if ok else 0.0
            # Start: the non-saturated average (Eq. 11 usable set), same order as the first pass.
            if use_init:
                for c in range(W):
                    S[c] = init_sum[r, c]
                    CNT[c] = init_cnt[r, c]
            else:
                for c in range(W):
                    S[c] = 0.0
                    CNT[c] = 0.0
                for i in range(n):  # X is 0 where not usable: the same sums as the first pass
                    xrow = X[i]
                    okrow = OK[i]
                    for c in range(W):
                        S[c] += xrow[c]
                        CNT[c] += okrow[c]
            for c in range(W):
                # Lower bound for a photosite saturated in every exposure (shortest exposure at v_sat).
                LB[c] = ((v_sat - BL[c]) * inv_gtmin - DD[c]) * IA[c]
                empty = CNT[c] == 0.0
                MU[c] = LB[c] if empty else S[c] / max(CNT[c], 1.0)
                DONE[c] = 1 if empty else 0
                FLAG[c] = 1 if empty else 0
            # Iterate Eq. 13 <-> Eq. 12 for the whole row at once (vectorisable inner loops).
            for it in range(max_iter):
                for c in range(W):
                    M[c] = MU[c] if MU[c] > 0.0 else 0.0
                    SW[c] = 0.0
                    SWX[c] = 0.0
                    NU[c] = 0.0
                rule = it > 0 and sat_sigmas > 0.0
                for i in range(n):
                    t = times[i]
                    okrow = OK[i]
                    xrow = X[i]
                    for c in range(W):
                        tga = t * g * A[c]
                        ok = okrow[c]
                        if rule:
                            # Near-saturation rule: drop (for good) a sample whose raw value
                            # predicted from the current estimate is within sat_sigmas of its
                            # own sigma of v_sat.
                            varv = _dvar(M[c], t, g, sigma2_R, DD[c], A[c], 0.0)  # Var(v_i), DN^2
                            gap = v_sat - (BL[c] + g * t * DD[c] + tga * M[c])
                            near = (gap <= 0.0) | (gap * gap <= sat2 * varv)
                            ok = 0.0 if near else ok
                            okrow[c] = ok
                        # w_i = 1 / Var(x_i) = (t g a)^2 / Var(v_i - b_i)  (Eq. 6, 13)
                        w = ok * ((tga * tga) / _dvar(M[c], t, g, sigma2_R, DD[c], A[c], k))
                        SW[c] += w
                        SWX[c] += w * xrow[c]
                        NU[c] += ok
                all_done = True
                for c in range(W):
                    if DONE[c]:
                        continue
                    ITER[c] = it + 1
                    if NU[c] == 0.0:
                        FLAG[c] = 1
                        DONE[c] = 1
                        continue
                    var = 1.0 / SW[c]  # Eq. 12: sigma^2 = 1 / sum w
                    new = SWX[c] * var
                    delta = new - MU[c]
                    MU[c] = new
                    SIG[c] = var  # variance here; square root taken once at the end
                    if it > 0 and delta * delta <= tol2 * max(new * new, var):
                        DONE[c] = 1
                    else:
                        all_done = False
                if all_done:
                    break
            for c in range(W):
                mu = MU[c]
                sig = math.sqrt(SIG[c])
                nu = NU[c]
                iters = ITER[c]
                flagged = FLAG[c] != 0
                a = A[c]
                D = DD[c]
                bl = BL[c]
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
                            v = float(values[i][r, c])
                            if not (v < white):
                                continue
                            t = times[i]
                            tga = t * g * a
                            if has_darks:
                                b = float(darks[i][r, c])
                            else:
                                b = BASE[c] + base_shift * g * D * (t - t_ref)
                            x = (v - b) / tga
                            if not math.isfinite(x):
                                continue
                            p = 0.5 * math.erfc((v - v_sat) / (_SQRT2 * sigma_R))
                            if p <= 0.0:
                                continue
                            w = (tga * tga) / _dvar(m, t, g, sigma2_R, D, a, k)
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
                    lb = LB[c]
                    est = mu if mu < lb else lb
                    out_irr[r, c] = _clamp32(est)
                    out_sig[r, c] = 0.0
                    out_nexp[r, c] = 0.0
                else:
                    out_irr[r, c] = _clamp32(mu)
                    out_sig[r, c] = _clamp32(sig)
                    out_nexp[r, c] = nu
                out_iter[r, c] = min(iters, 255)
