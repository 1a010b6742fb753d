"""The numba compile-target tuning (pipeline._numba_target)."""

from __future__ import annotations

import llvmlite.binding as llvm

from hdrcap.pipeline._numba_target import configure


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
