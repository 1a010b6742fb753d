"""Real camera files (#28): 8- to 16-bit PNG/TIFF brackets of scientific and machine-vision
cameras (Bayer or monochrome, LSB- or MSB-aligned), a self-calibration that says what the data
support, truthful summaries, and no merge with another camera's model."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from hdrcap.experiments.realfiles import ADC, BRACKET_SCENES, G8, MV, TIMES, bracket_frames, scene
from hdrcap.mock_camera import PRESETS
from hdrcap.mock_camera.backend import SimulatedCamera
from hdrcap.mock_camera.imagefiles import msb_align, requantise, requantised_gain, write_image
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.mock_camera.sensor import SensorSpec, SimulatedSensor
from hdrcap.pipeline.calibration.selfcal import MIN_RELATIVE_STDERR, self_calibrate
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.io.frameformat import FrameFormat, image_levels
from hdrcap.pipeline.io.raw import read_frame

SHAPE = (192, 256)


def _scene(name: str = "hdr", decades: float = 4.0, level: float = 1.0, shape=SHAPE) -> np.ndarray:
    """The camera's scene (:func:`hdrcap.experiments.realfiles.scene`) of this file's size by default."""
    return scene(shape, name, decades, level)


def _bracket(folder: Path, X: np.ndarray, seed: int, suffix: str = ".tif", spec: SensorSpec = MV, **kw) -> list[Path]:
    """The bracket as image files: the machine-vision camera's 8-bit files by default."""
    cam = SimulatedCamera(spec, X, seed=seed)
    folder.mkdir(parents=True, exist_ok=True)
    kw = {"bits": 8, **kw} if spec is MV or spec.name == MV.name else kw
    return [cam.capture_image_to(folder / f"f{i}{suffix}", t, **kw) for i, t in enumerate(TIMES)]


def _times() -> list[str]:
    return [str(t) for t in TIMES]


# --------------------------------------------------------------------------- the format
def test_levels_from_the_file_and_the_format():
    v8 = np.array([[0, 17], [254, 255]], np.uint8)
    lv = image_levels(v8, 8, None, "a.tif")
    assert (lv.bits, lv.step, lv.white_level, lv.black_level, lv.cfa_pattern) == (8, 1.0, 255.0, None, None)
    assert set(lv.assumed) == {"white_level", "black_level", "cfa"}
    msb = msb_align(np.array([[3, 4095], [100, 7]]), 12)
    lv = image_levels(msb, 16, None, "b.png")
    assert (lv.bits, lv.step, lv.white_level) == (12, 16.0, 65520.0) and "msb" in lv.assumed
    lsb = np.array([[3, 4095], [100, 7]], np.uint16)
    lv = image_levels(lsb, 16, None, "c.png")
    assert lv.white_level is None and "white_level_unknown" in lv.assumed  # nothing says the bits
    lv = image_levels(lsb, 16, FrameFormat(bits=12, cfa="rggb", black_level=64), "c.png")
    assert (lv.bits, lv.step, lv.white_level, lv.black_level, lv.cfa_pattern, lv.assumed) == (
        12,
        1.0,
        4095.0,
        64.0,
        "RGGB",
        (),
    )
    assert image_levels(msb, 16, FrameFormat(bits=12), "b.png").step == 16.0
    with pytest.raises(InputError, match=r"d.png: values up to 5000 DN are neither 12-bit data"):
        image_levels(np.array([[5000, 3]], np.uint16), 16, FrameFormat(bits=12), "d.png")
    with pytest.raises(InputError, match="--bits 12 exceeds the file's 8-bit values"):
        image_levels(v8, 8, FrameFormat(bits=12), "a.tif")
    with pytest.raises(InputError, match="CFA pattern 'RGBG'"):
        FrameFormat(cfa="RGBG")
    with pytest.raises(InputError, match="not below --white-level"):
        FrameFormat(black_level=300, white_level=255)


