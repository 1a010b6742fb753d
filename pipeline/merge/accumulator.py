"""The optimal HDR merge: iterative maximum likelihood with uncertainty (Sec. 4-5, Fig. 3).

For every photosite, from N exposures (v_i, b_i, t_i):

* x_i = (v_i - b_i) / (t_i g a) (Eq. 6), b_i the dark level of the chosen strategy;
* usable samples: v_i < v_sat (Eq. 11), and, once an estimate exists, the raw value
  predicted from it lies more than ``saturation_sigmas`` of its own standard deviation below
  v_sat (where the full well clips before the ADC, saturated samples slip under v_sat on read
  noise; each one would be a gross error);
* weights w_i = 1/Var(x_i) from the calibrated model at max(mu, 0) (Eq. 13, variance from
  :func:`pipeline.noise.variance_core`, the single place it is written), estimate
  mu = sum w x / sum w and sigma^2 = 1/sum w (Eq. 12), iterated from the non-saturated
  average until the change is below ``tolerance`` times max(|mu|, sigma) (Fig. 3). The estimate
  is never clipped (dark photosites may be negative);
* optionally the full saturation model (Eq. 8-10) as a censored (Tobit) likelihood: saturated
  samples contribute their survival probability; maximised by safeguarded Newton steps;
* photosites with no usable sample: ``nexp = 0``, ``sigma = 0`` and a lower bound;
* defective photosites (the calibration's ``defect_map``): ``nexp = 0``, ``sigma = 0``, and
  the reason in the ``quality`` bit field (:data:`pipeline.schema.QUALITY_BITS`), never a confident value;
* masked samples (a per-frame mask: impossible raw values the reader masked): no sample of
  that frame, like a saturated one, but never called saturated; the photosite is estimated
  from the other frames and carries the ``masked`` quality bit (masked in every frame:
  ``nexp = 0``, irradiance and sigma 0).

Dark strategies (each with its own variance term, see :mod:`pipeline.noise`): ``matched``
(one dark frame per exposure), ``master`` (per-exposure master darks, or one master dark,
averaged from ``n_dark`` frames), ``model`` (bias level plus calibrated dark current).

The work is done by the compiled kernels of :mod:`pipeline.merge.kernels`. :class:`MergeAccumulator`
takes frames one by one as they are captured (first pass) and finishes with the iterations;
:func:`merge_arrays` and :func:`merge_frames` use it, so streaming and batch results agree.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.exposure_ratio import (
    EXPOSURE_TIME_MODES,
    ExposureRatios,
    estimate_exposure_ratios,
    subsample_window,
)
from hdrcap.pipeline.io.raw import RawFrame, check_exposure_time, check_frames
from hdrcap.pipeline.merge.darks import DarkResolver, default_strategy
from hdrcap.pipeline.noise import DarkStrategy, dark_factor
from hdrcap.pipeline.params import DEFECT_BITS, Calibration
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import QUALITY_BITS
from hdrcap.pipeline.times import same_exposure

__all__ = [
    "MergeOptions",
    "MergeAccumulator",
    "merge_arrays",
    "merge_frames",
    "as_strategy",
    "quality_channel",
]


_SATURATION_MODELS = ("threshold", "probabilistic")
_PRNU_MODES = ("map", "scalar")


def as_strategy(value: DarkStrategy | str | None) -> DarkStrategy | None:
    """A dark strategy from its name (None stays None).

    Parameters
    ----------
    value : DarkStrategy, str or None
        ``"matched"``, ``"master"`` or ``"model"``.

    Returns
    -------
    DarkStrategy or None

    Raises
    ------
    InputError
        Any other value.
    """
    if value is None:
        return None
    try:
        return DarkStrategy(value)
    except ValueError:
        raise InputError(f"dark strategy must be matched, master or model, got {value!r}") from None


@dataclass(frozen=True)
class MergeOptions:
    """Options of the optimal merge; the defaults are the recommended setting.

    Attributes
    ----------
    iterations : int
        Maximum number of re-weighting steps per photosite (>= 1; the near-saturation rule
        needs >= 2). Dimensionless.
    tolerance : float
        Stop when |mu_new - mu| <= tolerance * max(|mu_new|, sigma). Relative, >= 0.
    saturation : {"threshold", "probabilistic"}
        Eq. 11 (plus the near-saturation rule) or the censored (Tobit) likelihood of Eq. 8-10.
    saturation_sigmas : float
        Margin of the near-saturation rule, in standard deviations of the raw value (0 turns
        the rule off).
    prnu : {"map", "scalar"}
        Use the calibration's per-photosite gain map a_j, or a = 1.
    dark_strategy : {"matched", "master", "model"} or None
        None: ``matched`` when dark frames are given, ``master`` with a master dark,
        ``model`` otherwise.
    n_dark : float
        Frames averaged into each master dark (``master`` only).
    master_dark_time : float or None
        Exposure time (s) of a single master dark; the dark current over the difference to
        each exposure time is added from the calibration. None: the master dark is used as is.
    exposure_times : {"nominal", "effective"}
        ``effective``: each frame's actual exposure time replaces the nominal one: first the
        calibration's shutter table (``Calibration.shutter``, per nominal time, as each frame
        is added), then the bracket's own estimate (:mod:`pipeline.exposure_ratio`, Sec. 7)
        refines the ratios of the frames that share well-exposed photosites, before the
        iterations (:func:`merge_frames`, the file merge and the capture session default to
        it); ``nominal``: the times as given, neither correction (the default of the
        array-level API).
    """

    iterations: int = 20
    tolerance: float = 1e-6
    saturation: str = "threshold"
    saturation_sigmas: float = 3.0
    prnu: str = "map"
    dark_strategy: DarkStrategy | None = None
    n_dark: float = 1
    master_dark_time: float | None = None
    exposure_times: str = "nominal"

    def __post_init__(self) -> None:
        if not isinstance(self.iterations, (int, np.integer)) or self.iterations < 1:
            raise InputError(f"iterations must be an integer >= 1, got {self.iterations!r}")
        if not (np.isfinite(self.tolerance) and self.tolerance >= 0):
            raise InputError(f"tolerance must be finite and >= 0, got {self.tolerance!r}")
        if self.saturation not in _SATURATION_MODELS:
            raise InputError(f"saturation must be one of {', '.join(_SATURATION_MODELS)}, got {self.saturation!r}")
        if not (np.isfinite(self.saturation_sigmas) and self.saturation_sigmas >= 0):
            raise InputError(f"saturation_sigmas must be finite and >= 0, got {self.saturation_sigmas!r}")
        if self.prnu not in _PRNU_MODES:
            raise InputError(f"prnu must be one of {', '.join(_PRNU_MODES)}, got {self.prnu!r}")
        object.__setattr__(self, "dark_strategy", as_strategy(self.dark_strategy))
        if not (np.isfinite(self.n_dark) and self.n_dark >= 1):
            raise InputError(f"n_dark (frames in the master dark) must be >= 1, got {self.n_dark!r}")
        if self.master_dark_time is not None and not (
            np.isfinite(self.master_dark_time) and self.master_dark_time >= 0
        ):
            raise InputError(f"master dark exposure time must be finite and >= 0, got {self.master_dark_time!r}")
        if self.exposure_times not in EXPOSURE_TIME_MODES:
            raise InputError(f"exposure_times must be effective or nominal, got {self.exposure_times!r}")

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON-ready data (the dark strategy by its name)."""
        out = dataclasses.asdict(self)
        out["dark_strategy"] = None if self.dark_strategy is None else self.dark_strategy.value
        return out


