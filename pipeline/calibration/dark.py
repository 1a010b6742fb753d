"""Dark frames: master darks per exposure time and the dark current (Eq. 7 averaged).

Master darks are the clipped per-photosite means of N dark frames at one exposure time
(streamed one time after the other); the dark current D comes from a straight-line fit of
their levels against the exposure time (>= 6 times), the per-photosite dark-current map from
the same fit at every photosite, with its standard error, shrunk toward D by empirical Bayes
(:func:`shrink_dark_current_map`). Units: DN, DN/s, s, e-/s.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from hdrcap.pipeline.calibration import _kernels as _k
from hdrcap.pipeline.calibration.frames import check_shape, frame_data, frame_name, group_by_exposure
from hdrcap.pipeline.calibration.stats import PixelStack, robust_mean_std
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.times import find_exposure, unique_exposures

__all__ = [
    "MasterDark",
    "DarkFit",
    "fit_dark_current",
    "stream_master_darks",
    "DarkSeries",
    "DarkCurrentMap",
    "shrink_dark_current_map",
]


@dataclass(frozen=True)
class MasterDark:
    """A master dark: the clipped per-photosite mean of N dark frames at one exposure time.

    Attributes
    ----------
    data : numpy.ndarray (float32)
        Mean dark frame, DN (bias included).
    n_frames : int
        N, the number of frames averaged (the merge's dark variance is divided by it).
    exposure_time : float
        Seconds.
    level, level_stderr : float
        Clipped spatial mean and its temporal standard error, DN.
    """

    data: np.ndarray
    n_frames: int
    exposure_time: float
    level: float
    level_stderr: float


@dataclass(frozen=True)
class DarkFit:
    """Dark current from a dark series (Eq. 7 averaged): level(t) = b0 + g D t.

    Attributes
    ----------
    slope, slope_stderr : float
        DN per second.
    intercept : float
        DN.
    times, levels : numpy.ndarray
        The series, s and DN.
    """

    slope: float
    slope_stderr: float
    intercept: float
    times: np.ndarray
    levels: np.ndarray


def fit_dark_current(
    times: Sequence[float] | np.ndarray,
    levels: Sequence[float] | np.ndarray,
    level_stderr: Sequence[float] | np.ndarray | None = None,
) -> DarkFit:
    """Straight-line fit of master-dark levels against exposure time (>= 6 times).

    Weighted least squares when ``level_stderr`` is given; the slope's standard error is the
    larger of the propagated one and the one from the residuals.

    Parameters
    ----------
    times : array_like
        Exposure times, s.
    levels : array_like
        Master-dark levels, DN.
    level_stderr : array_like, optional
        Standard error of each level, DN.

    Returns
    -------
    DarkFit
        Slope g D (DN/s), its standard error and the intercept (DN).

    Raises
    ------
    ValueError
        Fewer than six distinct exposure times.
    """
    t = np.asarray(times, float)
    y = np.asarray(levels, float)
    n_times = len(unique_exposures(t))
    if n_times < 6:
        raise ValueError(f"dark current needs dark frames at >= 6 exposure times, got {n_times}")
    w = np.ones_like(t) if level_stderr is None else 1.0 / np.maximum(np.asarray(level_stderr, float), 1e-12) ** 2
    A = np.stack([np.ones_like(t), t], axis=1)
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    b0, slope = cov @ (A.T @ (w * y))
    resid = y - (b0 + slope * t)
    chi2 = float(np.sum(w * resid**2)) / max(t.size - 2, 1)
    se = float(np.sqrt(cov[1, 1] * max(chi2, 1.0 if level_stderr is not None else chi2)))
    return DarkFit(float(slope), se, float(b0), t, y)


def _master(stack: PixelStack, t: float, clip: float | None) -> MasterDark:
    """The master dark of a stack of dark frames at ``t`` seconds."""
    mean_map, err_map, _ = stack.result(clip)
    level, _sd, keep = robust_mean_std(mean_map, clip)
    if err_map is not None:
        np.square(err_map, out=err_map)  # in place (the map is not kept): one temporary, the kept values
        level_se = float(np.sqrt(np.mean(err_map[keep]) / keep.sum()))
    else:
        level_se = float("nan")
    return MasterDark(mean_map.astype(np.float32, copy=False), stack.n, float(t), float(level), level_se)


def stream_master_darks(darks: Iterable, clip: float | None, shape: tuple[int, ...] | None) -> Iterator[MasterDark]:
    """Master darks per exposure time, streamed one run of frames after the other.

    Parameters
    ----------
    darks : iterable of frames
        Dark frames ordered by exposure time (``data`` in DN, ``exposure_time`` in s).
    clip : float or None
        Sigma-clipping threshold, standard deviations; None disables outlier rejection.
    shape : tuple of int or None
        Size of the bias frames, which every dark must have (None: not checked).

    Returns
    -------
    iterator of MasterDark
        One per exposure time, in the order of the frames.

    Raises
    ------
    InputError
        Frames of another size, or frames of one exposure time that are not consecutive.
    """
    seen: list[float] = []
    idx = 0
    stack = None  # one stack for every exposure time (reset: its maps' memory is reused)
    for t, group in group_by_exposure(darks):
        if find_exposure(t, seen) is not None:
            name = frame_name(group[0], "dark", idx)
            raise InputError(f"{name}: dark frames at {t:g} s are not consecutive; order them by exposure time")
        seen.append(t)
        for k, fr in enumerate(group):
            data = frame_data(fr)
            check_shape(data, shape, frame_name(fr, "dark", idx), "the bias frames")
            if k == 0:
                if stack is not None and stack.shape == data.shape:
                    stack.reset()
                else:
                    stack = PixelStack(data.shape)
                current = stack  # this exposure time's stack (a group is never empty)
            current.add(data)
            idx += 1
        yield _master(current, t, clip)


@dataclass
class DarkSeries:
    """The master darks of a dark series, reduced as they arrive.

    Keeps each master's time (s), level and its error (DN) and frame count, and the
    frame-count weighted sums of the per-photosite straight-line fit (float64 maps), not the
    masters themselves.
    """

    times: list[float] = field(default_factory=list)
    levels: list[float] = field(default_factory=list)
    level_stderr: list[float] = field(default_factory=list)
    n_frames: list[int] = field(default_factory=list)
    _sy: np.ndarray | None = None
    _sty: np.ndarray | None = None
    _syy: np.ndarray | None = None
    _sn: float = 0.0
    _st: float = 0.0
    _stt: float = 0.0

    def add(self, master: MasterDark) -> None:
        """Add one master dark.

        Parameters
        ----------
        master : MasterDark
            The master dark (DN) at its exposure time (s).
        """
        self.times.append(master.exposure_time)
        self.levels.append(master.level)
        self.level_stderr.append(master.level_stderr)
        self.n_frames.append(master.n_frames)
        if self._sy is None:
            self._sy = np.zeros(master.data.shape, np.float64)
            self._sty = np.zeros(master.data.shape, np.float64)
            self._syy = np.zeros(master.data.shape, np.float64)
        w = float(master.n_frames)
        data = np.ascontiguousarray(master.data)
        # sy += w m, sty += (w t) m (products in the master's type, as numpy's), syy += w m^2
        _k.series_add(
            data, data.dtype.type(w), data.dtype.type(w * master.exposure_time), w, self._sy, self._sty, self._syy
        )
        self._sn += w
        self._st += w * master.exposure_time
        self._stt += w * master.exposure_time**2

    def _sums(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fit's sum maps sy, sty, syy (a series holds them from its first master on)."""
        if self._sy is None or self._sty is None or self._syy is None:
            raise ValueError("the dark series holds no master dark yet")
        return self._sy, self._sty, self._syy

    def n_times(self) -> int:
        """Distinct exposure times in the series.

        Returns
        -------
        int
        """
        return len(unique_exposures(self.times))

    def fit(self) -> DarkFit:
        """Dark current of the mean levels (:func:`fit_dark_current`, weighted by the levels'
        errors when every one is finite).

        Returns
        -------
        DarkFit
            Slope in DN/s.
        """
        se = None if any(not np.isfinite(x) for x in self.level_stderr) else self.level_stderr
        return fit_dark_current(self.times, self.levels, se)

    def slope_map(self, rows: slice = slice(None)) -> np.ndarray:
        """Per-photosite slope of the straight-line fit, DN/s (float32).

        Parameters
        ----------
        rows : slice
            Rows of the map to compute (default all; row blocks keep the float64 temporaries
            small).

        Returns
        -------
        numpy.ndarray
        """
        sy_map, sty_map, _ = self._sums()
        if rows == slice(None):  # row blocks: no full-size float64 temporaries
            out = np.empty(sy_map.shape, np.float32)
            for blk in _row_blocks(sy_map.shape):
                out[blk] = self.slope_map(blk)
            return out
        den = self._sn * self._stt - self._st * self._st
        return ((self._sn * sty_map[rows] - self._st * sy_map[rows]) / den).astype(np.float32)

    def residual_map(self, rows: slice = slice(None)) -> np.ndarray:
        """Per-photosite weighted residual sum of squares of the straight-line fit, DN^2
        (weights: the frame counts N_k), float64.

        Parameters
        ----------
        rows : slice
            Rows of the map to compute (default all).

        Returns
        -------
        numpy.ndarray
        """
        sy_map, sty_map, syy_map = self._sums()
        sy = sy_map[rows]
        syy_c = syy_map[rows] - sy**2 / self._sn
        sty_c = sty_map[rows] - self._st * sy / self._sn
        stt_c = self._stt - self._st**2 / self._sn
        return np.maximum(syy_c - sty_c**2 / stt_c, 0.0)

    def design(self) -> tuple[np.ndarray, np.ndarray]:
        """The series' exposure times (s) and frame counts N_k, float64.

        Returns
        -------
        times, weights : numpy.ndarray
        """
        return np.asarray(self.times, float), np.asarray(self.n_frames, float)

    def to_dict(self) -> dict[str, list]:
        """The series for the provenance and the report plots (times s, levels DN).

        Returns
        -------
        dict
        """
        return {
            "times": self.times,
            "levels": self.levels,
            "level_stderr": self.level_stderr,
            "n_frames": self.n_frames,
        }


@dataclass(frozen=True)
class DarkCurrentMap:
    """The per-photosite dark current, shrunk toward the scalar D, with its standard errors.

    Attributes
    ----------
    rate, stderr : numpy.ndarray (float32)
        Shrunk dark current D_j (>= 0) and its standard error, e-/s.
    raw, raw_stderr : numpy.ndarray (float32)
        The per-photosite regression slope divided by g, and its standard error, e-/s.
    prior_mean, prior_sd : float
        D and the spread of the dark current over normal photosites (DCNU) beyond the
        estimation noise, e-/s.
    outlier_fraction : float
        Prior probability of a photosite outside the normal population (hot photosites).
    chi2 : float
        Residual sum of squares of the per-photosite fits over its expectation under the model
        (the standard errors are inflated by its square root when above 1).
    """

    rate: np.ndarray
    stderr: np.ndarray
    raw: np.ndarray
    raw_stderr: np.ndarray
    prior_mean: float
    prior_sd: float
    outlier_fraction: float
    chi2: float


def _slope_variance_terms(times: np.ndarray, weights: np.ndarray) -> tuple[float, float, float, float]:
    """Var(slope) = A sigma2_R + B g s and E[RSS] = a sigma2_R + b g s of the weighted
    straight-line fit (weights N_k), when a master dark at t_k has the variance
    (sigma2_R + g s t_k) / N_k (Eq. 5 averaged over N_k frames, s the dark slope in DN/s)."""
    X = np.stack([np.ones_like(times), times], axis=1)
    W = np.diag(weights)
    L = np.linalg.solve(X.T @ W @ X, X.T @ W)  # coefficients: (b0, slope) = L y
    R = np.eye(times.size) - X @ L  # residuals: r = R y
    terms = []
    for v in (1.0 / weights, times / weights):
        V = np.diag(v)
        terms.append(float(L[1] @ V @ L[1]))
        terms.append(float(np.trace(W @ R @ V @ R.T)))
    return terms[0], terms[2], terms[1], terms[3]


#: Photosites per row block of the dark-current map's passes (float64 temporaries of ~4 MB).
_BLOCK = 1 << 19


def _row_blocks(shape: tuple[int, ...]) -> list[slice]:
    """Row slices of about :data:`_BLOCK` photosites covering a map of ``shape``."""
    rows = shape[0]
    step = max(1, _BLOCK // max(1, int(np.prod(shape[1:]))))
    return [slice(i, min(i + step, rows)) for i in range(0, rows, step)]


def _population_limits(slope: np.ndarray, clip: float = 5.0) -> tuple[float, float]:
    """The median of the raw map and ``clip`` robust standard deviations (1.4826 MAD; inf when
    the MAD is 0): a photosite belongs to the population when |raw - median| <= the second.
    ``slope`` is float32; the medians are those of its float64 values and of their float64
    absolute deviations, exactly as ``numpy.median`` of those values (selected in two passes
    each by :func:`._kernels.median_f32`, without a float64 copy)."""
    data = np.ascontiguousarray(slope)
    med = float(_k.median_f32(data, 0.0, False))
    mad = 1.4826 * float(_k.median_f32(data, med, True))
    return med, (np.inf if mad == 0 else clip * mad)


def shrink_dark_current_map(
    series: DarkSeries, g: float, sigma2_R: float, D: float, D_stderr: float, min_outlier_fraction: float = 1e-4
) -> DarkCurrentMap:
    """Per-photosite dark current with its standard error, shrunk toward D (empirical Bayes).

    The raw estimate is the per-photosite slope of the master-dark level against t (Eq. 7
    averaged) divided by g. Its standard error follows from the variance of each master dark,
    (sigma2_R + g^2 D_j t_k) / N_k (Eq. 5), propagated through the regression, and is inflated
    by sqrt(chi2) when the residuals scatter more than that. The prior is a two-component
    mixture: the normal population N(D, tau^2) (tau^2 = spread of the raw map minus the mean
    squared standard error, at least that difference's own standard error) and, with
    probability pi, a flat component over the range of the map (hot photosites). The result
    is the posterior mean, floored at 0: a normal photosite moves toward D by the factor
    se^2 / (tau^2 + se^2), a hot one keeps its regression value.

    The maps are computed in row blocks (passes for the population's sums, then the maps):
    memory holds the float32 results (the medians are selected without a float64 copy of the
    slope map), not float64 maps of every intermediate.

    Parameters
    ----------
    series : DarkSeries
        The master darks, >= 6 exposure times.
    g : float
        Gain, DN per electron.
    sigma2_R : float
        Readout variance, DN^2.
    D, D_stderr : float
        The scalar dark current and its standard error, e-/s (the prior's centre).
    min_outlier_fraction : float
        Lower bound of pi.

    Returns
    -------
    DarkCurrentMap
        Maps in e-/s (float32) and the prior's parameters.
    """
    slope32 = series.slope_map()  # DN/s
    blocks = _row_blocks(slope32.shape)
    times, weights = series.design()
    A, B, a, b = _slope_variance_terms(times, weights)
    med, limit = _population_limits(slope32)

    def block(rows):
        slope = slope32[rows].astype(np.float64)
        s_pos = np.maximum(slope, 0.0)
        return slope, s_pos, np.abs(slope - med) <= limit

    # pass 1: chi2 of the population's fits
    rss_sum = exp_sum = 0.0
    for rows in blocks:
        slope, s_pos, pop = block(rows)
        rss_sum += float(np.sum(series.residual_map(rows)[pop]))
        exp_sum += float(np.sum((a * sigma2_R + b * g * s_pos)[pop]))
    chi2 = rss_sum / exp_sum
    inflate = max(chi2, 1.0)

    def raw_se(s_pos):
        return np.sqrt(inflate * (A * sigma2_R + B * g * s_pos)) / g

    # pass 2: the population's size, mean raw value and mean squared error; the map's range
    n_pop = 0
    raw_pop_sum = se2_pop_sum = se2_sum = 0.0
    raw_min, raw_max = np.inf, -np.inf
    for rows in blocks:
        slope, s_pos, pop = block(rows)
        raw = slope / g
        se2 = raw_se(s_pos) ** 2
        n_pop += int(np.count_nonzero(pop))
        raw_pop_sum += float(np.sum(raw[pop]))
        se2_pop_sum += float(np.sum(se2[pop]))
        se2_sum += float(np.sum(se2))
        raw_min, raw_max = min(raw_min, float(raw.min())), max(raw_max, float(raw.max()))
    raw_pop_mean = raw_pop_sum / max(n_pop, 1)
    # pass 3: the population's variance about its mean (two passes, as numpy's var)
    dev2 = 0.0
    for rows in blocks:
        slope, _s_pos, pop = block(rows)
        dev2 += float(np.sum(np.square(slope[pop] / g - raw_pop_mean)))
    size = slope32.size
    # tau^2 by the method of moments, floored at its own standard error so that an unresolved
    # DCNU is not taken as none (which would state the shrunk map too precise)
    mean_var = se2_pop_sum / max(n_pop, 1)
    tau2 = max(dev2 / max(n_pop, 1) - mean_var, np.sqrt(2.0 / max(n_pop, 1)) * mean_var)
    pi = max(1.0 - n_pop / size, min_outlier_fraction)
    # posterior probability of the normal population (densities in 1/(e-/s))
    span = max(raw_max - raw_min, 10.0 * float(np.sqrt(tau2 + se2_sum / size)))
    out = {k: np.empty(slope32.shape, np.float32) for k in ("rate", "stderr", "raw", "raw_se")}
    for rows in blocks:  # pass 4: the maps
        slope, s_pos, _pop = block(rows)
        raw = slope / g
        se = raw_se(s_pos)
        se2 = se**2
        var_pop = tau2 + se2
        dens = np.exp(-0.5 * (raw - D) ** 2 / var_pop) / np.sqrt(2 * np.pi * var_pop)
        p_pop = (1 - pi) * dens / ((1 - pi) * dens + pi / span)
        shrink = se2 / var_pop  # B_j, the weight of the prior mean
        m_pop = raw - shrink * (raw - D)
        v_pop = tau2 * se2 / var_pop + (shrink * D_stderr) ** 2
        rate = p_pop * m_pop + (1 - p_pop) * raw
        var = p_pop * (v_pop + (m_pop - rate) ** 2) + (1 - p_pop) * (se2 + (raw - rate) ** 2)
        out["rate"][rows] = np.maximum(rate, 0.0)
        out["stderr"][rows] = np.sqrt(var)
        out["raw"][rows] = raw
        out["raw_se"][rows] = se
    return DarkCurrentMap(
        out["rate"], out["stderr"], out["raw"], out["raw_se"], float(D), float(np.sqrt(tau2)), float(pi), chi2
    )
