"""Shared parameter types: the calibrated camera model the estimator assumes.

Both ``pipeline`` (the estimator) and ``mock_camera`` (the physics) read these types; the
simulator adds its own physical details (full well, hot pixels, temperature) on top.
Units: X in electrons per second per photosite, t in seconds, raw values
in DN, g in DN per electron, sigma2_R in DN^2 (quantisation included), D in electrons per
second.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrcap.pipeline.times import find_exposure, same_exposure

__all__ = ["SensorParams", "Calibration", "ShutterTable", "THIRD_STOP_TIMES", "DEFECT_BITS"]

_FAST = (
    8000,
    6400,
    5000,
    4000,
    3200,
    2500,
    2000,
    1600,
    1250,
    1000,
    800,
    640,
    500,
    400,
    320,
    250,
    200,
    160,
    125,
    100,
    80,
    60,
    50,
    40,
    30,
    25,
    20,
    15,
    13,
    10,
    8,
    6,
    5,
    4,
)
_SLOW = (0.3, 0.4, 0.5, 0.6, 0.8, 1, 1.3, 1.6, 2, 2.5, 3.2, 4, 5, 6, 8, 10, 13, 15, 20, 25, 30)

#: The usual nominal 1/3-EV shutter speeds of a camera, 1/8000 s to 30 s, ascending, seconds
#: (55 values). Shared by the simulated camera and the planner's default ladder.
THIRD_STOP_TIMES: tuple[float, ...] = tuple(1.0 / d for d in _FAST) + tuple(float(s) for s in _SLOW)


#: Bits of a calibration's defect map (a uint8 per photosite): what each kind of defective
#: photosite sets (a photosite may set several). See docs/calibration.md for the thresholds.
DEFECT_BITS: dict[str, int] = {"dead": 1, "weak": 2, "hot": 4, "stuck": 8}


@dataclass(frozen=True)
class SensorParams:
    """Scalar camera noise model of the paper (Eq. 2-5, Table 2).

    Attributes
    ----------
    g : float
        Overall camera gain, DN per electron.
    mu_R : float
        Mean of the readout noise (bias level), DN.
    sigma2_R : float
        Variance of the readout noise including quantisation, DN^2.
    v_sat : float
        Saturation limit, DN: samples at or above ``v_sat`` are treated as saturated.
    white_level : float
        Largest value the ADC can write, DN (``2**bits - 1``).
    dark_current : float
        Mean dark current D, electrons per second per photosite.
    name : str
        Free-text identity (camera model, preset name).
    """

    g: float
    mu_R: float
    sigma2_R: float
    v_sat: float
    white_level: float
    dark_current: float = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        for fname in ("g", "sigma2_R", "v_sat", "white_level"):
            value = getattr(self, fname)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"SensorParams.{fname} must be finite and > 0, got {value!r}")
        if not np.isfinite(self.mu_R) or self.mu_R < 0:
            raise ValueError(f"SensorParams.mu_R must be finite and >= 0, got {self.mu_R!r}")
        if not np.isfinite(self.dark_current) or self.dark_current < 0:
            raise ValueError(f"SensorParams.dark_current must be finite and >= 0, got {self.dark_current!r}")

    def replace(self, **changes: Any) -> SensorParams:
        """A copy with some fields changed.

        Parameters
        ----------
        **changes
            Field names and new values (same units as the fields).

        Returns
        -------
        SensorParams
        """
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dict (units as the fields).

        Returns
        -------
        dict
        """
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ShutterTable:
    """Per-time shutter corrections of a camera: t_eff = factor * t_nom (``hdrcap calibrate
    --shutter``, :func:`hdrcap.pipeline.calibration.shutter.estimate_shutter_table`).

    The absolute scale is the reference time's: its factor is 1 by definition, and every other
    factor is the ratio of effective times measured against it (the paper's Sec. 7
    normalisation, made once per camera).

    Attributes
    ----------
    times : tuple of float
        Nominal exposure times, s, ascending, distinct (:func:`pipeline.times.same_exposure`).
    factors : tuple of float
        t_eff / t_nom of each time relative to the reference time (dimensionless, > 0).
    stderr : tuple of float
        Standard error of each factor, relative (dimensionless, >= 0; 0 at the reference).
    reference : float
        The reference time, s (one of ``times``).
    frames : tuple of int
        Frames measured at each time (>= 1).
    jitter : float or None
        Relative standard deviation of one frame's effective time about its time's factor
        (frame-to-frame shutter jitter, and bias drift seen as such), measured from the scatter
        of repeated frames; None when no time had two frames.
    """

    times: tuple[float, ...]
    factors: tuple[float, ...]
    stderr: tuple[float, ...]
    reference: float
    frames: tuple[int, ...]
    jitter: float | None = None

    def __post_init__(self) -> None:
        n = len(self.times)
        if n == 0 or not (len(self.factors) == len(self.stderr) == len(self.frames) == n):
            raise ValueError("shutter table: times, factors, stderr and frames must have one entry per time")
        for name, lo in (("times", 0.0), ("factors", 0.0)):
            vals = getattr(self, name)
            if not all(isinstance(v, (int, float)) and np.isfinite(v) and v > lo for v in vals):
                raise ValueError(f"shutter table: {name} must be finite numbers > 0")
        if not all(isinstance(v, (int, float)) and np.isfinite(v) and v >= 0 for v in self.stderr):
            raise ValueError("shutter table: standard errors must be finite numbers >= 0")
        if not all(isinstance(k, int) and k >= 1 for k in self.frames):
            raise ValueError("shutter table: frame counts must be integers >= 1")
        if any(b <= a or same_exposure(a, b) for a, b in zip(self.times, self.times[1:])):
            raise ValueError("shutter table: times must be ascending and distinct")
        if find_exposure(self.reference, self.times) is None:
            raise ValueError(f"shutter table: reference time {self.reference!r} s is not one of its times")
        if self.jitter is not None and not (np.isfinite(self.jitter) and self.jitter >= 0):
            raise ValueError("shutter table: jitter must be a finite number >= 0 or null")

    def lookup(self, t: float) -> tuple[float, float] | None:
        """The correction of nominal time ``t`` (s): (factor, relative standard error), or None
        when ``t`` is not one of the table's times (:func:`pipeline.times.find_exposure`)."""
        i = find_exposure(t, self.times)
        return None if i is None else (self.factors[i], self.stderr[i])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields (units as the attributes)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, raw: Any) -> ShutterTable:
        """The table from :meth:`to_dict`'s form.

        Raises
        ------
        ValueError
            Not a table of that form, or values :meth:`__post_init__` refuses.
        """
        if not isinstance(raw, dict) or set(raw) - {f.name for f in dataclasses.fields(cls)}:
            raise ValueError("shutter table: not a table of times, factors, stderr, reference, frames, jitter")
        try:
            return cls(
                times=tuple(raw["times"]),
                factors=tuple(raw["factors"]),
                stderr=tuple(raw["stderr"]),
                reference=raw["reference"],
                frames=tuple(raw["frames"]),
                jitter=raw.get("jitter"),
            )
        except (KeyError, TypeError) as err:
            raise ValueError(f"shutter table: missing or malformed entry ({err})") from None


