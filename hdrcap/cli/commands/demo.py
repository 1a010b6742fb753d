"""``hdrcap demo``: the main job on the built-in simulated camera through the same capture
session as a real camera (MockCamera -> CaptureSession -> streamed merge), no hardware needed."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from hdrcap.cli.util import echo_json

if TYPE_CHECKING:
    from hdrcap.pipeline.result import HdrResult

#: The demo bracket: exposure times the simulated camera offers (1/1000 to 1 s, two stops apart).
DEMO_TIMES = (0.001, 0.004, 1 / 60, 1 / 15, 0.25, 1.0)


def run_demo(
    out: Path,
    camera: str,
    scene: str,
    size: str,
    seed: int,
    force: bool,
    progress: bool | None = None,
    target_snr: float | None = None,
) -> dict[str, Any]:
    """Capture, merge and summarise the demo into ``out``; returns the summary text and paths."""
    from hdrcap.acquire.capture.job import job_from_dict
    from hdrcap.acquire.capture.manifest import Manifest
    from hdrcap.acquire.capture.run import run_job
    from hdrcap.pipeline.errors import OutputExistsError
    from hdrcap.pipeline.io.files import atomic_output, check_new_output
    from hdrcap.pipeline.times import unique_exposures

    out = Path(out)
    for name in ("demo.exr", "demo.png", "summary.txt"):
        check_new_output(out / name, force)
    run_dir = out / "demo-run"
    if run_dir.exists():
        head = Manifest(run_dir).header()
        if head is not None and head.get("job_name") == "demo" and force:
            shutil.rmtree(run_dir)  # the previous demo's capture, replaced as --force says
        elif head is not None or any(run_dir.iterdir()):
            raise OutputExistsError(f"{run_dir}: holds an earlier capture; use --force to replace it")
    out.mkdir(parents=True, exist_ok=True)
    exposure: dict[str, Any] = {"mode": "bracket", "times": list(DEMO_TIMES)}
    if target_snr is not None:
        exposure = {"mode": "snr", "target_snr_db": target_snr, "times": list(DEMO_TIMES)}
    job = job_from_dict(
        {
            "job": {"name": "demo"},
            "camera": {"backend": "mock", "preset": camera, "size": size, "seed": seed},
            "scene": {"name": scene, "decades": 4.0, "x_max": 2e5},
            "exposure": exposure,
            "darks": {"strategy": "matched", "block_light": "mock"},
            "output": {"folder": str(run_dir)},
        }
    )
    res, session = run_job(
        job,
        run_dir=run_dir,
        progress=progress,
        force=force,
        exr_path=out / "demo.exr",
        png_path=out / "demo.png",
        return_result=True,
        echo=lambda s: click.echo(s, err=True),
    )
    # a new run (no resume) always captures, and with its calibration always merges
    assert session is not None and session.merge is not None
    err = res["error_vs_truth"]
    m = session.merge
    times = sorted(unique_exposures(r["file_exposure_s"] for r in session.frames.values() if r["kind"] == "light"))
    n_dark = sum(r["kind"] == "dark" for r in session.frames.values())
    lines = [
        "hdrcap demo: simulated camera -> capture session (bracket + dark frames) -> merge",
        f"camera: {camera} (MockCamera); scene: {scene} ({size}), 4 decades; seed {seed}",
        f"exposures (s): {', '.join(f'{t:g}' for t in times)} (+ {n_dark} dark frames)",
        f"capture: {res['frames']} frames verified and hashed in {run_dir / 'manifest.jsonl'} "
        f"({res['elapsed_s']:.1f} s)",
        f"merge: {m.info.get('method', 'ML')}, dark strategy {m.info.get('dark_strategy', 'matched')}, "
        f"{'streamed as frames landed' if res['streamed_merge'] else 'merged after the last frame'}",
        f"output: {out / 'demo.exr'} ({_channels(m)}), preview {out / 'demo.png'}",
        "error against the simulator's ground truth (photosites with an unsaturated exposure):",
        f"  median |relative error|   {err['median_abs_relative_error']:.4%}",
        f"  z = (estimate - truth)/sigma: mean {err['z_mean']:+.3f}, std {err['z_std']:.3f} (1 = honest sigma)",
        f"  |z| > 3: {err['fraction_abs_z_gt_3']:.4%}   |z| > 6: {err['fraction_abs_z_gt_6']:.5%}",
        f"  median SNR {err['median_snr_db']:.1f} dB; saturated in every exposure: {err['saturated_everywhere']}",
    ]
    text = "\n".join(lines) + "\n"
    with atomic_output(out / "summary.txt", force=force) as tmp:
        tmp.write_text(text)
    return {
        "text": text,
        "error": err,
        "exr": str(out / "demo.exr"),
        "png": str(out / "demo.png"),
        "run_dir": str(run_dir),
    }


@click.command("demo")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out"),
    show_default=True,
    help="Output folder (demo-run/ holds the captured DNGs, manifest and event log).",
)
@click.option("--camera", default="camera-B", show_default=True, help="Simulator preset: camera-A or camera-B.")
@click.option("--scene", default="hdr", show_default=True, help="Synthetic scene name or an EXR file.")
@click.option("--size", default="1024x768", show_default=True, help="Mosaic size WIDTHxHEIGHT.")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option(
    "--target-snr",
    type=float,
    default=None,
    help="Plan the exposures for this SNR (dB) with the planner instead of the fixed bracket.",
)
@click.option("--force", is_flag=True, help="Overwrite the outputs (and the capture) of an earlier demo.")
@click.option("--json", "as_json", is_flag=True, help="Print a one-line JSON summary instead of the text.")
def command(
    out: Path, camera: str, scene: str, size: str, seed: int, target_snr: float | None, force: bool, as_json: bool
) -> None:
    """Capture a bracket with dark frames from the simulated camera through the capture session,
    merge it, write out/demo.exr, a tone-mapped out/demo.png and out/summary.txt with the error
    against the simulator's ground truth."""
    # the capture's progress bar on a terminal only (None), never with --json
    res = run_demo(out, camera, scene, size, seed, force, progress=False if as_json else None, target_snr=target_snr)
    if as_json:
        echo_json({"exr": res["exr"], "png": res["png"], **res["error"]})
    else:
        click.echo(res["text"], nl=False)


def _channels(result: HdrResult) -> str:
    """The EXR channels of the demo's merge, and why sigma_calibration is missing when it is."""
    if getattr(result, "sigma_calibration", None) is not None:
        return "irradiance, sigma, sigma_calibration, nexp, quality"
    return "irradiance, sigma, nexp, quality; no sigma_calibration: the calibration has no standard errors"
