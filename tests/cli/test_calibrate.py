"""`hdrcap calibrate` end to end: simulated calibration set (DNG) and the real EMVA 1288 set."""

from __future__ import annotations

import json
import time

import pytest

from hdrcap.cli import main

# Published EMVA 1288 reference-implementation results for reference set 001 (Basler CCD,
# 12 bit): the example results file of EMVA1288/emva1288, doc/datasets/datasets_results.rst
# ("Results Comparison"), whose u_p_sat = 30957 photons and index_u_ysat = 36 identify it
# as set 001 (its 37th step, 10.30 ms, has 30957 photons in EMVA1288_Data.txt).
EMVA_REF001 = {
    "K": 0.280769280926,  # DN/e-
    "sigma_y_dark": 3.07341849276,  # DN
    "sigma_d": 10.8980275235,  # e-
    "PRNU1288": 0.432704411062,  # %
    "DSNU1288": 0.551787767644,  # e-
    "u_I_mean": 28.4074312749,  # e-/s
    "R": 0.126726922819,  # DN/photon
    "index_u_ysat": 36,
    "index_sensitivity_max": 25,
}


@pytest.fixture(scope="module")
def calibration_set(tmp_path_factory):
    out = tmp_path_factory.mktemp("calset")
    assert (
        main(
            [
                "simulate",
                "--calibration-set",
                "--camera",
                "camera-B",
                "--size",
                "96x96",
                "--seed",
                "5",
                "--out",
                str(out),
                "--json",
            ]
        )
        == 0
    )
    return out, json.loads((out / "calibration_set.json").read_text())


def test_simulate_then_calibrate(calibration_set, tmp_path, capsys):
    out, desc = calibration_set
    files = desc["files"]
    assert [len(files[k]) for k in ("bias", "saturation", "flat", "dark")] == [2, 1, 36 + 24, 12]
    capsys.readouterr()
    cal_path = tmp_path / "cam-B.cal"
    args = [
        "calibrate",
        "--bias",
        *files["bias"],
        "--saturation",
        *files["saturation"],
        "--flat",
        *files["flat"],
        "--dark",
        *files["dark"],
        "-o",
        str(cal_path),
        "--json",
        "--report",
        str(tmp_path / "rep"),
        "--dark-library",
        str(tmp_path / "lib"),
        "--temperature",
        "20",
    ]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("g", "g_stderr", "mu_R", "sigma2_R", "v_sat", "prnu_std", "dark_current", "n_frames"):
        assert key in summary and summary[key] is not None
    truth = desc["true_params"]
    assert summary["n_frames"] == 75
    assert summary["g"] == pytest.approx(truth["g"], rel=0.03)
    assert abs(summary["g"] - truth["g"]) < 4 * summary["g_stderr"]
    assert abs(summary["mu_R"] - truth["mu_R"]) < 0.2
    assert summary["sigma2_R"] == pytest.approx(truth["sigma2_R"], rel=0.1)
    assert summary["v_sat"] == pytest.approx(truth["v_sat"], rel=0.01)
    assert "photon-transfer" in summary["gain_method"]
    assert {p.split("/")[-1] for p in summary["report"]} == {
        "ptc.png",
        "prnu_hist.png",
        "prnu_map.png",
        "dark_current.png",
        "defects.png",
    }
    index = json.loads((tmp_path / "lib" / "index.json").read_text())
    assert sorted(e["exposure_time"] for e in index["entries"]) == [0.5, 1, 2, 4, 8, 16]
    assert all(e["n_frames"] == 2 and e["temperature"] == 20 for e in index["entries"])
    # the file loads, and is not overwritten without --force
    from hdrcap.pipeline.calibration import load_calibration

    cal = load_calibration(cal_path)
    assert cal.prnu.shape == (96, 96) and cal.params.g == pytest.approx(summary["g"])
    assert cal.provenance["iso"] == 400 and "Simulated camera-B" in cal.provenance["camera"]
    assert main(args) == 3
    assert "exists; use --force" in capsys.readouterr().err


def test_cli_errors_are_one_line(calibration_set, tmp_path, cli):
    out, desc = calibration_set
    f = desc["files"]
    proc = cli(
        "calibrate",
        "--bias",
        f["bias"][0],
        "--flat",
        *f["flat"][:4],
        "--saturation",
        out / "missing.dng",
        "-o",
        tmp_path / "x.npz",
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("hdrcap: error:") and "missing.dng" in proc.stderr
    proc = cli(
        "calibrate",
        "--bias",
        *f["bias"],
        "--flat",
        f["saturation"][0],
        f["flat"][0],
        "--saturation",
        f["saturation"][0],
        "-o",
        tmp_path / "y.npz",
    )
    assert proc.returncode != 0 and "saturation_002" in proc.stderr and "saturated" in proc.stderr
    assert not (tmp_path / "y.npz").exists()


def test_emva_reference_set_001(emva_dir, tmp_path, capsys):
    start = time.perf_counter()
    out = tmp_path / "emva.npz"
    assert main(["calibrate", "--emva", str(emva_dir / "EMVA1288_Data.txt"), "-o", str(out), "--json"]) == 0
    elapsed = time.perf_counter() - start
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    e = s["emva1288"]
    assert s["g"] == pytest.approx(EMVA_REF001["K"], rel=0.03)
    assert e["sigma_y_dark"] == pytest.approx(EMVA_REF001["sigma_y_dark"], rel=0.02)
    assert e["sigma_d"] == pytest.approx(EMVA_REF001["sigma_d"], rel=0.03)
    assert e["PRNU1288"] == pytest.approx(EMVA_REF001["PRNU1288"], rel=0.05)
    assert e["DSNU1288"] == pytest.approx(EMVA_REF001["DSNU1288"], rel=0.05)
    assert e["u_I_mean"] == pytest.approx(EMVA_REF001["u_I_mean"], rel=0.1)
    assert e["R"] == pytest.approx(EMVA_REF001["R"], rel=0.01)
    assert e["index_u_ysat"] == EMVA_REF001["index_u_ysat"]
    assert e["index_sensitivity_max"] == EMVA_REF001["index_sensitivity_max"]
    assert s["prnu_std"] == pytest.approx(EMVA_REF001["PRNU1288"] / 100, rel=0.05)
    assert elapsed < 60  # seconds, not minutes (about 5 s on one core)
    from hdrcap.pipeline.calibration import load_calibration

    cal = load_calibration(out)
    assert cal.prnu.shape == (480, 640) and abs(float(cal.prnu.mean()) - 1) < 1e-5
    assert cal.params.sigma2_R == pytest.approx(EMVA_REF001["sigma_y_dark"] ** 2, rel=0.04)