def quality_channel(nexp: np.ndarray, defect_map: np.ndarray | None) -> np.ndarray:
    """The per-photosite quality bit field (:data:`pipeline.schema.QUALITY_BITS`).

    Parameters
    ----------
    nexp : numpy.ndarray
        Unsaturated exposures used per photosite, as the iterations left it (0: saturated in
        every exposure, or no usable sample).
    defect_map : numpy.ndarray or None
        The calibration's defect bits (uint8, :data:`pipeline.params.DEFECT_BITS`), or None.

    Returns
    -------
    numpy.ndarray
        uint8, the shape of ``nexp``: defect bits | 16 where ``nexp == 0``.
    """
    q = (nexp == 0).view(np.uint8)  # a new array of 0/1: scaled in place, no further copies
    q *= np.uint8(QUALITY_BITS["saturated"])
    if defect_map is not None:
        dm = np.asarray(defect_map)
        if dm.shape != q.shape:
            raise InputError(f"calibration defect map has shape {dm.shape}, the frames {q.shape}")
        q |= dm.astype(np.uint8) & np.uint8(sum(DEFECT_BITS.values()))
    return q


def _flag_defects(irr: np.ndarray, sig: np.ndarray, nexp: np.ndarray, defect_map) -> tuple[np.ndarray, int]:
    """Defective photosites are no measurement: ``nexp = 0`` and ``sigma = 0`` in place (the
    irradiance keeps the kernel's value, which must not be used); returns the quality channel
    (:func:`quality_channel`, from ``nexp`` before the change) and the number of defects."""
    quality = quality_channel(nexp, defect_map)
    if defect_map is None:  # no defect bits in the quality channel
        return quality, 0
    bad = (quality & np.uint8(sum(DEFECT_BITS.values()))) != 0
    nexp[bad] = 0
    sig[bad] = 0
    return quality, int(bad.sum())


def _as_frame(arr, shape, what) -> np.ndarray:
    """uint16 stays uint16 (no copy); everything else becomes float32 (DN)."""
    arr = np.asarray(arr)
    if arr.ndim != 2:
        raise InputError(f"{what}: expected a 2-D mosaic, got shape {arr.shape}")
    if shape is not None and arr.shape != tuple(shape):
        raise InputError(f"{what}: size {arr.shape[1]}x{arr.shape[0]} differs from {shape[1]}x{shape[0]}")
    if arr.dtype == np.uint16 or arr.dtype == np.float32:
        return np.ascontiguousarray(arr)
    if arr.dtype.kind not in "uif" and arr.dtype != np.bool_:
        raise InputError(f"{what}: pixel type {arr.dtype} is not numeric")
    return np.ascontiguousarray(arr, dtype=np.float32)


