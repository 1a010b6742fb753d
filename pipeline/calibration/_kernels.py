"""Fused numba kernels for the streamed calibration (one pass, no full-size temporaries).

Private to :mod:`hdrcap.pipeline.calibration`; every accumulation is float64.
"""

from __future__ import annotations

import numpy as np

from hdrcap.pipeline._numba_target import numba  # numba, its compile target set (512-bit vectors on AVX-512)

__all__ = [
    "stack_add",
    "stack_add_equal",
    "stack_add_censored",
    "stack_add_batch",
    "stack_result",
    "masked_moments",
    "flat_moments",
    "pair_fused",
    "series_add",
    "response_defect_bits",
    "hot_mask",
    "median_f32",
]


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
def stack_add_censored(values, ref, w, censor, s, q, sw, cnt, mx, mn, wmx, wmn):  # pragma: no cover - compiled
    """:func:`stack_add` skipping the ``censor`` photosites, also summing per-photosite weights
    (``sw``) and sample counts (``cnt``). The update is written out, not shared with
    :func:`stack_add` through a helper: a helper function (plain or ``inline="always"``) made
    the loop 35 times slower (24 Mpixel: 2.5 s instead of 0.07 s)."""
    v = values.ravel()
    r = ref.ravel()
    c = censor.ravel()
    s_, q_, sw_, n_ = s.ravel(), q.ravel(), sw.ravel(), cnt.ravel()
    mx_, mn_, wx_, wn_ = mx.ravel(), mn.ravel(), wmx.ravel(), wmn.ravel()
    for i in range(v.size):
        if c[i]:
            continue
        d = np.float64(v[i]) - np.float64(r[i])
        s_[i] += w * d
        q_[i] += w * d * d
        sw_[i] += w
        n_[i] += 1.0
        if d > mx_[i]:
            mx_[i] = d
            wx_[i] = w
        if d < mn_[i]:
            mn_[i] = d
            wn_[i] = w


#: Photosites of a row tile of :func:`stack_add_batch`: the tile's maps (~40 bytes a photosite)
#: stay in the core's cache while the frames are added.
_TILE = 1024


