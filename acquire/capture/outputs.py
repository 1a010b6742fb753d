"""The outputs of a run: the merged EXR (with the planner's decisions in its header), the
preview PNG and, on the simulated camera, the error against the scene's truth."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdrcap.acquire.camera import Camera
from hdrcap.acquire.capture.job import Job

if TYPE_CHECKING:
    from hdrcap.acquire.capture.session import SessionResult
    from hdrcap.pipeline.params import Calibration


def _plan_merge_options(planned: dict[str, Any]) -> dict[str, Any]:
    """The merge options the planner decided (recorded in the manifest's planning record)."""
    if not planned:
        return {}
    from hdrcap.pipeline.planfile import PLAN_OPTIONS, check_plan

    decided = check_plan(planned, "planner").merge_options()
    return {k: v for k, v in decided.items() if k in PLAN_OPTIONS}


def _write_outputs(
    job: Job,
    run_dir: Path,
    result: SessionResult,
    calibration: Calibration,
    camera: Camera,
    exr_path: Path | None,
    png_path: Path | None,
    replace: dict[Path, bool],
    planner_header: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The run's outputs: the merge's EXR (the one header builder and writer every door uses),
    the preview PNG, and the error against the truth when the camera is simulated;
    ``replace``: output path -> whether it may replace an existing file."""
    from hdrcap.pipeline.header import with_merge_header
    from hdrcap.pipeline.io.raw import read_frame
    from hdrcap.pipeline.io.results import write_result
    from hdrcap.pipeline.preview import write_preview_png

    out: dict[str, Any] = {}
    merge = result.merge
    if merge is None:
        return out
    lights = sorted((r for r in result.frames.values() if r["kind"] == "light"), key=lambda r: r["index"])
    cfa = getattr(getattr(camera, "spec", None), "cfa", None)
    # the files' own metadata (exposure time, CFA pattern, capture time; the colour metadata is
    # read from the first one), as hdrcap merge reads it; the header lists them relative to the
    # run folder, as the manifest does
    frames = [read_frame(run_dir / r["file"], r["file_exposure_s"]) for r in lights]
    cfa = cfa or (frames[0].cfa_pattern if frames else None)
    run = {
        "run_dir": str(run_dir),
        "job": job.name,
        "camera": lights[0]["camera"] if lights else {},
        "manifest": "manifest.jsonl",
    }
    merge = with_merge_header(
        merge,
        frames,
        calibration,
        source_files=[r["file"] for r in lights],
        dark_sources=merge.header.get("dark_sources"),
        run=run,
        planner=planner_header,
    )
    if exr_path is not None:
        write_result(merge, exr_path, format="exr", force=replace.get(exr_path, False))
        out["exr"] = str(exr_path)
    if png_path is not None:
        write_preview_png(png_path, merge.irradiance, cfa, force=replace.get(png_path, False))
        out["png"] = str(png_path)
    truth = getattr(getattr(camera, "sim", None), "scene", None)
    if truth is not None:  # the simulator knows the truth: report the error against it
        from hdrcap.pipeline.evaluation import error_against_truth

        out["error_vs_truth"] = error_against_truth(merge.irradiance, merge.sigma, merge.nexp, truth)
    return out