def _as_mask(mask, shape, what) -> np.ndarray | None:
    """A frame's mask as a bool array of ``shape``, or None when nothing is masked."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise InputError(f"{what}: mask has shape {m.shape}, the frames {tuple(shape)}")
    if m.dtype != np.bool_:
        raise InputError(f"{what}: mask must be boolean, got {m.dtype}")
    return m if m.any() else None


def _drop_masked(v: np.ndarray, mask: np.ndarray, v_sat: float, threshold: bool) -> np.ndarray:
    """The frame with its masked samples made no sample for the kernels (Eq. 11 drops them).

    With the threshold model a uint16 frame keeps its type: masked values at or above v_sat
    stay as they are (no copy), others become 65535 (the kernels drop values >= v_sat). The
    censored likelihood (Eq. 8-10) would read such a value as saturated, i.e. information: for
    it, and for float frames, a float32 copy with NaN (dropped by both models). The flags of the
    photosites this leaves without a sample are fixed after the kernels
    (:meth:`MergeAccumulator._flag_masked`).

    Parameters
    ----------
    v : numpy.ndarray
        uint16 or float32 mosaic, DN.
    mask : numpy.ndarray
        bool, True where the sample is masked.
    v_sat : float
        Saturation level, DN.
    threshold : bool
        The threshold saturation model (Eq. 11) is used.

    Returns
    -------
    numpy.ndarray
        ``v`` itself, or a copy with the masked samples replaced.
    """
    if threshold and v.dtype == np.uint16 and v_sat <= 65535:
        if np.all(v[mask] >= v_sat):
            return v
        out = v.copy()
        out[mask] = 65535
        return out
    out = v.astype(np.float32, copy=True)
    out[mask] = np.nan
    return out


def _map_arg(arr, shape, scalar, what):
    """(float32 map, is_map, float scalar) for the kernels."""
    if arr is None:
        return np.zeros((1, 1), np.float32), False, float(scalar)
    arr = np.asarray(arr)
    if arr.shape != tuple(shape):
        raise InputError(f"calibration {what} map has shape {arr.shape}, the frames {tuple(shape)}")
    return np.ascontiguousarray(arr, dtype=np.float32), True, float(scalar)


# The weights of the iterations in float32 where that is provably safe (see
# MergeAccumulator._single_precision_safe); False forces float64 (tests compare the two).
SINGLE_PRECISION_WEIGHTS = True


def _at(map_arg, rows, cols) -> np.ndarray | float:
    """A kernel map argument (array, is_map, scalar) at the photosites (rows, cols), float64."""
    arr, is_map, scalar = map_arg
    return np.asarray(arr[rows, cols], np.float64) if is_map else float(scalar)


def _finite_positive(arr: np.ndarray) -> bool:
    """Whether every value of ``arr`` is finite and > 0, from its least and largest value (a NaN
    makes the least NaN): two passes without the full-size masks (0.1 s at 24 Mpixel)."""
    lo, hi = arr.min(), arr.max()
    return bool(np.isfinite(lo) and np.isfinite(hi) and lo > 0)


def _extrema(map_arg) -> tuple[float, float]:
    """(min, max) of a kernel map argument (array, is_map, scalar); non-finite values give
    (nan, nan). Maps are scanned on every call (about 3 % of a merge with two 4-megapixel
    maps), so a map changed in place is seen as it is now."""
    arr, is_map, scalar = map_arg
    if not is_map:
        return float(scalar), float(scalar)
    lo, hi = float(np.min(arr)), float(np.max(arr))
    return (lo, hi) if np.isfinite(lo) and np.isfinite(hi) else (math.nan, math.nan)


class MergeAccumulator:
    """Streaming optimal merge: add frames as they are captured, then :meth:`result`.

    Each :meth:`add` runs the first pass (the non-saturated average the iterations start
    from) on that frame; :meth:`result` runs the iterations. Frames are kept by reference
    (not copied): do not modify them after adding. The result equals :func:`merge_arrays`
    on the same frames in the same order.

    Parameters
    ----------
    calibration : Calibration
        Camera model and maps.
    shape : (int, int)
        Mosaic size (rows, columns).
    master_dark : array_like, optional
        One master dark (DN) for every exposure (``dark_strategy="master"``), averaged from
        ``n_dark`` frames, taken at ``master_dark_time`` seconds.
    stream : bool
        Run the first pass in :meth:`add` (default). ``False`` defers all work to
        :meth:`result`, which then computes the starting average itself in the same order
        (the batch merge: one pass over the frames, identical results).
    **options
        Fields of :class:`MergeOptions`.
    """

    def __init__(self, calibration: Calibration, shape, master_dark=None, *, stream: bool = True, **options):
        try:
            self.options = MergeOptions(**options)
        except TypeError as err:
            raise InputError(f"unknown merge option ({err})") from None
        self.calibration = calibration
        self.shape = tuple(int(s) for s in shape)
        if len(self.shape) != 2 or min(self.shape) < 1:
            raise InputError(f"image shape must be two positive sizes, got {shape!r}")
        p = calibration.params
        opts = self.options
        self.master_dark = None if master_dark is None else _as_frame(master_dark, self.shape, "master dark")
        strategy = opts.dark_strategy
        if strategy is None and self.master_dark is not None:
            strategy = DarkStrategy.MASTER
        self._strategy = strategy  # may still be None: decided by the first add()
        if self.master_dark is not None and strategy is not DarkStrategy.MASTER:
            raise InputError(f"a master dark was given but the dark strategy is {strategy.value!r}")
        use_map = opts.prnu == "map" and calibration.prnu is not None
        self._a = _map_arg(calibration.prnu if use_map else None, self.shape, 1.0, "PRNU")
        if use_map and not _finite_positive(self._a[0]):
            raise InputError("calibration PRNU map must be finite and > 0")
        self._D = _map_arg(calibration.dark_current_map, self.shape, p.dark_current, "dark-current")
        self._bias = _map_arg(calibration.bias_map, self.shape, p.mu_R, "bias")
        self.prnu_used = "map" if use_map else "scalar"
        self._values: list[np.ndarray] = []
        self._masks: list[np.ndarray | None] = []  # per frame, the masked samples (None: none)
        self._darks: list[np.ndarray | None] = []
        self._times: list[float] = []
        self._nominal: list[float] = []  # the times as given, s
        self._table: list[bool] = []  # whether the calibration's shutter table corrected the frame
        self._kinds: list[int] = []
        self._coefs: list[float] = []
        self._ks: list[float] = []
        self._shares: list[Any] = []  # what the frame's dark level is shared by (see _dark_groups)
        self._strats: list[DarkStrategy] = []
        self._ndark: list[float] = []
        self._ratios: ExposureRatios | None = None  # the effective-time estimate, once made
        self.stream = bool(stream)
        init_shape = self.shape if self.stream else (1, 1)
        self._sum = np.zeros(init_shape, np.float64)
        self._cnt = np.zeros(init_shape, np.int32)

    # -------------------------------------------------------------------------------- setup
    @property
    def dark_strategy(self) -> str:
        """The common dark strategy of the frames added, or ``"mixed"``."""
        used = set(self._strats)
        if len(used) > 1:
            return "mixed"
        return (used.pop() if used else (self._strategy or DarkStrategy.MODEL)).value

    def _frame_strategy(self, strategy, dark) -> DarkStrategy:
        if strategy is None:
            if self._strategy is None:
                self._strategy = default_strategy(dark is not None)
            return self._strategy
        return as_strategy(strategy)

    def add(self, values, t, dark=None, *, strategy=None, n_dark=None, mask=None) -> None:
        """Add one exposure: raw mosaic ``values`` (DN), exposure time ``t`` (s) and its dark
        level; ``mask`` (bool, the mosaic's shape) marks samples of this frame that are no
        sample at all (impossible raw values): they are left out of this frame only, and the
        photosites get the ``masked`` quality bit, never the ``saturated`` one.

        ``strategy`` (None: the accumulator's ``dark_strategy``, else ``matched`` when ``dark``
        is given and ``model`` otherwise) may differ from frame to frame: ``matched`` needs
        ``dark``, a dark frame at the same time; ``master`` takes ``dark`` as this exposure's
        master dark averaged from ``n_dark`` frames (default: the ``n_dark`` option), or
        without ``dark`` the accumulator's single master dark; ``model`` takes no dark frame
        (bias level plus calibrated dark current).
        """
        t = check_exposure_time(t)
        what = f"frame {len(self._values) + 1} (t={t:g} s)"
        nominal, t, from_table = t, *self._shutter_corrected(t)
        v = _as_frame(values, self.shape, what)
        s = self._frame_strategy(strategy, dark)
        p = self.calibration.params
        m = _as_mask(mask, self.shape, what)
        if m is not None:
            v = _drop_masked(v, m, float(p.v_sat), self.options.saturation == "threshold")
        n = self.options.n_dark if n_dark is None else n_dark
        if s is DarkStrategy.MODEL:
            if dark is not None:
                raise InputError(f"{what}: a dark frame was given but the dark strategy is model")
            kind, coef, d = 1, p.g * t, None
        elif dark is not None:
            kind, coef = 0, 0.0
            d = _as_frame(dark, self.shape, f"dark frame for t={nominal:g} s")
        elif s is DarkStrategy.MASTER and self.master_dark is not None:
            t_ref = self.options.master_dark_time
            kind, coef, d = 2, (0.0 if t_ref is None else p.g * (t - t_ref)), None
        else:
            raise InputError(f"{what}: no dark frame for the {s} dark strategy")
        k = dark_factor(s, n)
        if d is not None:
            own = [x for x in self._darks if x is not None]
            if own and d.dtype != own[0].dtype:
                d = d.astype(np.float32)
                if own[0].dtype != np.float32:
                    self._darks = [None if x is None else x.astype(np.float32) for x in self._darks]
        if self._values and v.dtype != self._values[0].dtype:
            v = v.astype(np.float32)
            if self._values[0].dtype != np.float32:
                self._values = [x.astype(np.float32) for x in self._values]
        if self.stream:
            from hdrcap.pipeline.merge.kernels import MapArg, first_pass_kernel

            base = (self.master_dark.astype(np.float32, copy=False), True, 0.0) if kind == 2 else self._bias
            first_pass_kernel(
                v,
                d if d is not None else np.zeros((1, 1), np.float32),
                kind,
                MapArg(*base),
                coef,
                t,
                float(p.g),
                float(p.v_sat),
                MapArg(*self._D),
                MapArg(*self._a),
                self._sum,
                self._cnt,
            )
        self._values.append(v)
        self._masks.append(m)
        self._darks.append(d)
        self._times.append(t)
        self._nominal.append(nominal)
        self._table.append(from_table)
        self._kinds.append(kind)
        self._coefs.append(coef)
        self._ks.append(k)
        # The dark level's identity: the caller's dark frame object (kept alive by the
        # reference), or the single master dark; None where the frame has no dark frame.
        self._shares.append(dark if kind == 0 else (self.master_dark if kind == 2 else None))
        self._strats.append(s)
        self._ndark.append(float(n) if s is DarkStrategy.MASTER else (1.0 if s is DarkStrategy.MATCHED else 0.0))

    def __len__(self) -> int:
        return len(self._values)

    def _shutter_corrected(self, t: float) -> tuple[float, bool]:
        """The exposure time (s) a frame of nominal time ``t`` starts from: ``t`` times the
        calibration's shutter-table factor for ``t`` with ``exposure_times="effective"`` (when
        the table has ``t``), else ``t``; and whether the table applied."""
        table = self.calibration.shutter
        if self.options.exposure_times != "effective" or table is None:
            return t, False
        hit = table.lookup(t)
        return (t, False) if hit is None else (t * hit[0], True)

    def _dark_groups(self) -> list[int]:
        """Per frame, the number of frames in its shared-dark group: the frames of the same
        exposure time (:func:`pipeline.times.same_exposure`) whose dark level is the same dark
        frame (the same array object: the :class:`pipeline.merge.darks.DarkResolver` serves one
        object per time) or the same single master dark; 1 for frames without a dark frame.

        Returns
        -------
        list of int
            Group size n per frame (>= 1).
        """
        sizes = []
        for src, t in zip(self._shares, self._nominal):
            if src is None:
                sizes.append(1)
                continue
            sizes.append(sum(1 for o, u in zip(self._shares, self._nominal) if o is src and same_exposure(u, t)))
        return sizes

    def _shared_dark_factors(self) -> np.ndarray:
        """The dark-level variance factor of every frame with shared darks: n k.

        The n frames of a group share one dark level b: x_j = (v_j - b)/(t g a) have variance
        [Var(v) + k Var(b)]/(t g a)^2 and covariance k Var(b)/(t g a)^2. The generalised least
        squares solution for this covariance averages the copies and subtracts the dark once,
        variance [Var(v)/n + k Var(b)]/(t g a)^2; it equals weighting each copy as an
        independent sample with the dark factor n k (its n weights sum to the group's). Where
        only some copies are usable (a copy at or above v_sat) the factor stays n k: the
        stated variance is then an upper bound of the true one, never below it.

        Returns
        -------
        numpy.ndarray
            n k per frame, float64.
        """
        return np.asarray(self._ks, np.float64) * np.asarray(self._dark_groups(), np.float64)

    def _shares_timed_master(self) -> np.ndarray:
        """Per frame, whether its dark level is the single master dark taken at a known time
        t_ref (extrapolated by g (t - t_ref) D): such frames, of whatever exposure time, share
        that master dark's noise, whose variance is (g^2 t_ref D + sigma_R^2)/N (Eq. 5 at
        t_ref, averaged over N frames).

        Returns
        -------
        numpy.ndarray
            bool per frame.
        """
        timed = self.options.master_dark_time is not None
        return np.array([timed and kind == 2 for kind in self._kinds], bool)

    def _dark_factors(self) -> np.ndarray:
        """The kernel's dark-level variance factor per frame: :meth:`_shared_dark_factors`, and 0
        for the frames that share one timed master dark: its noise is common to all of them
        (whatever their exposure times), so it is added after the kernel as one shared term
        (:meth:`_shared_terms`), not per frame.

        Returns
        -------
        numpy.ndarray
            Factor per frame, float64.
        """
        return np.where(self._shares_timed_master(), 0.0, self._shared_dark_factors())

    # -------------------------------------------------------------------------------- result
    def _single_precision_safe(self, values, darks, master) -> bool:
        """Whether the weights and their sums may be computed in float32 (twice the SIMD width):
        bounds of every float32 quantity of the iterations, from the pixel types, the
        calibration and the exposure times, must lie well inside the float32 range (1e-30 to
        1e30). Integer frames only; float dark frames and maps are bounded by their extrema."""
        if not all(v.dtype == np.uint16 for v in values):
            return False
        p = self.calibration.params
        g, s2, v_sat = float(p.g), float(p.sigma2_R), float(p.v_sat)
        t = np.asarray(self._times, np.float64)
        a_lo, a_hi = _extrema(self._a)
        d_lo, d_hi = _extrema(self._D)
        b_lo, b_hi = _extrema(self._bias)
        m_lo, m_hi = _extrema((master, True, 0.0)) if self.master_dark is not None else (0.0, 0.0)
        if not (a_lo > 0 and d_lo >= 0 and s2 > 0):
            return False
        b_abs = 0.0
        for d, kind, coef in zip(darks, self._kinds, self._coefs):
            if kind == 0:
                lo, hi = (0.0, 65535.0) if d.dtype == np.uint16 else _extrema((d, True, 0.0))
            else:
                lo, hi = (b_lo, b_hi) if kind == 1 else (m_lo, m_hi)
                lo, hi = lo - abs(coef) * d_hi, hi + abs(coef) * d_hi
            b_abs = max(b_abs, abs(lo), abs(hi))
        tg_lo, tg_hi = float(t.min()) * g, float(t.max()) * g
        x_max = (abs(v_sat) + b_abs) / (tg_lo * a_lo)
        u_max = a_hi * x_max + d_hi
        var_hi = g * tg_hi * (u_max + d_hi) + 2.0 * s2
        w_hi = (tg_hi * a_hi) ** 2 / s2
        w_lo = (tg_lo * a_lo) ** 2 / var_hi
        n = len(values)
        bounds = [
            x_max,
            u_max,
            var_hi,
            w_hi * n,
            w_hi * n * x_max,
            (tg_hi * a_hi) ** 2,
            abs(v_sat) + abs(b_lo) + abs(b_hi),
        ]
        small = [s2, w_lo, (tg_lo * a_lo) ** 2]
        return bool(np.all(np.isfinite(bounds + small)) and max(bounds) <= 1e30 and min(small) >= 1e-30)

    def _subsample(self, max_photosites: int = 250_000) -> tuple[slice, slice]:
        """A regular grid of at most about ``max_photosites`` photosites (both CFA phases of
        each axis kept: an odd step)."""
        return subsample_window(self.shape, max_photosites)

    def _dark_level(self, i: int, window) -> np.ndarray:
        """Frame ``i``'s dark level b_i on the photosites ``window``, DN (float64)."""
        kind, coef = self._kinds[i], self._coefs[i]
        if kind == 0:
            return np.asarray(self._darks[i][window], np.float64)
        base = self._bias if kind == 1 else (self.master_dark, True, 0.0)
        b = base[0][window] if base[1] else base[2]
        D = self._D[0][window] if self._D[1] else self._D[2]
        return np.asarray(b, np.float64) + coef * np.asarray(D, np.float64)

    def apply_exposure_times(self) -> ExposureRatios | None:
        """With the option ``exposure_times="effective"``: estimate every frame's effective
        exposure time from the frames added (:func:`pipeline.exposure_ratio.
        estimate_exposure_ratios`, Sec. 7) and use it from now on (x_i of Eq. 6 and the dark
        current's t g coefficient); once (later calls return the same estimate). The streamed
        first pass is then recomputed by the iterations (its x_i used the nominal times).

        Returns
        -------
        ExposureRatios or None
            None with ``exposure_times="nominal"`` or fewer than two frames.
        """
        if self.options.exposure_times != "effective" or len(self._values) < 2:
            return None
        if self._ratios is not None:
            return self._ratios
        p = self.calibration.params
        win = self._subsample()
        dm = self.calibration.defect_map
        ratios = estimate_exposure_ratios(
            [v[win] for v in self._values],
            [self._dark_level(i, win) for i in range(len(self._values))],
            self._times,
            float(p.g),
            float(p.sigma2_R),
            float(p.v_sat),
            dark_factors=self._ks,
            exclude=None if dm is None else np.asarray(dm)[win] != 0,
        )
        t_ref = self.options.master_dark_time
        for i, t in enumerate(ratios.effective):
            if self._kinds[i] == 1:
                self._coefs[i] = float(p.g) * t
            elif self._kinds[i] == 2 and t_ref is not None:
                self._coefs[i] = float(p.g) * (t - t_ref)
        self._times = list(ratios.effective)
        self.stream = False  # the iterations recompute the starting average with the new times
        self._ratios = ratios
        return ratios

    def _exposure_info(self) -> dict[str, Any]:
        """The header entries of the exposure times: nominal, after the calibration's shutter
        table (``exposure_times_calibrated``, with which frames it corrected), and the bracket's
        estimate on top of that (``exposure_time_ratios``: factors relative to the calibrated
        times)."""
        ratios = self._ratios
        table = self.calibration.shutter
        applied = any(self._table)
        return {
            "exposure_times_nominal": list(self._nominal),
            "exposure_times_calibrated": list(ratios.nominal) if ratios is not None else list(self._times),
            "shutter_table": {
                "applied": list(self._table),
                "reference": None if table is None else table.reference,
                "source": "calibration" if applied else None,
            },
            "exposure_time_ratios": None if ratios is None else ratios.to_dict(),
        }

    def result(self, *, release_frames: Callable[[], Any] | None = None) -> HdrResult:
        """Run the iterations (Eq. 12-13, Fig. 3) and return the merge.

        ``release_frames`` is called when the frames have been read: after the iterations and
        again after the calibration's error terms (which read them only for frames whose dark
        level comes from the calibration's maps). The file layer drops the pages of its
        memory-mapped frames there, so that the frames and every output are not all resident
        at once."""
        import numba

        from hdrcap.pipeline.merge.kernels import (
            CameraConstants,
            FrameTable,
            IterationOptions,
            MapArg,
            MapSet,
            MergeOutputs,
            StartSums,
            merge_kernel,
        )

        if not self._values:
            raise InputError("no frames to merge")
        self.apply_exposure_times()
        opts = self.options
        p = self.calibration.params
        strategy = self.dark_strategy
        # Plain lists (numba "reflected lists", read-only here): unlike numba.typed.List they
        # need no run-time compilation, which would cost seconds per process.
        values = list(self._values)
        own = [d for d in self._darks if d is not None]
        hold = np.zeros((1, 1), own[0].dtype if own else np.float32)  # frames without a dark frame
        darks = [hold if d is None else d for d in self._darks]
        times = np.asarray(self._times, np.float64)
        has_master = self.master_dark is not None
        master = self.master_dark.astype(np.float32, copy=False) if has_master else np.zeros((1, 1), np.float32)
        irr = np.empty(self.shape, np.float32)
        sig = np.empty(self.shape, np.float32)
        nexp = np.empty(self.shape, np.float32)
        iters = np.empty(self.shape, np.uint8)
        single = SINGLE_PRECISION_WEIGHTS and self._single_precision_safe(values, darks, master)
        # Rows in chunks run in parallel; per chunk: photosites with nexp = 0, sum and max of
        # the iteration counts.
        stats = np.zeros((max(1, min(self.shape[0], 8 * numba.get_num_threads())), 3))
        # the inputs of the merge kernel and of the calibration's error terms
        frames = FrameTable(
            np.asarray(self._kinds, np.int64), np.asarray(self._coefs, np.float64), self._dark_factors(), times
        )
        camera = CameraConstants(float(p.g), float(p.sigma2_R), float(p.v_sat), float(p.white_level))
        maps = MapSet(MapArg(*self._bias), MapArg(*self._D), MapArg(*self._a), MapArg(master, has_master, 0.0))
        with _reflected_lists_quiet():
            merge_kernel(
                values,
                darks,
                frames,
                camera,
                maps,
                StartSums(self._sum, self._cnt, self.stream),
                IterationOptions(
                    int(opts.iterations),
                    float(opts.tolerance),
                    float(opts.saturation_sigmas),
                    opts.saturation == "probabilistic",
                ),
                MergeOutputs(irr, sig, nexp, iters, stats),
                np.zeros(1, np.float32 if single else np.float64),
            )
        release = release_frames or (lambda: None)
        release()
        sig_cal, sig_master, cal_info = self._shared_terms(irr, nexp, values, darks, frames, camera, maps)
        release()
        _add_in_quadrature(sig, sig_cal, sig_master)
        sat = int(stats[:, 0].sum())
        quality, n_defects = _flag_defects(irr, sig, nexp, self.calibration.defect_map)
        masked = self._flag_masked(irr, sig, nexp, quality)
        info = {
            "method": "optimal ML merge (Eq. 6, 8-13, Fig. 3)",
            **opts.to_dict(),
            "dark_strategy": strategy,
            "n_dark": float(opts.n_dark) if strategy == DarkStrategy.MASTER else None,
            "dark_strategies": [s.value for s in self._strats],
            "n_dark_per_frame": list(self._ndark),
            "dark_shared_by": self._dark_groups(),
            "master_dark": self.master_dark is not None,
            "prnu": self.prnu_used,
            "exposure_times": list(self._times),
            **self._exposure_info(),
            "n_frames": len(self._values),
            "n_darks": len(own) + (1 if has_master and 2 in self._kinds else 0),
            "saturated_everywhere": sat - masked["masked_everywhere"],
            "defects_flagged": n_defects,
            **masked,
            "iterations_used_mean": float(stats[:, 1].sum() / max(irr.size, 1)),
            "iterations_used_max": int(stats[:, 2].max()),
            "kernel": "numba",
            "weights_precision": "float32" if single else "float64",
            "calibration_error": cal_info,
        }
        if sig_cal is not None:
            sig_cal[((quality & ~np.uint8(QUALITY_BITS["masked"])) != 0) | (nexp == 0)] = 0.0  # not a measurement
        return HdrResult(irr, sig, nexp, quality=quality, sigma_calibration=sig_cal, header={"merge": info})

    def _flag_masked(self, irr, sig, nexp, quality) -> dict[str, Any]:
        """The masked samples' fix-up after the kernels, in place: the ``masked`` bit where a
        frame was masked; where that left no usable sample (``nexp = 0``, no defect), the lower
        bound of the shortest exposure not masked (as the kernel's, Eq. 11 at v_sat), or, masked
        in every frame, no information: irradiance and sigma 0 and no ``saturated`` bit.

        Returns
        -------
        dict
            ``masked_per_frame`` (masked samples per frame), ``masked_photosites`` (photosites
            masked in at least one frame), ``masked_everywhere`` (in every frame).
        """
        counts = [0 if m is None else int(np.count_nonzero(m)) for m in self._masks]
        out = {"masked_per_frame": counts, "masked_photosites": 0, "masked_everywhere": 0}
        if not any(counts):
            return out
        hit = np.zeros(self.shape, bool)
        for m in self._masks:
            if m is not None:
                hit |= m
        quality[hit] |= np.uint8(QUALITY_BITS["masked"])
        defect = np.uint8(sum(DEFECT_BITS.values()))
        rows, cols = np.nonzero(hit & (nexp == 0) & ((quality & defect) == 0))
        t_min = np.full(rows.size, np.inf)
        for m, t in zip(self._masks, self._times):
            keep = slice(None) if m is None else ~m[rows, cols]
            t_min[keep] = np.minimum(t_min[keep], t)
        p = self.calibration.params
        bias, dark, prnu = (_at(arg, rows, cols) for arg in (self._bias, self._D, self._a))
        with np.errstate(invalid="ignore", divide="ignore"):
            bound = ((float(p.v_sat) - bias) / (float(p.g) * t_min) - dark) / prnu
        none = ~np.isfinite(t_min)
        irr[rows, cols] = np.where(none, 0.0, bound)
        sig[rows[none], cols[none]] = 0.0
        quality[rows[none], cols[none]] &= ~np.uint8(QUALITY_BITS["saturated"])
        out["masked_photosites"] = int(np.count_nonzero(hit))
        out["masked_everywhere"] = int(np.count_nonzero(none))
        return out

    def _calibration_errors(self) -> tuple[Any, Any, Any, dict[str, Any]]:
        """The standard errors of the bias level (DN), the dark current (e-/s) and the PRNU gain
        a_j (dimensionless) the merge uses, as maps or scalars (0: unknown), and a description.

        Without a bias map the photosite's offset is taken as mu_R: its error is the offset
        non-uniformity (``bias_dsnu_DN`` of the calibration) with the error of mu_R. With
        ``prnu="scalar"`` (a = 1) the error of a_j is the PRNU spread itself (``prnu_std``)."""
        cal = self.calibration
        se = cal.stderr or {}
        prov = cal.provenance or {}
        used, missing = [], []

        def pick(name, map_, scalar):
            if map_ is not None:
                used.append(f"{name} map")
                return np.asarray(map_, np.float32)
            if scalar is not None and np.isfinite(scalar) and scalar > 0:
                used.append(name)
                return float(scalar)
            missing.append(name)
            return 0.0

        if cal.bias_map is not None:
            s_b = pick("bias", cal.bias_map_stderr, None)
        else:
            dsnu = (prov.get("calibration") or {}).get("bias_dsnu_DN")
            s_b = pick("bias", None, math.hypot(float(se.get("mu_R", 0.0)), float(dsnu or 0.0)) or None)
        if cal.dark_current_map is not None:
            s_d = pick("dark current", cal.dark_current_map_stderr, None)
        else:
            s_d = pick("dark current", None, se.get("dark_current"))
        if self.prnu_used == "map":
            s_a = pick("PRNU", cal.prnu_stderr, None)
        else:
            s_a = pick("PRNU spread (prnu scalar)", None, prov.get("prnu_std"))
        g_rel = float(se.get("g", 0.0)) / float(cal.params.g)
        desc = {
            "included": used,
            "missing": missing,
            "gain_relative_stderr": g_rel,
            "note": "sigma includes the calibration's per-photosite error (sigma_calibration); the gain's "
            "relative error is common to every photosite and not included",
        }
        return s_b, s_d, s_a, desc

    def _shared_terms(
        self, irr: np.ndarray, nexp: np.ndarray, values: list, darks: list, frames, camera, maps
    ) -> tuple[np.ndarray | None, np.ndarray | None, dict]:
        """The errors common to all exposures of a photosite, propagated to X at the estimate
        with the weights (Eq. 13) of the samples the merge kept (Eq. 11 and the near-saturation
        rule, evaluated at the final estimate; with the censored likelihood of
        ``saturation="probabilistic"`` every sample with its share of the information,
        1/Var(x_i) below v_sat and lambda(z) (lambda(z) - z)/Var(x_i) at or above it, z the
        clip level's distance in standard deviations: the censored estimate moves with a shift
        of the dark level of sample i by -(this)/(t g a) over the sum, as the threshold model's
        does with its weights):

        * sigma_calibration: the first-order propagation of the standard errors of the
          calibration's bias, dark-current and PRNU maps;
        * the noise of one master dark taken at t_ref and shared by every frame extrapolated
          from it: d mu / d M = -sum_i w_i / (t_i g a) / W over those frames, variance
          (g^2 t_ref D + sigma_R^2)/N.

        Computed per photosite by :func:`pipeline.merge.kernels.calibration_terms_kernel` (parallel
        over rows) from the merge kernel's own inputs: ``values``, ``darks`` with their
        placeholders, and its ``frames``, ``camera`` and ``maps`` tuples (the dark-current
        coefficient of a frame with its own dark frame is 0).

        Returns
        -------
        (numpy.ndarray or None, numpy.ndarray or None, dict)
            sigma_calibration (None when ``desc["included"]`` is empty: the calibration's part
            is unknown, not zero) and the master dark's term (None when no frame shares a timed
            master dark), e-/s, float32; the description of the calibration's errors.
        """
        s_b, s_d, s_a, desc = self._calibration_errors()
        out = np.zeros(self.shape, np.float32) if desc["included"] else None
        master_used = self._shares_timed_master().astype(np.float64)
        out_m = np.zeros(self.shape, np.float32) if master_used.any() else None
        if out is None and out_m is None:
            return out, out_m, desc
        from hdrcap.pipeline.merge.kernels import ErrorMaps, MapArg, SharedTerms, calibration_terms_kernel

        bias_used = (frames.kinds == 1).astype(np.float64)
        # Only frames whose dark level comes from the calibration's maps need their weights.
        needs_weights = bool(np.any(bias_used > 0) or np.any(frames.coefs != 0) or master_used.any())
        t_ref = self.options.master_dark_time

        def err_arg(e):
            return MapArg(e, True, 0.0) if isinstance(e, np.ndarray) else MapArg(np.zeros((1, 1), np.float32), False, e)

        with _reflected_lists_quiet():
            calibration_terms_kernel(
                values,
                darks,
                frames,
                camera,
                maps,
                ErrorMaps(err_arg(s_b), err_arg(s_d), err_arg(s_a)),
                SharedTerms(
                    np.ascontiguousarray(np.stack([bias_used, master_used], axis=1)),
                    float(self.options.saturation_sigmas) ** 2,
                    self.options.saturation == "probabilistic",
                    needs_weights,
                    out is not None,
                    out_m is not None,
                    float(t_ref) if t_ref is not None else 0.0,
                    float(self.options.n_dark),
                ),
                irr,
                nexp,
                out if out is not None else out_m,  # a placeholder for the output not asked for
                out_m if out_m is not None else out,
            )
        return out, out_m, desc


