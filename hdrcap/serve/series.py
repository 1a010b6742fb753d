"""The zarr archives of ``hdrcap batch`` as the web server shows them: what each holds, a
region's irradiance over time with its uncertainty, and a run's preview.

The archive is opened with :func:`hdrcap.batch.archive.open_archive` (xarray, lazy) at every
request, so runs a batch commits while the server runs appear. A region is read run by run in
batches of :data:`RUNS_PER_READ` runs (each run is one chunk: its whole mosaic is decompressed,
the region kept), so memory stays that of a few runs however long the archive.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.errors import InputError
from hdrcap.serve.safety import Refused

__all__ = ["ArchiveSet", "SIGMA_OF_MEAN", "MAX_REGION"]

#: Runs whose region is read at once.
RUNS_PER_READ = 8
#: Largest region side, photosites.
MAX_REGION = 512
#: How the sigma of a region's mean is computed (sent with every series).
SIGMA_OF_MEAN = (
    "sigma of the mean over the region's valid photosites: sqrt(sum sigma_i^2) / n, the photosites' errors "
    "taken as independent; the calibration's systematic part common to every photosite (gain, exposure "
    "ratios) does not average down, so for large regions this understates it. Valid: nexp > 0 and no "
    "quality flag; irradiance and sigma are null where no photosite of the region is valid."
)


class ArchiveSet:
    """The archives given with ``--archive``, by name (the folder's name without ``.zarr``;
    ``-2``, ``-3``, ... when two are called the same).

    Parameters
    ----------
    paths : sequence of Path
        The ``.zarr`` folders.
    """

    def __init__(self, paths: list[Path] | tuple[Path, ...]):
        self.paths: dict[str, Path] = {}
        for p in paths:
            p = Path(p).resolve()
            base = re.sub(r"\.zarr$", "", p.name) or "archive"
            name, k = base, 2
            while name in self.paths:
                name, k = f"{base}-{k}", k + 1
            self.paths[name] = p

    def path(self, name: str | None) -> tuple[str, Path]:
        """(name, folder) of archive ``name`` (None: the first).

        Raises
        ------
        Refused
            404: no such archive.
        """
        if not self.paths:
            raise Refused(404, "no archive is served (hdrcap serve --archive A.zarr)")
        if name is None or name == "":
            name = next(iter(self.paths))
        if name not in self.paths:
            raise Refused(404, f"no archive {name!r}")
        return name, self.paths[name]

    def open(self, name: str | None) -> tuple[str, Any]:
        """(name, the archive as an xarray Dataset of its committed runs, by start time)."""
        from hdrcap.batch.archive import open_archive

        name, path = self.path(name)
        try:
            ds = open_archive(path)
        except InputError as err:
            raise Refused(404, str(err)) from None
        if "start_time" in ds.coords or "start_time" in ds:
            ds = ds.sortby("start_time")
        return name, ds

    def describe(self, name: str | None) -> dict[str, Any]:
        """What an archive holds: runs, mosaic size, CFA pattern, unit, first and last start
        time, failed runs."""
        name, ds = self.open(name)
        n = int(ds.sizes.get("run", 0))
        shape = [int(ds.sizes["y"]), int(ds.sizes["x"])] if "irradiance" in ds else None
        times = [str(t) for t in ds["start_time"].values] if n else []
        failed = json.loads(ds.attrs.get("hdrcap_failed_runs", "{}"))
        return {
            "name": name,
            "runs": n,
            "shape": shape,
            "cfa_pattern": self._cfa(ds, n - 1) if n else None,
            "unit": ds["irradiance"].attrs.get("units") if "irradiance" in ds else None,
            "first": times[0] if times else None,
            "last": times[-1] if times else None,
            "failed_runs": len(failed),
            "links": {
                "series": f"/api/archive/series?archive={name}&y=0&x=0&size=4",
                "preview": f"/api/archive/preview.png?archive={name}",
            },
        }

    def list(self) -> list[dict[str, Any]]:
        """:meth:`describe` of every archive (an unreadable one: its name and the error)."""
        out = []
        for name in self.paths:
            try:
                out.append(self.describe(name))
            except Refused as err:
                out.append({"name": name, "error": str(err)})
        return out

    @staticmethod
    def _cfa(ds, i: int) -> str | None:
        try:
            cfa = json.loads(str(ds["header"].values[i])).get("cfa_pattern")
        except (KeyError, ValueError, AttributeError):
            return None
        return cfa if isinstance(cfa, str) and len(cfa) == 4 else None

    def series(self, name: str | None, y: int, x: int, size: int) -> dict[str, Any]:
        """The mean irradiance over the ``size`` x ``size`` region whose top left photosite is
        (``y``, ``x``), and the sigma of that mean (:data:`SIGMA_OF_MEAN`), one entry per run
        in start-time order.

        Raises
        ------
        InputError
            A region outside the mosaic, a size out of 1 .. :data:`MAX_REGION`.
        """
        name, ds = self.open(name)
        if "irradiance" not in ds:
            raise InputError(f"archive {name!r} holds no run yet")
        h, w = int(ds.sizes["y"]), int(ds.sizes["x"])
        if not 1 <= size <= MAX_REGION:
            raise InputError(f"size must be 1 .. {MAX_REGION}, got {size}")
        if not (0 <= y <= h - size and 0 <= x <= w - size):
            raise InputError(f"the {size}x{size} region at y={y}, x={x} does not lie inside the {h}x{w} mosaic")
        region = ds[["irradiance", "sigma", "nexp", "quality"]].isel(y=slice(y, y + size), x=slice(x, x + size))
        n_runs = int(ds.sizes["run"])
        mean: list[float | None] = []
        sigma: list[float | None] = []
        used: list[int] = []
        from hdrcap.serve.runs import RENDER_LOCK

        for r0 in range(0, n_runs, RUNS_PER_READ):
            with RENDER_LOCK:  # one batch of runs decoded at a time, whatever the requests
                part = region.isel(run=slice(r0, r0 + RUNS_PER_READ)).compute()
            irr, sig = part["irradiance"].values.astype(np.float64), part["sigma"].values.astype(np.float64)
            ok = (part["nexp"].values > 0) & (part["quality"].values == 0) & np.isfinite(irr) & np.isfinite(sig)
            for k in range(irr.shape[0]):
                m = ok[k]
                n = int(np.count_nonzero(m))
                used.append(n)
                mean.append(float(irr[k][m].mean()) if n else None)
                sigma.append(float(np.sqrt(np.sum(sig[k][m] ** 2)) / n) if n else None)
        return {
            "archive": name,
            "y": y,
            "x": x,
            "size": size,
            "unit": ds["irradiance"].attrs.get("units"),
            "time": [str(t) for t in ds["start_time"].values],
            "run": [int(r) for r in ds["run"].values],
            "folder": [Path(str(f)).name for f in ds["folder"].values],
            "irradiance": mean,
            "sigma": sigma,
            "n": used,
            "sigma_of_mean": SIGMA_OF_MEAN,
        }

    def preview(self, name: str | None, run: int | None = None) -> bytes:
        """The tone-mapped preview (PNG) of run ``run`` (the ``run`` coordinate; None: the run
        that started last)."""
        from hdrcap.serve.images import preview_png

        name, ds = self.open(name)
        n = int(ds.sizes.get("run", 0))
        if not n or "irradiance" not in ds:
            raise Refused(404, f"archive {name!r} holds no run yet")
        if run is None:
            i = n - 1
        else:
            where = np.flatnonzero(ds["run"].values == run)
            if not where.size:
                raise Refused(404, f"archive {name!r} has no run {run}")
            i = int(where[0])
        irr = np.asarray(ds["irradiance"].isel(run=i).values)
        return preview_png(irr, self._cfa(ds, i))
