"""``hdrcap plan``: the exposures (and dark frames) that reach a target SNR on a scene (Sec. 8)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import click

from hdrcap.cli.util import echo_json, many_values
from hdrcap.pipeline.errors import InputError

if TYPE_CHECKING:
    import numpy as np

    from hdrcap.pipeline.params import Calibration
    from hdrcap.planner.meter import MeterReport


def _metered_irradiance(
    camera: str | None,
    scene: str,
    size: str,
    decades: float,
    x_max: float,
    seed: int,
    calibration: Calibration,
    allowed: Sequence[float] | None,
    meter_frames: int,
    meter_max_time: float,
) -> tuple[np.ndarray, MeterReport]:
    """The scene metered with quick frames of the simulated camera: (irradiance, MeterReport)."""
    import numpy as np

    from hdrcap.mock_camera import PRESETS, SimulatedSensor
    from hdrcap.mock_camera.scenes import load_scene, parse_size
    from hdrcap.planner import meter

    if not camera:
        raise InputError(
            "--meter needs a camera; `hdrcap plan` meters with the simulated camera only: give --camera PRESET"
        )
    if camera not in PRESETS:
        raise InputError(f"unknown camera preset {camera!r}; choose from {', '.join(PRESETS)}")
    X = load_scene(scene, parse_size(size), decades, x_max)
    sensor = SimulatedSensor(PRESETS[camera], X.shape, seed=seed)
    rng = np.random.default_rng([seed, 7])
    return meter(
        lambda t: sensor.expose(X, t, rng=rng),
        calibration,
        allowed,
        return_report=True,
        max_frames=meter_frames,
        max_time=meter_max_time,
    )


@many_values("--allowed-times", "--dark-library")
@click.command("plan")
@click.option("--calibration", type=click.Path(path_type=Path), help="Calibration file written by `hdrcap calibrate`.")
@click.option(
    "--camera",
    help="Simulator preset (camera-A, camera-B, or mock:camera-B as in capture): its nominal parameters, "
    "and the camera --meter uses.",
)
@click.option(
    "--irradiance",
    type=click.Path(path_type=Path),
    help="Irradiance map of the scene (EXR, e-/s per photosite), e.g. a previous merge or truth.exr.",
)
@click.option(
    "--meter",
    "do_meter",
    is_flag=True,
    help="Meter the scene with quick frames of the simulated camera instead of --irradiance.",
)
@click.option(
    "--scene",
    default="hdr",
    show_default=True,
    help="Scene the simulated camera sees with --meter (hdr, gradient, patches, edges, flat or an EXR).",
)
@click.option("--size", default="256x192", show_default=True, help="Scene size WIDTHxHEIGHT for --meter.")
@click.option(
    "--decades",
    default=4.0,
    show_default=True,
    type=float,
    help="Dynamic range of a synthetic --meter scene, orders of magnitude.",
)
@click.option(
    "--x-max",
    default=2e5,
    show_default=True,
    type=float,
    help="Brightest irradiance of a synthetic --meter scene, e-/s.",
)
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of the simulated metering frames.")
@click.option(
    "--meter-frames",
    default=2,
    show_default=True,
    type=click.IntRange(1, 5),
    help="Metering frames at most (shortest time first).",
)
@click.option("--meter-max-time", default=1.0, show_default=True, type=float, help="Longest metering exposure, s.")
@click.option(
    "--target-snr-db",
    "--target-snr",
    "target_snr_db",
    type=float,
    required=True,
    help="Target SNR of the merged irradiance, dB (20 log10); --target-snr is an alias, as in capture.",
)
@click.option(
    "--max-exposures", type=click.IntRange(min=1), help="Maximum number of exposures (dark frames not counted)."
)
@click.option("--time-budget", type=float, help="Maximum total capture time incl. dark frames and overheads, s.")
@click.option(
    "--overhead",
    type=float,
    help="Per-frame overhead besides the exposure (shutter latency, raw write, USB download), s.  [default: "
    "1, typical of a tethered DSLR]",
)
@click.option(
    "--highlight-fraction",
    type=click.FloatRange(0, 1, max_open=True),
    help="The first exposure is the longest that saturates at most this fraction of the eligible pixels "
    "(the scene's highlights).  [default: 0.05]",
)
@click.option(
    "--allowed-times",
    multiple=True,
    help="Exposure times the camera offers (s or fractions like 1/250, several after one flag).  [default: "
    "1/3-EV ladder 1/8000..30 s]",
)
@click.option(
    "--quantile",
    type=float,
    help="Fraction of eligible pixels that must reach the target.  [default: 1, all pixels not saturated at "
    "the shortest time]",
)
@click.option(
    "--dark-error",
    type=float,
    help="RMS error of the dark current subtracted without a dark frame, e-/s.  [default: from the calibration]",
)
@click.option(
    "--dark-library",
    multiple=True,
    help="Master darks available: TIME:N (exposure time in s or a fraction, frame count), several after one flag.",
)
@click.option(
    "--uniform-darks",
    is_flag=True,
    help="One dark strategy for all exposures (dark frames for all when any needs one).",
)
@click.option("--explain", is_flag=True, help="Print each model decision with the figure that drove it.")
@click.option("--json", "as_json", is_flag=True, help="Print the plan as one line of JSON.")
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write the Fig. 7 plot (sequence over the histogram, predicted SNR) to this PNG.",
)
@click.option("--force", is_flag=True, help="Overwrite an existing --plot file.")
def command(
    calibration: Path | None,
    camera: str | None,
    irradiance: Path | None,
    do_meter: bool,
    scene: str,
    size: str,
    decades: float,
    x_max: float,
    seed: int,
    meter_frames: int,
    meter_max_time: float,
    target_snr_db: float,
    max_exposures: int | None,
    time_budget: float | None,
    overhead: float | None,
    highlight_fraction: float | None,
    allowed_times: tuple[str, ...],
    quantile: float | None,
    dark_error: float | None,
    dark_library: tuple[str, ...],
    uniform_darks: bool,
    explain: bool,
    as_json: bool,
    plot: Path | None,
    force: bool,
) -> None:
    """Plan the exposures that reach --target-snr-db on a scene (greedy Eq. 18, Sec. 8).

    The scene comes from an irradiance map (--irradiance MAP.exr) or from metering quick
    frames (--meter; simulated camera). The plan lists exposure times in capture order (first
    the longest that does not saturate the scene's bulk, all but the brightest
    --highlight-fraction of the pixels), the dark strategy of each (matched dark frame, master
    dark, or model) and its dark-frame count, the merge options to use, the predicted minimum
    SNR, the total capture time and the model decisions (dark frames, PRNU, saturation model,
    merge iterations) with the figures that drove them. Infeasible requests are reported with
    the best achievable SNR (exit status 0; "feasible": false in the JSON).
    """
    import numpy as np

    from hdrcap.pipeline.io.files import check_new_output
    from hdrcap.planner import plan_exposures, systematic_errors_from_calibration
    from hdrcap.planner.ladder import parse_dark_library, parse_times
    from hdrcap.planner.meter import read_irradiance_map
    from hdrcap.planner.plan import DEFAULT_HIGHLIGHT_FRACTION, DEFAULT_OVERHEAD_S

    overhead = DEFAULT_OVERHEAD_S if overhead is None else overhead
    highlight_fraction = DEFAULT_HIGHLIGHT_FRACTION if highlight_fraction is None else highlight_fraction

    if bool(irradiance) == bool(do_meter):
        raise InputError("give exactly one scene source: --irradiance MAP.exr or --meter")
    if not np.isfinite(target_snr_db):
        raise InputError(f"--target-snr-db must be a finite number, got {target_snr_db!r}")
    if plot is not None:
        check_new_output(plot, force)
    from hdrcap.acquire.camera.model import camera_model
    from hdrcap.mock_camera.sensor import preset_name

    camera = preset_name(camera) if camera else None
    cal = camera_model(calibration, camera)
    try:
        allowed = parse_times(allowed_times)
    except ValueError as err:
        raise InputError(f"--allowed-times: {err}") from None
    try:
        library = parse_dark_library(dark_library)
    except ValueError as err:
        raise InputError(str(err)) from None
    meter_report = None
    if irradiance is not None:  # exactly one source, checked above
        X = read_irradiance_map(irradiance)
    else:
        X, meter_report = _metered_irradiance(
            camera, scene, size, decades, x_max, seed, cal, allowed, meter_frames, meter_max_time
        )
    errors = None
    if dark_error is not None:
        if not (np.isfinite(dark_error) and dark_error >= 0):
            raise InputError(f"--dark-error must be >= 0 e-/s, got {dark_error!r}")
        errors = dataclasses.replace(systematic_errors_from_calibration(cal), dark_current=dark_error)
    plan = plan_exposures(
        cal,
        X,
        target_snr_db,
        allowed,
        max_exposures=max_exposures,
        time_budget=time_budget,
        overhead=overhead,
        quantile=quantile,
        errors=errors,
        dark_library=library or None,
        uniform_darks=uniform_darks,
        highlight_fraction=highlight_fraction,
    )
    if plot is not None:
        from hdrcap.planner.plot import plot_plan

        plot_plan(plan, cal, plot, force=force)
    if as_json:
        out = plan.to_dict()
        if meter_report is not None:
            out["metering"] = meter_report.to_dict()
        if plot is not None:
            out["plot"] = str(plot)
        echo_json(out)
        return
    if meter_report is not None:
        click.echo(meter_report.message)
    click.echo(plan.explain() if explain else plan.message)
    if plot is not None:
        click.echo(f"wrote {plot}")