@contextlib.contextmanager
def _reflected_lists_quiet():
    """Silence numba's pending deprecation of reflected lists around a kernel call: the kernels
    take plain lists of frames on purpose (``numba.typed.List`` would cost its compilation in
    every process)."""
    import numba

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=numba.NumbaPendingDeprecationWarning)
        yield


def _add_in_quadrature(sigma: np.ndarray, *terms: np.ndarray | None, rows: int = 256) -> None:
    """sigma = sqrt(sigma^2 + sum of terms^2), in place, in float64 (the total uncertainty of
    independent error sources), a block of ``rows`` rows at a time (no full-size float64
    temporaries). Without terms it is |sigma| (sqrt of an exact float64 square: the same
    bits).

    Parameters
    ----------
    sigma : numpy.ndarray
        float32 standard uncertainties (any unit), 2-D; overwritten.
    *terms : numpy.ndarray or None
        Further standard uncertainties of the same shape and unit; None entries are skipped.
    rows : int
        Rows per block.
    """
    terms = [t for t in terms if t is not None]
    if not terms:
        np.abs(sigma, out=sigma)
        return
    for r0 in range(0, sigma.shape[0], rows):
        sl = slice(r0, r0 + rows)
        total = np.square(sigma[sl], dtype=np.float64)
        for t in terms:
            total += np.square(t[sl], dtype=np.float64)
        np.sqrt(total, out=sigma[sl], casting="unsafe")


