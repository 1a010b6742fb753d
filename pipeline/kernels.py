"""Compiled per-photosite kernels of the optimal merge (numba, parallel over rows).

The whole estimator of :mod:`pipeline.merge` runs here: one pass over the input frames, no
full-size per-frame temporaries (only buffers of one row per frame and thread), float64
arithmetic, float32 outputs. The variance is :func:`pipeline.noise.difference_variance`,
compiled as is (the formula is written only there).

The work on a row is split into small loops over the columns (load one frame's samples, add one
frame's weighted samples, update the estimates), each a separate compiled function over plain
1-D arrays without branches, so that LLVM vectorises them (SIMD over photosites).

Conventions shared by the kernels
---------------------------------
``values``/``darks``
    lists of 2-D arrays (DN), ``darks`` aligned with ``values`` (a 1x1 placeholder where a
    frame has no dark frame of its own).
per-frame arrays
    ``kinds[i]``: 0 the dark level is ``darks[i]`` (matched dark frame or a per-exposure master
    dark); 1 it is ``base + coefs[i] * D`` from the bias map ``bias`` (model strategy,
    ``coefs[i] = g t_i``); 2 it is ``master + coefs[i] * D`` (one master dark taken at t_ref,
    ``coefs[i] = g (t_i - t_ref)`` or 0). ``ks[i]``: the dark-level variance factor k of
    :func:`pipeline.noise.dark_factor` (1 matched, 1/N master, 0 model).
maps
    ``(array, is_map, scalar)``: a float32 map of the image's shape when ``is_map``, else the
    float64 ``scalar`` (PRNU gain a, dark current D in e-/s, bias in DN).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from .noise import difference_variance

__all__ = ["merge_kernel", "first_pass_kernel", "FLOAT32_MAX"]

FLOAT32_MAX = float(np.finfo(np.float32).max)

_FM = {"contract", "arcp", "nsz"}
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


# ------------------------------------------------------------------------ row loops (SIMD)
@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _fill_row(out, arr, is_map, scalar, r):
    if is_map:
        src = arr[r]
        for c in range(out.shape[0]):
            out[c] = src[c]
    else:
        for c in range(out.shape[0]):
            out[c] = scalar


@numba.njit(inline="always", cache=True)
def _keep(sample, xrow, okrow, S, CNT, c):
    """Store a sample (x, usable) of :func:`_sample` (0 where not usable) and add it to the
    sums of the starting average."""
    x, ok = sample
    xv = x if ok else 0.0
    okv = 1.0 if ok else 0.0
    xrow[c] = xv
    okrow[c] = okv
    S[c] += xv
    CNT[c] += okv


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _load_dark(vrow, drow, xrow, okrow, S, CNT, inv_tg, IA, v_sat, c0, c1):
    """One frame's samples x_i and usable flags (Eq. 6, 11), dark level from a dark frame row;
    adds the usable x_i to the sums S, CNT of the starting average."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        _keep(_sample(float(vrow[c]), float(drow[c]), inv_tg, IA[c], v_sat), xrow, okrow, S, CNT, c)


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _load_base(vrow, BASE, DD, coef, xrow, okrow, S, CNT, inv_tg, IA, v_sat, c0, c1):
    """As :func:`_load_dark` with the dark level BASE + coef * D (bias or master dark plus
    dark current)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        _keep(_sample(float(vrow[c]), BASE[c] + coef * DD[c], inv_tg, IA[c], v_sat), xrow, okrow, S, CNT, c)


@numba.njit(inline="always", cache=True)
def _weigh(x, okv, a, D, bl, m, t, g, sigma2_R, k, v_sat, sat2, rule):
    """One sample's (usable flag, weight w_i, w_i x_i) at the current estimate m = max(mu, 0).

    w_i = 1/Var(x_i) = (t g a)^2 / Var(v_i - b_i) (Eq. 6, 13). With ``rule`` (the
    near-saturation rule), a sample whose raw value predicted from m lies within sqrt(sat2) of
    its own standard deviation of v_sat is dropped (saturated samples that slip under v_sat on
    read noise)."""
    tga = t * g * a
    varv = _dvar(m, t, g, sigma2_R, D, a, 0.0)  # Var(v_i), DN^2
    gap = v_sat - (bl + g * t * D + tga * m)
    near = rule & ((gap <= 0.0) | (gap * gap <= sat2 * varv))
    ok = 0.0 if near else okv
    w = ok * ((tga * tga) / _dvar(m, t, g, sigma2_R, D, a, k))
    return ok, w, w * x


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _accumulate(xrow, okrow, t, k, A, DD, BL, M, SW, SWX, NU, g, sigma2_R, v_sat, sat2, rule, c0, c1):
    """Add one frame's weighted samples (:func:`_weigh`) to the sums of Eq. 12; samples dropped
    by the near-saturation rule are dropped for good (``okrow``)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        ok, w, wx = _weigh(xrow[c], okrow[c], A[c], DD[c], BL[c], M[c], t, g, sigma2_R, k, v_sat, sat2, rule)
        okrow[c] = ok
        SW[c] += w
        SWX[c] += wx
        NU[c] += ok


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _accumulate3(x1, o1, t1, k1, x2, o2, t2, k2, x3, o3, t3, k3, A, DD, BL, M, SW, SWX, NU, g, sigma2_R,
                 v_sat, sat2, rule, c0, c1):
    """:func:`_accumulate` for three frames in one pass (the per-photosite maps and sums are
    read and written once for three samples)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        a = A[c]
        D = DD[c]
        bl = BL[c]
        m = M[c]
        ok1, w1, wx1 = _weigh(x1[c], o1[c], a, D, bl, m, t1, g, sigma2_R, k1, v_sat, sat2, rule)
        ok2, w2, wx2 = _weigh(x2[c], o2[c], a, D, bl, m, t2, g, sigma2_R, k2, v_sat, sat2, rule)
        ok3, w3, wx3 = _weigh(x3[c], o3[c], a, D, bl, m, t3, g, sigma2_R, k3, v_sat, sat2, rule)
        o1[c] = ok1
        o2[c] = ok2
        o3[c] = ok3
        SW[c] += (w1 + w2) + w3
        SWX[c] += (wx1 + wx2) + wx3
        NU[c] += (ok1 + ok2) + ok3


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_start(S, CNT, MU, DONE, FLAG, LB, BL, DD, IA, v_sat, inv_gtmin, c0, c1):
    """The starting estimate: the non-saturated average (Eq. 11 usable set); photosites with no
    usable sample get the lower bound of the shortest exposure at v_sat and are done."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        LB[c] = ((v_sat - BL[c]) * inv_gtmin - DD[c]) * IA[c]
        empty = CNT[c] == 0.0
        MU[c] = LB[c] if empty else S[c] / max(CNT[c], 1.0)
        DONE[c] = 1.0 if empty else 0.0
        FLAG[c] = 1.0 if empty else 0.0


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_update(MU, SIG, SW, SWX, NU, DONE, FLAG, ITER, it, tol2, c0, c1):
    """Eq. 12 for the photosites not yet converged: mu = sum w x / sum w, sigma^2 = 1/sum w;
    converged when the change is within tol * max(|mu|, sigma) (Fig. 3). Returns the number of
    photosites still iterating."""
    active = 0
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        live = DONE[c] == 0.0
        none = NU[c] == 0.0
        var = 1.0 / (SW[c] if SW[c] > 0.0 else 1.0)
        new = SWX[c] * var
        delta = new - MU[c]
        conv = (it > 0) & (delta * delta <= tol2 * max(new * new, var))
        upd = live & (not none)
        ITER[c] = it + 1.0 if live else ITER[c]
        FLAG[c] = 1.0 if (live & none) else FLAG[c]
        MU[c] = new if upd else MU[c]
        SIG[c] = var if upd else SIG[c]  # variance here; square root taken at the end
        fin = live & (none | conv)
        DONE[c] = 1.0 if fin else DONE[c]
        active += 1 if (live & (not fin)) else 0
    return active


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_output(r, MU, SIG, NU, ITER, FLAG, LB, out_irr, out_sig, out_nexp, out_iter, c0, c1):
    """Results of the threshold model: flagged photosites (no usable sample) get nexp = 0,
    sigma = 0 and the lower bound; everything clamped to finite float32."""
    oi = out_irr[r]
    os_ = out_sig[r]
    on = out_nexp[r]
    ot = out_iter[r]
    big = FLOAT32_MAX
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        flagged = FLAG[c] != 0.0
        mu = MU[c]
        mu = 0.0 if mu != mu else mu
        est = min(mu, LB[c]) if flagged else mu
        oi[c] = min(max(est, -big), big)
        s = math.sqrt(SIG[c])
        s = 0.0 if s != s else s
        os_[c] = 0.0 if flagged else min(s, big)
        on[c] = 0.0 if flagged else NU[c]
        ot[c] = min(ITER[c], 255.0)


