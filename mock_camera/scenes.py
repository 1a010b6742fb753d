"""Synthetic scenes: irradiance maps in electrons per second per photosite.

Every scene spans ``decades`` orders of magnitude below ``x_max`` (e-/s). Names:

``gradient``  a horizontal logarithmic ramp from x_max 10^-decades to x_max;
``patches``   a grid of constant patches, log-spaced over the range (good for statistics);
``edges``     step edges and a disk of strong contrast on a darker background;
``hdr``       a composite: gradient band, patch band and edge band (the default);
``flat``      a uniform field at x_max (for flat fields and statistics).

:func:`near_clip_scene` places every photosite of a given sensor near the clip level of one
exposure of a bracket (the censored likelihood's hardest case).

:func:`load_scene_exr` reads any single-channel EXR (channel ``irradiance``, or ``Y``/``R``)
as a scene.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from hdrcap.pipeline.errors import InputError

if TYPE_CHECKING:
    from hdrcap.mock_camera.sensor import SensorSpec, SimulatedSensor

__all__ = ["SCENES", "make_scene", "load_scene_exr", "load_scene", "parse_size", "electrons_at_k", "near_clip_scene"]

SCENES = ("hdr", "gradient", "patches", "edges", "flat")


def _gradient(h, w, lo, hi):
    ramp = np.logspace(np.log10(lo), np.log10(hi), w)
    return np.broadcast_to(ramp, (h, w)).copy()


def _patches(h, w, lo, hi, n=(4, 8)):
    rows, cols = n
    levels = np.logspace(np.log10(lo), np.log10(hi), rows * cols).reshape(rows, cols)
    yi = np.minimum((np.arange(h) * rows) // h, rows - 1)
    xi = np.minimum((np.arange(w) * cols) // w, cols - 1)
    return levels[yi[:, None], xi[None, :]].astype(np.float64)


def _edges(h, w, lo, hi):
    out = np.full((h, w), np.sqrt(lo * hi) / 10.0)
    out[:, w // 2 :] = np.sqrt(lo * hi)
    yy, xx = np.mgrid[0:h, 0:w]
    r = min(h, w) / 5.0
    out[(yy - h / 2) ** 2 + (xx - w / 4) ** 2 < r**2] = hi
    out[(yy - h / 2) ** 2 + (xx - 3 * w / 4) ** 2 < r**2] = lo
    out[: h // 8, :] = lo * 3.0
    return np.clip(out, lo, hi)


def make_scene(
    name: str = "hdr", shape: tuple[int, int] = (768, 1024), decades: float = 4.0, x_max: float = 2e5
) -> np.ndarray:
    """Return the irradiance map of scene ``name`` (float64, e-/s per photosite).

    Parameters
    ----------
    name : str
        One of :data:`SCENES`.
    shape : (int, int)
        Height and width in photosites.
    decades : float
        Dynamic range of the scene, orders of magnitude (> 0).
    x_max : float
        Brightest irradiance, e-/s (> 0).
    """
    h, w = (int(s) for s in shape)
    if h < 2 or w < 2:
        raise ValueError(f"scene shape must be at least 2x2, got {shape!r}")
    if not decades > 0 or not x_max > 0:
        raise ValueError("decades and x_max must be > 0")
    lo, hi = x_max * 10.0 ** (-min(decades, 400.0)), x_max
    if not lo > np.finfo(float).tiny or not np.isfinite(hi):
        raise ValueError(f"a scene of {decades:g} decades below {x_max:g} e-/s is outside float range")
    if name == "gradient":
        return _gradient(h, w, lo, hi)
    if name == "patches":
        return _patches(h, w, lo, hi)
    if name == "edges":
        return _edges(h, w, lo, hi)
    if name == "flat":
        return np.full((h, w), hi)
    if name == "hdr":
        out = np.empty((h, w))
        a, b = h // 3, 2 * h // 3
        out[:a] = _gradient(a, w, lo, hi)
        out[a:b] = _patches(b - a, w, lo, hi, n=(2, 8))
        out[b:] = _edges(h - b, w, lo, hi)
        return out
    raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)} or an .exr file")


def electrons_at_k(spec: SensorSpec, v_sat: float, k: float | np.ndarray) -> np.ndarray:
    """The signal whose mean lies ``k`` of its standard deviations from the clip level ``v_sat``.

    Solves mu_R + g E = v_sat + k sqrt(g^2 E + sigma_R^2) for E by fixed-point iteration (10
    steps), with the spec's nominal gain, bias and read-noise variance.

    Parameters
    ----------
    spec : SensorSpec
        The sensor's specification.
    v_sat : float
        Clip level, DN.
    k : float or numpy.ndarray
        Distance from the clip level, standard deviations of the value (negative: below it).

    Returns
    -------
    numpy.ndarray
        Electrons per photosite (float64).
    """
    e = (v_sat - spec.mu_R) / spec.g
    for _ in range(10):
        e = (v_sat + k * np.sqrt(spec.g**2 * e + spec.sigma2_R) - spec.mu_R) / spec.g
    return np.asarray(e, dtype=np.float64)


def near_clip_scene(
    sensor: SimulatedSensor, rng: np.random.Generator, times: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Every photosite at k ~ U(-3.5, 3.5) standard deviations of the clip level of an exposure.

    Each photosite picks one of ``times`` that has a shorter one (never the shortest: above its
    clip level there is only a lower bound) and k; its irradiance puts the mean value of that
    exposure k standard deviations from the nominal clip level, through the sensor's own PRNU
    and dark-current map (the truth the merge must recover).

    Parameters
    ----------
    sensor : SimulatedSensor
        The sensor (its shape, PRNU and dark-current map).
    rng : numpy.random.Generator
        Draws the exposure and k of each photosite.
    times : sequence of float
        The bracket's exposure times, s, shortest first.

    Returns
    -------
    tuple of numpy.ndarray
        Irradiance, e-/s (float64, the sensor's shape), and each photosite's k.
    """
    spec = sensor.spec
    shape = sensor.prnu.shape
    t = np.asarray(times)[rng.integers(1, len(times), shape)]
    k = rng.uniform(-3.5, 3.5, shape)
    e = electrons_at_k(spec, spec.nominal_params().v_sat, k)
    return (e / t - sensor.dark_current_map()) / sensor.prnu, k