@numba.njit(parallel=True, cache=True)
def stack_add_batch(
    f0,
    f1,
    f2,
    f3,
    f4,
    f5,
    f6,
    f7,
    nk,
    corrected,
    bias,
    rate,
    rate_on,
    trs,
    scales,
    ws,
    uppers,
    censor_on,
    count_on,
    set_ref,
    ref,
    s,
    q,
    mx,
    mn,
    wmx,
    wmn,
    sw,
    cnt,
):  # pragma: no cover - compiled
    """Several frames into the stack's maps in one pass over each row (the row's maps stay in
    cache while the frames are added one after the other, so every photosite sees its samples in
    the frames' order: bit for bit :func:`stack_add`, :func:`stack_add_equal` and
    :func:`stack_add_censored` frame by frame).

    ``f0`` .. ``f7``: the frames (2-D, one type; the first ``nk`` are added, the others are
    placeholders: a typed list would cost its compilation in every process). With ``corrected`` a sample is the
    dark-corrected, scaled value ((float32(v) - bias) - rate * trs[k]) / scales[k], each step
    rounded to float32 as numpy computed the image (``bias``/``rate``: maps of the frame's shape
    or (1, 1) arrays; the rate only for the frames with ``rate_on[k]``); without, it is the raw
    value v. Frame k has the weight ``ws[k]``; with ``censor_on[k]`` its photosites with raw
    v >= ``uppers[k]`` are left out; with ``count_on[k]`` its samples are added to the
    per-photosite weight sums and counts ``sw``/``cnt`` (maps of the frame's shape, else
    ignored). ``wmx``/``wmn`` (the extremes' weights) are kept when they have the frame's size.
    With ``set_ref`` the first frame's sample becomes the reference ``ref`` (float32).

    Each row and frame runs two loops without branches on the common path (so that they
    vectorise): the samples into a row buffer, then the update."""
    rows, cols = s.shape
    frames = (f0, f1, f2, f3, f4, f5, f6, f7)
    per_b = bias.shape == s.shape
    per_r = rate.shape == s.shape
    track_w = wmx.shape == s.shape
    counts = sw.shape == s.shape
    n_tiles = (cols + _TILE - 1) // _TILE
    for it in numba.prange(rows * n_tiles):
        i = it // n_tiles
        j0 = (it % n_tiles) * _TILE
        j1 = min(j0 + _TILE, cols)
        n = j1 - j0
        s_, q_, mx_, mn_, ref_ = s[i, j0:j1], q[i, j0:j1], mx[i, j0:j1], mn[i, j0:j1], ref[i, j0:j1]
        b_ = bias[i, j0:j1] if per_b else np.full(n, bias[0, 0])
        r_ = rate[i, j0:j1] if per_r else rate[0]
        wx_ = wmx[i, j0:j1] if track_w else wmx[0]
        wn_ = wmn[i, j0:j1] if track_w else wmn[0]
        x_ = np.empty(n, np.float64)
        d_ = np.empty(n, np.float64)
        for k in range(nk):
            v = frames[k][i, j0:j1]
            w = ws[k]
            if corrected:
                tr = trs[k]
                sc = scales[k]
                if per_r and rate_on[k]:
                    for j in range(n):
                        c = np.float32(np.float32(v[j]) - b_[j])
                        x_[j] = np.float32(np.float32(c - r_[j] * tr) / sc)
                else:
                    for j in range(n):
                        x_[j] = np.float32(np.float32(np.float32(v[j]) - b_[j]) / sc)
            else:
                for j in range(n):
                    x_[j] = v[j]
            if set_ref and k == 0:
                for j in range(n):
                    ref_[j] = np.float32(x_[j])
            if censor_on[k] or (count_on[k] and counts):
                _row_add_general(
                    x_,
                    v,
                    ref_,
                    w,
                    censor_on[k],
                    uppers[k],
                    count_on[k] and counts,
                    track_w,
                    i,
                    j0,
                    s_,
                    q_,
                    mx_,
                    mn_,
                    wmx,
                    wmn,
                    sw,
                    cnt,
                )
                continue
            # the common path in short loops of few arrays (few aliasing checks), every value
            # loaded before the selects: each loop vectorises
            for j in range(n):
                d_[j] = x_[j] - np.float64(ref_[j])
            for j in range(n):
                d = d_[j]
                s_[j] += w * d
                q_[j] += w * d * d
            if track_w:
                _row_extreme_w(d_, mx_, wx_, np.float32(w), True)
                _row_extreme_w(d_, mn_, wn_, np.float32(w), False)
            else:
                _row_extreme(d_, mx_, True)
                _row_extreme(d_, mn_, False)


@numba.njit(inline="always")
def _row_extreme_w(d_, m_, w_, w32, largest):  # pragma: no cover - compiled
    """m_ = d_ where d_ > m_ (``largest``) or d_ < m_ (the largest or smallest sample), w_ = w32
    there; compared in float64 (a sample that rounds to the float32 extreme but exceeds it takes
    the weight)."""
    for j in range(d_.size):
        d = d_[j]
        m = m_[j]
        wo = w_[j]
        new = d > np.float64(m) if largest else d < np.float64(m)
        m_[j] = np.float32(d) if new else m
        w_[j] = w32 if new else wo


@numba.njit(inline="always")
def _row_extreme(d_, m_, largest):  # pragma: no cover - compiled
    """m_ = d_ where d_ > m_ (``largest``) or d_ < m_ (the largest or smallest sample). Compared
    in float32: float32(d) > m exactly when d > float64(m) changes m's value (rounding is
    monotone; where float32(d) == m the float64 compare stored the same value; NaN never
    replaces), and the float32 compare and select run twice as many lanes (24 Mpixel: the
    extremes ~45 -> ~25 ms a frame)."""
    for j in range(d_.size):
        x = np.float32(d_[j])
        m = m_[j]
        new = x > m if largest else x < m
        m_[j] = x if new else m


