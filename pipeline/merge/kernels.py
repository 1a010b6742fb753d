"""Compiled per-photosite kernels of the optimal merge (numba, parallel over rows).

The whole estimator of :mod:`pipeline.merge.accumulator` runs here: one pass over the input frames, no
full-size per-frame temporaries (only buffers of one row per frame and thread), float32
outputs. The variance is :func:`pipeline.noise.variance_of_rate`, the one place the formula is
written, compiled into the kernels (numba inlines it: :func:`_weigh` calls it with per-frame
constants, :func:`_tobit_terms` at each sample).

The work on a row is split into small loops over blocks of columns (load one frame's samples,
weigh three frames' samples, update the estimates), each a separate compiled function over
plain 1-D arrays without branches, so that LLVM vectorises them (SIMD over photosites).

Precision: the samples x_i, the starting average and the estimates are float64. The weights
and their sums use the precision of the caller's ``proto`` array: float32 (twice the SIMD
width, a quarter of the cost of a division) where :func:`pipeline.merge.precision.single_precision_safe`
proves every such quantity stays well inside the float32 range, else
float64. Three samples share one division (w_i = n_i/d_i from 1/(d1 d2 d3)) where the block's
variances allow it.

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
    :class:`MapArg` ``(array, is_map, scalar)``: a float32 map of the image's shape when
    ``is_map``, else the float64 ``scalar`` (PRNU gain a, dark current D in e-/s, bias in DN).

The kernels take their inputs grouped into the named tuples below (numba compiles named tuples
of arrays and scalars in nopython mode); they are unpacked once at the top of each kernel.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
from numba import prange

from hdrcap.pipeline._numba_target import numba  # numba, its compile target set (512-bit vectors on AVX-512)
from hdrcap.pipeline.noise import variance_of_rate

__all__ = [
    "merge_kernel",
    "calibration_terms_kernel",
    "ErrorMaps",
    "SharedTerms",
    "first_pass_kernel",
    "FLOAT32_MAX",
    "MapArg",
    "FrameTable",
    "CameraConstants",
    "MapSet",
    "StartSums",
    "IterationOptions",
    "MergeOutputs",
    "STATS_COLUMNS",
    "RULE_CLIP",
    "RULE_FALLBACK",
    "CLIP_WINDOW",
    "reflected_lists_quiet",
]

FLOAT32_MAX = float(np.finfo(np.float32).max)

_FM = {"contract", "arcp", "nsz"}
_var = numba.njit(inline="always", cache=True)(variance_of_rate)  # Var(v_i - b_i), DN^2 (Eq. 3, 5)


@contextlib.contextmanager
def reflected_lists_quiet() -> Iterator[None]:
    """Silence numba's pending deprecation of reflected lists around a kernel call: the kernels
    take plain lists of frames on purpose (``numba.typed.List`` would cost its compilation in
    every process).

    Yields
    ------
    None
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=numba.NumbaPendingDeprecationWarning)
        yield


class MapArg(NamedTuple):
    """A per-photosite quantity: a float32 ``array`` of the image's shape when ``is_map``, else
    ``scalar`` (float; the array is then a 1x1 placeholder)."""

    array: np.ndarray
    is_map: bool
    scalar: float


class FrameTable(NamedTuple):
    """Per-frame arrays, aligned with the frames: ``kinds`` (int64: 0 own dark frame, 1 bias
    plus dark current, 2 master dark plus dark current), ``coefs`` (float64, DN per e-/s: the
    factor of D in the dark level), ``ks`` (float64: dark-level variance factor k) and
    ``times`` (float64, s)."""

    kinds: np.ndarray
    coefs: np.ndarray
    ks: np.ndarray
    times: np.ndarray


class CameraConstants(NamedTuple):
    """The camera model's scalars: gain ``g`` (DN/e-), readout variance ``sigma2_R`` (DN^2),
    saturation limit ``v_sat`` (DN) and the ADC's ``white`` level (DN)."""

    g: float
    sigma2_R: float
    v_sat: float
    white: float


class MapSet(NamedTuple):
    """The maps of the merge, each a :class:`MapArg`: ``bias`` (DN), ``dark_current`` (e-/s),
    ``prnu`` (gain a, mean 1) and ``master`` (one master dark, DN; ``is_map`` False when
    there is none)."""

    bias: MapArg
    dark_current: MapArg
    prnu: MapArg
    master: MapArg


class StartSums(NamedTuple):
    """Sums of the starting average from the streaming first pass: ``total`` (float64, e-/s)
    and ``counts`` (int32) per photosite; used instead of the kernel's own when ``use``."""

    total: np.ndarray
    counts: np.ndarray  # not "count": that would hide tuple.count
    use: bool


class IterationOptions(NamedTuple):
    """``max_iter`` (int), relative ``tol``, ``sat_sigmas`` (the near-saturation margin in
    standard deviations of the raw value), ``probabilistic`` (Eq. 8-10), ``clip_sigmas`` (the
    clip rule's threshold k_c, 0: no clip rule; :func:`_clip_rule`) and ``censored_spacing`` (the
    widest spacing at which the censored likelihood's estimate stands, :func:`_tobit_trusted`;
    0: always) of the merge."""

    max_iter: int
    tol: float
    sat_sigmas: float
    probabilistic: bool
    clip_sigmas: float
    censored_spacing: float


class MergeOutputs(NamedTuple):
    """Output arrays of :func:`merge_kernel`: float32 ``irradiance`` and ``sigma`` (e-/s),
    float32 ``nexp``, uint8 ``iterations`` and uint8 ``rules`` (image shape: bit
    :data:`RULE_CLIP` where the clip rule rejected a sample, :data:`RULE_FALLBACK` where the
    censored likelihood fell back to the threshold estimate) and float64 ``stats`` (one row per
    chunk of rows: photosites with nexp = 0, sum and maximum of the iteration counts, photosites
    that lost a sample to the clip rule, samples it rejected, censored-likelihood fallbacks)."""

    irradiance: np.ndarray
    sigma: np.ndarray
    nexp: np.ndarray
    iterations: np.ndarray
    rules: np.ndarray
    stats: np.ndarray


#: Columns of :attr:`MergeOutputs.stats`.
STATS_COLUMNS = 6

#: Bits of :attr:`MergeOutputs.rules`.
RULE_CLIP = 1
RULE_FALLBACK = 2

#: The clip rule's window: a usable sample is possibly clipped when its raw value lies within
#: this many of its model standard deviation at v_sat, sqrt(g (v_sat - bias) + sigma_R^2), of
#: v_sat (:func:`_clip_rule`).
CLIP_WINDOW = 3.0


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


# ------------------------------------------------------------------------ row loops (SIMD)
@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _fill_row(out, arr, is_map, scalar, r):
    """A row buffer from a map's row (the padding beyond the image is left as it is) or a
    scalar (padding included)."""
    if is_map:
        src = arr[r]
        for c in range(src.shape[0]):
            out[c] = src[c]
    else:
        for c in range(out.shape[0]):
            out[c] = scalar


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _floor_row(out):
    """Clamp a row buffer at 0 in place: the dark current inside a variance (a negative
    estimate of it would let the variance of Eq. 3, 5 go negative at long exposures)."""
    for c in range(out.shape[0]):
        out[c] = max(out[c], 0.0)


