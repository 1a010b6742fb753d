"""``hdrcap export``: one run of a zarr archive back as the EXR of ``hdrcap merge``."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("export")
@click.argument("archive", type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "--run", "run", type=click.IntRange(min=0), required=True, help="Run number (the archive's run coordinate)."
)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="Output EXR file.")
@click.option(
    "--exr-compression",
    type=click.Choice(["zip", "zips", "piz", "zstd", "rle", "none"]),
    default="zip",
    show_default=True,
    help="EXR compression.",
)
@click.option(
    "--sigma-precision",
    type=click.Choice(["auto", "half", "float"]),
    default="auto",
    show_default=True,
    help="Storage of sigma and sigma_calibration: give the batch's --sigma-precision (the archive holds the values "
    "as that precision stored them).",
)
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
def command(archive: Path, run: int, output: Path, exr_compression: str, sigma_precision: str, force: bool) -> None:
    """Write run RUN of the zarr ARCHIVE (from `hdrcap batch`) as an EXR: the channels and
    header `hdrcap merge` writes for that run (the archive holds the channels as they are
    stored, so the EXR is the merge's bit for bit)."""
    from hdrcap.batch.archive import read_run
    from hdrcap.pipeline.io.files import check_new_output
    from hdrcap.pipeline.io.results import write_result

    check_new_output(output, force)
    result = read_run(archive, run)
    write_result(
        result, output, format="exr", force=force, compression=exr_compression, sigma_precision=sigma_precision
    )
    h, w = result.shape
    click.echo(f"wrote {output}: run {run} of {archive}, {w}x{h}")
