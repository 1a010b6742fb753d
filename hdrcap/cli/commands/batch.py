"""``hdrcap batch``: many runs merged on local worker processes or a Dask cluster into one zarr archive."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from hdrcap.cli.commands.merge import command as _merge
from hdrcap.cli.util import echo_json
from hdrcap.pipeline.errors import HdrcapError


class BatchIncomplete(HdrcapError):
    """Some runs failed (the others landed); exit status 1."""

    exit_code = 1

    def __init__(self, message: str, reported: bool = False) -> None:
        super().__init__(message)
        self.reported = reported


#: The options of ``hdrcap merge`` that ``hdrcap batch`` takes too (the same click options).
SHARED = (
    "calibration",
    "camera",
    "weighting",
    "iterations",
    "tolerance",
    "saturation",
    "saturation_sigmas",
    "prnu",
    "dark_strategy",
    "master_dark_frames",
    "exposure_times",
    "sigma_precision",
    "calibration_mismatch",
)


@click.command("batch")
@click.argument("runs", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="The zarr archive (created if missing; new runs are appended).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Local worker processes, each merging one run at a time (default: one per core).",
)
@click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=None,
    help="Merge-kernel threads of each local worker (default: the cores shared among the workers).",
)
@click.option(
    "--scheduler",
    metavar="ADDRESS",
    default=None,
    help="Address of a running Dask scheduler (e.g. tcp://head:8786) whose workers merge the runs, instead of local workers.",
)
@click.option("--force", is_flag=True, help="Merge runs already in the archive again (rewritten in place).")
@click.option("--progress/--no-progress", default=None, help="Progress bar with ETA (default: on a terminal).")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
@click.pass_context
def command(
    ctx: click.Context,
    runs: tuple[Path, ...],
    output: Path,
    workers: int | None,
    threads: int | None,
    scheduler: str | None,
    force: bool,
    progress: bool | None,
    as_json: bool,
    **merge_opts: Any,
) -> None:
    """Merge many RUNS (capture run folders with manifest.jsonl, or folders of raw brackets)
    into the zarr archive OUTPUT, one task per run on local workers (or a Dask cluster), with the options of `hdrcap merge`.

    Runs already in the archive are skipped (unless --force); a run that fails is recorded in
    the archive's hdrcap_failed_runs attribute and the others go on. Open the archive with
    xarray.open_zarr; `hdrcap export` writes one run back as an EXR. See docs/batch.md.
    """
    from click.core import ParameterSource

    from hdrcap.batch.driver import BatchSettings, calibration_identity, run_batch
    from hdrcap.pipeline.errors import InputError
    from hdrcap.pipeline.merge.accumulator import MergeOptions
    from hdrcap.pipeline.merge.weighting import WEIGHTING_METHODS

    o = merge_opts
    if not (o["calibration"] or o["camera"]):
        raise InputError("no camera model: give --calibration FILE (from `hdrcap calibrate`) or --camera PRESET")
    if o["weighting"] != "optimal" and o["weighting"] not in WEIGHTING_METHODS:
        raise InputError(f"--weighting {o['weighting']!r}: choose from optimal, {', '.join(WEIGHTING_METHODS)}")
    given = frozenset(
        n
        for n in SHARED
        if ctx.get_parameter_source(n) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)
    )
    calibration = str(o["calibration"]) if o["calibration"] else None
    settings = BatchSettings(
        calibration=calibration,
        camera=o["camera"],
        options=MergeOptions(
            iterations=o["iterations"],
            tolerance=o["tolerance"],
            saturation=o["saturation"],
            saturation_sigmas=o["saturation_sigmas"],
            prnu=o["prnu"],
            dark_strategy=o["dark_strategy"],
            exposure_times=o["exposure_times"],
        ),
        given=given,
        weighting=o["weighting"],
        dark_strategy=o["dark_strategy"],
        master_dark_frames=o["master_dark_frames"],
        calibration_id=calibration_identity(calibration, o["camera"]),
        sigma_precision=o["sigma_precision"],
        calibration_mismatch=o["calibration_mismatch"],
    )
    report = run_batch(
        runs,
        output,
        settings,
        workers=workers,
        threads=threads,
        scheduler=scheduler,
        force=force,
        progress=progress if progress is not None else (None if not as_json else False),
    )
    for w in report.warnings:
        click.echo(f"hdrcap: warning: {w}", err=True)
    for folder, err in report.failed.items():
        click.echo(f"hdrcap: run failed: {folder}: {err}", err=True)
    if as_json:
        echo_json(report.to_dict())
    else:
        click.echo(
            f"{output}: {len(report.committed)} runs merged, {len(report.skipped)} already there, "
            f"{len(report.failed)} failed, {report.seconds:.1f} s"
        )
    if report.failed:
        raise BatchIncomplete(
            f"{len(report.failed)} of {len(report.failed) + len(report.committed)} runs failed; "
            f"recorded in {output} (attribute hdrcap_failed_runs); run again to retry them",
            reported=as_json,  # the report above is the JSON answer; no second JSON object
        )


command.params.extend(p for p in _merge.params if p.name in SHARED)