@numba.njit(inline="always", cache=True)
def _keep(sample, xrow, S, CNT, c):
    """Store a sample (x, usable) of :func:`_sample` (NaN where not usable) and add it to the
    sums of the starting average."""
    x, ok = sample
    xrow[c] = x if ok else math.nan
    S[c] += x if ok else 0.0
    CNT[c] += 1.0 if ok else 0.0


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _load_dark(vrow, drow, xrow, S, CNT, inv_tg, IA, v_sat, c0, c1):
    """One frame's samples x_i (Eq. 6; NaN where not usable, Eq. 11), dark level from a dark
    frame row; adds the usable x_i to the sums S, CNT of the starting average."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        _keep(_sample(float(vrow[c]), float(drow[c]), inv_tg, IA[c], v_sat), xrow, S, CNT, c)


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _load_dark3(v1, d1, x1, inv1, v2, d2, x2, inv2, v3, d3, x3, inv3, S, CNT, IA, v_sat, c0, c1):
    """:func:`_load_dark` for three frames in one pass (the sums are added to in the frames'
    order, as three single passes would)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        ia = IA[c]
        _keep(_sample(float(v1[c]), float(d1[c]), inv1, ia, v_sat), x1, S, CNT, c)
        _keep(_sample(float(v2[c]), float(d2[c]), inv2, ia, v_sat), x2, S, CNT, c)
        _keep(_sample(float(v3[c]), float(d3[c]), inv3, ia, v_sat), x3, S, CNT, c)


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _load_base(vrow, BASE, DD, coef, xrow, S, CNT, inv_tg, IA, v_sat, c0, c1):
    """As :func:`_load_dark` with the dark level BASE + coef * D (bias or master dark plus
    dark current)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        _keep(_sample(float(vrow[c]), BASE[c] + coef * DD[c], inv_tg, IA[c], v_sat), xrow, S, CNT, c)


# Range of variances (DN^2) within which three samples share one division (their product
# stays far inside the range of the arithmetic: float64, float32); a block whose variances
# may leave it takes one division per sample (extreme gains, times or read noise).
_SHARED_RANGE64 = (1e-90, 1e90)
_SHARED_RANGE32 = (1e-12, 1e12)


# Constants written as float32 so that the helpers below keep the precision of their arrays
# (float32 constants in float64 arithmetic are exact; float64 ones would promote float32 code).
_NAN32 = np.float32(np.nan)
_ZERO32 = np.float32(0.0)
_ONE32 = np.float32(1.0)


@numba.njit(inline="always", cache=True)
def _weigh(x, u, vsb, a2, D, fr, s2, sat2, rule):
    """One sample's terms at the current estimate through u = a max(mu, 0) + D: (x kept, or
    NaN once dropped; numerator n_i; variance d_i), so that the weight
    w_i = n_i / d_i = (t g a)^2 / Var(v_i - b_i) = 1 / Var(x_i) (Eq. 6, 13; 0 when not usable).

    ``fr`` holds the frame's constants (t g, g^2 t, (t g)^2, k); the variance
    d_i = Var(v_i - b_i) and, for the rule, Var(v_i) are :func:`pipeline.noise.variance_of_rate`
    (with k and with 0).
    With ``rule`` (the near-saturation rule; a compile-time constant), a sample whose raw
    value predicted from the estimate lies within sqrt(sat2) of its own standard deviation of
    v_sat is dropped for good (saturated samples that slip under v_sat on read noise)."""
    tg, g2t, tg2, k = fr
    use = x == x
    if rule:
        varv = _var(u, g2t, D, s2, _ZERO32)  # Var(v_i), DN^2
        gap = vsb - tg * u  # v_sat - E(v_i), DN
        use = use & (gap > 0.0) & (gap * gap > sat2 * varv)
    d = _var(u, g2t, D, s2, k)
    return (x if use else _NAN32), (tg2 * a2 if use else _ZERO32), d


@numba.njit(inline="always", cache=True)
def _frame(FR, i):
    return FR[i, 0], FR[i, 1], FR[i, 2], FR[i, 3]


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _accumulate(x1, f1, U, VSB, A2, DD, SW, SWX, s2, sat2, rule, c0, c1):
    """Add one frame's weighted samples (:func:`_weigh`, one division each) to the sums of
    Eq. 12."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        y1, n1, d1 = _weigh(x1[c], U[c], VSB[c], A2[c], DD[c], f1, s2, sat2, rule)
        w1 = n1 / d1
        if rule:
            x1[c] = y1
        SW[c] += w1
        SWX[c] += w1 * y1 if n1 > _ZERO32 else _ZERO32


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _accumulate3(x1, f1, x2, f2, x3, f3, U, VSB, A2, DD, SW, SWX, s2, sat2, rule, c0, c1):
    """:func:`_accumulate` for three frames in one pass, with one division for the three
    weights: r = 1 / (d1 d2 d3), w3 = n3 d1 d2 r, w1 = n1 d2 (d3 r), w2 = n2 d1 (d3 r) (the
    caller checks that every d lies within _SHARED_RANGE64 or _SHARED_RANGE32)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        u = U[c]
        vsb = VSB[c]
        a2 = A2[c]
        D = DD[c]
        y1, n1, d1 = _weigh(x1[c], u, vsb, a2, D, f1, s2, sat2, rule)
        y2, n2, d2 = _weigh(x2[c], u, vsb, a2, D, f2, s2, sat2, rule)
        y3, n3, d3 = _weigh(x3[c], u, vsb, a2, D, f3, s2, sat2, rule)
        p = d1 * d2
        r = _ONE32 / (p * d3)
        e = d3 * r
        w1 = n1 * d2 * e
        w2 = n2 * d1 * e
        w3 = n3 * p * r
        if rule:
            x1[c] = y1
            x2[c] = y2
            x3[c] = y3
        SW[c] += (w1 + w2) + w3
        z = _ZERO32
        SWX[c] += ((w1 * y1 if n1 > z else z) + (w2 * y2 if n2 > z else z)) + (w3 * y3 if n3 > z else z)


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _iterate(X, FR, n, U, VSB, A2, DD, SW, SWX, s2, sat2, rule, shared, c0, c1):
    """One pass of Eq. 13 -> Eq. 12 sums (cleared by :func:`_estimate`) over all frames, three
    at a time with ``shared`` (one division for three samples)."""
    i = 0
    while shared and i + 3 <= n:
        _accumulate3(
            X[i],
            _frame(FR, i),
            X[i + 1],
            _frame(FR, i + 1),
            X[i + 2],
            _frame(FR, i + 2),
            U,
            VSB,
            A2,
            DD,
            SW,
            SWX,
            s2,
            sat2,
            rule,
            c0,
            c1,
        )
        i += 3
    while i < n:
        _accumulate(X[i], _frame(FR, i), U, VSB, A2, DD, SW, SWX, s2, sat2, rule, c0, c1)
        i += 1


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_start(S, CNT, MU, DONE, FLAG, LB, BL, DD, IA, A, U, SW, SWX, v_sat, inv_gtmin, u_lo, u_hi, c0, c1):
    """The starting estimate: the non-saturated average (Eq. 11 usable set); photosites with no
    usable sample get the lower bound of the shortest exposure at v_sat and are done. Prepares
    the first pass (:func:`_estimate`); returns the number of photosites outside its range."""
    bad = 0
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        LB[c] = ((v_sat - BL[c]) * inv_gtmin - DD[c]) * IA[c]
        empty = CNT[c] == 0.0
        m = LB[c] if empty else S[c] / max(CNT[c], 1.0)
        MU[c] = m
        DONE[c] = 1.0 if empty else 0.0
        FLAG[c] = 1.0 if empty else 0.0
        bad += _estimate(m, A[c], DD[c], U, SW, SWX, c, u_lo, u_hi)
    return bad


@numba.njit(inline="always", cache=True)
def _estimate(m, a, D, U, SW, SWX, c, u_lo, u_hi):
    """u = a max(mu, 0) + max(D, 0), the estimate the weights of the next pass are taken at
    (Eq. 13), into U; clears the sums of that pass. Every term of u is floored at 0 (and the
    variance's own D term, the caller's DW row, too), so that no variance can go negative
    whatever the dark-current map holds. Returns 1 when u + k D (0 <= k <= 1) may leave
    [u_lo, u_hi], the range in which every frame's variance allows the shared division, else 0
    (an integer count: vectorises, unlike a floating-point min/max)."""
    dp = D if D > 0.0 else 0.0
    u = a * (m if m > 0.0 else 0.0) + dp
    U[c] = u
    SW[c] = _ZERO32
    SWX[c] = _ZERO32
    out = (u < u_lo) | (u + dp > u_hi) | (u != u)
    return 1 if out else 0


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_usable(X, n, NU, c0, c1):
    """NU = the number of usable samples (x not NaN) of every photosite."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        NU[c] = 0.0
    for i in range(n):
        xi = X[i]
        for c in range(numba.uint64(c0), numba.uint64(c1)):
            NU[c] += 1.0 if xi[c] == xi[c] else 0.0


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_update(MU, SIG, SW, SWX, DONE, FLAG, ITER, A, DD, U, it, tol2, u_lo, u_hi, c0, c1):
    """Eq. 12 for the photosites not yet converged: mu = sum w x / sum w, sigma^2 = 1/sum w;
    converged when the change is within tol * max(|mu|, sigma) (Fig. 3); no usable sample left
    (sum w = 0: every weight of a usable sample is > 0, every variance is floored) flags the
    photosite: it keeps nexp = 0, never a placeholder sigma. Prepares the next
    pass (:func:`_estimate`). Returns the number of photosites still iterating and the number
    outside the next pass's range."""
    active = 0
    bad = 0
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        live = DONE[c] == 0.0
        sw = SW[c]
        none = not (sw > _ZERO32)
        var = float(_ONE32 / (sw if sw > _ZERO32 else _ONE32))  # in the precision of the sums; unused where none
        new = SWX[c] * var
        m = MU[c]
        delta = new - m
        conv = (it > 0) & (delta * delta <= tol2 * max(new * new, var))
        upd = live & (not none)
        ITER[c] = it + 1.0 if live else ITER[c]
        FLAG[c] = 1.0 if (live & none) else FLAG[c]
        m = new if upd else m
        MU[c] = m
        SIG[c] = var if upd else SIG[c]  # variance here; square root taken at the end
        fin = live & (none | conv)
        DONE[c] = 1.0 if fin else DONE[c]
        active += 1 if (live & (not fin)) else 0
        bad += _estimate(m, A[c], DD[c], U, SW, SWX, c, u_lo, u_hi)
    return active, bad


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_output(r, MU, SIG, NU, ITER, FLAG, LB, out_irr, out_sig, out_nexp, out_iter, c0, c1):
    """Results of the threshold model: flagged photosites (no usable sample) get nexp = 0,
    sigma = 0 and the lower bound; everything clamped to finite float32. Returns the number of
    photosites with nexp = 0, the sum and the maximum of the iteration counts (integer
    reductions: they vectorise, floating-point ones would not without reassociation)."""
    oi = out_irr[r]
    os_ = out_sig[r]
    on = out_nexp[r]
    ot = out_iter[r]
    big = FLOAT32_MAX
    n0 = 0
    isum = 0
    imax = 0
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        flagged = FLAG[c] != 0.0
        mu = MU[c]
        mu = 0.0 if mu != mu else mu
        est = min(mu, LB[c]) if flagged else mu
        oi[c] = min(max(est, -big), big)
        s = math.sqrt(SIG[c])
        s = 0.0 if s != s else s
        os_[c] = 0.0 if flagged else min(s, big)
        nu = 0.0 if flagged else NU[c]
        on[c] = nu
        it = int(min(ITER[c], 255.0))
        ot[c] = it
        n0 += 1 if nu == 0.0 else 0
        isum += it
        imax = max(imax, it)
    return n0, isum, imax