@pytest.mark.parametrize("suffix", [".tif", ".png"])
def test_8_and_16_bit_files_are_read_with_their_format(tmp_path, suffix):
    rng = np.random.default_rng(1)
    v = rng.integers(0, 4096, (24, 30))
    p8 = write_image(tmp_path / f"a{suffix}", requantise(v, 12, 8).astype(np.uint8))
    fr = read_frame(p8, 0.01, fmt=FrameFormat(cfa="GBRG"))
    assert fr.data.dtype == np.uint16 and (fr.white_level, fr.cfa_pattern, fr.bits) == (255.0, "GBRG", 8)
    p16 = write_image(tmp_path / f"b{suffix}", msb_align(v, 12))
    fr = read_frame(p16, 0.01)
    assert (fr.bits, fr.quantisation_step, fr.white_level) == (12, 16.0, 65520.0)
    assert np.array_equal(fr.data, v << 4)


# --------------------------------------------------------------------------- done when (1)
def test_bayer_8bit_tiff_bracket_merges_with_white_level_255_and_develops(tmp_path, cli):
    """Done when: an 8-bit Bayer TIFF bracket with --times and --cfa GBRG merges with white level
    255, the longest frame's 255s count as saturated, and develop works on the result; the
    format's assumptions are said once."""
    files = _bracket(tmp_path / "b", _scene(), seed=3)
    out = tmp_path / "m.exr"
    proc = cli("merge", *files, "--times", *_times(), "--cfa", "GBRG", "-o", out, "--json", check=True)
    assert proc.stderr.count("the file does not say its format") == 1
    assert "white level 255 DN from the 8-bit depth" in proc.stderr
    img = read_exr(out)
    sc = img.header["self_calibration"]
    assert sc["white_level"] == 255 and sc["saturation_level"] == 255
    assert img.header["cfa_pattern"] == "GBRG"
    longest = read_frame(files[-1], TIMES[-1]).data
    nexp = img.channels["nexp"]
    assert np.count_nonzero(longest == 255) > 1000
    assert (nexp[longest == 255] < len(TIMES)).all()  # never used where it reads 255
    assert (nexp[longest < 250] == len(TIMES)).mean() > 0.99
    g = sc["gain"]
    assert g["estimated"] and abs(g["value"] / G8 - 1) < 0.03, g
    black = float(re.search(r"([0-9.]+) \+-", sc["black_level_source"]).group(1))
    assert black == pytest.approx(requantised_gain(MV.mu_R, ADC, 8), abs=0.05)
    summary = json.loads(proc.stdout)
    assert summary["unit"] == img.header["unit"] == "electrons per second per photosite"
    dev = cli("develop", out, "-o", tmp_path / "rgb.exr")
    assert dev.returncode == 0, dev.stderr


def test_msb_aligned_12bit_pngs_set_the_quantisation_step(tmp_path, cli):
    """12-bit data stored MSB-aligned in 16-bit PNGs: the alignment is detected and said, the
    white level is 65520 DN and the read-noise floor 16^2/12 DN^2; the gain comes out in the
    file's DN (16 x the ADC's)."""
    spec = PRESETS["camera-A"].replace(cfa="RGGB")
    X = make_scene("hdr", SHAPE, decades=4.0, x_max=0.8 * 3500 / (spec.g * TIMES[0]))
    files = _bracket(tmp_path / "b", X, seed=4, suffix=".png", spec=spec, msb=True)
    out = tmp_path / "m.exr"
    proc = cli("merge", *files, "--times", *_times(), "--cfa", "RGGB", "--black-level", "2048", "-o", out, check=True)
    assert "12-bit data MSB-aligned in 16-bit words (every value a multiple of 16" in proc.stderr
    sc = read_exr(out).header["self_calibration"]
    assert sc["quantisation_step"] == 16 and sc["white_level"] == 65520
    assert sc["read_noise_variance"]["quantisation_floor"] == pytest.approx(256 / 12)
    assert abs(sc["gain"]["value"] / (16 * spec.g) - 1) < 0.05


