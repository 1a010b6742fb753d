"""EMVA 1288 data sets of every kind, written from the simulator and analysed against its truth.

Varying exposure time, varying irradiance at a constant exposure time or both; 8 to 16 bits;
PNG, TIFF and PGM images; Windows and POSIX paths in the descriptor; a quantisation-limited
8-bit CMOS; and the real reference set 001 against its published results.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrcap.mock_camera import PRESETS, SimulatedSensor
from hdrcap.mock_camera.emva_sets import EmvaSetSpec, write_emva_set, write_pgm
from hdrcap.mock_camera.sensor import SensorSpec
from hdrcap.pipeline.calibration.emva import QUANTISATION_LIMIT, QUANTISATION_VARIANCE, calibrate_descriptor, emva_data
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.emva_descriptor import read_emva_descriptor

#: An 8-bit CMOS whose read noise (0.1 DN^2 with the rounding) is below one DN: the dark
#: variance is quantisation-limited and the dark signal of its short exposures far below 1 DN.
CMOS8 = SensorSpec(
    name="cmos8",
    g=0.05,
    mu_R=10.0,
    sigma2_R=0.1,
    bits=8,
    full_well=4500.0,
    dark_current=5.0,
    prnu=0.01,
    width=96,
    height=96,
)
SIXTEEN = PRESETS["camera-A"].replace(bits=16, g=2.0, full_well=30000.0, mu_R=500.0)

CASES = {
    "12-bit, time, PNG, POSIX": (PRESETS["camera-A"], EmvaSetSpec()),
    "10-bit, irradiance, PGM, Windows": (
        PRESETS["camera-B"],
        EmvaSetSpec(mode="irradiance", image_format="pgm", windows_paths=True),
    ),
    "12-bit, both, TIFF, stacks": (PRESETS["camera-A"], EmvaSetSpec(mode="both", image_format="tif", stack=8)),
    "8-bit CMOS, time, PNG, Windows": (CMOS8, EmvaSetSpec(n_steps=20, exposure_time=0.05, windows_paths=True)),
    "8-bit CMOS, irradiance, PGM": (CMOS8, EmvaSetSpec(mode="irradiance", image_format="pgm")),
    "16-bit, time, TIFF": (SIXTEEN, EmvaSetSpec(image_format="tif")),
}


@pytest.mark.parametrize("case", list(CASES))
def test_every_kind_of_data_set_gives_the_true_gain(case, tmp_path):
    spec, kind = CASES[case]
    sensor = SimulatedSensor(spec, (96, 96), seed=1)
    desc = write_emva_set(sensor, tmp_path / "set", kind, seed=1)
    cal, res = calibrate_descriptor(desc)
    assert res.K == pytest.approx(spec.g, rel=0.03)
    assert abs(res.K - spec.g) < 4 * res.K_stderr
    assert cal.params.g == res.K and cal.params.white_level == 2**spec.bits - 1
    assert res.QE == pytest.approx(100.0, rel=0.05)  # the simulator's photons are electrons
    d = res.to_dict()
    json.dumps(d, allow_nan=False)  # no NaN in the summary: unsupported numbers are null with a reason
    # dark current: never negative, never a number the data cannot support
    if kind.mode != "time" or spec is CMOS8:
        assert d["u_I_mean"] is None and d["notes"]["dark_current"]
        assert cal.params.dark_current == 0 and cal.dark_current_map is None
        assert (
            "dark_current" in cal.provenance["calibration"]["dark_current_note"]
            or "D = 0" in (cal.provenance["calibration"]["dark_current_note"])
        )
    assert d["u_I_mean"] is None or d["u_I_mean"] > 0


def test_quantisation_limited_dark_noise_follows_the_standard(tmp_path):
    sensor = SimulatedSensor(CMOS8, (96, 96), seed=2)
    desc = write_emva_set(sensor, tmp_path / "cmos8", EmvaSetSpec(n_steps=20, exposure_time=0.05), seed=2)
    data = emva_data(read_emva_descriptor(desc))
    assert float(data.dark_s2[0]) < QUANTISATION_LIMIT  # the set is what it claims
    cal, res = calibrate_descriptor(desc)
    assert res.quantisation_limited
    assert res.sigma_y_dark == pytest.approx(np.sqrt(QUANTISATION_LIMIT))  # 0.49 DN, the rule's value
    assert "0.24" in res.notes["sigma_y_dark"] and "upper limit" in res.notes["sigma_y_dark"]
    true_sigma_d = np.sqrt(CMOS8.sigma2_R - QUANTISATION_VARIANCE) / CMOS8.g
    assert res.sigma_d > true_sigma_d  # an upper limit holds
    assert np.isnan(res.u_I_mean) and "quantisation-limited" in res.notes["dark_current"]
    assert cal.params.sigma2_R == pytest.approx(QUANTISATION_LIMIT)


def test_dark_current_reported_when_the_series_supports_it(tmp_path):
    spec = PRESETS["camera-A"].replace(dark_current=300.0)
    sensor = SimulatedSensor(spec, (96, 96), seed=3)
    desc = write_emva_set(sensor, tmp_path / "dark", EmvaSetSpec(exposure_time=0.5), seed=3)
    cal, res = calibrate_descriptor(desc)
    truth = float(sensor.dark_current_map().mean())
    assert res.u_I_mean == pytest.approx(truth, rel=0.1)
    assert abs(res.u_I_mean - truth) < 4 * res.u_I_mean_stderr
    assert cal.params.dark_current == pytest.approx(res.u_I_mean)
    # the same camera with a dark signal far below the noise: not detected, with its limit
    weak = SimulatedSensor(spec.replace(dark_current=0.2), (96, 96), seed=3)
    _, res = calibrate_descriptor(write_emva_set(weak, tmp_path / "weak", EmvaSetSpec(), seed=3))
    assert np.isnan(res.u_I_mean) and res.notes["dark_current"].startswith("not detected")


def test_pgm_values_are_read_as_stored(tmp_path):
    from hdrcap.pipeline.calibration.emva import _read_pgm  # private on purpose: the PGM reader alone

    rng = np.random.default_rng(4)
    for bits in (8, 10, 12, 16):
        a = rng.integers(0, 2**bits, (5, 7)).astype(np.uint16)
        write_pgm(tmp_path / f"x{bits}.pgm", a, 2**bits - 1)
        np.testing.assert_array_equal(_read_pgm(tmp_path / f"x{bits}.pgm"), a)
    (tmp_path / "bad.pgm").write_bytes(b"P2\n2 2\n255\n1 2 3 4\n")
    with pytest.raises(InputError, match="binary PGM"):
        _read_pgm(tmp_path / "bad.pgm")


def test_bright_step_without_its_dark_is_refused(tmp_path):
    sensor = SimulatedSensor(PRESETS["camera-B"], (32, 32), seed=5)
    desc = write_emva_set(sensor, tmp_path / "s", EmvaSetSpec(n_steps=4), seed=5)
    lines = desc.read_text().splitlines()
    first_dark = next(i for i, line in enumerate(lines) if line.startswith("d "))
    desc.write_text("\n".join(lines[:first_dark] + lines[first_dark + 3 :]) + "\n")
    with pytest.raises(InputError, match="no dark pair at that exposure time"):
        calibrate_descriptor(desc)


def test_reference_set_001_gain_within_one_percent(emva_dir):
    """Published (EMVA1288/emva1288 reference implementation): K = 0.28077 DN/e-."""
    cal, res = calibrate_descriptor(emva_dir / "EMVA1288_Data.txt")
    assert res.K == pytest.approx(0.2801, rel=0.01)
    assert res.K == pytest.approx(0.280769, rel=0.01)
    assert not res.quantisation_limited and res.notes == {}
    assert res.u_I_mean == pytest.approx(28.4074, rel=0.1)
