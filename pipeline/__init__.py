"""hdrcap's numerical core: noise model, calibration, merge, I/O. Knows nothing of cameras."""

from ._numba_target import configure as _configure_numba

__version__ = "0.1.0"

_configure_numba()

__all__ = ["__version__"]
