"""Effective exposure times: each frame's actual exposure ratio, estimated from the bracket itself.

Real shutters deviate from their nominal times by a few percent (and nominal third stops are
rounded: 1/125 s is not 2^-7 s). Every exposure then carries a multiplicative bias of x_i
(Eq. 6), a step wherever the dominant exposure changes, far outside the stated sigma at high
SNR. The paper normalises its reference images for this reason (Sec. 7: "we normalized the
images such that the spatial average is constant for every sample of each exposure time").
This module generalises that normalisation to a bracket of different times:

* for every pair of frames (i, j), the photosites well exposed in both (signal above
  ``min_snr`` standard deviations, below ``max_level`` of the range above the dark level,
  no defect) give q = s_j / s_i, s = v - b the dark-corrected signal (DN); the PRNU gain, the
  gain g and the irradiance cancel, so q = t_j^eff / t_i^eff up to noise. "Well exposed" is
  judged on the pair's inverse-variance weighted rate (the merge's Eq. 12 estimate of the two),
  whose noise is uncorrelated with that of log q: a selection on either observed signal would
  bias q (cutting s_j at the top and s_i at the bottom keeps the photosites whose q fluctuated
  low: -0.35 % per factor 8 in time on camera-R);
* log q is averaged with inverse-variance weights (Var(v - b) of Eq. 3, 5 at the observed
  signal, delta method), corrected for the second-order bias of the logarithm and made robust by
  iterative clipping at ``clip_sigmas`` standard deviations;
* the pair estimates d_ij = log(t_j^eff / t_i^eff) are combined by weighted least squares into
  one log correction l_i per frame (t_i^eff = t_i exp(l_i)), normalised so that the corrections
  of each connected set of frames average to 0 (the nominal times are right on average: a
  bracket alone cannot tell the absolute scale, which is the calibration's).

Frames that share no well-exposed photosites with any other keep their nominal time
(``estimated`` False). Units: times in s, signals in DN, g in DN/e-, sigma2_R in DN^2.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hdrcap.pipeline.errors import InputError

__all__ = [
    "RatioOptions",
    "ExposureRatios",
    "estimate_exposure_ratios",
    "subsample_window",
    "EXPOSURE_TIME_MODES",
]

#: Values of the merge option ``exposure_times``: estimated effective times, or the nominal ones.
EXPOSURE_TIME_MODES = ("effective", "nominal")


@dataclass(frozen=True)
class RatioOptions:
    """Settings of the ratio estimate.

    Attributes
    ----------
    min_snr : float
        Least signal-to-noise ratio of a photosite in both frames of a pair (dimensionless).
    max_level : float
        Largest signal as a fraction of the range above the dark level, v_sat - b (keeps clear
        of saturation and of the non-linearity near full well; EMVA 1288 uses 70 %).
    clip_sigmas : float
        Robust clipping of the per-photosite log ratios, in their standard deviations.
    min_photosites : int
        Least number of photosites for a pair to count.
    """

    min_snr: float = 20.0
    max_level: float = 0.7
    clip_sigmas: float = 5.0
    min_photosites: int = 50

    def __post_init__(self) -> None:
        if not (self.min_snr > 0 and 0 < self.max_level <= 1 and self.clip_sigmas > 0 and self.min_photosites >= 2):
            raise InputError("ratio options: min_snr > 0, 0 < max_level <= 1, clip_sigmas > 0, min_photosites >= 2")


@dataclass(frozen=True)
class ExposureRatios:
    """Effective exposure times of a bracket.

    Attributes
    ----------
    nominal, effective : tuple of float
        Exposure times, s, in the frames' order.
    factors : tuple of float
        effective / nominal (1 where not estimated).
    stderr : tuple of float
        Standard error of each factor (relative, dimensionless; 0 where not estimated).
    estimated : tuple of bool
        Whether the frame shared well-exposed photosites with another frame.
    pairs : int
        Frame pairs used.
    covariance : numpy.ndarray or None
        Covariance of the log corrections log(factor) (n x n, dimensionless; rows and columns
        of frames not estimated are 0), under the constraint that each connected set of frames
        averages to 0; ``stderr`` is the square root of its diagonal.
    linked_set : tuple of int
        Per frame, the index of its connected set of frames (linked by pairs, each set's
        corrections averaging to 0), -1 for a frame not estimated; empty when not computed.
    """

    nominal: tuple[float, ...]
    effective: tuple[float, ...]
    factors: tuple[float, ...]
    stderr: tuple[float, ...]
    estimated: tuple[bool, ...]
    pairs: int
    covariance: np.ndarray | None = field(default=None, repr=False, compare=False)
    linked_set: tuple[int, ...] = ()

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return {
            "nominal": list(self.nominal),
            "effective": list(self.effective),
            "factors": list(self.factors),
            "stderr": list(self.stderr),
            "estimated": list(self.estimated),
            "pairs": self.pairs,
        }


def subsample_window(shape: tuple[int, int], max_photosites: int = 250_000) -> tuple[slice, slice]:
    """A regular grid of at most about ``max_photosites`` photosites of a mosaic of ``shape``
    (rows, columns), both CFA phases of each axis kept (an odd step): what the ratio estimate
    needs, at a fraction of the cost on large frames.

    Parameters
    ----------
    shape : (int, int)
        Mosaic size, photosites.
    max_photosites : int
        Target number of photosites.

    Returns
    -------
    (slice, slice)
        Row and column slices.
    """
    h, w = shape
    step = max(1, int(math.ceil(math.sqrt(h * w / max_photosites))))
    step += 1 - step % 2
    return slice(0, h, step), slice(0, w, step)


def _pair_rate(si, vi, ti, sj, vj, tj):
    """The inverse-variance weighted rate of two frames' signals, DN/s (Eq. 12 for two)."""
    wi, wj = ti * ti / vi, tj * tj / vj
    return (wi * si / ti + wj * sj / tj) / (wi + wj)


