"""``hdrcap simulate``: write a simulated bracket (DNG), dark frames and the true irradiance."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from hdrcap.acquire.cliutil import echo_json, many_values
from hdrcap.pipeline.errors import HdrcapError, InputError


def parse_size(text: str | None, default=(768, 1024)) -> tuple[int, int]:
    """'WIDTHxHEIGHT' -> (height, width)."""
    if not text:
        return default
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 1024x768, got {text!r}") from None
    if w < 22 or h < 22 or w % 2 or h % 2:
        raise InputError(f"--size needs even width and height >= 22 (whole Bayer tiles; LibRaw reads nothing smaller), got {text!r}")
    return h, w


def load_scene(scene: str, shape, decades: float, x_max: float) -> np.ndarray:
    from hdrcap.mock_camera.scenes import SCENES, load_scene_exr, make_scene

    if scene.lower().endswith(".exr"):
        try:
            return load_scene_exr(scene)
        except (OSError, ValueError, RuntimeError) as err:
            raise InputError(f"{scene}: cannot load scene ({err})") from None
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose from {', '.join(SCENES)} or give an .exr file")
    return make_scene(scene, shape, decades=decades, x_max=x_max)


def frame_name(index: int, t: float, dark: bool) -> str:
    kind = "dark" if dark else "frame"
    return f"{kind}_{index:03d}_{t:.6g}s.dng"


def simulate_bracket(camera_name: str, scene: str, times, out: Path, darks: bool, shape, decades, x_max,
                     seed: int, temperature, force: bool, progress: bool = True) -> dict:
    """Simulate a bracket into ``out``; return a description of what was written."""
    from tqdm import tqdm

    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap import __version__
    from hdrcap.pipeline.io import HdrImage, atomic_output, write_exr

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
    clash = [p for p in targets + [out / "truth.exr", out / "simulation.json"] if p.exists()]
    if clash and not force:
        raise HdrcapError(f"{clash[0]}: exists; use --force to overwrite (or choose another --out)")
    written = {"frames": [], "darks": []}
    for (i, t, d), path in tqdm(list(zip(plan, targets)), desc="simulate", unit="frame", disable=None if progress else True):
        cam.capture_to(path, t, dark=d, overwrite=force)
        written["darks" if d else "frames"].append(str(path))
    params = spec.nominal_params(temperature)
    attrs = {
        "unit": "electrons per second per photosite",
        "content": "ground truth irradiance of the simulation",
        "camera": camera_name,
        "scene": scene,
        "seed": seed,
        "hdrcap_version": __version__,
    }
    write_exr(out / "truth.exr", HdrImage({"irradiance": X.astype(np.float32)}, attrs), force=force)
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


def simulate_calibration_set(camera_name: str, out: Path, shape, seed: int, temperature, force: bool,
                             progress: bool = True, plan: dict | None = None) -> dict:
    """Write a full calibration series of the simulated camera into ``out`` (DNG files) and
    ``calibration_set.json`` (file lists per kind and the true parameters)."""
    from tqdm import tqdm

    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.backend import SimulatedCamera
    from hdrcap.pipeline.io import atomic_output

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
    clash = [p for p in names + [manifest] if p.exists()]
    if clash and not force:
        raise HdrcapError(f"{clash[0]}: exists; use --force to overwrite (or choose another --out)")
    out.mkdir(parents=True, exist_ok=True)
    cam = SimulatedCamera(spec, np.full(shape, X), seed=seed, temperature=temperature)
    files: dict[str, list[str]] = {"bias": [], "saturation": [], "flat": [], "dark": []}
    for (kind, t, dark), path in tqdm(list(zip(shots, names)), desc="calibration set", unit="frame",
                                      disable=None if progress else True):
        cam.capture_to(path, t, dark=dark, overwrite=force)
        files["flat" if kind == "ptc" else kind].append(str(path))
    desc = {"camera": camera_name, "seed": seed, "shape": list(shape), "temperature": temperature,
            "irradiance": X, "true_params": nominal.to_dict(), "plan": {k: list(v) if isinstance(v, tuple) else v
                                                                          for k, v in cfg.items()},
            "files": files, "n_frames": len(shots)}
    with atomic_output(out / "calibration_set.json", force=force) as tmp:
        tmp.write_text(json.dumps(desc, indent=2))
    return desc


@many_values("--times")
@click.command("simulate")
@click.option("--camera", "camera_name", default="camera-B", show_default=True,
              help="Simulator preset: camera-A (12 bit) or camera-B (10 bit), Table 2 of the paper.")
@click.option("--scene", default="hdr", show_default=True,
              help="Scene: hdr, gradient, patches, edges, flat, or an EXR file of irradiance (e-/s).")
@click.option("--times", multiple=True, type=float, help="Exposure times in seconds (several after one flag).  [default: 1/1000 to 1 s, 6 steps]")
@click.option("--darks/--no-darks", default=False, help="Also take one matching dark frame per exposure.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True, help="Output folder.")
@click.option("--size", default="1024x768", show_default=True, help="Mosaic size WIDTHxHEIGHT (even numbers).")
@click.option("--decades", default=4.0, show_default=True, type=float, help="Dynamic range of a synthetic scene, orders of magnitude.")
@click.option("--x-max", default=2e5, show_default=True, type=float, help="Brightest irradiance of a synthetic scene, e-/s.")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed (fixed patterns and noise).")
@click.option("--temperature", default=None, type=float, help="Sensor temperature, degrees C (dark current doubles every 6.3 C).")
@click.option("--force", is_flag=True, help="Overwrite existing files in the output folder.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
@click.option("--calibration-set", is_flag=True, help="Instead of a bracket, write a calibration series (bias, saturation, 36 flats, a photon-transfer series, darks at 6 times) and calibration_set.json, for `hdrcap calibrate`.")
def command(camera_name, scene, times, darks, out, size, decades, x_max, seed, temperature, force, as_json,
            calibration_set):
    """Simulate a bracket: DNG frames (and dark frames) plus truth.exr and simulation.json.

    The DNGs hold the CFA mosaic with BlackLevel, WhiteLevel, ExposureTime and ISO (IFD0 and
    EXIF IFD), camera model and timestamp; they open in rawpy/LibRaw tools such as HDRMerge.
    """
    if calibration_set:
        desc = simulate_calibration_set(camera_name, out, parse_size(size), seed, temperature, force,
                                        progress=not as_json)
        if as_json:
            echo_json({"camera": camera_name, "seed": seed, "shape": desc["shape"], "out": str(out),
                       "n_frames": desc["n_frames"], "manifest": str(out / "calibration_set.json")}
                      | {f"n_{k}": len(v) for k, v in desc["files"].items()})
        else:
            click.echo(f"wrote a calibration set of {desc['n_frames']} frames and calibration_set.json to {out}")
        return
    desc = simulate_bracket(camera_name, scene, list(times) or list(DEFAULT_TIMES), out, darks,
                            parse_size(size), decades, x_max, seed, temperature, force, progress=not as_json)
    if as_json:
        echo_json({k: desc[k] for k in ("camera", "scene", "seed", "shape", "exposure_times", "truth")}
                  | {"n_frames": len(desc["frames"]), "n_darks": len(desc["darks"]), "out": str(out)})
    else:
        click.echo(f"wrote {len(desc['frames'])} frames, {len(desc['darks'])} dark frames and truth.exr to {out}")
