"""A camera's noise model by name: a calibration file, or a simulated camera's nominal one."""

from __future__ import annotations

import os

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.params import Calibration

__all__ = ["camera_model"]


def camera_model(
    calibration: str | os.PathLike[str] | None = None,
    camera: str | None = None,
    temperature: float | None = None,
) -> Calibration:
    """The calibration a merge, a plan or a capture uses: a file written by ``hdrcap
    calibrate``, else the nominal parameters of a simulator preset.

    Parameters
    ----------
    calibration : path, optional
        A calibration file; wins over ``camera``.
    camera : str, optional
        A simulator preset, ``camera-B`` or ``mock:camera-B``.
    temperature : float, optional
        Sensor temperature of a preset, degrees C.

    Returns
    -------
    Calibration

    Raises
    ------
    InputError
        Neither given; an unreadable calibration file; an unknown preset or a real camera's
        name (it has no nominal parameters).

    Examples
    --------
    >>> camera_model(camera="mock:camera-A").params.v_sat
    3709.0
    """
    if calibration:
        from hdrcap.pipeline.calibration import load_calibration

        return load_calibration(calibration)
    if camera:
        from hdrcap.mock_camera.sensor import preset_calibration

        return preset_calibration(camera, temperature)
    raise InputError("no camera model: give --calibration FILE (from `hdrcap calibrate`) or --camera PRESET")