def load_scene_exr(path: str | os.PathLike[str]) -> np.ndarray:
    """Load an irradiance map (e-/s) from an EXR file as a scene (float64)."""
    import OpenEXR  # the simulator reads scenes itself: it imports nothing of pipeline's I/O

    with OpenEXR.File(str(path)) as exr:
        channels = {name: ch.pixels for name, ch in exr.channels().items()}
    for name in ("irradiance", "Y", "R", "G"):
        if name in channels:
            data = np.asarray(channels[name], dtype=np.float64)
            break
    else:
        raise ValueError(f"{path}: no irradiance, Y or R channel in this EXR")
    if not np.all(np.isfinite(data)) or np.any(data < 0):
        raise ValueError(f"{path}: scene irradiance must be finite and >= 0")
    return data


def load_scene(scene: str, shape: tuple[int, int], decades: float, x_max: float) -> np.ndarray:
    """The irradiance map (e-/s per photosite) of a scene named on the command line or in a job.

    Parameters
    ----------
    scene : str
        One of :data:`SCENES`, or an EXR file (its size is the scene's).
    shape : (int, int)
        Height and width of a synthetic scene, photosites.
    decades : float
        Dynamic range of a synthetic scene, orders of magnitude.
    x_max : float
        Brightest irradiance of a synthetic scene, e-/s.

    Returns
    -------
    numpy.ndarray
        float64 irradiance, e-/s.

    Raises
    ------
    InputError
        Unknown scene name or unreadable EXR file.
    """
    if scene.lower().endswith(".exr"):
        try:
            return load_scene_exr(scene)
        except (OSError, ValueError, RuntimeError) as err:
            raise InputError(f"{scene}: cannot load scene ({err})") from None
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose from {', '.join(SCENES)} or give an .exr file")
    return make_scene(scene, shape, decades=decades, x_max=x_max)


def parse_size(text: str | None, default: tuple[int, int] = (768, 1024)) -> tuple[int, int]:
    """Mosaic size from ``'WIDTHxHEIGHT'``.

    Parameters
    ----------
    text : str or None
        E.g. ``"1024x768"``; None or empty gives ``default``.
    default : (int, int)
        (height, width) without ``text``.

    Returns
    -------
    (int, int)
        (height, width), photosites: even and at least 22 (whole Bayer tiles; LibRaw reads
        nothing smaller).

    Raises
    ------
    InputError
        Malformed, odd or too small sizes.
    """
    if not text:
        return default
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 1024x768, got {text!r}") from None
    if w < 22 or h < 22 or w % 2 or h % 2:
        raise InputError(
            f"--size needs even width and height >= 22 (whole Bayer tiles; LibRaw reads nothing smaller), got {text!r}"
        )
    return h, w