# ------------------------------------------------------------------------ the clip rule
@numba.njit(cache=True, error_model="numpy")
def _clip_window(VTH, BL, g, s2, v_sat):
    """VTH = v_sat - CLIP_WINDOW sqrt(g max(v_sat - bias, 0) + sigma_R^2): the least raw value of
    a possibly clipped sample (the model's standard deviation of a raw value at v_sat, Eq. 3)."""
    for c in range(VTH.shape[0]):
        VTH[c] = v_sat - CLIP_WINDOW * math.sqrt(g * max(v_sat - BL[c], 0.0) + s2)


@numba.njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_candidates(vrow, xrow, VTH, CAND, c0, c1):
    """CAND += 1 where this frame's sample is still usable (x not NaN) and its raw value is at
    least VTH: possibly clipped (:func:`_clip_rule`)."""
    for c in range(numba.uint64(c0), numba.uint64(c1)):
        CAND[c] += 1.0 if ((xrow[c] == xrow[c]) & (float(vrow[c]) >= VTH[c])) else 0.0


@numba.njit(cache=True, error_model="numpy")
def _others(X, FR, n, c, skip, mu, a, Dw, s2, tol, max_iter):
    """Eq. 12-13 iterated (Fig. 3) over the usable samples of photosite ``c`` (x not NaN) but
    sample ``skip``, from ``mu``. Returns the estimate, the sum of the weights at it (0: no
    such sample) and the passes made."""
    a2 = a * a
    sw = 0.0
    steps = 0
    for _ in range(max_iter):
        u = a * (mu if mu > 0.0 else 0.0) + Dw
        sw = 0.0
        swx = 0.0
        for j in range(n):
            x = float(X[j, c])
            if j == skip or x != x:
                continue
            w = float(FR[j, 2]) * a2 / _var(u, float(FR[j, 1]), Dw, s2, float(FR[j, 3]))
            sw += w
            swx += w * x
        steps += 1
        if not sw > 0.0:
            return mu, 0.0, steps
        new = swx / sw
        done = (new - mu) * (new - mu) <= tol * tol * max(new * new, 1.0 / sw)
        mu = new
        if done:
            break
    return mu, sw, steps


@numba.njit(cache=True, error_model="numpy")
def _saturated_bounds(values, darks, frames, r, c, FR, n, a, bl, master_c, D, Dw, g, s2, v_sat, kc, out):
    """Per frame j into ``out``: where its sample is saturated (v_j >= v_sat, its dark level
    b_j usable), the lower bound of X it sets, L_j = (v_sat - kc s_j - b_j)/(t_j g a), s_j the
    standard deviation of v_j - b_j at v_sat (Eq. 3, 5: g max(v_sat - bias, 0) + sigma_R^2 plus
    the dark level's); -inf elsewhere."""
    kinds, coefs, ks, times = frames
    span = g * max(v_sat - bl, 0.0)
    for j in range(n):
        out[j] = -math.inf
        v = float(values[j][r, c])
        b = _dark_level(darks, kinds, coefs, j, r, c, bl, master_c, D)
        if v >= v_sat and b < v_sat and math.isfinite(b):
            k = float(FR[j, 3])
            sd = math.sqrt(span + s2 + k * (float(FR[j, 1]) * Dw + s2))
            out[j] = (v_sat - kc * sd - b) / (float(FR[j, 0]) * a)


@numba.njit(cache=True, error_model="numpy")
def _clip_rule(values, r, c, X, FR, n, vth, v_sat, mu, a, Dw, s2, kc, tol, max_iter, BOUND):
    """The clip rule of photosite (r, c) after the iterations: reject usable samples that are
    possibly clipped (raw value at least ``vth``) and lie far below what the other samples say,
    or are more likely clipped values than not, one at a time (the worst first) until none
    does; sets their x to NaN in ``X``. Clipping only lowers a sample, so the two z tests are
    one-sided; sample i fails when z_i < -kc for

    * the other usable samples (leave-one-out): z_i = (x_i - mu_{-i}) / sqrt(Var(x_i | mu_{-i})
      + 1/W_{-i}), mu_{-i} and W_{-i} (the sum of their weights) iterated to the estimate of the
      usable samples but i (Eq. 12-13, :func:`_others`), the variances at mu_{-i}, never at the
      current estimate (which a slipped sample may dominate); no test without another sample;
    * the saturated samples of shorter exposures (``BOUND``, :func:`_saturated_bounds`: a
      shorter exposure saturated says X >= L_j, and a longer one is then saturated too):
      z_i = (x_i - L) / sqrt(Var(x_i | L)), L the largest L_j of the exposures shorter than i;

    and when, given the other samples, it is more likely a clipped value than an unclipped one
    (the odds of the mixture of :func:`_tobit_terms`): with S^2 = Var(x_i | mu_{-i}) + 1/W_{-i},
    x_clip = x_i + (v_clip - v_i)/(t_i g a) and v_clip = v_sat + 3 sigma_R,
    P_c phi(e_i) t_i g a / sigma_R > phi(z_i) / S, P_c = 1 - Phi((x_clip - mu_{-i})/S) and
    e_i = (v_i - v_clip)/sigma_R. This catches a slipped value where the others are too
    uncertain for the z test (sparse brackets: S many times sigma_R/(t_i g a)); it cannot fire
    unless S t_i g a > 90 sigma_R phi(z_i)/phi(3) or so (e_i < -3 below v_sat). Such a sample
    ranks as z = min(z_i, -kc) among the failing ones.

    Returns
    -------
    tuple
        (samples rejected, the estimate of the samples kept (``mu`` when none was rejected),
        passes made).
    """
    rejected = 0
    steps = 0
    a2 = a * a
    sigma_R = math.sqrt(s2)
    v_clip = v_sat + 3.0 * sigma_R
    while True:
        worst = -1
        worst_z = -kc
        worst_mu = mu
        for i in range(n):
            x = float(X[i, c])
            if x != x or float(values[i][r, c]) < vth:
                continue  # not usable, or not possibly clipped
            tg = float(FR[i, 0])
            lo = -math.inf  # the shorter saturated samples' bound
            for j in range(n):
                if float(FR[j, 0]) < tg and BOUND[j] > lo:
                    lo = BOUND[j]
            if lo > -math.inf:
                vi = _var(a * (lo if lo > 0.0 else 0.0) + Dw, float(FR[i, 1]), Dw, s2, float(FR[i, 3]))
                z = (x - lo) / math.sqrt(vi / (float(FR[i, 2]) * a2))
                if z < worst_z:
                    worst, worst_z, worst_mu = i, z, mu
            m, sw, st = _others(X, FR, n, c, i, mu, a, Dw, s2, tol, max_iter)
            steps += st
            if sw > 0.0:
                vi = _var(a * (m if m > 0.0 else 0.0) + Dw, float(FR[i, 1]), Dw, s2, float(FR[i, 3]))
                sx = math.sqrt(vi / (float(FR[i, 2]) * a2) + 1.0 / sw)
                z = (x - m) / sx
                if z < worst_z:
                    worst, worst_z, worst_mu = i, z, m
                # more likely a clipped value than not, given the others
                tga = float(FR[i, 0]) * a
                e = (float(values[i][r, c]) - v_clip) / sigma_R
                pc = _survival((x + (v_clip - float(values[i][r, c])) / tga - m) / sx)
                odds = math.log(max(pc, 1e-300)) - 0.5 * e * e + 0.5 * z * z + math.log(sx * tga / sigma_R)
                zr = min(z, -kc)
                if odds > 0.0 and (worst < 0 or zr < worst_z):
                    worst, worst_z, worst_mu = i, zr, m
        if worst < 0:
            return rejected, mu, steps
        X[worst, c] = math.nan
        rejected += 1
        mu = worst_mu


