"""The optimal HDR merge: :class:`MergeAccumulator` and the batch merges over it (Sec. 4-5, Fig. 3).

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
:func:`merge_arrays` and :func:`pipeline.merge.files.merge_files` use it, so streaming and batch results agree. Its
parts: the options (:mod:`pipeline.merge.options`), the frames and their dark levels
(:mod:`pipeline.merge.frames`), the calibration's maps (:mod:`pipeline.merge.kernel_inputs`),
the exposure times (:mod:`pipeline.merge.exposure_times`), the weights' precision
(:mod:`pipeline.merge.precision`), the shared error terms (:mod:`pipeline.merge.calibration_errors`)
and the quality flags (:mod:`pipeline.merge.flags`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.exposure_ratio import ExposureRatios, subsample_window
from hdrcap.pipeline.io.raw import check_exposure_time
from hdrcap.pipeline.merge.calibration_errors import add_in_quadrature, shared_terms
from hdrcap.pipeline.merge.exposure_times import ExposureTimes
from hdrcap.pipeline.merge.flags import (
    clear_unmeasured,
    drop_masked,
    flag_clip_rejected,
    flag_defects,
    flag_masked,
    quality_channel,
)
from hdrcap.pipeline.merge.frames import DarkLevel, FrameBook, as_frame, as_mask
from hdrcap.pipeline.merge.kernel_inputs import KernelInputs, calibration_maps
from hdrcap.pipeline.merge.options import MergeOptions, as_strategy
from hdrcap.pipeline.merge.precision import single_precision_safe
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.result import HdrResult

if TYPE_CHECKING:
    from hdrcap.pipeline.merge.kernels import MergeOutputs

__all__ = [
    "MergeOptions",
    "MergeAccumulator",
    "merge_arrays",
    "as_strategy",
    "quality_channel",
]

# The weights of the iterations in float32 where that is provably safe
# (:func:`pipeline.merge.precision.single_precision_safe`); False forces float64 (tests compare
# the two).
SINGLE_PRECISION_WEIGHTS = True


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

    def __init__(
        self,
        calibration: Calibration,
        shape: Sequence[int],
        master_dark: ArrayLike | None = None,
        *,
        stream: bool = True,
        **options: Any,
    ) -> None:
        try:
            self.options = MergeOptions(**options)
        except TypeError as err:
            raise InputError(f"unknown merge option ({err})") from None
        self.calibration = calibration
        self.shape = _image_shape(shape)
        opts = self.options
        master = None if master_dark is None else as_frame(master_dark, self.shape, "master dark")
        strategy = opts.dark_strategy
        if master is not None:
            strategy = strategy or DarkStrategy.MASTER
            if strategy is not DarkStrategy.MASTER:
                raise InputError(f"a master dark was given but the dark strategy is {strategy.value!r}")
        self.maps = calibration_maps(calibration, self.shape, opts.prnu)
        # the strategy may still be None: decided by the first add()
        self.frames = FrameBook(self.shape, master, opts.master_dark_time, strategy)
        self._exposure = ExposureTimes(calibration, opts.exposure_times)
        self.stream = bool(stream)
        init_shape = self.shape if self.stream else (1, 1)
        self._sum = np.zeros(init_shape, np.float64)
        self._cnt = np.zeros(init_shape, np.int32)

    @property
    def master_dark(self) -> np.ndarray | None:
        """The single master dark (uint16 or float32, DN), or None."""
        return self.frames.master_dark

    @property
    def dark_strategy(self) -> str:
        """The common dark strategy of the frames added, or ``"mixed"``."""
        return self.frames.common_strategy()

    def __len__(self) -> int:
        return len(self.frames)

    # -------------------------------------------------------------------------------- frames
    def add(
        self,
        values: ArrayLike,
        t: float,
        dark: ArrayLike | None = None,
        *,
        strategy: DarkStrategy | str | None = None,
        n_dark: float | None = None,
        mask: ArrayLike | None = None,
    ) -> None:
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
        what = f"frame {len(self) + 1} (t={t:g} s)"
        nominal, (t, from_table) = t, self._exposure.shutter_corrected(t)
        v = as_frame(values, self.shape, what)
        s = self.frames.strategy_for(strategy, dark)
        p = self.calibration.params
        m = as_mask(mask, self.shape, what)
        if m is not None:
            v = drop_masked(v, m, float(p.v_sat), self.options.saturation == "threshold")
        n = self.options.n_dark if n_dark is None else n_dark
        level = self.frames.dark_level(s, dark, t, nominal, n, p.g, what)
        v, d = self.frames.common_types(v, level.dark)
        if self.stream:
            self._first_pass(v, d, level, t)
        self.frames.append(v, m, d, level, (t, nominal, from_table))

    def _first_pass(self, v: np.ndarray, d: np.ndarray | None, level: DarkLevel, t: float) -> None:
        """Add frame ``v`` (dark frame ``d``, time ``t``) to the sums of the starting average."""
        from hdrcap.pipeline.merge.kernels import MapArg, first_pass_kernel

        p = self.calibration.params
        if level.kind == 2:
            assert self.master_dark is not None  # kind 2: the single master dark
            base = MapArg(self.master_dark.astype(np.float32, copy=False), True, 0.0)
        else:
            base = MapArg(*self.maps.bias)
        first_pass_kernel(
            v,
            d if d is not None else np.zeros((1, 1), np.float32),
            level.kind,
            base,
            level.coef,
            t,
            float(p.g),
            float(p.v_sat),
            MapArg(*self.maps.dark_current),
            MapArg(*self.maps.prnu),
            self._sum,
            self._cnt,
        )

    # ------------------------------------------------------------------------ exposure times
    def _subsample(self, max_photosites: int = 250_000) -> tuple[slice, slice]:
        """A regular grid of at most about ``max_photosites`` photosites (both CFA phases of
        each axis kept: an odd step)."""
        return subsample_window(self.shape, max_photosites)

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
        if self.options.exposure_times != "effective" or len(self) < 2:
            return None
        if self._exposure.ratios is None:
            self._exposure.estimate(self.frames, self._subsample(), self.maps)
            self.stream = False  # the iterations recompute the starting average with the new times
        return self._exposure.ratios

    def _exposure_info(self) -> dict[str, Any]:
        """The header entries of the exposure times (:meth:`pipeline.merge.exposure_times.
        ExposureTimes.info`)."""
        return self._exposure.info(self.frames)

    # -------------------------------------------------------------------------------- result
    def _single_precision_safe(self, values: list[np.ndarray], darks: list[np.ndarray], master: np.ndarray) -> bool:
        """Whether the weights and their sums may be computed in float32
        (:func:`pipeline.merge.precision.single_precision_safe`)."""
        return single_precision_safe(values, darks, master, self.frames, self.calibration.params, self.maps)

    def _kernel_frames(self) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
        """The frames, their dark frames and the master dark as the kernels take them.

        Plain lists (numba "reflected lists", read-only here): unlike numba.typed.List they
        need no run-time compilation, which would cost seconds per process. A 1x1 placeholder
        stands for a frame's missing dark frame and for a missing master dark; it has the
        type of the dark frames, or of the frames without any (never read: merges of 16-bit
        frames with and without dark frames share one compiled kernel)."""
        book = self.frames
        own = [d for d in book.darks if d is not None]
        hold = np.zeros((1, 1), (own or list(book.values))[0].dtype)
        darks = [hold if d is None else d for d in book.darks]
        if book.master_dark is None:
            master = np.zeros((1, 1), np.float32)
        else:
            master = book.master_dark.astype(np.float32, copy=False)
        return list(book.values), darks, master

    def _kernel_inputs(self, values: list[np.ndarray], darks: list[np.ndarray], master: np.ndarray) -> KernelInputs:
        """The inputs of the merge kernel and of the calibration's error terms."""
        from hdrcap.pipeline.merge.kernels import CameraConstants, FrameTable, MapArg, MapSet

        book, p, maps = self.frames, self.calibration.params, self.maps
        frames = FrameTable(
            np.asarray(book.kinds, np.int64),
            np.asarray(book.coefs, np.float64),
            book.dark_factors(),
            np.asarray(book.times, np.float64),
        )
        camera = CameraConstants(float(p.g), float(p.sigma2_R), float(p.v_sat), float(p.white_level))
        kernel_maps = MapSet(
            MapArg(*maps.bias),
            MapArg(*maps.dark_current),
            MapArg(*maps.prnu),
            MapArg(master, book.master_dark is not None, 0.0),
        )
        return KernelInputs(values, darks, frames, camera, kernel_maps)

    def _iterate(self, inputs: KernelInputs, single: bool) -> MergeOutputs:
        """Run the merge kernel (float32 weights when ``single``): its outputs."""
        import numba

        from hdrcap.pipeline.merge.kernels import (
            STATS_COLUMNS,
            IterationOptions,
            MergeOutputs,
            StartSums,
            merge_kernel,
            reflected_lists_quiet,
        )

        opts = self.options
        # Rows in chunks run in parallel; per chunk: photosites with nexp = 0, sum and max of
        # the iteration counts.
        out = MergeOutputs(
            np.empty(self.shape, np.float32),
            np.empty(self.shape, np.float32),
            np.empty(self.shape, np.float32),
            np.empty(self.shape, np.uint8),
            np.empty(self.shape, np.uint8),
            np.zeros((max(1, min(self.shape[0], 8 * numba.get_num_threads())), STATS_COLUMNS)),
        )
        with reflected_lists_quiet():
            merge_kernel(
                *inputs,
                StartSums(self._sum, self._cnt, self.stream),
                IterationOptions(
                    int(opts.iterations),
                    float(opts.tolerance),
                    float(opts.saturation_sigmas),
                    opts.saturation == "probabilistic",
                    float(opts.clip_sigmas),
                    float(opts.censored_spacing),
                ),
                out,
                np.zeros(1, np.float32 if single else np.float64),
            )
        return out

    def result(self, *, release_frames: Callable[[], Any] | None = None) -> HdrResult:
        """Run the iterations (Eq. 12-13, Fig. 3) and return the merge.

        ``release_frames`` is called when the frames have been read: after the iterations and
        again after the calibration's error terms (which read them only for frames whose dark
        level comes from the calibration's maps). The file layer drops the pages of its
        memory-mapped frames there, so that the frames and every output are not all resident
        at once."""
        if not len(self):
            raise InputError("no frames to merge")
        self.apply_exposure_times()
        values, darks, master = self._kernel_frames()
        single = SINGLE_PRECISION_WEIGHTS and self._single_precision_safe(values, darks, master)
        inputs = self._kernel_inputs(values, darks, master)
        out = self._iterate(inputs, single)
        irr, sig, nexp = out.irradiance, out.sigma, out.nexp
        release = release_frames or (lambda: None)
        release()
        timed = self.frames.shares_timed_master()
        sig_cal, sig_master, cal_info = shared_terms(
            irr, nexp, out.rules, inputs, timed, self.calibration, self.maps.prnu_used, self.options
        )
        release()
        add_in_quadrature(sig, sig_cal, sig_master)
        quality, n_defects = flag_defects(irr, sig, nexp, self.calibration.defect_map)
        if out.stats[:, 3].any():  # photosites that lost a sample to the clip rule (none: no full-size pass)
            flag_clip_rejected(quality, out.rules)
        book = self.frames
        masked = flag_masked((irr, sig, nexp, quality), book.masks, book.times, self.calibration.params, self.maps)
        info = self._info(out.stats, single, {"defects_flagged": n_defects, **masked}, cal_info)
        if sig_cal is not None:
            clear_unmeasured(sig_cal, quality, nexp)
        return HdrResult(irr, sig, nexp, quality=quality, sigma_calibration=sig_cal, header={"merge": info})

    def _info(self, stats: np.ndarray, single: bool, flags: dict[str, Any], cal_info: dict[str, Any]) -> dict[str, Any]:
        """The merge's header entries (:data:`pipeline.schema.HEADER_KEYS`) from the kernel's
        ``stats``, the weights' precision, the flags' counts (``defects_flagged`` and those of
        :func:`pipeline.merge.flags.flag_masked`) and the calibration's errors."""
        opts, book = self.options, self.frames
        strategy = self.dark_strategy
        n_own = sum(d is not None for d in book.darks)
        saturated = int(stats[:, 0].sum()) - flags["masked_everywhere"]
        return {
            "method": "optimal ML merge (Eq. 6, 8-13, Fig. 3)",
            **opts.to_dict(),
            "dark_strategy": strategy,
            "n_dark": float(opts.n_dark) if strategy == DarkStrategy.MASTER else None,
            "dark_strategies": [s.value for s in book.strategies],
            "n_dark_per_frame": list(book.n_darks),
            "dark_shared_by": book.dark_groups(),
            "master_dark": book.master_dark is not None,
            "prnu": self.maps.prnu_used,
            "exposure_times": list(book.times),
            **self._exposure_info(),
            "n_frames": len(book),
            "n_darks": n_own + (1 if book.master_dark is not None and 2 in book.kinds else 0),
            "saturated_everywhere": saturated,
            **flags,
            "clip_rejected": int(stats[:, 3].sum()),
            "clip_rejected_samples": int(stats[:, 4].sum()),
            "censored_fallback": int(stats[:, 5].sum()) if opts.saturation == "probabilistic" else None,
            "iterations_used_mean": float(stats[:, 1].sum() / max(self.shape[0] * self.shape[1], 1)),
            "iterations_used_max": int(stats[:, 2].max()),
            "kernel": "numba",
            "weights_precision": "float32" if single else "float64",
            "calibration_error": cal_info,
        }


