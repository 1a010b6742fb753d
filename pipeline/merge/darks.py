"""Which dark frame serves an exposure: one rule for the batch, streaming and baseline merges.

The dark level b_i of exposure i follows its :class:`pipeline.noise.DarkStrategy`:

``matched``
    the first dark frame of the same exposure time (:func:`pipeline.times.same_exposure`);
    its variance enters once (Eq. 5).
``master``
    the dark frames of that exposure time, averaged when there are several (N = their number
    times the frames each of them averages); else the single master dark given for every
    exposure (the merge holds it, with its own N and reference time); else a master dark of
    that time from the dark library (its recorded N). The variance enters divided by N.
``model``
    no dark frame: the merge subtracts the bias level plus the calibrated dark current.

:class:`DarkResolver` answers "which dark frame serves this exposure" for all merges:
:func:`pipeline.merge.files.merge_files`, the baselines of :mod:`pipeline.merge.weighting`, the file
merge of the command line and the streaming merge of a capture session.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrcap.pipeline.calibration.darklibrary import DarkLibrary
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.times import ExposureMap

__all__ = ["DarkSource", "DarkResolver", "default_strategy", "ORIGINS"]

#: Where a dark level comes from: dark frames of the exposure time, the single master dark of
#: the merge, a master dark from the dark library (given or looked up), or no dark frame.
ORIGINS = ("frames", "single master", "library", "model")


@dataclass(frozen=True)
class DarkSource:
    """The dark level that serves one exposure.

    Attributes
    ----------
    strategy : DarkStrategy
        The exposure's dark strategy.
    data : numpy.ndarray or None
        Dark level, DN (bias included); None for ``model`` and for the merge's single master
        dark (the merge holds that one itself).
    n_frames : float or None
        Frames averaged into a master dark, N (None: not a master dark, or the merge's single
        master dark whose N is a merge option).
    source : str
        What serves it, for records: file names, a library file, or ``"model"``.
    origin : str
        One of :data:`ORIGINS`.
    """

    strategy: DarkStrategy
    data: np.ndarray | None
    n_frames: float | None
    source: str
    origin: str


def default_strategy(has_darks: bool, has_master: bool = False) -> DarkStrategy:
    """The dark strategy when none is asked for.

    Parameters
    ----------
    has_darks : bool
        Dark frames (per exposure time) are given.
    has_master : bool
        One master dark for every exposure is given.

    Returns
    -------
    DarkStrategy
        ``matched`` with dark frames, ``master`` with a master dark, ``model`` otherwise.
    """
    if has_darks:
        return DarkStrategy.MATCHED
    return DarkStrategy.MASTER if has_master else DarkStrategy.MODEL


class _Darks:
    """The dark frames of one exposure time: the first one, their float64 sum, their names."""

    def __init__(self, data: np.ndarray, name: str):
        self.first = data
        self.total: np.ndarray | None = None
        self.count = 1
        self.names = [name]
        self.mean: np.ndarray | None = None  # set once a master is served: no more frames

    def add(self, data: np.ndarray, name: str) -> None:
        if self.total is None:
            self.total = self.first.astype(np.float64)
        self.total += data
        self.count += 1
        self.names.append(name)

    def average(self) -> np.ndarray:
        if self.mean is None:
            total, self.total = self.total, None  # no sum: a single frame (add() makes it)
            self.mean = self.first if total is None else (total / self.count).astype(np.float32)
        return self.mean


class DarkResolver:
    """Serves each exposure its dark level by the rule of the module docstring.

    Parameters
    ----------
    frames_per_dark : float, optional
        Frames averaged into each dark frame given with :meth:`add_dark` when it serves a
        master exposure (N per file; default 1).
    master_dark : str, optional
        Name of the single master dark the merge holds for every master exposure (None: there
        is none).
    library : DarkLibrary, str or path, optional
        Dark library searched for master exposures that nothing else serves.
    temperature : float, optional
        Sensor temperature, degrees C, for the library search.
    """

    def __init__(
        self,
        *,
        frames_per_dark: float | None = None,
        master_dark: str | None = None,
        library: DarkLibrary | str | None = None,
        temperature: float | None = None,
    ):
        self.frames_per_dark = frames_per_dark
        self.master_dark = master_dark
        self.library = DarkLibrary(library) if library is not None and not isinstance(library, DarkLibrary) else library
        self.temperature = temperature
        self._darks: ExposureMap[_Darks] = ExposureMap()
        self._masters: ExposureMap[DarkSource] = ExposureMap()

    def add_dark(self, data: np.ndarray, t: float, name: str = "") -> None:
        """Add a dark frame of exposure time ``t`` (s), DN.

        Raises
        ------
        InputError
            A master dark of that time was already served (its dark frames must all come
            before).
        """
        from hdrcap.pipeline.errors import InputError

        hit = self._darks.get(t)
        if hit is None:
            self._darks[t] = _Darks(data, name)
            return
        if hit.mean is not None:
            raise InputError(f"a dark frame for exposure {t:g} s came after its light frames")
        hit.add(data, name)

    def add_master(self, data: np.ndarray, t: float, n_frames: float, name: str = "") -> None:
        """Add a master dark of exposure time ``t`` (s), DN, averaged from ``n_frames`` frames
        (e.g. from the dark library, loaded before a capture)."""
        self._masters[t] = DarkSource(
            DarkStrategy.MASTER, np.asarray(data, np.float32), float(n_frames), name or "dark library", "library"
        )

    def dark_frames(self, t: float) -> int:
        """Number of dark frames of exposure time ``t`` (s) added so far."""
        hit = self._darks.get(t)
        return 0 if hit is None else hit.count

    def resolve(
        self, t: float, strategy: DarkStrategy | str, *, camera: str | None = None, iso: float | None = None
    ) -> DarkSource | None:
        """The dark level that serves exposure time ``t``.

        Parameters
        ----------
        t : float
            Exposure time, s.
        strategy : DarkStrategy or str
            The exposure's dark strategy.
        camera : str, optional
            Camera name, for the dark-library search.
        iso : float, optional
            ISO speed, for the dark-library search.

        Returns
        -------
        DarkSource or None
            None when nothing serves the exposure (no dark frame of that time for ``matched``;
            no dark frame, single master dark or library master for ``master``).
        """
        strategy = DarkStrategy(strategy)
        if strategy is DarkStrategy.MODEL:
            return DarkSource(strategy, None, None, "model", "model")
        hit = self._darks.get(t)
        if strategy is DarkStrategy.MATCHED:
            return None if hit is None else DarkSource(strategy, hit.first, None, hit.names[0], "frames")
        if hit is not None:
            n = (self.frames_per_dark or 1) * hit.count
            return DarkSource(strategy, hit.average(), n, ", ".join(hit.names), "frames")
        if self.master_dark is not None:
            return DarkSource(strategy, None, None, self.master_dark, "single master")
        found = self._masters.get(t)
        if found is None and self.library is not None:
            found = self._from_library(self.library, t, camera, iso)
        return found

    def _from_library(self, library: DarkLibrary, t: float, camera: str | None, iso: float | None) -> DarkSource | None:
        masters = library.masters([t], camera=camera, iso=iso, temperature=self.temperature)
        if not masters:
            return None
        data, n, entry = next(iter(masters.values()))
        found = DarkSource(DarkStrategy.MASTER, data, float(n), str(library.root / entry.file), "library")
        self._masters[t] = found
        return found
