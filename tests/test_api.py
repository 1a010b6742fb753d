"""The public Python API (``hdrcap.api``, re-exported lazily by ``hdrcap``) and its README example."""

from __future__ import annotations

import importlib.resources
import json
import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np
import pytest

import hdrcap
from hdrcap import api
from hdrcap.pipeline.errors import HdrcapError, InputError, OutputExistsError
from hdrcap.pipeline.params import Calibration

ROOT = Path(__file__).resolve().parents[1]
SHAPE = (64, 96)


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    match = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    assert match, "no ```python block under '## Python API'"
    return match.group(1)


def one_line(err: pytest.ExceptionInfo) -> str:
    msg = str(err.value)
    assert msg and "\n" not in msg and "Traceback" not in msg, msg
    return msg


@pytest.fixture(scope="module")
def sim() -> api.Simulation:
    return hdrcap.simulate("camera-B", "hdr", [0.001, 0.01, 0.1, 1.0], seed=3, shape=SHAPE, darks=True)


# --------------------------------------------------------------------------- package surface


def test_readme_python_example_runs(tmp_path, monkeypatch, capsys):
    """The first python block under README's "## Python API" runs as written."""
    code = _readme_example()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    exec(compile(code, "README.md:Python API", "exec"), {"__name__": "__readme__"})  # noqa: S102
    out = capsys.readouterr().out
    assert "z: mean" in out
    assert list(tmp_path.rglob("scene.exr")), "the example writes its EXR into the temporary folder"


