"""Defective photosites never give a confident wrong number: on camera-R with a calibration
estimated from simulated frames, every photosite of the calibration's defect map gets nexp = 0,
sigma = 0 and its defect bits in the quality channel (plus 16 where saturated everywhere); the
EXR carries the channel; the denoiser never uses them. Checked against the simulator's truth."""

import numpy as np
import pytest

import hdrcap
from hdrcap.experiments.calibrated import bracket, calibrated_sensor
from hdrcap.mock_camera import preset
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.denoise.filter import DenoiseSettings, denoise
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.params import DEFECT_BITS
from hdrcap.pipeline.result import summarise as summary
from hdrcap.pipeline.schema import QUALITY_BITS

SHAPE = (128, 128)
TIMES = (0.004, 0.03, 0.25, 2.0)


@pytest.fixture(scope="module")
def merged():
    # more stuck photosites than the preset's 0.01 % to have some in a small frame; exact shutter
    # times (the effective exposure times are tested in tests/pipeline/test_exposure_ratio.py)
    spec = preset("camera-R", stuck_fraction=1e-3, shutter_error=0.0, shutter_jitter=0.0)
    sensor, cal = calibrated_sensor(spec, seed=8, shape=SHAPE)
    X = make_scene("gradient", SHAPE, decades=3.0, x_max=2e5)
    frames, darks = bracket(sensor, X, TIMES, seed=8)
    res = hdrcap.merge(frames, calibration=cal, darks=darks)
    return sensor, cal, X, frames, res


def test_every_defect_of_the_calibration_is_flagged_not_measured(merged):
    sensor, cal, X, _frames, res = merged
    dm = cal.defect_map
    assert dm is not None and np.count_nonzero(dm) > 20
    defect = dm != 0
    assert np.all(res.nexp[defect] == 0) and np.all(res.sigma[defect] == 0)
    q = res.quality
    assert q.dtype == np.uint8 and q.shape == SHAPE
    np.testing.assert_array_equal(q & 15, dm)  # the calibration's bits, unchanged
    assert res.info["defects_flagged"] == int(defect.sum())
    # the merge's own flag: saturated everywhere, set exactly where a normal photosite has nexp = 0
    sat = (q & QUALITY_BITS["saturated"]) != 0
    np.testing.assert_array_equal(sat & ~defect, (res.nexp == 0) & ~defect)
    # against the truth: the simulator's dead, hot and stuck photosites are all flagged
    for kind in ("dead", "hot", "stuck"):
        true = sensor.defects[kind]
        assert true.sum() > 0
        assert np.all(q[true] & DEFECT_BITS[kind] | (q[true] & 15 != 0)), kind
        assert np.all(res.nexp[true] == 0), kind


def test_no_confident_wrong_number(merged):
    """Every photosite with nexp > 0 agrees with the truth within 6 sigma (a wrong defect would
    be far outside: a stuck photosite writes a constant, a dead one nothing)."""
    sensor, _cal, X, _frames, res = merged
    used = res.nexp > 0
    truth = X  # the scene's irradiance; PRNU is in the calibration's map
    z = (res.irradiance[used] - truth[used]) / res.sigma[used]
    assert np.mean(np.abs(z) > 6) < 1e-3, float(np.mean(np.abs(z) > 6))
    assert np.std(z) < 1.1, float(np.std(z))


def test_quality_channel_in_the_exr_and_the_denoiser_skips_it(merged, tmp_path):
    _sensor, cal, X, frames, res = merged
    path = res.write(tmp_path / "m.exr")
    img = read_exr(path)
    np.testing.assert_array_equal(img.channels["quality"], res.quality.astype(np.float32))
    assert "16 saturated" in img.header["quality"] and "1 dead" in img.header["quality"]
    s = summary(res)
    assert s["defects_flagged"] == res.info["defects_flagged"]
    # the denoiser leaves the flagged photosites alone and never averages them in
    ch = img.channels
    out = denoise(ch["irradiance"], ch["sigma"], ch["nexp"], DenoiseSettings(layout="cfa"), quality=ch["quality"])
    flagged = ch["quality"] != 0
    np.testing.assert_array_equal(out.irradiance[flagged], ch["irradiance"][flagged])
    # a neighbour of a defect is as close to the truth as the other photosites
    ok = ~flagged
    rel = np.abs(out.irradiance[ok] - X[ok]) / X[ok]
    assert np.percentile(rel, 99.9) < 0.2
