"""``hdrcap develop`` and :mod:`pipeline.develop`: scene-linear RGB from the merged CFA irradiance.

Expectations come from outside the code under test: colour-demosaicing called directly on the
mosaic, published colorimetry (the sRGB matrix of IEC 61966-2-1, the D50 white), a simulated
scene of known colours, and Monte-Carlo draws of noisy mosaics.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess

import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from hdrcap.cli import main
from hdrcap.pipeline.develop import (
    DEMOSAIC_METHODS,
    SIGMA_NOT_PROPAGATED,
    develop,
    develop_image,
    output_matrix,
    propagate_variance,
    support_radius,
)
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.dngwrite import (
    CameraColour,
    camera_colour,
    colour_from_dng_tags,
    colour_from_libraw,
    colour_tags,
    write_float_dng,
)
from hdrcap.pipeline.io.exr import read_exr, write_exr
from hdrcap.pipeline.result import HdrResult
from tests.helpers.colour_sim import CANON_CM, CANON_NEUTRAL, XYZ_TO_SRGB, camera_mosaic, mosaic, recolour_frames

#: D50 white, CIE 15 chromaticity (0.3457, 0.3585), as XYZ with Y = 1 (the DNG connection space white).
D50_XYZ = np.array([0.3457 / 0.3585, 1.0, (1 - 0.3457 - 0.3585) / 0.3585])


def _mosaic(irr, cfa):
    """A merge result holding only an irradiance mosaic of ``cfa``."""
    return HdrResult(irr, np.ones_like(irr), np.ones_like(irr), header={"cfa_pattern": cfa})


def _reference(mos, cfa, method):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the library's scipy.ndimage.filters imports
        import colour_demosaicing

    return getattr(colour_demosaicing, DEMOSAIC_METHODS[method])(mos, cfa)


# --------------------------------------------------------------------------- colour


def test_grey_comes_out_grey_with_the_published_whites():
    colour = CameraColour(color_matrix_1=CANON_CM.ravel(), as_shot_neutral=tuple(CANON_NEUTRAL))
    k = 1234.5
    grey = np.broadcast_to(k * CANON_NEUTRAL / CANON_NEUTRAL.max(), (16, 16, 3))
    mos = mosaic(np.array(grey))
    for space, expected in (("xyz", k * D50_XYZ), ("linear-srgb", k * np.ones(3)), ("camera", grey[0, 0])):
        res = develop(mos, None, None, "RGGB", method="bilinear", space=space, colour=colour)
        np.testing.assert_allclose(res.rgb[8, 8], expected, rtol=2e-4, err_msg=space)
        np.testing.assert_allclose(res.rgb[2:-2, 2:-2].reshape(-1, 3).std(axis=0), 0, atol=1e-3 * k)


def test_two_matrices_interpolated_still_map_the_neutral_to_white():
    # Colour-hdri's docstring camera: illuminant A (17) and D65 (21) matrices, a tungsten-ish neutral.
    cm1 = [[0.5309, -0.0229, -0.0336], [-0.6241, 1.3265, 0.3337], [-0.0817, 0.1215, 0.6664]]
    colour = CameraColour(
        color_matrix_1=np.ravel(cm1),
        illuminant_1=17,
        color_matrix_2=CANON_CM.ravel(),
        illuminant_2=21,
        as_shot_neutral=(0.41307, 1.0, 0.646465),
    )
    m = output_matrix("linear-srgb", colour)
    np.testing.assert_allclose(m @ np.array([0.41307, 1.0, 0.646465]), np.ones(3), rtol=2e-4)


def test_camera_that_sees_srgb_develops_to_the_same_colours():
    # A camera whose XYZ-to-camera matrix is sRGB's own: its white (1, 1, 1) is D65, and every
    # colour, not only grey, must come out as it went in.
    colour = CameraColour(color_matrix_1=XYZ_TO_SRGB.ravel(), as_shot_neutral=(1.0, 1.0, 1.0))
    m = output_matrix("linear-srgb", colour)
    np.testing.assert_allclose(m, np.eye(3), atol=2e-4)


def test_spaces_that_need_a_matrix_are_refused_without_one():
    mos = np.ones((16, 16))
    with pytest.raises(InputError, match="records none.*--space camera"):
        develop(mos, None, None, "RGGB", space="xyz")
    no_wb = CameraColour(color_matrix_1=CANON_CM.ravel())
    with pytest.raises(InputError, match="no white balance"):
        develop(mos, None, None, "RGGB", space="linear-srgb", colour=no_wb)
    with pytest.raises(InputError, match="unknown colour space"):
        develop(mos, None, None, "RGGB", space="prophoto")
    with pytest.raises(InputError, match="unknown demosaicing method 'vng'"):
        develop(mos, None, None, "RGGB", method="vng")
    with pytest.raises(InputError, match="Bayer"):
        develop(mos, None, None, "none")


# --------------------------------------------------------------------------- demosaic and sigma


@pytest.mark.parametrize("method", sorted(DEMOSAIC_METHODS))
@pytest.mark.parametrize("cfa", ["RGGB", "GBRG"])
def test_channels_agree_with_the_library_on_the_samemosaic(method, cfa):
    mos = np.random.default_rng(3).lognormal(6, 1.5, (24, 32))
    res = develop(mos, None, None, cfa, method=method)
    ref = _reference(mos, cfa, method)
    np.testing.assert_allclose(res.rgb, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


@pytest.mark.parametrize("method", sorted(DEMOSAIC_METHODS))
def test_support_radius_bounds_every_dependence(method):
    rng = np.random.default_rng(11)
    r = support_radius(method)
    for _ in range(3):
        x = rng.lognormal(3, 1, (40, 40))
        base = _reference(x, "RGGB", method)
        for a in (0, 1):
            for b in (0, 1):
                y = x.copy()
                y[20 + a, 20 + b] *= 3
                changed = np.abs(_reference(y, "RGGB", method) - base).max(axis=2) > 1e-9 * x.max()
                ii, jj = np.nonzero(changed)
                assert np.abs(ii - 20 - a).max() <= r and np.abs(jj - 20 - b).max() <= r


@pytest.mark.parametrize("method", ["bilinear", "malvar2004"])
def test_propagated_sigma_matches_monte_carlo(method):
    """sigma per channel and tile position against the spread of 600 seeded noisy mosaics."""
    rng = np.random.default_rng(2024)
    h, w = 24, 28
    truth = rng.lognormal(7, 1, (h, w))
    sigma = truth * rng.uniform(0.01, 0.2, (h, w))  # an uneven uncertainty, as in a merge
    colour = CameraColour(color_matrix_1=CANON_CM.ravel(), as_shot_neutral=tuple(CANON_NEUTRAL))
    m = output_matrix("linear-srgb", colour)
    res = develop(truth, sigma, None, "GRBG", method=method, space="linear-srgb", colour=colour)
    draws = np.stack(
        [_reference(truth + sigma * rng.standard_normal((h, w)), "GRBG", method) @ m.T for _ in range(600)]
    )
    mc = draws.std(axis=0, ddof=1)
    ratio = res.sigma / mc
    for k in range(3):
        for a in (0, 1):
            for b in (0, 1):
                r = ratio[a::2, b::2, k]  # edges included: the mirrored border is propagated exactly
                # 600 draws: each MC std within about 3 % (1 sd); the median of ~100 far tighter.
                assert 0.97 < np.median(r) < 1.03, (k, a, b, np.median(r))
                assert np.all((r > 0.85) & (r < 1.15)), (k, a, b, r.min(), r.max())
    edge = np.ones((h, w), bool)
    edge[2:-2, 2:-2] = False
    assert 0.95 < np.median(ratio[edge]) < 1.05


@pytest.mark.parametrize("method", ["bilinear", "malvar2004"])
@pytest.mark.parametrize("shape", [(16, 22), (8, 10)])
def test_propagated_variance_is_the_sum_over_impulse_responses(method, shape):
    """Deterministic: sum_q (demosaic of the unit impulse at q)^2 var_q, the library's own
    weights one photosite at a time, edges and the mirrored border included."""
    rng = np.random.default_rng(7)
    var = rng.uniform(0.5, 2.0, shape)
    m = rng.normal(size=(3, 3))
    brute = np.zeros((*shape, 3))
    for q in np.ndindex(*shape):
        impulse = np.zeros(shape)
        impulse[q] = 1.0
        brute += (_reference(impulse, "BGGR", method) @ m.T) ** 2 * var[q]
    np.testing.assert_allclose(propagate_variance(var, "BGGR", method, m), brute, rtol=1e-9, atol=1e-12)


def test_defects_are_filled_from_neighbours_and_flagged():
    mos = np.full((20, 20), 500.0)
    sigma = np.full((20, 20), 5.0)
    nexp = np.full((20, 20), 4.0)
    quality = np.zeros((20, 20))
    mos[10, 10], nexp[10, 10], quality[10, 10], sigma[10, 10] = 9e6, 0, 4, 0  # a hot photosite
    mos[5, 6], nexp[5, 6], quality[5, 6], sigma[5, 6] = 8e5, 0, 16, 0  # saturated everywhere: a lower bound
    res = develop(mos, sigma, nexp, "RGGB", method="bilinear", quality=quality)
    assert res.info["defects_filled"] == 1
    # The hot value leaves no trace: the scene is uniform around it.
    np.testing.assert_allclose(res.rgb[7:14, 7:14], 500.0, rtol=1e-6)
    # Flagged exactly where the bilinear support (3x3) reaches the defect.
    hot = (res.quality.astype(int) & 4) > 0
    assert np.array_equal(np.argwhere(hot), np.argwhere(np.pad(np.ones((3, 3)), ((9, 8), (9, 8))) > 0))
    sat = (res.quality.astype(int) & 16) > 0
    assert sat[4:7, 5:8].all() and sat.sum() == 9 and res.rgb[5, 6].max() >= 8e5 * 0.99
    assert np.array_equal(res.nexp == 0, hot | sat) and res.nexp.max() == 4
    assert np.all(np.isfinite(res.sigma)) and res.sigma[10, 10].min() > 0


def test_menon_writes_no_sigma_and_says_so():
    mos = np.random.default_rng(5).lognormal(6, 1, (24, 24))
    res = develop(mos, 0.05 * mos, np.ones_like(mos), "RGGB", method="menon2007")
    assert res.sigma is None and res.info["sigma"] == SIGMA_NOT_PROPAGATED
    image = develop_image(HdrResult(mos, 0.05 * mos, np.ones_like(mos), header={"cfa_pattern": "RGGB"}), "menon2007")
    assert not any(name.startswith("sigma") for name in image.channels)
    assert image.header["sigma"] == SIGMA_NOT_PROPAGATED


# --------------------------------------------------------------------------- end to end


#: Linear sRGB of the four patches of the colour scene (fractions of the brightest irradiance).
PATCHES = np.array([[0.6, 0.15, 0.08], [0.12, 0.5, 0.15], [0.08, 0.15, 0.7], [0.4, 0.4, 0.4]])
#: e-/s of a linear sRGB value 1 in the camera's strongest neutral channel: dim enough (at most
#: about 1000 e- in the longest exposure) that photon noise, which the merge's sigma states, dwarfs
#: the simulator's 1 % PRNU, which a preset camera model leaves out.
SCALE = 1500.0
#: Width of each patch, photosites (RawTherapee 5.9 refuses float DNGs under about 30000 photosites).
PATCH_W = 32


@pytest.fixture(scope="module")
def colour_bracket(tmp_path_factory):
    """A simulated camera-A bracket of four flat colour patches, its frames carrying the Canon
    colour matrix and D65 neutral, merged and developed by the command line."""
    from tests.helpers.cli import run_cli

    d = tmp_path_factory.mktemp("develop")
    h, w = 256, 4 * PATCH_W
    rgb = np.empty((h, w, 3))
    for i, patch in enumerate(PATCHES):
        rgb[:, i * PATCH_W : (i + 1) * PATCH_W] = patch
    write_exr(d / "scene.exr", {"irradiance": camera_mosaic(rgb, SCALE).astype(np.float32)}, {})
    sim = d / "sim"
    run_cli("simulate", "--camera", "camera-A", "--scene", d / "scene.exr", "--out", sim, "--seed", "9", check=True)
    frames = recolour_frames(sorted(sim.glob("frame_*.dng")), d)
    run_cli("merge", *frames, "--camera", "camera-A", "-o", d / "m.exr", check=True)
    proc = run_cli(
        "develop", d / "m.exr", "-o", d / "rgb.exr", "--space", "linear-srgb", "--preview", d / "p.png", "--json"
    )
    assert proc.returncode == 0, proc.stderr
    return d, json.loads(proc.stdout)


def test_merge_records_the_frames_colour_metadata(colour_bracket):
    d, _ = colour_bracket
    recorded = CameraColour.from_attrs(read_exr(d / "m.exr").header["camera_colour"])
    np.testing.assert_allclose(recorded.color_matrix_1, CANON_CM.ravel(), atol=1e-4)
    np.testing.assert_allclose(recorded.as_shot_neutral, CANON_NEUTRAL / CANON_NEUTRAL.max(), atol=1e-4)
    assert recorded.illuminant_1 == 21


def test_developed_exr_matches_the_reference_demosaic_of_the_merge(colour_bracket):
    d, info = colour_bracket
    merged = read_exr(d / "m.exr")
    developed = read_exr(d / "rgb.exr")  # OpenEXR's reader groups R, G, B (and sigma.R/G/B)
    m = np.array(info["matrix_camera_to_output"])
    ref = _reference(merged.channels["irradiance"].astype(np.float64), merged.header["cfa_pattern"], "malvar2004")
    np.testing.assert_allclose(developed.channels["RGB"], ref @ m.T, rtol=1e-5, atol=1e-5 * np.abs(ref).max())
    assert developed.channels["sigma"].shape == ref.shape and developed.header["source_header"]["cfa_pattern"] == "RGGB"
    assert (d / "p.png").stat().st_size > 0


def test_developed_colours_are_the_scenes_within_sigma(colour_bracket):
    """The simulator's truth: each patch's linear sRGB, times the scale, within the propagated sigma."""
    d, _ = colour_bracket
    developed = read_exr(d / "rgb.exr")
    rgb, sig, nexp = developed.channels["RGB"], developed.channels["sigma"], developed.channels["nexp"]
    for i, patch in enumerate(PATCHES):
        sl = (slice(3, -3), slice(i * PATCH_W + 3, (i + 1) * PATCH_W - 3))  # away from the patch edges
        assert (nexp[sl] > 0).all()
        z = (rgb[sl] - patch * SCALE) / sig[sl]
        for k in range(3):
            assert abs(np.mean(z[..., k])) < 0.5, (i, k, np.mean(z[..., k]))
            assert 0.75 < np.std(z[..., k]) < 1.3, (i, k, np.std(z[..., k]))


# --------------------------------------------------------------------------- command line


def _merged_like(tmp_path, attrs):
    mos = np.random.default_rng(1).lognormal(5, 1, (16, 16)).astype(np.float32)
    path = tmp_path / "in.exr"
    write_exr(path, {"irradiance": mos, "sigma": 0.1 * mos, "nexp": np.ones_like(mos)}, attrs)
    return path


def test_bad_input_is_a_one_line_error_with_exit_2(tmp_path, capsys):
    mono = _merged_like(tmp_path, {"cfa_pattern": "none"})
    assert main(["develop", str(mono), "-o", str(tmp_path / "a.exr")]) == 2
    assert "Bayer" in capsys.readouterr().err
    ok = tmp_path / "ok"
    ok.mkdir()
    good = _merged_like(ok, {"cfa_pattern": "RGGB"})
    assert main(["develop", str(good), "-o", str(tmp_path / "b.exr"), "--demosaic", "ahd"]) == 2
    assert "unknown demosaicing method 'ahd'" in capsys.readouterr().err
    assert main(["develop", str(good), "-o", str(tmp_path / "c.exr"), "--space", "xyz"]) == 2
    err = capsys.readouterr().err
    assert "colour matrix" in err and "--space camera" in err and err.count("\n") == 1
    assert main(["develop", str(good), "-o", str(tmp_path / "d.exr")]) == 0
    capsys.readouterr()
    assert main(["develop", str(tmp_path / "d.exr"), "-o", str(tmp_path / "e.exr")]) == 2  # not a mosaic
    assert "no irradiance channel" in capsys.readouterr().err
    assert main(["develop", str(good), "-o", str(tmp_path / "d.exr")]) == 3  # exists: OutputExistsError
    assert not any((tmp_path / n).exists() for n in ("a.exr", "b.exr", "c.exr", "e.exr"))


def test_help_does_not_import_the_colour_libraries():
    import subprocess
    import sys

    code = "import sys; from hdrcap.cli import main; main(['--help']); print(sorted(m for m in sys.modules if m.startswith('colour')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("[]")


# --------------------------------------------------------------------------- colour metadata (float DNG too)


def test_libraw_metadata_maps_to_dng_colour_tags():
    """rawpy's ``rgb_xyz_matrix`` (rows in ``color_desc`` order) and ``camera_whitebalance``
    (multipliers) of a non-DNG raw: the tests have no CR2/NEF, so LibRaw-like values."""
    rows = np.vstack([CANON_CM, CANON_CM[1]])  # RGBG: the second green repeats the first
    got = colour_from_libraw(rows, [2.0, 1.0, 1.6, 1.0], b"RGBG", source="x.cr2")
    np.testing.assert_allclose(got.color_matrix_1, CANON_CM.ravel())
    np.testing.assert_allclose(got.as_shot_neutral, [0.5, 1.0, 0.625])
    assert got.illuminant_1 == 21
    shuffled = colour_from_libraw(rows[[2, 1, 0, 3]], [1.6, 1.0, 2.0, 1.0], b"BGRG")
    np.testing.assert_allclose(shuffled.color_matrix_1, CANON_CM.ravel())
    np.testing.assert_allclose(shuffled.as_shot_neutral, [0.5, 1.0, 0.625])
    assert colour_from_libraw(np.zeros((4, 3)), [2.0, 1.0, 1.6, 1.0], b"RGBG") is None  # unknown camera
    assert colour_from_libraw(rows, [0, 0, 0, 0], b"RGBG").as_shot_neutral is None  # no white balance
    assert colour_from_libraw(rows, [1, 1, 1, 1], b"CMYG") is None


def test_float_dng_of_a_non_dng_source_gets_libraws_matrix(tmp_path, monkeypatch):
    import rawpy

    class FakeRaw:  # what rawpy gives for a CR2 whose camera LibRaw knows
        rgb_xyz_matrix = np.vstack([CANON_CM, CANON_CM[1]])
        camera_whitebalance = [2.0, 1.0, 1.6, 1.0]
        color_desc = b"RGBG"

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    src = tmp_path / "IMG_0001.CR2"
    src.write_bytes(b"not a tiff")
    real_imread = rawpy.imread
    monkeypatch.setattr(rawpy, "imread", lambda p: FakeRaw() if p == str(src) else real_imread(p))
    assert camera_colour(src).source == "IMG_0001.CR2: LibRaw"
    irr = np.random.default_rng(4).gamma(2.0, 50.0, (32, 32)).astype(np.float32)
    write_float_dng(tmp_path / "o.dng", _mosaic(irr, "RGGB"), source=src)
    with tifffile.TiffFile(tmp_path / "o.dng") as tif:
        tags = {code: t.value for code, t in tif.pages[0].tags.items()}
    back = colour_from_dng_tags(tags)
    np.testing.assert_allclose(back.color_matrix_1, CANON_CM.ravel(), atol=1e-6)
    np.testing.assert_allclose(back.as_shot_neutral, [0.5, 1.0, 0.625], atol=1e-6)
    assert tags[50778] == 21
    with real_imread(str(tmp_path / "o.dng")) as raw:  # LibRaw reads them back as camera white balance
        wb = np.array(raw.camera_whitebalance[:3])
    np.testing.assert_allclose(wb / wb[1], [2.0, 1.0, 1.6], rtol=1e-3)


_finite = st.floats(-3, 3, allow_nan=False).filter(lambda v: abs(v) > 1e-3)


@settings(max_examples=40, deadline=None)
@given(st.lists(_finite, min_size=9, max_size=9), st.lists(st.floats(0.05, 4), min_size=3, max_size=3))
def test_colour_tags_round_trip_through_a_dng(matrix, neutral):
    if abs(np.linalg.det(np.reshape(matrix, (3, 3)))) < 1e-3:
        return
    colour = CameraColour(color_matrix_1=matrix, as_shot_neutral=neutral, illuminant_1=17)
    assert CameraColour.from_attrs(json.loads(json.dumps(colour.to_attrs()))) == colour
    buf = io.BytesIO()
    with tifffile.TiffWriter(buf) as tw:
        tw.write(np.zeros((4, 4), np.uint16), extratags=colour_tags(colour))
    buf.seek(0)
    with tifffile.TiffFile(buf) as tif:
        back = colour_from_dng_tags({code: t.value for code, t in tif.pages[0].tags.items()})
    np.testing.assert_allclose(back.color_matrix_1, matrix, atol=1e-6)
    np.testing.assert_allclose(back.as_shot_neutral, neutral, atol=1e-6)
    assert back.illuminant_1 == 17


def test_colour_preview_keeps_hues_and_orders_brightness():
    from hdrcap.pipeline.preview import tonemap_log_colour

    rgb = np.array([[[1.0, 0.5, 0.25], [10.0, 5.0, 2.5], [100.0, 100.0, 100.0], [-1.0, 2.0, 0.0]]])
    out = tonemap_log_colour(rgb, 0, 100).astype(float)
    np.testing.assert_allclose(out[0, 1] / out[0, 1, 0], [1.0, 0.5, 0.25], atol=2 / 255)  # hue kept
    assert out[0, 0, 0] < out[0, 1, 0] < out[0, 2, 0] == 255 and out[0, 2, 0] == out[0, 2, 2]
    assert out[0, 3, 0] == 0 and out[0, 3, 1] > 0  # negatives to 0, never wrapped


@pytest.mark.skipif(shutil.which("rawtherapee-cli") is None, reason="rawtherapee-cli is not installed")
def test_rawtherapee_develops_the_float_dng_with_the_cameras_colours(colour_bracket, tmp_path):
    """RawTherapee (5.9) reads the float DNG, its CFA and colour tags; in its picture of the
    scene each colour patch keeps its dominant primary and the grey patch stays grey."""
    from tests.helpers.cli import run_cli

    d, _ = colour_bracket
    frames = sorted(d.glob("frame_*.dng"))
    run_cli("merge", *frames, "--camera", "camera-A", "-o", tmp_path / "m.dng", check=True)
    env = dict(os.environ, HOME=str(tmp_path), XDG_CONFIG_HOME=str(tmp_path / "cfg"))
    proc = subprocess.run(
        ["rawtherapee-cli", "-q", "-o", str(tmp_path / "rt.tif"), "-t", "-b16", "-Y", "-c", str(tmp_path / "m.dng")],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    rgb = tifffile.imread(tmp_path / "rt.tif").astype(np.float64)
    irr = read_exr(d / "m.exr").channels["irradiance"].astype(np.float64)
    cut = ((irr.shape[0] - rgb.shape[0]) // 2, (irr.shape[1] - rgb.shape[1]) // 2)  # its border crop
    assert 0 <= cut[0] <= 8 and 0 <= cut[1] <= 8
    for i, patch in enumerate(PATCHES[:3]):  # red, green, blue
        x0, x1 = i * PATCH_W + 4 - cut[1], (i + 1) * PATCH_W - 4 - cut[1]
        mean = rgb[6:-6, x0:x1].reshape(-1, 3).mean(axis=0)
        assert np.argmax(mean) == np.argmax(patch), (i, mean)
    grey = rgb[6:-6, 3 * PATCH_W + 4 - cut[1] : 4 * PATCH_W - 4 - cut[1]].reshape(-1, 3).mean(axis=0)
    assert grey.max() < 65000 and grey.max() / grey.min() < 1.05, grey  # AsShotNeutral applied: grey stays grey
