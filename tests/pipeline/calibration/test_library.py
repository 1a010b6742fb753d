"""The calibration library: calibrate once (--save-to-library), merge without --calibration."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrcap.pipeline.calibration.library import entry_name, library_dir, model_slug
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr


def test_keys_and_folder(monkeypatch, tmp_path):
    assert model_slug("Canon EOS 5D  Mark II") == "canon-eos-5d-mark-ii"
    assert entry_name("Canon EOS 5D", None, 400) == "canon-eos-5d__any__iso400.cal"
    assert entry_name("Canon EOS 5D", "SN 12", 100.0) == "canon-eos-5d__sn-12__iso100.cal"
    with pytest.raises(InputError, match="camera model"):
        entry_name("  ", None, 100)
    monkeypatch.setenv("HDRCAP_DATA_DIR", str(tmp_path / "d"))
    assert library_dir() == tmp_path / "d" / "calibrations"
    monkeypatch.delenv("HDRCAP_DATA_DIR")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "x"))
    assert library_dir() == tmp_path / "x" / "hdrcap" / "calibrations"


def test_calibrate_once_then_merge_finds_it(tmp_path, cli):
    env = {"HDRCAP_DATA_DIR": str(tmp_path / "data")}
    cal = tmp_path / "calset"
    cli(
        "simulate",
        "--calibration-set",
        "--camera",
        "camera-B",
        "--size",
        "64x48",
        "--seed",
        "5",
        "--out",
        cal,
        "--json",
        check=True,
        env=env,
    )
    files = json.loads((cal / "calibration_set.json").read_text())["files"]
    cli(
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
        tmp_path / "b.cal",
        "--save-to-library",
        "--json",
        check=True,
        env=env,
    )
    listed = json.loads(cli("calibrations", "list", "--json", check=True, env=env).stdout)
    assert len(listed["entries"]) == 1
    name = listed["entries"][0]["name"]
    assert name.endswith("__iso400.cal") and listed["entries"][0]["model"].startswith("hdrcap-simulated-camera-b")
    shown = json.loads(cli("calibrations", "show", name, "--json", check=True, env=env).stdout)
    assert shown["params"]["g"] == pytest.approx(0.92, rel=0.05) and "prnu" in shown["maps"]
    # a bracket of the same camera, ISO and size: the library's calibration is used
    sim = tmp_path / "sim"
    cli("simulate", "--camera", "camera-B", "--out", sim, "--size", "64x48", "--seed", "5", check=True, env=env)
    frames = sorted(sim.glob("frame_*.dng"))
    proc = cli("merge", *frames, "-o", tmp_path / "m.exr", check=True, env=env)
    assert "from the calibration library" in proc.stderr and name in proc.stderr
    img = read_exr(tmp_path / "m.exr")
    assert img.header["self_calibration"] is None and img.header["calibration"]["params"]["g"] == shown["params"]["g"]
    truth = read_exr(sim / "truth.exr").channels["irradiance"]
    ok = img.channels["nexp"] > 0
    assert abs(np.median((img.channels["irradiance"][ok] - truth[ok]) / img.channels["sigma"][ok])) < 0.5
    # another size: not this calibration (its maps do not fit): self-calibrated instead
    other = tmp_path / "other"
    cli("simulate", "--camera", "camera-B", "--out", other, "--size", "96x64", "--seed", "6", check=True, env=env)
    proc = cli("merge", *sorted(other.glob("frame_*.dng")), "-o", tmp_path / "o.exr", check=True, env=env)
    assert "self-calibrated from the bracket" in proc.stderr and "none in the library" in proc.stderr
    # remove, then gone
    cli("calibrations", "remove", name, check=True, env=env)
    assert json.loads(cli("calibrations", "list", "--json", check=True, env=env).stdout)["entries"] == []
    proc = cli("calibrations", "remove", name, env=env)
    assert proc.returncode != 0 and "no such calibration" in proc.stderr and "Traceback" not in proc.stderr


def test_entries_match_by_the_shared_model_rule(monkeypatch, tmp_path):
    """An entry stored under libgphoto2's name serves frames whose EXIF spells the model its own
    way, and a different model (D7500) is not served."""
    from hdrcap.pipeline.calibration.library import find_calibration, store_calibration
    from hdrcap.pipeline.params import Calibration, SensorParams

    monkeypatch.setenv("HDRCAP_DATA_DIR", str(tmp_path / "lib"))
    cal = Calibration(params=SensorParams(g=0.5, mu_R=64.0, sigma2_R=4.0, v_sat=4000.0, white_level=4095.0))
    store_calibration(cal, camera="Nikon DSC D750", iso=400)
    found = find_calibration("NIKON CORPORATION NIKON D750", 400, (100, 150))
    assert found is not None and found[1].params == cal.params
    assert find_calibration("NIKON CORPORATION NIKON D7500", 400, (100, 150)) is None
    assert find_calibration("NIKON CORPORATION NIKON D750", 800, (100, 150)) is None
