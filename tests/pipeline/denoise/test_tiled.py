"""``hdrcap denoise --chunks``: overlapping tiles give the whole-image filter bit for bit (tile
borders invisible), for both layouts, several reaches and tile heights, with lower bounds and
defects in the image."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdrcap.cli import main
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.pipeline.denoise.filter import DenoiseSettings, support_depth
from hdrcap.pipeline.io.exr import ExrRows, read_exr, read_exr_layout, write_exr

SHAPE = (90, 64)


@pytest.fixture(scope="module")
def merged(tmp_path_factory):
    """A merged-looking EXR: an HDR scene with Poisson-like noise, sigma, nexp (a saturated
    block: 0) and quality (a few defects), header with a CFA pattern (seeded)."""
    rng = np.random.default_rng(3)
    X = make_scene("edges", SHAPE, 3.0, 1e4).astype(np.float32)
    sigma = np.sqrt(X + 25.0).astype(np.float32)
    irr = (X + rng.normal(size=SHAPE) * sigma).astype(np.float32)
    nexp = np.full(SHAPE, 3, np.float32)
    nexp[40:46, 10:20] = 0
    quality = np.zeros(SHAPE, np.float32)
    quality[rng.integers(0, SHAPE[0], 20), rng.integers(0, SHAPE[1], 20)] = 4
    nexp[quality > 0] = 0
    path = tmp_path_factory.mktemp("dn") / "merged.exr"
    channels = {"irradiance": irr, "sigma": sigma, "nexp": nexp, "quality": quality}
    write_exr(path, channels, {"cfa_pattern": "RGGB", "sigma": "test"}, precision={"sigma": "half"})
    return path


def _denoise(src, out, args, capsys):
    code = main(["denoise", str(src), "-o", str(out), "--json", *map(str, args)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return read_exr(out), json.loads(captured.out.strip().splitlines()[-1])


@pytest.mark.parametrize(
    ("options", "rows"),
    [
        ([], 10),  # cfa, radius 2: reach 4 rows
        (["--layout", "mono", "--radius", "3"], 4),  # reach 3 rows, tiles barely taller
        (["--radius", "5", "--method", "constant", "--bandwidth", "200"], 6),  # reach 10 > a tile
        (["--radius", "0"], 2),
    ],
)
def test_tiled_denoise_is_the_whole_image_filter(merged, tmp_path, capsys, options, rows):
    ref, ref_info = _denoise(merged, tmp_path / "mem.exr", options, capsys)
    tiled, info = _denoise(merged, tmp_path / "tiled.exr", [*options, "--chunks", rows], capsys)
    assert set(ref.channels) == set(tiled.channels)
    for name in ref.channels:
        assert ref.channels[name].tobytes() == tiled.channels[name].tobytes(), name
    assert ref.header == tiled.header
    # bands at least as tall as the filter's reach; dask may merge a last band shorter than it
    assert info["chunk_rows"] == max(rows, 10 if "5" in options else rows)
    assert info["tiles"] in (-(-SHAPE[0] // info["chunk_rows"]), SHAPE[0] // info["chunk_rows"])
    assert info["unchanged_nexp0"] == ref_info["unchanged_nexp0"] > 0
    for key in ("median_relative_sigma_before", "median_relative_sigma_after"):  # under 1e6 photosites: all
        assert info[key] == ref_info[key]
    # the filter did something: borders of tiles are no place where it stopped
    assert not np.array_equal(tiled.channels["irradiance"], read_exr(merged).channels["irradiance"]) or "0" in options


def test_support_depth():
    assert support_depth(DenoiseSettings(radius=2, layout="cfa")) == 4
    assert support_depth(DenoiseSettings(radius=3, layout="mono")) == 3


def test_exr_rows_read_bands(merged):
    attrs, names, shape = read_exr_layout(merged)
    ref = read_exr(merged)
    assert shape == SHAPE and set(names) == set(ref.channels) and attrs["cfa_pattern"] == "RGGB"
    for name in names:
        rows = ExrRows(str(merged), name, shape)
        assert np.array_equal(rows.rows(7, 31), ref.channels[name][7:31])
        assert np.array_equal(rows[80:200, 3:9], ref.channels[name][80:, 3:9])


def test_tiled_denoise_refuses_odd_rows(merged, tmp_path, capsys):
    code = main(["denoise", str(merged), "-o", str(tmp_path / "x.exr"), "--chunks", "5"])
    err = capsys.readouterr().err
    assert code != 0 and "even number of rows" in err
