"""Every door writes the same file: the same bracket merged by ``hdrcap merge``, the Python API
(``hdrcap.merge(...).write``, ``hdrcap.write_exr``), ``hdrcap capture``, ``hdrcap run``,
``hdrcap demo`` and ``hdrcap batch`` + ``hdrcap export`` gives the same channels, bit for bit and
stored alike (float irradiance, half sigma, uint nexp and quality), and a header with the same
keys; the values differ only where they name where the frames came from."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import hdrcap
from hdrcap.cli import main
from hdrcap.pipeline.io.exr import read_exr, stored_precisions
from hdrcap.pipeline.schema import HEADER_KEYS

TIMES = ["0.001", "0.01", "0.1", "1"]
#: Header entries that say where the frames came from (file paths, the run folder).
PROVENANCE = {"source_files", "dark_sources", "run", "capture_times"}


def _cli(*args) -> None:
    assert main([str(a) for a in args]) == 0


def _files(run: Path) -> tuple[list[Path], list[Path]]:
    """The light and dark frames of a capture run folder, in capture order (from the manifest)."""
    recs = [json.loads(line) for line in (run / "manifest.jsonl").read_text().splitlines()]
    frames = sorted((r for r in recs if r.get("type") == "frame"), key=lambda r: r["index"])
    return [run / r["file"] for r in frames if r["kind"] == "light"], [
        run / r["file"] for r in frames if r["kind"] == "dark"
    ]


def _assert_same_file(path: Path, ref: Path) -> None:
    """``path`` holds ``ref``'s channels bit for bit, stored alike, and a header with the same keys
    (all of the schema's) whose values differ only in provenance."""
    a, b = read_exr(path), read_exr(ref)
    assert stored_precisions(path) == stored_precisions(ref)
    for name in b.channels:
        assert a.channels[name].tobytes() == b.channels[name].tobytes(), (path.name, name)
    assert set(a.header) == set(b.header) == set(HEADER_KEYS)
    differ = {k for k in HEADER_KEYS if a.header[k] != b.header[k]}
    assert differ <= PROVENANCE, (path.name, differ)


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """One bracket with matched dark frames captured by `hdrcap capture` on the simulated camera,
    and `hdrcap merge` of its files: the reference every other door is held to."""
    root = tmp_path_factory.mktemp("doors")
    run = root / "run"
    _cli("capture", "--camera", "mock:camera-B", "--times", *TIMES, "--size", "64x48", "--out", run)
    frames, darks = _files(run)
    ref = root / "merge.exr"
    _cli("merge", *frames, "--darks", *darks, "--camera", "camera-B", "-o", ref)
    return root, run, frames, darks, ref


def test_capture_writes_what_merge_writes(captured):
    _root, run, _frames, _darks, ref = captured
    _assert_same_file(run / "hdr.exr", ref)
    assert stored_precisions(ref) == {"irradiance": "float", "sigma": "half", "nexp": "uint", "quality": "uint"}


def test_the_api_writes_what_merge_writes(captured):
    root, _run, frames, darks, ref = captured
    hdr = hdrcap.merge(frames, calibration="camera-B", darks=darks)
    _assert_same_file(hdr.write(root / "api.exr"), ref)
    _assert_same_file(hdrcap.write_exr(root / "api2.exr", hdr), ref)
    # read back and written again: the same file (half sigma stored as it was)
    _assert_same_file(hdrcap.read_exr(ref).write(root / "again.exr"), ref)


def test_batch_and_export_write_what_merge_writes(captured):
    root, run, _frames, _darks, ref = captured
    _cli("batch", run, "--camera", "camera-B", "-o", root / "a.zarr", "--workers", "1")
    _cli("export", root / "a.zarr", "--run", "0", "-o", root / "export.exr")
    _assert_same_file(root / "export.exr", ref)


def test_run_writes_what_merge_writes(tmp_path):
    job = tmp_path / "job.toml"
    job.write_text(
        "[job]\nname = 'doors'\n\n[camera]\nbackend = 'mock'\npreset = 'camera-B'\nsize = '48x32'\n\n"
        f"[exposure]\nmode = 'bracket'\ntimes = [{', '.join(TIMES)}]\n\n[darks]\nstrategy = 'matched'\n\n"
        "[output]\nfolder = 'runs/r'\n"
    )
    _cli("run", job)
    run = tmp_path / "runs" / "r"
    frames, darks = _files(run)
    _cli("merge", *frames, "--darks", *darks, "--camera", "camera-B", "-o", tmp_path / "merge.exr")
    _assert_same_file(run / "hdr.exr", tmp_path / "merge.exr")
    assert read_exr(run / "hdr.exr").header["run"]["job"] == "doors"


def test_demo_writes_what_merge_writes(tmp_path):
    _cli("demo", "--out", tmp_path / "d", "--size", "48x32")
    frames, darks = _files(tmp_path / "d" / "demo-run")
    _cli("merge", *frames, "--darks", *darks, "--camera", "camera-B", "-o", tmp_path / "merge.exr")
    _assert_same_file(tmp_path / "d" / "demo.exr", tmp_path / "merge.exr")


def test_the_check_can_fail(captured, tmp_path):
    """Another sigma precision or another option is caught."""
    root, _run, frames, darks, ref = captured
    hdr = hdrcap.merge(frames, calibration="camera-B", darks=darks)
    with pytest.raises(AssertionError):
        _assert_same_file(hdr.write(tmp_path / "f.exr", sigma_precision="float"), ref)
    other = hdrcap.merge(frames, calibration="camera-B", darks=darks, options=hdrcap.MergeOptions(iterations=1))
    with pytest.raises(AssertionError):
        _assert_same_file(other.write(tmp_path / "i.exr"), ref)
    assert np.array_equal(read_exr(ref).channels["irradiance"], hdr.irradiance)
