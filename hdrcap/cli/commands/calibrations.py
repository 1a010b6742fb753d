"""``hdrcap calibrations list|show|remove``: the calibration library."""

from __future__ import annotations

import click

from hdrcap.cli.util import echo_json


@click.group("calibrations")
def command() -> None:
    """The calibration library: calibrations stored by `hdrcap calibrate --save-to-library`, keyed by
    camera model, serial and ISO, that `hdrcap merge` uses when no --calibration is given. Folder:
    $HDRCAP_DATA_DIR/calibrations, else $XDG_DATA_HOME/hdrcap/calibrations (~/.local/share)."""


@command.command("list")
@click.option("--json", "as_json", is_flag=True, help="Print one line of JSON.")
def list_(as_json: bool) -> None:
    """List the library's calibrations (name, model, serial, ISO)."""
    from hdrcap.pipeline.calibration.library import library_dir, library_entries

    entries = library_entries()
    if as_json:
        echo_json(
            {
                "folder": str(library_dir()),
                "entries": [
                    {"name": e.name, "model": e.model, "serial": e.serial, "iso": e.iso, "path": str(e.path)}
                    for e in entries
                ],
            }
        )
        return
    click.echo(f"{library_dir()}: {len(entries)} calibration(s)")
    for e in entries:
        click.echo(f"  {e.name}  model {e.model}, serial {e.serial or 'any'}, ISO {e.iso:g}")


@command.command("show")
@click.argument("name")
@click.option("--json", "as_json", is_flag=True, help="Print one line of JSON.")
def show(name: str, as_json: bool) -> None:
    """Show the calibration NAME (a name from `hdrcap calibrations list`)."""
    from hdrcap.pipeline.calibration import load_calibration
    from hdrcap.pipeline.calibration.library import library_dir
    from hdrcap.pipeline.errors import InputError

    path = library_dir() / (name if name.endswith(".cal") else name + ".cal")
    if not path.is_file():
        raise InputError(f"{name}: no such calibration in the library {library_dir()}")
    calib = load_calibration(path)
    info = {
        "name": path.name,
        "path": str(path),
        "params": calib.params.to_dict(),
        "stderr": calib.stderr,
        "camera": calib.provenance.get("camera"),
        "iso": calib.provenance.get("iso"),
        "created": calib.provenance.get("created"),
        "maps": [
            k
            for k in ("prnu", "bias_map", "dark_current_map", "saturation_map", "defect_map")
            if getattr(calib, k) is not None
        ],
    }
    if as_json:
        echo_json(info)
        return
    p = calib.params
    click.echo(
        f"{path}\n  camera {info['camera']}, ISO {info['iso']}, created {info['created']}\n"
        f"  g = {p.g:.4g} DN/e-, mu_R = {p.mu_R:.4g} DN, sigma_R^2 = {p.sigma2_R:.4g} DN^2, "
        f"v_sat = {p.v_sat:.6g} DN, D = {p.dark_current:.3g} e-/s\n  maps: {', '.join(info['maps']) or 'none'}"
    )


@command.command("remove")
@click.argument("name")
def remove(name: str) -> None:
    """Remove the calibration NAME from the library."""
    from hdrcap.pipeline.calibration.library import remove_calibration

    click.echo(f"removed {remove_calibration(name)}")