def _pair_log_ratio(si, vi, pi, sj, vj, pj, ok, clip):
    """Robust weighted mean of log(s_j / s_i) over ``ok`` (Eq. 3, 5 variances ``vi``, ``vj`` of
    the signals at their predicted values ``pi``, ``pj``, DN^2): (estimate, standard error,
    photosites kept) or None."""
    ri = vi[ok] / (pi[ok] * pi[ok])  # relative variances
    rj = vj[ok] / (pj[ok] * pj[ok])
    # E[log s] = log mu - Var/(2 mu^2) to second order: add the half relative variances back
    lq = (np.log(sj[ok]) + 0.5 * rj) - (np.log(si[ok]) + 0.5 * ri)
    var = ri + rj
    w = 1.0 / var
    keep = np.ones(lq.shape, bool)
    m = float(np.median(lq))
    for _ in range(5):
        r = (lq - m) / np.sqrt(var)
        new = np.abs(r) < clip
        if new.sum() < 2:
            return None
        m = float(np.sum(w[new] * lq[new]) / np.sum(w[new]))
        if np.array_equal(new, keep):
            break
        keep = new
    n = int(keep.sum())
    chi2 = float(np.sum(w[keep] * (lq[keep] - m) ** 2)) / max(n - 1, 1)
    se = math.sqrt(max(chi2, 1.0) / float(np.sum(w[keep])))
    return m, se, n


def _components(n, edges):
    """Connected sets of frames (lists of indices) linked by the pairs ``edges``."""
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j in edges:
        parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return list(groups.values())