# --------------------------------------------------------------------------- the fit
def _frames_8bit(X: np.ndarray, sensor: SimulatedSensor, rng: np.random.Generator, black=None):
    """An 8-bit bracket in memory (as read from TIFF files: black level unknown)."""
    from hdrcap.pipeline.io.raw import RawFrame

    return [
        RawFrame(
            requantise(sensor.expose(X, t, rng=rng), ADC, 8).astype(np.uint16),
            t,
            black_level=black,
            white_level=255.0,
            cfa_pattern="GBRG",
            path=f"f{i}.tif",
            bits=8,
        )
        for i, t in enumerate(TIMES)
    ]


def test_read_noise_below_quantisation_is_held_at_the_floor():
    """A camera whose read noise is far below its 8-bit step: sigma_R^2 is not fitted below the
    floor (1/12 DN^2) but constrained to it, the weights stay bounded, and no estimate claims a
    relative standard error below 1e-6."""
    spec = MV.replace(sigma2_R=(0.5 * MV.g) ** 2 + 1 / 12)  # 0.5 e-: 0.05 DN (8-bit)
    sensor = SimulatedSensor(spec, SHAPE, seed=2)
    notes: list[str] = []
    sc = self_calibrate(_frames_8bit(_scene(), sensor, np.random.default_rng(5)), warn=notes.append)
    head = sc.header()
    r = head["read_noise_variance"]
    assert r["value"] >= 1 / 12 - 1e-12 and r["quantisation_floor"] == pytest.approx(1 / 12)
    assert head["photon_transfer_fit"]["max_weight_ratio"] < 1e8
    assert sc.gain_known and abs(sc.fit["g"] / G8 - 1) < 0.03
    stated = [sc.gain_relative_stderr, *sc.time_relative_stderr]
    stated += [q.ratio_stderr / q.ratio for q in sc.pairs]
    assert min(stated) >= MIN_RELATIVE_STDERR
    if r["at_floor"]:
        assert r["stderr"] is None and any("below the quantisation floor" in n for n in notes)


def test_a_model_the_data_reject_inflates_the_stated_errors():
    """A black level 6 DN off (what a PNG without one gave before): the reduced chi^2 exceeds
    what its degrees of freedom allow, the errors are scaled by its square root and a note says
    so; the variances are missed by so much that the gain is declared not estimable (DN/s). A
    black level 1.2 DN off still fits (chi^2 about 1) and gives the gain within 3 %."""
    sensor = SimulatedSensor(MV, SHAPE, seed=2)
    notes: list[str] = []
    sc = self_calibrate(_frames_8bit(_scene(), sensor, np.random.default_rng(6), black=0.0), warn=notes.append)
    head = sc.header()
    fit = head["photon_transfer_fit"]
    assert fit["model_rejected"] and fit["reduced_chi2"] > fit["chi2_limit"]
    assert fit["stderr_scale"] == pytest.approx(np.sqrt(fit["reduced_chi2"]))
    assert any("does not describe this bracket" in n for n in notes)
    assert not sc.gain_known and sc.unit.startswith("DN per second")
    assert "misses the variances" in head["gain"]["not_estimable"] and fit["relative_misfit"] > 0.1
    near = self_calibrate(_frames_8bit(_scene(), sensor, np.random.default_rng(6), black=5.0))
    assert near.gain_known and abs(near.fit["g"] / G8 - 1) < 0.03