@numba.njit(cache=True, error_model="numpy")
def _refit(X, FR, n, c, mu, a, Dw, vsb, s2, sat2, tol, max_iter):
    """Eq. 12-13 with the near-saturation rule (margin sqrt(sat2), samples it drops set to NaN
    in ``X``), iterated from ``mu`` over the usable samples of photosite ``c``, as the
    vectorised iterations do. Returns (mu, variance 1/sum w (0: no sample left), passes)."""
    a2 = a * a
    var = 0.0
    steps = 0
    for _ in range(max_iter):
        u = a * (mu if mu > 0.0 else 0.0) + Dw
        sw = 0.0
        swx = 0.0
        for j in range(n):
            x = float(X[j, c])
            if x != x:
                continue
            if sat2 > 0.0:
                gap = vsb - float(FR[j, 0]) * u
                if not (gap > 0.0 and gap * gap > sat2 * _var(u, float(FR[j, 1]), Dw, s2, 0.0)):
                    X[j, c] = math.nan
                    continue
            w = float(FR[j, 2]) * a2 / _var(u, float(FR[j, 1]), Dw, s2, float(FR[j, 3]))
            sw += w
            swx += w * x
        steps += 1
        if not sw > 0.0:
            return mu, 0.0, steps
        var = 1.0 / sw
        new = swx * var
        done = (new - mu) * (new - mu) <= tol * tol * max(new * new, var)
        mu = new
        if done:
            break
    return mu, var, steps


@numba.njit(inline="always", cache=True)
def _survival(z):
    """1 - Phi(z) of the standard normal distribution."""
    return 0.5 * math.erfc(z / _SQRT2)


@numba.njit(inline="always", cache=True)
def _mills(z):
    """The inverse Mills ratio lambda(z) = phi(z) / (1 - Phi(z)) of the standard normal: the
    score of a censored sample in units of its standard deviation. Direct up to z = 30, then
    its continued fraction z + 1/(z + 2/(z + 3/(z + 4/z))) (the survival underflows near 38;
    relative error < 1e-9 there)."""
    if z > 30.0:
        return z + 1.0 / (z + 2.0 / (z + 3.0 / (z + 4.0 / z)))
    return _INV_SQRT_2PI * math.exp(-0.5 * z * z) / _survival(z)


@numba.njit(inline="always", cache=True)
def _dark_level(darks, kinds, coefs, i, r, c, bl, master_c, D):
    """The dark level b_i of frame i at photosite (r, c), DN (see the module docstring)."""
    kind = kinds[i]
    if kind == 0:
        return float(darks[i][r, c])
    if kind == 1:
        return bl + coefs[i] * D
    return master_c + coefs[i] * D


@numba.njit(cache=True, error_model="numpy")
def _tobit_terms(values, darks, frames, camera, r, c, mu, a, D, bl, master_c):
    """The censored log-likelihood's derivatives at ``mu`` for one photosite (Eq. 8-10 as a
    censored Gaussian model, the variances held at the estimate as in Eq. 13).

    A sample with v < v_sat contributes the Gaussian density of v - b_i (mean t g a mu,
    variance :func:`pipeline.noise.variance_of_rate` at max(mu, 0): photon, read, dark frame);
    where the full well clips before the ADC, mixed with the clipped values' density: a
    Gaussian of sd sigma_R around v_clip = v_sat + 3 sigma_R (Sec. 6) weighted by the
    probability Q = 1 - Phi((v_clip - E v)/sd) that the sample is clipped. A sample with
    v >= v_sat contributes its survival probability P = 1 - Phi(z), z = (v_sat - E v)/sd.

    Returns
    -------
    tuple of float
        The score dL/dmu ((e-/s)^-1), the observed information -d2L/dmu2 and the complete-data
        information (the unsaturated part's share; positive whenever a sample is), both
        (e-/s)^-2, the expected number of unclipped samples among those below v_sat, the
        number of those more likely unclipped than clipped.
    """
    kinds, coefs, ks, times = frames
    g, sigma2_R, v_sat, white = camera
    sigma_R = math.sqrt(sigma2_R)
    full_well = white - v_sat > 3.0 * sigma_R
    v_clip = v_sat + 3.0 * sigma_R
    Dv = D if D > 0.0 else 0.0  # the dark current inside the variances, floored (the dark level keeps D)
    m = mu if mu > 0.0 else 0.0
    score = 0.0
    info = 0.0
    info_c = 0.0
    nu = 0.0
    nr = 0
    for i in range(len(values)):
        v = float(values[i][r, c])
        b = _dark_level(darks, kinds, coefs, i, r, c, bl, master_c, D)
        if not (math.isfinite(v) and math.isfinite(b) and b < v_sat):
            continue  # an unusable sample (Eq. 11: a saturated dark frame) carries nothing
        t = times[i]
        tga = t * g * a
        sd = math.sqrt(_var(a * m + Dv, g * g * t, Dv, sigma2_R, ks[i]))  # sd(v - b), DN
        kap = tga / sd  # d/dmu of the standardised value, (e-/s)^-1
        ev = b + tga * mu  # E(v | mu, b) without clipping, DN
        if v < v_sat:
            y = (v - ev) / sd
            d1 = y * kap
            d2 = -kap * kap
            rr = 1.0
            e = (v - v_clip) / sigma_R
            if full_well and e > -38.0:  # else the clipped density is below 1e-300 of the peak
                zc = (v_clip - ev) / sd
                la = -0.5 * y * y - math.log(sd)
                lb = math.log(max(_survival(zc), 1e-300)) - 0.5 * e * e - math.log(sigma_R)
                rr = 1.0 / (1.0 + math.exp(min(lb - la, 700.0)))  # P(unclipped | v, mu)
                lam = _mills(zc)
                d1 = rr * y * kap + (1.0 - rr) * lam * kap
                d2 = (rr * (y * y - 1.0) + (1.0 - rr) * zc * lam) * kap * kap - d1 * d1
            score += d1
            info -= d2
            info_c += rr * kap * kap
            nu += rr
            nr += 1 if rr > 0.5 else 0
        else:
            z = (v_sat - ev) / sd
            lam = _mills(z)
            h = lam * (lam - z) * kap * kap  # >= 0: the survival function is log-concave
            score += lam * kap
            info += h
            info_c += h
    return score, info, info_c, nu, nr


