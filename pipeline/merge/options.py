"""The options of the optimal merge: :class:`MergeOptions` and dark strategies by name.

:class:`pipeline.merge.accumulator.MergeAccumulator` takes its keyword options as the fields of
:class:`MergeOptions`, which refuses bad values with an :class:`pipeline.errors.InputError`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.exposure_ratio import EXPOSURE_TIME_MODES
from hdrcap.pipeline.noise import DarkStrategy

__all__ = ["MergeOptions", "as_strategy", "CENSORED_SPACING"]


_SATURATION_MODELS = ("threshold", "probabilistic")
_PRNU_MODES = ("map", "scalar")

#: Widest spacing of exposure times (ratio) at which the probabilistic model's censored
#: likelihood keeps its estimate near a clip level (``MergeOptions.censored_spacing``): in the
#: sweep of benchmarks/extremes.py its z is honest at x10 and not at x100 (docs/merge.md, item 5).
CENSORED_SPACING = 10.0


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
    clip_sigmas : float
        Threshold k_c of the clip rule, standard deviations (0 turns the rule off): where the
        full well clips before the ADC, a usable sample whose raw value lies within 3 of its
        model standard deviation at v_sat of v_sat (possibly a clipped value that slipped
        under v_sat) is rejected when it lies more than k_c standard deviations below the
        estimate of the other samples (leave-one-out; docs/merge.md, item 4).
    censored_spacing : float
        ``saturation="probabilistic"`` only: the censored likelihood's estimate stands where the
        samples it rests on near their clip level (censored, or possibly clipped) come from
        exposures at most this many times longer than the longest sample surely below its clip;
        elsewhere the threshold estimate is kept and counted (``censored_fallback``;
        docs/merge.md, item 5). Default :data:`CENSORED_SPACING`; 0: always the censored
        likelihood's. Dimensionless, >= 1 or 0.
    exposure_times : {"nominal", "effective"}
        ``effective``: each frame's actual exposure time replaces the nominal one: first the
        calibration's shutter table (``Calibration.shutter``, per nominal time, as each frame
        is added), then the bracket's own estimate (:mod:`pipeline.exposure_ratio`, Sec. 7)
        refines the ratios of the frames that share well-exposed photosites, before the
        iterations (:func:`pipeline.merge.files.merge_files` and the capture session default to
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
    clip_sigmas: float = 4.0
    censored_spacing: float = CENSORED_SPACING

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
        if not (np.isfinite(self.clip_sigmas) and self.clip_sigmas >= 0):
            raise InputError(f"clip_sigmas must be finite and >= 0, got {self.clip_sigmas!r}")
        if not (np.isfinite(self.censored_spacing) and (self.censored_spacing >= 1 or self.censored_spacing == 0)):
            raise InputError(f"censored_spacing must be >= 1 (or 0), got {self.censored_spacing!r}")
        if self.exposure_times not in EXPOSURE_TIME_MODES:
            raise InputError(f"exposure_times must be effective or nominal, got {self.exposure_times!r}")

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON-ready data (the dark strategy by its name)."""
        out = dataclasses.asdict(self)
        out["dark_strategy"] = None if self.dark_strategy is None else self.dark_strategy.value
        return out
