"""``hdrcap merge``: raw bracket (+ dark frames) -> EXR with irradiance, sigma and nexp, or a float DNG."""

from __future__ import annotations

import os
import time
from pathlib import Path

import click

from hdrcap.cli.util import echo_json, many_values
from hdrcap.pipeline.dark_strategy import DarkStrategy
from hdrcap.pipeline.errors import InputError


def _memory_here() -> str:
    """The default memory budget on this machine, for the help text (the budget itself is
    :func:`pipeline.merge.tiled.default_memory_budget`)."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return ""
    return f" (here {total / 2**31:.1f} GiB)"


@many_values("--darks", "--times")
@click.command("merge")
@click.argument("frames", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--darks",
    multiple=True,
    type=click.Path(path_type=Path),
    help="Dark frames, one per exposure time (several after one flag); for master exposures, the master dark of that time (several of one time are averaged).",
)
@click.option(
    "--calibration",
    type=click.Path(path_type=Path),
    help="Calibration file written by `hdrcap calibrate` (its dark library serves master darks). Without it and --camera the bracket calibrates itself (docs/selfcal.md).",
)
@click.option("--camera", help="Use a simulator preset's nominal parameters as the calibration (camera-A, camera-B).")
@click.option(
    "--times",
    multiple=True,
    type=float,
    help="Exposure times (s), one per frame; override EXIF (needed for PNG/TIFF frames).",
)
@click.option(
    "--plan",
    "plan_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Plan JSON from `hdrcap plan --json`: its per-exposure dark strategies and decided merge options are applied (options given here win); recorded in the EXR header.",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output file: EXR (default), or a float DNG when it ends in .dng or with --format dng.",
)
@click.option(
    "--format",
    "out_format",
    type=click.Choice(["exr", "dng"]),
    default=None,
    help="Output format. exr (default unless OUTPUT ends in .dng): irradiance, sigma, sigma_calibration (when the calibration has "
    "standard errors), nexp, quality and the header. dng: a linear floating-point CFA DNG of the irradiance alone (first frame's colour "
    "matrices, white balance, orientation) that raw developers open like any raw; it cannot hold "
    "sigma or nexp (docs/merge.md, Float DNG).",
)
@click.option(
    "--dng-bits",
    type=click.Choice(["32", "16"]),
    default="32",
    show_default=True,
    help="Float width of the DNG; 16 scales the irradiance by a power of two written in the file.",
)
@click.option(
    "--weighting",
    default="optimal",
    show_default=True,
    help="Weighting: 'optimal' (iterative ML merge) or a baseline name from hdrcap.pipeline.merge.weighting.",
)
@click.option(
    "--iterations",
    type=click.IntRange(min=1),
    default=20,
    show_default=True,
    help="Maximum re-weighting steps per photosite.",
)
@click.option(
    "--tolerance",
    type=click.FloatRange(min=0),
    default=1e-6,
    show_default=True,
    help="Stop when the change is below this times max(|estimate|, sigma).",
)
@click.option(
    "--saturation",
    type=click.Choice(["threshold", "probabilistic"]),
    default="threshold",
    show_default=True,
    help="Saturation model: Eq. 11 plus the near-saturation rule, or the censored likelihood of Eq. 8-10.",
)
@click.option(
    "--saturation-sigmas",
    type=click.FloatRange(min=0),
    default=3.0,
    show_default=True,
    help="Drop samples predicted within this many sigma of v_sat (0: off).",
)
@click.option(
    "--prnu",
    type=click.Choice(["map", "scalar"]),
    default="map",
    show_default=True,
    help="Per-photosite gain map from the calibration, or a = 1.",
)
@click.option(
    "--dark-strategy",
    type=click.Choice([s.value for s in DarkStrategy]),
    default=None,
    help="For every exposure (overrides a --plan's). Default: the plan's per exposure; else matched with --darks, master with --master-dark, model otherwise. master without --darks/--master-dark: the calibration's dark library.",
)
@click.option(
    "--master-dark",
    type=click.Path(path_type=Path),
    help="One master dark frame (raw file or 16-bit image) for the master exposures.",
)
@click.option(
    "--master-dark-frames",
    type=click.FloatRange(min=1),
    default=None,
    help="Number of frames averaged into each master dark file given here (N; library masters carry their own).",
)
@click.option(
    "--exposure-times",
    "exposure_times",
    type=click.Choice(["effective", "nominal"]),
    default="effective",
    show_default=True,
    help="effective: each frame's actual exposure time, from the calibration's shutter table (calibrate --shutter) "
    "refined by the bracket's own estimate (photosites well exposed in two frames; nominal, calibrated and effective "
    "times in the EXR header); nominal: the times as given, neither correction.",
)
@click.option(
    "--bad-values",
    type=click.Choice(["refuse", "mask"]),
    default="refuse",
    show_default=True,
    help="Raw values no sensor writes (above the white level's ADC range): refuse the file, or mask them: left out "
    "of that frame only, the photosite estimated from the other frames and flagged (quality bit 32), the count per "
    "file warned and recorded in the EXR header (masked_values). Other problems are always refused. mask needs "
    "--calibration or --camera and the in-memory merge (docs/testing.md).",
)
@click.option(
    "--exr-compression",
    type=click.Choice(["zip", "zips", "piz", "zstd", "rle", "none"]),
    default="zip",
    show_default=True,
    help="EXR compression (none/rle write fastest, zip is about a third smaller; zstd is smaller and faster but needs OpenEXR >= 3.4 to read).",
)
@click.option(
    "--sigma-precision",
    type=click.Choice(["auto", "half", "float"]),
    default="auto",
    show_default=True,
    help="Storage of sigma (and sigma_calibration): half loses at most 0.05 % of sigma, refused outside 6.1e-5..65504; auto is half where the channel fits, else float. irradiance is always float32; nexp and quality are stored as uint (lossless).",
)
@click.option(
    "--chunks",
    type=click.IntRange(min=2),
    default=None,
    metavar="ROWS",
    help="Merge tile by tile, bands of ROWS rows (even: whole CFA periods) through dask.array, reading only each "
    "tile's rows of every file and calibration map; identical to the in-memory merge (docs/batch.md, One huge "
    "frame). Uncompressed DNGs are read row by row; other raw formats (LibRaw) are decoded whole once per file "
    "into a temporary file beside the output (with a warning). EXR output and --weighting optimal only.",
)
@click.option(
    "--memory-budget",
    default=None,
    metavar="SIZE",
    help="Tile automatically (as --chunks, rows chosen to fit) when the in-memory merge would need more than SIZE "
    f"(e.g. 2GB; K/M/G/T are powers of 1024). Default: half of this machine's physical memory{_memory_here()}.",
)
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
@click.pass_context
def command(
    ctx,
    frames,
    darks,
    calibration,
    camera,
    times,
    plan_file,
    output,
    weighting,
    iterations,
    tolerance,
    saturation,
    saturation_sigmas,
    prnu,
    dark_strategy,
    master_dark,
    master_dark_frames,
    exposure_times,
    bad_values,
    exr_compression,
    sigma_precision,
    chunks,
    memory_budget,
    force,
    as_json,
    out_format,
    dng_bits,
):
    """Merge raw FRAMES (DNG/raw files or 16-bit PNG/TIFF with --times) into an EXR (or a float DNG).

    The EXR holds float32 channels irradiance (e-/s per photosite), sigma (its standard
    deviation) and nexp (unsaturated exposures used), and header attributes with the unit, CFA
    pattern, exposure times, calibration, all merge options, the dark frame of every exposure
    and, with --plan, the planner's decisions. With --format dng (or OUTPUT.dng) the irradiance
    alone is written as a linear float CFA DNG for raw developers.
    """
    from click.core import ParameterSource

    from hdrcap.pipeline.io import write_exr
    from hdrcap.pipeline.merge.files import (
        build_hdr_image,
        exr_precision,
        library_root,
        merge_files,
        merge_options,
        summary,
    )

    def given(name):
        return ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)

    out_format = out_format or ("dng" if output.suffix.lower() == ".dng" else "exr")
    if output.exists() and not force:
        raise InputError(f"{output}: exists; use --force to overwrite")
    plan = None
    if plan_file:
        from hdrcap.pipeline.planfile import read_plan  # the planner only when a plan is given

        plan = read_plan(plan_file)
    if plan is not None and weighting != "optimal":
        raise InputError(f"--plan works with --weighting optimal, not {weighting}")
    if dark_strategy == DarkStrategy.MATCHED and not darks:
        raise InputError("--dark-strategy matched needs dark frames (--darks)")
    if master_dark and darks and plan is None:
        raise InputError("give either --darks or --master-dark, not both (both only with --plan)")
    if master_dark and dark_strategy not in (None, DarkStrategy.MASTER):
        raise InputError(f"--master-dark needs --dark-strategy master, not {dark_strategy}")
    _check_bad_values(bad_values, calibration or camera, weighting)
    if weighting == "optimal":
        from hdrcap.pipeline.merge.files import start_warm_up

        start_warm_up()  # numba's set-up while the calibration loads and the frames are read
    t0 = time.perf_counter()
    warn = lambda m: click.echo(f"hdrcap: warning: {m}", err=True)  # noqa: E731
    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.pipeline.merge.files import bracket_calibration

    given_model = camera_model(calibration, camera) if (calibration or camera) else None
    calib, times, selfcal = bracket_calibration(
        given_model,
        frames,
        times,
        darks=bool(darks),
        warn=warn,
        say=lambda m: click.echo(m, err=True),
        exposure_times=exposure_times,
    )
    merge_times = exposure_times
    if selfcal is not None and times == list(selfcal.effective_times):
        merge_times = "nominal"  # the self-calibration's pairs gave the effective times: not estimated twice
    if selfcal is not None:
        click.echo(f"  {_selfcal_summary(selfcal)}", err=True)
    lib_root = library_root(calib, calibration)
    if dark_strategy == DarkStrategy.MASTER and not (darks or master_dark or lib_root):
        raise InputError(
            "--dark-strategy master needs --master-dark FILE, per-exposure master darks (--darks) "
            "or a calibration with a dark library (--calibration)"
        )
    if weighting != "optimal" and weighting not in _weighting_methods():
        raise InputError(f"--weighting {weighting!r}: choose from optimal, {', '.join(_weighting_methods())}")
    options = merge_options(
        iterations, tolerance, saturation, prnu, dark_strategy, master_dark_frames, saturation_sigmas, merge_times
    )
    rows = _tile_rows(frames, darks, calib, chunks, memory_budget, weighting, out_format, bad_values)
    common = dict(  # what the tiled and the in-memory merge are both given
        dark_paths=darks,
        times=times,
        plan=plan,
        plan_file=str(plan_file) if plan_file else None,
        dark_strategy=dark_strategy,
        master_dark=master_dark,
        master_dark_frames=master_dark_frames,
        library=lib_root,
        given=given,
        progress=not as_json,
        warn=warn,
    )
    if rows:  # one frame larger than the memory budget: tile by tile
        from hdrcap.pipeline.merge.tiled import merge_tiled

        tiled = merge_tiled(
            frames,
            calib,
            options,
            output,
            rows=rows,
            selfcal=selfcal,
            selfcal_times=exposure_times == "effective",
            force=force,
            compression=exr_compression,
            sigma_precision=sigma_precision,
            **common,
        )
        info = tiled.summary | {"output": str(output), "seconds": round(time.perf_counter() - t0, 3)}
        info |= {"n_frames": tiled.n_frames, "n_darks": tiled.n_darks, "chunk_rows": rows, "tiles": tiled.tiles}
        return _report(info, selfcal, as_json)
    done = merge_files(frames, calib, options, weighting=weighting, bad_values=bad_values, **common)
    image = build_hdr_image(done.result, done.frames, calib, done.extra)
    if selfcal is not None:
        from hdrcap.pipeline.calibration.selfcal import apply_self_calibration

        apply_self_calibration(image, selfcal, times_applied=exposure_times == "effective")
    if out_format == "dng":
        from hdrcap.pipeline.io.dngwrite import write_float_dng

        write_float_dng(output, image, bits=int(dng_bits), force=force)
    else:
        write_exr(
            output,
            image,
            force=force,
            compression=exr_compression,
            precision=exr_precision(image.channels, sigma_precision),
        )
    info = summary(done.result) | {
        "output": str(output),
        "seconds": round(time.perf_counter() - t0, 3),
        "n_frames": len(done.frames),
        "n_darks": len(done.darks),
    }
    _report(info, selfcal, as_json)


def _report(info: dict, selfcal, as_json: bool) -> None:
    """Print the merge's summary: one JSON line, or one sentence."""
    output = info["output"]
    if selfcal is not None:
        info["calibration"] = selfcal.calibration.provenance["source"]
        info["unit"] = selfcal.unit
    if as_json:
        echo_json(info)
    else:
        click.echo(
            f"wrote {output}: {info['shape'][1]}x{info['shape'][0]}, irradiance "
            f"{info['irradiance_min']:.4g}..{info['irradiance_max']:.4g} e-/s, "
            f"{info['saturated_everywhere']} photosites saturated everywhere, {info['seconds']:.2f} s"
        )