def _image_shape(shape: Sequence[int]) -> tuple[int, int]:
    """``shape`` as two positive ints (rows, columns)."""
    dims = tuple(int(s) for s in shape)
    if len(dims) != 2 or min(dims) < 1:
        raise InputError(f"image shape must be two positive sizes, got {shape!r}")
    return dims[0], dims[1]


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
    values: Iterable[ArrayLike],
    times: Iterable[float],
    calibration: Calibration,
    darks: np.ndarray | Sequence[ArrayLike | None] | None = None,
    *,
    dark_strategies: Sequence[DarkStrategy | str | None] | None = None,
    n_darks: Sequence[float | None] | None = None,
    masks: Sequence[ArrayLike | None] | None = None,
    **options: Any,
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
    master, per_frame = _dark_arrays(darks, len(values), options)
    default = as_strategy(options.get("dark_strategy"))
    if darks is None and default in (DarkStrategy.MATCHED, DarkStrategy.MASTER) and not all(strategies):
        raise InputError(f"the {default} dark strategy needs dark frames")
    # Frames merged with the model strategy ignore any dark frame given for them.
    per_frame = [None if (s or default) is DarkStrategy.MODEL else d for d, s in zip(per_frame, strategies)]
    n_per_frame = _per_frame(n_darks, len(values), "master-dark frame counts")
    masks_per_frame = _per_frame(masks, len(values), "masks")
    acc = MergeAccumulator(calibration, shape, master_dark=master, stream=False, **options)
    return _accumulate(acc, values, times, per_frame, strategies, n_per_frame, masks_per_frame)


