"""Compile-target tuning for the numba kernels.

On AVX-512 machines LLVM's tuning for the host CPU prefers 256-bit vectors
(``prefer-256-bit``), which halves the width of the merge kernel's loops. Measured on the
2-core AVX-512 machines hdrcap is developed on (``benchmarks/bench_merge.py``, 24 Mpix), 512-bit
vectors take the merge kernel from 2.4x to 2.1x one ``np.sum`` of its input (0.87x the time).
This module lifts the preference by giving
numba the host's own CPU features plus ``-prefer-256-bit``; nothing else changes (same
instructions available, same results up to the order of floating-point sums).

Modules that compile with numba take ``numba`` from here (``from ._numba_target import
numba``), so :func:`configure` runs before their first compilation, and only in processes that
compile (llvmlite's import costs ~70 ms, which commands that never compile should not pay).
It must run before numba compiles or loads its first function in the process; it does
nothing when the user has set ``NUMBA_CPU_NAME`` or ``NUMBA_CPU_FEATURES`` or when
``HDRCAP_NUMBA_PREFER_256=1``, and nothing on CPUs without AVX-512. It sets numba's own
configuration (``numba.core.config.CPU_FEATURES``), never ``os.environ``: child processes and
other programs in the same process see the environment as the user left it.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Any


def configure() -> str | None:
    """Set numba's CPU features (see the module docstring); returns the features string set,
    or None when nothing was changed."""
    if os.environ.get("NUMBA_CPU_NAME") or os.environ.get("NUMBA_CPU_FEATURES"):
        return None
    if os.environ.get("HDRCAP_NUMBA_PREFER_256", "") not in ("", "0"):
        return None
    try:
        import llvmlite.binding as llvm

        features = llvm.get_host_cpu_features().flatten()
    except Exception:  # no host feature detection: keep numba's defaults
        return None
    if "+avx512f" not in features.split(","):
        return None
    features += ",-prefer-256-bit"
    # numba itself first, then its configuration: the order of numba's own __init__. Importing
    # ``numba.core`` first takes its import lock before numba's, and a thread doing that while
    # another runs ``import numba`` trips CPython's deadlock detection (gh-83065). numba reads
    # the environment once, at import; we never write it, and nothing is compiled at import.
    import numba

    config: Any = numba.core.config  # set through globals() at import: invisible to a type checker

    if config.CPU_FEATURES not in (None, features):  # set by the user through numba's own configuration
        return None
    config.CPU_FEATURES = features
    return features


configure()

import numba  # noqa: E402  (configure() imported it; nothing compiled before the target is set)

__all__ = ["configure", "numba", "warm_up"]


def warm_up() -> None:
    """Initialise numba's CPU target: the registries of implementations that numba builds once
    per process before it compiles or loads any function (about a second on the 2-core hosts
    measured), under numba's compiler lock as its own loading does. For a background thread
    that runs while a command reads its inputs; it changes no result."""
    with numba.core.compiler_lock.global_compiler_lock:
        numba.core.registry.cpu_target.target_context.refresh()


#: The line said once per process when numba starts compiling one of hdrcap's functions: its
#: cache (``__pycache__`` beside the sources, or ``NUMBA_CACHE_DIR``) does not hold them yet.
COMPILE_NOTICE = (
    "compiling hdrcap's numba kernels for this CPU (first run after an install or upgrade): "
    "about 20-60 s, once; later runs load them from numba's cache (`hdrcap warm-up` compiles ahead)"
)


class _CompileNotice(numba.core.event.Listener):
    """Logs :data:`COMPILE_NOTICE` as a warning of the ``hdrcap`` logger (stderr with the
    command line; Python's last-resort handler otherwise) on the first compilation of a
    function of hdrcap's in the process. Loading a function from numba's cache compiles
    nothing and says nothing."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._said = False

    def on_start(self, event: Any) -> None:
        dispatcher = event.data.get("dispatcher")
        module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
        if not module.startswith("hdrcap."):
            return
        with self._lock:
            said, self._said = self._said, True
        if not said:
            logging.getLogger("hdrcap.pipeline.compile").warning(COMPILE_NOTICE)

    def on_end(self, event: Any) -> None:
        pass


numba.core.event.register("numba:compile", _CompileNotice())