def test_seven_brackets_of_one_8bit_camera_give_consistent_gains(tmp_path):
    """Done when: seven brackets of one 8-bit camera (different scenes and levels), written as
    8-bit TIFF and self-calibrated, give gains that agree within their stated errors (chi^2/dof
    <= 4) or are declared not estimable; none states a relative error below 1e-6."""
    sensor = SimulatedSensor(MV, SHAPE, seed=11)
    gains, errors = [], []
    for k, (name, decades, level) in enumerate(BRACKET_SCENES):
        frames = bracket_frames(sensor, _scene(name, decades, level), tmp_path, f"b{k}", np.random.default_rng([28, k]))
        sc = self_calibrate(frames)
        if sc.gain_known:
            gains.append(sc.fit["g"])
            errors.append(sc.fit["g_stderr"])
            assert sc.gain_relative_stderr >= MIN_RELATIVE_STDERR
    assert len(gains) >= 5
    g, s = np.array(gains), np.array(errors)
    mean = np.sum(g / s**2) / np.sum(1 / s**2)
    chi2_dof = float(np.sum(((g - mean) / s) ** 2) / (len(g) - 1))
    assert chi2_dof <= 4.0, (g, s, chi2_dof)
    assert abs(mean / G8 - 1) < 0.02


# --------------------------------------------------------------------------- done when (3)
@pytest.fixture(scope="module")
def camera_a_frames(tmp_path_factory):
    d = tmp_path_factory.mktemp("cam-a")
    spec = PRESETS["camera-A"]
    X = make_scene("hdr", (48, 64), decades=3.0, x_max=0.5 * 3500 / (spec.g * 0.002))
    cam = SimulatedCamera(spec, X, seed=1)
    return [cam.capture_to(d / f"a{i}.dng", t) for i, t in enumerate((0.002, 0.016, 0.128))]


def test_frames_merged_with_another_cameras_model_are_refused_in_one_line(camera_a_frames, tmp_path, cli):
    """Done when: camera-A frames (white level 4095) with --camera camera-B, or with a camera-B
    calibration file, are refused with one line naming what differs; --calibration-mismatch warn
    merges them deliberately."""
    proc = cli("merge", *camera_a_frames, "--camera", "camera-B", "-o", tmp_path / "x.exr")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "preset camera-B" in proc.stderr and "another camera" in proc.stderr and not (tmp_path / "x.exr").exists()
    from hdrcap.api import camera_calibration, merge, save_calibration

    cal_b = camera_calibration("camera-B")
    unnamed = save_calibration(tmp_path / "b.cal", cal_b.replace(provenance={}))
    proc = cli("merge", *camera_a_frames, "--calibration", unnamed, "-o", tmp_path / "y.exr")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "white level 4095 DN (12-bit)" in proc.stderr and "white level 1023 DN (10-bit)" in proc.stderr
    proc = cli(
        "merge", *camera_a_frames, "--camera", "camera-B", "--calibration-mismatch", "warn", "-o", tmp_path / "z.exr"
    )
    assert proc.returncode == 0 and "merged with it anyway" in proc.stderr
    with pytest.raises(InputError, match="another camera"):
        merge(camera_a_frames, calibration="camera-B")
    assert merge(camera_a_frames, calibration="camera-B", calibration_mismatch="warn").shape == (48, 64)
    assert merge(camera_a_frames, calibration="camera-A").shape == (48, 64)  # its own model


def test_size_and_cfa_of_a_calibration_are_checked(camera_a_frames):
    from hdrcap.api import camera_calibration, merge

    cal = camera_calibration("camera-A")
    with pytest.raises(InputError, match=r"a0.dng is 64x48 photosites, but preset camera-A is of 32x48"):
        merge(camera_a_frames, calibration=cal.replace(prnu=np.ones((48, 32), np.float32)))
    with pytest.raises(InputError, match="has CFA pattern RGGB, but preset camera-A has BGGR"):
        merge(camera_a_frames, calibration=cal.replace(provenance={**cal.provenance, "cfa_pattern": "BGGR"}))