@numba.njit(cache=True)
def _row_add_general(
    x_, v, ref_, w, cens, up, cnt_on, track_w, i, j0, s_, q_, mx_, mn_, wmx, wmn, sw, cnt
):  # pragma: no cover
    """One row tile (row ``i`` from column ``j0``) of :func:`stack_add_batch` with censoring or
    per-photosite counts."""
    for j in range(x_.size):
        if cens and np.float64(v[j]) >= up:
            continue
        d = x_[j] - np.float64(ref_[j])
        s_[j] += w * d
        q_[j] += w * d * d
        if cnt_on:
            sw[i, j0 + j] += w
            cnt[i, j0 + j] += 1.0
        if d > mx_[j]:
            mx_[j] = d
            if track_w:
                wmx[i, j0 + j] = w
        if d < mn_[j]:
            mn_[j] = d
            if track_w:
                wmn[i, j0 + j] = w


@numba.njit(inline="always")
def _nanmax(a, b):  # pragma: no cover - compiled
    """numpy.maximum of two floats: NaN when either is NaN."""
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@numba.njit(inline="always", error_model="numpy")
def _reject(s, q, sw, cnt, v, w, sign, min_cnt, clip2, floor):  # pragma: no cover - compiled
    """Reject the extreme sample ``v`` (weight ``w``) when it lies more than sqrt(clip2)
    standard deviations from the weighted mean of the others; the updated (s, q, sw, cnt, rejected).
    Selects, not branches (the row loop vectorises)."""
    few = cnt < min_cnt  # too few uncensored samples to reject one
    v = 0.0 if few else v
    w = 0.0 if few else w
    s_o = s - w * v
    sw_o = sw - w
    mean_o = s_o / sw_o
    var_o = _nanmax(q - w * v * v - sw_o * (mean_o * mean_o), 0.0) / max(cnt - 2.0, 1.0)
    dev = sign * (v - mean_o)
    rej = dev * dev * w > clip2 * _nanmax(var_o, floor) * (1.0 + w / _nanmax(sw_o, 1e-300))
    return (
        s - w * v if rej else s,
        q - w * v * v if rej else q,
        sw - w if rej else sw,
        cnt - 1.0 if rej else cnt,
        1 if rej else 0,
    )


