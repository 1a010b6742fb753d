"""The one header builder: what a merge's EXR header records (:data:`pipeline.schema.HEADER_KEYS`)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.raw import RawFrame
from hdrcap.pipeline.params import Calibration
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import UNIT_ELECTRONS, channel, new_header

__all__ = ["with_merge_header"]


def _warn(message: str) -> None:
    print(f"hdrcap: warning: {message}", file=sys.stderr)


def _camera_colour(frames: Sequence[RawFrame], warn: Callable[[str], None]) -> dict[str, Any] | None:
    """The first frame's colour metadata (colour matrices, white balance), so that ``hdrcap
    develop`` works from the EXR alone; None without a file or a matrix."""
    from hdrcap.pipeline.io.dngwrite import camera_colour

    path = frames[0].path if frames else None
    if not path:
        return None
    try:
        found = camera_colour(path)
    except InputError as err:
        warn(f"no colour matrix recorded: {err}")
        return None
    return None if found is None else found.to_attrs()


def _shutter_corrections(calibration: Calibration, info: dict[str, Any]) -> dict[str, Any] | None:
    """The calibration's shutter table as the header records it (None without one): the table
    (times s, factors, relative standard errors, reference s) and, per frame, whether it
    applied (``--exposure-times nominal`` or a time not in the table: not applied)."""
    table = calibration.shutter
    if table is None:
        return None
    applied = (info.get("shutter_table") or {}).get("applied")
    return {**table.to_dict(), "applied": applied}


def with_merge_header(
    result: HdrResult,
    frames: Sequence[RawFrame],
    calibration: Calibration,
    *,
    warn: Callable[[str], None] = _warn,
    **entries: Any,
) -> HdrResult:
    """``result`` with the complete header of a merge (:data:`pipeline.schema.HEADER_KEYS`).

    Parameters
    ----------
    result : HdrResult
        A merge; its ``header["merge"]`` (the merge's own record) is kept.
    frames : sequence of RawFrame
        The frames merged, in the merge's order: their exposure times (s), files, CFA pattern;
        the first one's file gives the colour metadata.
    calibration : Calibration
        The camera model the merge used.
    warn : callable
        Called with a one-line message when the colour metadata cannot be read.
    **entries
        Further header keys (``weighting``, ``dark_sources``, ``master_dark_file``,
        ``masked_values``, ``planner``, ``run``; ``source_files`` or ``cfa_pattern`` to
        override what the frames say).

    Returns
    -------
    HdrResult
        A copy with the new header (arrays shared).

    Raises
    ------
    KeyError
        An entry that is not a header key.
    """
    from hdrcap import __version__

    info = result.info
    nominal = [fr.exposure_time for fr in frames]
    effective = info.get("exposure_times", nominal)
    header = new_header(
        unit=UNIT_ELECTRONS,
        sigma=channel("sigma").description,
        sigma_calibration=None if result.sigma_calibration is None else channel("sigma_calibration").description,
        nexp=channel("nexp").description,
        quality=None if result.quality is None else channel("quality").description,
        cfa_pattern=(frames[0].cfa_pattern if frames else None) or "none",
        exposure_times=nominal,
        capture_times=[fr.timestamp for fr in frames] if any(fr.timestamp for fr in frames) else None,
        exposure_times_calibrated=info.get("exposure_times_calibrated", effective),
        exposure_times_effective=effective,
        shutter_corrections=_shutter_corrections(calibration, info),
        source_files=[fr.path for fr in frames] if any(fr.path for fr in frames) else None,
        calibration={"params": calibration.params.to_dict(), "provenance": calibration.provenance},
        camera_colour=_camera_colour(frames, warn),
        weighting="optimal",
        hdrcap_version=__version__,
        merge=info,
    )
    unknown = set(entries) - set(header)
    if unknown:
        raise KeyError(f"not a header key: {', '.join(sorted(unknown))}")
    header.update(entries)
    return result.replace(header=header)
