"""``hdrcap merge --chunks``: the tiled merge equals the in-memory merge bit for bit (every channel
and the header), with a calibration estimated from simulated frames, every dark strategy, the
self-calibration, spilled (non-DNG) inputs and the float32/float64 choice made per frame."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdrcap.cli import main
from hdrcap.experiments.calibrated import calibrated_sensor
from hdrcap.mock_camera.dng import write_dng
from hdrcap.mock_camera.scenes import make_scene
from hdrcap.mock_camera.sensor import preset
from hdrcap.pipeline.calibration import save_calibration
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr
from hdrcap.pipeline.merge.tiled import RowFile, chunk_rows_for, parse_memory, row_source
from hdrcap.pipeline.params import ShutterTable

SHAPE = (98, 128)  # 98 rows: the last tile of 20 rows is short
TIMES = (0.001, 0.004, 0.016, 0.064)


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    """DNG bracket (4 frames, a matched dark frame each, one master dark of 0.064 s) of a
    realistic camera-A (hot photosites, dark current) and its calibration estimated from
    simulated frames, saved as a file."""
    root = tmp_path_factory.mktemp("tiled")
    spec = preset("camera-A", realistic=True)
    sensor, cal = calibrated_sensor(spec, 11, SHAPE)
    save_calibration(root / "cal.npz", cal)
    table = ShutterTable(TIMES, (1.03, 1.0, 0.99, 1.0), (0.002, 0.0, 0.001, 0.001), 0.004, (3, 3, 3, 3))
    save_calibration(root / "cal_shutter.npz", cal.replace(shutter=table))
    X = make_scene("hdr", SHAPE, 4.0, 1e5)
    rng = np.random.default_rng(7)
    paths = {"frames": [], "darks": [], "png": []}
    for i, t in enumerate(TIMES):
        for kind, dark in (("frames", False), ("darks", True)):
            p = root / f"{kind}_{i}.dng"
            with open(p, "wb") as fh:
                write_dng(
                    fh,
                    sensor.expose(X, t, dark=dark, rng=rng),
                    exposure_time=t,
                    iso=spec.iso,
                    black_level=spec.mu_R,
                    white_level=spec.white_level,
                    model=spec.model,  # the camera the preset names (the merge checks it)
                )
            paths[kind].append(p)
    master = root / "master.dng"
    with open(master, "wb") as fh:
        write_dng(
            fh,
            sensor.expose(0.0, 0.064, dark=True, rng=rng),
            exposure_time=0.064,
            iso=spec.iso,
            black_level=spec.mu_R,
            white_level=spec.white_level,
        )
    from PIL import Image

    for i, t in enumerate(TIMES):  # 16-bit PNGs: not DNG, decoded whole and spilled
        p = root / f"png_{i}.png"
        Image.fromarray(sensor.expose(X, t, rng=rng).astype(np.uint16)).save(p)
        paths["png"].append(p)
    return {"root": root, "cal": root / "cal.npz", "cal_shutter": root / "cal_shutter.npz", "master": master, **paths}


def _merge(tmp, name, args, capsys):
    out = tmp / f"{name}.exr"
    code = main(["merge", *map(str, args), "-o", str(out), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return read_exr(out), json.loads(captured.out.strip().splitlines()[-1]), captured.err


def _assert_identical(a, b, channels=("irradiance", "sigma", "nexp", "sigma_calibration", "quality")):
    """``b`` (tiled) equals ``a`` (in memory): every channel bit for bit, and the header but for
    the tiling ``b`` records."""
    assert set(a.channels) == set(b.channels) == set(channels)
    for name in a.channels:
        assert a.channels[name].tobytes() == b.channels[name].tobytes(), name
    tiling = b.header["merge"].pop("tiling")
    assert "tiling" not in a.header["merge"] and tiling["rows"] >= 2 and tiling["tiles"] >= 1
    assert a.header == b.header


CASES = {
    "matched": lambda b: [*b["frames"], "--darks", *b["darks"], "--calibration", b["cal"]],
    "master-frames": lambda b: [
        *b["frames"],
        "--darks",
        *b["darks"],
        "--calibration",
        b["cal"],
        "--dark-strategy",
        "master",
        "--master-dark-frames",
        "8",
        "--sigma-precision",
        "float",
    ],
    "single-master": lambda b: [*b["frames"], "--master-dark", b["master"], "--calibration", b["cal"]],
    "model-nominal": lambda b: [*b["frames"], "--calibration", b["cal"], "--exposure-times", "nominal"],
    "self-calibrated": lambda b: [*b["frames"], "--darks", *b["darks"]],
    "shutter-table": lambda b: [*b["frames"], "--darks", *b["darks"], "--calibration", b["cal_shutter"]],
    # a preset's nominal parameters carry no standard errors: no sigma_calibration channel
    "preset-no-errors": lambda b: [*b["frames"], "--darks", *b["darks"], "--camera", "camera-A"],
    "png-spilled": lambda b: [*b["png"], "--times", *TIMES, "--calibration", b["cal"], "--saturation", "probabilistic"],
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_tiled_merge_is_the_in_memory_merge(bracket, tmp_path, capsys, monkeypatch, case):
    monkeypatch.setenv("HDRCAP_DATA_DIR", str(tmp_path / "data"))  # no calibration library entry
    args = CASES[case](bracket)
    ref, ref_info, _ = _merge(tmp_path, "mem", args, capsys)
    tiled, info, err = _merge(tmp_path, "tiled", [*args, "--chunks", "20"], capsys)
    if case == "preset-no-errors":
        _assert_identical(ref, tiled, ("irradiance", "sigma", "nexp", "quality"))
        assert ref.header["merge"]["calibration_error"]["included"] == []
    else:
        _assert_identical(ref, tiled)
    assert info["tiles"] == 5 and info["chunk_rows"] == 20
    assert {k: v for k, v in info.items() if k not in ("seconds", "output", "tiles", "chunk_rows")} == {
        k: v for k, v in ref_info.items() if k not in ("seconds", "output")
    }
    assert ("decodes each such file whole" in err) == (case == "png-spilled")
    assert any(ref.header["merge"]["shutter_table"]["applied"]) == (case == "shutter-table")


def test_memory_budget_tiles_automatically(bracket, tmp_path, capsys):
    args = [*bracket["frames"], "--darks", *bracket["darks"], "--calibration", bracket["cal"]]
    ref, _, _ = _merge(tmp_path, "mem", args, capsys)
    tiled, info, _ = _merge(tmp_path, "auto", [*args, "--memory-budget", "1MB"], capsys)
    assert info["chunk_rows"] == 2 and info["tiles"] == SHAPE[0] // 2
    _assert_identical(ref, tiled)
    _, info, _ = _merge(tmp_path, "big", [*args, "--memory-budget", "64G"], capsys)
    assert "chunk_rows" not in info


def test_weight_precision_is_chosen_for_the_whole_frame(bracket, tmp_path, capsys, monkeypatch):
    """A tile whose own extrema would allow float32 weights where the whole frame does not is
    merged again with the whole frame's choice (here: a rule on the bias map's maximum that
    half of the tiles pass)."""
    from hdrcap.pipeline.merge import accumulator as pm
    from hdrcap.pipeline.merge.precision import extrema

    def rule(self, values, darks, master):
        return extrema(self.maps.bias)[1] < limit

    from hdrcap.pipeline.calibration import load_calibration

    bias = np.asarray(load_calibration(bracket["cal"]).bias_map)
    limit = float(np.median([bias[r : r + 20].max() for r in range(0, SHAPE[0], 20)]))
    # private on purpose: the precision rule is replaced by one that half of the tiles pass
    monkeypatch.setattr(pm.MergeAccumulator, "_single_precision_safe", rule)
    args = [*bracket["frames"], "--darks", *bracket["darks"], "--calibration", bracket["cal"]]
    ref, _, _ = _merge(tmp_path, "mem", args, capsys)
    tiled, _, _ = _merge(tmp_path, "tiled", [*args, "--chunks", "20"], capsys)
    assert ref.header["merge"]["weights_precision"] == "float64"
    _assert_identical(ref, tiled)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--chunks", "7"], "even number of rows"),
        (["--chunks", "8", "--weighting", "debevec-malik"], "tiled merges use --weighting optimal"),
        (["--chunks", "8", "--format", "dng"], "tiled merges write EXR"),
        (["--memory-budget", "lots"], "memory size 'lots'"),
    ],
)
def test_tiled_merge_refuses(bracket, tmp_path, capsys, extra, message):
    code = main(["merge", *map(str, bracket["frames"]), "--camera", "camera-A", "-o", str(tmp_path / "x.exr"), *extra])
    err = capsys.readouterr().err
    assert code != 0 and message in err and "Traceback" not in err


@settings(max_examples=25, deadline=None)
@given(
    h=st.integers(1, 9),
    w=st.integers(1, 7),
    top=st.integers(0, 3),
    left=st.integers(0, 3),
    r0=st.integers(0, 12),
    n=st.integers(0, 12),
)
def test_row_file_reads_the_rows_of_a_mapped_window(tmp_path_factory, h, w, top, left, r0, n):
    """Rows of a window of a memory-mapped array (as a cropped DNG's active area) read from the
    file equal the window's rows; an in-memory array is spilled and reads back the same."""
    full = np.arange((h + top) * (w + left), dtype=np.uint16).reshape(h + top, w + left)
    path = tmp_path_factory.mktemp("rows") / "a.bin"
    full.tofile(path)
    window = np.memmap(path, np.uint16, mode="c", shape=full.shape).view(np.ndarray)[top:, left:]
    src, spilled = row_source(window, path.parent, "w")
    assert not spilled and src.path == str(path)
    assert np.array_equal(src.rows(r0, r0 + n), window[r0 : r0 + n])
    assert np.array_equal(src.mapped(), window)
    copy, spilled = row_source(np.array(window), path.parent, "c")
    assert spilled and np.array_equal(copy.rows(r0, r0 + n), window[r0 : r0 + n])


def test_row_file_writes_rows(tmp_path):
    out = RowFile.create(tmp_path / "o.bin", (5, 3), np.float32)
    out.write(2, np.ones((2, 3)))
    assert np.array_equal(out.rows(0, 5).sum(axis=1), [0, 0, 3, 3, 0])


def test_memory_sizes():
    assert parse_memory("2GB") == 2 * 2**30 and parse_memory("1500M") == 1500 * 2**20
    assert parse_memory("512MiB") == 512 * 2**20 and parse_memory("3e9") == 3_000_000_000
    for bad in ("", "-1G", "0", "2 XB", "nan"):
        with pytest.raises(InputError):
            parse_memory(bad)
    # a tile's working set stays within half of what the budget leaves after the baseline
    rows = chunk_rows_for(2 * 2**30, 10_000, 8, 3)
    assert rows % 2 == 0 and 100 <= rows <= 1000