def estimate_exposure_ratios(
    values: Sequence[np.ndarray],
    dark_levels: Sequence[np.ndarray | float],
    times: Sequence[float],
    g: float,
    sigma2_R: float,
    v_sat: float,
    *,
    dark_factors: Sequence[float] | None = None,
    exclude: np.ndarray | None = None,
    options: RatioOptions = RatioOptions(),
) -> ExposureRatios:
    """Each frame's effective exposure time from the bracket (module docstring; Sec. 7).

    Parameters
    ----------
    values : sequence of 2-D arrays
        Raw values of the frames (or of one subsample of photosites common to all), DN.
    dark_levels : sequence of arrays or floats
        Each frame's dark level b_i on the same photosites, DN.
    times : sequence of float
        Nominal exposure times, s (> 0).
    g : float
        Gain, DN/e- (> 0).
    sigma2_R : float
        Readout variance, DN^2 (> 0).
    v_sat : float
        Saturation limit, DN.
    dark_factors : sequence of float, optional
        The dark-level variance factor k of each frame (1 matched, 1/N master, 0 model;
        default 1).
    exclude : 2-D bool array, optional
        Photosites never to use (defects).
    options : RatioOptions

    Returns
    -------
    ExposureRatios
    """
    n = len(values)
    times = [float(t) for t in times]
    if len(times) != n or len(dark_levels) != n or n == 0:
        raise InputError(f"{n} frames, {len(times)} exposure times and {len(dark_levels)} dark levels differ")
    if not (g > 0 and sigma2_R > 0) or any(not (t > 0 and math.isfinite(t)) for t in times):
        raise InputError("exposure ratios need g > 0, sigma2_R > 0 and exposure times > 0")
    ks = [1.0] * n if dark_factors is None else [float(k) for k in dark_factors]
    sig, var, good, room = [], [], [], []
    for v, b, k in zip(values, dark_levels, ks):
        v = np.asarray(v, np.float64)
        b = np.broadcast_to(np.asarray(b, np.float64), v.shape)
        s = v - b
        vs = g * np.maximum(s, 0.0) + sigma2_R * (1.0 + k)  # Var(v - b) at the observed signal (Eq. 3, 5)
        ok = (v < v_sat) & (s > 0) & np.isfinite(s)
        if exclude is not None:
            ok &= ~np.asarray(exclude, bool)
        sig.append(s.ravel())
        var.append(vs.ravel())
        good.append(ok.ravel())
        room.append((options.max_level * (v_sat - b)).ravel())
    rows, ys, ws, edges = [], [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            # the pair's photosites usable in both frames, in their order: every value below is
            # computed elementwise, so on these alone (a fraction of the subsample) it is the same
            take = np.flatnonzero(good[i] & good[j])
            if take.size < options.min_photosites:
                continue
            si, sj = sig[i][take], sig[j][take]
            # the pair's weighted rate (DN/s), its noise uncorrelated with that of log(s_j / s_i);
            # the variances at the signals it predicts (weights from the observed signals would
            # favour the photosites whose s_i fluctuated high: q biased low)
            rate = _pair_rate(si, var[i][take], times[i], sj, var[j][take], times[j])
            vi = g * np.maximum(rate * times[i], 0.0) + sigma2_R * (1.0 + ks[i])
            vj = g * np.maximum(rate * times[j], 0.0) + sigma2_R * (1.0 + ks[j])
            rate = _pair_rate(si, vi, times[i], sj, vj, times[j])
            pi, pj = rate * times[i], rate * times[j]
            vi = g * np.maximum(pi, 0.0) + sigma2_R * (1.0 + ks[i])
            vj = g * np.maximum(pj, 0.0) + sigma2_R * (1.0 + ks[j])
            lo, hi = (i, j) if times[i] <= times[j] else (j, i)
            p_lo, v_lo = (pi, vi) if lo == i else (pj, vj)
            both = ((pj if hi == j else pi) <= room[hi][take]) & (p_lo * p_lo >= options.min_snr**2 * v_lo) & (p_lo > 0)
            if both.sum() < options.min_photosites:
                continue
            est = _pair_log_ratio(si, vi, pi, sj, vj, pj, both, options.clip_sigmas)
            if est is None or est[2] < options.min_photosites:
                continue
            m, se, _ = est
            rows.append((i, j))
            ys.append(m - math.log(times[j] / times[i]))  # l_j - l_i
            ws.append(1.0 / (se * se))
            edges.append((i, j))
    logs = np.zeros(n)
    errs = np.zeros(n)
    cov = np.zeros((n, n))
    estimated = [False] * n
    linked = [-1] * n
    if rows:
        A = np.zeros((len(rows), n))
        for r, (i, j) in enumerate(rows):
            A[r, i], A[r, j] = -1.0, 1.0
        W = np.asarray(ws)
        y = np.asarray(ys)
        comps = [c for c in _components(n, edges) if len(c) > 1]
        C = np.zeros((len(comps), n))
        for r, c in enumerate(comps):
            C[r, c] = 1.0 / len(c)  # the corrections of each connected set average to 0
            for i in c:
                estimated[i] = True
                linked[i] = r
        # weighted least squares with the constraints (KKT system), unused frames pinned at 0
        free = np.asarray(estimated)
        N = A.T @ (W[:, None] * A) + np.diag(~free * 1.0)
        K = np.block([[N, C.T], [C, np.zeros((len(comps), len(comps)))]])
        rhs = np.concatenate([A.T @ (W * y), np.zeros(len(comps))])
        Kinv = np.linalg.pinv(K)
        sol = Kinv @ rhs
        logs = np.where(free, sol[:n], 0.0)
        cov = np.where(free[:, None] & free[None, :], Kinv[:n, :n], 0.0)
        errs = np.sqrt(np.maximum(np.diag(cov), 0.0))
    factors = np.exp(logs)
    return ExposureRatios(
        nominal=tuple(times),
        effective=tuple(float(t * f) for t, f in zip(times, factors)),
        factors=tuple(float(f) for f in factors),
        stderr=tuple(float(e) for e in errs),
        estimated=tuple(estimated),
        pairs=len(rows),
        covariance=cov,
        linked_set=tuple(linked),
    )
