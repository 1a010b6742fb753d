"""One compatibility check of calibration, dark library, camera and frames.

Everything a run combines must come from the same camera at the same ISO: the calibration
(its provenance: camera, serial, ISO, temperature), the master darks of the dark library,
the camera that is connected (its identity) and each frame it delivers (EXIF make/model and
ISO). :func:`check_compatible` compares two :class:`CameraProfile` and is used at plan time,
when each frame is verified and on resume:

* **model**: names are normalised (:func:`normalise_model`, the one rule the dark
  library, the calibration library and the camera locks share) so libgphoto2's ``Nikon DSC D750`` and the EXIF
  ``NIKON CORPORATION`` + ``NIKON D750`` are the same camera; a mismatch is an error. Unknown
  names match anything.
* **serial**: when both are known it decides (a mismatch is an error even for equal models).
* **ISO**: when both are known they must agree (an error: the gain g depends on it).
* **temperature**: a difference above the tolerance (or an unknown temperature where one is
  expected) is only a warning; the dark current depends on it, the calibration still holds.
* **white level, size, CFA pattern** (a calibration against the frames of a merge,
  :meth:`CameraProfile.from_frame`): when both are known, the white levels must imply the same
  ADC range (:func:`pipeline.io.raw.adc_maximum`: 12-bit against 10-bit is another camera) and
  the calibration's saturation level must lie within the frames' white level; the calibration's
  maps must have the frames' size; the CFA patterns must be equal (``none``: monochrome).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hdrcap.pipeline.errors import InputError

if TYPE_CHECKING:  # numpy and the parameters are not needed to compare cameras
    from hdrcap.pipeline.params import Calibration

__all__ = [
    "CameraProfile",
    "CompatibilityError",
    "check_compatible",
    "normalise_model",
    "same_model",
    "TEMPERATURE_TOLERANCE_C",
]

#: Largest temperature difference, degrees C, before a warning (the dark current of a typical
#: sensor doubles every ~6 degrees C).
TEMPERATURE_TOLERANCE_C = 5.0


class CompatibilityError(InputError):
    """Calibration, dark library, camera or frame belong to different cameras or ISOs."""


@dataclass(frozen=True)
class CameraProfile:
    """What identifies the camera behind a calibration, a master dark, a connection or a frame.

    Attributes
    ----------
    source : str
        What this describes, for messages (``calibration cal.json``, ``camera``, ``frame 0003``).
    model : str
        Camera name as that source spells it ("" when unknown).
    serial : str
        Serial number ("" when unknown).
    iso : float or None
        ISO speed.
    temperature_c : float or None
        Sensor temperature, degrees C.
    white_level : float or None
        Largest value the ADC writes, DN.
    saturation : float or None
        Saturation level v_sat the model assumes, DN (a calibration's).
    shape : (int, int) or None
        Photosites (rows, columns) of the frames, or of a calibration's maps.
    cfa_pattern : str or None
        2x2 Bayer tile (``RGGB`` ...), ``none`` for monochrome; None when unknown.
    """

    source: str
    model: str = ""
    serial: str = ""
    iso: float | None = None
    temperature_c: float | None = None
    white_level: float | None = None
    saturation: float | None = None
    shape: tuple[int, int] | None = None
    cfa_pattern: str | None = None

    @classmethod
    def from_calibration(cls, calibration: Calibration, name: str = "calibration") -> CameraProfile:
        """The camera a :class:`pipeline.params.Calibration` was made on (its provenance)."""
        prov: dict[str, Any] = dict(getattr(calibration, "provenance", {}) or {})
        params = getattr(calibration, "params", None)
        shapes = [
            tuple(int(n) for n in getattr(calibration, f).shape)
            for f in ("prnu", "bias_map", "dark_current_map", "saturation_map", "defect_map")
            if getattr(calibration, f, None) is not None
        ]
        return cls(
            name,
            str(prov.get("camera") or ""),
            str(prov.get("serial") or ""),
            _num(prov.get("iso")),
            _num(prov.get("temperature")),
            white_level=None if params is None else float(params.white_level),
            saturation=None if params is None else float(params.v_sat),
            shape=(shapes[0][0], shapes[0][1]) if shapes else None,
            cfa_pattern=str(prov["cfa_pattern"] or "none") if "cfa_pattern" in prov else None,
        )

    @classmethod
    def from_frame(cls, frame: object, source: str | None = None) -> CameraProfile:
        """A frame (:class:`pipeline.io.raw.RawFrame`): its camera, serial, ISO, white level,
        size and CFA pattern (``none`` for a monochrome one; unknown for an array without one, or
        a PNG/TIFF whose pattern was not given)."""
        path = getattr(frame, "path", None)
        shape = tuple(int(n) for n in getattr(getattr(frame, "data", None), "shape", ()))
        cfa = getattr(frame, "cfa_pattern", None)
        cfa_known = cfa is not None or (path is not None and "cfa" not in getattr(frame, "assumed", ()))
        return cls(
            source or (f"frame {path}" if path else "the frame"),
            str(getattr(frame, "camera", "") or ""),
            str(getattr(frame, "serial", "") or ""),
            _num(getattr(frame, "iso", None)),
            white_level=_num(getattr(frame, "white_level", None)),
            shape=(shape[0], shape[1]) if len(shape) == 2 else None,
            cfa_pattern=str(cfa or "none") if cfa_known else None,
        )

    @classmethod
    def from_camera(cls, camera: object, iso: float | None = None) -> CameraProfile:
        """A connected camera: its identity (model, serial) and temperature, and ``iso`` (s)et."""
        ident = getattr(camera, "identity", None)
        try:
            temp = camera.temperature() if hasattr(camera, "temperature") else None
        except Exception:  # a camera that cannot say: unknown
            temp = None
        return cls(
            "camera",
            str(getattr(ident, "model", "") or ""),
            str(getattr(ident, "serial", "") or ""),
            _num(iso),
            _num(temp),
        )

    @classmethod
    def from_record(cls, record: dict, source: str) -> CameraProfile:
        """A camera identity recorded in a manifest (``{"model": ..., "serial": ...}``)."""
        return cls(source, str(record.get("model") or ""), str(record.get("serial") or ""))


def check_compatible(
    expected: CameraProfile, actual: CameraProfile, temperature_tolerance: float = TEMPERATURE_TOLERANCE_C
) -> list[str]:
    """Refuse ``actual`` unless it is the camera and ISO of ``expected``.

    Parameters
    ----------
    expected : CameraProfile
        What the run relies on (the calibration, the run's first camera, the run's ISO).
    actual : CameraProfile
        What is offered (the connected camera, a master dark, a frame).
    temperature_tolerance : float
        Largest temperature difference, degrees C, before a warning.

    Returns
    -------
    list of str
        Warnings (temperature).

    Raises
    ------
    CompatibilityError
        Different serial numbers, models, ISO speeds, white levels (ADC ranges), sizes or CFA
        patterns, or a saturation level above the other side's white level (one line naming
        both sides).
    """
    a, b = expected, actual
    if a.serial and b.serial:
        if a.serial.strip().upper() != b.serial.strip().upper():
            raise CompatibilityError(
                f"{b.source} is camera serial {b.serial} ({b.model or 'model unknown'}), but "
                f"{a.source} belongs to serial {a.serial} ({a.model or 'model unknown'})"
            )
    elif not same_model(a.model, b.model):
        raise CompatibilityError(
            f"{b.source} is a {b.model!r}, but {a.source} belongs to a {a.model!r} (another camera)"
        )
    if a.iso is not None and b.iso is not None and abs(a.iso - b.iso) > 0.5:
        raise CompatibilityError(
            f"{b.source} is at ISO {b.iso:g}, but {a.source} is at ISO {a.iso:g} (the gain depends on the ISO)"
        )
    _check_format(a, b)
    warnings = []
    if a.temperature_c is not None:
        if b.temperature_c is None:
            warnings.append(f"{b.source}: temperature unknown; {a.source} was at {a.temperature_c:g} C")
        elif abs(a.temperature_c - b.temperature_c) > temperature_tolerance:
            warnings.append(
                f"{b.source} is at {b.temperature_c:g} C, {a.source} at {a.temperature_c:g} C "
                f"(more than {temperature_tolerance:g} C apart: dark current differs)"
            )
    return warnings


def _check_format(a: CameraProfile, b: CameraProfile) -> None:
    """White level (ADC range), saturation, size and CFA of ``b`` against ``a`` (both known)."""
    from hdrcap.pipeline.io.raw import adc_maximum

    if a.white_level and b.white_level and adc_maximum(a.white_level) != adc_maximum(b.white_level):
        raise CompatibilityError(
            f"{b.source} has white level {b.white_level:g} DN ({adc_maximum(b.white_level).bit_length()}-bit), but "
            f"{a.source} is of a camera with white level {a.white_level:g} DN "
            f"({adc_maximum(a.white_level).bit_length()}-bit)"
        )
    for x, y in ((a, b), (b, a)):
        if x.saturation is not None and y.white_level and x.saturation > y.white_level:
            raise CompatibilityError(
                f"{x.source} saturates at {x.saturation:g} DN, above the white level {y.white_level:g} DN of {y.source}"
            )
    if a.shape and b.shape and tuple(a.shape) != tuple(b.shape):
        raise CompatibilityError(
            f"{b.source} is {b.shape[1]}x{b.shape[0]} photosites, but {a.source} is of {a.shape[1]}x{a.shape[0]}"
        )
    if a.cfa_pattern and b.cfa_pattern and a.cfa_pattern != b.cfa_pattern:
        raise CompatibilityError(f"{b.source} has CFA pattern {b.cfa_pattern}, but {a.source} has {a.cfa_pattern}")


def _num(value) -> float | None:
    try:
        return None if value is None or value == "" else float(value)
    except (TypeError, ValueError):
        return None


#: Words of camera names that are not part of the model: company suffixes, libgphoto2's labels
#: and the brands (EXIF writes the brand twice: Make "NIKON CORPORATION", Model "NIKON D750").
_NOISE_WORDS = {
    "CORPORATION",
    "CORP",
    "INC",
    "CO",
    "LTD",
    "COMPANY",
    "GMBH",
    "AG",
    "KK",
    "IMAGING",
    "OPTICAL",
    "ELECTRIC",
    "DIGITAL",
    "CAMERA",
    "DSC",
    "PTP",
    "MODE",
    "CONTROL",
    "PC",
    "USB",
    "NIKON",
    "CANON",
    "SONY",
    "FUJIFILM",
    "FUJI",
    "OLYMPUS",
    "OM",
    "PENTAX",
    "RICOH",
    "PANASONIC",
    "LEICA",
    "SIGMA",
    "HASSELBLAD",
    "KODAK",
    "EASTMAN",
    "SAMSUNG",
    "HDRCAP",
    "ZWO",
    "QHY",
}


def normalise_model(name: str | None) -> tuple[str, ...]:
    """The words of a camera name that name the model, upper case.

    Parameters
    ----------
    name : str or None
        A camera name as libgphoto2, EXIF (make + model) or a user wrote it.

    Returns
    -------
    tuple of str
        ``("D750",)`` for ``Nikon DSC D750`` and ``NIKON CORPORATION NIKON D750``; ``()`` for
        an unknown name.
    """
    words = re.findall(r"[A-Z0-9]+", (name or "").upper())
    return tuple(w for w in words if w not in _NOISE_WORDS)


def same_model(a: str | None, b: str | None) -> bool:
    """Whether two camera names denote the same model: equal normalised words, or one's are
    the end of the other's (a make written in front); an unknown name matches any. So
    libgphoto2's "Nikon DSC D750" and the EXIF "NIKON CORPORATION NIKON D750" match, while
    "Nikon D750" and "Nikon D7500" do not (whole words, never substrings). The dark library
    (:func:`pipeline.calibration.darklibrary.same_camera`) and the compatibility check both use it.

    Parameters
    ----------
    a, b : str or None
        Camera names.

    Returns
    -------
    bool
    """
    x, y = normalise_model(a), normalise_model(b)
    if not x or not y:
        return True
    short, long_ = sorted((x, y), key=len)
    return long_[len(long_) - len(short) :] == short