@numba.njit(cache=True, error_model="numpy")
def _tobit_moments(values, darks, frames, camera, r, c, mu, a, D, bl, master_c):
    """Expectations, over the censored model at ``mu`` (not over what was observed), of the
    log-likelihood's derivatives of one photosite: the terms of the first-order mean of the
    Wald statistic (mu_hat - X)/sigma_hat.

    Each usable sample i (as in :func:`_tobit_terms`) is a Gaussian of sd s_i censored at
    v_sat (the full-well mixture of :func:`_tobit_terms` left out), u_i = (v_sat - E v_i)/s_i,
    kappa_i = t_i g a/s_i, phi the standard normal density and lambda = phi/(1 - Phi) the
    inverse Mills ratio (:func:`_mills`). The first and
    second derivatives of a sample's log-likelihood are kappa y and -kappa^2 when it is below
    v_sat (y its standardised value), kappa lambda(u) and -kappa^2 lambda (lambda - u) when it
    is censored, so that

    * the expected information is I = sum kappa_i^2 [Phi(u_i) + phi(u_i) (lambda_i - u_i)];
    * kappa_{11,1} = E[l'' l'] = sum kappa_i^3 phi(u_i) [1 - lambda_i (lambda_i - u_i)] > 0.

    A sample far below v_sat (u > 8, phi(u) < 1e-14) adds kappa^2 to I and nothing to
    kappa_{11,1}; one far above it (u < -8) adds nothing to either.

    Returns
    -------
    tuple of float
        I ((e-/s)^-2), kappa_{11,1} ((e-/s)^-3) and the spacing the root rests on: the longest
        exposure time among the samples not far above v_sat (u >= -3) that are not surely below
        it (censored or possibly clipped: u <= 3, or v >= v_sat) over the longest among those
        surely below it (u > 3 and v < v_sat); 1 when no sample is near v_sat, inf when none is
        surely below.
    """
    kinds, coefs, ks, times = frames
    g, sigma2_R, v_sat, white = camera
    Dv = D if D > 0.0 else 0.0
    m = mu if mu > 0.0 else 0.0
    info = 0.0
    k11_1 = 0.0
    t_far = 0.0
    t_near = 0.0
    for i in range(len(values)):  # the samples as in _tobit_terms
        b = _dark_level(darks, kinds, coefs, i, r, c, bl, master_c, D)
        v = float(values[i][r, c])
        if not (math.isfinite(v) and math.isfinite(b) and b < v_sat):
            continue
        tga = times[i] * g * a
        sd = math.sqrt(_var(a * m + Dv, g * g * times[i], Dv, sigma2_R, ks[i]))
        kap = tga / sd
        k2 = kap * kap
        u = (v_sat - b - tga * mu) / sd
        below = (u > 3.0) & (v < v_sat)  # surely neither censored nor clipped
        t_far = max(t_far, times[i]) if below else t_far
        t_near = max(t_near, times[i]) if (not below) & (u >= -3.0) else t_near
        if u > 8.0:  # never censored (phi(u) < 1e-14): the Gaussian's information, no third-order term
            info += k2
            continue
        if u < -8.0:  # always censored, and then it carries no information (below 1e-14 kappa^2)
            continue
        phi = _INV_SQRT_2PI * math.exp(-0.5 * u * u)
        surv = _survival(u)  # >= 6e-16 here
        lam = phi / surv
        info += k2 * (1.0 - surv + phi * (lam - u))
        k11_1 += k2 * kap * phi * (1.0 - lam * (lam - u))
    spacing = 1.0 if t_near == 0.0 else (t_near / t_far if t_far > 0.0 else math.inf)
    return info, k11_1, spacing


@numba.njit(cache=True, error_model="numpy")
def _tobit(values, darks, frames, camera, r, c, mu, sig, a, D, bl, master_c, tol):
    """The censored (Tobit) maximum-likelihood estimate of one photosite (Eq. 8-10 with the
    saturated samples' survival probability, :func:`_tobit_terms`), from the threshold
    model's estimate ``mu`` (standard deviation ``sig``, e-/s).

    The score's root is bracketed by steps of ``sig`` doubling away from ``mu``, then found by
    Newton steps on the observed information, a bisection wherever a step would leave the
    bracket (the mixture of a full well clipping first is not log-concave), until the step is
    within ``tol`` max(|mu|, sigma). sigma = 1/sqrt(observed information) at the root (the
    complete-data information where the observed one is not positive): the information the
    saturated samples carry is in it.

    The root is then moved by the first-order mean of the Wald statistic z = (mu_hat - X)/sigma:
    mu = mu_hat - kappa_{11,1}/(2 I^2) (:func:`_tobit_moments`, at mu_hat). With the expansions
    mu_hat - X = U/I + (U V/I^2 + kappa_111 U^2/(2 I^3)) (U the score, V = l'' + I) and
    sigma^-1 = sqrt(I) (1 - (V + kappa_111 (mu_hat - X))/(2 I)), E z = kappa_{11,1}/(2 I^(3/2))
    (the same with the expected information at mu_hat), so the shift is that mean times
    1/sqrt(I). The Cox-Snell bias correction of mu_hat itself, (kappa_{11,1} + kappa_111/2)/I^2,
    removes the estimate's bias but leaves z biased the other way (sigma_hat is correlated with
    mu_hat): see docs/merge.md and ``benchmarks/tobit_bias_model.py``.

    Returns
    -------
    tuple
        (mu, sigma (e-/s), number of samples used, score evaluations, flagged, spacing):
        flagged when no sample below v_sat is more likely unclipped than clipped (only a lower
        bound is known); spacing = the spacing the root rests on (:func:`_tobit_moments`), which
        :func:`_tobit_trusted` judges (0 when flagged).
    """
    f, h, hc, nu, nr = _tobit_terms(values, darks, frames, camera, r, c, mu, a, D, bl, master_c)
    steps = 1
    if nr == 0:
        return mu, sig, 0.0, steps, True, 0.0
    scale = sig if (sig > 0.0 and math.isfinite(sig)) else 1.0 / math.sqrt(hc)
    lo = mu
    hi = mu
    direction = 1.0 if f > 0.0 else -1.0
    far = mu
    found = f == 0.0
    for _ in range(64):  # bracket the root: lo with a positive score, hi with a negative one
        if found:
            break
        far = far + direction * scale
        fn = _tobit_terms(values, darks, frames, camera, r, c, far, a, D, bl, master_c)[0]
        steps += 1
        found = (fn > 0.0) != (direction > 0.0) or fn == 0.0
        if direction > 0.0:
            lo = far if not found else lo
            hi = far if found else hi
        else:
            hi = far if not found else hi
            lo = far if found else lo
        scale *= 2.0
    if not found:  # the likelihood keeps growing: no finite estimate, a bound at most
        return mu, sig, 0.0, steps, True, 0.0
    x = mu
    for _ in range(100):
        if f == 0.0:  # at the root (a Newton step of 0 would land on the bracket's end)
            break
        hh = h if h > 0.0 else hc
        xn = x + f / hh
        if not (lo < xn < hi):
            xn = 0.5 * (lo + hi)
        done = abs(xn - x) <= tol * max(abs(xn), 1.0 / math.sqrt(hh))
        x = xn
        f, h, hc, nu, nr = _tobit_terms(values, darks, frames, camera, r, c, x, a, D, bl, master_c)
        steps += 1
        if done:
            break
        if f > 0.0:
            lo = x
        elif f < 0.0:
            hi = x
    if nr == 0:
        return x, sig, 0.0, steps, True, 0.0
    hh = h if h > 0.0 else hc
    # Centre the Wald statistic: its first-order mean is kappa_{11,1}/(2 I^(3/2)) whether sigma
    # comes from the observed or the expected information (docs/merge.md, item 5)
    ie, k11_1, spacing = _tobit_moments(values, darks, frames, camera, r, c, x, a, D, bl, master_c)
    if ie > 0.0:  # else no sample informs at the root (every one far above v_sat): nothing to centre
        x -= 0.5 * k11_1 / (ie * ie)
    return x, 1.0 / math.sqrt(hh), float(nr), steps, False, spacing


@numba.njit(inline="always", cache=True)
def _tobit_trusted(spacing, limit):
    """Whether the censored likelihood's estimate stands (else the threshold model's does): the
    samples it rests on near their clip level (censored, or values that may be clipped) come
    from exposures at most ``limit`` times longer than the longest sample surely below its
    clip (``spacing``, :func:`_tobit_moments`). With wider spacing the samples below the clip
    carry about 1/spacing of the information just above it, the likelihood is far from
    Gaussian (a sharp edge, or a second, wide mode where a clipped value reads as unclipped)
    and sigma from its curvature is too small (docs/merge.md, item 5). ``limit`` 0: always."""
    return (not limit > 0.0) or spacing <= limit * (1.0 + 1e-9)


