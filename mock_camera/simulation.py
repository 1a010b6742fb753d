"""Simulated brackets and calibration sets written to files: the library behind ``hdrcap
simulate``. The physics is :mod:`hdrcap.mock_camera`; this module writes its DNG frames, the
true irradiance (``truth.exr``) and a JSON description."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.mock_camera.scenes import load_scene
from hdrcap.pipeline.errors import InputError

__all__ = ["frame_name", "simulate_bracket", "simulate_calibration_set", "DEFAULT_TIMES", "CALIBRATION_SET"]


def frame_name(index: int, t: float, dark: bool) -> str:
    kind = "dark" if dark else "frame"
    return f"{kind}_{index:03d}_{t:.6g}s.dng"


def simulate_bracket(
    camera_name: str,
    scene: str,
    times: Sequence[float],
    out: Path,
    darks: bool,
    shape: tuple[int, int],
    decades: float,
    x_max: float,
    seed: int,
    temperature: float | None,
    force: bool,
    progress: bool = True,
) -> dict[str, Any]:
    """Simulate a bracket into ``out``; return a description of what was written."""
    from tqdm import tqdm

    from hdrcap import __version__
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.pipeline.io.exr import write_exr
    from hdrcap.pipeline.io.files import atomic_output, check_new_output
    from hdrcap.pipeline.schema import UNIT_ELECTRONS

    if camera_name not in PRESETS:
        raise InputError(f"unknown camera preset {camera_name!r}; choose from {', '.join(PRESETS)}")
    if not times:
        raise InputError("give at least one exposure time with --times")
    for t in times:
        if not (t > 0 and np.isfinite(t)):
            raise InputError(f"exposure times must be positive seconds, got {t!r}")
    if len(set(times)) != len(times):
        raise InputError("--times lists the same exposure time twice")
    spec = PRESETS[camera_name]
    X = load_scene(scene, shape, decades, x_max)
    out.mkdir(parents=True, exist_ok=True)
    cam = SimulatedCamera(spec, X, seed=seed, temperature=temperature)
    plan = [(i, t, False) for i, t in enumerate(times)]
    if darks:
        plan += [(i, t, True) for i, t in enumerate(times)]
    targets = [out / frame_name(i, t, d) for i, t, d in plan]
    for p in targets + [out / "truth.exr", out / "simulation.json"]:
        check_new_output(p, force)
    written: dict[str, list[str]] = {"frames": [], "darks": []}
    for (_i, t, d), path in tqdm(
        list(zip(plan, targets)), desc="simulate", unit="frame", disable=None if progress else True
    ):
        cam.capture_to(path, t, dark=d, overwrite=force)
        written["darks" if d else "frames"].append(str(path))
    params = spec.nominal_params(temperature)
    attrs = {
        "unit": UNIT_ELECTRONS,
        "content": "ground truth irradiance of the simulation",
        "camera": camera_name,
        "scene": scene,
        "seed": seed,
        "hdrcap_version": __version__,
    }
    write_exr(out / "truth.exr", {"irradiance": X.astype(np.float32)}, attrs, force=force)
    desc = {
        "camera": camera_name,
        "scene": scene,
        "seed": seed,
        "shape": list(X.shape),
        "exposure_times": [cam.actual_time(t) for t in times],
        "temperature": temperature,
        "params": params.to_dict(),
        **written,
        "truth": str(out / "truth.exr"),
    }
    with atomic_output(out / "simulation.json", force=force) as tmp:
        tmp.write_text(json.dumps(desc, indent=2))
    return desc


DEFAULT_TIMES = (0.001, 0.004, 0.016, 0.064, 0.25, 1.0)

#: What ``--calibration-set`` writes (see docs/calibration.md): 2 bias frames at 1/10000 s,
#: 1 saturation frame, 36 flats at 75 % of saturation (18 pairs, Eq. 16), a photon-transfer
#: series of 12 pairs from 3 % to 85 % of saturation, and 2 dark frames at each of 6 times.
CALIBRATION_SET = {
    "bias_time": 1e-4,
    "n_bias": 2,
    "flat_time": 0.01,
    "flat_fraction": 0.75,
    "n_flats": 36,
    "ptc_fractions": tuple(round(0.03 + i * (0.85 - 0.03) / 11, 4) for i in range(12)),
    "saturation_factor": 10.0,
    "dark_times": (0.5, 1.0, 2.0, 4.0, 8.0, 16.0),
    "n_darks": 2,
}


def simulate_calibration_set(
    camera_name: str,
    out: Path,
    shape: tuple[int, int],
    seed: int,
    temperature: float | None,
    force: bool,
    progress: bool = True,
    plan: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write a full calibration series of the simulated camera into ``out`` (DNG files) and
    ``calibration_set.json`` (file lists per kind and the true parameters)."""
    from tqdm import tqdm

    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.pipeline.io.files import atomic_output, check_new_output

    if camera_name not in PRESETS:
        raise InputError(f"unknown camera preset {camera_name!r}; choose from {', '.join(PRESETS)}")
    cfg = dict(CALIBRATION_SET, **(plan or {}))
    spec = PRESETS[camera_name]
    nominal = spec.nominal_params(temperature)
    span = nominal.v_sat - spec.mu_R
    X = cfg["flat_fraction"] * span / spec.g / cfg["flat_time"]  # e-/s giving the flat level
    shots = [("bias", cfg["bias_time"], True) for _ in range(cfg["n_bias"])]  # light blocked
    shots += [("saturation", cfg["flat_time"] * cfg["saturation_factor"], False)]
    shots += [("flat", cfg["flat_time"], False) for _ in range(cfg["n_flats"])]
    for f in cfg["ptc_fractions"]:
        t = cfg["flat_time"] * f / cfg["flat_fraction"]
        shots += [("ptc", t, False), ("ptc", t, False)]
    for t in cfg["dark_times"]:
        shots += [("dark", t, True) for _ in range(cfg["n_darks"])]
    names = [out / f"{kind}_{i:03d}_{t:.6g}s.dng" for i, (kind, t, _) in enumerate(shots)]
    manifest = out / "calibration_set.json"
    for p in names + [manifest]:
        check_new_output(p, force)
    out.mkdir(parents=True, exist_ok=True)
    cam = SimulatedCamera(spec, np.full(shape, X), seed=seed, temperature=temperature)
    files: dict[str, list[str]] = {"bias": [], "saturation": [], "flat": [], "dark": []}
    for (kind, t, dark), path in tqdm(
        list(zip(shots, names)), desc="calibration set", unit="frame", disable=None if progress else True
    ):
        cam.capture_to(path, t, dark=dark, overwrite=force)
        files["flat" if kind == "ptc" else kind].append(str(path))
    desc = {
        "camera": camera_name,
        "seed": seed,
        "shape": list(shape),
        "temperature": temperature,
        "irradiance": X,
        "true_params": nominal.to_dict(),
        "plan": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
        "files": files,
        "n_frames": len(shots),
    }
    with atomic_output(out / "calibration_set.json", force=force) as tmp:
        tmp.write_text(json.dumps(desc, indent=2))
    return desc