@dataclass(frozen=True)
class Calibration:
    """Everything the merge needs to know about a camera: scalars, maps and provenance.

    Attributes
    ----------
    params : SensorParams
        The scalar model.
    prnu : numpy.ndarray or None
        Per-photosite gain a_j (Eq. 14), mean 1, float32, shape of the raw mosaic.
        ``None`` means a_j = 1 everywhere.
    bias_map : numpy.ndarray or None
        Per-photosite mean bias (offset) in DN, float32; ``None`` means ``params.mu_R``.
    dark_current_map : numpy.ndarray or None
        Per-photosite dark current in electrons per second, float32; ``None`` means
        ``params.dark_current``.
    stderr : dict
        Standard error of each scalar estimate, keyed by field name, same unit as the field.
    provenance : dict
        Camera model and serial, ISO, temperature, frame counts, dates, hdrcap version.
    prnu_stderr : numpy.ndarray or None
        Estimated standard error of each a_j (dimensionless), float32; ``None`` if unknown.
    dark_library : str or None
        Folder of a dark library (master darks with their frame count N, see
        ``pipeline.calibration.darklibrary``) that belongs to this calibration; ``None`` if none.
    saturation_map : numpy.ndarray or None
        Per-photosite saturation limit, DN, float32 (from >= 3 saturation frames); ``None``
        means ``params.v_sat`` everywhere.
    bias_map_stderr : numpy.ndarray or None
        Standard error of each value of ``bias_map`` (sqrt(sigma2_R / n_bias)), DN, float32;
        ``None`` if unknown.
    dark_current_map_stderr : numpy.ndarray or None
        Standard error of each value of ``dark_current_map`` (from the regression, after the
        shrinkage toward D), e-/s, float32; ``None`` if unknown.
    defect_map : numpy.ndarray or None
        Defective photosites, uint8 bit field (:data:`DEFECT_BITS`: 1 dead, 2 weak, 4 hot,
        8 stuck; 0 a normal photosite); ``None`` if not measured.
    shutter : ShutterTable or None
        Per-time shutter corrections (``hdrcap calibrate --shutter``); ``None`` if not measured
        (the merge then starts from the nominal times).
    """

    params: SensorParams
    prnu: np.ndarray | None = None
    bias_map: np.ndarray | None = None
    dark_current_map: np.ndarray | None = None
    stderr: dict[str, float] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    prnu_stderr: np.ndarray | None = None
    dark_library: str | None = None
    saturation_map: np.ndarray | None = None
    bias_map_stderr: np.ndarray | None = None
    dark_current_map_stderr: np.ndarray | None = None
    defect_map: np.ndarray | None = None
    shutter: ShutterTable | None = None

    def replace(self, **changes: Any) -> Calibration:
        """A copy with some fields changed.

        Parameters
        ----------
        **changes
            Field names and new values.

        Returns
        -------
        Calibration
        """
        return dataclasses.replace(self, **changes)