# ------------------------------------------------------------------------------- kernels
@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FM)
def first_pass_kernel(
    v_arr: np.ndarray,
    d_arr: np.ndarray,
    kind: int,
    base: MapArg,
    coef: float,
    t: float,
    g: float,
    v_sat: float,
    dark_current: MapArg,
    prnu: MapArg,
    init_sum: np.ndarray,
    init_cnt: np.ndarray,
) -> None:
    """Streaming first pass: add one frame's usable x_i to the non-saturated average.

    Computes x_i exactly as :func:`merge_kernel` does, so that a merge started from these
    sums equals the batch merge bit for bit when the frames come in the same order.

    Parameters
    ----------
    v_arr, d_arr : 2-D arrays
        The frame and (``kind`` 0) its dark frame, DN.
    kind : int
        0: dark level ``d_arr``; otherwise ``base + coef * D``.
    base, dark_current, prnu : MapArg
        Bias or master dark (DN), dark current D (e-/s) and PRNU gain.
    coef : float
        Factor of D in the dark level, DN per e-/s.
    t, g, v_sat : float
        Exposure time (s), gain (DN/e-) and saturation limit (DN).
    init_sum, init_cnt : 2-D arrays
        Sums (float64, e-/s) and counts (int32) of the starting average, added to in place.
    """
    base_map, base_is_map, base_scalar = base
    D_map, D_is_map, D_scalar = dark_current
    a_map, a_is_map, _a_scalar = prnu
    H, W = v_arr.shape
    inv_tg = 1.0 / (t * g)
    for r in prange(H):
        for c in range(W):
            a = _pick(a_map, a_is_map, 1.0, r, c)
            if kind == 0:
                b = float(d_arr[r, c])
            else:
                b = _pick(base_map, base_is_map, base_scalar, r, c) + coef * _pick(D_map, D_is_map, D_scalar, r, c)
            x, ok = _sample(float(v_arr[r, c]), b, inv_tg, 1.0 / a, v_sat)
            if ok:
                init_sum[r, c] += x
                init_cnt[r, c] += 1