def import_kernels() -> Callable[[], None]:
    """Import numba (its compile target set, :mod:`pipeline._numba_target`) and the merge
    kernels in the calling thread, and return what may then run in a background thread while
    the frames are read: the initialisation of numba's CPU target (its registries of numpy
    implementations, built once per process before numba compiles or loads any function: a
    third of a second or more), under numba's compiler lock, importing only numba's own
    modules that no other thread imports outside that lock (:mod:`pipeline.merge.files`
    starts it). It changes no result.

    Returns
    -------
    callable
        :func:`pipeline._numba_target.warm_up`.
    """
    from hdrcap.pipeline._numba_target import warm_up
    from hdrcap.pipeline.merge import kernels  # noqa: F401  (its decorators import what they need, here)

    return warm_up


def merge_arrays(
    values, times, calibration: Calibration, darks=None, *, dark_strategies=None, n_darks=None, masks=None, **options
) -> HdrResult:
    """Merge raw mosaics into irradiance and uncertainty (Eq. 6, 8-13, Fig. 3).

    Parameters
    ----------
    values : sequence of 2-D arrays
        Raw mosaics, DN (uint16 or float).
    times : sequence of float
        Exposure times, s, one per mosaic.
    calibration : Calibration
        Camera model (g, mu_R, sigma2_R, v_sat, D; optional PRNU, bias and dark-current maps).
    darks : sequence of 2-D arrays (or None entries), or one 2-D array, optional
        A sequence aligned with ``values``: each mosaic's dark frame (``matched``), its master
        dark (``master``, ``n_dark`` frames) or None (``model``, or the single master dark). One
        array: a master dark for all exposures (see ``master_dark_time``). None: the ``model``
        strategy.
    dark_strategies : sequence of str or None, optional
        Dark strategy per mosaic (``matched``, ``master``, ``model``; None entries take the
        ``dark_strategy`` option): a plan may mix them.
    n_darks : sequence of float or None, optional
        Frames averaged into each mosaic's master dark (None entries: the ``n_dark`` option).
    masks : sequence of 2-D bool arrays (or None entries), optional
        Per mosaic, samples that are no sample (impossible raw values): left out of that mosaic
        only, flagged ``masked`` in ``quality`` (:meth:`MergeAccumulator.add`).
    **options
        Fields of :class:`MergeOptions` (iterations, tolerance, saturation, saturation_sigmas,
        prnu, dark_strategy, n_dark, master_dark_time).

    Returns
    -------
    HdrResult
        float32 irradiance (e-/s), sigma (e-/s) and nexp; ``info`` records the options and the
        dark strategy of every frame.
    """
    values = list(values)
    times = list(times)
    if not values:
        raise InputError("no frames to merge")
    if len(times) != len(values):
        raise InputError(f"{len(times)} exposure times for {len(values)} frames")
    shape = np.shape(values[0])
    if len(shape) != 2:
        raise InputError(f"frame 1: expected a 2-D mosaic, got shape {shape}")
    strategies = [as_strategy(s) for s in _per_frame(dark_strategies, len(values), "dark strategies")]
    master = None
    per_frame = [None] * len(values)
    if darks is not None:
        if isinstance(darks, np.ndarray) and darks.ndim == 2:
            master = darks
            options.setdefault("dark_strategy", DarkStrategy.MASTER)
        else:
            per_frame = list(darks)
            if len(per_frame) != len(values):
                raise InputError(f"{len(per_frame)} dark frames for {len(values)} frames")
    default = as_strategy(options.get("dark_strategy"))
    if darks is None and default in (DarkStrategy.MATCHED, DarkStrategy.MASTER) and not all(strategies):
        raise InputError(f"the {default} dark strategy needs dark frames")
    # Frames merged with the model strategy ignore any dark frame given for them.
    per_frame = [None if (s or default) is DarkStrategy.MODEL else d for d, s in zip(per_frame, strategies)]
    return _accumulate(
        calibration,
        shape,
        master,
        values,
        times,
        per_frame,
        strategies,
        _per_frame(n_darks, len(values), "master-dark frame counts"),
        options,
        _per_frame(masks, len(values), "masks"),
    )


