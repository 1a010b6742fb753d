"""Helpers shared by the command modules: multi-value options, calibration lookup, JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from hdrcap.pipeline.errors import InputError

__all__ = ["ManyValuesCommand", "many_values", "echo_json", "resolve_calibration", "resolve_merge_calibration"]


class ManyValuesCommand(click.Command):
    """A click command whose options listed in ``many_value_options`` take several values
    after one flag (``--darks a.dng b.dng``), as well as the flag repeated.

    Values run until the next token that starts with ``-`` (a negative number still counts
    as a value).
    """

    many_value_options: tuple[str, ...] = ()

    def parse_args(self, ctx, args):
        opts = set(getattr(self, "many_value_options", ()))
        out: list[str] = []
        current = None
        for tok in args:
            if tok == "--":
                current = None
                out.append(tok)
                continue
            if tok.startswith("-") and not _is_number(tok):
                current = tok if tok in opts else None
                if current is None:
                    out.append(tok)
                continue
            if current is not None:
                out.extend([current, tok])
            else:
                out.append(tok)
        return super().parse_args(ctx, out)


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def many_values(*names: str):
    """Decorator: make a command parse ``names`` as multi-value options."""

    def deco(cmd: click.Command) -> click.Command:
        cmd.__class__ = type("ManyValues" + type(cmd).__name__, (ManyValuesCommand, type(cmd)), {})
        cmd.many_value_options = tuple(names)
        return cmd

    return deco


def echo_json(obj: Any) -> None:
    """Print ``obj`` as one line of JSON on stdout."""
    click.echo(json.dumps(obj, sort_keys=True, default=_default))


def _default(obj):
    import numpy as np

    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(type(obj).__name__)


def preset_name(camera: str | None) -> str | None:
    """The simulator preset a ``--camera`` value names: ``camera-B`` or ``mock:camera-B`` (the
    spelling of ``capture``); None for None. A real camera (``gphoto2[:MODEL]``) has no preset.

    Parameters
    ----------
    camera : str or None
        The option's value.

    Returns
    -------
    str or None
        The preset name.
    """
    if camera is None:
        return None
    backend, sep, name = camera.partition(":")
    if not sep:
        return camera
    if backend == "mock":
        return name or "camera-B"
    raise InputError(
        f"--camera {camera}: a real camera has no nominal parameters here; give --calibration FILE "
        "(from `hdrcap calibrate`) or a simulator preset (mock:PRESET)"
    )


def resolve_calibration(calibration: str | None, camera: str | None, temperature: float | None = None):
    """Return a :class:`pipeline.params.Calibration` from a calibration file or a preset.

    ``calibration`` is a file written by ``hdrcap calibrate``; ``camera`` names a simulator
    preset (``camera-A``, ``camera-B``, also spelt ``mock:camera-B`` as in ``capture``) whose
    nominal parameters are used.
    """
    from hdrcap.pipeline.params import Calibration

    camera = None if calibration else preset_name(camera)

    if calibration:
        try:
            from hdrcap.pipeline.calibration import load_calibration
        except ImportError:  # pragma: no cover - before the calibration module exists
            raise InputError("calibration files are not supported yet; use --camera PRESET") from None
        return load_calibration(calibration)
    if camera:
        from hdrcap.mock_camera import PRESETS

        if camera not in PRESETS:
            raise InputError(f"unknown camera preset {camera!r}; choose from {', '.join(PRESETS)}")
        spec = PRESETS[camera]
        prov = {"source": f"preset {camera} (nominal simulator parameters)", "camera": spec.model, "iso": spec.iso}
        if temperature is not None:
            prov["temperature"] = temperature
        return Calibration(params=spec.nominal_params(temperature), provenance=prov)
    raise InputError("no camera model: give --calibration FILE (from `hdrcap calibrate`) or --camera PRESET")


def resolve_merge_calibration(
    calibration: str | None,
    camera: str | None,
    frame_paths,
    times=None,
    *,
    darks: bool = False,
    warn=None,
    temperature: float | None = None,
    say=None,
    exposure_times: str = "effective",
):
    """The camera model of a merge: a calibration file or preset when given, else the
    calibration library's entry for the frames' camera model, ISO and size
    (:mod:`pipeline.calibration_library`), else a self-calibration from the bracket
    (:mod:`pipeline.selfcal`).

    Parameters
    ----------
    calibration, camera : str or None
        As :func:`resolve_calibration`.
    frame_paths : sequence of path
        The bracket.
    times : sequence of float, optional
        Exposure times (s) overriding the files'.
    darks : bool
        Dark frames are given: they are matched to the frames by nominal exposure time, so a
        self-calibration hands the merge the nominal times where an effective one differs by more
        than the matching tolerance (the merge then estimates the effective times itself, after
        matching the dark frames, and says so).
    warn : callable, optional
        Called with one-line messages on what was assumed.
    say : callable, optional
        Called with one line saying which calibration is used when none was given.
    exposure_times : {"effective", "nominal"}
        ``nominal``: a self-calibration hands the merge the nominal times, not its effective ones.

    Returns
    -------
    (Calibration, list of float or None, SelfCalibration or None)
        The calibration, the exposure times to merge with (None: the files'), and the
        self-calibration when one was made.
    """
    if calibration or camera:
        return resolve_calibration(calibration, camera, temperature), (list(times) if times else None), None
    from hdrcap.acquire.filemerge import read_frames
    from hdrcap.pipeline.calibration_library import find_calibration, library_dir
    from hdrcap.pipeline.selfcal import self_calibrate
    from hdrcap.pipeline.times import same_exposure

    frames = read_frames(frame_paths, times or None)
    first = frames[0]
    found = find_calibration(first.camera, first.iso, first.shape)
    if found is not None:
        if say is not None:
            say(f"no --calibration: using {found[0].path} from the calibration library")
        return found[1], (list(times) if times else None), None
    sc = self_calibrate(frames, warn=warn)
    if say is not None:
        say(
            f"no --calibration and none in the library {library_dir()} for {first.camera} at ISO {first.iso}: "
            f"{sc.calibration.provenance['source']}"
        )
    if exposure_times == "nominal":
        return sc.calibration, list(sc.nominal_times), sc
    if darks and not all(same_exposure(a, b) for a, b in zip(sc.effective_times, sc.nominal_times)):
        if warn is not None:
            warn(
                "effective exposure times differ from the nominal ones, but dark frames are matched by nominal "
                "time: the merge estimates the effective times itself after matching them"
            )
        return sc.calibration, list(sc.nominal_times), sc
    return sc.calibration, list(sc.effective_times), sc
