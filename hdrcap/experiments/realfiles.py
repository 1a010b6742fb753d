"""The simulated machine-vision camera of the real-file checks (issue #28; docs/selfcal.md):
a 12-bit ADC whose frames are saved as 8-bit TIFF (im2uint8-style), 0.09 DN/e- in 8-bit DN,
read noise 5 e-, black 100 DN (12-bit), 1 % PRNU, Bayer GBRG, and its seven exposure times.
``benchmarks/bench_realfiles.py`` and ``tests/end_to_end/test_png_tiff_cameras.py`` both take
it from here.

>>> MV.bits, MV.cfa, round(MV.g * 255 / 4095, 3) == G8
(12, 'GBRG', True)
"""

from __future__ import annotations

from hdrcap.mock_camera.sensor import SensorSpec

__all__ = ["ADC", "G8", "MV", "TIMES"]

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
