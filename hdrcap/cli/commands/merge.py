"""``hdrcap merge``: raw bracket (+ dark frames) -> EXR with irradiance, sigma and nexp, or a float DNG."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

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
    "--cfa",
    type=click.Choice(["RGGB", "BGGR", "GRBG", "GBRG", "mono"], case_sensitive=False),
    default=None,
    help="The frames' 2x2 Bayer tile, or mono (no colour filter): for PNG/TIFF frames, which do not say it "
    "(default: monochrome, with a warning); overrides a raw file's.",
)
@click.option(
    "--black-level",
    type=click.FloatRange(min=0),
    default=None,
    metavar="DN",
    help="Black level of the frames, DN. Default: the raw file's; for PNG/TIFF frames the self-calibration "
    "estimates it from the bracket.",
)
@click.option(
    "--white-level",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    metavar="DN",
    help="White level of the frames, DN. Default: the raw file's; for PNG/TIFF frames (2^bits - 1) x the "
    "quantisation step (255 for 8-bit files).",
)
@click.option(
    "--bits",
    type=click.IntRange(1, 16),
    default=None,
    metavar="N",
    help="Significant bits of the values: N-bit data stored LSB-aligned (0..2^N - 1) or MSB-aligned (multiples "
    "of 2^(16-N), detected) in 16-bit words; sets the white level and the quantisation step. Default: the file's "
    "bit depth, MSB alignment detected and said.",
)
@click.option(
    "--calibration-mismatch",
    type=click.Choice(["refuse", "warn"]),
    default="refuse",
    show_default=True,
    help="A --calibration or --camera made for another camera than the frames' (model or serial, ISO, white "
    "level, size, CFA pattern): refuse in one line, or warn and merge anyway (deliberate use).",
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
    ctx: click.Context,
    frames: tuple[Path, ...],
    darks: tuple[Path, ...],
    calibration: Path | None,
    camera: str | None,
    times: tuple[float, ...],
    plan_file: Path | None,
    output: Path,
    weighting: str,
    iterations: int,
    tolerance: float,
    saturation: str,
    saturation_sigmas: float,
    prnu: str,
    dark_strategy: str | None,
    master_dark: Path | None,
    master_dark_frames: float | None,
    exposure_times: str,
    bad_values: str,
    exr_compression: str,
    sigma_precision: str,
    chunks: int | None,
    memory_budget: str | None,
    force: bool,
    as_json: bool,
    out_format: str | None,
    dng_bits: str,
    cfa: str | None,
    black_level: float | None,
    white_level: float | None,
    bits: int | None,
    calibration_mismatch: str,
) -> None:
    """Merge raw FRAMES (DNG/raw files, or 8- to 16-bit PNG/TIFF with --times) into an EXR (or a float DNG).

    The EXR holds irradiance (e-/s per photosite), sigma (its standard uncertainty),
    sigma_calibration (when the calibration has standard errors), nexp (unsaturated exposures
    used) and quality, and a header with the unit, CFA pattern, exposure times, calibration,
    all merge options, the dark frame of every exposure and, with --plan, the planner's
    decisions (docs/merge.md). With --format dng (or OUTPUT.dng) the irradiance alone is
    written as a linear float CFA DNG for raw developers.
    """
    from click.core import ParameterSource

    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.pipeline.io.files import check_new_output
    from hdrcap.pipeline.io.frameformat import FrameFormat
    from hdrcap.pipeline.io.results import output_format, write_result
    from hdrcap.pipeline.merge.accumulator import MergeOptions, as_strategy
    from hdrcap.pipeline.merge.files import MergeRequest, merge_files, start_warm_up
    from hdrcap.pipeline.result import summarise

    t0 = time.perf_counter()
    out_format = output_format(output, out_format)
    check_new_output(output, force)
    if weighting == "optimal":
        start_warm_up()  # numba's set-up while the calibration loads and the frames are read
    plan = None
    if plan_file:
        from hdrcap.pipeline.planfile import read_plan

        plan = read_plan(plan_file)
    options = MergeOptions(
        iterations=iterations,
        tolerance=tolerance,
        saturation=saturation,
        saturation_sigmas=saturation_sigmas,
        prnu=prnu,
        dark_strategy=as_strategy(dark_strategy),
        exposure_times=exposure_times,
    )
    given = frozenset(
        name
        for name in ctx.params
        if ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)
    )
    if chunks is not None and out_format != "exr":
        raise InputError(f"--chunks {chunks}: tiled merges write EXR, not {out_format}")
    request = MergeRequest(
        frames=list(frames),
        calibration=calibration if calibration else (camera_model(camera=camera) if camera else None),
        options=options,
        darks=list(darks),
        times=list(times) or None,
        master_dark=master_dark,
        master_dark_frames=master_dark_frames,
        plan=plan,
        given=given,
        weighting=weighting,
        bad_values=bad_values,
        tiling=chunks if chunks is not None else ("auto" if out_format == "exr" else None),
        memory_budget=_memory_budget(memory_budget),
        scratch_dir=output.parent if output.parent.is_dir() else None,
        frame_format=FrameFormat(cfa=cfa, black_level=black_level, white_level=white_level, bits=bits),
        calibration_mismatch=calibration_mismatch,
    )
    warn = lambda m: click.echo(f"hdrcap: warning: {m}", err=True)  # noqa: E731
    result = merge_files(request, progress=not as_json, warn=warn, say=lambda m: click.echo(m, err=True))
    selfcal = result.header.get("self_calibration")
    if selfcal is not None:
        click.echo(f"  {_selfcal_summary(selfcal)}", err=True)
    write_result(
        result,
        output,
        format=out_format,
        force=force,
        compression=exr_compression,
        sigma_precision=sigma_precision,
        dng_bits=int(dng_bits),
    )
    info = summarise(result) | {
        "output": str(output),
        "seconds": round(time.perf_counter() - t0, 3),
        "n_frames": result.info.get("n_frames", len(frames)),
        "n_darks": result.info.get("n_darks", len(darks)),
    }
    tiling = result.info.get("tiling")
    if tiling:
        info |= {"chunk_rows": tiling["rows"], "tiles": tiling["tiles"]}
    if selfcal is not None:
        info["calibration"] = selfcal["source"]
    _report(info, as_json)


def _memory_budget(text: str | None) -> int | None:
    """Bytes of --memory-budget (None: the default, half of this machine's memory)."""
    if text is None:
        return None
    from hdrcap.pipeline.merge.tiled import parse_memory

    return parse_memory(text)


def _report(info: dict[str, Any], as_json: bool) -> None:
    """Print the merge's summary: one JSON line, or one sentence in the unit written."""
    from hdrcap.pipeline.schema import UNIT_ELECTRONS

    if as_json:
        echo_json(info)
        return
    unit = "e-/s" if info.get("unit") in (None, UNIT_ELECTRONS) else "DN/s"
    click.echo(
        f"wrote {info['output']}: {info['shape'][1]}x{info['shape'][0]}, irradiance "
        f"{info['irradiance_min']:.4g}..{info['irradiance_max']:.4g} {unit}, "
        f"{info['saturated_everywhere']} photosites saturated everywhere, {info['seconds']:.2f} s"
    )


def _selfcal_summary(head: dict[str, Any]) -> str:
    """One line from the header's ``self_calibration``: the gain and the read-noise variance
    used, with their standard errors, and the fit's reduced chi^2."""
    g, r = head["gain"], head["read_noise_variance"]
    fit = head.get("photon_transfer_fit", {})
    noise = f"sigma_R^2 = {r['value']:.3g}" + (
        f" +- {r['stderr']:.2g} DN^2" if r.get("stderr") is not None else " DN^2 (the quantisation floor)"
    )
    if not g.get("estimated"):
        return f"gain not estimable: irradiance in DN/s, sigma relative; {noise}"
    chi2 = fit.get("reduced_chi2")
    scaled = f", errors scaled by {fit['stderr_scale']:.3g}" if fit.get("model_rejected") else ""
    return (
        f"g = {g['value']:.4g} +- {g['stderr']:.2g} DN/e-, {noise}, from {fit.get('n_photosites')} photosites "
        f"in {len(head.get('exposure_ratios', []))} pairs"
        + (f" (chi^2/dof {chi2:.3g} over {fit.get('dof')}{scaled})" if chi2 is not None else "")
    )