def _check_bad_values(bad_values: str, calibrated, weighting: str) -> None:
    """``--bad-values mask`` needs a calibration given (a self-calibration or library look-up
    reads the frames before any mask) and the optimal merge (the baselines take no mask)."""
    if bad_values != "mask":
        return
    if not calibrated:
        raise InputError(
            "--bad-values mask needs --calibration or --camera (the self-calibration would read the masked values)"
        )
    if weighting != "optimal":
        raise InputError(f"--bad-values mask works with --weighting optimal, not {weighting}")


def _tile_rows(frames, darks, calib, chunks, memory_budget, weighting, out_format, bad_values) -> int | None:
    """Rows per tile (--chunks, or chosen when the merge would exceed --memory-budget), or None."""
    from hdrcap.pipeline.merge.tiled import default_memory_budget, parse_memory, tiling_rows

    budget = parse_memory(memory_budget) if memory_budget is not None else default_memory_budget()
    rows = tiling_rows(frames, len(darks), calib, chunks=chunks, budget=budget)
    if rows is None:
        return None
    why = f"--chunks {chunks}" if chunks else f"the merge would need more than --memory-budget {budget / 2**30:.2f} GiB"
    if weighting != "optimal":
        raise InputError(f"{why}: tiled merges use --weighting optimal, not {weighting}")
    if out_format != "exr":
        raise InputError(f"{why}: tiled merges write EXR, not {out_format}")
    if bad_values == "mask":
        raise InputError(f"{why}: tiled merges refuse bad values; --bad-values mask needs the in-memory merge")
    return rows


def _weighting_methods():
    """The baseline weightings by name (imported only when a baseline is asked for)."""
    from hdrcap.pipeline.merge.weighting import WEIGHTING_METHODS

    return WEIGHTING_METHODS


def _selfcal_summary(sc) -> str:
    """One line: the estimated gain and read noise with their standard errors."""
    f = sc.fit
    if not sc.gain_known:
        return "gain not estimable: irradiance in DN/s, sigma relative"
    return (
        f"g = {f['g']:.4g} +- {f['g_stderr']:.2g} DN/e-, sigma_R^2 = {f['sigma2_R']:.3g} +- "
        f"{f['sigma2_R_stderr']:.2g} DN^2, from {f['n_photosites']} photosites in {len(sc.pairs)} pairs"
    )
