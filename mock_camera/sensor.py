"""A physically based, seeded simulation of a linear raw image sensor.

This is physics, not the estimator's model: electrons are Poisson, read noise Gaussian,
values are rounded and clipped. It never calls ``pipeline.noise`` (tests must be able to
catch a wrong variance formula).

Per exposure of time t (s) on a scene of irradiance X (e-/s per photosite):

* t_eff = t (1 + jitter N(0,1)) when shutter jitter is configured, one draw per frame;
* E = min(Poisson(t_eff (a X + D(T))), full_well) electrons, a the per-photosite PRNU gain
  and D(T) the per-photosite dark current at sensor temperature T;
* V = clip(round(g E + mu_R + offset_j + N(0, s_e^2)), 0, 2^bits - 1) DN, with the
  electronic read-noise variance s_e^2 = sigma2_R - 1/12 so that the total readout variance
  including rounding equals the calibrated sigma2_R (Eq. 3).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from hdrcap.pipeline.params import SensorParams

__all__ = ["SensorSpec", "SimulatedSensor", "PRESETS", "preset", "QUANTISATION_VARIANCE"]

#: Variance of the rounding error of a uniform quantiser with step 1 DN.
QUANTISATION_VARIANCE = 1.0 / 12.0


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
    iso : int
        ISO written into the files.
    width, height : int
        Default mosaic size, photosites.
    cfa : str
        Bayer pattern of the mosaic, four letters from R, G, B (row-major 2x2 tile).
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
        if len(self.cfa) != 4 or set(self.cfa) - set("RGB"):
            raise ValueError(f"cfa must be four letters of R, G, B, got {self.cfa!r}")

    @property
    def white_level(self) -> int:
        return (1 << self.bits) - 1

    @property
    def v_saturation(self) -> float:
        """Mean raw value of a saturated photosite (full well or ADC limit, whichever first)."""
        return min(self.mu_R + self.g * self.full_well, float(self.white_level))

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
        if self.mu_R + self.g * self.full_well < self.white_level:
            v_sat = self.mu_R + self.g * self.full_well - 3 * sigma_r
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

    def replace(self, **changes) -> "SensorSpec":
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


def preset(name: str, **changes) -> SensorSpec:
    """Return the preset ``name`` (``camera-A`` or ``camera-B``), optionally modified."""
    try:
        spec = PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown camera preset {name!r}; choose from {', '.join(PRESETS)}") from None
    return spec.replace(**changes) if changes else spec


class SimulatedSensor:
    """A sensor instance: a spec plus its fixed patterns (PRNU, DCNU, hot pixels, offsets).

    The fixed patterns are drawn once from ``seed``; every exposure draws its temporal noise
    from the generator given to :meth:`expose` (or from the sensor's own stream).
    """

    def __init__(self, spec: SensorSpec, shape: tuple[int, int] | None = None, seed: int = 0):
        self.spec = spec
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
        if spec.hot_pixel_fraction > 0:
            hot = pattern_rng.random((h, w)) < spec.hot_pixel_fraction
            dcnu = np.where(hot, spec.hot_pixel_factor, dcnu)
        self.dark_pattern = dcnu  # relative dark current per photosite, mean ~1
        self.offset = (
            spec.offset_fpn * pattern_rng.standard_normal((h, w)) if spec.offset_fpn > 0 else None
        )

    def dark_current_map(self, temperature: float | None = None) -> np.ndarray:
        """Per-photosite dark current at ``temperature``, e-/s."""
        return self.spec.dark_current_at(temperature) * self.dark_pattern

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

        ``dark=True`` blocks the light (a dark frame); ``t=0`` gives a bias frame.
        """
        spec = self.spec
        rng = self.rng if rng is None else rng
        if t < 0 or not np.isfinite(t):
            raise ValueError(f"exposure time must be finite and >= 0, got {t!r}")
        t_eff = t
        if spec.shutter_jitter > 0 and t > 0:
            t_eff = t * max(0.0, 1.0 + spec.shutter_jitter * rng.standard_normal())
        rate = self.dark_current_map(temperature)
        if not dark:
            X = np.broadcast_to(np.asarray(X, dtype=np.float64), self.shape)
            if np.any(X < 0) or not np.all(np.isfinite(X)):
                raise ValueError("irradiance must be finite and >= 0")
            rate = rate + self.prnu * X
        electrons = rng.poisson(rate * t_eff).astype(np.float64)
        np.minimum(electrons, spec.full_well, out=electrons)
        value = spec.g * electrons + spec.mu_R
        if self.offset is not None:
            value += self.offset
        sigma_e = np.sqrt(spec.sigma2_R - QUANTISATION_VARIANCE)
        value += sigma_e * rng.standard_normal(self.shape)
        np.rint(value, out=value)
        np.clip(value, 0, spec.white_level, out=value)
        return value.astype(np.uint16)
