"""The frames a merge holds and their dark levels: the per-frame table of the merge kernels.

:class:`FrameBook` keeps, for every frame added to a
:class:`pipeline.merge.accumulator.MergeAccumulator`, the raw mosaic, its mask, its exposure
times and how its dark level b_i is formed (:class:`DarkLevel`: an own dark frame, the bias
plus the calibrated dark current, or the single master dark), and derives from them the
dark-level variance factors of frames that share one dark frame (Eq. 5 and generalised least
squares over the group).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.merge.darks import default_strategy
from hdrcap.pipeline.merge.kernel_inputs import MapTuple, map_values
from hdrcap.pipeline.merge.options import as_strategy
from hdrcap.pipeline.noise import DarkStrategy, dark_factor
from hdrcap.pipeline.times import same_exposure

__all__ = ["DarkLevel", "FrameBook", "as_frame", "as_mask"]


def as_frame(arr: Any, shape: Sequence[int] | None, what: str) -> np.ndarray:
    """A raw mosaic as the kernels take it: uint16 and float32 stay as they are (no copy when
    contiguous); every other numeric type becomes float32.

    Parameters
    ----------
    arr : array_like
        2-D mosaic, DN.
    shape : (int, int) or None
        The shape it must have (None: any).
    what : str
        What it is, for error messages.

    Returns
    -------
    numpy.ndarray
        C-contiguous uint16 or float32 array, DN.

    Raises
    ------
    InputError
        Not 2-D, another shape, or not numeric.
    """
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


def as_mask(mask: Any, shape: Sequence[int], what: str) -> np.ndarray | None:
    """A frame's mask of samples that are no sample.

    Parameters
    ----------
    mask : array_like or None
        bool, True where the sample is masked.
    shape : (int, int)
        The frames' shape.
    what : str
        Which frame, for error messages.

    Returns
    -------
    numpy.ndarray or None
        The bool mask, or None when nothing is masked.

    Raises
    ------
    InputError
        Another shape, or not boolean.
    """
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise InputError(f"{what}: mask has shape {m.shape}, the frames {tuple(shape)}")
    if m.dtype != np.bool_:
        raise InputError(f"{what}: mask must be boolean, got {m.dtype}")
    return m if m.any() else None


@dataclass(frozen=True)
class DarkLevel:
    """How one frame's dark level b_i is formed (the kernels' per-frame table).

    Attributes
    ----------
    strategy : DarkStrategy
        The frame's dark strategy.
    kind : int
        0: the frame's own dark frame ``dark``; 1: the bias plus ``coef`` times the dark
        current (``model``); 2: the single master dark plus ``coef`` times the dark current.
    coef : float
        Factor of the dark current D (e-/s) in the dark level, DN per e-/s: g t (kind 1),
        g (t - t_ref) or 0 (kind 2), 0 (kind 0).
    dark : numpy.ndarray or None
        The own dark frame (kind 0), uint16 or float32, DN.
    k : float
        Dark-level variance factor of :func:`pipeline.noise.dark_factor` (1 matched, 1/N
        master, 0 model).
    n_frames : float
        Frames averaged into the dark level, for the header: N (master), 1 (matched), 0 (model).
    share : object
        What the dark level is shared by: the caller's dark frame object (kind 0), the single
        master dark (kind 2), or None.
    """

    strategy: DarkStrategy
    kind: int
    coef: float
    dark: np.ndarray | None
    k: float
    n_frames: float
    share: Any


class FrameBook:
    """The frames of one merge, column by column as the kernels take them.

    Parameters
    ----------
    shape : (int, int)
        Mosaic size (rows, columns).
    master_dark : numpy.ndarray or None
        The single master dark (DN) of every ``master`` frame without its own dark frame.
    master_dark_time : float or None
        Its exposure time, s (None: used as is, without the dark current's difference).
    strategy : DarkStrategy or None
        The dark strategy of frames added without one (None: decided by the first frame).
    """

    def __init__(
        self,
        shape: tuple[int, int],
        master_dark: np.ndarray | None,
        master_dark_time: float | None,
        strategy: DarkStrategy | None,
    ) -> None:
        self.shape = shape
        self.master_dark = master_dark
        self.master_dark_time = master_dark_time
        self.default = strategy
        self.values: list[np.ndarray] = []
        self.masks: list[np.ndarray | None] = []  # per frame, the masked samples (None: none)
        self.darks: list[np.ndarray | None] = []
        self.times: list[float] = []  # the times the merge uses, s
        self.nominal: list[float] = []  # the times as given, s
        self.table: list[bool] = []  # whether the calibration's shutter table corrected the frame
        self.kinds: list[int] = []
        self.coefs: list[float] = []
        self.ks: list[float] = []
        self.shares: list[Any] = []  # what the frame's dark level is shared by (see dark_groups)
        self.strategies: list[DarkStrategy] = []
        self.n_darks: list[float] = []

    def __len__(self) -> int:
        return len(self.values)

    def strategy_for(self, strategy: DarkStrategy | str | None, dark: Any) -> DarkStrategy:
        """The dark strategy of a frame added with ``strategy`` (None: the book's default, which
        the first such frame sets: ``matched`` with a ``dark``, ``model`` without).

        Parameters
        ----------
        strategy : DarkStrategy, str or None
            The strategy asked for.
        dark : array_like or None
            The frame's dark frame.

        Returns
        -------
        DarkStrategy
        """
        if strategy is None:
            if self.default is None:
                self.default = default_strategy(dark is not None)
            return self.default
        chosen = as_strategy(strategy)
        assert chosen is not None  # strategy is not None
        return chosen

    def common_strategy(self) -> str:
        """The common dark strategy of the frames added, or ``"mixed"``.

        Returns
        -------
        str
            ``"matched"``, ``"master"``, ``"model"`` or ``"mixed"``.
        """
        used = set(self.strategies)
        if len(used) > 1:
            return "mixed"
        return (used.pop() if used else (self.default or DarkStrategy.MODEL)).value

    def dark_level(
        self, strategy: DarkStrategy, dark: Any, t: float, nominal: float, n_dark: float, g: float, what: str
    ) -> DarkLevel:
        """The dark level of a frame of exposure time ``t`` (s; ``nominal`` as given).

        Parameters
        ----------
        strategy : DarkStrategy
            The frame's dark strategy.
        dark : array_like or None
            Its dark frame (``matched``), or its own master dark (``master``), DN.
        t, nominal : float
            Exposure time the merge uses and as given, s.
        n_dark : float
            Frames averaged into a master dark.
        g : float
            Gain, DN/e-.
        what : str
            Which frame, for error messages.

        Returns
        -------
        DarkLevel

        Raises
        ------
        InputError
            A dark frame with ``model``, or no dark level for the strategy.
        """
        if strategy is DarkStrategy.MODEL:
            if dark is not None:
                raise InputError(f"{what}: a dark frame was given but the dark strategy is model")
            kind, coef, d = 1, g * t, None
        elif dark is not None:
            kind, coef = 0, 0.0
            d = as_frame(dark, self.shape, f"dark frame for t={nominal:g} s")
        elif strategy is DarkStrategy.MASTER and self.master_dark is not None:
            t_ref = self.master_dark_time
            kind, coef, d = 2, (0.0 if t_ref is None else g * (t - t_ref)), None
        else:
            raise InputError(f"{what}: no dark frame for the {strategy} dark strategy")
        k = dark_factor(strategy, n_dark)
        recorded = (
            float(n_dark) if strategy is DarkStrategy.MASTER else (1.0 if strategy is DarkStrategy.MATCHED else 0.0)
        )
        # The dark level's identity: the caller's dark frame object (kept alive by the
        # reference), or the single master dark; None where the frame has no dark frame.
        share = dark if kind == 0 else (self.master_dark if kind == 2 else None)
        return DarkLevel(strategy, kind, coef, d, k, recorded, share)

    def common_types(self, values: np.ndarray, dark: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """A new frame and its dark frame in the types of those held: when the pixel types
        differ, float32 (the frames held are converted too).

        Parameters
        ----------
        values : numpy.ndarray
            The new frame, uint16 or float32, DN.
        dark : numpy.ndarray or None
            Its own dark frame, uint16 or float32, DN.

        Returns
        -------
        (numpy.ndarray, numpy.ndarray or None)
            The frame and its dark frame.
        """
        if dark is not None:
            own = [x for x in self.darks if x is not None]
            if own and dark.dtype != own[0].dtype:
                dark = dark.astype(np.float32)
                if own[0].dtype != np.float32:
                    self.darks = [None if x is None else x.astype(np.float32) for x in self.darks]
        if self.values and values.dtype != self.values[0].dtype:
            values = values.astype(np.float32)
            if self.values[0].dtype != np.float32:
                self.values = [x.astype(np.float32) for x in self.values]
        return values, dark

    def append(
        self,
        values: np.ndarray,
        mask: np.ndarray | None,
        dark: np.ndarray | None,
        level: DarkLevel,
        times: tuple[float, float, bool],
    ) -> None:
        """Hold one frame (after :meth:`common_types`).

        Parameters
        ----------
        values : numpy.ndarray
            The frame, DN (masked samples already dropped).
        mask : numpy.ndarray or None
            Its masked samples.
        dark : numpy.ndarray or None
            Its own dark frame, DN.
        level : DarkLevel
            Its dark level.
        times : (float, float, bool)
            The exposure time the merge uses (s), the nominal one (s), and whether the
            calibration's shutter table corrected it.
        """
        t, nominal, from_table = times
        self.values.append(values)
        self.masks.append(mask)
        self.darks.append(dark)
        self.times.append(t)
        self.nominal.append(nominal)
        self.table.append(from_table)
        self.kinds.append(level.kind)
        self.coefs.append(level.coef)
        self.ks.append(level.k)
        self.shares.append(level.share)
        self.strategies.append(level.strategy)
        self.n_darks.append(level.n_frames)

    def retime(self, times: Sequence[float], g: float) -> None:
        """Use new exposure times (s) from now on, with the dark current's coefficients of the
        frames whose dark level is the bias or the timed master dark (g t, g (t - t_ref)).

        Parameters
        ----------
        times : sequence of float
            One exposure time per frame, s.
        g : float
            Gain, DN/e-.
        """
        t_ref = self.master_dark_time
        for i, t in enumerate(times):
            if self.kinds[i] == 1:
                self.coefs[i] = g * t
            elif self.kinds[i] == 2 and t_ref is not None:
                self.coefs[i] = g * (t - t_ref)
        self.times = list(times)

    def dark_groups(self) -> list[int]:
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
        for src, t in zip(self.shares, self.nominal):
            if src is None:
                sizes.append(1)
                continue
            sizes.append(sum(1 for o, u in zip(self.shares, self.nominal) if o is src and same_exposure(u, t)))
        return sizes

    def shared_dark_factors(self) -> np.ndarray:
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
        return np.asarray(self.ks, np.float64) * np.asarray(self.dark_groups(), np.float64)

    def shares_timed_master(self) -> np.ndarray:
        """Per frame, whether its dark level is the single master dark taken at a known time
        t_ref (extrapolated by g (t - t_ref) D): such frames, of whatever exposure time, share
        that master dark's noise, whose variance is (g^2 t_ref D + sigma_R^2)/N (Eq. 5 at
        t_ref, averaged over N frames).

        Returns
        -------
        numpy.ndarray
            bool per frame.
        """
        timed = self.master_dark_time is not None
        return np.array([timed and kind == 2 for kind in self.kinds], bool)

    def dark_factors(self) -> np.ndarray:
        """The kernel's dark-level variance factor per frame: :meth:`shared_dark_factors`, and 0
        for the frames that share one timed master dark: its noise is common to all of them
        (whatever their exposure times), so it is added after the kernel as one shared term
        (:func:`pipeline.merge.calibration_errors.shared_terms`), not per frame.

        Returns
        -------
        numpy.ndarray
            Factor per frame, float64.
        """
        return np.where(self.shares_timed_master(), 0.0, self.shared_dark_factors())

    def level_at(self, i: int, window: Any, bias: MapTuple, dark_current: MapTuple) -> np.ndarray:
        """Frame ``i``'s dark level b_i on some photosites.

        Parameters
        ----------
        i : int
            The frame's index.
        window : tuple
            A numpy index of the image (e.g. two slices).
        bias, dark_current : MapTuple
            The merge's bias (DN) and dark-current (e-/s) maps.

        Returns
        -------
        numpy.ndarray
            b_i on ``window``, DN, float64.
        """
        kind, coef = self.kinds[i], self.coefs[i]
        if kind == 0:
            own = self.darks[i]
            assert own is not None  # kind 0: the frame's own dark frame
            return np.asarray(own[window], np.float64)
        if kind == 1:
            base = bias
        else:
            assert self.master_dark is not None  # kind 2: the single master dark
            base = (self.master_dark, True, 0.0)
        b = map_values(base, window)
        return np.asarray(b, np.float64) + coef * np.asarray(map_values(dark_current, window), np.float64)