def _accumulate(calibration, shape, master, values, times, darks, strategies, n_darks, options, masks) -> HdrResult:
    """The batch merge of aligned per-frame inputs (one pass, :class:`MergeAccumulator`)."""
    acc = MergeAccumulator(calibration, shape, master_dark=master, stream=False, **options)
    for v, t, d, s, n, m in zip(values, times, darks, strategies, n_darks, masks):
        acc.add(v, t, d, strategy=s, n_dark=n, mask=m)
    return acc.result()


def _per_frame(items, n, what) -> list:
    if items is None:
        return [None] * n
    items = list(items)
    if len(items) != n:
        raise InputError(f"{len(items)} {what} for {n} frames")
    return items


def merge_frames(
    frames: Sequence[RawFrame],
    calibration: Calibration,
    darks: Sequence[RawFrame] | None = None,
    master_dark: RawFrame | None = None,
    *,
    dark_strategies: Sequence[DarkStrategy | str | None] | None = None,
    n_darks: Sequence[float | None] | None = None,
    **options,
) -> HdrResult:
    """Merge a bracket of raw frames into irradiance and uncertainty (Eq. 6, 8-13).

    Each frame's dark level is the one :class:`pipeline.merge.darks.DarkResolver` serves its
    exposure time and dark strategy.

    Parameters
    ----------
    frames : sequence of RawFrame
        The bracket; any order. Masked photosites of a frame (:attr:`pipeline.io.raw.RawFrame.
        masked`) are left out of that frame (see :meth:`MergeAccumulator.add`).
    calibration : Calibration
        Camera model (g, mu_R, sigma2_R, v_sat, D; optional PRNU and dark-current maps).
    darks : sequence of RawFrame, optional
        Dark frames matched to the exposures by exposure time (``matched``: the first of that
        time; ``master``: those of that time averaged, each a master dark of ``n_dark``
        frames). Without darks (and without ``master_dark``) the bias level and the calibrated
        dark current are subtracted (``model``). Frames merged with the ``model`` strategy
        need none.
    master_dark : RawFrame, optional
        One master dark for all exposures (averaged from ``n_dark`` frames); its exposure time
        is used as ``master_dark_time`` unless given.
    dark_strategies, n_darks : sequences aligned with ``frames``, optional
        Per-frame dark strategy and master-dark frame count (see :func:`merge_arrays`).
    **options
        Fields of :class:`MergeOptions`; ``exposure_times`` defaults to ``"effective"`` here
        (each frame's exposure time estimated from the bracket, :mod:`pipeline.exposure_ratio`).

    Returns
    -------
    HdrResult
        As :func:`merge_arrays`.
    """
    frames = check_frames(frames)
    shape = frames[0].shape
    n = len(frames)
    options.setdefault("exposure_times", "effective")
    strategies = [as_strategy(s) for s in _per_frame(dark_strategies, n, "dark strategies")]
    n_darks = _per_frame(n_darks, n, "master-dark frame counts")
    asked = as_strategy(options.get("dark_strategy"))
    uses_darks = bool(darks) and (
        asked is not DarkStrategy.MODEL or any(s not in (None, DarkStrategy.MODEL) for s in strategies)
    )
    if (
        not darks
        and master_dark is None
        and asked in (DarkStrategy.MATCHED, DarkStrategy.MASTER)
        and not all(strategies)
    ):
        raise InputError(f"the {asked} dark strategy needs dark frames")
    if uses_darks and master_dark is not None and all(s is None for s in strategies):
        raise InputError("give either dark frames or a master dark, not both")
    if master_dark is not None:
        if master_dark.shape != shape:
            raise InputError(f"{master_dark.path}: master dark size differs from the bracket's")
        options.setdefault("master_dark_time", master_dark.exposure_time)
        options.setdefault("dark_strategy", DarkStrategy.MASTER)
    resolver = DarkResolver(
        frames_per_dark=options.get("n_dark"), master_dark=None if master_dark is None else str(master_dark.path)
    )
    if uses_darks:
        darks = check_frames(darks, "dark frame")
        if darks[0].shape != shape:
            raise InputError(f"{darks[0].path}: dark frame size differs from the bracket's")
        for d in darks:
            resolver.add_dark(d.data, d.exposure_time, str(d.path))
    default = as_strategy(options.get("dark_strategy")) or default_strategy(uses_darks, master_dark is not None)
    per_frame = []
    for i, (f, s) in enumerate(zip(frames, strategies)):
        src = resolver.resolve(f.exposure_time, s or default)
        if src is None:
            raise InputError(f"{f.path}: no dark frame with exposure time {f.exposure_time:g} s")
        per_frame.append(src.data)
        if n_darks[i] is None and src.origin == "frames" and src.strategy is DarkStrategy.MASTER:
            n_darks[i] = src.n_frames
    return _accumulate(
        calibration,
        shape,
        None if master_dark is None else np.asarray(master_dark.data),
        [f.data for f in frames],
        [f.exposure_time for f in frames],
        per_frame,
        strategies,
        n_darks,
        options,
        [f.masked for f in frames],
    )
