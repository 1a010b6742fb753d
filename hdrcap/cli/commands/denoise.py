"""``hdrcap denoise``: uncertainty-driven bilateral filtering of a merged EXR (Sec. 9)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from hdrcap.cli.util import echo_json
from hdrcap.pipeline.errors import InputError

#: The filter options as given: (method, range_scale, bandwidth, radius, spatial_sigma, layout).
FilterOptions = tuple[str, float | None, float | None, int | None, float | None, str]

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
    help="Storage of the filtered sigma, the rule of `hdrcap merge --sigma-precision`: half loses at most 0.05 % of "
    "sigma, refused outside 6.1e-5..65504; auto is half where the channel fits, else float. irradiance is always "
    "float32; the other channels are stored as in the input (lossless).",
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
    """Denoise a merged EXR (channels irradiance, sigma, optional nexp) with a bilateral filter
    whose range bandwidth follows each photosite's predicted sigma (Sec. 9).

    The header is kept; the filter settings are added under "denoise". The output sigma is the
    noise propagated through the filter's weights (independent inputs); it does not include the
    bias the filter introduces. Photosites with nexp = 0 (saturated everywhere) are unchanged.
    The JSON's median relative sigmas are taken over a regular subsample (at most about 1e6
    photosites, the same ones as with --chunks).
    """
    import numpy as np

    from hdrcap import __version__
    from hdrcap.pipeline.denoise.filter import (
        SIGMA_MEANING,
        denoise,
        denoise_header,
        layout_from_metadata,
        settings_from_options,
    )
    from hdrcap.pipeline.denoise.tiled import exr_pixel_types, median_relative_sigma, output_precision
    from hdrcap.pipeline.io.exr import read_exr, write_exr
    from hdrcap.pipeline.io.files import check_new_output

    t0 = time.perf_counter()
    from hdrcap.pipeline._numba_target import warm_up
    from hdrcap.pipeline.merge.files import start_warm_up

    start_warm_up(warm_up)  # numba's set-up while the EXR is read
    if method == "adaptive" and bandwidth is not None:
        raise InputError("--bandwidth is for --method constant; the adaptive method uses --range-scale")
    if method == "constant" and range_scale is not None:
        raise InputError("--range-scale is for --method adaptive; the constant method uses --bandwidth")
    check_new_output(output, force)
    if input_exr.exists() and output.exists() and input_exr.resolve() == output.resolve():
        raise InputError(f"{output}: is the input file; inputs are never modified, choose another output")
    if chunks:  # tile by tile: the same result without holding the image
        filter_options: FilterOptions = (method, range_scale, bandwidth, radius, spatial_sigma, layout)
        return _denoise_tiled(input_exr, output, filter_options, chunks, (sigma_precision, exr_compression))(
            force, as_json, t0
        )
    # the stored types: the channels carried over are written back without a float32 round trip
    image = read_exr(input_exr, native=True)
    missing = [c for c in ("irradiance", "sigma") if c not in image.channels]
    if missing:
        raise InputError(
            f"{input_exr}: no {' or '.join(missing)} channel; denoise needs an EXR written by `hdrcap merge`"
        )
    ch = image.channels
    shapes = {name: arr.shape for name, arr in ch.items()}
    if len(set(shapes.values())) > 1:
        sizes = ", ".join(f"{k} {v[1]}x{v[0]}" for k, v in shapes.items())
        raise InputError(f"{input_exr}: channel sizes differ ({sizes})")
    chosen_layout = layout_from_metadata(image.header) if layout == "auto" else layout
    settings = settings_from_options(method, range_scale, bandwidth, radius, spatial_sigma, chosen_layout)
    result = denoise(
        ch["irradiance"], ch["sigma"], ch.get("nexp"), settings, name=str(input_exr), quality=ch.get("quality")
    )
    channels = dict(ch)  # other channels are carried over unchanged
    channels["irradiance"] = result.irradiance
    channels["sigma"] = result.sigma
    attrs = dict(image.header)
    attrs["sigma"] = SIGMA_MEANING
    attrs["denoise"] = denoise_header(
        settings,
        result,
        "header cfa_pattern" if layout == "auto" else "--layout",
        image.header.get("sigma", "standard deviation of irradiance"),
        __version__,
        source_file=str(input_exr),
    )
    precision = output_precision(exr_pixel_types(input_exr), sigma_precision)
    write_exr(output, channels, attrs, force=force, compression=exr_compression, precision=precision)
    ok = np.asarray(ch["nexp"]) > 0 if "nexp" in ch else np.ones(result.irradiance.shape, bool)
    if "quality" in ch:  # the photosites the filter changes, as with --chunks
        ok &= np.asarray(ch["quality"]) == 0
    info = {
        "output": str(output),
        "shape": list(result.irradiance.shape),
        "settings": settings.to_dict(),
        "median_relative_sigma_before": median_relative_sigma(ch["irradiance"], ch["sigma"], ok),
        "median_relative_sigma_after": median_relative_sigma(result.irradiance, result.sigma, ok),
        "unchanged_nexp0": result.info["unchanged_nexp0"],
        "seconds": round(time.perf_counter() - t0, 3),
    }
    if as_json:
        echo_json(info)
    else:
        click.echo(
            f"wrote {output}: {info['shape'][1]}x{info['shape'][0]}, {settings.method} bilateral ({chosen_layout}), "
            f"median relative sigma {_g(info['median_relative_sigma_before'])} -> "
            f"{_g(info['median_relative_sigma_after'])}, "
            f"{info['seconds']:.2f} s"
        )


def _g(value: float | None) -> str:
    """A figure of the summary line: 3 significant digits, or "n/a" where no photosite had one."""
    return "n/a" if value is None else f"{value:.3g}"


def _denoise_tiled(
    input_exr: Path, output: Path, filter_options: FilterOptions, chunks: int, storage: tuple[str, str]
) -> Callable[[bool, bool, float], None]:
    """``hdrcap denoise --chunks``: returns the step that filters and reports (force, as_json, t0).
    ``filter_options``: (method, range_scale, bandwidth, radius, spatial_sigma, layout) as given;
    ``storage``: (sigma precision, EXR compression)."""
    import numpy as np

    from hdrcap import __version__
    from hdrcap.pipeline.denoise.filter import (
        DenoiseResult,
        denoise_header,
        layout_from_metadata,
        settings_from_options,
    )
    from hdrcap.pipeline.denoise.tiled import denoise_tiled, exr_layout, exr_pixel_types, output_precision

    method, range_scale, bandwidth, radius, spatial_sigma, layout = filter_options
    sigma_precision, compression = storage

    attrs, names, shape = exr_layout(input_exr)
    missing = [c for c in ("irradiance", "sigma") if c not in names]
    if missing:
        raise InputError(
            f"{input_exr}: no {' or '.join(missing)} channel; denoise needs an EXR written by `hdrcap merge`"
        )
    chosen_layout = layout_from_metadata(attrs) if layout == "auto" else layout
    settings = settings_from_options(method, range_scale, bandwidth, radius, spatial_sigma, chosen_layout)

    def entry(unchanged: int) -> dict[str, Any]:
        # the header needs the count only; the filtered tiles are already in the output file
        empty = np.empty((0, 0), np.float32)
        return denoise_header(
            settings,
            DenoiseResult(empty, empty, empty, info={"unchanged_nexp0": unchanged}),
            "header cfa_pattern" if layout == "auto" else "--layout",
            attrs.get("sigma", "standard deviation of irradiance"),
            __version__,
            source_file=str(input_exr),
        )

    def run(force: bool, as_json: bool, t0: float) -> None:
        done = denoise_tiled(
            input_exr,
            output,
            settings,
            rows=chunks,
            precision=output_precision(exr_pixel_types(input_exr), sigma_precision),
            compression=compression,
            attrs=attrs,
            names=names,
            shape=shape,
            header_entry=entry,
            force=force,
            progress=not as_json,
        )
        info = {
            "output": str(output),
            "shape": list(shape),
            "settings": settings.to_dict(),
            "median_relative_sigma_before": done.median_relative_sigma_before,
            "median_relative_sigma_after": done.median_relative_sigma_after,
            "unchanged_nexp0": done.unchanged_nexp0,
            "seconds": round(time.perf_counter() - t0, 3),
            "chunk_rows": done.rows,
            "tiles": done.tiles,
        }
        if as_json:
            echo_json(info)
        else:
            click.echo(
                f"wrote {output}: {shape[1]}x{shape[0]}, {settings.method} bilateral ({chosen_layout}), "
                f"{done.tiles} tiles of {done.rows} rows, {info['seconds']:.2f} s"
            )

    return run
