"""The EMVA 1288 descriptor file (``EMVA1288_Data.txt``, Release 3.0 format) and its image list."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.files import check_readable

__all__ = ["EmvaDataset", "EmvaStep", "read_emva_descriptor"]


@dataclass(frozen=True)
class EmvaStep:
    """One step of an EMVA 1288 descriptor: bright (``b``) or dark (``d``) images."""

    kind: str  # "b" or "d"
    exposure_time: float  # seconds
    photons: float | None  # mean photons per pixel (bright steps)
    images: tuple[Path, ...]


@dataclass(frozen=True)
class EmvaDataset:
    """An EMVA 1288 descriptor file (Release 3.0 format) and its image list."""

    path: Path
    bits: int
    width: int
    height: int
    steps: tuple[EmvaStep, ...]
    version: str | None = None

    def bright(self) -> list[EmvaStep]:
        return [s for s in self.steps if s.kind == "b"]

    def dark(self) -> list[EmvaStep]:
        return [s for s in self.steps if s.kind == "d"]


def read_emva_descriptor(path: str | os.PathLike[str]) -> EmvaDataset:
    """Parse an EMVA 1288 descriptor (``EMVA1288_Data.txt``).

    Lines: ``v`` version, ``n bits width height``, ``b <t ns> <photons>`` and ``d <t ns>`` open
    a bright or dark step, ``i <relative path>`` lists its images (Windows separators allowed).

    Parameters
    ----------
    path : str or os.PathLike
        The descriptor; image paths in it are relative to its folder.

    Returns
    -------
    EmvaDataset
        Bit depth, image size and the bright and dark steps (exposure time in s, photons per
        photosite, image paths).
    """
    path = Path(path)
    check_readable(path)
    base = path.parent
    bits = width = height = None
    version = None
    steps: list[EmvaStep] = []
    current: dict[str, Any] | None = None

    def close():
        if current is not None:
            steps.append(EmvaStep(current["kind"], current["t"], current["photons"], tuple(current["images"])))

    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split(None, 1)
            key, rest = parts[0], (parts[1] if len(parts) > 1 else "")
            try:
                if key == "v":
                    version = rest.strip()
                elif key == "n":
                    bits, width, height = (int(x) for x in rest.split()[:3])
                elif key in ("b", "d"):
                    close()
                    vals = rest.split()
                    t = float(vals[0]) * 1e-9
                    photons = float(vals[1]) if key == "b" and len(vals) > 1 else None
                    current = {"kind": key, "t": t, "photons": photons, "images": []}
                elif key == "i":
                    if current is None:
                        raise ValueError("image line before any b/d step")
                    rel = rest.strip().replace("\\", "/")
                    if not rel.isprintable():
                        raise ValueError(f"image path {rel!r} holds control characters")
                    current["images"].append(base / rel)
                else:
                    raise ValueError(f"unknown line type {key!r}")
            except (ValueError, IndexError) as err:
                raise InputError(f"{path}:{lineno}: bad EMVA 1288 descriptor line ({err})") from None
    close()
    if bits is None or width is None or height is None:  # set together
        raise InputError(f"{path}: no 'n bits width height' line; not an EMVA 1288 descriptor")
    if not steps:
        raise InputError(f"{path}: no b/d steps")
    return EmvaDataset(path=path, bits=bits, width=width, height=height, steps=tuple(steps), version=version)
