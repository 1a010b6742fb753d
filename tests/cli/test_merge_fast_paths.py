"""The fast paths of the `hdrcap merge` command give the results of the plain formulas: EXR
channel checks by blocks, the total sigma by blocks, memory-mapped frames released after the
merge; and `hdrcap --help` / `hdrcap merge --help` do not import numpy."""

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from hdrcap.pipeline.io import exr as pexr  # its private block checks, on purpose: fast path vs formula
from hdrcap.pipeline.io import files as pfiles
from hdrcap.pipeline.io import raw as praw
from hdrcap.pipeline.merge.calibration_errors import add_in_quadrature
from tests.helpers.dng import write_test_dng

_FLOATS = hnp.arrays(
    np.float32,
    hnp.array_shapes(min_dims=2, max_dims=2, max_side=40),
    elements=st.floats(width=32, allow_nan=True, allow_infinity=True),
)


def _reference_range(arr):
    """min and max of |value| over finite non-zero values, from a boolean mask (the plain way)."""
    mag = np.abs(arr[np.isfinite(arr) & (arr != 0)].astype(np.float64))
    return (None, None) if mag.size == 0 else (float(mag.min()), float(mag.max()))


@settings(max_examples=200, deadline=None)
@given(_FLOATS)
def test_magnitude_range_equals_the_masked_reference(arr):
    assert pexr._magnitude_range(arr) == _reference_range(arr)


def test_magnitude_range_over_many_blocks_finds_extremes_anywhere():
    arr = np.full((700, 300), 2.0, np.float32)  # > 3 blocks
    arr[650, 299], arr[3, 0], arr[400, 7], arr[100, 100] = 7e4, 3e-6, np.nan, -np.inf
    assert pexr._magnitude_range(arr) == (float(np.float32(3e-6)), 7e4)
    assert pexr._magnitude_range(np.zeros((500, 500), np.float32)) == (None, None)


@settings(max_examples=200, deadline=None)
@given(_FLOATS)
def test_whole_uint32_equals_the_plain_check(arr):
    a64 = arr.astype(np.float64)
    expected = bool(np.isfinite(a64).all() and (a64 >= 0).all() and (a64 <= 2**32 - 1).all())
    expected = expected and bool((a64 == np.round(a64)).all())
    assert pexr._whole_uint32(arr) == expected


@pytest.mark.parametrize(
    ("arr", "whole"),
    [
        (np.array([[0, 3, 65535]], np.uint16), True),
        (np.array([[0, -1]], np.int32), False),
        (np.array([[0, 2**33]], np.int64), False),
        (np.array([[True, False]]), True),
        (np.array([[0.0, 5.0, 4e9]]), True),
        (np.array([[0.0, 5.5]]), False),
        (np.array([[np.nan]]), False),
        (np.array([[-0.0, np.inf]]), False),
    ],
)
def test_whole_uint32_by_dtype(arr, whole):
    assert pexr._whole_uint32(arr) is whole


@settings(max_examples=100, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        st.tuples(st.integers(1, 600), st.integers(1, 5)),
        elements=st.floats(0, 2.0**120, width=32),
    ),
    st.integers(0, 2),
    st.integers(1, 300),
)
def test_add_in_quadrature_by_blocks_equals_the_full_array_formula(sig, n_terms, rows):
    rng = np.random.default_rng(n_terms)
    terms = [(rng.random(sig.shape) * 1e3).astype(np.float32) for _ in range(n_terms)]
    expected = np.square(sig, dtype=np.float64)
    for t in terms:
        expected = expected + np.square(t, dtype=np.float64)
    expected = np.sqrt(expected).astype(np.float32)
    got = sig.copy()
    add_in_quadrature(got, *terms, None, rows=rows)
    assert got.tobytes() == expected.tobytes()  # bit-identical, not merely close


def _resident_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="resident set of file mappings: Linux")
def test_released_frames_leave_memory_and_stay_readable(tmp_path):
    data = np.random.default_rng(1).integers(64, 4096, (2048, 4096), dtype=np.uint16)  # 16 MB
    path = write_test_dng(tmp_path / "f.dng", data)
    frame = praw.read_frame(path)
    assert np.array_equal(frame.data, data)  # every page touched: resident
    before = _resident_mb()
    assert pfiles.release_mapped_pages([frame.data, frame.data[:10]]) >= data.nbytes  # one mapping, once
    after = _resident_mb()
    assert before - after > 0.75 * data.nbytes / 2**20
    assert np.array_equal(frame.data, data)  # read again from the file
    plain = data.copy()
    assert pfiles.release_mapped_pages([plain]) == 0
    assert np.array_equal(plain, data)


@pytest.mark.parametrize("args", [["--help"], ["merge", "--help"]])
def test_help_does_not_import_numpy(args):
    code = (
        "import sys\n"
        "from hdrcap.cli import main\n"
        f"rc = main({args!r})\n"
        "heavy = sorted(m for m in ('numpy', 'scipy', 'numba', 'OpenEXR', 'tifffile') if m in sys.modules)\n"
        "print('RESULT', rc, heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "Usage: hdrcap" in out
    assert out.strip().splitlines()[-1] == "RESULT 0 []", f"`hdrcap {' '.join(args)}`: {out.splitlines()[-1]}"


_MERGE_DIGEST = """
import hashlib, sys
from hdrcap.api import simulate
from hdrcap.pipeline.merge.accumulator import merge_arrays
warm = sys.argv[1] == "warm"
if warm:
    from hdrcap.pipeline.merge.files import start_warm_up
    thread = start_warm_up()  # the merge below races it, as in hdrcap merge
    assert start_warm_up() is thread  # once per process (the command and merge_files both ask)
sim = simulate("camera-A", "hdr", [0.001, 0.01, 0.1], seed=5, shape=(24, 36), darks=True)
res = merge_arrays(list(sim.frames), [0.001, 0.01, 0.1], sim.calibration, list(sim.darks))
if warm:
    thread.join(timeout=300)
    assert not thread.is_alive()
h = hashlib.sha256(b"".join(getattr(res, n).tobytes() for n in ("irradiance", "sigma", "nexp")))
print(h.hexdigest())
"""


def test_kernel_warm_up_thread_racing_the_merge_changes_nothing():
    digests = [
        subprocess.run([sys.executable, "-c", _MERGE_DIGEST, mode], capture_output=True, text=True, check=True).stdout
        for mode in ("warm", "cold")
    ]
    assert len(digests[0].strip()) == 64
    assert digests[0] == digests[1]


def test_a_merge_without_a_terminal_imports_no_progress_bar(tmp_path):
    """tqdm (40 ms of imports) only where it shows a bar: stderr a terminal."""
    from tests.helpers.cli import run_cli

    run_cli("simulate", "--size", "32x24", "--times", "0.01", "0.1", "--out", tmp_path, check=True)
    frames = sorted(str(p) for p in tmp_path.glob("frame_*.dng"))
    code = (
        "import sys\n"
        "from hdrcap.cli import main\n"
        f"rc = main(['merge', *{frames!r}, '--camera', 'camera-B', '-o', {str(tmp_path / 'o.exr')!r}])\n"
        "print('RESULT', rc, 'tqdm' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "RESULT 0 False"
