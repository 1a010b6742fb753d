"""``hdrcap merge``: raw bracket (+ dark frames) -> EXR with irradiance, sigma and nexp."""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from acquire.cliutil import echo_json, many_values, resolve_calibration
from pipeline.errors import InputError


def read_frames(paths, times=None, what="frame", progress=False):
    """Read raw files / 16-bit images; ``times`` (seconds, one per path) override EXIF."""
    from tqdm import tqdm

    from pipeline.io import read_frame

    paths = list(paths)
    if times:
        if len(times) != len(paths):
            raise InputError(f"--times gives {len(times)} exposure times for {len(paths)} {what}s")
    else:
        times = [None] * len(paths)
    return [read_frame(p, t) for p, t in tqdm(list(zip(paths, times)), desc=f"read {what}s", unit="file",
                                               disable=None if progress else True, leave=False)]


def build_hdr_image(result, frames, calibration, extra=None):
    """The EXR content of a merge: channels and header attributes."""
    from pipeline import __version__
    from pipeline.io import HdrImage

    attrs = {
        "unit": "electrons per second per photosite",
        "sigma": "standard deviation of irradiance, same unit",
        "nexp": "number of unsaturated exposures used (0: saturated everywhere, irradiance is a lower bound)",
        "cfa_pattern": frames[0].cfa_pattern or "none",
        "exposure_times": [fr.exposure_time for fr in frames],
        "source_files": [fr.path for fr in frames],
        "calibration": {"params": calibration.params.to_dict(), "provenance": calibration.provenance},
        "hdrcap_version": __version__,
        "merge": result.info,
    }
    if extra:
        attrs.update(extra)
    return HdrImage({"irradiance": result.irradiance, "sigma": result.sigma, "nexp": result.nexp}, attrs)


def summary(result) -> dict:
    irr, sig, nexp = result.irradiance, result.sigma, result.nexp
    ok = nexp > 0
    return {
        "shape": list(irr.shape),
        "irradiance_min": float(irr.min()),
        "irradiance_max": float(irr.max()),
        "median_relative_sigma": float(np.median(sig[ok] / np.maximum(np.abs(irr[ok]), 1e-30))) if ok.any() else None,
        "saturated_everywhere": int((~ok).sum()),
        "finite": bool(np.isfinite(irr).all() and np.isfinite(sig).all()),
    }


@many_values("--darks", "--times")
@click.command("merge")
@click.argument("frames", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--darks", multiple=True, type=click.Path(path_type=Path), help="Matching dark frames, one per exposure time (several after one flag).")
@click.option("--calibration", type=click.Path(path_type=Path), help="Calibration file written by `hdrcap calibrate`.")
@click.option("--camera", help="Use a simulator preset's nominal parameters as the calibration (camera-A, camera-B).")
@click.option("--times", multiple=True, type=float, help="Exposure times (s), one per frame; override EXIF (needed for PNG/TIFF frames).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Output EXR file.")
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
def command(frames, darks, calibration, camera, times, output, force, as_json):
    """Merge raw FRAMES (DNG/raw files or 16-bit PNG/TIFF with --times) into an EXR.

    The EXR holds float32 channels irradiance (e-/s per photosite), sigma (its standard
    deviation) and nexp (unsaturated exposures used), and header attributes with the unit, CFA
    pattern, exposure times, calibration and options.
    """
    from pipeline.io import write_exr
    from pipeline.merge import merge_frames

    if output.exists() and not force:
        raise InputError(f"{output}: exists; use --force to overwrite")
    t0 = time.perf_counter()
    calib = resolve_calibration(str(calibration) if calibration else None, camera)
    fr = read_frames(frames, times, "frame", progress=not as_json)
    dk = read_frames(darks, None, "dark frame", progress=not as_json) if darks else None
    result = merge_frames(fr, calib, dk)
    write_exr(output, build_hdr_image(result, fr, calib), force=force)
    info = summary(result) | {"output": str(output), "seconds": round(time.perf_counter() - t0, 3),
                              "n_frames": len(fr), "n_darks": len(dk or [])}
    if as_json:
        echo_json(info)
    else:
        click.echo(f"wrote {output}: {info['shape'][1]}x{info['shape'][0]}, irradiance "
                   f"{info['irradiance_min']:.4g}..{info['irradiance_max']:.4g} e-/s, "
                   f"{info['saturated_everywhere']} photosites saturated everywhere, {info['seconds']:.2f} s")