def test_import_hdrcap_is_cheap():
    """``import hdrcap`` imports neither numpy nor numba nor the API; the first use does."""
    code = (
        "import sys, hdrcap; before = {m for m in ('numpy', 'numba', 'hdrcap.api') if m in sys.modules}; "
        "hdrcap.merge; print(sorted(before), 'hdrcap.api' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/", check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["[]", "True"]


def test_lazy_names_match_the_api():
    assert set(hdrcap.__all__) == {"__version__", *api.__all__}
    for name in api.__all__:
        assert getattr(hdrcap, name) is getattr(api, name)
        assert name in dir(hdrcap)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        hdrcap.nope  # noqa: B018
    assert isinstance(hdrcap.__version__, str)


def test_public_functions_are_typed_and_documented():
    import inspect

    for name in api.__all__:
        obj = getattr(api, name)
        if not inspect.isfunction(obj):
            continue
        sig = inspect.signature(obj)
        assert sig.return_annotation is not inspect.Signature.empty, name
        for p in sig.parameters.values():
            assert p.annotation is not inspect.Parameter.empty, f"{name}({p.name})"
        doc = inspect.getdoc(obj) or ""
        if name not in ("save_calibration",):
            assert "Returns\n-------" in doc, name


def test_py_typed_is_installed():
    """PEP 561 marker: in the installed package and in the package data of pyproject.toml."""
    assert importlib.resources.files("hdrcap").joinpath("py.typed").is_file()
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in cfg["tool"]["setuptools"]["package-data"]["hdrcap"]


# --------------------------------------------------------------------------- simulate


def test_simulate_is_seeded_and_physical(sim):
    again = hdrcap.simulate("camera-B", "hdr", [0.001, 0.01, 0.1, 1.0], seed=3, shape=SHAPE, darks=True)
    assert all(np.array_equal(a, b) for a, b in zip(sim.frames, again.frames))
    other = hdrcap.simulate("camera-B", "hdr", [0.001, 0.01, 0.1, 1.0], seed=4, shape=SHAPE)
    assert not np.array_equal(sim.frames[2], other.frames[2])
    assert other.darks is None and len(sim.darks) == 4
    assert all(f.dtype == np.uint16 and f.shape == SHAPE for f in sim.frames + sim.darks)
    assert sim.truth.shape == SHAPE and sim.cfa_pattern == "RGGB"
    assert sim.times == pytest.approx([0.001, 0.01, 0.1, 1.0])
    # the mean raw value of the dark frames is the bias plus the dark signal (Eq. 2), DN
    p = sim.calibration.params
    assert np.mean(sim.darks[-1]) == pytest.approx(p.mu_R + p.g * sim.times[-1] * p.dark_current, abs=0.5)
    assert sim.calibration.prnu is not None and sim.calibration.prnu.shape == SHAPE


def test_simulate_scene_array_and_errors():
    X = np.full((8, 10), 1000.0)
    s = hdrcap.simulate("camera-A", X, [0.01, 0.01], seed=0)
    assert s.truth.shape == (8, 10) and len(s.frames) == 2
    # mean electrons g t a X: a photosite average close to the model
    assert np.mean(s.frames[0]) == pytest.approx(128.0 + 0.23 * 0.01 * (1000 + 0.2), abs=1.0)
    for kwargs, text in (
        ({"camera": "camera-Z"}, "unknown camera preset"),
        ({"scene": "moon"}, "unknown scene"),
        ({"times": [0.1, -1]}, "positive"),
        ({"scene": np.full((4, 4), -1.0)}, ">= 0"),
    ):
        with pytest.raises(InputError) as err:
            hdrcap.simulate(**kwargs)
        assert text in one_line(err)


# --------------------------------------------------------------------------- merge


@pytest.mark.parametrize("camera", ["camera-A", "camera-B"])
def test_merge_sigma_is_the_real_uncertainty(camera):
    """z = (estimate - truth) / sigma has unit spread on the photosites with a measurement."""
    s = hdrcap.simulate(camera, "hdr", [0.0005, 0.004, 0.03, 0.25, 2.0], seed=11, shape=(96, 128))
    hdr = hdrcap.merge(s.frames, s.times, calibration=s.calibration)
    assert isinstance(hdr, hdrcap.HdrResult)
    ok = hdr.measured
    assert ok.mean() > 0.99
    z = (hdr.irradiance[ok] - s.truth[ok]) / hdr.sigma[ok]
    assert 0.9 < z.std() < 1.1, z.std()
    assert abs(z.mean()) < 0.1
    assert hdr.irradiance.dtype == np.float32 and np.all(np.isfinite(hdr.irradiance))
    assert hdr.header["exposure_times"] == pytest.approx(list(s.times))
    assert hdr.header["unit"] == "electrons per second per photosite"


def test_merge_arrays_and_paths_agree(sim, tmp_path):
    """The same frames as arrays, as 16-bit TIFF files (times given) and as RawFrames."""
    import tifffile

    from hdrcap.pipeline.io.raw import read_frame

    paths, dpaths = [], []
    for i, (f, d) in enumerate(zip(sim.frames, sim.darks)):
        paths.append(tmp_path / f"f{i}.tif")
        dpaths.append(tmp_path / f"d{i}.tif")
        tifffile.imwrite(paths[-1], f)
        tifffile.imwrite(dpaths[-1], d)
    cal = tmp_path / "cam.cal"
    hdrcap.save_calibration(cal, sim.calibration)
    a = hdrcap.merge(sim.frames, sim.times, calibration=sim.calibration, darks=sim.darks)
    b = hdrcap.merge(paths, sim.times, calibration=cal, darks=dpaths, dark_times=sim.times)
    c = hdrcap.merge(
        [read_frame(p, t) for p, t in zip(paths, sim.times)],
        calibration=sim.calibration,
        darks=[read_frame(p, t) for p, t in zip(dpaths, sim.times)],
    )
    d = hdrcap.merge(np.stack(sim.frames), sim.times, calibration=sim.calibration, darks=np.stack(sim.darks))
    for other in (b, c, d):
        for name in ("irradiance", "sigma", "nexp"):
            assert np.array_equal(getattr(a, name), getattr(other, name)), name
    assert a.header["merge"]["dark_strategy"] == "matched"
    assert b.header["source_files"] == [str(p) for p in paths]


def test_merge_options_and_dark_strategies(sim):
    """Options reach the merge; a master dark and the model strategy give finite results."""
    model = hdrcap.merge(
        sim.frames, sim.times, calibration=sim.calibration, options=hdrcap.MergeOptions(iterations=3, prnu="scalar")
    )
    assert model.header["merge"]["dark_strategy"] == "model"
    assert model.header["merge"]["iterations"] == 3 and model.header["merge"]["prnu"] == "scalar"
    m = hdrcap.merge(
        sim.frames,
        sim.times,
        calibration=sim.calibration,
        master_dark=sim.darks[0],
        options=hdrcap.MergeOptions(master_dark_time=sim.times[0], n_dark=1),
    )
    assert m.header["merge"]["dark_strategy"] == "master" and np.all(np.isfinite(m.irradiance))
    mixed = hdrcap.merge(
        sim.frames,
        sim.times,
        calibration=sim.calibration,
        darks=sim.darks,
        plan={"exposures": list(sim.times), "darks": ["model", "model", "matched", "matched"]},
    )
    assert mixed.header["merge"]["dark_strategies"] == ["model", "model", "matched", "matched"]
    preset = hdrcap.merge(sim.frames, sim.times, calibration="camera-B")
    assert preset.header["calibration"]["params"]["name"] == "camera-B"


def test_merge_bad_input_gives_one_line_errors(sim, tmp_path):
    cal = sim.calibration
    cases = [
        (lambda: hdrcap.merge(sim.frames, calibration=cal), "exposure time"),
        (lambda: hdrcap.merge(sim.frames, sim.times[:2], calibration=cal), "2 exposure times for 4 frames"),
        (lambda: hdrcap.merge(sim.frames, sim.times), "no camera model"),
        (lambda: hdrcap.merge(sim.frames, sim.times, calibration=tmp_path / "missing.cal"), "missing.cal"),
        (lambda: hdrcap.merge(sim.frames, sim.times, calibration="camera-Z"), "not a camera preset"),
        (lambda: hdrcap.merge(sim.frames, sim.times, calibration=ROOT / "README.md"), "calibration file"),
        (lambda: hdrcap.merge([], [], calibration=cal), "no frames"),
        (lambda: hdrcap.merge([sim.frames[0], sim.frames[1][:10]], [0.1, 0.2], calibration=cal), "differs"),
        (lambda: hdrcap.merge([sim.frames[0], sim.frames[0]], [0.1, 0.2], calibration=cal), "duplicate"),
        (lambda: hdrcap.MergeOptions(saturation="fuzzy"), "saturation"),
        (lambda: hdrcap.merge(sim.frames, sim.times, calibration=cal, options={"iterations": 3}), "MergeOptions"),
        (
            lambda: hdrcap.merge(
                sim.frames, sim.times, calibration=cal, options=hdrcap.MergeOptions(dark_strategy="matched")
            ),
            "needs dark frames",
        ),
        (lambda: hdrcap.merge([tmp_path / "nope.dng"], calibration=cal), "nope.dng: no such file"),
        (lambda: hdrcap.merge([np.zeros((4, 4, 3))], [0.1], calibration=cal), "2-D"),
        (lambda: hdrcap.merge(sim.frames, [0.1, 0.2, float("nan"), 1.0], calibration=cal), "exposure time"),
    ]
    for call, text in cases:
        with pytest.raises(HdrcapError) as err:
            call()
        assert text in one_line(err), (text, str(err.value))


# --------------------------------------------------------------------------- results and files


def test_write_and_read_exr_round_trip(sim, tmp_path):
    hdr = hdrcap.merge(sim.frames, sim.times, calibration=sim.calibration, cfa_pattern="RGGB")
    path = hdr.write(tmp_path / "a.exr")
    back = hdrcap.read_exr(path)
    for name in ("irradiance", "nexp", "quality"):
        assert np.array_equal(getattr(back, name), getattr(hdr, name))
    # sigma is stored as half where it fits, as `hdrcap merge` stores it: 11 significant bits
    assert np.array_equal(back.sigma, hdr.sigma.astype(np.float16).astype(np.float32))
    assert back.header == json.loads(json.dumps(hdr.header))
    assert back.header["cfa_pattern"] == "RGGB"
    assert back.header["exposure_times"] == pytest.approx(list(sim.times))
    with pytest.raises(OutputExistsError) as err:
        hdrcap.write_exr(path, hdr)
    assert "exists" in one_line(err)
    hdrcap.write_exr(path, hdr, force=True, compression="none")
    with pytest.raises(InputError) as err:
        hdr.write(tmp_path / "a2.exr", compression="lzma")
    assert "compression" in one_line(err)
    with pytest.raises(InputError) as err:
        hdrcap.read_exr(tmp_path / "none.exr")
    assert "none.exr" in one_line(err)


def test_result_is_frozen(sim):
    import dataclasses

    hdr = hdrcap.merge(sim.frames, sim.times, calibration=sim.calibration)
    with pytest.raises(dataclasses.FrozenInstanceError):
        hdr.irradiance = None
    assert hdr.shape == SHAPE


# --------------------------------------------------------------------------- denoise


def test_denoise_returns_a_new_result(sim):
    hdr = hdrcap.merge(sim.frames, sim.times, calibration=sim.calibration, cfa_pattern=sim.cfa_pattern)
    irr0 = hdr.irradiance.copy()
    out = hdrcap.denoise(hdr)
    assert np.array_equal(hdr.irradiance, irr0) and out is not hdr
    assert out.header["denoise"]["settings"]["layout"] == "cfa"
    ok = hdr.measured

    def rel(r):
        return np.median(r.sigma[ok] / np.abs(r.irradiance[ok]))

    assert rel(out) < 0.7 * rel(hdr)
    assert np.array_equal(out.nexp, hdr.nexp)
    # a flat region: the filtered values stay within a few of their sigma of the truth
    z = (out.irradiance[ok] - sim.truth[ok]) / hdr.sigma[ok]
    assert abs(np.median(z)) < 0.2
    mono = hdrcap.denoise(hdr, layout="mono", method="constant", bandwidth=float("inf"), radius=1)
    assert mono.header["denoise"]["settings"]["layout"] == "mono"
    for kwargs, text in (
        ({"method": "median"}, "method"),
        ({"radius": -1}, "radius"),
        ({"layout": "rgb"}, "layout"),
        ({"method": "constant"}, "bandwidth"),
    ):
        with pytest.raises(InputError) as err:
            hdrcap.denoise(hdr, **kwargs)
        assert text in one_line(err)
    with pytest.raises(InputError) as err:
        hdrcap.denoise(hdr.irradiance)
    assert "HdrResult" in one_line(err)


# --------------------------------------------------------------------------- plan


def test_plan_meets_its_target_on_a_flat_scene():
    """Simulate the planned exposures (with the planned dark strategies): the measured SNR of
    the merge on a flat scene is the predicted one, independently of the planner's formulas."""
    X = np.full((64, 64), 400.0)
    truth = hdrcap.simulate("camera-B", X, [0.01], seed=5)  # the sensor's calibration
    p = hdrcap.plan(truth.calibration, X, target_snr_db=30, allowed_times=[0.01, 0.1, 0.5, 1.0, 2.0], overhead=0.0)
    assert p.feasible and p.predicted_min_snr_db >= 30 - 0.2
    s = hdrcap.simulate("camera-B", X, p.exposures, seed=5, darks=True)
    hdr = hdrcap.merge(
        s.frames,
        s.times,
        calibration=s.calibration,
        darks=s.darks,
        plan=p,
    )
    err = hdr.irradiance - X
    measured_db = 20 * np.log10(400.0 / err.std())
    assert measured_db == pytest.approx(p.predicted_min_snr_db, abs=1.0)
    # the same request through a preset name, an HdrResult and a Calibration object
    a = hdrcap.plan("camera-B", hdr, 25, allowed_times=[0.01, 0.1, 1.0])
    b = hdrcap.plan(hdrcap.camera_calibration("camera-B"), hdr.irradiance, 25, allowed_times=[0.01, 0.1, 1.0])
    assert a.exposures == b.exposures and a.darks == b.darks


def test_plan_bad_input():
    X = np.full((8, 8), 100.0)
    cases = [
        (lambda: hdrcap.plan("camera-B", np.full((4, 4), np.nan), 20), "NaN"),
        (lambda: hdrcap.plan("camera-B", X, float("inf")), "finite"),
        (lambda: hdrcap.plan("camera-B", X, 20, budget=3), "unknown plan option 'budget'"),
        (lambda: hdrcap.plan("camera-B", X, 20, allowed_times=[-1.0]), "positive"),
        (lambda: hdrcap.plan(42, X, 20), "calibration"),
    ]
    for call, text in cases:
        with pytest.raises(InputError) as err:
            call()
        assert text in one_line(err), (text, str(err.value))


# --------------------------------------------------------------------------- calibrate


def _calibration_frames(seed: int = 2, shape=(48, 64)):
    """Bias, saturation, flat pairs at 4 levels and darks at 6 times from the simulated sensor."""
    from hdrcap.mock_camera import PRESETS, SimulatedSensor

    spec = PRESETS["camera-B"]
    sensor = SimulatedSensor(spec, shape, seed=seed)
    rng = np.random.default_rng([seed, 9])
    X = 0.6 * (1023 - 32) / spec.g / 0.01  # 60 % of the range at 10 ms
    bias = [sensor.expose(0.0, 1e-4, dark=True, rng=rng) for _ in range(4)]
    sat = [sensor.expose(X, 0.2, rng=rng)]
    flat_times = [t for t in (0.002, 0.004, 0.007, 0.01) for _ in range(8)]
    flats = [sensor.expose(X, t, rng=rng) for t in flat_times]
    dark_times = [t for t in (0.5, 1.0, 2.0, 4.0, 8.0, 16.0) for _ in range(2)]
    darks = [sensor.expose(0.0, t, dark=True, rng=rng) for t in dark_times]
    return sensor, bias, sat, flats, flat_times, darks, dark_times


def test_calibrate_from_arrays_recovers_the_sensor(tmp_path):
    sensor, bias, sat, flats, flat_times, darks, dark_times = _calibration_frames()
    cal = hdrcap.calibrate(
        bias,
        sat,
        flats,
        darks,
        flat_times=flat_times,
        dark_times=dark_times,
        bias_times=[1e-4] * 4,
        white_level=1023,
        provenance={"camera": "sim"},
    )
    assert isinstance(cal, Calibration)
    p, se = cal.params, cal.stderr
    assert abs(p.g - 0.92) < max(4 * se["g"], 0.02 * 0.92)
    assert p.mu_R == pytest.approx(32.0, abs=0.3)
    assert p.sigma2_R == pytest.approx(18.0, rel=0.1)
    assert p.v_sat == pytest.approx(1023.0, abs=1.0)
    assert p.dark_current == pytest.approx(1.0, rel=0.3)
    assert np.corrcoef(cal.prnu.ravel(), sensor.prnu.ravel())[0, 1] > 0.5
    assert cal.provenance["camera"] == "sim" and p.name == "sim"
    # save and load: the same model
    path = hdrcap.save_calibration(tmp_path / "cam.cal", cal)
    back = hdrcap.load_calibration(path)
    assert back.params == cal.params and np.array_equal(back.prnu, cal.prnu)


def test_calibrate_paths_equal_arrays(tmp_path):
    import tifffile

    _, bias, sat, flats, flat_times, darks, dark_times = _calibration_frames(seed=4, shape=(32, 32))

    def write(frames, kind):
        out = []
        for i, f in enumerate(frames):
            out.append(tmp_path / f"{kind}{i:02d}.tif")
            tifffile.imwrite(out[-1], f)
        return out

    a = hdrcap.calibrate(
        bias, sat, flats, darks, flat_times=flat_times, dark_times=dark_times, bias_times=[1e-4] * 4, white_level=1023
    )
    b = hdrcap.calibrate(
        write(bias, "b"),
        write(sat, "s"),
        write(flats, "f"),
        write(darks, "d"),
        flat_times=flat_times,
        dark_times=dark_times,
        bias_times=[1e-4] * 4,
        saturation_times=[0.2],
        white_level=1023,
    )
    assert a.params == b.params
    assert np.array_equal(a.prnu, b.prnu) and np.array_equal(a.dark_current_map, b.dark_current_map)


def test_calibrate_bad_input():
    _, bias, sat, flats, flat_times, _, _ = _calibration_frames(shape=(16, 16))
    cases = [
        (lambda: hdrcap.calibrate(bias, sat, flats), "exposure time"),
        (lambda: hdrcap.calibrate([], sat, flats, flat_times=flat_times), "no bias frames"),
        (lambda: hdrcap.calibrate(bias, sat, None), "no flat fields"),
        (lambda: hdrcap.calibrate(bias, sat, flats, flat_times=flat_times[:3]), "exposure times for"),
        (lambda: hdrcap.calibrate(bias, sat, flats, flat_times=flat_times, gain_method="magic"), "gain_method"),
        (lambda: hdrcap.calibrate(flats[:2], sat, flats, flat_times=flat_times, white_level=1023), "bias"),
    ]
    for call, text in cases:
        with pytest.raises(InputError) as err:
            call()
        assert text in one_line(err), (text, str(err.value))