@numba.njit(inline="always", error_model="numpy")
def _result_px(si, qi, swi, ci, ref_ij, floor):  # pragma: no cover - compiled
    """The weighted mean (+ ``ref_ij``) and its standard error of one photosite (float32); every
    sample censored (``swi`` <= 0): the first (censored) value, 100 % error."""
    none = swi <= 0.0
    mean_rel = si / swi
    var1 = _nanmax(qi - swi * (mean_rel * mean_rel), 0.0) / max(ci - 1.0, 1.0)
    m = si + ref_ij if none else mean_rel + ref_ij
    e = abs(ref_ij) if none else np.sqrt(_nanmax(var1, floor) / swi)
    return np.float32(m), np.float32(e)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def stack_result(
    s, q, sw_map, cnt_map, sw0, cnt0, mx, wmx, mn, wmn, w0, ref, clip2, do_max, do_min, floors, mean, err
):  # pragma: no cover - compiled
    """Per photosite: reject the largest/smallest sample (``do_max``/``do_min``, threshold
    ``clip2`` in variances), then the weighted mean (+ ``ref``) and its standard error into
    ``mean``/``err`` (float32). ``sw_map``/``cnt_map`` (weight sums, counts) and ``wmx``/``wmn``
    (the extremes' weights) are used when they have the frame's size, else the scalars ``sw0``,
    ``cnt0``, ``w0``. ``floors``: the variance floors (max, min, final). Returns the rejections.
    Rows in parallel; per row, the weights into float64 buffers, then one loop per case without
    branches (it vectorises)."""
    rows, cols = s.shape
    per_px_sw = sw_map.shape == s.shape
    per_px_w = wmx.shape == s.shape
    f_max, f_min, f_var = floors[0], floors[1], floors[2]
    nrej = 0
    for i in numba.prange(rows):
        k = 0
        sw_r = sw_map[i] if per_px_sw else np.full(cols, sw0)
        c_r = cnt_map[i] if per_px_sw else np.full(cols, cnt0)
        wx_r = np.empty(cols)
        wn_r = np.empty(cols)
        for j in range(cols):
            wx_r[j] = np.float64(wmx[i, j]) if per_px_w else w0
            wn_r[j] = np.float64(wmn[i, j]) if per_px_w else w0
        s_r, q_r, mx_r, mn_r, ref_r, m_r, e_r = s[i], q[i], mx[i], mn[i], ref[i], mean[i], err[i]
        if do_max and do_min:
            for j in range(cols):
                si, qi, swi, ci, r1 = _reject(
                    s_r[j], q_r[j], sw_r[j], c_r[j], np.float64(mx_r[j]), wx_r[j], 1.0, 3.0, clip2, f_max
                )
                si, qi, swi, ci, r2 = _reject(si, qi, swi, ci, np.float64(mn_r[j]), wn_r[j], -1.0, 4.0, clip2, f_min)
                k += r1 + r2
                m_r[j], e_r[j] = _result_px(si, qi, swi, ci, np.float64(ref_r[j]), f_var)
        elif do_max:
            for j in range(cols):
                si, qi, swi, ci, r1 = _reject(
                    s_r[j], q_r[j], sw_r[j], c_r[j], np.float64(mx_r[j]), wx_r[j], 1.0, 3.0, clip2, f_max
                )
                k += r1
                m_r[j], e_r[j] = _result_px(si, qi, swi, ci, np.float64(ref_r[j]), f_var)
        else:
            for j in range(cols):
                m_r[j], e_r[j] = _result_px(s_r[j], q_r[j], sw_r[j], c_r[j], np.float64(ref_r[j]), f_var)
        nrej += k
    return nrej


# --------------------------------------------------------------------------- fused flat-field passes
# A flat's dark-corrected value is computed on the fly, as numpy computed the float32 image
# before (``c = data.astype(float32); c -= bias; c -= rate * t``): each step rounded to float32,
# in the type numpy chose (float32 for float32 maps and scalars). ``bias`` and ``rate`` are maps
# of the frame's shape, or (1, 1) arrays (a scalar bias; no rate); ``tr`` is t in rate's type.


# The reductions of the fused passes may be reordered (fastmath "reassoc" only: no FMA
# contraction, no assumptions on NaN or infinity), so that they vectorise; their sums then differ
# from a sequential loop's in the last bits. Integer sums (counts, raw values) stay exact.


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def flat_moments(data, bias, rate, tr, lo, hi, clip_on, upper):  # pragma: no cover - compiled
    """One pass over a flat: the photosites at or above ``upper`` (raw values, compared in
    float64) and the count, mean and sum of squared deviations of the dark-corrected values
    within [``lo``, ``hi``] (float32 bounds; all with ``clip_on`` False), shifted by the first
    corrected value (as :func:`masked_moments` on the float32 image)."""
    v = data.ravel()
    b = bias.ravel()
    r = rate.ravel()
    per_b = b.size == v.size
    has_r = r.size == v.size
    b0 = b[0]
    c0 = np.float32(np.float32(v[0]) - b0)
    if has_r:
        c0 = np.float32(c0 - r[0] * tr)
    shift = np.float64(c0)
    n = 0
    n_up = 0
    s1 = 0.0
    s2 = 0.0
    for i in range(v.size):
        n_up += np.float64(v[i]) >= upper
        c = np.float32(np.float32(v[i]) - (b[i] if per_b else b0))
        if has_r:
            c = np.float32(c - r[i] * tr)
        x = np.float64(c)
        k = (x >= lo) & (x <= hi) if clip_on else True
        d = x - shift if k else 0.0
        n += k
        s1 += d
        s2 += d * d
    if n == 0:
        return 0, 0.0, 0.0, n_up
    m = s1 / n
    return n, m + shift, s2 - n * m * m, n_up