# --------------------------------------------------------------------------- monochrome
def test_monochrome_sensor_through_merge_denoise_and_batch_develop_refuses(tmp_path, cli):
    spec = PRESETS["camera-B"].replace(cfa="mono")
    X = make_scene("hdr", (64, 96), decades=3.0, x_max=0.8 * 990 / (spec.g * 0.001))
    cam = SimulatedCamera(spec, X, seed=7)
    run = tmp_path / "run1"
    run.mkdir()
    files = [cam.capture_to(run / f"m{i}.dng", t) for i, t in enumerate((0.001, 0.008, 0.064, 0.5))]
    assert read_frame(files[0]).cfa_pattern is None
    out = tmp_path / "m.exr"
    cli("merge", *files, "-o", out, check=True)  # self-calibrated
    assert read_exr(out).header["cfa_pattern"] == "none"
    cli("merge", *files, "--camera", "camera-B", "-o", tmp_path / "p.exr", check=True)
    den = cli("denoise", out, "-o", tmp_path / "d.exr", "--json", check=True)
    assert read_exr(tmp_path / "d.exr").header["denoise"]["settings"]["layout"] == "mono", den.stdout
    dev = cli("develop", out, "-o", tmp_path / "rgb.exr")
    assert dev.returncode == 2 and len(dev.stderr.strip().splitlines()) == 1
    assert "no colour filter" in dev.stderr and "monochrome" in dev.stderr
    batch = cli("batch", run, "-o", tmp_path / "a.zarr", "--camera", "camera-B", "--workers", "1", "--json")
    assert batch.returncode == 0, batch.stderr
    assert json.loads(batch.stdout.strip().splitlines()[-1])["committed"] == 1


def test_monochrome_8bit_png_bracket_merges(tmp_path, cli):
    spec = MV.replace(cfa="mono")
    files = _bracket(tmp_path / "b", _scene(), seed=5, suffix=".png", spec=spec, bits=8)
    out = tmp_path / "m.exr"
    proc = cli("merge", *files, "--times", *_times(), "--cfa", "mono", "-o", out, check=True)
    assert "no colour filter" not in proc.stderr  # said, not assumed
    img = read_exr(out)
    assert img.header["cfa_pattern"] == "none" and img.header["self_calibration"]["gain"]["estimated"]


# --------------------------------------------------------------------------- summaries
def test_summary_states_the_unit_written_and_the_read_noise_used(tmp_path, cli):
    """Two frames of a flat scene cannot give the gain (one signal level): the summary says DN/s
    as the EXR does, and prints the read-noise variance the merge used."""
    files = _bracket(tmp_path / "b", np.full(SHAPE, 0.3 * 250 / (G8 * TIMES[1])), seed=8)
    out = tmp_path / "m.exr"
    proc = cli("merge", *files[:2], "--times", *_times()[:2], "--cfa", "GBRG", "--black-level", "6.2", "-o", out)
    assert proc.returncode == 0, proc.stderr
    img = read_exr(out)
    assert img.header["unit"].startswith("DN per second")
    assert "gain not estimable" in proc.stderr and " DN/s" in proc.stdout and "e-/s" not in proc.stdout
    used = img.header["self_calibration"]["read_noise_variance"]["value"]
    assert f"sigma_R^2 = {used:.3g}" in proc.stderr


def test_no_effective_time_warning_when_the_times_agree_within_their_errors(tmp_path, cli):
    """Exact shutter times and dark frames: no warning that the effective times differ."""
    spec = PRESETS["camera-B"]
    X = make_scene("hdr", (96, 128), decades=3.0, x_max=0.8 * 990 / (spec.g * 0.001))
    cam = SimulatedCamera(spec, X, seed=9)
    times = (0.001, 0.008, 0.064, 0.5)
    files = [cam.capture_to(tmp_path / f"f{i}.dng", t) for i, t in enumerate(times)]
    darks = [cam.capture_to(tmp_path / f"d{i}.dng", t, dark=True) for i, t in enumerate(times)]
    proc = cli("merge", *files, "--darks", *darks, "-o", tmp_path / "m.exr", check=True)
    assert "effective exposure times differ" not in proc.stderr


