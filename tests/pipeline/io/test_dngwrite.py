"""Float DNG output of the merge (`pipeline.io.dngwrite`, `hdrcap merge -o out.dng`)."""

from __future__ import annotations

import io
import shutil
import subprocess

import numpy as np
import pytest
import rawpy
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hdrcap.mock_camera.dng import write_dng
from hdrcap.pipeline.errors import InputError, OutputExistsError
from hdrcap.pipeline.io.dngwrite import dng_layout, write_float_dng
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.result import HdrResult

#: LibRaw converts a float raw image to integers, its maximum mapped to this value.
_LIBRAW_FLOAT_TARGET = 16383


def _mosaic(irr, cfa):
    """A merge result holding only an irradiance mosaic of ``cfa``."""
    return HdrResult(irr, np.ones_like(irr), np.ones_like(irr), header={"cfa_pattern": cfa})


@pytest.fixture(scope="module")
def merged(tmp_path_factory):
    """A simulated camera-A bracket merged by the CLI twice: to EXR and to float DNG."""
    from tests.helpers.cli import run_cli

    d = tmp_path_factory.mktemp("dng")
    sim = d / "sim"
    run_cli("simulate", "--camera", "camera-A", "--out", sim, "--size", "64x48", "--seed", "5", check=True)
    frames = sorted(sim.glob("frame_*.dng"))
    run_cli("merge", *frames, "--camera", "camera-A", "-o", d / "m.exr", check=True)
    run_cli("merge", *frames, "--camera", "camera-A", "-o", d / "m.dng", "--json", check=True)
    return d, sim, frames


def _tags(path):
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        return {code: t.value for code, t in page.tags.items()}, page.asarray()


def test_float_dng_holds_the_exr_irradiance_exactly(merged):
    d, sim, frames = merged
    exr = read_exr(d / "m.exr")
    tags, data = _tags(d / "m.dng")
    assert data.dtype == np.float32 and tags[339] == 3 and tags[258] == 32 and tags[262] == 32803
    np.testing.assert_array_equal(data, exr.channels["irradiance"])
    codes = {"R": 0, "G": 1, "B": 2}
    assert tuple(tags[33422]) == tuple(codes[c] for c in exr.header["cfa_pattern"]) and tuple(tags[33421]) == (2, 2)
    assert tags[50714] == 0 and tags[50717] >= data.max() > tags[50717] - 1
    assert "2^0 = irradiance in electrons per second per photosite" in tags[270]
    # Independent of the code: the simulator's truth, within the merge's own sigma.
    truth = read_exr(sim / "truth.exr").channels["irradiance"]
    ok = exr.channels["nexp"] > 0
    z = (data[ok] - truth[ok]) / exr.channels["sigma"][ok]
    assert abs(np.median(z)) < 0.2 and 0.8 < np.std(z) < 1.25


def test_float_dng_carries_the_first_frames_colour_tags(merged):
    d, _, frames = merged
    src, _ = _tags(frames[0])
    out, _ = _tags(d / "m.dng")
    for code in (50721, 50728, 50778, 274, 271, 272, 50708):
        assert code in src and out[code] == src[code], code


def test_rawpy_develops_the_float_dng(merged):
    d, _, _ = merged
    irr = read_exr(d / "m.exr").channels["irradiance"].astype(np.float64)
    with rawpy.imread(str(d / "m.dng")) as raw:
        assert raw.color_desc == b"RGBG" and raw.raw_image.shape == irr.shape
        got = raw.raw_image.astype(np.float64)
        rgb = raw.postprocess(use_camera_wb=True, no_auto_bright=True, gamma=(1, 1), output_bps=16)
    # LibRaw (0.22) keeps no floats: it scales the maximum to 16383 and truncates.
    expected = np.clip(irr, 0, None) * _LIBRAW_FLOAT_TARGET / irr.max()
    assert np.all(np.abs(got - expected) <= 1.0)
    assert rgb.shape[:2] == irr.shape and rgb.max() > 0