@numba.njit(inline="always")
def _pair_kept(av, bv, i, lo_a, hi_a, lo_b, hi_b, lo_d, hi_d, clip_on, limit, f32_total, upper_on):  # pragma: no cover
    """Whether photosite ``i`` of a pair is kept (clip bounds) and whether it is censored."""
    x = np.float64(av[i])
    y = np.float64(bv[i])
    d = x - y
    k = (lo_a <= x) & (x <= hi_a) & (lo_b <= y) & (y <= hi_b) & (lo_d <= d) & (d <= hi_d) if clip_on else True
    if f32_total:
        tot = np.float32(av[i]) + np.float32(bv[i])
    else:
        tot = np.float32(np.float64(np.float32(av[i])) + y)
    return k, upper_on & (tot >= limit)


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def pair_fused(a, b, lo_a, hi_a, lo_b, hi_b, lo_d, hi_d, clip_on, limit, f32_total, upper_on):  # pragma: no cover
    """The clip of a pair (a, b and a - b within their bounds), the pair-mean censoring (float32
    total a + b >= ``limit``, a float32 value; as numpy's ``total = a.astype(float32); total +=
    b``, added in float32 when ``f32_total`` (b's type promotes to float32), else in float64 and
    rounded) and the moments of c = a - b - (mean a - mean b) over the kept photosites, in two
    passes without a mask: n, mean a, mean b, mean c^2, mean c^4 and the kept photosites
    censored (``upper_on``). The sums of raw values are exact for integer frames (whatever their
    order)."""
    av = a.ravel()
    bv = b.ravel()
    n = 0
    n_cens = 0
    sa = 0.0
    sb = 0.0
    a0 = np.float64(av[0])
    b0 = np.float64(bv[0])
    for i in range(av.size):
        k, cens = _pair_kept(av, bv, i, lo_a, hi_a, lo_b, hi_b, lo_d, hi_d, clip_on, limit, f32_total, upper_on)
        n_cens += k & cens
        k = k & ~cens
        n += k
        sa += np.float64(av[i]) - a0 if k else 0.0
        sb += np.float64(bv[i]) - b0 if k else 0.0
    if n == 0:
        return 0, 0.0, 0.0, 0.0, 0.0, n_cens
    mu_a = sa / n + a0
    mu_b = sb / n + b0
    delta = mu_a - mu_b
    s2 = 0.0
    s4 = 0.0
    for i in range(av.size):
        k, cens = _pair_kept(av, bv, i, lo_a, hi_a, lo_b, hi_b, lo_d, hi_d, clip_on, limit, f32_total, upper_on)
        c = np.float64(av[i]) - np.float64(bv[i]) - delta if k & ~cens else 0.0
        c2 = c * c
        s2 += c2
        s4 += c2 * c2
    return n, mu_a, mu_b, s2 / n, s4 / n, n_cens


@numba.njit(cache=True, nogil=True)
def series_add(data, w32, wt32, w, sy, sty, syy):  # pragma: no cover - compiled
    """The dark series' sums of one master dark, as numpy computed them (``sy += w * m``,
    ``sty += (w t) * m`` with the products in float32 for a float32 master, ``syy += w m^2``
    in float64), in one pass without temporaries."""
    m_ = data.ravel()
    y_, ty_, yy_ = sy.ravel(), sty.ravel(), syy.ravel()
    for i in range(m_.size):
        m = m_[i]
        y_[i] += w32 * m
        ty_[i] += wt32 * m
        m64 = np.float64(m)
        yy_[i] += w * (m64 * m64)