@numba.njit(cache=True, error_model="numpy")
def _probabilistic(values, darks, kinds, coefs, ks, times, g, sigma2_R, v_sat, white, r, c, mu, sig, a, D,
                   bl, base_c, master_c, max_iter, tol):
    """Eq. 8-10: blend of the unclipped Gaussian and a uniform density by P_nsat; Newton
    steps on the log-likelihood (EM step where not concave), damped to one sigma, from ``mu``.
    Samples at or above v_sat are saturated (Eq. 11); below, P_nsat is the probability that the
    observed value is not saturated given the current estimate (see the comment in the loop).
    Returns (mu, sigma, n used, steps, flagged)."""
    sigma_R = math.sqrt(sigma2_R)
    full_well = white - v_sat > 3.0 * sigma_R
    v_clip = v_sat + 3.0 * sigma_R
    nu = 0.0
    steps = 0
    for _ in range(max_iter):
        m = mu if mu > 0.0 else 0.0
        L1 = 0.0
        L2 = 0.0
        swr = 0.0
        nr = 0
        for i in range(len(values)):
            v = float(values[i][r, c])
            if not (v < v_sat):  # Eq. 11: values at or above the limit are saturated
                continue
            t = times[i]
            tga = t * g * a
            kind = kinds[i]
            if kind == 0:
                b = float(darks[i][r, c])
            elif kind == 1:
                b = base_c + coefs[i] * D
            else:
                b = master_c + coefs[i] * D
            x = (v - b) / tga
            if not math.isfinite(x):
                continue
            # P_nsat (Eq. 8), the probability that the observed v < v_sat is not saturated,
            # given the current estimate. Where the ADC clips (v_sat at the white level) a
            # saturated value never lies below v_sat: P_nsat = 1. Where the full well clips
            # first, saturated values scatter around v_clip = v_sat + 3 sigma_R (Sec. 6: v_sat
            # is the saturation level minus three sigma) and may slip under v_sat: P_nsat is
            # the posterior of "unclipped" (prior: the value predicted from the estimate stays
            # below v_clip; likelihoods: Gaussians around E(v) and around v_clip).
            p = 1.0
            if full_well:
                ev = bl + g * t * D + tga * m  # E(v_i) without clipping, DN
                sv = math.sqrt(_dvar(m, t, g, sigma2_R, D, a, 0.0))
                pu = 1.0 - 0.5 * math.erfc((v_clip - ev) / (_SQRT2 * sv))
                zu = (v - ev) / sv
                zc = (v - v_clip) / sigma_R
                la = math.log(max(pu, 1e-300)) - 0.5 * zu * zu - math.log(sv)
                lb = math.log(max(1.0 - pu, 1e-300)) - 0.5 * zc * zc - math.log(sigma_R)
                p = 1.0 / (1.0 + math.exp(min(lb - la, 700.0)))
            if p <= 0.0:
                continue
            w = (tga * tga) / _dvar(m, t, g, sigma2_R, D, a, ks[i])
            d = x - mu
            num = p * math.sqrt(w) * _INV_SQRT_2PI * math.exp(-0.5 * w * d * d)
            den = (1.0 - p) * tga / max(white - bl, 1.0) + num
            rr = num / den if den > 0.0 else 0.0
            L1 += rr * w * d
            L2 += w * (rr * (1.0 - rr) * w * d * d - rr)
            swr += rr * w
            if rr > 0.5:
                nr += 1
        steps += 1
        if swr <= 0.0 or nr == 0:
            return mu, sig, nu, steps, True
        sig = math.sqrt(1.0 / swr)
        # Newton step, damped to one standard deviation (the blended likelihood has flat
        # stretches where the bare Newton step overshoots).
        step = -L1 / L2 if L2 < 0.0 else L1 / swr
        step = min(max(step, -sig), sig)
        mu += step
        nu = float(nr)
        if abs(step) <= tol * max(abs(mu), sig):
            break
    return mu, sig, nu, steps, False