@numba.njit(parallel=True, cache=True, error_model="numpy", fastmath=_FM)
def merge_kernel(
    values: list[np.ndarray],
    darks: list[np.ndarray],
    frames: FrameTable,
    camera: CameraConstants,
    maps: MapSet,
    start: StartSums,
    options: IterationOptions,
    out: MergeOutputs,
    proto: np.ndarray,
) -> None:
    """The ML merge of every photosite (Eq. 6, 8-13, Fig. 3); results into ``out``.

    Per photosite: x_i (Eq. 6); start from the non-saturated average (Eq. 11 usable set);
    iterate w_i = 1/Var(x_i) at max(mu, 0) (Eq. 13) and mu = sum w x / sum w, sigma^2 =
    1/sum w (Eq. 12) until |change| <= tol * max(|mu|, sigma) or ``max_iter`` steps. From the
    second step on, a sample whose raw value predicted from the current estimate lies within
    ``sat_sigmas`` of its own standard deviation of ``v_sat`` is dropped for good (saturated
    samples that slip under v_sat on read noise). With ``probabilistic``, the censored (Tobit)
    likelihood of Eq. 8-10 is maximised from that estimate (:func:`_tobit`: saturated samples
    contribute their survival probability; sigma from the observed information; the root
    moved by the first-order mean of (mu - X)/sigma).
    Photosites with no usable sample get ``nexp = 0``, ``sigma = 0`` and a lower bound of the
    irradiance. The rows are split into ``len(stats)`` chunks (run in parallel); each chunk's
    row of ``stats`` receives its number of photosites with nexp = 0, the sum and the maximum
    of its iteration counts.

    The weights and their sums are computed in the precision of ``proto`` (a 1-element array,
    float64 or float32; the caller picks float32 only where every quantity provably stays
    inside its range). The samples x_i are computed, and the estimates updated, in float64.

    Parameters
    ----------
    values, darks : lists of 2-D arrays
        The frames and their dark frames (a 1x1 placeholder where a frame has none), DN.
    frames : FrameTable
        Per-frame kinds, coefficients, dark-variance factors and exposure times (s).
    camera : CameraConstants
        g (DN/e-), sigma2_R (DN^2), v_sat and white level (DN).
    maps : MapSet
        Bias (DN), dark current (e-/s), PRNU gain and the single master dark (DN).
    start : StartSums
        The streaming first pass's sums of the starting average.
    options : IterationOptions
        Iteration limit, tolerance, near-saturation margin, saturation model.
    out : MergeOutputs
        Arrays the results are written into.
    proto : 1-element array
        Its dtype is the precision of the weights.
    """
    kinds, coefs, ks, times = frames
    g, sigma2_R, v_sat, white = camera
    bias, bias_is_map, bias_scalar = maps.bias
    D_map, D_is_map, D_scalar = maps.dark_current
    a_map, a_is_map, _a_scalar = maps.prnu
    master, has_master, _m_scalar = maps.master
    init_sum, init_cnt, use_init = start
    max_iter, tol, sat_sigmas, probabilistic, clip_sigmas, censored_spacing = options
    out_irr, out_sig, out_nexp, out_iter, out_rules, stats = out
    n = len(values)
    H, W = values[0].shape
    tmin = times[0]
    for i in range(n):
        tmin = min(tmin, times[i])
    sat2 = sat_sigmas * sat_sigmas
    tol2 = tol * tol
    # The clip rule where the full well clips before the ADC (saturated values then scatter
    # around v_sat + 3 sigma_R and some slip under v_sat; the ADC's clip is the white level).
    clip_on = (clip_sigmas > 0.0) & (white - v_sat > 3.0 * math.sqrt(sigma2_R))
    inv_gtmin = 1.0 / (g * tmin)
    nchunk = stats.shape[0]
    # Blocks of columns: whole rows up to 8192 columns (fewer loop prologues and remainders).
    # The row buffers are padded to a multiple of 64 columns so that the loops that touch only
    # buffers run without scalar remainders; padded columns hold no usable sample (x NaN).
    block = 8192
    Wp = (W + 63) // 64 * 64
    # Per-frame constants of the weights (see _weigh): t g, g^2 t, (t g)^2, k, sigma_R^2 (1 + k)
    # (the range check of the shared division),
    # and the scalars, in the precision of the weights.
    FR = np.empty((n, 5), proto.dtype)
    for i in range(n):
        tg = times[i] * g
        FR[i, 0] = tg
        FR[i, 1] = g * tg
        FR[i, 2] = tg * tg
        FR[i, 3] = ks[i]
        FR[i, 4] = _var(0.0, g * tg, 0.0, sigma2_R, ks[i])  # the variance at u = D = 0
    SC = np.empty(2, proto.dtype)
    SC[0] = sigma2_R
    SC[1] = sat2
    s2w = SC[0]
    sat2w = SC[1]
    # The shared division needs every variance d_i = g^2 t_i (u + k D) + s2k_i within
    # [shared_lo, shared_hi]: each s2k_i inside it, and u + k D within [u_lo, u_hi].
    shared_lo, shared_hi = _SHARED_RANGE32 if proto.itemsize == 4 else _SHARED_RANGE64
    shared_frames = True
    u_lo = -math.inf
    u_hi = math.inf
    for i in range(n):
        shared_frames &= (FR[i, 4] >= shared_lo) & (FR[i, 4] <= shared_hi)
        u_lo = max(u_lo, (shared_lo - FR[i, 4]) / FR[i, 1])
        u_hi = min(u_hi, (shared_hi - FR[i, 4]) / FR[i, 1])
    for ch in prange(nchunk):
        # Row buffers, allocated once per chunk of rows (not per row).
        X = np.full((n, Wp), np.nan, proto.dtype)  # x_i of Eq. 6, NaN where not usable (branch-free loops)
        A = np.empty(Wp)
        A2 = np.empty(Wp, proto.dtype)
        IA = np.empty(Wp)
        DD = np.empty(Wp)
        DW = np.empty(Wp, proto.dtype)
        BL = np.empty(Wp)
        VSB = np.empty(Wp, proto.dtype)
        MB = np.empty(Wp)
        MU = np.empty(Wp)
        U = np.empty(Wp, proto.dtype)
        SIG = np.empty(Wp)
        NU = np.empty(Wp)
        SW = np.empty(Wp, proto.dtype)
        SWX = np.empty(Wp, proto.dtype)
        ITER = np.empty(Wp)
        DONE = np.empty(Wp)
        FLAG = np.empty(Wp)
        LB = np.empty(Wp)
        S = np.empty(Wp)
        CNT = np.empty(Wp)
        VTH = np.empty(Wp)  # the clip rule's window: raw values at least this are possibly clipped
        CAND = np.empty(Wp)
        BOUND = np.empty(n)  # the clip rule's lower bounds from saturated samples, per frame
        # Maps given as scalars are filled once per chunk, maps once per row.
        _fill_row(A, a_map, False, 1.0, 0)
        _fill_row(IA, a_map, False, 1.0, 0)
        _fill_row(A2, a_map, False, 1.0, 0)
        _fill_row(DD, D_map, False, D_scalar, 0)
        _fill_row(DW, D_map, False, D_scalar, 0)
        _floor_row(DW)
        _fill_row(BL, bias, False, bias_scalar, 0)
        _fill_row(VSB, bias, False, v_sat - bias_scalar, 0)
        _clip_window(VTH, BL, g, sigma2_R, v_sat)
        n0 = 0
        isum = 0
        imax = 0
        nclip = 0
        nrej = 0
        nfall = 0
        for r in range(ch * H // nchunk, (ch + 1) * H // nchunk):
            if a_is_map:
                _fill_row(A, a_map, True, 1.0, r)
                for c in range(W):
                    IA[c] = 1.0 / A[c]
                    A2[c] = A[c] * A[c]
            if D_is_map:
                _fill_row(DD, D_map, True, D_scalar, r)
                _fill_row(DW, D_map, True, D_scalar, r)
                _floor_row(DW)
            if bias_is_map:
                _fill_row(BL, bias, True, bias_scalar, r)
                for c in range(W):
                    VSB[c] = v_sat - BL[c]
                _clip_window(VTH, BL, g, sigma2_R, v_sat)
            if has_master:
                _fill_row(MB, master, True, 0.0, r)
            for c in range(Wp):
                SIG[c] = 0.0
                NU[c] = 0.0
                ITER[c] = 0.0
            for c0 in range(0, W, block):
                c1 = min(W, c0 + block)
                cp = Wp if c1 == W else c1  # the buffer-only loops run over the padding too
                for c in range(numba.uint64(c0), numba.uint64(cp)):
                    S[c] = 0.0
                    CNT[c] = 0.0
                i = 0
                while i < n:  # x_i and the sums of the non-saturated average
                    inv_tg = 1.0 / (times[i] * g)
                    kind = kinds[i]
                    if kind == 0 and i + 3 <= n and kinds[i + 1] == 0 and kinds[i + 2] == 0:
                        _load_dark3(
                            values[i][r],
                            darks[i][r],
                            X[i],
                            inv_tg,
                            values[i + 1][r],
                            darks[i + 1][r],
                            X[i + 1],
                            1.0 / (times[i + 1] * g),
                            values[i + 2][r],
                            darks[i + 2][r],
                            X[i + 2],
                            1.0 / (times[i + 2] * g),
                            S,
                            CNT,
                            IA,
                            v_sat,
                            c0,
                            c1,
                        )
                        i += 3
                        continue
                    if kind == 0:
                        _load_dark(values[i][r], darks[i][r], X[i], S, CNT, inv_tg, IA, v_sat, c0, c1)
                    elif kind == 1:
                        _load_base(values[i][r], BL, DD, coefs[i], X[i], S, CNT, inv_tg, IA, v_sat, c0, c1)
                    else:
                        _load_base(values[i][r], MB, DD, coefs[i], X[i], S, CNT, inv_tg, IA, v_sat, c0, c1)
                    i += 1
                if use_init:  # the first pass of the streaming merge summed the same values in the same order
                    for c in range(numba.uint64(c0), numba.uint64(c1)):
                        S[c] = init_sum[r, c]
                        CNT[c] = init_cnt[r, c]
                bad = _row_start(
                    S, CNT, MU, DONE, FLAG, LB, BL, DD, IA, A, U, SW, SWX, v_sat, inv_gtmin, u_lo, u_hi, c0, cp
                )
                # Iterate Eq. 13 <-> Eq. 12 for the whole block at once, frames three at a time
                # (the near-saturation rule from the second step on); one division for three
                # samples when no variance of the block can leave the safe range.
                for it in range(max_iter):
                    shared = shared_frames & (bad == 0)
                    if it > 0 and sat_sigmas > 0.0:
                        _iterate(X, FR, n, U, VSB, A2, DW, SW, SWX, s2w, sat2w, True, shared, c0, cp)
                    else:
                        _iterate(X, FR, n, U, VSB, A2, DW, SW, SWX, s2w, sat2w, False, shared, c0, cp)
                    active, bad = _row_update(
                        MU, SIG, SW, SWX, DONE, FLAG, ITER, A, DD, U, it, tol2, u_lo, u_hi, c0, cp
                    )
                    if active == 0:
                        break
                orules = out_rules[r]
                for c in range(numba.uint64(c0), numba.uint64(c1)):
                    orules[c] = 0
                if clip_on:  # the clip rule (_clip_rule) where a usable sample may be clipped
                    for c in range(numba.uint64(c0), numba.uint64(c1)):
                        CAND[c] = 0.0
                    for i in range(n):
                        _row_candidates(values[i][r], X[i], VTH, CAND, c0, c1)
                    for c in range(c0, c1):
                        if CAND[c] == 0.0 or FLAG[c] != 0.0:
                            continue
                        a_c = A[c]
                        d_c = float(DW[c])
                        vsb_c = float(VSB[c])
                        _saturated_bounds(
                            values,
                            darks,
                            frames,
                            r,
                            c,
                            FR,
                            n,
                            a_c,
                            BL[c],
                            MB[c],
                            DD[c],
                            d_c,
                            g,
                            sigma2_R,
                            v_sat,
                            clip_sigmas,
                            BOUND,
                        )
                        k, m, st = _clip_rule(
                            values,
                            r,
                            c,
                            X,
                            FR,
                            n,
                            VTH[c],
                            v_sat,
                            MU[c],
                            a_c,
                            d_c,
                            sigma2_R,
                            clip_sigmas,
                            tol,
                            max_iter,
                            BOUND,
                        )
                        if k == 0:
                            continue  # (its passes are not counted: the iterations report the re-weighting)
                        ITER[c] += st
                        m, var, st = _refit(X, FR, n, c, m, a_c, d_c, vsb_c, sigma2_R, sat2, tol, max_iter)
                        ITER[c] += st
                        MU[c] = m
                        if var > 0.0:
                            SIG[c] = var
                        else:
                            FLAG[c] = 1.0
                        orules[c] = RULE_CLIP
                        nclip += 1
                        nrej += k
                _row_usable(X, n, NU, c0, cp)
                if probabilistic:  # the censored likelihood, from the threshold model's estimate
                    for c in range(numba.uint64(c0), numba.uint64(c1)):
                        if FLAG[c] != 0.0:
                            # no sample kept by Eq. 11 and the near-saturation rule: saturated in
                            # every exposure, or only values that slipped under v_sat (full well)
                            # or lie within the rule's margin of the shortest exposure's clip; a
                            # lower bound only (nexp = 0)
                            continue
                        mu, sg, nu, steps, flagged, spacing = _tobit(
                            values,
                            darks,
                            frames,
                            camera,
                            r,
                            c,
                            MU[c],
                            math.sqrt(SIG[c]),
                            A[c],
                            DD[c],
                            BL[c],
                            MB[c],
                            tol,
                        )
                        ITER[c] += steps
                        if flagged:
                            FLAG[c] = 1.0
                        elif _tobit_trusted(spacing, censored_spacing):
                            MU[c] = mu
                            SIG[c] = sg * sg
                            NU[c] = nu
                        else:  # the threshold model's estimate stands (_tobit_trusted)
                            orules[c] |= RULE_FALLBACK
                            nfall += 1
                b0, bsum, bmax = _row_output(
                    r, MU, SIG, NU, ITER, FLAG, LB, out_irr, out_sig, out_nexp, out_iter, c0, c1
                )
                n0 += b0
                isum += bsum
                imax = max(imax, bmax)
        stats[ch, 0] = n0
        stats[ch, 1] = isum
        stats[ch, 2] = imax
        stats[ch, 3] = nclip
        stats[ch, 4] = nrej
        stats[ch, 5] = nfall


class ErrorMaps(NamedTuple):
    """Standard errors of the calibration, each a :class:`MapArg` (0 where unknown): ``bias``
    (DN), ``dark_current`` (e-/s) and ``prnu`` (the gain a_j, dimensionless)."""

    bias: MapArg
    dark_current: MapArg
    prnu: MapArg


class SharedTerms(NamedTuple):
    """What :func:`calibration_terms_kernel` computes and with which rules: per-frame ``use``
    (float64, (n, 2): 1 where the dark level holds the bias map, 1 where it is the timed master
    dark; the factor of D in the dark level is the frame table's ``coefs``, 0 for an own dark
    frame); ``sat2`` (the
    near-saturation margin squared, 0: no rule), ``censored`` (the samples' censored
    information instead of 1/Var), ``weights`` (False: the PRNU term alone, no frame needed),
    ``calibration`` and ``master`` (which outputs to fill), the master dark's time ``t_ref``
    (s) and frame count ``n_master``."""

    use: np.ndarray
    sat2: float
    censored: bool
    weights: bool
    calibration: bool
    master: bool
    t_ref: float
    n_master: float


@numba.njit(cache=True, error_model="numpy")
def _terms_weights_row(
    WROW, vrow, BROW, MU, MP, A, DR, BIAS, U, RL, t, g, s2, k, v_sat, sat2, censored
):  # pragma: no cover - compiled
    """Each sample's weight on one row (see :func:`calibration_terms_kernel`); in the order of
    the numpy formulas' operations."""
    tg = t * g
    g2t = g * g * t
    for c in range(WROW.shape[0]):
        v = float(vrow[c])
        b = BROW[c]
        tga = tg * A[c]
        var_x = _var(A[c] * MP[c] + DR[c], g2t, DR[c], s2, k) / (tga * tga)
        if censored and (RL[c] & RULE_FALLBACK) == 0:
            if not ((b < v_sat) and math.isfinite(v) and math.isfinite(b)):
                WROW[c] = 0.0
            elif v < v_sat:
                WROW[c] = 1.0 / var_x
            else:
                z = (v_sat - b - tga * MU[c]) / (math.sqrt(var_x) * tga)
                lam = _mills(z)
                WROW[c] = lam * (lam - z) / var_x
        else:
            ok = (v < v_sat) & (b < v_sat) & ((v - b) - (v - b) == 0.0)  # the last: finite
            if sat2 > 0:
                gap = v_sat - BIAS[c] - tg * U[c]
                ok = ok & (gap > 0) & (gap * gap > sat2 * (g2t * U[c] + s2))
            WROW[c] = 1.0 / var_x if ok else 0.0


@numba.njit(cache=True, error_model="numpy")
def _terms_sums_row(WROW, inv_tg, ub, ud, um, WS, NB, ND, NM):  # pragma: no cover - compiled
    """W += w, and the numerators of d mu / d b, d mu / d D, d mu / d M (one frame, one row)."""
    cb, cd, cm = ub * inv_tg, ud * inv_tg, um * inv_tg
    for c in range(WROW.shape[0]):
        w = WROW[c]
        WS[c] += w
        NB[c] += w * cb
        ND[c] += w * cd
        NM[c] += w * cm


@numba.njit(parallel=True, cache=True, error_model="numpy")
def calibration_terms_kernel(
    values: list[np.ndarray],
    darks: list[np.ndarray],
    frames: FrameTable,
    camera: CameraConstants,
    maps: MapSet,
    errors: ErrorMaps,
    terms: SharedTerms,
    irr: np.ndarray,
    nexp: np.ndarray,
    rules: np.ndarray,
    out: np.ndarray,
    out_m: np.ndarray,
) -> None:
    """The errors common to all exposures of a photosite (:func:`pipeline.merge.calibration_errors.
    shared_terms`), parallel over rows, a row of each frame at a time (row
    buffers, no full-size temporaries).

    The calibration's errors are systematic: the same bias map b_j, dark-current map D_j and
    PRNU map a_j enter every exposure, so averaging exposures does not reduce them. With
    x_i = (v_i - b_i)/(t_i g a) (Eq. 6) and b_i = bias_i b_j + coef_i D_j (the model strategy:
    b_j + g t_i D_j; one master dark at t_ref: master + g (t_i - t_ref) D_j; a dark frame: no
    calibration term), the estimate mu = sum w_i x_i / sum w_i (Eq. 12, weights held fixed)
    moves by d mu/d b_j = -sum w_i bias_i/(t_i g a)/W, d mu/d D_j = -sum w_i coef_i/(t_i g a)/W
    and d mu/d ln a_j = -mu (first order).

    Per photosite at the estimate mu = ``irr`` (e-/s): each sample's weight w_i = 1/Var(x_i)
    (Eq. 6, 13; the variance at max(mu, 0) with the map's D) where it is usable (Eq. 11 and the
    near-saturation rule at mu), or with ``terms.censored`` its share of the censored
    likelihood's information (1/Var(x_i) below v_sat, lambda(z) (lambda(z) - z)/Var(x_i) at
    or above it) except where ``rules`` has :data:`RULE_FALLBACK` (the threshold estimate
    stands there); W = sum w_i; d mu/d b_j = -sum w_i bias_i/(t_i g)/W, d mu/d D_j =
    -sum w_i coef_i/(t_i g)/W, d mu/d M = -sum w_i master_i/(t_i g)/W; then
    ``out`` = sqrt((db sigma_b)^2 + (dD sigma_D)^2 + (mu sigma_a)^2)/a and ``out_m`` =
    |dM| sqrt((g^2 t_ref D + sigma_R^2)/N)/a where nexp > 0, else 0 (float32). The operations
    are those of the numpy formulas, in their order (no fast-math: the same bits)."""
    kinds, coefs, ks, times = frames
    g, s2, v_sat, _white = camera
    bias_map, bias_is_map, bias_scalar = maps.bias
    D_map, D_is_map, D_scalar = maps.dark_current
    a_map, a_is_map, a_scalar = maps.prnu
    master = maps.master.array
    sb_map, sb_is_map, sb_scalar = errors.bias
    sd_map, sd_is_map, sd_scalar = errors.dark_current
    sa_map, sa_is_map, sa_scalar = errors.prnu
    use, sat2, censored, weighted, want_cal, want_master, t_ref, n_master = terms
    n = len(values)
    H, Wd = irr.shape
    for r in prange(H):
        MU = np.empty(Wd)
        A = np.empty(Wd)
        SA = np.empty(Wd)
        for c in range(Wd):
            MU[c] = float(irr[r, c])
            A[c] = _pick(a_map, a_is_map, a_scalar, r, c)
            SA[c] = _pick(sa_map, sa_is_map, sa_scalar, r, c)
        if not weighted:  # the PRNU term alone: (mu sigma_a / a)^2
            for c in range(Wd):
                out[r, c] = abs(MU[c]) * SA[c] / A[c] if nexp[r, c] > 0 else 0.0
            continue
        DR = np.empty(Wd)
        BIAS = np.empty(Wd)
        MP = np.empty(Wd)
        U = np.empty(Wd)
        for c in range(Wd):
            DR[c] = _pick(D_map, D_is_map, D_scalar, r, c)
            BIAS[c] = _pick(bias_map, bias_is_map, bias_scalar, r, c)
            MP[c] = max(MU[c], 0.0)
            U[c] = A[c] * MP[c] + DR[c]
        WS = np.zeros(Wd)
        NB = np.zeros(Wd)
        ND = np.zeros(Wd)
        NM = np.zeros(Wd)
        BROW = np.empty(Wd)
        WROW = np.empty(Wd)
        for i in range(n):
            master_frame = kinds[i] == 2  # the master dark is read only then (else a placeholder)
            for c in range(Wd):
                mc = float(master[r, c]) if master_frame else 0.0
                BROW[c] = _dark_level(darks, kinds, coefs, i, r, c, BIAS[c], mc, DR[c])
            _terms_weights_row(
                WROW,
                values[i][r],
                BROW,
                MU,
                MP,
                A,
                DR,
                BIAS,
                U,
                rules[r],
                times[i],
                g,
                s2,
                ks[i],
                v_sat,
                sat2,
                censored,
            )
            _terms_sums_row(WROW, 1.0 / (times[i] * g), use[i, 0], coefs[i], use[i, 1], WS, NB, ND, NM)
        for c in range(Wd):
            used = nexp[r, c] > 0
            wd = WS[c] if WS[c] > 0 else math.inf
            if want_cal:
                db = (NB[c] / wd) * _pick(sb_map, sb_is_map, sb_scalar, r, c)
                dd = (ND[c] / wd) * _pick(sd_map, sd_is_map, sd_scalar, r, c)
                ma = MU[c] * SA[c]
                out[r, c] = math.sqrt((db * db + dd * dd + ma * ma) / (A[c] * A[c])) if used else 0.0
            if want_master:
                sd_m = math.sqrt((g * g * t_ref * DR[c] + s2) / n_master)
                dm = (NM[c] / wd) * sd_m
                out_m[r, c] = math.sqrt(dm * dm / (A[c] * A[c])) if used else 0.0
