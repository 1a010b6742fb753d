"""``hdrcap run JOB.toml``: a measurement job end to end (meter -> plan -> capture -> merge ->
outputs), optionally repeated on a schedule."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from hdrcap.cli.util import echo_json


@click.command("run")
@click.argument("job_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--resume",
    is_flag=True,
    help="Continue the newest incomplete run of the job; on a finished run only report it (exit 0).",
)
@click.option(
    "--repeat", type=click.IntRange(min=1), default=None, help="Run the job N times (overrides [schedule] repeat)."
)
@click.option(
    "--every",
    "every",
    type=click.FloatRange(min=0),
    default=None,
    metavar="SECONDS",
    help="Start a repetition every SECONDS (overrides [schedule] every_s).",
)
@click.option(
    "--keep-going",
    is_flag=True,
    help="A failed repetition does not end the schedule (the exit status is the first failure's).",
)
@click.option(
    "--run-dir",
    "--out",
    "run_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Run folder (overrides [output] folder; with --repeat it must contain {n}); --out as in capture.",
)
@click.option("--force", is_flag=True, help="Overwrite the EXR/PNG outputs of an earlier run in the same folder.")
@click.option(
    "--check",
    is_flag=True,
    help="Only validate the job, the camera's range and the free disk space (exit 6 when short); take no frame.",
)
@click.option("--progress/--no-progress", default=None, help="Progress bar (default: on a terminal).")
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print one JSON line per repetition as it ends (an error: a JSON object, see docs/acquisition.md).",
)
def command(
    job_file: Path,
    resume: bool,
    repeat: int | None,
    every: float | None,
    keep_going: bool,
    run_dir: Path | None,
    force: bool,
    check: bool,
    progress: bool | None,
    as_json: bool,
) -> None:
    """Run the measurement described by JOB_FILE (TOML; see docs/acquisition.md).

    The job is validated before any frame is taken; every frame is verified, hashed and
    recorded in the run folder's manifest.jsonl, events go to events.jsonl. An interrupted
    run (also by SIGTERM or Ctrl-C, which end it cleanly) continues with --resume without
    duplicating or losing a frame. Exit status: see docs/acquisition.md.
    """
    from hdrcap.acquire.capture.camera_setup import check_free_space, check_job_against_camera, open_camera
    from hdrcap.acquire.capture.job import load_job
    from hdrcap.acquire.capture.runfolder import run_folder
    from hdrcap.acquire.capture.schedule import run_schedule
    from hdrcap.acquire.capture.session import stop_on_signals

    job = load_job(job_file)
    if check:
        cam = open_camera(job)
        try:
            check_job_against_camera(job, cam, lambda line: click.echo(line, err=True))
            reps = repeat or job["schedule"]["repeat"]
            space = check_free_space(job, cam, run_dir or run_folder(job), repetitions=reps)
        finally:
            cam.close()
        frames = f"{space['frames']} frames" if space["frames"] else "frames decided by metering (1 counted)"
        click.echo(
            f"{job_file}: ok; disk: {frames} and outputs need about {space['need_bytes'] / 1e6:.0f} MB"
            + (f" for {reps} runs" if reps > 1 else "")
            + f", {space['free_bytes'] / 1e6:.0f} MB free "
            f"in {space['folder']}"
        )
        return

    def report(res: dict[str, Any]) -> None:
        if as_json:
            echo_json(res)
        else:
            click.echo(_describe(res))

    with stop_on_signals() as stop:
        run_schedule(
            job,
            repeat=repeat,
            every_s=every,
            resume=resume,
            progress=progress,
            run_dir=run_dir,
            force=force,
            keep_going=keep_going,
            on_result=report,
            stop=stop,
        )


def _describe(res: dict[str, Any]) -> str:
    if res.get("status") == "failed":
        return f"run {res.get('run_dir') or '-'}: failed (exit {res['exit_code']}): {res['error']}"
    if res.get("status") == "nothing_to_resume":
        return f"run: {res['message']}; nothing to do"
    done = " (already complete; nothing resumed)" if res.get("status") == "already_complete" else ""
    if "frames" not in res:
        return f"run {res['run_dir']}: complete{done}"
    lines = [
        f"run {res['run_dir']}: {res['frames']} frames ({res['captured']} captured now, "
        f"{res['resumed']} from before, {res['adopted']} adopted) in {res['elapsed_s']:.1f} s{done}"
    ]
    if res["retries"]:
        lines.append("  recovered faults: " + ", ".join(f"{k} {v}" for k, v in sorted(res["retries"].items())))
    for k in ("exr", "png"):
        if k in res:
            lines.append(f"  {k}: {res[k]}")
    err = res.get("error_vs_truth")
    if err and err.get("n_used"):
        lines.append(
            f"  vs simulator truth: median |rel. error| {err['median_abs_relative_error']:.3%}, "
            f"z mean {err['z_mean']:+.3f} std {err['z_std']:.3f}"
        )
    return "\n".join(lines)