def _dark_arrays(
    darks: np.ndarray | Sequence[ArrayLike | None] | None, n: int, options: dict[str, Any]
) -> tuple[np.ndarray | None, list[Any]]:
    """The single master dark and the per-frame dark levels of :func:`merge_arrays`' ``darks``
    for ``n`` frames; one master dark makes ``master`` the default strategy in ``options``."""
    if darks is None:
        return None, [None] * n
    if isinstance(darks, np.ndarray) and darks.ndim == 2:
        options.setdefault("dark_strategy", DarkStrategy.MASTER)
        return darks, [None] * n
    per_frame = list(darks)
    if len(per_frame) != n:
        raise InputError(f"{len(per_frame)} dark frames for {n} frames")
    return None, per_frame


def _accumulate(acc: MergeAccumulator, *per_frame: Sequence[Any]) -> HdrResult:
    """The batch merge of aligned per-frame inputs (values, times, darks, strategies, n_darks,
    masks) with ``acc`` (one pass)."""
    for v, t, d, s, n, m in zip(*per_frame):
        acc.add(v, t, d, strategy=s, n_dark=n, mask=m)
    return acc.result()


def _per_frame(items: Iterable[Any] | None, n: int, what: str) -> list[Any]:
    """``items`` as a list of ``n`` (None: ``n`` Nones)."""
    if items is None:
        return [None] * n
    items = list(items)
    if len(items) != n:
        raise InputError(f"{len(items)} {what} for {n} frames")
    return items


