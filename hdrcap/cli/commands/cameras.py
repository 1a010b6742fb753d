"""``hdrcap cameras``: list the cameras libgphoto2 detects (and the simulator presets)."""

from __future__ import annotations

import click

from hdrcap.cli.util import echo_json


@click.command("cameras")
@click.option("--json", "as_json", is_flag=True, help="Print JSON on stdout.")
def command(as_json: bool) -> None:
    """List detected cameras (model, port and serial number, via libgphoto2) and the simulated
    camera presets usable as backend = "mock". The serial is what a job's [camera] serial = "..."
    matches; it keeps the camera found after a re-plug gives it a new port."""
    from hdrcap.mock_camera import PRESETS

    try:
        from hdrcap.acquire.camera.gphoto2 import list_cameras

        found = list_cameras(serials=True)
        problem = None
    except Exception as err:  # libgphoto2 missing or failing: still list the presets
        found, problem = [], f"{type(err).__name__}: {err}"
    mock = [{"preset": k, "model": v.model} for k, v in PRESETS.items()]
    if as_json:
        echo_json(
            {"gphoto2": [{"model": m, "port": p, "serial": s} for m, p, s in found], "mock": mock, "problem": problem}
        )
        return
    if found:
        for m, p, s in found:
            click.echo(f"{m:40s} {p:16s} serial {s or '(not reported)'}")
    else:
        click.echo("no camera detected by libgphoto2" + (f" ({problem})" if problem else ""))
    click.echo('simulated cameras (backend = "mock"): ' + ", ".join(x["preset"] for x in mock))
