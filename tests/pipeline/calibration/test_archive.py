"""The calibration file: maps stored uncompressed and memory-mapped on load; old compressed files load."""

from __future__ import annotations

import io
import zipfile

import numpy as np

from hdrcap.pipeline.calibration import load_calibration, save_calibration
from hdrcap.pipeline.params import Calibration, SensorParams


def _calibration(shape=(40, 60), seed=3):
    rng = np.random.default_rng(seed)
    return Calibration(
        params=SensorParams(g=0.5, mu_R=64.0, sigma2_R=4.0, v_sat=4000.0, white_level=4095.0, dark_current=1.0),
        prnu=(1 + 0.01 * rng.standard_normal(shape)).astype(np.float32),
        bias_map=(64 + rng.standard_normal(shape)).astype(np.float32),
        dark_current_map=np.abs(1 + 0.1 * rng.standard_normal(shape)).astype(np.float32),
        defect_map=(rng.random(shape) < 0.01).astype(np.uint8),
    )


def test_maps_are_stored_uncompressed_and_memory_mapped(tmp_path):
    cal = _calibration()
    path = save_calibration(tmp_path / "c.cal", cal)
    with zipfile.ZipFile(path) as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
    got = load_calibration(path)
    for name in ("prnu", "bias_map", "dark_current_map", "defect_map"):
        arr = getattr(got, name)
        assert isinstance(arr, np.memmap), name
        np.testing.assert_array_equal(arr, getattr(cal, name))
    assert got.defect_map.dtype == np.uint8
    before = path.read_bytes()
    got.prnu[0, 0] = 7.0  # copy-on-write: this process's copy only
    assert path.read_bytes() == before
    assert load_calibration(path).prnu[0, 0] == cal.prnu[0, 0]


def test_compressed_files_of_earlier_versions_still_load(tmp_path):
    cal = _calibration()
    path = save_calibration(tmp_path / "c.cal", cal)
    old = tmp_path / "old.cal"
    with np.load(path) as z:
        arrays = {k: np.asarray(z[k]) for k in z.files}
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    old.write_bytes(buf.getvalue())
    got = load_calibration(old)
    np.testing.assert_array_equal(got.prnu, cal.prnu)
    np.testing.assert_array_equal(got.dark_current_map, cal.dark_current_map)
    assert got.params == cal.params


def _verdict(name, arr, params):
    """What load_calibration's value checks say of ``arr``: None or the error message."""
    # private on purpose: the elementwise check itself, against its shortcut on the extremes
    from hdrcap.pipeline.calibration.archive import _check_map_range
    from hdrcap.pipeline.errors import InputError

    if not np.all(np.isfinite(arr)):
        return "not finite"
    try:
        _check_map_range("c.cal", name, arr, params)
    except InputError as err:
        return str(err)
    return None


def test_map_checks_on_the_extremes_say_what_they_say_on_the_whole_map():
    """The float maps are checked on their least and largest value alone: the same verdict (and
    message) as the elementwise checks, at the thresholds too (float32 rounding of the bounds)."""
    from hdrcap.pipeline.calibration.archive import _extremes  # private on purpose: the shortcut

    params = _calibration().params
    rng = np.random.default_rng(7)
    edges = [0.0, -0.0, 1e-2, 1e2, 4095.0, 1e12, np.nan, np.inf, -np.inf, 1.0, -1.0, 5e-3, 2e2, 5000.0, 3e12]
    names = ("prnu", "prnu_stderr", "bias_map", "bias_map_stderr", "dark_current_map", "dark_current_map_stderr")
    seen = set()
    for dtype in (np.float32, np.float64):
        tricky = [
            v for e in edges for v in (e, np.nextafter(dtype(e), dtype(-np.inf)), np.nextafter(dtype(e), dtype(np.inf)))
        ]
        for name in names:
            for _ in range(60):
                arr = (1 + 0.01 * rng.standard_normal((5, 7))).astype(dtype)
                k = rng.integers(0, 3)
                arr.flat[rng.choice(arr.size, k, replace=False)] = rng.choice(np.asarray(tricky, dtype), k)
                whole = _verdict(name, arr, params)
                assert _verdict(name, _extremes(arr), params) == whole, (name, dtype, arr)
                seen.add(whole is None)
    assert seen == {True, False}
    defects = (rng.random((5, 7)) < 0.3).astype(np.uint8)
    assert _extremes(defects) is defects and _extremes(np.zeros((0, 3), np.float32)).size == 0
