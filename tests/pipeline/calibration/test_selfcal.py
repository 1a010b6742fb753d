"""Merging without a calibration: the self-calibration from the bracket against the
simulator's truth, and its refusals."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS
from hdrcap.mock_camera.backend import SimulatedCamera
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.mock_camera.sensor import SensorSpec, SimulatedSensor
from hdrcap.pipeline.calibration.selfcal import SELF_CALIBRATED, self_calibrate
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.io.raw import RawFrame

REPO = Path(__file__).resolve().parents[3]
TIMES = (1 / 2000, 1 / 250, 1 / 30, 1 / 4, 2.0)
G14 = 0.4


def spec14(**changes) -> SensorSpec:
    """A 14-bit sensor (ADC clips before the full well), 1 % PRNU, 0.5 e-/s dark current."""
    spec = SensorSpec(
        name="sim-14bit",
        g=G14,
        mu_R=512.0,
        sigma2_R=9.0,
        bits=14,
        full_well=1.1 * (16383 - 512) / G14,
        iso=200,
        model="Simulated 14-bit",
    )
    return spec.replace(**changes) if changes else spec


def bracket(tmp_path: Path, spec: SensorSpec, shape, seed: int, times=TIMES, scene="hdr", decades=6.0):
    x_max = 0.8 * (spec.white_level - spec.mu_R) / (spec.g * min(times))
    X = make_scene(scene, shape, decades=decades, x_max=x_max)
    cam = SimulatedCamera(spec, X, seed=seed)
    files = [cam.capture_to(tmp_path / f"f{i}_{spec.iso}.dng", t) for i, t in enumerate(times)]
    return files, X, cam.sensor


def arrays(spec: SensorSpec, X, times, seed: int, **meta) -> list[RawFrame]:
    sensor = SimulatedSensor(spec, np.shape(X), seed=seed)
    return [
        RawFrame(
            sensor.expose(X, t),
            t,
            iso=meta.get("iso", 100),
            black_level=spec.mu_R,
            white_level=float(spec.white_level),
            cfa_pattern="RGGB",
            camera="sim",
        )
        for t in times
    ]


def test_merge_without_calibration_14bit_against_truth(tmp_path, cli):
    """Done-when figures: the gain within 5 % (and within 4 of its standard errors), the read
    noise within 10 %, and z = (x - a X) / sigma of spread 0.9-1.2 in every irradiance decade,
    a X being what each photosite receives (a bracket cannot tell PRNU from the scene)."""
    files, X, sensor = bracket(tmp_path, spec14(), (768, 1024), seed=5)
    out = tmp_path / "out.exr"
    proc = cli("merge", *files, "-o", out, check=True)
    assert "self-calibrated from the bracket" in proc.stderr
    img = read_exr(out)
    sc = img.header["self_calibration"]
    assert sc["source"] == SELF_CALIBRATED
    g, se = sc["gain"]["value"], sc["gain"]["stderr"]
    assert abs(g / G14 - 1) < 0.05 and abs(g - G14) < 4 * se
    assert abs(sc["read_noise_variance"]["value"] / 9.0 - 1) < 0.1
    assert img.header["unit"] == "electrons per second per photosite"
    np.testing.assert_allclose(sc["effective_exposure_times"], TIMES, rtol=2e-3)
    ch = img.channels
    ok = ch["nexp"] > 0
    assert ok.all() and (ch["sigma_calibration"] <= ch["sigma"]).all() and (ch["sigma_calibration"] > 0).all()
    z = (ch["irradiance"] - sensor.prnu * X) / ch["sigma"]
    for e in range(1, 8):
        sel = (X >= 10**e) & (X < 10 ** (e + 1))
        if sel.sum() > 1000:
            assert 0.9 <= np.std(z[sel]) <= 1.2, (e, np.std(z[sel]))
            assert abs(np.median(z[sel])) < 0.5, (e, np.median(z[sel]))


def test_self_calibrated_merge_applies_the_times_asked_for_once(tmp_path, cli):
    """The self-calibration's effective times are the ones merged (the merge does not estimate
    them a second time), and --exposure-times nominal merges the nominal times."""
    files, X, sensor = bracket(tmp_path, spec14(shutter_error=0.03), (192, 256), seed=3)
    eff = tmp_path / "eff.exr"
    cli("merge", *files, "-o", eff, check=True)
    img = read_exr(eff)
    sc = img.header["self_calibration"]
    assert sc["merged_with"] == "effective exposure times"
    assert img.header["exposure_times_effective"] == sc["effective_exposure_times"]
    assert max(abs(a / b - 1) for a, b in zip(sc["effective_exposure_times"], TIMES)) > 1e-3  # shutter errors seen
    nom = tmp_path / "nom.exr"
    cli("merge", *files, "-o", nom, "--exposure-times", "nominal", check=True)
    img = read_exr(nom)
    assert img.header["self_calibration"]["merged_with"] == "nominal exposure times"
    np.testing.assert_allclose(img.header["exposure_times_effective"], TIMES, rtol=1e-9)


def test_shutter_errors_give_effective_times(tmp_path):
    """Shutter errors of +-3 % per nominal time are found from the pairs: the estimated ratios
    match the true ones within 3 standard errors and 0.2 %."""
    spec = spec14(shutter_error=0.03)
    X = make_scene("hdr", (256, 384), decades=6.0, x_max=0.8 * 15871 / (G14 * TIMES[0]))
    frames = arrays(spec, X, TIMES, seed=2)
    sc = self_calibrate(frames)
    truth = SimulatedSensor(spec, X.shape, seed=2)
    true_t = np.array([t * truth.shutter_factor(t) for t in TIMES])
    for q in sc.pairs:
        r = true_t[q.long] / true_t[q.short]
        assert abs(q.ratio / r - 1) < 2e-3 and abs(q.ratio - r) < 3 * q.ratio_stderr + 1e-9
    eff = np.array(sc.effective_times)
    np.testing.assert_allclose(eff / eff[0], true_t / true_t[0], rtol=3e-3)
    assert np.exp(np.mean(np.log(eff))) == pytest.approx(np.exp(np.mean(np.log(TIMES))), rel=1e-9)


def test_full_well_saturation_found_below_white_level():
    """camera-A's full well clips below its 12-bit white level: v_sat is found from the
    pile-up within 3 sigma_R of the simulator's (mean - 3 std of a saturation frame)."""
    spec = PRESETS["camera-A"]
    p = spec.nominal_params()
    times = (0.002, 0.016, 0.128)
    X = make_scene("hdr", (192, 256), decades=4.0, x_max=0.8 * (p.v_sat - p.mu_R) / (p.g * times[0]))
    sc = self_calibrate(arrays(spec, X, times, seed=4))
    assert abs(sc.calibration.params.v_sat - p.v_sat) < 3 * np.sqrt(p.sigma2_R)
    assert any("pile up" in n for n in sc.notes)
    assert abs(sc.fit["g"] / p.g - 1) < 0.05


