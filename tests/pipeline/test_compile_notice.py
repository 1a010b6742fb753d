"""A process that compiles hdrcap's numba kernels (a cold cache) says so once on stderr; one that
loads them from numba's cache says nothing about it."""

import os
import subprocess
import sys

import pytest

from hdrcap.pipeline._numba_target import COMPILE_NOTICE
from tests.helpers.cli import run_cli

_SMALL_KERNEL = (
    "import numpy as np\n"
    "from hdrcap.pipeline.calibration import _kernels as k\n"
    "x = np.arange(6.0)\n"
    "print(k.masked_moments(x, x > 1, 0.0)[0])\n"
    "print(k.masked_moments(x.astype(np.float32), x > 2, 0.0)[0])\n"  # a second compilation
)


def _python(code, cache):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)


def test_cold_cache_says_it_once_and_a_warm_one_not_at_all(tmp_path):
    cold = _python(_SMALL_KERNEL, tmp_path / "cache")
    assert cold.returncode == 0, cold.stderr
    assert cold.stdout.split() == ["4", "3"]
    assert cold.stderr.count(COMPILE_NOTICE) == 1
    warm = _python(_SMALL_KERNEL, tmp_path / "cache")
    assert warm.returncode == 0, warm.stderr
    assert "compil" not in warm.stderr


def test_a_user_function_compiled_in_the_same_process_is_not_announced(tmp_path):
    code = "from hdrcap.pipeline._numba_target import numba\nprint(numba.njit(lambda a: a + 1)(1))\n"
    proc = _python(code, tmp_path / "cache")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "2"
    assert COMPILE_NOTICE not in proc.stderr


@pytest.mark.slow
def test_warm_up_on_a_cold_cache_compiles_what_merges_load(tmp_path):
    """`hdrcap warm-up` on a cold cache prints the line once; merges with and without dark frames
    then load every kernel they need (nothing said about compiling), as does warm-up again."""
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    run_cli("simulate", "--size", "32x24", "--times", "0.01", "0.1", "--darks", "--out", tmp_path, check=True)
    frames = sorted(str(p) for p in tmp_path.glob("frame_*.dng"))
    darks = sorted(str(p) for p in tmp_path.glob("dark_*.dng"))
    cold = run_cli("warm-up", "--json", env=env, check=True)
    assert cold.stderr.count(COMPILE_NOTICE) == 1
    assert "hdrcap warm-up" in COMPILE_NOTICE  # the line names the command that compiles ahead
    for extra in (("--darks", *darks), ()):
        merge = run_cli("merge", *frames, *extra, "--camera", "camera-B", "-o", tmp_path / "o.exr", "--force", env=env)
        assert merge.returncode == 0, merge.stderr
        assert "compil" not in merge.stderr
    again = run_cli("warm-up", env=env, check=True)
    assert "compil" not in again.stderr
    assert "merge kernels ready" in again.stdout