def compile_kernels() -> list[str]:
    """Compile the merge kernels for merges of raw files (16-bit frames, with or without dark
    frames, weights in float32 and in float64, the streamed first pass, the calibration's
    error terms), or load them from numba's cache where they were compiled before: what
    ``hdrcap warm-up`` runs after an install, so that the first merge does not wait for the
    compiler. It changes no result.

    Returns
    -------
    list of str
        The specialisations made ready, e.g. ``"uint16 frames, float32 weights"``.

    Examples
    --------
    >>> compile_kernels()  # doctest: +SKIP
    ['uint16 frames, float32 weights', 'uint16 frames, float64 weights']
    """
    from hdrcap.pipeline.params import SensorParams

    params = SensorParams(g=1.0, mu_R=10.0, sigma2_R=4.0, v_sat=4000.0, white_level=4095.0)
    calibration = Calibration(params, stderr={"mu_R": 0.1})  # an error term: its kernel too
    acc = MergeAccumulator(calibration, (2, 2), stream=True)  # the streamed first pass too
    for i in range(2):
        acc.add(np.full((2, 2), 100 * (i + 1), np.uint16), 0.01 * (i + 1), np.full((2, 2), 10, np.uint16))
    info = acc.result().info
    single = info["weights_precision"] == "float32"
    acc._iterate(acc._kernel_inputs(*acc._kernel_frames()), not single)  # the other precision
    return [f"uint16 frames, {p} weights" for p in ("float32", "float64")]
