"""The PNG and TIFF files scientific and machine-vision cameras write: bit depth and alignment.

Such a camera (or the software that saves its frames) does not write a raw file: it writes the
ADC's values, often converted to fewer bits, into an 8- or 16-bit image without any level or
colour filter metadata. This is the physics of that conversion, applied to a simulated frame:

* :func:`requantise`: an ``adc_bits`` value converted to ``bits`` bits the way MATLAB's
  ``im2uint8`` converts (scale by (2^bits - 1) / (2^adc_bits - 1), round, clip): a second
  rounding, whose step is the new unit;
* :func:`msb_align`: N-bit values stored in the top bits of 16-bit words (shifted left by
  16 - N: every value a multiple of 2^(16 - N));
* :func:`write_image`: the values as a single-channel PNG or TIFF (by the file's suffix),
  8-bit words when they fit, else 16-bit.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["requantise", "msb_align", "write_image", "requantised_gain"]


def requantise(values: np.ndarray, adc_bits: int, bits: int) -> np.ndarray:
    """Convert ``adc_bits``-bit values to ``bits`` bits, im2uint8-style: round(v x (2^bits - 1)
    / (2^adc_bits - 1)), clipped to 0 .. 2^bits - 1.

    Parameters
    ----------
    values : numpy.ndarray
        Raw values, DN of the ADC.
    adc_bits : int
        The ADC's bits (the values' full scale is 2^adc_bits - 1).
    bits : int
        Bits of the output, 1..16.

    Returns
    -------
    numpy.ndarray
        uint8 (``bits`` <= 8) or uint16 values, DN of the output.

    Examples
    --------
    >>> requantise(np.array([0, 8, 4095]), 12, 8).tolist()
    [0, 0, 255]
    """
    top = (1 << bits) - 1
    scaled = np.rint(np.asarray(values, dtype=np.float64) * (top / ((1 << adc_bits) - 1)))
    return np.clip(scaled, 0, top).astype(np.uint8 if bits <= 8 else np.uint16)


def requantised_gain(gain: float, adc_bits: int, bits: int) -> float:
    """The gain (or any level) of :func:`requantise`'s output: ``gain`` x (2^bits - 1) /
    (2^adc_bits - 1) (DN of the output per DN of the ADC's unit).

    Parameters
    ----------
    gain : float
        In DN of the ADC (per electron, or a level in DN).
    adc_bits, bits : int
        As :func:`requantise`.

    Returns
    -------
    float
        In DN of the output.
    """
    return gain * ((1 << bits) - 1) / ((1 << adc_bits) - 1)


def msb_align(values: np.ndarray, bits: int) -> np.ndarray:
    """Store ``bits``-bit values in the top bits of 16-bit words (shifted left by 16 - bits).

    Parameters
    ----------
    values : numpy.ndarray
        Values within 0 .. 2^bits - 1.
    bits : int
        Their bits, 1..16.

    Returns
    -------
    numpy.ndarray
        uint16, every value a multiple of 2^(16 - bits).

    Raises
    ------
    ValueError
        A value beyond ``bits`` bits.
    """
    v = np.asarray(values)
    if v.size and int(v.max()) > (1 << bits) - 1:
        raise ValueError(f"values up to {int(v.max())} do not fit in {bits} bits")
    return (v.astype(np.uint32) << (16 - bits)).astype(np.uint16)


def write_image(path: str | os.PathLike[str], values: np.ndarray) -> Path:
    """Write values as a single-channel image: PNG (Pillow) or TIFF (tifffile) by the suffix,
    in 8-bit words when every value fits (and ``values`` is uint8), else 16-bit.

    Parameters
    ----------
    path : str or os.PathLike
        ``.png``, ``.tif`` or ``.tiff``.
    values : numpy.ndarray
        2-D values, DN (uint8 or uint16).

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        Another suffix, or not a 2-D array of 8- or 16-bit unsigned values.
    """
    path = Path(path)
    v = np.asarray(values)
    if v.ndim != 2 or v.dtype not in (np.uint8, np.uint16):
        raise ValueError("write_image takes a 2-D uint8 or uint16 array")
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        import tifffile

        tifffile.imwrite(path, v, photometric="minisblack")
    elif suffix == ".png":
        from PIL import Image

        Image.fromarray(v).save(path)
    else:
        raise ValueError(f"{path}: write a .png, .tif or .tiff file")
    return path
