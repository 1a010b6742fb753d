"""The merge on the realistic simulated sensor camera-R with a calibration estimated from its
frames, against the simulator's truth: the calibration's "done when" of docs/calibration.md.

camera-R: 0.1 % hot, 0.05 % dead, 0.05 % weak, 0.01 % stuck photosites, +-3 % shutter errors
plus 0.2 % jitter, a bias that drifts by 0.2 DN between frames, 2 e-/s dark current (30 % DCNU)
and a 0.2 % loss of response at full well. Per sensor seed, a calibration ESTIMATED from its
simulated frames (:func:`hdrcap.experiments.calibrated.calibrated_sensor`: 2 bias frames, 1
saturation frame, 16 flats at :data:`FLAT_LEVEL` of the range, a photon-transfer series of one
pair at each of ``n_ptc`` levels from 5 % to 70 % of saturation, 2 dark frames at each of 6
times), then a 4-decade gradient (1 to 2e4 e-/s) merged from a bracket of :data:`TIMES` with
matched dark frames. Figures against the truth, on the photosites that are no defect:

* ``g_error_pct`` and ``g_stderr_pct``: the gain against the truth, and its stated error;
* ``z_spread``: standard deviation of z = (estimate - k truth) / sigma (pooled and per decade),
  k the global scale fit (a bracket cannot tell the absolute scale: that is g's and the shutter's);
* ``beyond_6_sigma``: the fraction with |z| > 6;
* ``bias_pct``: per irradiance decade, mean(estimate / (k truth)) - 1, with its statistical
  standard error ``bias_stderr_pct`` (from the stated sigmas);
* ``drift_scale_pct``: per decade, sqrt(2) b / (g t_max) mean(1 / X), the relative error a bias
  drift b (DN, the spec's) between the longest frame and its dark frame gives: no estimate from
  the bracket can see it (the whole bracket stays consistent with an additive irradiance).

``benchmarks/bench_realistic.py`` prints these figures per seed as JSON.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hdrcap.experiments.calibrated import bracket, calibrated_sensor
from hdrcap.mock_camera import preset
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.mock_camera.sensor import SensorSpec, SimulatedSensor
from hdrcap.pipeline.merge.accumulator import MergeOptions
from hdrcap.pipeline.merge.files import MergeRequest, merge_files
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.result import HdrResult

__all__ = ["FLAT_LEVEL", "TIMES", "calibrated_camera_r", "case_figures", "figures", "ptc_levels", "run_case"]

#: The bracket's nominal exposure times, s (up to 300 s, as the issue asks).
TIMES = (0.08, 0.6, 5.0, 40.0, 300.0)
#: Flat level for the PRNU map and the Eq. 16 pairs, fraction of the range above the bias.
FLAT_LEVEL = 0.875


def ptc_levels(n: int) -> tuple[float, ...]:
    """``n`` photon-transfer levels from 5 % to 70 % of saturation (EMVA 1288 range).

    Parameters
    ----------
    n : int
        Number of levels (0: none).

    Returns
    -------
    tuple of float
        Fractions of the range above the bias, rounded to 4 digits; () for 0.
    """
    return tuple(float(f) for f in np.round(np.linspace(0.05, 0.7, n), 4)) if n else ()


def calibrated_camera_r(seed: int, size: int, n_ptc: int = 10, **changes: Any) -> tuple[SimulatedSensor, Calibration]:
    """camera-R (with ``changes`` to its spec) and its calibration estimated from simulated frames.

    Parameters
    ----------
    seed : int
        Sensor seed (fixed patterns and calibration frames).
    size : int
        Photosites per side.
    n_ptc : int
        Photon-transfer levels (:func:`ptc_levels`).
    **changes
        Fields of camera-R's :class:`~hdrcap.mock_camera.sensor.SensorSpec` to change.

    Returns
    -------
    tuple of SimulatedSensor and Calibration
        The sensor and its estimated calibration (flats at :data:`FLAT_LEVEL`).
    """
    return calibrated_sensor(
        preset("camera-R", **changes),
        seed=seed,
        shape=(size, size),
        flat_level=FLAT_LEVEL,
        ptc_levels=ptc_levels(n_ptc),
    )


def figures(res: HdrResult, X: np.ndarray, mask: np.ndarray, spec: SensorSpec) -> dict[str, Any]:
    """The accuracy figures of a merge against the truth (see the module docstring).

    Parameters
    ----------
    res : HdrResult
        The merge.
    X : numpy.ndarray
        The true irradiance, e-/s.
    mask : numpy.ndarray
        Photosites to count (bool); of those, only the ones with nexp > 0.
    spec : SensorSpec
        The sensor's specification (gain and bias drift of the drift scale).

    Returns
    -------
    dict
        ``scale_k``, ``z_spread``, ``beyond_6_sigma``, ``worst_decade_bias_pct`` and, per decade
        of the truth keyed by its lower end (``"1e2"``), ``z_spread_per_decade``, ``bias_pct``,
        ``bias_stderr_pct`` and ``drift_scale_pct``.
    """
    ok = mask & (res.nexp > 0)
    x, s, t = res.irradiance[ok].astype(np.float64), res.sigma[ok].astype(np.float64), X[ok]
    k = float(np.sum(x * t / s**2) / np.sum(t * t / s**2))
    z = (x - k * t) / s
    dec = np.floor(np.log10(t)).astype(int)
    out: dict[str, Any] = {
        "scale_k": k,
        "z_spread": float(np.std(z)),
        "beyond_6_sigma": float(np.mean(np.abs(z) > 6)),
        "z_spread_per_decade": {},
        "bias_pct": {},
        "bias_stderr_pct": {},
        "drift_scale_pct": {},
    }
    drift = np.sqrt(2.0) * spec.bias_drift / (spec.g * max(TIMES))
    for d in np.unique(dec):
        m = dec == d
        key = f"1e{d}"
        out["z_spread_per_decade"][key] = float(np.std(z[m]))
        out["bias_pct"][key] = 100 * float(np.mean(x[m] / (k * t[m]) - 1))
        out["bias_stderr_pct"][key] = 100 * float(np.sqrt(np.mean((s[m] / (k * t[m])) ** 2) / m.sum()))
        out["drift_scale_pct"][key] = 100 * float(drift * np.mean(1.0 / t[m]))
    out["worst_decade_bias_pct"] = max(abs(b) for b in out["bias_pct"].values())
    return out


def case_figures(
    sensor: SimulatedSensor, cal: Calibration, seed: int, exposure_times: str = "effective"
) -> dict[str, Any]:
    """The gain against the truth, then a bracket merged with ``cal`` and its :func:`figures`.

    Parameters
    ----------
    sensor : SimulatedSensor
        The sensor (camera-R or a changed one).
    cal : Calibration
        Its estimated calibration.
    seed : int
        Seed of the bracket's noise.
    exposure_times : {"effective", "nominal"}
        The merge's exposure times (:class:`~hdrcap.pipeline.merge.accumulator.MergeOptions`).

    Returns
    -------
    dict
        ``seed``, ``g``, ``g_true``, ``g_error_pct``, ``g_stderr_pct``, ``gain_method``,
        ``warnings`` (the calibration's) and the :func:`figures` of the non-defect photosites.
    """
    h, w = sensor.shape
    X = make_scene("gradient", (h, w), decades=4.0, x_max=2e4)
    frames, darks = bracket(sensor, X, TIMES, seed=seed)
    options = MergeOptions(exposure_times=exposure_times)
    res = merge_files(MergeRequest(frames=frames, calibration=cal, options=options, darks=darks))
    normal = ~np.logical_or.reduce(list(sensor.defects.values()))
    info = cal.provenance["calibration"]
    return {
        "seed": seed,
        "g": cal.params.g,
        "g_true": sensor.spec.g,
        "g_error_pct": 100 * (cal.params.g / sensor.spec.g - 1),
        "g_stderr_pct": 100 * cal.stderr["g"] / sensor.spec.g,
        "gain_method": info["gain_method"],
        "warnings": info.get("warnings", []),
        **figures(res, X, normal, sensor.spec),
    }


def run_case(
    seed: int, size: int = 256, n_ptc: int = 10, exposure_times: str = "effective", **changes: Any
) -> dict[str, Any]:
    """One sensor seed: :func:`calibrated_camera_r`, then :func:`case_figures`.

    Parameters
    ----------
    seed : int
        Sensor seed (also the bracket's).
    size : int
        Photosites per side.
    n_ptc : int
        Photon-transfer levels of the calibration.
    exposure_times : {"effective", "nominal"}
        The merge's exposure times.
    **changes
        Fields of camera-R's spec to change.

    Returns
    -------
    dict
        The :func:`case_figures` of that seed.
    """
    sensor, cal = calibrated_camera_r(seed, size, n_ptc, **changes)
    return case_figures(sensor, cal, seed, exposure_times)