def test_colour_matrix_and_white_balance_copied_from_a_dng(tmp_path):
    src = tmp_path / "src.dng"
    matrix = [[0.7, -0.2, -0.05], [-0.4, 1.2, 0.2], [-0.1, 0.2, 0.6]]
    buf = io.BytesIO()
    mosaic = np.full((32, 32), 1000, np.uint16)
    write_dng(
        buf,
        mosaic,
        exposure_time=0.01,
        iso=100,
        black_level=64,
        white_level=4095,
        color_matrix=matrix,
        as_shot_neutral=(0.5, 1.0, 0.625),
    )
    src.write_bytes(buf.getvalue())
    irr = np.random.default_rng(1).gamma(2.0, 50.0, (32, 32)).astype(np.float32)
    write_float_dng(tmp_path / "o.dng", _mosaic(irr, "GRBG"), source=src)
    tags, data = _tags(tmp_path / "o.dng")
    cm = np.array(tags[50721], float).reshape(9, 2)
    np.testing.assert_allclose(cm[:, 0] / cm[:, 1], np.ravel(matrix), atol=1e-4)
    wb = np.array(tags[50728], float).reshape(3, 2)
    np.testing.assert_allclose(wb[:, 0] / wb[:, 1], [0.5, 1.0, 0.625], atol=1e-4)
    assert tuple(tags[33422]) == (1, 0, 2, 1)
    np.testing.assert_array_equal(data, irr)
    with rawpy.imread(str(tmp_path / "o.dng")) as raw:
        wb_libraw = np.array(raw.camera_whitebalance[:3])
    np.testing.assert_allclose(wb_libraw / wb_libraw[1], [2.0, 1.0, 1.6], rtol=1e-3)


def test_sixteen_bit_dng_scales_by_a_power_of_two(tmp_path):
    irr = np.random.default_rng(2).lognormal(8, 3, (32, 32)).astype(np.float32)
    irr[0, 0] = 3.0e8  # a bright highlight: beyond half's range unless scaled
    lay = write_float_dng(tmp_path / "h.dng", _mosaic(irr, "RGGB"), bits=16)
    tags, data = _tags(tmp_path / "h.dng")
    assert data.dtype == np.float16 and tags[258] == 16 and tags[339] == 3 and lay.exponent > 0
    assert f"2^{lay.exponent} =" in tags[270]
    back = data.astype(np.float64) * 2.0**lay.exponent
    normal = data.astype(np.float64) >= np.finfo(np.float16).tiny
    np.testing.assert_allclose(back[normal], irr[normal], rtol=2.0**-11)


def test_invalid_input_is_refused(tmp_path):
    irr = np.ones((32, 32), np.float32)
    with pytest.raises(InputError, match="Bayer"):
        write_float_dng(tmp_path / "a.dng", _mosaic(irr, "none"))
    bad = irr.copy()
    bad[3, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_float_dng(tmp_path / "b.dng", _mosaic(bad, "RGGB"))
    with pytest.raises(InputError, match="16 or 32"):
        dng_layout(irr, 24)
    write_float_dng(tmp_path / "c.dng", _mosaic(irr, "RGGB"))
    with pytest.raises(OutputExistsError, match="exists"):
        write_float_dng(tmp_path / "c.dng", _mosaic(irr, "RGGB"))
    assert not (tmp_path / "a.dng").exists() and not (tmp_path / "b.dng").exists()


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (4, 4), elements=st.floats(-1e3, 1e9, allow_nan=False)), st.sampled_from([16, 32]))
def test_layout_never_clips_and_fits_the_float(irr, bits):
    lay = dng_layout(irr, bits)
    top = max(irr.max(), 0.0)
    assert lay.white_level * lay.scale >= top and lay.white_level >= 1
    if bits == 16:
        assert top / lay.scale <= np.finfo(np.float16).max / 2
    else:
        assert lay.exponent == 0


@pytest.mark.skipif(shutil.which("darktable-cli") is None, reason="darktable-cli is not installed")
def test_darktable_develops_the_float_dng(merged, tmp_path):
    d, _, _ = merged
    out = tmp_path / "dt.tif"
    proc = subprocess.run(
        ["darktable-cli", str(d / "m.dng"), str(out), "--core", "--configdir", str(tmp_path / "cfg")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    lum = tifffile.imread(out).astype(np.float64).mean(axis=2)
    irr = read_exr(d / "m.exr").channels["irradiance"].astype(np.float64)
    assert lum.shape == irr.shape
    # The developed picture follows the scene: rank correlation of 2x2 means (one Bayer tile).
    h, w = irr.shape

    def tiles(a):
        return a.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3)).ravel()

    ranks = [np.argsort(np.argsort(tiles(a))) for a in (lum, irr)]
    assert np.corrcoef(*ranks)[0, 1] > 0.9


def test_format_option_and_help(merged, tmp_path):
    from tests.helpers.cli import run_cli

    _, _, frames = merged
    run_cli(
        "merge",
        *frames,
        "--camera",
        "camera-A",
        "-o",
        tmp_path / "x.raw",
        "--format",
        "dng",
        "--dng-bits",
        "16",
        check=True,
    )
    tags, data = _tags(tmp_path / "x.raw")
    assert data.dtype == np.float16 and tuple(tags[50706]) == (1, 4, 0, 0)
    text = run_cli("merge", "--help", check=True).stdout
    assert "--format" in text and "cannot hold sigma or nexp" in " ".join(text.split())
