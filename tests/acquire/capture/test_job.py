"""Jobs: validation before any frame (with the job file's line), `hdrcap run` end to end on the
mock camera (accuracy against the simulator's truth), resume after a kill, repeats, capture."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hdrcap.acquire.capture.job import JobError, job_from_dict, load_job
from hdrcap.pipeline.errors import InputError

GOOD = """\
[job]
name = "t"

[camera]
backend = "mock"
preset = "camera-B"
size = "64x48"
seed = 3

[scene]
name = "hdr"
decades = 3.0
x_max = 2e4

[exposure]
mode = "bracket"
times = [0.001, 0.004, 0.016, 0.064, 0.25, 1.0]

[darks]
strategy = "matched"
block_light = "mock"

[output]
folder = "runs/{job}-{date}"
"""


def _write(tmp_path, text, name="job.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_good_job_loads_with_defaults(tmp_path):
    job = load_job(_write(tmp_path, GOOD))
    assert job["camera"]["seed"] == 3 and job["session"]["max_attempts"] == 12
    assert job.where("exposure", "times") == f"{tmp_path / 'job.toml'}:17"


@pytest.mark.parametrize(
    "change, line, words",
    [
        (("seed = 3", "seed = 3\nshutter = 5"), 9, "unknown key"),
        (("[darks]", "[dark]"), 19, "unknown section"),
        (('strategy = "matched"', 'strategy = "best"'), 20, "matched, master or model"),
        (('size = "64x48"', "size = 64"), 7, "expected a string"),
        (('block_light = "mock"', 'block_light = "command"'), 19, "cover_command"),
        (("[output]", '[calibration]\nfile = "nope.json"\n\n[output]'), 24, "does not exist"),
        (('folder = "runs/{job}-{date}"', 'folder = "afile/runs"'), 24, "not a writable folder"),
        (('mode = "bracket"', 'mode = "snr"'), 15, "target_snr_db"),
        # frame counts no run takes: refused when read, never planned frame by frame (the fuzzer's
        # repeats = 8.4e17 made `run --check` build the plan until it ran out of time and memory)
        (('mode = "bracket"', 'mode = "bracket"\nrepeats = 841858151345640960'), 17, "more frames than a run takes"),
        (('mode = "bracket"', 'mode = "bracket"\nrepeats = 20000'), 17, "120000 light frames per run"),
        (('block_light = "mock"', 'block_light = "mock"\ncount = 200000'), 22, "more frames than a run takes"),
        (
            ("[output]", '[calibration]\nseries = [{kind = "bias", times = [0.001], count = 1000000}]\n\n[output]'),
            0,
            "1000000 frames, more than a run takes",
        ),
    ],
)
def test_bad_jobs_name_the_line(tmp_path, change, line, words):
    (tmp_path / "afile").write_text("x")
    p = _write(tmp_path, GOOD.replace(*change))
    with pytest.raises(InputError) as e:
        load_job(p)
    msg = str(e.value)
    assert words in msg and msg.startswith(f"{p}:"), msg
    if line:
        assert f"{p}:{line}:" in msg, msg


_SERIES_WITHOUT_KIND = ("[output]", "[calibration]\nseries = [{times = [0.001]}]\n\n[output]")


@pytest.mark.parametrize(
    "change, line, label, words",
    [
        # a wrong type
        (("seed = 3", "seed = true"), 8, "camera.seed", "expected an integer, got True"),
        (("x_max = 2e4", 'x_max = "2e4"'), 13, "scene.x_max", "expected a number, got '2e4'"),
        # a value out of range
        (("seed = 3", "seed = -1"), 8, "camera.seed", "must be >= 0, got -1"),
        (("decades = 3.0", "decades = inf"), 12, "scene.decades", "must be a finite number, got inf"),
        (("[0.001, 0.004,", "[0.001, -0.004,"), 17, "exposure.times", "item 2: must be > 0, got -0.004"),
        # an unknown key
        (("x_max = 2e4", "x_max = 2e4\nxmax = 1"), 14, "scene.xmax", "unknown key; known: decades, name, x_max"),
        # a missing required key (the table's line when the key is not in the file)
        (('mode = "bracket"', 'mode = "snr"'), 15, "exposure.target_snr_db", 'mode = "snr" needs target_snr_db'),
        (_SERIES_WITHOUT_KIND, 24, "calibration.series", "item 1: kind: required, not given"),
    ],
)
def test_schema_errors_are_one_line_with_the_keys_line(tmp_path, change, line, label, words):
    p = _write(tmp_path, GOOD.replace(*change))
    with pytest.raises(JobError) as e:
        load_job(p)
    assert str(e.value) == f"{p}:{line}: {label}: {words}"


def test_the_first_problem_in_the_file_is_reported(tmp_path):
    # [schedule] comes after [camera] in the schema but first in this file
    p = _write(tmp_path, "[schedule]\nrepeat = 0\n\n" + GOOD.replace("seed = 3", "seed = -1"))
    with pytest.raises(JobError) as e:
        load_job(p)
    assert str(e.value) == f"{p}:2: schedule.repeat: must be >= 1, got 0"
    p = _write(tmp_path, "stray = 1\n" + GOOD)  # a key before any table stands where a table would
    with pytest.raises(JobError, match=r"job.toml:1: \[stray\]: unknown section; known: job, camera"):
        load_job(p)


def test_the_schema_names_every_dark_strategy_in_order():
    from typing import get_args

    from hdrcap.acquire.capture.schema import DarkStrategyName
    from hdrcap.pipeline.dark_strategy import DarkStrategy

    assert get_args(DarkStrategyName) == tuple(s.value for s in DarkStrategy)


def test_a_table_not_given_keeps_its_rules(tmp_path):
    p = _write(tmp_path, "")  # no [exposure]: its default, a fixed bracket, still needs times
    with pytest.raises(JobError) as e:
        load_job(p)
    assert str(e.value) == f"{p}: exposure.times: a fixed bracket needs times = [...] (seconds)"


def test_a_job_given_as_a_dict_has_no_line():
    with pytest.raises(JobError) as e:
        job_from_dict({"camera": {"seed": -1}, "exposure": {"times": [0.01]}})
    assert str(e.value) == "<job>: camera.seed: must be >= 0, got -1"
    job = job_from_dict({"exposure": {"times": [0.01]}, "darks": {"count": 2}})
    assert job["darks"]["count"] == 2 and "iso" not in job["camera"] and job.spec.camera.iso is None
    assert job.spec.darks.model_fields_set == {"count"}


def test_toml_syntax_error_names_the_line(tmp_path):
    p = _write(tmp_path, GOOD.replace('preset = "camera-B"', "preset = camera-B"))
    with pytest.raises(InputError, match=r"line 6"):
        load_job(p)


def test_exposure_outside_camera_range_rejected_before_any_frame(tmp_path, cli):
    p = _write(tmp_path, GOOD.replace("1.0]", "1.0, 120.0]"))
    proc = cli("run", p)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert f"{p}:17: exposure.times: exposure 120 s is outside the camera's range" in proc.stderr
    assert not (tmp_path / "runs").exists()  # no frame, not even a run folder


def test_run_job_merge_within_stated_uncertainty(tmp_path, cli):
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.pipeline.io.exr import read_exr

    p = _write(tmp_path, GOOD)
    proc = cli("run", p, "--json", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["frames"] == 12 and res["captured"] == 12
    img = read_exr(res["exr"])
    truth = make_scene("hdr", (48, 64), decades=3.0, x_max=2e4)  # the simulator's scene, rebuilt independently
    irr, sig, nexp = (img.channels[k].astype(np.float64) for k in ("irradiance", "sigma", "nexp"))
    ok = nexp > 0
    assert ok.mean() > 0.99
    z = (irr[ok] - truth[ok]) / sig[ok]
    spread = 1.4826 * np.median(np.abs(z - np.median(z)))  # robust: the merge's tails do not dominate
    assert 0.8 < spread < 1.25, spread
    assert abs(np.median(z)) < 0.15
    assert np.isfinite(irr).all() and np.isfinite(sig).all()
    manifest = Path(res["run_dir"]) / "manifest.jsonl"
    recs = [json.loads(l) for l in manifest.read_text().splitlines()]
    assert recs[0]["type"] == "run" and recs[0]["job_name"] == "t"
    assert sum(r["type"] == "frame" for r in recs) == 12
    # the header lists the frames relative to the run folder and carries the first frame's colour
    # metadata, read from the file itself (the run is not started from its own folder)
    sources = img.header["source_files"]
    assert len(sources) == 6 and all((Path(res["run_dir"]) / f).is_file() for f in sources)
    assert len(img.header["camera_colour"]["color_matrix_1"]) == 9, img.header.get("camera_colour")
    developed = tmp_path / "rgb.exr"
    proc = cli("develop", res["exr"], "-o", developed, "--space", "linear-srgb")
    assert proc.returncode == 0 and developed.is_file(), proc.stderr


def test_run_killed_then_resumed_completes(tmp_path, cli):
    fast = "\n[session]\nbackoff_s = 0.001\n"
    text = GOOD.replace("seed = 3", "seed = 3\nfaults = { kill_after = 7, busy_rate = 0.2, seed = 1 }") + fast
    p = _write(tmp_path, text)
    first = cli("run", p, "--no-progress")
    assert first.returncode == 137 and "Traceback" not in first.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert not (run_dir / "hdr.exr").exists()
    _write(tmp_path, GOOD.replace("seed = 3", "seed = 3\nfaults = { busy_rate = 0.2, seed = 2 }") + fast)
    second = cli("run", p, "--resume", "--json", "--no-progress")
    assert second.returncode == 0, second.stderr
    res = json.loads(second.stdout.strip().splitlines()[-1])
    assert res["run_dir"] == str(run_dir)
    assert res["resumed"] == 6 and res["captured"] == 6 and res["frames"] == 12
    recs = [json.loads(l) for l in (run_dir / "manifest.jsonl").read_text().splitlines()]
    keys = [r["key"] for r in recs if r["type"] == "frame"]
    assert len(keys) == len(set(keys)) == 12
    assert (run_dir / "hdr.exr").exists()


def test_repeat_every_makes_separate_runs(tmp_path, cli):
    p = _write(
        tmp_path,
        GOOD.replace('folder = "runs/{job}-{date}"', 'folder = "runs/{job}-{n:02d}"').replace(
            "[0.001, 0.004, 0.016, 0.064, 0.25, 1.0]", "[0.004, 0.064]"
        ),
    )
    proc = cli("run", p, "--repeat", "2", "--every", "0.5", "--json", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    runs = [json.loads(l) for l in proc.stdout.strip().splitlines()]
    assert [Path(r["run_dir"]).name for r in runs] == ["t-00", "t-01"]
    # the two repetitions are independent captures (different noise)
    a, b = (
        [
            json.loads(line)
            for line in (Path(r["run_dir"]) / "manifest.jsonl").read_text().splitlines()
            if '"type":"frame"' in line
        ][-1]["sha256"]
        for r in runs
    )
    assert a != b
    again = cli("run", p, "--no-progress")
    assert again.returncode == 5 and "--resume" in again.stderr and "Traceback" not in again.stderr


def test_capture_command_plans_for_a_target_snr(tmp_path, cli):
    proc = cli(
        "capture",
        "--camera",
        "mock:camera-A",
        "--size",
        "48x32",
        "--target-snr",
        "20",
        "--times",
        "0.01",
        "0.1",
        "--out",
        tmp_path / "cap",
        "--no-progress",
        "--json",
    )
    assert proc.returncode == 0, proc.stderr
    assert "plan:" in proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert Path(res["exr"]).exists() and res["frames"] >= 2


def test_capture_rejects_bad_camera_and_cameras_lists(tmp_path, cli):
    proc = cli("capture", "--camera", "nikon", "--times", "0.01", "--out", tmp_path / "x")
    assert proc.returncode != 0 and "hdrcap: error: camera must be mock:PRESET" in proc.stderr
    proc = cli("cameras", "--json")
    assert proc.returncode == 0
    out = json.loads(proc.stdout)
    assert {m["preset"] for m in out["mock"]} == {"camera-A", "camera-B", "camera-R"}


def test_master_darks_come_from_the_dark_library(tmp_path, cli):
    from hdrcap.acquire.camera.mock import MockCamera
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.pipeline.calibration import darklibrary
    from hdrcap.pipeline.io.raw import read_frame

    lib = darklibrary.DarkLibrary(tmp_path / "darks")
    cam = MockCamera("camera-B", make_scene("hdr", (48, 64), decades=3.0, x_max=2e4), seed=3)
    cam.cover()
    for t in (0.001, 0.004):
        cam.set_exposure(t)
        stack = [read_frame(cam.capture(tmp_path / f"d{t:g}_{k}.dng").path).data for k in range(6)]
        lib.add(np.mean(stack, axis=0), 6, camera=cam.identity.model, iso=None, exposure_time=t)
    text = GOOD.replace('strategy = "matched"', 'strategy = "master"\ncount = 2').replace(
        "[output]", '[calibration]\npreset = "camera-B"\ndark_library = "darks"\n\n[output]'
    )
    p = _write(tmp_path, text)
    proc = cli("run", p, "--json", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    recs = [json.loads(l) for l in (Path(res["run_dir"]) / "manifest.jsonl").read_text().splitlines()]
    dark_times = sorted({r["file_exposure_s"] for r in recs if r.get("kind") == "dark"})
    assert 0.001 not in dark_times and 0.004 not in dark_times and len(dark_times) == 4
    assert recs[0]["plan"]["library_times"] == [0.001, 0.004]


def test_run_honours_a_mixed_plan_and_records_the_decisions(tmp_path, monkeypatch):
    """A plan mixing "model" and "matched": dark frames only for the matched times, each light
    frame merged with its own strategy and the planner's merge options, the decisions in the
    EXR header, and the result within its stated uncertainty of the truth."""
    from hdrcap import planner
    from hdrcap.acquire.capture.run import run_job
    from hdrcap.mock_camera import PRESETS
    from hdrcap.mock_camera.scenes import make_scene
    from hdrcap.mock_camera.sensor import SimulatedSensor
    from hdrcap.pipeline.calibration import save_calibration
    from hdrcap.pipeline.io.exr import read_exr
    from hdrcap.pipeline.params import Calibration
    from hdrcap.planner.plan import Plan

    # a calibration that knows the mock camera's fixed patterns (seed 3), so z measures the merge alone
    sensor = SimulatedSensor(PRESETS["camera-B"], (48, 64), seed=3)
    save_calibration(
        tmp_path / "cal.npz",
        Calibration(
            params=PRESETS["camera-B"].nominal_params(),
            prnu=sensor.prnu.astype(np.float32),
            dark_current_map=sensor.dark_current_map().astype(np.float32),
            provenance={"source": "simulator truth"},
        ),
    )
    times = [1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0]  # from the camera's ladder, as the planner's
    darks = ["model", "matched", "model", "matched", "model", "matched"]
    decisions = {
        "saturation": {"choice": "probabilistic", "reason": "test", "figure": 0.2},
        "prnu": {"choice": "map", "reason": "test", "figure": 0.4},
        "iterations": {"choice": 5, "reason": "test", "figure": 0.01},
    }
    fake = Plan(times, darks, 22.0, 3.0, decisions, True, "a test plan", 20.0, 1.0, [0] * 6, {})
    lit = planner.MeterReport([0.000125, 1.0], 48 * 64, 0, None, 0, None, 0, None)  # no photosite dark

    def meter(*a, return_report=False, **k):
        return (np.ones((48, 64)), lit) if return_report else np.ones((48, 64))

    monkeypatch.setattr(planner, "meter", meter)
    monkeypatch.setattr(planner, "plan_exposures", lambda *a, **k: fake)
    text = (
        GOOD.replace('mode = "bracket"', 'mode = "snr"\ntarget_snr_db = 20.0')
        .replace('strategy = "matched"\n', "")
        .replace("[output]", '[calibration]\nfile = "cal.npz"\n\n[output]')
    )
    summary, res = run_job(
        load_job(_write(tmp_path, text)),
        run_dir=tmp_path / "run",
        progress=False,
        echo=lambda s: None,
        return_result=True,
    )
    dark_times = sorted(r["file_exposure_s"] for r in res.frames.values() if r["kind"] == "dark")
    assert dark_times == pytest.approx([1 / 250, 1 / 15, 1.0], rel=1e-3)
    img = read_exr(summary["exr"])
    m, p = img.header["merge"], img.header["planner"]
    assert m["dark_strategies"] == darks and m["iterations"] == 5 and m["saturation"] == "probabilistic"
    assert p["decisions"] == decisions and p["predicted_min_snr_db"] == 22.0
    assert p["options_from_plan"] == {
        "saturation": "probabilistic",
        "prnu": "map",
        "iterations": 5,
        "saturation_sigmas": 3.0,
    }
    truth = make_scene("hdr", (48, 64), decades=3.0, x_max=2e4)
    ok = img.channels["nexp"] > 0
    z = (img.channels["irradiance"][ok] - truth[ok]) / img.channels["sigma"][ok]
    assert ok.mean() > 0.99 and 0.9 < z.std() < 1.1 and abs(z.mean()) < 0.1, (z.std(), z.mean())