@numba.njit(cache=True, nogil=True)
def response_defect_bits(
    prnu, prnu_stderr, has_err, prnu_std2, bias_map, has_bias, mu_R, bias_sd, limits, bits, out
):  # pragma: no cover - compiled
    """The dead, stuck and weak bits (``bits``) of :func:`~.defects.response_defects` into
    ``out`` (uint8), per photosite in float64 as the numpy expressions there; ``limits``: the
    dead response, weak deviation, weak sigma and stuck sigma thresholds."""
    dead, weak_dev, weak_sigma, stuck_sigma = limits[0], limits[1], limits[2], limits[3]
    a_, e_, b_, o_ = prnu.ravel(), prnu_stderr.ravel(), bias_map.ravel(), out.ravel()
    for i in range(a_.size):
        a = np.float64(a_[i])
        spread2 = prnu_std2
        if has_err:
            e = np.float64(e_[i])
            spread2 = prnu_std2 + e * e
        weak_limit = 1.0 - _nanmax(weak_dev, weak_sigma * np.sqrt(spread2))
        no_response = a < dead
        stuck = has_bias and no_response and abs(np.float64(b_[i]) - mu_R) > stuck_sigma * bias_sd
        f = 0
        if no_response and not stuck:
            f |= bits[0]
        if stuck:
            f |= bits[1]
        if not no_response and a < weak_limit:
            f |= bits[2]
        o_[i] = f


@numba.njit(cache=True, nogil=True)
def hot_mask(raw, raw_stderr, D, dcnu2, hot_sigma, out):  # pragma: no cover - compiled
    """``out`` = raw - D > hot_sigma sqrt(dcnu2 + raw_stderr^2), per photosite in float64."""
    r_, e_, o_ = raw.ravel(), raw_stderr.ravel(), out.ravel()
    for i in range(r_.size):
        e = np.float64(e_[i])
        o_[i] = np.float64(r_[i]) - D > hot_sigma * np.sqrt(dcnu2 + e * e)


# --------------------------------------------------------------------------- exact medians
#: Bits of the order-preserving key that pick a histogram bin of :func:`median_f32` (the top 20
#: of 64: sign, exponent and 8 mantissa bits, 256 bins per octave).
_SEL_SHIFT = 44


@numba.njit(cache=True)
def _sel_value(v, centre, absdev):  # pragma: no cover - compiled
    """The float64 value whose median is taken: v, or |v - centre| with ``absdev``."""
    x = np.float64(v)
    return abs(x - centre) if absdev else x


@numba.njit(cache=True)
def _sel_key(x):  # pragma: no cover - compiled
    """An unsigned integer in the order of the float64 ``x`` (negative values bit-inverted)."""
    b = np.float64(x).view(np.uint64)
    return ~b if b >> np.uint64(63) else b | (np.uint64(1) << np.uint64(63))


@numba.njit(cache=True, nogil=True)
def median_f32(data, centre, absdev):  # pragma: no cover - compiled
    """The median of the float64 values of ``data`` (or of |data - centre| with ``absdev``),
    as ``numpy.median`` of those values computes it (the middle value, or 0 + the two middle
    values over 2; NaN when any value is NaN), without a float64 copy: one pass into a
    histogram of the values' top key bits, a second one gathering the values of the bins that
    hold the middle ranks, which are sorted."""
    v = data.ravel()
    n = v.size
    hist = np.zeros(1 << (64 - _SEL_SHIFT), np.int64)
    shift = np.uint64(_SEL_SHIFT)
    for i in range(n):
        x = _sel_value(v[i], centre, absdev)
        if x != x:
            return np.nan
        hist[_sel_key(x) >> shift] += 1
    k_hi = n // 2
    k_lo = k_hi - 1 if n % 2 == 0 else k_hi
    below = 0  # values in the bins before b_lo
    b_lo = 0
    while below + hist[b_lo] <= k_lo:
        below += hist[b_lo]
        b_lo += 1
    b_hi = b_lo
    upto = below + hist[b_lo]
    while upto <= k_hi:
        b_hi += 1
        upto += hist[b_hi]
    cand = np.empty(upto - below, np.float64)
    m = 0
    lo = np.uint64(b_lo)
    hi = np.uint64(b_hi)
    for i in range(n):
        x = _sel_value(v[i], centre, absdev)
        b = _sel_key(x) >> shift
        if b >= lo and b <= hi:
            cand[m] = x
            m += 1
    cand.sort()
    if n % 2 == 1:
        return cand[k_hi - below]
    return (0.0 + cand[k_lo - below] + cand[k_hi - below]) / 2.0