def test_no_overlap_is_refused_and_few_pairs_fall_back_to_dn_per_second():
    spec = spec14(prnu=0.0)
    # a flat scene that saturates the long frame everywhere: no photosite usable in both
    flat = np.full((64, 64), 0.9 * 15871 / (G14 * 0.01))
    with pytest.raises(InputError, match="no overlap between the exposures"):
        self_calibrate(arrays(spec, flat, (0.01, 1.0), seed=1))
    # a flat scene usable in both frames: one signal level, no photon-transfer slope
    flat = np.full((64, 64), 0.1 * 15871 / (G14 * 0.04))
    notes = []
    sc = self_calibrate(arrays(spec, flat, (0.01, 0.04), seed=1), warn=notes.append)
    assert not sc.gain_known and sc.calibration.params.g == 1.0 and sc.unit.startswith("DN per second")
    assert "sigma relative" in notes[-1] and "relative only" in sc.header()["sigma"]


@pytest.mark.parametrize("field,value", [("iso", 400), ("camera", "other"), ("cfa_pattern", "BGGR")])
def test_mixed_brackets_are_refused(field, value):
    spec = spec14()
    frames = arrays(spec, np.full((32, 32), 1e4), (0.01, 0.02), seed=1)
    frames[1] = RawFrame(**{**frames[1].__dict__, field: value})
    with pytest.raises(InputError, match="differs from"):
        self_calibrate(frames)
    with pytest.raises(InputError, match="at least two frames"):
        self_calibrate(frames[:1])


def test_cli_refuses_mixed_iso_in_one_line(tmp_path, cli):
    files, _, _ = bracket(tmp_path, spec14(), (32, 32), seed=1, times=(0.01, 0.02))
    other, _, _ = bracket(tmp_path, spec14(iso=800), (32, 32), seed=1, times=(0.04,))
    proc = cli("merge", *files, *other, "-o", tmp_path / "x.exr")
    assert proc.returncode != 0 and "ISO 800" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def _have_hdrmerge_and_codecs() -> bool:
    if shutil.which("hdrmerge") is None:
        return False
    try:
        import imagecodecs  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.skipif(not _have_hdrmerge_and_codecs(), reason="needs hdrmerge (apt-get) and imagecodecs (pip)")
def test_snr_at_least_hdrmerge_in_every_decade(tmp_path):
    """The benchmark side by side: hdrcap without a calibration against HDRMerge on the same
    DNGs, SNR per decade after a global scale fit (equal, to float rounding, in the top decade
    where both have only the shortest exposure)."""
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "bench_selfcal.py"), "--size", "512x384", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    diff = res["hdrcap_minus_hdrmerge_db"]
    assert len(diff) >= 5 and min(diff.values()) >= -0.05, diff
    assert abs(res["hdrcap (no calibration)"]["gain"]["relative_error"]) < 0.05


def test_frames_without_a_black_level_count_as_0_dn():
    """A bracket where one frame carries no black level (within the spread allowed of the others):
    that frame's level is taken as 0 DN (as the note says), and the levels' difference noted."""
    spec = spec14(prnu=0.0, mu_R=100.0)
    X = np.geomspace(10, 1e5, 64 * 64).reshape(64, 64)
    frames = arrays(spec, X, (0.01, 0.04, 0.16), seed=1)
    frames[1] = RawFrame(**{**frames[1].__dict__, "black_level": None})
    notes: list[str] = []
    self_calibrate(frames, warn=notes.append)
    assert any("black levels differ between frames (0, 100 DN)" in n for n in notes)
