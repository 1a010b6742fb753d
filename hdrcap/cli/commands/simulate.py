"""``hdrcap simulate``: write a simulated bracket (DNG), dark frames and the true irradiance."""

from __future__ import annotations

from pathlib import Path

import click

from hdrcap.cli.util import echo_json, many_values


@many_values("--times")
@click.command("simulate")
@click.option(
    "--camera",
    "camera_name",
    default="camera-B",
    show_default=True,
    help="Simulator preset: camera-A (12 bit) or camera-B (10 bit), Table 2 of the paper.",
)
@click.option(
    "--scene",
    default="hdr",
    show_default=True,
    help="Scene: hdr, gradient, patches, edges, flat, or an EXR file of irradiance (e-/s).",
)
@click.option(
    "--times",
    multiple=True,
    type=float,
    help="Exposure times in seconds (several after one flag).  [default: 1/1000 to 1 s, 6 steps]",
)
@click.option("--darks/--no-darks", default=False, help="Also take one matching dark frame per exposure.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True, help="Output folder.")
@click.option("--size", default="1024x768", show_default=True, help="Mosaic size WIDTHxHEIGHT (even numbers).")
@click.option(
    "--decades",
    default=4.0,
    show_default=True,
    type=float,
    help="Dynamic range of a synthetic scene, orders of magnitude.",
)
@click.option(
    "--x-max", default=2e5, show_default=True, type=float, help="Brightest irradiance of a synthetic scene, e-/s."
)
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed (fixed patterns and noise).")
@click.option(
    "--temperature", default=None, type=float, help="Sensor temperature, degrees C (dark current doubles every 6.3 C)."
)
@click.option("--force", is_flag=True, help="Overwrite existing files in the output folder.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary on stdout.")
@click.option(
    "--calibration-set",
    is_flag=True,
    help="Instead of a bracket, write a calibration series (bias, saturation, 36 flats, a photon-transfer series, darks at 6 times) and calibration_set.json, for `hdrcap calibrate`.",
)
def command(
    camera_name: str,
    scene: str,
    times: tuple[float, ...],
    darks: bool,
    out: Path,
    size: str,
    decades: float,
    x_max: float,
    seed: int,
    temperature: float | None,
    force: bool,
    as_json: bool,
    calibration_set: bool,
) -> None:
    """Simulate a bracket: DNG frames (and dark frames) plus truth.exr and simulation.json.

    The DNGs hold the CFA mosaic with BlackLevel, WhiteLevel, ExposureTime and ISO (IFD0 and
    EXIF IFD), camera model and timestamp; they open in rawpy/LibRaw tools such as HDRMerge.
    """
    from hdrcap.mock_camera.scenes import parse_size
    from hdrcap.mock_camera.simulation import DEFAULT_TIMES, simulate_bracket, simulate_calibration_set

    if calibration_set:
        desc = simulate_calibration_set(
            camera_name, out, parse_size(size), seed, temperature, force, progress=not as_json
        )
        if as_json:
            echo_json(
                {
                    "camera": camera_name,
                    "seed": seed,
                    "shape": desc["shape"],
                    "out": str(out),
                    "n_frames": desc["n_frames"],
                    "manifest": str(out / "calibration_set.json"),
                }
                | {f"n_{k}": len(v) for k, v in desc["files"].items()}
            )
        else:
            click.echo(f"wrote a calibration set of {desc['n_frames']} frames and calibration_set.json to {out}")
        return
    desc = simulate_bracket(
        camera_name,
        scene,
        list(times) or list(DEFAULT_TIMES),
        out,
        darks,
        parse_size(size),
        decades,
        x_max,
        seed,
        temperature,
        force,
        progress=not as_json,
    )
    if as_json:
        echo_json(
            {k: desc[k] for k in ("camera", "scene", "seed", "shape", "exposure_times", "truth")}
            | {"n_frames": len(desc["frames"]), "n_darks": len(desc["darks"]), "out": str(out)}
        )
    else:
        click.echo(f"wrote {len(desc['frames'])} frames, {len(desc['darks'])} dark frames and truth.exr to {out}")
