"""The simulated machine-vision camera of the real-file checks (issue #28; docs/selfcal.md):
a 12-bit ADC whose frames are saved as 8-bit TIFF (im2uint8-style), 0.09 DN/e- in 8-bit DN,
read noise 5 e-, black 100 DN (12-bit), 1 % PRNU, Bayer GBRG, its seven exposure times, the
scenes of its seven brackets and how a bracket is written and read back.
``benchmarks/bench_realfiles.py`` and ``tests/end_to_end/test_png_tiff_cameras.py`` both take
it from here.

>>> MV.bits, MV.cfa, round(MV.g * 255 / 4095, 3) == G8
(12, 'GBRG', True)
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from hdrcap.mock_camera.sensor import SensorSpec

if TYPE_CHECKING:
    import numpy as np

    from hdrcap.mock_camera.sensor import SimulatedSensor
    from hdrcap.pipeline.io.raw import RawFrame

__all__ = ["ADC", "G8", "MV", "BRACKET_SCENES", "TIMES", "bracket_frames", "scene"]

#: Gain in 8-bit DN, DN/e-.
G8 = 0.09
#: Bits of the camera's ADC (its files keep the top 8).
ADC = 12
_G12 = G8 * 4095 / 255
#: The camera.
MV = SensorSpec(
    name="mv-8",
    g=_G12,
    mu_R=100.0,
    sigma2_R=(5 * _G12) ** 2 + 1 / 12,
    bits=ADC,
    full_well=1.2 * (4095 - 100) / _G12,
    prnu=0.01,
    dark_current=0.0,
    cfa="GBRG",
    make="Acme",
    model="MV-8",
)
#: The bracket's exposure times, s (25 ms to 3.9 s).
TIMES = (0.025, 0.05, 0.2, 0.39, 0.98, 1.95, 3.9)
#: The seven brackets of one camera: (scene, decades, level: the brightest photosite gives level x
#: 250 DN in the shortest frame).
BRACKET_SCENES = (
    ("hdr", 4.0, 1.0),
    ("hdr", 3.0, 0.5),
    ("gradient", 3.0, 0.3),
    ("patches", 3.0, 1.0),
    ("edges", 2.0, 0.2),
    ("hdr", 5.0, 2.0),
    ("gradient", 2.0, 0.1),
)


def scene(shape: tuple[int, int], name: str = "hdr", decades: float = 4.0, level: float = 1.0) -> np.ndarray:
    """The irradiance map (e-/s) of scene ``name`` over ``decades`` whose brightest photosite
    gives ``level`` x 250 DN (8-bit) in the shortest frame of :data:`TIMES`."""
    from hdrcap.mock_camera.scenes import make_scene

    return make_scene(name, shape, decades=decades, x_max=level * 250 / (G8 * TIMES[0]))


def bracket_frames(
    sensor: SimulatedSensor, X: np.ndarray, folder: Path, stem: str, rng: np.random.Generator
) -> list[RawFrame]:
    """One bracket of the camera at :data:`TIMES`: each frame exposed on ``sensor``, kept to its
    top 8 bits, written as ``folder/STEM_I.tif`` and read back as a GBRG frame."""
    from hdrcap.mock_camera.imagefiles import requantise, write_image
    from hdrcap.pipeline.io.frameformat import FrameFormat
    from hdrcap.pipeline.io.raw import read_frame

    frames = []
    for i, t in enumerate(TIMES):
        v = requantise(sensor.expose(X, t, rng=rng), ADC, 8).astype("uint8")
        frames.append(read_frame(write_image(folder / f"{stem}_{i}.tif", v), t, fmt=FrameFormat(cfa="GBRG")))
    return frames
