"""Camera calibration (Sec. 6 of the paper, with the EMVA 1288 photon-transfer method).

Estimators for the noise model of :mod:`hdrcap.pipeline.params` from bias, saturation,
flat-field and dark frames, each with its standard error, plus the calibration file:

* readout noise mu_R, sigma2_R from bias frames; sigma2_R from the difference of two frames so
  that the fixed pattern (DSNU) cancels; a per-photosite offset map from several frames;
* saturation limit v_sat = mean - 3 std of a saturation frame (Sec. 6);
* per-photosite gain a_j from dark-corrected flat fields averaged over many frames (Eq. 14);
* camera gain g from flat pairs (Eq. 16, 17) and from the EMVA 1288 photon-transfer
  regression of the pair variance on the mean over 0-70 % of saturation;
* dark current D (mean and per photosite) from dark frames at >= 6 exposure times, and
  master darks averaged over N frames.

Frames are streamed: every estimator takes an iterable and holds at most a few float64 maps
(sums, not frame stacks), so memory does not grow with the number of frames. Units: DN for raw
values, DN^2 for variances, DN per electron for g, electrons per second for D, seconds for t.

Modules:

* :mod:`.stats` -- sigma-clipped spatial statistics, EMVA 1288 pair variances, the streaming
  per-photosite stack;
* :mod:`.frames` -- access to a frame's values, time and name; runs of one exposure time;
* :mod:`.readout` -- mu_R, sigma2_R and the offset map from bias frames;
* :mod:`.saturation` -- v_sat from saturation frames;
* :mod:`.flats` -- the PRNU map (Eq. 14) and the flat pairs;
* :mod:`.gain` -- g from pairs (Eq. 16, 17) and by the photon-transfer regression;
* :mod:`.dark` -- master darks and the dark current;
* :mod:`.workflow` -- :func:`calibrate`, the steps in order, and the summary;
* :mod:`.shutter` -- per-time shutter corrections from frames of a static scene;
* :mod:`.files` -- :func:`calibrate_files`, the calibration of frame files (``hdrcap calibrate``),
  and :func:`add_shutter_table` (``--shutter``);
* :mod:`.archive` -- the calibration file (:func:`save_calibration`, :func:`load_calibration`).
"""

from __future__ import annotations

import importlib
from typing import Any

#: Where each public name lives. The submodules are imported on first use of a name (PEP 562),
#: so that loading a calibration file (``archive``) does not import the estimators and their
#: numba kernels (about 0.5 s).
_HOME = {
    "FORMAT": "archive",
    "FORMAT_VERSION": "archive",
    "load_calibration": "archive",
    "save_calibration": "archive",
    "DarkFit": "dark",
    "MasterDark": "dark",
    "fit_dark_current": "dark",
    "add_shutter_table": "files",
    "calibrate_files": "files",
    "FlatResult": "flats",
    "estimate_flats": "flats",
    "PhotonTransferFit": "gain",
    "gain_from_pair": "gain",
    "gain_from_pairs": "gain",
    "photon_transfer_gain": "gain",
    "prnu_correction_factor": "gain",
    "ReadoutEstimate": "readout",
    "estimate_readout": "readout",
    "estimate_saturation": "saturation",
    "estimate_shutter_table": "shutter",
    "DEFAULT_CLIP": "stats",
    "PairStats": "stats",
    "PixelStack": "stats",
    "pair_statistics": "stats",
    "robust_mean_std": "stats",
    "GAIN_METHODS": "workflow",
    "calibrate": "workflow",
    "calibration_summary": "workflow",
    "format_summary": "workflow",
    "with_file_metadata": "workflow",
}

__all__ = list(_HOME)


def __getattr__(name: str) -> Any:
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{home}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOME))
