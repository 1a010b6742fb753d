"""The command line end to end: simulate -> merge -> EXR, demo, and every bad input of the
walking-skeleton issue giving a one-line error without a traceback."""

import json

import numpy as np
import pytest

from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.io.raw import read_raw


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    from tests.helpers.cli import run_cli

    out = tmp_path_factory.mktemp("sim")
    proc = run_cli(
        "simulate",
        "--camera",
        "camera-B",
        "--scene",
        "patches",
        "--size",
        "64x48",
        "--times",
        "0.002",
        "0.02",
        "0.2",
        "--darks",
        "--out",
        out,
        "--seed",
        "3",
        "--json",
        check=True,
    )
    return out, json.loads(proc.stdout)


def _no_traceback(proc):
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("hdrcap: error:"), proc.stderr


def test_simulate_writes_dngs_truth_and_description(bracket):
    out, info = bracket
    assert info["n_frames"] == 3 and info["n_darks"] == 3 and info["shape"] == [48, 64]
    desc = json.loads((out / "simulation.json").read_text())
    for path, t in zip(desc["frames"], desc["exposure_times"]):
        fr = read_raw(path)
        assert fr.exposure_time == t and fr.iso == 400 and fr.cfa_pattern == "RGGB"
        assert fr.black_level == 32 and fr.white_level == 1023
    truth = read_exr(out / "truth.exr")
    assert truth.channels["irradiance"].shape == (48, 64)


def test_merge_end_to_end_against_truth(bracket, cli, tmp_path):
    out, _ = bracket
    frames = sorted(str(p) for p in out.glob("frame_*.dng"))
    darks = sorted(str(p) for p in out.glob("dark_*.dng"))
    exr = tmp_path / "m.exr"
    proc = cli("merge", *frames, "--darks", *darks, "--camera", "camera-B", "-o", exr, "--json", check=True)
    summary = json.loads(proc.stdout)
    assert summary["finite"] and summary["n_frames"] == 3 and summary["n_darks"] == 3
    img = read_exr(exr)
    assert set(img.channels) >= {"irradiance", "sigma", "nexp"}
    assert img.header["unit"].startswith("electrons per second")
    assert img.header["cfa_pattern"] == "RGGB" and len(img.header["exposure_times"]) == 3
    truth = read_exr(out / "truth.exr").channels["irradiance"].astype(float)
    ok = img.channels["nexp"] > 0
    z = (img.channels["irradiance"][ok] - truth[ok]) / img.channels["sigma"][ok]
    assert abs(np.median(z)) < 0.2 and 0.6 < np.subtract(*np.percentile(z, [84, 16])) / 2 < 1.5
    # never overwrite without --force; with --force it works
    again = cli("merge", *frames, "--camera", "camera-B", "-o", exr)
    assert again.returncode != 0 and "exists" in again.stderr
    _no_traceback(again)
    assert cli("merge", *frames, "--camera", "camera-B", "-o", exr, "--force").returncode == 0


def test_bad_inputs_one_line_errors(bracket, cli, tmp_path):
    out, _ = bracket
    frames = sorted(str(p) for p in out.glob("frame_*.dng"))
    o = tmp_path / "x.exr"
    blob = open(frames[0], "rb").read()
    (tmp_path / "trunc.dng").write_bytes(blob[: len(blob) // 3])
    (tmp_path / "text.dng").write_text("not raw\n" * 100)
    from tests.helpers.dng import write_test_dng

    write_test_dng(tmp_path / "small.dng", np.ones((40, 40), np.uint16))
    from PIL import Image

    Image.fromarray(np.ones((48, 64), np.uint16)).save(tmp_path / "a.png")
    cases = {
        "no such file": ["merge", str(tmp_path / "missing.dng"), "--camera", "camera-B", "-o", o],
        "not a raw file": ["merge", str(tmp_path / "text.dng"), "--camera", "camera-B", "-o", o],
        "truncated": ["merge", str(tmp_path / "trunc.dng"), "--camera", "camera-B", "-o", o],
        "differs": ["merge", frames[0], str(tmp_path / "small.dng"), "--camera", "camera-B", "-o", o],
        "exposure time": ["merge", str(tmp_path / "a.png"), "--camera", "camera-B", "-o", o],
        "twice": ["merge", frames[0], frames[0], "--camera", "camera-B", "-o", o],
        "at least two frames": ["merge", frames[0], "-o", o],
        "unknown camera preset": ["merge", frames[0], "--camera", "camera-Z", "-o", o],
        "--times gives": ["merge", frames[0], "--times", "0.1", "0.2", "--camera", "camera-B", "-o", o],
        "no dark frame": [
            "merge",
            *frames,
            "--darks",
            str(out / "dark_000_0.002s.dng"),
            "--camera",
            "camera-B",
            "-o",
            o,
        ],
        "--size": ["simulate", "--size", "10x10", "--out", tmp_path / "s"],
    }
    for needle, args in cases.items():
        proc = cli(*args)
        assert proc.returncode != 0, needle
        _no_traceback(proc)
        assert needle in proc.stderr, (needle, proc.stderr)
    assert not o.exists()
    # duplicate frames under different names: same pixels
    (tmp_path / "copy.dng").write_bytes(blob)
    proc = cli("merge", frames[0], str(tmp_path / "copy.dng"), "--camera", "camera-B", "-o", o)
    _no_traceback(proc)
    assert "duplicate" in proc.stderr
    # inputs are never modified
    assert open(frames[0], "rb").read() == blob


def test_simulate_refuses_to_overwrite(bracket, cli):
    out, _ = bracket
    proc = cli("simulate", "--times", "0.002", "--out", out, "--size", "64x48")
    assert proc.returncode != 0 and "exists" in proc.stderr
    _no_traceback(proc)


def test_help_documents_every_command(cli):
    proc = cli("--help", check=True)
    for name in ("simulate", "merge", "demo"):
        assert name in proc.stdout
        sub = cli(name, "--help", check=True)
        assert "--help" in sub.stdout and "Usage" in sub.stdout


def test_demo_reports_error_against_truth(cli, tmp_path):
    proc = cli("demo", "--out", tmp_path / "d", "--size", "128x96", "--json", check=True)
    res = json.loads(proc.stdout)
    for name in ("demo.exr", "demo.png", "summary.txt"):
        assert (tmp_path / "d" / name).is_file()
    text = (tmp_path / "d" / "summary.txt").read_text()
    assert "error against the simulator's ground truth" in text
    from hdrcap.pipeline.io.exr import read_exr

    written = set(read_exr(tmp_path / "d" / "demo.exr").channels)
    listed = text.split("demo.exr (", 1)[1].split(")", 1)[0]
    assert {c.strip() for c in listed.split(";")[0].split(",")} == written  # the summary names what is there
    assert res["median_abs_relative_error"] < 0.2 and res["n_used"] > 0.9 * 128 * 96
    assert 0.7 < res["z_std"] < 2.0


def test_demo_text_output_has_no_progress_bar_off_a_terminal(cli, tmp_path):
    """`make demo` piped into a log: the summary only, no progress bar redrawn into the file."""
    proc = cli("demo", "--out", tmp_path / "d", "--size", "128x96", check=True)
    assert "error against the simulator's ground truth" in proc.stdout
    assert "frame/s" not in proc.stderr and "%|" not in proc.stderr, proc.stderr
    assert "warning" not in proc.stderr.lower(), proc.stderr  # the demo's own bracket is one the camera offers
