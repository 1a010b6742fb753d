"""The merge's output schema: channel names, units, descriptions, storage types and header keys.

One place for what an hdrcap merge writes, whichever door it came in by (``hdrcap merge``,
``run``, ``capture``, ``demo``, ``export``, ``batch`` and the Python API all write through
:func:`hdrcap.pipeline.io.results.write_result`):

========================= ============ ===========================================================
channel                   storage      meaning
========================= ============ ===========================================================
``irradiance``            float32      irradiance X (Eq. 12), :data:`UNIT_ELECTRONS` (or DN/s, see
                                       the header's ``unit``)
``sigma``                 half / float total standard uncertainty of ``irradiance``, same unit
``sigma_calibration``     half / float the calibration's part of ``sigma`` (absent when unknown)
``nexp``                  uint         unsaturated exposures used (0: no measurement)
``quality``               uint         bit field of :data:`QUALITY_BITS` (0: trusted)
========================= ============ ===========================================================

"half / float": half (16-bit) where the channel's finite non-zero values fit half's normal
range, else float32, or as the writer's ``sigma_precision`` says.

The header (:data:`HEADER_KEYS`) has the same keys for every merge; an entry that does not
apply holds None.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hdrcap.pipeline.params import DEFECT_BITS

__all__ = [
    "UNIT_ELECTRONS",
    "UNIT_DN",
    "QUALITY_BITS",
    "Channel",
    "CHANNELS",
    "CHANNEL_NAMES",
    "SIGMA_PRECISIONS",
    "HEADER_KEYS",
    "channel",
    "storage_precision",
    "new_header",
]

#: Unit of the irradiance of a calibrated merge (the paper's scaled irradiance X).
UNIT_ELECTRONS = "electrons per second per photosite"

#: Unit of the irradiance when the gain could not be estimated (self-calibration, g = 1 DN/e-).
UNIT_DN = "DN per second per photosite (gain unknown: not electrons)"

#: Bits of the ``quality`` channel: the calibration's defect kinds, then ``saturated`` (in every
#: exposure: the irradiance is a lower bound), ``masked`` (a frame's impossible raw value was
#: left out; with nexp > 0 the photosite is estimated from the other frames) and
#: ``clip_rejected`` (the merge's clip rule rejected a sample as a clipped value that slipped
#: under v_sat; with nexp > 0 still a measurement, from the other samples).
QUALITY_BITS: dict[str, int] = {**DEFECT_BITS, "saturated": 16, "masked": 32, "clip_rejected": 64}


@dataclass(frozen=True)
class Channel:
    """One channel of a merge.

    Attributes
    ----------
    name : str
        The EXR channel name.
    description : str
        What it holds, as the header records it.
    storage : {"float", "sigma", "uint"}
        How it is stored: float32; as the writer's ``sigma_precision`` says (half where it
        fits by default); 32-bit unsigned integers (whole numbers, lossless).
    """

    name: str
    description: str
    storage: str


CHANNELS: tuple[Channel, ...] = (
    Channel("irradiance", "irradiance (Eq. 12); the header's unit", "float"),
    Channel(
        "sigma",
        "total standard uncertainty of irradiance (noise plus calibration error), same unit",
        "sigma",
    ),
    Channel(
        "sigma_calibration",
        "the calibration's part of sigma alone (systematic: more frames do not reduce it), same unit",
        "sigma",
    ),
    Channel(
        "nexp",
        "number of unsaturated exposures used (0: saturated everywhere, irradiance is a lower bound)",
        "uint",
    ),
    Channel(
        "quality",
        "bit field, 0 a trusted measurement; any bit but masked and clip_rejected: nexp = 0, not a measurement; "
        "masked (a frame's impossible raw value left out) or clip_rejected (a sample rejected as a clipped value "
        "that slipped under the saturation level) with nexp > 0: estimated from the other frames: "
        + ", ".join(f"{bit} {name}" for name, bit in QUALITY_BITS.items()),
        "uint",
    ),
)

#: Channel names in the order they are written.
CHANNEL_NAMES: tuple[str, ...] = tuple(c.name for c in CHANNELS)

#: Storage choices for the ``sigma`` channels: ``auto`` is half where the channel fits half's
#: normal range (at most 0.05 % of sigma lost), else float32.
SIGMA_PRECISIONS: tuple[str, ...] = ("auto", "half", "float")

#: Keys of every merge's header, in order; None where an entry does not apply.
HEADER_KEYS: tuple[str, ...] = (
    "unit",  # of irradiance, sigma and sigma_calibration
    "sigma",  # channel descriptions: the five channels (None for an absent channel)
    "sigma_calibration",
    "nexp",
    "quality",
    "cfa_pattern",  # Bayer tile of the mosaic ("RGGB", ...) or "none"
    "exposure_times",  # as given (s), one per frame
    "capture_times",  # each frame's capture date and time from its file (EXIF), or None
    "exposure_times_calibrated",  # after the calibration's shutter table (s)
    "exposure_times_effective",  # what the merge used (s)
    "shutter_corrections",  # the calibration's shutter table and where it applied, or None
    "source_files",  # the frames' files (None for arrays)
    "calibration",  # {"params", "provenance"} of the camera model used
    "self_calibration",  # the bracket's own fit when no calibration was given, or None
    "camera_colour",  # the first frame's colour matrices and white balance, or None
    "weighting",  # "optimal" or a baseline of Table 1
    "dark_sources",  # the dark frame each exposure was merged with, or None
    "master_dark_file",  # a --master-dark file, or None
    "masked_values",  # impossible raw values masked per file (--bad-values mask), or None
    "planner",  # the plan the merge followed, or None
    "run",  # the capture run (folder, job, camera, manifest) the frames came from, or None
    "denoise",  # the filter's settings once denoised, or None
    "hdrcap_version",
    "merge",  # the merge's own record: options, dark strategies, iterations, counts
)


def channel(name: str) -> Channel:
    """The channel called ``name``.

    Parameters
    ----------
    name : str
        One of :data:`CHANNEL_NAMES`.

    Returns
    -------
    Channel

    Raises
    ------
    KeyError
        Not a merge channel.

    Examples
    --------
    >>> channel("nexp").storage
    'uint'
    """
    for c in CHANNELS:
        if c.name == name:
            return c
    raise KeyError(name)


def storage_precision(names: Any, sigma_precision: str = "auto") -> dict[str, str]:
    """Storage precision of each merge channel for :func:`hdrcap.pipeline.io.exr.write_exr`.

    Parameters
    ----------
    names : iterable of str
        The channels present (others, such as a developed image's, are stored as float).
    sigma_precision : {"auto", "half", "float"}
        Precision of the ``sigma`` channels.

    Returns
    -------
    dict of str to str
        Channel name -> ``"float"``, ``"half"``, ``"auto"`` or ``"uint"``.

    Raises
    ------
    ValueError
        An unknown ``sigma_precision``.

    Examples
    --------
    >>> storage_precision(["irradiance", "sigma", "nexp"])
    {'irradiance': 'float', 'sigma': 'auto', 'nexp': 'uint'}
    """
    if sigma_precision not in SIGMA_PRECISIONS:
        raise ValueError(f"sigma precision must be one of {', '.join(SIGMA_PRECISIONS)}, got {sigma_precision!r}")
    out = {}
    for name in names:
        storage = channel(name).storage if name in CHANNEL_NAMES else "float"
        out[name] = sigma_precision if storage == "sigma" else storage
    return out


def new_header(**entries: Any) -> dict[str, Any]:
    """A merge header: every key of :data:`HEADER_KEYS` (None unless given), in order.

    Parameters
    ----------
    **entries
        Values of some of the keys.

    Returns
    -------
    dict
        The header.

    Raises
    ------
    KeyError
        A key that is not in :data:`HEADER_KEYS`.

    Examples
    --------
    >>> list(new_header(weighting="optimal"))[:2], new_header()["planner"] is None
    (['unit', 'sigma'], True)
    """
    unknown = set(entries) - set(HEADER_KEYS)
    if unknown:
        raise KeyError(f"not a header key: {', '.join(sorted(unknown))}")
    return {key: entries.get(key) for key in HEADER_KEYS}