# --------------------------------------------------------------------------- EMVA 1288 (real data)
def _emva_bright(root: Path) -> list[tuple[float, Path]]:
    """(exposure time s, first image) of each temporal bright step of the descriptor."""
    steps: list[tuple[float, Path]] = []
    kind = None
    for line in (root / "EMVA1288_Data.txt").read_text().splitlines():
        p = line.split()
        if p and p[0] in ("b", "d"):
            kind, t = p[0], float(p[1]) * 1e-9
            first = True
        elif p and p[0] == "i" and kind == "b" and first:
            steps.append((t, root / p[1].replace("\\", "/")))
            first = False
    return steps[:50]


def test_emva_reference_bracket_self_calibrates_to_its_gain(emva_dir, tmp_path, cli):
    """A bracket of the real CCD's flat fields (12-bit values in 16-bit PNGs, --bits 12, the
    dark level as --black-level): the self-calibrated gain agrees with the standard's K within
    3 % and four of its stated (chi^2-scaled) standard errors."""
    steps = _emva_bright(emva_dir)
    pick = [steps[i] for i in (1, 3, 6, 10, 15, 21)]
    out = tmp_path / "emva.exr"
    proc = cli(
        "merge",
        *[p for _, p in pick],
        "--times",
        *[repr(t) for t, _ in pick],
        "--bits",
        "12",
        "--black-level",
        "14.7",
        "-o",
        out,
        check=True,
    )
    sc = read_exr(out).header["self_calibration"]
    g, se = sc["gain"]["value"], sc["gain"]["stderr"]
    assert sc["white_level"] == 4095 and sc["saturation_level"] == 4095, proc.stderr
    assert abs(g / 0.280769 - 1) < 0.03 and abs(g - 0.280769) < 4 * se, (g, se)


def test_a_negative_intercept_is_fitted_at_the_floor_with_bounded_weights():
    """Bin variances whose straight line crosses below the floor (what the issue's bracket gave:
    sigma_R^2 = -0.149): sigma_R^2 is held at the floor and not stated as estimated, the gain
    is fitted with it, and no weight is more than 1e8 times the median."""
    from hdrcap.pipeline.calibration.selfcal import PairEstimate, photon_transfer_fit

    rng = np.random.default_rng(3)
    pairs = []
    for k, r in enumerate((2.0, 4.0, 1.96)):
        m = np.geomspace(0.5, 150, 12)
        var = G8 * m * (1 + r) - 0.15 * (1 + r**2)
        var = np.maximum(var, 1e-6) * (1 + 0.01 * rng.standard_normal(m.size))
        n = np.full(m.size, 5000)
        pairs.append(PairEstimate(k, k + 1, r, 1e-3, int(n.sum()), m, var, n))
    fit = photon_transfer_fit(pairs, floor=1 / 12)
    assert fit is not None and fit["constrained"] and fit["sigma2_R"] == 1 / 12
    assert fit["sigma2_R_stderr"] is None and fit["sigma2_R_fitted"] < 1 / 12
    assert fit["max_weight_ratio"] < 1e8 and fit["g_stderr"] >= 1e-6 * fit["g"]
    assert fit["model_rejected"]  # the line does not hold at the floor: said, errors scaled


def test_arrays_in_memory_take_the_format(tmp_path):
    """The API's merge of arrays with a CFA pattern and bits: the format is the frames'."""
    from hdrcap.api import camera_calibration, merge

    cal = camera_calibration("camera-B")
    sensor = SimulatedSensor(PRESETS["camera-B"], (32, 48), seed=1)
    X = make_scene("hdr", (32, 48), decades=2.0, x_max=2e4)
    times = [0.001, 0.01, 0.1]
    frames = [sensor.expose(X, t) for t in times]
    hdr = merge(frames, times, calibration=cal, cfa_pattern="GBRG", bits=10)
    assert hdr.header["cfa_pattern"] == "GBRG"
    with pytest.raises(InputError, match="CFA pattern 'XYZW'"):
        merge(frames, times, calibration=cal, cfa_pattern="XYZW")
