"""A physically based, seeded simulation of a linear raw image sensor.

This is physics, not the estimator's model: electrons are Poisson, read noise Gaussian,
values are rounded and clipped. It never calls ``pipeline.noise`` (tests must be able to
catch a wrong variance formula).

Per exposure of time t (s) on a scene of irradiance X (e-/s per photosite):

* t_eff = t (1 + e(t)) (1 + jitter N(0,1)): e(t) the systematic shutter error of the nominal
  time t (uniform in +-``shutter_error``, fixed per time and sensor seed), the jitter one draw
  per frame;
* E = min(Poisson(t_eff (a X + D(T))), full_well) electrons, a the per-photosite PRNU gain
  (0 for a dead photosite, ``weak_factor`` times it for a weak one) and D(T) the per-photosite
  dark current at sensor temperature T (``hot_pixel_factor`` times the mean for a hot one);
* soft non-linearity near full well: E' = E (1 - n (E / full_well)^p), n = ``nonlinearity``;
* V = clip(round(g E' + mu_R + offset_j + b_f + r_row + c_col + N(0, s_e^2)), floor,
  2^bits - 1) DN, with b_f the frame's bias drift, r/c the frame's row and column offsets,
  floor = ``black_clip`` and the electronic read-noise variance s_e^2 = sigma2_R - 1/12 so that
  the total readout variance including rounding equals the calibrated sigma2_R (Eq. 3);
* a stuck photosite writes its own constant value, whatever the light and the time.

Every effect beyond Eq. 3 is off by default (and in the presets camera-A and camera-B);
``preset(name, realistic=True)`` and the preset camera-R switch on a realistic set
(:data:`REALISTIC`). The true defect sets and shutter errors are attributes of
:class:`SimulatedSensor`, for tests.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.params import Calibration, SensorParams

__all__ = [
    "SensorSpec",
    "SimulatedSensor",
    "PRESETS",
    "REALISTIC",
    "preset",
    "preset_name",
    "preset_calibration",
    "QUANTISATION_VARIANCE",
    "DEFECT_KINDS",
]

#: Variance of the rounding error of a uniform quantiser with step 1 DN.
QUANTISATION_VARIANCE = 1.0 / 12.0

#: Kinds of defective photosite the simulator knows (keys of :attr:`SimulatedSensor.defects`).
DEFECT_KINDS = ("dead", "weak", "hot", "stuck")


@dataclass(frozen=True)
class SensorSpec:
    """Physical description of a simulated sensor.

    Attributes
    ----------
    name : str
        Preset name or camera model.
    g : float
        Gain, DN per electron.
    mu_R : float
        Bias level, DN.
    sigma2_R : float
        Total readout variance including quantisation, DN^2 (>= 1/12).
    bits : int
        ADC bit depth; the white level is 2**bits - 1 DN.
    full_well : float
        Full-well capacity, electrons.
    dark_current : float
        Mean dark current at ``temperature_ref``, electrons per second.
    dcnu : float
        Relative spread (std / mean) of the per-photosite dark current (log-normal).
    temperature_ref : float
        Reference sensor temperature, degrees C.
    doubling_temperature : float
        Dark current doubles every this many degrees C.
    prnu : float
        Standard deviation of the per-photosite gain a (mean 1).
    offset_fpn : float
        Standard deviation of a per-photosite bias offset (DSNU of the bias), DN.
    hot_pixel_fraction : float
        Fraction of photosites whose dark current is ``hot_pixel_factor`` times the mean.
    hot_pixel_factor : float
        Dark-current multiplier of a hot pixel.
    shutter_jitter : float
        Relative standard deviation of the actual exposure time, per frame.
    dead_fraction : float
        Fraction of photosites that do not respond to light (a = 0; bias, read noise and dark
        current as the others).
    weak_fraction, weak_factor : float
        Fraction of photosites whose response to light is ``weak_factor`` times their PRNU gain.
    stuck_fraction : float
        Fraction of photosites that always write one constant value (uniform over the ADC
        range, drawn once), without noise.
    shutter_error : float
        Half-width of the systematic relative error of each nominal exposure time: the actual
        time is t (1 + e(t)), e(t) uniform in +-``shutter_error``, fixed for a time and a
        sensor seed.
    row_noise, column_noise : float
        Standard deviation of a per-frame offset common to a row (column), DN.
    bias_drift : float
        Standard deviation of a per-frame offset common to the whole frame, DN (the bias level
        moves between frames, independently from one frame to the next).
    black_clip : float
        Values below this level are written as it, DN (0: the ADC's own floor).
    nonlinearity : float
        Relative loss of response at full well: E' = E (1 - n (E / full_well)^p); within
        0..1/(p + 1) so that the response stays monotonic.
    nonlinearity_power : float
        The exponent p (the larger, the closer to full well the loss concentrates).
    iso : int
        ISO written into the files.
    width, height : int
        Default mosaic size, photosites.
    cfa : str
        Bayer pattern of the mosaic, four letters from R, G, B (row-major 2x2 tile), or ``mono``
        (no colour filter: a monochrome sensor; the physics is the same).
    make, model : str
        Written into the DNG files.
    """

    name: str
    g: float
    mu_R: float
    sigma2_R: float
    bits: int
    full_well: float
    dark_current: float = 0.5
    dcnu: float = 0.1
    temperature_ref: float = 20.0
    doubling_temperature: float = 6.3
    prnu: float = 0.01
    offset_fpn: float = 0.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_factor: float = 100.0
    shutter_jitter: float = 0.0
    dead_fraction: float = 0.0
    weak_fraction: float = 0.0
    weak_factor: float = 0.5
    stuck_fraction: float = 0.0
    shutter_error: float = 0.0
    row_noise: float = 0.0
    column_noise: float = 0.0
    bias_drift: float = 0.0
    black_clip: float = 0.0
    nonlinearity: float = 0.0
    nonlinearity_power: float = 6.0
    iso: int = 400
    width: int = 1024
    height: int = 768
    cfa: str = "RGGB"
    make: str = "hdrcap"
    model: str = "Simulated"

    def __post_init__(self) -> None:
        if self.sigma2_R < QUANTISATION_VARIANCE:
            raise ValueError("sigma2_R includes quantisation and cannot be below 1/12 DN^2")
        if self.g <= 0 or self.full_well <= 0 or not 8 <= self.bits <= 16:
            raise ValueError("g and full_well must be > 0 and bits within 8..16")
        if self.cfa != "mono" and (len(self.cfa) != 4 or set(self.cfa) - set("RGB")):
            raise ValueError(f"cfa must be four letters of R, G, B or mono, got {self.cfa!r}")
        fractions = (self.dead_fraction, self.weak_fraction, self.stuck_fraction, self.hot_pixel_fraction)
        if any(not 0 <= f <= 1 for f in fractions) or sum(fractions[:3]) > 1:
            raise ValueError("defect fractions must lie within 0..1 (dead + weak + stuck at most 1)")
        if min(self.shutter_error, self.shutter_jitter, self.row_noise, self.column_noise, self.bias_drift) < 0:
            raise ValueError("shutter errors and row, column and drift noise must be >= 0")
        if not 0 <= self.shutter_error < 1 or not 0 <= self.weak_factor <= 1:
            raise ValueError("shutter_error must lie within 0..1 and weak_factor within 0..1")
        if self.nonlinearity_power <= 0 or not 0 <= self.nonlinearity * (self.nonlinearity_power + 1) <= 1:
            raise ValueError("nonlinearity must lie within 0..1/(nonlinearity_power + 1) (monotonic response)")

    @property
    def white_level(self) -> int:
        return (1 << self.bits) - 1

    @property
    def full_well_signal(self) -> float:
        """Electrons a full photosite reports, after the soft non-linearity (e-)."""
        return self.full_well * (1.0 - self.nonlinearity)

    @property
    def v_saturation(self) -> float:
        """Mean raw value of a saturated photosite (full well or ADC limit, whichever first)."""
        return min(self.mu_R + self.g * self.full_well_signal, float(self.white_level))

    def dark_current_at(self, temperature: float | None) -> float:
        """Mean dark current at ``temperature`` (degrees C), e-/s (doubling law)."""
        if temperature is None:
            return self.dark_current
        return self.dark_current * 2.0 ** ((temperature - self.temperature_ref) / self.doubling_temperature)

    def nominal_params(self, temperature: float | None = None) -> SensorParams:
        """The scalar model a perfect calibration would find (Table 2 style).

        v_sat follows Sec. 6: mean minus three standard deviations of a saturation frame.
        """
        sigma_r = np.sqrt(self.sigma2_R)
        if self.mu_R + self.g * self.full_well_signal < self.white_level:
            v_sat = self.mu_R + self.g * self.full_well_signal - 3 * sigma_r
        else:
            v_sat = float(self.white_level)
        return SensorParams(
            g=self.g,
            mu_R=self.mu_R,
            sigma2_R=self.sigma2_R,
            v_sat=float(v_sat),
            white_level=float(self.white_level),
            dark_current=self.dark_current_at(temperature),
            name=self.name,
        )

    def replace(self, **changes: Any) -> SensorSpec:
        return dataclasses.replace(self, **changes)


def _full_well_for(v_sat: float, mu_R: float, g: float, sigma2_R: float) -> float:
    """Full well such that a saturation frame's mean - 3 std equals the published v_sat."""
    return (v_sat + 3.0 * np.sqrt(sigma2_R) - mu_R) / g


#: Presets with the paper's Table 2 values (g, mu_R, sigma2_R, v_sat; ISO 400).
#: camera-A (Canon EOS 5D, 12 bit): v_sat 3709 < 4095, so the full well clips before the ADC;
#: the full well is chosen so that mean - 3 sigma of a saturation frame is 3709 DN.
#: camera-B (Canon PowerShot S5, 10 bit): v_sat = 1023, the ADC clips first; the full well is
#: set 10 % above the ADC range. Dark current, DCNU and PRNU (1 %) are documented choices.
PRESETS: dict[str, SensorSpec] = {
    "camera-A": SensorSpec(
        name="camera-A",
        g=0.23,
        mu_R=128.0,
        sigma2_R=6.5,
        bits=12,
        full_well=_full_well_for(3709.0, 128.0, 0.23, 6.5),
        dark_current=0.2,
        model="Simulated camera-A (Canon EOS 5D, Table 2)",
    ),
    "camera-B": SensorSpec(
        name="camera-B",
        g=0.92,
        mu_R=32.0,
        sigma2_R=18.0,
        bits=10,
        full_well=1.1 * (1023.0 - 32.0) / 0.92,
        dark_current=1.0,
        model="Simulated camera-B (Canon PowerShot S5, Table 2)",
    ),
}


#: The realistic set of effects ``preset(name, realistic=True)`` adds: 0.1 % hot photosites
#: (100 times the mean dark current), 0.05 % dead, 0.05 % weak (half the response), 0.01 %
#: stuck, shutter errors of +-3 % per nominal time plus 0.2 % jitter per frame, a bias that
#: drifts by 0.2 DN between frames, a dark current of 2 e-/s with 30 % DCNU (at 300 s, 600 e-)
#: and a 0.2 % loss of response at full well (p = 8: the local slope is 0.65 % low at 88 % of
#: full well, 0.1 % at 70 %). No row or column noise (the merge's model has none).
REALISTIC: dict[str, float] = {
    "hot_pixel_fraction": 1e-3,
    "hot_pixel_factor": 100.0,
    "dead_fraction": 5e-4,
    "weak_fraction": 5e-4,
    "weak_factor": 0.5,
    "stuck_fraction": 1e-4,
    "shutter_error": 0.03,
    "shutter_jitter": 0.002,
    "bias_drift": 0.2,
    "dark_current": 2.0,
    "dcnu": 0.3,
    "nonlinearity": 0.002,
    "nonlinearity_power": 8.0,
}

PRESETS["camera-R"] = PRESETS["camera-A"].replace(
    name="camera-R", model="Simulated camera-R (camera-A with realistic defects, shutter and dark current)", **REALISTIC
)


def preset(name: str, realistic: bool = False, **changes: Any) -> SensorSpec:
    """Return the preset ``name``, optionally made realistic and modified.

    Parameters
    ----------
    name : str
        ``camera-A``, ``camera-B`` (ideal sensors of Table 2) or ``camera-R`` (camera-A with the
        :data:`REALISTIC` effects).
    realistic : bool
        Add the :data:`REALISTIC` effects (defects, shutter errors, dark current, drift).
    **changes
        Further :class:`SensorSpec` fields to set (applied last).

    Returns
    -------
    SensorSpec

    Raises
    ------
    ValueError
        Unknown preset.
    """
    try:
        spec = PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown camera preset {name!r}; choose from {', '.join(PRESETS)}") from None
    if realistic:
        spec = spec.replace(**REALISTIC)
    return spec.replace(**changes) if changes else spec


def _time_key(t: float) -> tuple[int, int]:
    """Two integers naming the nominal exposure time ``t`` (s): a unit tag and the time in
    nanoseconds below 1 s, else in microseconds (so that 1/125 computed two ways maps to one
    key, and no two distinct times share one)."""
    return (0, int(round(t * 1e9))) if t < 1 else (1, int(round(t * 1e6)))


class SimulatedSensor:
    """A sensor instance: a spec plus its fixed patterns (PRNU, DCNU, defects, offsets).

    The fixed patterns are drawn once from ``seed``; every exposure draws its temporal noise
    from the generator given to :meth:`expose` (or from the sensor's own stream). Truth for
    tests: :attr:`prnu` (a_j as the light sees it, 0 for dead photosites), :attr:`dark_pattern`
    and :meth:`dark_current_map`, :attr:`defects` (boolean maps per kind of
    :data:`DEFECT_KINDS`, disjoint), :attr:`stuck_values` (DN) and :meth:`shutter_factor`.
    """

    def __init__(self, spec: SensorSpec, shape: tuple[int, int] | None = None, seed: int = 0):
        self.spec = spec
        self.seed = seed
        self.shape = tuple(shape) if shape is not None else (spec.height, spec.width)
        pattern_rng = np.random.default_rng([seed, 1])
        self.rng = np.random.default_rng([seed, 2])
        h, w = self.shape
        self.prnu = (1.0 + spec.prnu * pattern_rng.standard_normal((h, w))).astype(np.float64)
        if spec.dcnu > 0:
            s2 = np.log1p(spec.dcnu**2)
            dcnu = pattern_rng.lognormal(-0.5 * s2, np.sqrt(s2), (h, w))
        else:
            dcnu = np.ones((h, w))
        hot = np.zeros((h, w), bool)
        if spec.hot_pixel_fraction > 0:
            hot = pattern_rng.random((h, w)) < spec.hot_pixel_fraction
        self.offset = spec.offset_fpn * pattern_rng.standard_normal((h, w)) if spec.offset_fpn > 0 else None
        self.defects = self._draw_defects(hot)
        self.dark_pattern = np.where(self.defects["hot"], spec.hot_pixel_factor, dcnu)  # relative, mean ~1
        self.prnu[self.defects["dead"]] = 0.0
        self.prnu[self.defects["weak"]] *= spec.weak_factor
        self.stuck_values = (
            np.random.default_rng([seed, 4])
            .integers(0, spec.white_level + 1, int(self.defects["stuck"].sum()))
            .astype(np.float64)
        )

    def _draw_defects(self, hot: np.ndarray) -> dict[str, np.ndarray]:
        """Disjoint boolean maps of the dead, weak, hot and stuck photosites (own random stream,
        so that the patterns of a sensor without defects do not change)."""
        spec = self.spec
        u = (
            np.random.default_rng([self.seed, 3]).random(self.shape)
            if (spec.dead_fraction + spec.weak_fraction + spec.stuck_fraction > 0)
            else np.ones(self.shape)
        )
        edges = np.cumsum([spec.dead_fraction, spec.weak_fraction, spec.stuck_fraction])
        dead = u < edges[0]
        weak = (u >= edges[0]) & (u < edges[1])
        stuck = (u >= edges[1]) & (u < edges[2])
        return {"dead": dead, "weak": weak, "hot": hot & ~(dead | weak | stuck), "stuck": stuck}

    def dark_current_map(self, temperature: float | None = None) -> np.ndarray:
        """Per-photosite dark current at ``temperature``, e-/s."""
        return self.spec.dark_current_at(temperature) * self.dark_pattern

    def shutter_factor(self, t: float) -> float:
        """The systematic ratio of actual to nominal exposure time, 1 + e(t) (no jitter).

        Parameters
        ----------
        t : float
            Nominal exposure time, s.

        Returns
        -------
        float
            Fixed for ``t`` and the sensor's seed; 1 without ``shutter_error`` or at t = 0.
        """
        if self.spec.shutter_error == 0 or t <= 0:
            return 1.0
        u = np.random.default_rng([self.seed, 5, *_time_key(t)]).random()
        return 1.0 + self.spec.shutter_error * (2.0 * u - 1.0)

    def _electrons(
        self, X, t_eff: float, dark: bool, temperature: float | None, rng: np.random.Generator
    ) -> np.ndarray:
        """Photo- and dark electrons of one exposure, clipped at full well, after the soft
        non-linearity (float64 e-)."""
        spec = self.spec
        rate = self.dark_current_map(temperature)
        if not dark:
            X = np.broadcast_to(np.asarray(X, dtype=np.float64), self.shape)
            if np.any(X < 0) or not np.all(np.isfinite(X)):
                raise ValueError("irradiance must be finite and >= 0")
            rate = rate + self.prnu * X
        electrons = rng.poisson(rate * t_eff).astype(np.float64)
        np.minimum(electrons, spec.full_well, out=electrons)
        if spec.nonlinearity > 0:
            electrons *= 1.0 - spec.nonlinearity * (electrons / spec.full_well) ** spec.nonlinearity_power
        return electrons

    def _frame_offsets(self, rng: np.random.Generator) -> np.ndarray | float:
        """The frame's bias drift plus its row and column offsets, DN (0 when all are off)."""
        spec = self.spec
        h, w = self.shape
        out: np.ndarray | float = 0.0
        if spec.bias_drift > 0:
            out = out + spec.bias_drift * rng.standard_normal()
        if spec.row_noise > 0:
            out = out + spec.row_noise * rng.standard_normal((h, 1))
        if spec.column_noise > 0:
            out = out + spec.column_noise * rng.standard_normal((1, w))
        return out

    def expose(
        self,
        X: np.ndarray | float,
        t: float,
        *,
        dark: bool = False,
        temperature: float | None = None,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Simulate one raw frame (uint16 mosaic) of irradiance ``X`` (e-/s) for ``t`` seconds.

        ``dark=True`` blocks the light (a dark frame); ``t=0`` gives a bias frame. ``t`` is the
        nominal time: the shutter error and jitter of the spec apply to it.
        """
        spec = self.spec
        rng = self.rng if rng is None else rng
        if t < 0 or not np.isfinite(t):
            raise ValueError(f"exposure time must be finite and >= 0, got {t!r}")
        t_eff = t * self.shutter_factor(t)
        if spec.shutter_jitter > 0 and t > 0:
            t_eff = t_eff * max(0.0, 1.0 + spec.shutter_jitter * rng.standard_normal())
        electrons = self._electrons(X, t_eff, dark, temperature, rng)
        value = spec.g * electrons + spec.mu_R
        if self.offset is not None:
            value += self.offset
        sigma_e = np.sqrt(spec.sigma2_R - QUANTISATION_VARIANCE)
        value += sigma_e * rng.standard_normal(self.shape)
        value += self._frame_offsets(rng)
        np.rint(value, out=value)
        np.clip(value, max(spec.black_clip, 0.0), spec.white_level, out=value)
        if self.stuck_values.size:
            value[self.defects["stuck"]] = self.stuck_values
        return value.astype(np.uint16)


def preset_name(camera: str) -> str:
    """The simulator preset a camera option names: ``camera-B``, or ``mock:camera-B`` (the
    spelling of ``hdrcap capture --camera``; ``mock:`` alone is camera-B).

    Parameters
    ----------
    camera : str
        The option's value.

    Returns
    -------
    str
        The preset name (not checked against :data:`PRESETS`).

    Raises
    ------
    InputError
        A real camera (``gphoto2[:MODEL]``): it has no nominal parameters.

    Examples
    --------
    >>> preset_name("mock:camera-A"), preset_name("camera-B")
    ('camera-A', 'camera-B')
    """
    backend, sep, name = camera.partition(":")
    if not sep:
        return camera
    if backend == "mock":
        return name or "camera-B"
    raise InputError(
        f"camera {camera}: a real camera has no nominal parameters; give its calibration file "
        "(--calibration, from `hdrcap calibrate`) or a simulator preset (mock:PRESET)"
    )


def preset_calibration(camera: str, temperature: float | None = None) -> Calibration:
    """The nominal calibration of a simulator preset: its Table 2 scalars, no maps, no
    standard errors (its calibration error is unknown, not zero).

    Parameters
    ----------
    camera : str
        Preset name, also spelt ``mock:NAME`` (:func:`preset_name`).
    temperature : float, optional
        Sensor temperature, degrees C (the dark current doubles every
        ``doubling_temperature``); recorded in the provenance.

    Returns
    -------
    Calibration
        g (DN/e-), mu_R (DN), sigma2_R (DN^2), v_sat (DN), dark current (e-/s); provenance
        ``source``, ``camera`` (the model name its files carry) and ``iso``.

    Raises
    ------
    InputError
        Unknown preset, or a real camera's name.

    Examples
    --------
    >>> cal = preset_calibration("camera-B")
    >>> cal.params.v_sat, cal.stderr
    (1023.0, {})
    """
    name = preset_name(camera)
    if name not in PRESETS:
        raise InputError(f"unknown camera preset {name!r}; choose from {', '.join(PRESETS)}")
    spec = PRESETS[name]
    prov: dict = {"source": f"preset {name} (nominal simulator parameters)", "camera": spec.model, "iso": spec.iso}
    if temperature is not None:
        prov["temperature"] = temperature
    return Calibration(params=spec.nominal_params(temperature), provenance=prov)
