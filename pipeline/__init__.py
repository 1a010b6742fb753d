"""hdrcap's numerical core: noise model, calibration, merge, I/O. Knows nothing of cameras."""
