"""hdrcap's numerical core: noise model, calibration, merge, I/O. Knows nothing of cameras."""

__version__ = "0.1.0"

__all__ = ["__version__"]
