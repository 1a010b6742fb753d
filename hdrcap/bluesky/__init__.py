"""hdrcap as a Bluesky detector: :class:`HdrDetector` (``pip install 'hdrcap[bluesky]'``; see
docs/bluesky.md). One trigger is one hdrcap measurement, its maps external HDF5 data."""

from __future__ import annotations

try:
    import bluesky  # noqa: F401
    import event_model  # noqa: F401
    import h5py  # noqa: F401
    import ophyd_async  # noqa: F401
except ImportError as err:  # pragma: no cover - the extra is part of the test environment
    raise ImportError(
        f"hdrcap.bluesky needs the bluesky extra ({err.name} is missing): pip install 'hdrcap[bluesky]'"
    ) from err

from hdrcap.bluesky.detector import FolderPathProvider, HdrDetector
from hdrcap.bluesky.hdf5 import MAPS, MapFile
from hdrcap.bluesky.measurement import READINGS, Measurement, Measurer

__all__ = ["HdrDetector", "FolderPathProvider", "Measurer", "Measurement", "READINGS", "MAPS", "MapFile"]
