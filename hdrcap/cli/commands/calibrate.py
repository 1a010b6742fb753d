"""``hdrcap calibrate``: bias/saturation/flat/dark frames or an EMVA 1288 data set -> calibration file."""

from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path
from typing import Any

import click

from hdrcap.cli.util import echo_json, many_values
from hdrcap.pipeline.errors import InputError

_FILE = click.Path(dir_okay=False, path_type=Path)
_FOLDER = click.Path(file_okay=False, path_type=Path)
_FRAMES = click.Path(path_type=Path)


@many_values("--bias", "--saturation", "--flat", "--dark", "--shutter", "--times")
@click.command("calibrate", short_help="Calibrate the camera noise model from bias, saturation, flat and dark frames.")
@click.option(
    "--bias",
    multiple=True,
    type=_FRAMES,
    help="Bias frames (zero or shortest exposure); two or more for the pair-difference read noise.",
)
@click.option("--saturation", multiple=True, type=_FRAMES, help="Saturation frame(s): every photosite at full well.")
@click.option(
    "--flat",
    multiple=True,
    type=_FRAMES,
    help="Flat fields; consecutive frames at the same exposure time form pairs (gain). "
    "Pairs at >= 3 levels give the photon-transfer regression.",
)
@click.option(
    "--dark",
    multiple=True,
    type=_FRAMES,
    help="Dark frames at >= 6 exposure times (ordered by time) for the dark current.",
)
@click.option(
    "--shutter",
    multiple=True,
    type=_FRAMES,
    help="Frames of a static scene at the camera's exposure times (several per time allowed; adjacent "
    "times must share well-exposed photosites): per-time shutter corrections stored in the calibration.",
)
@click.option(
    "--shutter-reference",
    type=float,
    help="Reference time (s) of the shutter corrections, whose factor is 1 (default: the longest).",
)
@click.option(
    "--calibration",
    "base_calibration",
    type=_FILE,
    help="Existing calibration to add the --shutter corrections to (written to -o, a new file; never changed).",
)
@click.option(
    "--times",
    multiple=True,
    type=float,
    help="Exposure times (s), one per frame in the order bias, saturation, flat, dark, shutter; "
    "needed for PNG/TIFF frames, override EXIF.",
)
@click.option(
    "--emva", "emva", type=_FILE, help="EMVA 1288 descriptor file (EMVA1288_Data.txt) instead of frame lists."
)
@click.option("-o", "--output", type=_FILE, required=True, help="Calibration file to write (.npz format, any name).")
@click.option(
    "--force", is_flag=True, help="Overwrite an existing output file (and report plots, dark-library entries)."
)
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
@click.option(
    "--report", type=_FOLDER, help="Folder for PNG plots: photon transfer, PRNU histogram and map, dark-current fit."
)
@click.option(
    "--dark-library", type=_FOLDER, help="Store the master darks (with their frame count) in this dark-library folder."
)
@click.option(
    "--gain-method",
    type=click.Choice(["auto", "pairs", "ptc"]),
    default="auto",
    show_default=True,
    help="ptc: EMVA 1288 regression; pairs: Eq. 16 average; auto: ptc when >= 3 levels.",
)
@click.option(
    "--clip",
    type=float,
    default=5.0,
    show_default=True,
    help="Sigma-clipping threshold for hot pixels and cosmic rays.",
)
@click.option("--no-clip", is_flag=True, help="Disable all outlier rejection (for comparison only).")
@click.option(
    "--saturation-criterion",
    type=click.Choice(["frame", "emva"]),
    default="frame",
    show_default=True,
    help="For --emva: v_sat as mean - 3 std of the brightest frames (Sec. 6) or the EMVA 1288 saturation point.",
)
@click.option("--white-level", type=float, help="ADC white level, DN (default: from the raw files).")
@click.option("--camera-name", help="Camera model for the provenance (default: from the files).")
@click.option("--serial", help="Camera serial number for the provenance.")
@click.option("--iso", type=float, help="ISO for the provenance (default: from EXIF).")
@click.option(
    "--temperature", type=float, help="Sensor temperature, degrees C, for the provenance and the dark library."
)
@click.option(
    "--save-to-library",
    is_flag=True,
    help="Also store the calibration in the calibration library (keyed by camera model, serial and ISO; "
    "`hdrcap merge` without --calibration finds it there; see `hdrcap calibrations`).",
)
def command(
    bias: tuple[Path, ...],
    saturation: tuple[Path, ...],
    flat: tuple[Path, ...],
    dark: tuple[Path, ...],
    shutter: tuple[Path, ...],
    shutter_reference: float | None,
    base_calibration: Path | None,
    times: tuple[float, ...],
    emva: Path | None,
    output: Path,
    force: bool,
    as_json: bool,
    report: Path | None,
    dark_library: Path | None,
    gain_method: str,
    clip: float,
    no_clip: bool,
    saturation_criterion: str,
    white_level: float | None,
    camera_name: str | None,
    serial: str | None,
    iso: float | None,
    temperature: float | None,
    save_to_library: bool,
) -> None:
    """Calibrate the camera noise model (Sec. 6 of the paper, EMVA 1288) into a calibration file.

    From frame lists: mu_R and sigma2_R from bias frames (pair difference), v_sat from a
    saturation frame, the PRNU map a_j (Eq. 14) and the gain g from flat fields (pairs, Eq. 16,
    or the EMVA 1288 photon-transfer regression), the dark current from darks at >= 6 times.
    Or from an EMVA 1288 data set with --emva. Every estimate carries its standard error.
    With --shutter, the per-time shutter corrections (t_eff/t_nom, relative to the reference
    time) measured from frames of a static scene, added to this calibration or, with
    --calibration FILE, to an existing one.
    """
    from hdrcap import __version__
    from hdrcap.pipeline.calibration import (
        add_shutter_table,
        calibrate_files,
        calibration_summary,
        format_summary,
        load_calibration,
        save_calibration,
    )
    from hdrcap.pipeline.io.files import check_new_output

    t0 = time.perf_counter()
    prov: dict[str, Any] = {
        "hdrcap_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
    for key, val in (("camera", camera_name), ("serial", serial), ("iso", iso), ("temperature", temperature)):
        if val is not None:
            prov[key] = val
    if base_calibration is not None and output.resolve() == base_calibration.resolve():
        raise InputError(f"{output}: is the calibration given with --calibration; write the result to a new file")
    check_new_output(output, force)
    emva_res = None
    if base_calibration is not None:
        if bias or saturation or flat or dark or emva is not None:
            raise InputError(
                "give either --calibration FILE or calibration frames (--bias/--flat/... or --emva), not both"
            )
        if not shutter:
            raise InputError("--calibration FILE needs --shutter frames to add to it")
        calib = add_shutter_table(load_calibration(base_calibration), shutter, times, reference=shutter_reference)
    elif emva is not None:
        if bias or saturation or flat or dark:
            raise InputError("give either --emva or frame lists (--bias/--saturation/--flat/--dark), not both")
        from hdrcap.pipeline.calibration.emva import calibrate_descriptor

        calib, emva_res = calibrate_descriptor(emva, saturation_criterion, prov)
        if shutter:
            calib = add_shutter_table(calib, shutter, times, reference=shutter_reference)
    else:
        calib = calibrate_files(
            bias,
            saturation,
            flat,
            dark,
            times,
            shutter=shutter,
            shutter_reference=shutter_reference,
            clip=None if no_clip else clip,
            gain_method=gain_method,
            white_level=white_level,
            provenance=prov,
            dark_library=dark_library,
            force=force,
        )
    save_calibration(output, calib, force=force)
    stored = None
    if save_to_library:
        from hdrcap.pipeline.calibration.library import store_calibration

        stored = store_calibration(calib, force=force)
    plots = []
    if report is not None:
        from hdrcap.pipeline.calibration.report import write_report

        plots = write_report(calib, report, force=force)
    summary = calibration_summary(calib, output=output, seconds=time.perf_counter() - t0, emva=emva_res, report=plots)
    if stored is not None:
        summary["library_file"] = str(stored)
    if as_json:
        echo_json(summary)
    else:
        click.echo(format_summary(summary))
        click.echo(f"wrote {output} ({summary['n_frames']} frames, {summary['seconds']:.1f} s)")
        if stored is not None:
            click.echo(f"stored in the calibration library as {stored}")
