"""The simulated camera: a :class:`~mock_camera.sensor.SimulatedSensor` looking at a scene,
writing each capture as a DNG file the way a real camera writes raw files.
"""

from __future__ import annotations

import datetime as _dt
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from hdrcap.mock_camera.dng import exposure_rational, write_dng
from hdrcap.mock_camera.sensor import SensorSpec, SimulatedSensor

__all__ = ["SimulatedCamera"]


class SimulatedCamera:
    """A simulated raw camera.

    Parameters
    ----------
    spec : SensorSpec
        The sensor physics (see :mod:`mock_camera.sensor`).
    scene : numpy.ndarray
        Irradiance map, e-/s per photosite; its shape is the mosaic's.
    seed : int
        Seeds the fixed patterns and the temporal noise.
    temperature : float, optional
        Sensor temperature, degrees C (dark current doubles every
        ``spec.doubling_temperature``).
    serial : str
        Serial number written into the files.
    """

    def __init__(
        self,
        spec: SensorSpec,
        scene: np.ndarray,
        seed: int = 0,
        temperature: float | None = None,
        serial: str | None = None,
    ):
        self.spec = spec
        self.scene = np.asarray(scene, dtype=np.float64)
        self.sensor = SimulatedSensor(spec, self.scene.shape, seed=seed)
        self.temperature = temperature
        self.serial = serial or f"SIM{seed:06d}"
        self._clock = _dt.datetime.now(_dt.UTC).replace(microsecond=0)

    @staticmethod
    def actual_time(t: float) -> float:
        """The exposure time the camera really uses: the rational written in the file."""
        num, den = exposure_rational(t)
        return float(Fraction(num, den))

    def capture_array(self, t: float, dark: bool = False) -> np.ndarray:
        """Expose for ``t`` seconds (light blocked when ``dark``) and return the uint16 mosaic."""
        return self.sensor.expose(self.scene, self.actual_time(t), dark=dark, temperature=self.temperature)

    def capture_image_to(
        self, path: str | os.PathLike[str], t: float, *, bits: int | None = None, msb: bool = False, dark: bool = False
    ) -> Path:
        """Capture one frame and write it as a PNG or TIFF (by the suffix), as machine-vision
        software saves it: no metadata, the ADC's values converted to ``bits`` bits
        (:func:`mock_camera.imagefiles.requantise`, im2uint8-style rounding and clipping; default
        the ADC's own), in 8-bit words up to 8 bits, else in 16-bit words, LSB-aligned or
        (``msb``) MSB-aligned."""
        from hdrcap.mock_camera.imagefiles import msb_align, requantise, write_image

        mosaic = self.capture_array(t, dark=dark)
        n = bits or self.spec.bits
        out = mosaic if n == self.spec.bits else requantise(mosaic, self.spec.bits, n)
        if msb:
            out = msb_align(out, n)
        elif n <= 8:
            out = out.astype(np.uint8)
        return write_image(path, out)

    def capture_to(self, path: str | os.PathLike[str], t: float, dark: bool = False, overwrite: bool = False) -> Path:
        """Capture one frame and write it as a DNG to ``path`` (written atomically; an existing
        file is never replaced unless ``overwrite``)."""
        path = Path(path)
        mosaic = self.capture_array(t, dark=dark)
        self._clock += _dt.timedelta(seconds=max(1, int(np.ceil(t))))
        tmp = path.with_name(f".{path.name}.partial")
        with open(tmp, "wb") as f:
            write_dng(
                f,
                mosaic,
                exposure_time=t,
                iso=self.spec.iso,
                black_level=self.spec.mu_R,
                white_level=self.spec.white_level,
                cfa=self.spec.cfa,
                make=self.spec.make,
                model=self.spec.model,
                serial=self.serial,
                timestamp=self._clock,
                description="dark frame" if dark else "",
            )
            f.flush()
            os.fsync(f.fileno())
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise
            except OSError:  # no hard links (exFAT/FAT): claim the name exclusively, then rename onto it
                os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
                os.replace(tmp, path)
            finally:
                tmp.unlink(missing_ok=True)
        return path
