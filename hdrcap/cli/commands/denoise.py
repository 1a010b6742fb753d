"""``hdrcap denoise``: uncertainty-driven bilateral filtering of a merged EXR (Sec. 9)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from hdrcap.cli.util import echo_json
from hdrcap.pipeline.errors import InputError

__all__ = ["command"]


@click.command("denoise")
@click.argument("input_exr", metavar="IN.exr", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Output EXR file.")
@click.option(
    "--method",
    type=click.Choice(["adaptive", "constant"]),
    default="adaptive",
    show_default=True,
    help="adaptive: range bandwidth K x predicted sigma per photosite (Sec. 9); constant: one bandwidth B.",
)
@click.option(
    "--range-scale",
    "range_scale",
    type=float,
    default=None,
    help="K, the range bandwidth as a multiple of the predicted sigma (adaptive; default 3).",
)
@click.option(
    "--bandwidth",
    type=float,
    default=None,
    help="Constant range bandwidth B, e-/s (constant method; 'inf' = Gaussian).",
)
@click.option(
    "--radius", type=int, default=None, help="Half-width of the square support, same-colour steps (default 2)."
)
@click.option(
    "--spatial-sigma",
    "spatial_sigma",
    type=float,
    default=None,
    help="Spatial Gaussian standard deviation, same-colour steps (default 1.5).",
)
@click.option(
    "--layout",
    type=click.Choice(["auto", "cfa", "mono"]),
    default="auto",
    show_default=True,
    help="cfa: filter each colour plane of the 2x2 mosaic; mono: one channel; "
    "auto: cfa when the header names a CFA pattern.",
)
@click.option(
    "--chunks",
    type=click.IntRange(min=2),
    default=None,
    metavar="ROWS",
    help="Filter tile by tile, bands of ROWS rows (even) read from the EXR with the filter's reach of overlap "
    "(dask.array map_overlap; at least the reach, 2 x radius rows for cfa): identical to the whole-image filter, "
    "memory for a few bands only. The JSON's "
    "median relative sigmas are then taken over a regular subsample (at most about 1e6 photosites).",
)
@click.option(
    "--sigma-precision",
    "sigma_precision",
    type=click.Choice(["auto", "half", "float"]),
    default="auto",
    show_default=True,
    help="Storage of the sigma channels (sigma, sigma_calibration), as for `hdrcap merge`: half loses at most 0.05 % "
    "of sigma, refused outside 6.1e-5..65504; auto is half where the channel fits, else float. irradiance is always "
    "float32, nexp and quality unsigned integers (lossless).",
)
@click.option(
    "--exr-compression",
    "exr_compression",
    type=click.Choice(["zip", "zips", "piz", "zstd", "rle", "none"]),
    default="zip",
    show_default=True,
    help="EXR compression, as for `hdrcap merge` (none/rle write fastest; zstd is as small as zip and faster but "
    "needs OpenEXR >= 3.4 to read; docs/evaluation.md has the 24 Mpixel figures).",
)
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
def command(
    input_exr: Path,
    output: Path,
    method: str,
    range_scale: float | None,
    bandwidth: float | None,
    radius: int | None,
    spatial_sigma: float | None,
    layout: str,
    chunks: int | None,
    sigma_precision: str,
    exr_compression: str,
    force: bool,
    as_json: bool,
) -> None:
    """Denoise a merged EXR (channels irradiance, sigma, optional nexp, quality, sigma_calibration)
    with a bilateral filter whose range bandwidth follows each photosite's predicted sigma (Sec. 9).

    The header is kept; the filter settings are added under "denoise". The output sigma is the
    noise propagated through the filter's weights (independent inputs); it does not include the
    bias the filter introduces. Photosites with nexp = 0 (saturated everywhere) are unchanged.
    The JSON's median relative sigmas are taken over a regular subsample (at most about 1e6
    photosites, the same ones as with --chunks).
    """
    from hdrcap.pipeline._numba_target import warm_up
    from hdrcap.pipeline.denoise.files import DenoiseOptions, denoise_file
    from hdrcap.pipeline.io.files import check_new_output
    from hdrcap.pipeline.io.results import write_result
    from hdrcap.pipeline.merge.files import start_warm_up

    t0 = time.perf_counter()
    start_warm_up(warm_up)  # numba's set-up while the EXR is read
    if method == "adaptive" and bandwidth is not None:
        raise InputError("--bandwidth is for --method constant; the adaptive method uses --range-scale")
    if method == "constant" and range_scale is not None:
        raise InputError("--range-scale is for --method adaptive; the constant method uses --bandwidth")
    check_new_output(output, force)
    if input_exr.exists() and output.exists() and input_exr.resolve() == output.resolve():
        raise InputError(f"{output}: is the input file; inputs are never modified, choose another output")
    options = DenoiseOptions(method, range_scale, bandwidth, radius, spatial_sigma, layout)
    scratch = output.parent if output.parent.is_dir() else None  # the tiles' files beside the output
    result, figures = denoise_file(input_exr, options, rows=chunks, scratch_dir=scratch, progress=not as_json)
    write_result(result, output, force=force, sigma_precision=sigma_precision, compression=exr_compression)
    entry = result.header["denoise"]
    info = {
        "output": str(output),
        "shape": list(result.shape),
        "settings": entry["settings"],
        "median_relative_sigma_before": figures.median_relative_sigma_before,
        "median_relative_sigma_after": figures.median_relative_sigma_after,
        "unchanged_nexp0": figures.unchanged_nexp0,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    if chunks:
        info.update(chunk_rows=figures.chunk_rows, tiles=figures.tiles)
    if as_json:
        echo_json(info)
        return
    h, w = result.shape
    done = (
        f"{figures.tiles} tiles of {figures.chunk_rows} rows"
        if chunks
        else f"median relative sigma {_g(figures.median_relative_sigma_before)} -> "
        f"{_g(figures.median_relative_sigma_after)}"
    )
    click.echo(
        f"wrote {output}: {w}x{h}, {entry['settings']['method']} bilateral ({entry['settings']['layout']}), "
        f"{done}, {info['seconds']:.2f} s"
    )


def _g(value: float | None) -> str:
    """A figure of the summary line: 3 significant digits, or "n/a" where no photosite had one."""
    return "n/a" if value is None else f"{value:.3g}"
