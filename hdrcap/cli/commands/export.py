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
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
def command(archive, run, output, exr_compression, force):
    """Write run RUN of the zarr ARCHIVE (from `hdrcap batch`) as an EXR: the channels
    the channels and header attributes `hdrcap merge` writes for that run."""
    from hdrcap.batch.archive import read_run
    from hdrcap.pipeline.errors import InputError
    from hdrcap.pipeline.io import write_exr

    if output.exists() and not force:
        raise InputError(f"{output}: exists; use --force to overwrite")
    img = read_run(archive, run)
    write_exr(output, img, force=force, compression=exr_compression)
    h, w = img.shape
    click.echo(f"wrote {output}: run {run} of {archive}, {w}x{h}")
