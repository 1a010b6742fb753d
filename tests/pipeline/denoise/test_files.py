"""The one path of denoising (``pipeline.denoise.files``): the Python API and ``hdrcap denoise`` write
the same file, and the tiled filter gives the in-memory result bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import hdrcap
from hdrcap.cli import main
from hdrcap.pipeline.denoise.files import DenoiseOptions, denoise_file, denoise_result
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr, stored_precisions

SHAPE = (64, 96)


@pytest.fixture(scope="module")
def merged() -> hdrcap.HdrResult:
    """A merge of a simulated camera-B bracket with saturated photosites (nexp 0, quality 16) and
    a calibration part of sigma, so that every channel of the schema is there (seeded)."""
    sim = hdrcap.simulate("camera-B", "hdr", [0.01, 0.1, 1.0], seed=3, shape=SHAPE, darks=True, decades=6)
    hdr = hdrcap.merge(sim.frames, sim.times, calibration=sim.calibration, cfa_pattern=sim.cfa_pattern)
    assert hdr.quality is not None and (hdr.nexp == 0).sum() > 100
    return hdr.replace(sigma_calibration=(0.01 * np.abs(hdr.irradiance) + 0.5).astype(np.float32))


def _assert_same_file(p1, p2, *, source_file: bool = False) -> None:
    """The same channels (as stored, bit for bit) and header; with ``source_file``, ``p2`` alone
    names its input under ``denoise.source_file``."""
    assert stored_precisions(p1) == stored_precisions(p2)
    a, b = read_exr(p1, native=True), read_exr(p2, native=True)
    assert set(a.channels) == set(b.channels) == {"irradiance", "sigma", "sigma_calibration", "nexp", "quality"}
    for name, arr in a.channels.items():
        assert arr.dtype == b.channels[name].dtype and arr.tobytes() == b.channels[name].tobytes(), name
    header = dict(b.header)
    if source_file:
        entry = dict(header["denoise"])
        assert "source_file" not in a.header["denoise"] and entry.pop("source_file")
        header["denoise"] = entry
    assert a.header == header


@pytest.mark.parametrize(
    ("options", "args"),
    [
        ({}, []),
        (
            {"layout": "mono", "method": "constant", "bandwidth": 200.0, "radius": 1},
            ["--layout", "mono", "--method", "constant", "--bandwidth", "200", "--radius", "1"],
        ),
    ],
)
def test_api_and_command_write_the_same_file(merged, tmp_path, capsys, options, args):
    # a file holding the result exactly (float sigma): the API filters what the command reads
    exact = merged.write(tmp_path / "exact.exr", sigma_precision="float")
    p1 = hdrcap.denoise(merged, **options).write(tmp_path / "api.exr")
    assert main(["denoise", str(exact), "-o", str(tmp_path / "cli.exr"), *args]) == 0
    _assert_same_file(p1, tmp_path / "cli.exr", source_file=True)
    # the merge as `hdrcap merge` stores it (half sigma where it fits), read back by the API
    stored = merged.write(tmp_path / "merged.exr")
    p3 = hdrcap.denoise(hdrcap.read_exr(stored), **options).write(tmp_path / "api_read.exr")
    assert main(["denoise", str(stored), "-o", str(tmp_path / "cli_read.exr"), *args, "--chunks", "8"]) == 0
    _assert_same_file(p3, tmp_path / "cli_read.exr", source_file=True)
    capsys.readouterr()
    assert read_exr(p1).header["denoise"]["settings"] == DenoiseOptions(**options).settings(merged.header).to_dict()


@pytest.mark.parametrize("rows", [2, 8, 30])
def test_tiled_is_the_in_memory_result(merged, tmp_path, rows):
    src = merged.write(tmp_path / "merged.exr")
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    mem, fig_mem = denoise_file(src)
    tiled, fig_tiled = denoise_file(src, rows=rows, scratch_dir=scratch)
    assert list(mem.channels()) == list(tiled.channels()) == list(merged.channels())
    for name, arr in mem.channels().items():
        other = tiled.channels()[name]
        assert arr.dtype == other.dtype and arr.tobytes() == np.asarray(other).tobytes(), name
        assert not other.flags.writeable  # a read-only map of a temporary file
    assert mem.header == tiled.header and mem.header["denoise"]["source_file"] == str(src)
    assert not list(scratch.iterdir())  # the temporary files are gone, their maps still valid
    assert fig_mem.chunk_rows is None and (fig_tiled.chunk_rows, fig_tiled.tiles) == (
        max(rows, 4),
        -(-SHAPE[0] // max(rows, 4)),
    )
    for key in ("median_relative_sigma_before", "median_relative_sigma_after", "unchanged_nexp0"):
        assert getattr(fig_mem, key) == getattr(fig_tiled, key), key
    assert fig_mem.unchanged_nexp0 == int(((merged.nexp == 0) | (merged.quality != 0)).sum())
    assert fig_mem.median_relative_sigma_after < 0.7 * fig_mem.median_relative_sigma_before
    # the one writer: the same file from either
    _assert_same_file(mem.write(tmp_path / "mem.exr"), tiled.write(tmp_path / "tiled.exr"))


def test_in_memory_result_shares_the_unfiltered_channels(merged):
    out = denoise_result(merged, DenoiseOptions(radius=1), name="x")
    assert out.nexp is merged.nexp and out.quality is merged.quality
    assert out.sigma_calibration is merged.sigma_calibration
    assert out.header["denoise"]["layout_source"] == "header cfa_pattern"
    assert out.header["denoise"]["input_sigma"] == merged.header["sigma"] != out.header["sigma"]
    assert "bias" in out.header["sigma"] and merged.header["denoise"] is None
    assert out.header["denoise"]["unchanged_nexp0"] == int((merged.nexp == 0).sum())
    assert not np.array_equal(out.irradiance, merged.irradiance)


def test_bad_requests_refused(merged, tmp_path):
    with pytest.raises(InputError, match="layout must be auto, cfa or mono"):
        DenoiseOptions(layout="rgb")
    with pytest.raises(InputError, match="no such file"):
        denoise_file(tmp_path / "missing.exr")
    src = merged.write(tmp_path / "merged.exr")
    with pytest.raises(InputError, match="even number of rows"):
        denoise_file(src, rows=5)
    with pytest.raises(InputError, match="needs a bandwidth"):
        denoise_file(src, DenoiseOptions(method="constant"))
