"""`hdrcap plan`: JSON contract, plot, explanations and user errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrcap.cli import main
from hdrcap.mock_camera import PRESETS
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.io.exr import read_exr, write_exr
from hdrcap.pipeline.params import THIRD_STOP_TIMES


def _run(capsys, *args):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def scene_exr(tmp_path):
    X = make_scene("hdr", (48, 64), decades=3, x_max=5e4).astype(np.float32)
    path = tmp_path / "truth.exr"
    write_exr(path, {"irradiance": X}, {"unit": "e-/s"})
    return path


def test_plan_json_contract_from_irradiance_map(capsys, scene_exr):
    code, out, _ = _run(
        capsys,
        "plan",
        "--camera",
        "camera-B",
        "--irradiance",
        scene_exr,
        "--target-snr-db",
        20,
        "--overhead",
        0.1,
        "--json",
    )
    assert code == 0
    d = json.loads(out)
    for key in ("exposures", "darks", "predicted_min_snr_db", "total_time_s", "decisions", "feasible"):
        assert key in d
    assert d["feasible"] and d["predicted_min_snr_db"] >= 20 - 1e-6
    assert len(d["darks"]) == len(d["exposures"]) >= 2
    assert d["total_time_s"] >= sum(d["exposures"]) + 0.1 * len(d["exposures"])
    for name in ("dark_strategy", "prnu", "saturation", "iterations", "first_exposure"):
        assert {"choice", "reason", "figure"} <= set(d["decisions"][name])
    # what `hdrcap merge --plan` reads: per-exposure darks and n_dark, and the merge options
    assert len(d["n_dark"]) == len(d["exposures"])
    assert all(n == {"model": 0, "matched": 1}[k] for k, n in zip(d["darks"], d["n_dark"]))
    opts = d["merge_options"]
    assert opts["saturation_sigmas"] == 3.0 and opts["prnu"] in ("map", "scalar")
    assert opts["saturation"] in ("threshold", "probabilistic") and opts["iterations"] >= 1
    assert d["overhead_s"] == 0.1
    # the first exposure is the longest ladder time that clips at most 5 % of the scene
    # (simulator parameters; 3 sigma margin), and it is listed first
    spec = PRESETS["camera-B"]
    x = read_exr(scene_exr).channels["irradiance"].astype(np.float64).ravel()

    def clips(t):
        e = t * (x + spec.dark_current)
        return spec.mu_R + spec.g * e + 3 * np.sqrt(spec.g**2 * e + spec.sigma2_R) >= spec.nominal_params().v_sat

    t_bulk = max(t for t in THIRD_STOP_TIMES if np.mean(clips(t)) <= 0.05)  # no pixel clips at 1/8000 s here
    assert d["exposures"][0] == pytest.approx(t_bulk, rel=1e-9)


def test_plan_allowed_times_budget_and_infeasible(capsys, scene_exr):
    code, out, _ = _run(
        capsys,
        "plan",
        "--camera",
        "camera-B",
        "--irradiance",
        scene_exr,
        "--target-snr-db",
        30,
        "--allowed-times",
        "1/1000",
        "1/100",
        "1/10",
        "--time-budget",
        0.5,
        "--json",
    )
    assert code == 0
    d = json.loads(out)
    assert not d["feasible"] and "INFEASIBLE" in d["message"]
    assert set(d["exposures"]) <= {0.001, 0.01, 0.1} and d["total_time_s"] <= 0.5 + 1e-9


def test_plan_meter_explain_and_plot(capsys, tmp_path):
    png = tmp_path / "plan.png"
    code, out, _ = _run(
        capsys,
        "plan",
        "--camera",
        "camera-B",
        "--meter",
        "--scene",
        "gradient",
        "--size",
        "64x32",
        "--decades",
        2,
        "--x-max",
        2e4,
        "--target-snr-db",
        18,
        "--explain",
        "--plot",
        png,
    )
    assert code == 0
    assert "metered with" in out and "decisions:" in out and "dark_strategy" in out
    assert png.stat().st_size > 10000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, _, err = _run(
        capsys, "plan", "--camera", "camera-B", "--meter", "--size", "64x32", "--target-snr-db", 18, "--plot", png
    )
    assert code != 0 and "exists" in err


@pytest.mark.parametrize(
    "args,msg",
    [
        (["--camera", "camera-B", "--target-snr-db", 20], "exactly one scene source"),
        (["--camera", "camera-B", "--meter", "--target-snr-db", 20, "--allowed-times", "0"], "--allowed-times"),
        (["--meter", "--calibration", "nope.toml", "--target-snr-db", 20], "calibration"),
        (["--camera", "camera-B", "--irradiance", "missing.exr", "--target-snr-db", 20], "missing.exr"),
        (["--camera", "camera-B", "--meter", "--target-snr-db", 20, "--dark-library", "1/8"], "--dark-library"),
    ],
)
def test_plan_user_errors_are_one_line(capsys, args, msg):
    code, _, err = _run(capsys, "plan", *args)
    assert code != 0 and msg in err and "Traceback" not in err and err.startswith("hdrcap: error:")


def test_plan_subprocess_json(cli, scene_exr):
    proc = cli("plan", "--camera", "camera-A", "--irradiance", scene_exr, "--target-snr-db", 15, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["feasible"]
