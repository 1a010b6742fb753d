"""``hdrcap capture``: capture one plan (a fixed bracket or a target SNR) into a run folder,
with dark frames, verification, manifest and resume; the job-file-free form of ``hdrcap run``."""

from __future__ import annotations

from pathlib import Path

import click

from hdrcap.cli.util import echo_json, many_values
from hdrcap.pipeline.dark_strategy import DarkStrategy


@many_values("--times")
@click.command("capture")
@click.option(
    "--camera",
    default="mock:camera-B",
    show_default=True,
    help="mock:PRESET or PRESET (simulator, as in plan and merge) or gphoto2[:MODEL] (a real camera; "
    "see `hdrcap cameras`).",
)
@click.option("--port", default=None, help="gphoto2 port of the camera (usb:001,004).")
@click.option("--serial", default=None, help="gphoto2 camera serial number (see `hdrcap cameras`).")
@click.option("--iso", type=click.IntRange(min=1), default=None, help="ISO speed to set (read back and checked).")
@click.option(
    "--enforce",
    is_flag=True,
    help="Set wrong camera settings (program, focus, RAW, ISO, long-exposure NR) instead of refusing.",
)
@click.option("--times", multiple=True, type=float, help="Exposure times, s (a fixed bracket; several after one flag).")
@click.option(
    "--target-snr-db",
    "--target-snr",
    "target_snr",
    type=float,
    default=None,
    help="Plan the exposures for this SNR, dB (meter + planner), as in plan; --target-snr is an alias.",
)
@click.option(
    "--dark-strategy",
    "--darks",
    "dark_strategy",
    type=click.Choice([s.value for s in DarkStrategy]),
    default=None,
    help="Dark frames: one per exposure, N averaged per exposure, or none (model), as in merge; --darks "
    "is a deprecated alias (merge's --darks takes dark frame files).  "
    "[default: matched; with --target-snr-db the planner's choice]",
)
@click.option(
    "--dark-count",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Dark frames per exposure time for --darks master.",
)
@click.option(
    "--block-light",
    type=click.Choice(["mock", "prompt", "command", "none"]),
    default=None,
    help="How the light is blocked for dark frames (default: mock for the simulator, prompt otherwise).",
)
@click.option("--cover-command", default=None, help="Shell command that blocks the light (--block-light command).")
@click.option("--uncover-command", default=None, help="Shell command that unblocks the light.")
@click.option("--calibration", default=None, help="Calibration file (from `hdrcap calibrate`).")
@click.option("--scene", default="hdr", show_default=True, help="Simulator scene (mock camera).")
@click.option("--size", default="256x192", show_default=True, help="Simulator mosaic WIDTHxHEIGHT (mock camera).")
@click.option("--seed", default=0, show_default=True, type=int, help="Simulator seed (mock camera).")
@click.option(
    "--run-dir",
    "--out",
    "out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Run folder (as in run; --out is an alias).",
)
@click.option("--resume", is_flag=True, help="Continue an interrupted capture in --run-dir.")
@click.option("--force", is_flag=True, help="Overwrite hdr.exr / preview.png in --run-dir.")
@click.option("--progress/--no-progress", default=None, help="Progress bar (default: on a terminal).")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary.")
def command(
    camera: str,
    port: str | None,
    serial: str | None,
    iso: int | None,
    enforce: bool,
    times: tuple[float, ...],
    target_snr: float | None,
    dark_strategy: str | None,
    dark_count: int,
    block_light: str | None,
    cover_command: str | None,
    uncover_command: str | None,
    calibration: str | None,
    scene: str,
    size: str,
    seed: int,
    out: Path,
    resume: bool,
    force: bool,
    progress: bool | None,
    as_json: bool,
) -> None:
    """Capture one bracket (or a plan for --target-snr) with dark frames into --out, verify and
    hash every frame into manifest.jsonl, and merge it to --run-dir/hdr.exr.

    SIGTERM or Ctrl-C ends the capture cleanly before the next frame (exit 143 / 130, camera
    closed); --resume continues it. Exit status: see docs/acquisition.md.
    """
    from hdrcap.acquire.capture.job import capture_job
    from hdrcap.acquire.capture.run import run_job
    from hdrcap.acquire.capture.session import stop_on_signals
    from hdrcap.cli.commands.run import _describe

    job = capture_job(
        camera,
        out,
        times=times,
        target_snr_db=target_snr,
        dark_strategy=dark_strategy,
        dark_count=dark_count,
        block_light=block_light,
        cover_command=cover_command,
        uncover_command=uncover_command,
        calibration=calibration,
        scene=scene,
        size=size,
        seed=seed,
        port=port,
        serial=serial,
        iso=iso,
        enforce=enforce,
    )
    with stop_on_signals() as stop:  # SIGTERM / Ctrl-C: a clean, resumable stop (exit 143 / 130)
        res = run_job(job, resume=resume, run_dir=out, progress=progress, force=force, stop=stop)
    if as_json:
        echo_json(res)
    else:
        click.echo(_describe(res))
