"""The dark strategies of the merge, by name (no numerical dependencies: the command line reads
them without importing numpy).

``matched``
    one dark frame taken at the same exposure time (the paper, Eq. 5);
``master``
    a master dark averaged from several frames;
``model``
    no dark frame: the bias level and the calibrated dark current are subtracted.

The variance each implies is written in :mod:`pipeline.noise`, which re-exports
:class:`DarkStrategy` under its historical name ``hdrcap.pipeline.noise.DarkStrategy``.
"""

from __future__ import annotations

from enum import Enum

__all__ = ["DarkStrategy"]


class DarkStrategy(str, Enum):
    """How the dark level is obtained for an exposure (see module docstring). A str enum: its
    members equal, print and serialise (JSON) as their values ``"matched"``, ``"master"`` and
    ``"model"``."""

    MATCHED = "matched"
    MASTER = "master"
    MODEL = "model"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)
