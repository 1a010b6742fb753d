"""What ``hdrcap denoise`` stores, by the merge's storage rules (``pipeline.schema``, the one writer
``write_result``): the filtered irradiance bit for bit as float32, the sigma channels by
``--sigma-precision`` (half: at most 2**-11 relative; a half channel stays half, bit for bit), nexp
and quality as uint with their values exact; in memory and tile by tile alike."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from hdrcap.cli import main
from hdrcap.pipeline.denoise.filter import DenoiseSettings, denoise
from hdrcap.pipeline.io.exr import HALF_RELATIVE_ERROR, read_exr, stored_precisions, write_exr

SHAPE = (40, 36)


@pytest.fixture(scope="module")
def merged(tmp_path_factory):
    """A merge-like EXR stored as `hdrcap merge` stores it: irradiance float, sigma half,
    sigma_calibration float (values below half's range), nexp and quality uint (seeded)."""
    rng = np.random.default_rng(11)
    X = rng.uniform(10.0, 5e4, SHAPE).astype(np.float32)
    sigma = np.sqrt(X + 25.0).astype(np.float32)
    irr = (X + rng.normal(size=SHAPE) * sigma).astype(np.float32)
    nexp = np.full(SHAPE, 3, np.float32)
    nexp[5:8, 4:9] = 0
    quality = np.zeros(SHAPE, np.float32)
    quality[20, 7] = 4
    quality[0, 14] = 4  # a defect with nexp > 0 (a foreign file) where the median's subsample looks
    sig_cal = rng.uniform(1e-6, 1e-3, SHAPE).astype(np.float32)
    channels = {"irradiance": irr, "sigma": sigma, "sigma_calibration": sig_cal, "nexp": nexp, "quality": quality}
    path = tmp_path_factory.mktemp("dns") / "merged.exr"
    precision = {"sigma": "half", "nexp": "uint", "quality": "uint"}
    write_exr(path, channels, {"cfa_pattern": "RGGB"}, precision=precision)
    return path


def _cli(src, dst, *args):
    assert main(["denoise", str(src), "-o", str(dst), "--json", *map(str, args)]) == 0


def exr_pixel_types(path):
    """Channel name -> "float", "half" or "uint", as the file stores it."""
    return stored_precisions(path)


@pytest.mark.parametrize("chunks", [[], ["--chunks", 8]])
def test_stored_channels(merged, tmp_path, capsys, chunks):
    src = read_exr(merged)
    ch = src.channels
    ref = denoise(ch["irradiance"], ch["sigma"], ch["nexp"], DenoiseSettings(), quality=ch["quality"])
    dst = tmp_path / "out.exr"
    _cli(merged, dst, *chunks)
    capsys.readouterr()
    assert exr_pixel_types(dst) == {
        "irradiance": "float",
        "sigma": "half",
        "sigma_calibration": "float",
        "nexp": "uint",
        "quality": "uint",
    }
    out = read_exr(dst).channels
    assert out["irradiance"].tobytes() == ref.irradiance.tobytes()
    for name in ("sigma_calibration", "nexp", "quality"):
        assert out[name].tobytes() == ch[name].tobytes(), name
    rel = np.abs(out["sigma"].astype(np.float64) / ref.sigma - 1.0)
    assert rel.max() <= HALF_RELATIVE_ERROR
    assert rel.max() > 0  # it is stored as half: not the float values
    # --sigma-precision float: the filter's sigma bit for bit
    _cli(merged, dst, "--force", "--sigma-precision", "float", *chunks)
    capsys.readouterr()
    assert exr_pixel_types(dst)["sigma"] == "float"
    assert read_exr(dst).channels["sigma"].tobytes() == ref.sigma.tobytes()
    # another compression: the same pixels, the file says which
    _cli(merged, dst, "--force", "--exr-compression", "rle", *chunks)
    capsys.readouterr()
    assert read_exr(dst).channels["irradiance"].tobytes() == ref.irradiance.tobytes()
    with OpenEXR.File(str(dst), header_only=True) as f:
        assert f.header()["compression"] == OpenEXR.RLE_COMPRESSION


def test_float_input_by_the_schema(tmp_path, capsys):
    """A file whose channels are all float (an old merge, a foreign file): irradiance stays float, a
    filtered sigma above half's range (>= 1e6 / 5 e-/s here) stays float under auto, nexp is stored
    as uint with its whole values exact. (Before the one writer the carried channels kept the
    input's float storage; the schema stores nexp as uint, so a non-whole nexp is refused.)"""
    rng = np.random.default_rng(2)
    irr = rng.uniform(1e5, 2e5, SHAPE).astype(np.float32)
    ch = {"irradiance": irr, "sigma": np.full(SHAPE, 1e6, np.float32), "nexp": np.full(SHAPE, 2.0, np.float32)}
    src = tmp_path / "in.exr"
    write_exr(src, ch, {"cfa_pattern": "RGGB"})
    dst = tmp_path / "out.exr"
    _cli(src, dst)
    capsys.readouterr()
    assert exr_pixel_types(dst) == {"irradiance": "float", "sigma": "float", "nexp": "uint"}
    np.testing.assert_array_equal(read_exr(dst).channels["nexp"], 2.0)
    ch["nexp"][3, 4] = 2.5
    write_exr(src, ch, {"cfa_pattern": "RGGB"}, force=True)
    code = main(["denoise", str(src), "-o", str(tmp_path / "bad.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "nexp" in err and "whole numbers" in err and err.count("\n") == 1, err
    assert not (tmp_path / "bad.exr").exists()


@pytest.mark.parametrize("chunks", [[], ["--chunks", 8]])
def test_half_sigma_calibration_stays_half(tmp_path, capsys, chunks):
    """A half sigma_calibration (what `hdrcap merge` writes where it fits) stays half, bit for bit,
    under auto and half; --sigma-precision float stores both sigma channels as float, values exact."""
    rng = np.random.default_rng(7)
    irr = rng.uniform(100.0, 1e4, SHAPE).astype(np.float32)
    ch = {
        "irradiance": irr,
        "sigma": np.sqrt(irr + 25.0),
        "sigma_calibration": (0.01 * irr).astype(np.float16),
        "nexp": np.full(SHAPE, 3.0, np.float32),
    }
    src = tmp_path / "in.exr"
    write_exr(src, ch, {"cfa_pattern": "RGGB"}, precision={"sigma": "half", "sigma_calibration": "half"})
    stored = read_exr(src, native=True).channels["sigma_calibration"]
    for precision, kind in (("auto", "half"), ("half", "half"), ("float", "float")):
        dst = tmp_path / f"{precision}.exr"
        _cli(src, dst, "--sigma-precision", precision, *chunks)
        capsys.readouterr()
        assert exr_pixel_types(dst)["sigma_calibration"] == kind, precision
        out = read_exr(dst, native=True).channels["sigma_calibration"]
        assert out.astype(np.float16).tobytes() == stored.tobytes(), precision


def test_read_exr_float_channels_not_copied_and_exact(merged):
    """read_exr keeps the decoded float arrays (they own their memory) and converts half and uint
    exactly: the values OpenEXR decodes."""
    img = read_exr(merged)
    with OpenEXR.File(str(merged)) as f:
        raw = {k: c.pixels.copy() for k, c in f.channels().items()}
    for name, arr in img.channels.items():
        assert arr.dtype == np.float32 and arr.flags["C_CONTIGUOUS"] and arr.flags["WRITEABLE"]
        np.testing.assert_array_equal(arr, raw[name].astype(np.float32))
        assert arr.flags["OWNDATA"] or name != "irradiance"


def test_median_subsample_same_in_memory_and_tiled(merged, tmp_path, capsys, monkeypatch):
    """Above the sample limit (lowered here to 100 photosites) both paths report the median over
    the same regular subsample, and it is the subsample's median computed independently."""
    import json

    import hdrcap.pipeline.denoise.files as df

    monkeypatch.setattr(df, "MEDIAN_SAMPLES", 100)
    infos = []
    for extra in ([], ["--chunks", 8]):
        _cli(merged, tmp_path / f"o{len(infos)}.exr", *extra)
        infos.append(json.loads(capsys.readouterr().out.strip().splitlines()[-1]))
    ch = read_exr(merged).channels
    step = ch["irradiance"].size // 100
    ok = ((ch["nexp"] > 0) & (ch["quality"] == 0)).ravel()[::step]
    expected = np.median(ch["sigma"].ravel()[::step][ok] / np.abs(ch["irradiance"].ravel()[::step][ok]))
    for info in infos:
        assert info["median_relative_sigma_before"] == pytest.approx(expected, rel=1e-6)
    assert infos[0]["median_relative_sigma_after"] == infos[1]["median_relative_sigma_after"]