# ------------------------------------------------------------------------------- kernels
@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FM)
def first_pass_kernel(v_arr, d_arr, kind, base, base_is_map, base_scalar, coef, t, g, v_sat,
                      D_map, D_is_map, D_scalar, a_map, a_is_map, init_sum, init_cnt):
    """Streaming first pass: add one frame's usable x_i to the non-saturated average.

    Computes x_i exactly as :func:`merge_kernel` does, so that a merge started from these
    sums equals the batch merge bit for bit when the frames come in the same order. ``kind``
    0: dark level ``d_arr``; otherwise ``base + coef * D`` (bias or master dark map/scalar).
    """
    H, W = v_arr.shape
    inv_tg = 1.0 / (t * g)
    for r in prange(H):
        for c in range(W):
            a = _pick(a_map, a_is_map, 1.0, r, c)
            if kind == 0:
                b = float(d_arr[r, c])
            else:
                b = _pick(base, base_is_map, base_scalar, r, c) + coef * _pick(D_map, D_is_map, D_scalar, r, c)
            x, ok = _sample(float(v_arr[r, c]), b, inv_tg, 1.0 / a, v_sat)
            if ok:
                init_sum[r, c] += x
                init_cnt[r, c] += 1


@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FM)
def merge_kernel(values, darks, kinds, coefs, ks, times, g, sigma2_R, v_sat, white,
                 master, has_master, bias, bias_is_map, bias_scalar,
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
    blended likelihood of Eq. 8-10 follow (damped to one sigma), started from that estimate.
    Photosites with no usable sample get ``nexp = 0``, ``sigma = 0`` and a lower bound of the
    irradiance.
    """
    n = len(values)
    H, W = values[0].shape
    tmin = times[0]
    for i in range(n):
        tmin = min(tmin, times[i])
    sat2 = sat_sigmas * sat_sigmas
    tol2 = tol * tol
    inv_gtmin = 1.0 / (g * tmin)
    nchunk = min(H, max(1, n_chunks))
    block = 1024
    for ch in prange(nchunk):
        # Row buffers, allocated once per chunk of rows (not per row).
        X = np.empty((n, W))
        OK = np.empty((n, W))  # 1.0 usable, 0.0 not (float: branch-free, vectorisable loops)
        A = np.empty(W)
        IA = np.empty(W)
        DD = np.empty(W)
        BL = np.empty(W)
        MB = np.empty(W)
        MU = np.empty(W)
        M = np.empty(W)
        SIG = np.empty(W)
        NU = np.empty(W)
        SW = np.empty(W)
        SWX = np.empty(W)
        ITER = np.empty(W)
        DONE = np.empty(W)
        FLAG = np.empty(W)
        LB = np.empty(W)
        S = np.empty(W)
        CNT = np.empty(W)
        for r in range(ch * H // nchunk, (ch + 1) * H // nchunk):
            _fill_row(A, a_map, a_is_map, 1.0, r)
            _fill_row(DD, D_map, D_is_map, D_scalar, r)
            _fill_row(BL, bias, bias_is_map, bias_scalar, r)
            if has_master:
                _fill_row(MB, master, True, 0.0, r)
            for c in range(W):
                IA[c] = 1.0 / A[c]
                SIG[c] = 0.0
                NU[c] = 0.0
                ITER[c] = 0.0
            # Blocks of columns small enough for all their buffers to stay in the L1 cache
            # through the loads and all the iterations.
            for c0 in range(0, W, block):
                c1 = min(W, c0 + block)
                for c in range(numba.uint64(c0), numba.uint64(c1)):
                    S[c] = 0.0
                    CNT[c] = 0.0
                for i in range(n):  # x_i, usable flags and the sums of the non-saturated average
                    inv_tg = 1.0 / (times[i] * g)
                    kind = kinds[i]
                    if kind == 0:
                        _load_dark(values[i][r], darks[i][r], X[i], OK[i], S, CNT, inv_tg, IA, v_sat, c0, c1)
                    elif kind == 1:
                        _load_base(values[i][r], BL, DD, coefs[i], X[i], OK[i], S, CNT, inv_tg, IA, v_sat, c0, c1)
                    else:
                        _load_base(values[i][r], MB, DD, coefs[i], X[i], OK[i], S, CNT, inv_tg, IA, v_sat, c0, c1)
                if use_init:  # the first pass of the streaming merge summed the same values in the same order
                    for c in range(numba.uint64(c0), numba.uint64(c1)):
                        S[c] = init_sum[r, c]
                        CNT[c] = init_cnt[r, c]
                _row_start(S, CNT, MU, DONE, FLAG, LB, BL, DD, IA, v_sat, inv_gtmin, c0, c1)
                # Iterate Eq. 13 <-> Eq. 12 for the whole block at once, frames three at a time.
                for it in range(max_iter):
                    for c in range(numba.uint64(c0), numba.uint64(c1)):
                        M[c] = MU[c] if MU[c] > 0.0 else 0.0
                        SW[c] = 0.0
                        SWX[c] = 0.0
                        NU[c] = 0.0
                    rule = it > 0 and sat_sigmas > 0.0
                    i = 0
                    while i + 3 <= n:
                        _accumulate3(X[i], OK[i], times[i], ks[i], X[i + 1], OK[i + 1], times[i + 1], ks[i + 1],
                                     X[i + 2], OK[i + 2], times[i + 2], ks[i + 2], A, DD, BL, M, SW, SWX, NU,
                                     g, sigma2_R, v_sat, sat2, rule, c0, c1)
                        i += 3
                    while i < n:
                        _accumulate(X[i], OK[i], times[i], ks[i], A, DD, BL, M, SW, SWX, NU, g, sigma2_R, v_sat,
                                    sat2, rule, c0, c1)
                        i += 1
                    if _row_update(MU, SIG, SW, SWX, NU, DONE, FLAG, ITER, it, tol2, c0, c1) == 0:
                        break
                if probabilistic:
                    for c in range(numba.uint64(c0), numba.uint64(c1)):
                        if FLAG[c] != 0.0:
                            continue
                        mu, sg, nu, steps, flagged = _probabilistic(
                            values, darks, kinds, coefs, ks, times, g, sigma2_R, v_sat, white, r, c, MU[c],
                            math.sqrt(SIG[c]), A[c], DD[c], BL[c], BL[c], MB[c], max_iter, tol)
                        MU[c] = mu
                        SIG[c] = sg * sg
                        ITER[c] += steps
                        if flagged:
                            FLAG[c] = 1.0
                        else:
                            NU[c] = nu
                _row_output(r, MU, SIG, NU, ITER, FLAG, LB, out_irr, out_sig, out_nexp, out_iter, c0, c1)
