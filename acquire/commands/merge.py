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
    return list(_read_parallel(paths, times, what, progress))


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


def _median_relative_sigma(irr, sig, ok, max_samples=1_000_000):
    """Median of sigma/|irradiance| over usable photosites (a regular subsample of at most
    ``max_samples`` of them on large images)."""
    step = max(1, irr.size // max_samples)
    i, s, o = irr.ravel()[::step], sig.ravel()[::step], ok.ravel()[::step]
    if not o.any():
        return None
    return float(np.median(s[o] / np.maximum(np.abs(i[o]), 1e-30)))


def summary(result) -> dict:
    irr, sig, nexp = result.irradiance, result.sigma, result.nexp
    ok = nexp > 0
    return {
        "shape": list(irr.shape),
        "irradiance_min": float(irr.min()),
        "irradiance_max": float(irr.max()),
        "median_relative_sigma": _median_relative_sigma(irr, sig, ok),
        "saturated_everywhere": int((~ok).sum()),
        "finite": bool(np.isfinite(irr).all() and np.isfinite(sig).all()),
    }


def _read_parallel(paths, times, what, progress):
    """Decode raw files in a thread pool (LibRaw releases the GIL), yielding frames in order."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from pipeline.io import read_frame

    paths = list(paths)
    if times:
        if len(times) != len(paths):
            raise InputError(f"--times gives {len(times)} exposure times for {len(paths)} {what}s")
    else:
        times = [None] * len(paths)
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = [pool.submit(read_frame, p, t) for p, t in zip(paths, times)]
        for fut in tqdm(futures, desc=f"read {what}s", unit="file", disable=None if progress else True, leave=False):
            yield fut.result()


def merge_options(iterations, tolerance, saturation, prnu, dark_strategy, master_dark_frames, saturation_sigmas):
    """Keyword options of :func:`pipeline.merge.merge_arrays` from the command-line knobs."""
    opts = {"iterations": iterations, "tolerance": tolerance, "saturation": saturation, "prnu": prnu,
            "saturation_sigmas": saturation_sigmas}
    if dark_strategy:
        opts["dark_strategy"] = dark_strategy
    if master_dark_frames is not None:
        opts["n_dark"] = master_dark_frames
    return opts


def streamed_merge(frame_paths, dark_paths, times, calib, options, master_dark=None, progress=False):
    """Read the bracket (in parallel threads) and feed each frame to a
    :class:`pipeline.merge.MergeAccumulator` as soon as it is decoded, darks matched by
    exposure time. Returns (result, frames without pixel data kept, darks)."""
    from pipeline.io import RawFrame, check_frames
    from pipeline.merge import MergeAccumulator

    strategy = options.get("dark_strategy")
    darks = list(_read_parallel(dark_paths, None, "dark frame", progress)) if dark_paths and strategy != "model" else []
    if darks:
        darks = check_frames(darks, "dark frame")
    by_time = {}
    for d in darks:
        by_time.setdefault(round(d.exposure_time, 12), d)
    acc = None
    frames = []
    for fr in _read_parallel(frame_paths, times, "frame", progress):
        if acc is None:
            if master_dark is not None:
                options = dict(options, dark_strategy="master")
                options.setdefault("master_dark_time", master_dark.exposure_time)
            # stream=False: the frames are all read here anyway, so the merge does its single
            # pass at the end (less memory than the first-pass sums of a live capture).
            acc = MergeAccumulator(calib, fr.shape, master_dark=None if master_dark is None else master_dark.data,
                                   stream=False, **options)
        if darks:
            d = by_time.get(round(fr.exposure_time, 12))
            if d is None:
                raise InputError(f"{fr.path}: no dark frame with exposure time {fr.exposure_time:g} s")
            if d.shape != fr.shape:
                raise InputError(f"{d.path}: dark frame size differs from the bracket's")
            acc.add(fr.data, fr.exposure_time, d.data)
        else:
            acc.add(fr.data, fr.exposure_time)
        frames.append(fr)
    check_frames(frames)
    return acc.result(), frames, darks


@many_values("--darks", "--times")
@click.command("merge")
@click.argument("frames", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--darks", multiple=True, type=click.Path(path_type=Path), help="Matching dark frames, one per exposure time (several after one flag); with --dark-strategy master, one master dark per exposure time.")
@click.option("--calibration", type=click.Path(path_type=Path), help="Calibration file written by `hdrcap calibrate`.")
@click.option("--camera", help="Use a simulator preset's nominal parameters as the calibration (camera-A, camera-B).")
@click.option("--times", multiple=True, type=float, help="Exposure times (s), one per frame; override EXIF (needed for PNG/TIFF frames).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Output EXR file.")
@click.option("--weighting", default="optimal", show_default=True, help="Weighting: 'optimal' (iterative ML merge) or a baseline name from pipeline.weighting.")
@click.option("--iterations", type=click.IntRange(min=1), default=20, show_default=True, help="Maximum re-weighting steps per photosite.")
@click.option("--tolerance", type=click.FloatRange(min=0), default=1e-6, show_default=True, help="Stop when the change is below this times max(|estimate|, sigma).")
@click.option("--saturation", type=click.Choice(["threshold", "probabilistic"]), default="threshold", show_default=True, help="Saturation model: Eq. 11 plus the near-saturation rule, or the blended likelihood of Eq. 8-10.")
@click.option("--saturation-sigmas", type=click.FloatRange(min=0), default=3.0, show_default=True, help="Drop samples predicted within this many sigma of v_sat (0: off).")
@click.option("--prnu", type=click.Choice(["map", "scalar"]), default="map", show_default=True, help="Per-photosite gain map from the calibration, or a = 1.")
@click.option("--dark-strategy", type=click.Choice(["matched", "master", "model"]), default=None, help="Default: matched with --darks, master with --master-dark, model otherwise.")
@click.option("--master-dark", type=click.Path(path_type=Path), help="One master dark frame (raw file or 16-bit image) for all exposures.")
@click.option("--master-dark-frames", type=click.FloatRange(min=1), default=None, help="Number of frames averaged into each master dark (N).")
@click.option("--exr-compression", type=click.Choice(["zip", "zips", "piz", "zstd", "rle", "none"]), default="zip", show_default=True, help="EXR compression (none/rle write fastest, zip is about a third smaller; zstd is smaller and faster but needs OpenEXR >= 3.4 to read).")
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
def command(frames, darks, calibration, camera, times, output, weighting, iterations, tolerance, saturation,
            saturation_sigmas, prnu, dark_strategy, master_dark, master_dark_frames, exr_compression, force, as_json):
    """Merge raw FRAMES (DNG/raw files or 16-bit PNG/TIFF with --times) into an EXR.

    The EXR holds float32 channels irradiance (e-/s per photosite), sigma (its standard
    deviation) and nexp (unsaturated exposures used), and header attributes with the unit, CFA
    pattern, exposure times, calibration and all merge options.
    """
    from pipeline.io import write_exr

    if output.exists() and not force:
        raise InputError(f"{output}: exists; use --force to overwrite")
    if dark_strategy == "master" and not (darks or master_dark):
        raise InputError("--dark-strategy master needs --master-dark FILE or per-exposure master darks (--darks)")
    if dark_strategy == "matched" and not darks:
        raise InputError("--dark-strategy matched needs dark frames (--darks)")
    if master_dark and darks:
        raise InputError("give either --darks or --master-dark, not both")
    if master_dark and dark_strategy not in (None, "master"):
        raise InputError(f"--master-dark needs --dark-strategy master, not {dark_strategy}")
    t0 = time.perf_counter()
    calib = resolve_calibration(str(calibration) if calibration else None, camera)
    options = merge_options(iterations, tolerance, saturation, prnu, dark_strategy, master_dark_frames,
                            saturation_sigmas)
    extra = {"weighting": weighting}
    if weighting != "optimal":
        try:
            from pipeline.weighting import WEIGHTING_METHODS, merge_weighted
        except ImportError:
            raise InputError(f"--weighting {weighting}: baseline weightings are not available in this build; use 'optimal'") from None
        if weighting not in WEIGHTING_METHODS:
            raise InputError(f"--weighting {weighting!r}: choose from optimal, {', '.join(WEIGHTING_METHODS)}")
        fr = read_frames(frames, times, "frame", progress=not as_json)
        dk = read_frames(darks, None, "dark frame", progress=not as_json) if darks else None
        result = merge_weighted([f.data for f in fr], [f.exposure_time for f in fr], calib,
                                [d.data for d in dk] if dk else None, method=weighting)
    else:
        md = None
        if master_dark:
            from pipeline.io import read_frame

            if master_dark.suffix.lower() in (".png", ".tif", ".tiff"):  # no exposure time: used as is
                md = read_frame(master_dark, 1.0)
                options["master_dark_time"] = None
            else:
                md = read_frame(master_dark)
        result, fr, dk = streamed_merge(frames, darks, times, calib, options, md, progress=not as_json)
        if master_dark:
            extra["master_dark_file"] = str(master_dark)
    write_exr(output, build_hdr_image(result, fr, calib, extra), force=force, compression=exr_compression)
    info = summary(result) | {"output": str(output), "seconds": round(time.perf_counter() - t0, 3),
                              "n_frames": len(fr), "n_darks": len(dk or [])}
    if as_json:
        echo_json(info)
    else:
        click.echo(f"wrote {output}: {info['shape'][1]}x{info['shape'][0]}, irradiance "
                   f"{info['irradiance_min']:.4g}..{info['irradiance_max']:.4g} e-/s, "
                   f"{info['saturated_everywhere']} photosites saturated everywhere, {info['seconds']:.2f} s")
