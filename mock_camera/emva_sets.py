"""EMVA 1288 data sets (descriptor and images) written from the simulated sensor.

The EMVA 1288 standard (Release 3) measures a camera with pairs of images at a series of
photon counts, each with a dark pair at the same exposure time, plus optional stacks for the
non-uniformities. The photon count may be varied through the exposure time, through the
irradiance at a constant exposure time, or both; laboratories use all three, with images of 8
to 16 bits stored as PNG, TIFF or PGM and descriptors written on Windows or POSIX. This module
writes every such kind from a :class:`~hdrcap.mock_camera.sensor.SimulatedSensor`, so that the
analysis can be tested against the simulator's truth.

Descriptor lines: ``v 3.0``; ``n <bits> <width> <height>``; ``b <t ns> <photons>`` or
``d <t ns>`` open a bright or dark step; ``i <path>`` lists its images. The simulator's
photons are electrons (quantum efficiency 1): photons = X t per photosite.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrcap.mock_camera.sensor import SimulatedSensor

__all__ = ["EmvaSetSpec", "write_emva_set", "write_pgm"]

_FORMATS = ("png", "tif", "pgm")
_MODES = ("time", "irradiance", "both")


@dataclass(frozen=True)
class EmvaSetSpec:
    """What to measure and how to store it.

    Attributes
    ----------
    mode : {"time", "irradiance", "both"}
        How the photon count varies: exposure time at a constant irradiance, irradiance at a
        constant exposure time, or both (the time doubles half-way and the irradiance starts
        again).
    n_steps : int
        Bright steps (each with a dark pair at its exposure time).
    max_fraction : float
        Photon count of the last step, as a fraction of the count that reaches saturation
        (above 1 to show the saturation).
    exposure_time : float
        The constant exposure time, or the longest one when the time varies, s.
    min_fraction : float
        Photon count of the first step, fraction of the saturation count.
    stack : int
        Images of the bright and of the dark non-uniformity stack (0: none).
    image_format : {"png", "tif", "pgm"}
    windows_paths : bool
        Write image paths with backslashes.
    """

    mode: str = "time"
    n_steps: int = 16
    max_fraction: float = 1.1
    exposure_time: float = 0.02
    min_fraction: float = 0.02
    stack: int = 0
    image_format: str = "png"
    windows_paths: bool = False

    def __post_init__(self) -> None:
        if self.mode not in _MODES:
            raise ValueError(f"mode must be one of {', '.join(_MODES)}, got {self.mode!r}")
        if self.image_format not in _FORMATS:
            raise ValueError(f"image_format must be one of {', '.join(_FORMATS)}, got {self.image_format!r}")
        if self.n_steps < 3 or not 0 < self.min_fraction < self.max_fraction or self.exposure_time <= 0:
            raise ValueError("need >= 3 steps, 0 < min_fraction < max_fraction and a positive exposure time")


def _steps(spec: EmvaSetSpec, saturation_count: float) -> list[tuple[float, float]]:
    """(exposure time s, photons per photosite) of every bright step."""
    counts = np.linspace(spec.min_fraction, spec.max_fraction, spec.n_steps) * saturation_count
    T = spec.exposure_time
    if spec.mode == "time":
        return [(T * c / counts[-1], c) for c in counts]
    if spec.mode == "irradiance":
        return [(T, c) for c in counts]
    half = spec.n_steps // 2  # "both": the first half at T/2, the second at T
    return [(T / 2 if i < half else T, c) for i, c in enumerate(counts)]


def write_pgm(path: Path, data: np.ndarray, maxval: int) -> None:
    """Write a binary PGM (P5): one byte per value up to ``maxval`` 255, else two, big-endian.

    Parameters
    ----------
    path : Path
    data : numpy.ndarray
        2-D unsigned integers, DN.
    maxval : int
        The largest value the format declares (2**bits - 1).
    """
    h, w = data.shape
    body = data.astype(">u2" if maxval > 255 else "u1").tobytes()
    path.write_bytes(f"P5\n{w} {h}\n{maxval}\n".encode("ascii") + body)


def _save(path: Path, data: np.ndarray, bits: int, fmt: str) -> None:
    """One image in ``fmt``: 8-bit PNG/TIFF for <= 8 bits, else 16-bit; PGM with maxval."""
    arr = data.astype(np.uint8 if bits <= 8 else np.uint16)
    if fmt == "pgm":
        write_pgm(path, arr, (1 << bits) - 1)
    elif fmt == "tif":
        import tifffile

        tifffile.imwrite(path, arr)
    else:
        from PIL import Image

        Image.fromarray(arr).save(path)


def write_emva_set(
    sensor: SimulatedSensor, folder: str | Path, spec: EmvaSetSpec = EmvaSetSpec(), seed: int = 0
) -> Path:
    """Simulate an EMVA 1288 measurement and write its descriptor and images.

    Parameters
    ----------
    sensor : SimulatedSensor
        The camera (its bit depth sets the images' and the descriptor's).
    folder : str or Path
        Output folder (created); images go to ``images/``.
    spec : EmvaSetSpec
        The kind of data set.
    seed : int
        Seed of the temporal noise.

    Returns
    -------
    Path
        The descriptor, ``folder/EMVA1288_Data.txt``.
    """
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 1288])
    s = sensor.spec
    h, w = sensor.shape
    saturation_count = (s.v_saturation - s.mu_R) / s.g
    lines = ["v 3.0", f"n {s.bits} {w} {h}"]
    sep = "\\" if spec.windows_paths else "/"
    k = 0

    def put(data: np.ndarray) -> None:
        nonlocal k
        name = f"img_{k:04d}.{spec.image_format}"
        _save(folder / "images" / name, data, s.bits, spec.image_format)
        lines.append(f"i images{sep}{name}")
        k += 1

    def step(t: float, photons: float | None, n: int) -> None:
        lines.append(f"b {t * 1e9:.1f} {photons:.3f}" if photons is not None else f"d {t * 1e9:.1f}")
        for _ in range(n):
            put(sensor.expose(photons / t if photons is not None else 0.0, t, dark=photons is None, rng=rng))

    steps = _steps(spec, saturation_count)
    for t, photons in steps:
        step(t, photons, 2)
        step(t, None, 2)
    if spec.stack:
        t, photons = steps[len(steps) // 2]
        step(t, photons, spec.stack)
        step(t, None, spec.stack)
    path = folder / "EMVA1288_Data.txt"
    path.write_text("\n".join(lines) + "\n")
    return path
