"""A merge result to and from its files: the one writer every door uses, and its reader."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import EXR_COMPRESSIONS, read_exr, write_exr
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import CHANNEL_NAMES, SIGMA_PRECISIONS, storage_precision

__all__ = ["OUTPUT_FORMATS", "output_format", "read_result", "write_result"]

#: Output formats of :func:`write_result`.
OUTPUT_FORMATS = ("exr", "dng")


def output_format(path: str | os.PathLike[str], format: str | None = None) -> str:
    """The format a result is written in: ``format`` if given, else ``dng`` for a ``.dng`` file
    and ``exr`` for anything else.

    Parameters
    ----------
    path : str or path-like
        The output file.
    format : {"exr", "dng"}, optional
        An explicit choice.

    Returns
    -------
    str
        ``"exr"`` or ``"dng"``.

    Raises
    ------
    InputError
        An unknown format.

    Examples
    --------
    >>> output_format("merged.DNG"), output_format("merged.dng", "exr")
    ('dng', 'exr')
    """
    if format is None:
        return "dng" if Path(path).suffix.lower() == ".dng" else "exr"
    if format not in OUTPUT_FORMATS:
        raise InputError(f"output format must be exr or dng, got {format!r}")
    return format


def write_result(
    result: HdrResult,
    path: str | os.PathLike[str],
    *,
    format: str | None = None,
    force: bool = False,
    compression: str = "zip",
    sigma_precision: str = "auto",
    dng_bits: int = 32,
) -> Path:
    """Write a merge, atomically: an EXR with every channel of the result and its header
    (:mod:`hdrcap.pipeline.schema`), or a linear float CFA DNG of the irradiance alone.

    Every door (``hdrcap merge``, ``run``, ``capture``, ``demo``, ``export``, ``batch``, the
    Python API) writes through here, so one result gives the same file whichever door it came
    in by.

    Parameters
    ----------
    result : HdrResult
        The merge.
    path : str or path-like
        Output file; its folder must exist.
    format : {"exr", "dng"}, optional
        Default: :func:`output_format` of ``path``.
    force : bool
        Replace an existing file.
    compression : str
        EXR compression (:data:`hdrcap.pipeline.io.exr.EXR_COMPRESSIONS`).
    sigma_precision : {"auto", "half", "float"}
        Storage of the sigma channels (``auto``: half where they fit, at most 0.05 % lost).
        ``irradiance`` is always float32, ``nexp`` and ``quality`` unsigned integers.
    dng_bits : {32, 16}
        Float width of a DNG.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    InputError
        A bad option, or a result a DNG cannot hold (no Bayer pattern).
    OutputExistsError
        The file exists and ``force`` is false.
    """
    fmt = output_format(path, format)
    if fmt == "dng":
        from hdrcap.pipeline.io.dngwrite import write_float_dng

        if dng_bits not in (16, 32):
            raise InputError(f"DNG float width must be 16 or 32 bits, got {dng_bits!r}")
        write_float_dng(path, result, bits=dng_bits, force=force)
        return Path(path)
    if compression not in EXR_COMPRESSIONS:
        raise InputError(f"EXR compression must be one of {', '.join(EXR_COMPRESSIONS)}, got {compression!r}")
    if sigma_precision not in SIGMA_PRECISIONS:
        raise InputError(f"sigma precision must be one of {', '.join(SIGMA_PRECISIONS)}, got {sigma_precision!r}")
    channels = result.channels()
    try:
        return write_exr(
            path,
            channels,
            result.header,
            force=force,
            compression=compression,
            precision=storage_precision(channels, sigma_precision),
        )
    except ValueError as err:  # a channel that does not fit the precision asked for
        raise InputError(f"{path}: {err}") from None


def read_result(path: str | os.PathLike[str]) -> HdrResult:
    """Read a merge's EXR (``hdrcap merge``, ``denoise``, :func:`write_result`).

    Parameters
    ----------
    path : str or path-like
        The EXR: channels ``irradiance`` and ``sigma`` (the header's unit), optionally
        ``nexp``, ``quality``, ``sigma_calibration``; other channels are not read.

    Returns
    -------
    HdrResult
        float32 irradiance, sigma and nexp (1 everywhere when the file has no ``nexp``),
        uint8 quality, and the header.

    Raises
    ------
    InputError
        Missing or unreadable file, no irradiance or sigma channel, channels of different sizes.
    """
    content = read_exr(path, channels=CHANNEL_NAMES)
    ch = content.channels
    missing = [c for c in ("irradiance", "sigma") if c not in ch]
    if missing:
        raise InputError(f"{path}: no {' or '.join(missing)} channel; expected a merge result")
    shapes = {np.shape(a) for a in ch.values()}
    if len(shapes) > 1:
        raise InputError(f"{path}: channel sizes differ ({', '.join(f'{k} {np.shape(v)}' for k, v in ch.items())})")
    irr = ch["irradiance"]
    quality = ch.get("quality")
    return HdrResult(
        irradiance=irr,
        sigma=ch["sigma"],
        nexp=ch["nexp"] if "nexp" in ch else np.ones(irr.shape, np.float32),
        quality=None if quality is None else quality.astype(np.uint8),
        sigma_calibration=ch.get("sigma_calibration"),
        header=dict(content.header),
    )
