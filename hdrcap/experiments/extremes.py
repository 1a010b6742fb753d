"""The sensors of the stability sweep at the extremes (``benchmarks/extremes.py``, docs/merge.md,
*Stability at the extremes*): per bit depth one camera whose full well clips before the ADC and
one whose ADC clips first, with a dark current that dominates the darker photosites' signal in
the longest exposures; and where a photosite stands against the clip level (:func:`nearest_clip`),
which this sweep and ``benchmarks/bench_honesty.py`` band their statistics by.

>>> sorted(cameras())[:2]
['10-bit-adc', '10-bit-fw']
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from hdrcap.mock_camera.sensor import SensorSpec

if TYPE_CHECKING:
    import numpy as np

    from hdrcap.mock_camera.sensor import SimulatedSensor

__all__ = ["T_MAX", "T_MIN", "cameras", "nearest_clip"]

#: The sweep's shortest and longest exposure times, s.
T_MIN, T_MAX = 1e-6, 3600.0


def _camera(name: str, g: float, mu_R: float, sigma2_R: float, bits: int, full_well: float) -> SensorSpec:
    """A sweep sensor: dark current 30 % of the full well over :data:`T_MAX` (30 % DCNU), 1 % PRNU."""
    return SensorSpec(
        name=name,
        g=g,
        mu_R=mu_R,
        sigma2_R=sigma2_R,
        bits=bits,
        full_well=full_well,
        dark_current=0.3 * full_well / T_MAX,
        dcnu=0.3,
        prnu=0.01,
    )


def cameras() -> dict[str, SensorSpec]:
    """The sweep's sensors by name.

    Per bit depth (8, 10, 12, 14, 16) one whose full well clips first (``fw``: saturated values
    scatter around v_sat + 3 sigma_R, some slip under v_sat on read noise) and one whose ADC clips
    first (``adc``, the full well at least 5 read-noise sigma above the white level). 10-bit:
    camera-B's g, mu_R and sigma2_R; 12-bit fw: camera-A's; 14-bit fw: 42 000 e- at 0.37 DN/e-.

    Returns
    -------
    dict of str to SensorSpec
        ``"8-bit-fw"``, ``"8-bit-adc"``, ... ``"16-bit-adc"``.
    """
    specs = [
        ("8-bit-fw", 0.12, 8.0, 0.7, 8, 1800.0),
        ("8-bit-adc", 0.12, 8.0, 0.7, 8, 2400.0),
        ("10-bit-fw", 0.92, 32.0, 18.0, 10, 1000.0),
        ("10-bit-adc", 0.92, 32.0, 18.0, 10, 1100.0),
        ("12-bit-fw", 0.23, 128.0, 6.5, 12, (3709.0 + 3.0 * math.sqrt(6.5) - 128.0) / 0.23),
        ("12-bit-adc", 0.23, 128.0, 6.5, 12, 20000.0),
        ("14-bit-fw", 0.37, 510.0, 6.5, 14, 42000.0),
        ("14-bit-adc", 0.37, 510.0, 6.5, 14, 46000.0),
        ("16-bit-fw", 0.5, 1000.0, 9.0, 16, 120000.0),
        ("16-bit-adc", 0.5, 1000.0, 9.0, 16, 140000.0),
    ]
    return {s[0]: _camera(*s) for s in specs}


def nearest_clip(
    sensor: SimulatedSensor, X: np.ndarray, times: Sequence[float], v_sat: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per photosite, k = (E[v] - v_sat) / sigma_v of the exposure whose clip level ``v_sat`` (DN)
    is nearest, from the simulator's truth (PRNU, dark-current map, effective times), and that
    exposure's index in ``times`` (s); ``X`` is the irradiance, e-/s."""
    import numpy as np

    spec = sensor.spec
    u = sensor.prnu * X + sensor.dark_current_map()
    best = np.full(X.shape, np.inf)
    which = np.zeros(X.shape, np.int64)
    for j, t in enumerate(times):
        e = t * sensor.shutter_factor(t) * u
        k = (spec.mu_R + spec.g * e - v_sat) / np.sqrt(spec.g**2 * e + spec.sigma2_R)
        nearer = np.abs(k) < np.abs(best)
        best = np.where(nearer, k, best)
        which = np.where(nearer, j, which)
    return best, which
