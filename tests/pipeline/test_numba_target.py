"""The numba compile-target tuning (pipeline._numba_target)."""

from __future__ import annotations

import llvmlite.binding as llvm

from hdrcap.pipeline._numba_target import configure  # the private module under test


def test_user_settings_win(monkeypatch):
    monkeypatch.setenv("NUMBA_CPU_FEATURES", "+sse2")
    assert configure() is None
    monkeypatch.delenv("NUMBA_CPU_FEATURES")
    monkeypatch.setenv("NUMBA_CPU_NAME", "generic")
    assert configure() is None
    monkeypatch.delenv("NUMBA_CPU_NAME")
    monkeypatch.setenv("HDRCAP_NUMBA_PREFER_256", "1")
    assert configure() is None


def test_host_features_plus_512_bit_vectors_only_with_avx512(monkeypatch):
    for name in ("NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME", "HDRCAP_NUMBA_PREFER_256"):
        monkeypatch.delenv(name, raising=False)
    host = llvm.get_host_cpu_features().flatten()
    got = configure()
    if "+avx512f" in host.split(","):
        assert got == host + ",-prefer-256-bit"
    else:
        assert got is None


def test_no_environment_change_and_wide_vectors_in_compiled_code():
    """Importing the kernels leaves os.environ alone, and on AVX-512 the code uses 512-bit registers."""
    import subprocess
    import sys

    code = (
        "import os; before = dict(os.environ)\n"
        "from hdrcap.pipeline._numba_target import numba\n"
        "import numpy as np\n"
        "@numba.njit\n"
        "def f(a, b):\n"
        "    for i in range(a.size):\n"
        "        b[i] = a[i] * 2.0 + 1.0\n"
        "f(np.ones(64), np.ones(64))\n"
        "print(dict(os.environ) == before)\n"
        "print('zmm' in next(iter(f.inspect_asm().values())))\n"
    )
    env = {
        k: v
        for k, v in __import__("os").environ.items()
        if k not in ("NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME", "HDRCAP_NUMBA_PREFER_256")
    }
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    unchanged, zmm = out.stdout.split()
    assert unchanged == "True"
    host = llvm.get_host_cpu_features().flatten()
    if "+avx512f" in host.split(","):
        assert zmm == "True"
