"""The run folders under ROOT as the web server shows them: the list, one run's detail, its files.

A run's state comes from :func:`hdrcap.acquire.capture.runfolder.run_status` (manifest, event log
and locks, read one line at a time); its plan from the manifest's run record
(:class:`hdrcap.acquire.capture.session.CapturePlan`); its figures from its EXR
(:func:`hdrcap.pipeline.io.results.read_result`, :func:`hdrcap.pipeline.result.summarise`).
Nothing here reads a frame, and a folder's file list is read one page at a time.
"""

from __future__ import annotations

import datetime as _dt
import heapq
import math
import os
import threading
from dataclasses import asdict
from pathlib import Path
from typing import Any
from urllib.parse import quote

from hdrcap.serve.cache import StampCache, file_stamp
from hdrcap.serve.safety import Refused, child_path

__all__ = ["RunIndex", "MAX_PAGE", "RENDER_LOCK"]

#: Most runs or files one page holds.
MAX_PAGE = 1000
#: One EXR read or figure drawn at a time: memory stays that of one image, however many requests.
RENDER_LOCK = threading.Lock()
#: Output names when the run's record does not name them.
DEFAULT_EXR, DEFAULT_PNG = "hdr.exr", "preview.png"


class RunIndex:
    """The run folders that are direct subfolders of ``root``.

    Parameters
    ----------
    root : Path
        The folder holding the run folders (``[output] folder``'s parent).
    """

    def __init__(self, root: Path):
        self.root = Path(root).resolve()
        self._runs: set[str] = set()  # names known to be run folders (a run folder stays one)
        self._started: StampCache[str] = StampCache(100_000)
        self._status: StampCache[dict] = StampCache(10_000)
        self._figures: StampCache[dict] = StampCache(10_000)

    # ------------------------------------------------------------------ the list
    def folder(self, name: str) -> Path:
        """The run folder ``name`` (resolved, inside ROOT).

        Raises
        ------
        Refused
            404: no such run; 403: it lies outside ROOT (a symbolic link).
        """
        from hdrcap.acquire.capture.runfolder import is_run_folder

        path = child_path(self.root, name)
        if not path.is_dir() or not (name in self._runs or is_run_folder(path)):
            raise Refused(404, f"no run {name!r}")
        self._runs.add(name)
        return path

    def names(self) -> list[str]:
        """Names of the run folders, newest start first (then by name)."""
        from hdrcap.acquire.capture.runfolder import is_run_folder

        found = []
        with os.scandir(self.root) as it:
            for entry in it:
                if entry.name.startswith(".") or not entry.is_dir():
                    continue
                if entry.is_symlink():
                    try:
                        child_path(self.root, entry.name)
                    except Refused:
                        continue  # a run folder elsewhere: not served, not listed
                if entry.name not in self._runs:
                    if not is_run_folder(Path(entry.path)):
                        continue
                    self._runs.add(entry.name)
                found.append((self._start(entry.name), entry.name))
        found.sort(reverse=True)
        return [name for _start, name in found]

    def _start(self, name: str) -> str:
        """Start time of a run (its manifest's run record, else the folder's time), cached."""
        from hdrcap.acquire.capture.manifest import MANIFEST_NAME, Manifest

        path = self.root / name
        stamp = file_stamp(path / MANIFEST_NAME)
        key = None if stamp is None or stamp[0] == 0 else stamp[2]  # the first line never changes

        def read() -> str:
            head = Manifest(path).header() if key is not None else None
            if head and head.get("time"):
                return str(head["time"])
            return _iso(path.stat().st_mtime)

        return self._started.get(name, key, read)

    def page(self, limit: int = 100, offset: int = 0) -> tuple[int, list[dict[str, Any]]]:
        """(number of runs, the summaries of runs ``offset`` .. ``offset + limit``)."""
        from hdrcap.acquire.capture.session import held_locks

        names = self.names()
        held = held_locks()
        return len(names), [self.summary(n, held) for n in names[offset : offset + limit]]

    # ------------------------------------------------------------------ one run
    def summary(self, name: str, held: frozenset | None = None) -> dict[str, Any]:
        """The run's entry of ``GET /api/runs`` (see docs/serve.md)."""
        from hdrcap.acquire.capture.manifest import EVENTS_NAME, MANIFEST_NAME
        from hdrcap.acquire.capture.runfolder import run_is_active, run_status
        from hdrcap.acquire.capture.session import held_locks

        path = self.folder(name)
        held = held_locks() if held is None else held
        exr = self._outputs(path)["exr"] or DEFAULT_EXR
        active = None if held is None else run_is_active(path, held)
        stamp = (file_stamp(path / MANIFEST_NAME), file_stamp(path / EVENTS_NAME), file_stamp(path / exr), active)

        def make() -> dict[str, Any]:
            status = asdict(run_status(path, held, exr=exr))
            status.pop("last_event")
            return {"name": name, **status}

        out = dict(self._status.get(name, stamp, make))
        figures = self.figures(name) if out["state"] == "complete" else None
        out["achieved_snr_db"] = (figures or {}).get("median_snr_db")
        return out

    def detail(self, name: str) -> dict[str, Any]:
        """``GET /api/runs/{name}``: the summary, the last event, the plan, the outputs, the
        merge's figures and the completion record."""
        from hdrcap.acquire.capture.manifest import EventLog, Manifest

        path = self.folder(name)
        out = self.summary(name)
        head = Manifest(path).header()
        outputs = self._outputs(path)
        out["last_event"] = _last_event(EventLog(path))
        out["outputs"] = outputs
        out["plan"] = plan_table(head) if head else None
        out["calibration"] = (head or {}).get("calibration")
        out["camera_record"] = (head or {}).get("camera")
        out["figures"] = self.figures(name)
        done = Manifest(path).completion()
        out["completion"] = done.get("summary") if done else None
        maps = ("snr", "sigma", "quality") if outputs["exr"] else ()
        images = (("preview",) if outputs["exr"] or outputs["png"] else ()) + maps
        base = f"/api/runs/{quote(name)}"
        out["links"] = {kind: f"{base}/{kind}.png" for kind in images}
        out["links"].update(events=f"{base}/events", files=f"{base}/files")
        return out

    @staticmethod
    def _outputs(path: Path) -> dict[str, str | None]:
        """Names of the run's EXR and preview PNG in the run folder (None: not there): the
        default names (``hdr.exr``, ``preview.png``), else the first of that type by name."""
        out: dict[str, str | None] = {}
        for kind, default in (("exr", DEFAULT_EXR), ("png", DEFAULT_PNG)):
            if (path / default).is_file():
                out[kind] = default
            else:
                found = sorted(p.name for p in path.glob(f"*.{kind}") if not p.name.startswith("."))
                out[kind] = found[0] if found else None
        return out

    def _output(self, name: str, kind: str) -> Path:
        """The run's EXR or PNG output (resolved, inside the run folder). Refused 404 when there
        is none, 403 when it is a symbolic link out of ROOT."""
        path = self.folder(name)
        found = self._outputs(path)[kind]
        if found is None:
            raise Refused(404, f"run {name!r} has no {kind.upper()} output")
        return child_path(path, found)

    def exr_path(self, name: str) -> Path:
        """The run's EXR (see :meth:`_output`)."""
        return self._output(name, "exr")

    def png_path(self, name: str) -> Path:
        """The run's preview PNG (see :meth:`_output`)."""
        return self._output(name, "png")

    def figures(self, name: str) -> dict[str, Any] | None:
        """:func:`hdrcap.pipeline.result.summarise` of the run's EXR and its median SNR (dB,
        ``20 log10(1 / median relative sigma)`` over the measured photosites); None without an
        EXR or when it cannot be read."""
        try:
            exr = self.exr_path(name)
        except Refused:
            return None

        def make() -> dict[str, Any]:
            from hdrcap.pipeline.errors import InputError
            from hdrcap.pipeline.io.results import read_result
            from hdrcap.pipeline.result import summarise

            with RENDER_LOCK:
                try:
                    result = read_result(exr)
                except InputError as err:
                    return {"error": str(err)}
                figures = summarise(result)
            rel = figures.get("median_relative_sigma")
            figures["median_snr_db"] = 20 * math.log10(1 / rel) if rel and rel > 0 else None
            return figures

        return self._figures.get(name, file_stamp(exr), make)

    # ------------------------------------------------------------------ files
    def files(self, name: str, folder: str = "", offset: int = 0, limit: int = 100) -> dict[str, Any]:
        """One page of a run folder's files (or of a subfolder's, ``frames`` for example), by
        name; hidden files (locks, unfinished downloads) are left out. Reads the folder's names
        once, keeping only ``offset + limit`` of them."""
        run = self.folder(name)
        parts = [p for p in folder.split("/") if p] if folder else []
        base = child_path(run, *parts) if parts else run
        if not base.is_dir():
            raise Refused(404, "not a folder")
        total = 0

        def visible():
            nonlocal total
            with os.scandir(base) as it:
                for entry in it:
                    if not entry.name.startswith("."):
                        total += 1
                        yield entry.name

        first = heapq.nsmallest(offset + limit, visible())
        entries = []
        for fname in first[offset:]:
            try:
                p = child_path(run, *parts, fname)
            except Refused:
                continue  # a symbolic link out of the run folder
            st = p.stat()
            entries.append(
                {
                    "name": fname,
                    "path": "/".join([*parts, fname]),
                    "kind": "folder" if p.is_dir() else "file",
                    "bytes": None if p.is_dir() else st.st_size,
                    "modified": _iso(st.st_mtime),
                }
            )
        nxt = offset + limit if offset + limit < total else None
        return {
            "folder": "/".join(parts),
            "offset": offset,
            "limit": limit,
            "total": total,
            "next_offset": nxt,
            "files": entries,
        }

    def file(self, name: str, relpath: str) -> Path:
        """A file of the run folder to send (``relpath`` relative to it)."""
        parts = relpath.split("/")
        path = child_path(self.folder(name), *parts)
        if not path.is_file():
            raise Refused(404, "not a file")
        return path


def plan_table(head: dict[str, Any]) -> dict[str, Any]:
    """The plan of a manifest's run record as the run page shows it: per exposure time its dark
    strategy and frame counts, the calibration series, and (a planned run) the planner's
    target, prediction, options and decisions.

    Parameters
    ----------
    head : dict
        The manifest's ``run`` record.

    Returns
    -------
    dict
    """
    from hdrcap.acquire.capture.session import DARK_KINDS, CapturePlan

    plan = CapturePlan.from_dict(head["plan"])
    strategies = plan.strategies()
    lights: dict[float, int] = {}
    darks: dict[float, int] = {}
    series: dict[tuple[str, float], int] = {}
    for f in plan.frames:
        if f.kind == "light":
            lights[f.exposure_s] = lights.get(f.exposure_s, 0) + 1
        elif f.kind == "dark":
            darks[f.exposure_s] = darks.get(f.exposure_s, 0) + 1
        else:
            series[(f.kind, f.exposure_s)] = series.get((f.kind, f.exposure_s), 0) + 1
    exposures = [
        {
            "exposure_s": t,
            "dark_strategy": strategies[t].value,
            "light_frames": n,
            "dark_frames": darks.get(t, 0),
            "library_master": any(math.isclose(t, lt, rel_tol=1e-3) for lt in plan.library_times),
        }
        for t, n in sorted(lights.items())
    ]
    planning = head.get("planning") or {}
    decided = planning.get("plan") or {}
    return {
        "mode": planning.get("mode"),
        "dark_strategy": plan.dark_strategy,
        "n_dark": plan.n_dark,
        "frames": len(plan.frames),
        "exposures": exposures,
        "series": [
            {"kind": k, "exposure_s": t, "frames": n, "dark": k in DARK_KINDS} for (k, t), n in sorted(series.items())
        ],
        "target_snr_db": decided.get("target_snr_db"),
        "predicted_min_snr_db": planning.get("predicted_min_snr_db"),
        "feasible": planning.get("feasible"),
        "message": planning.get("message"),
        "total_time_s": decided.get("total_time_s"),
        "merge_options": decided.get("merge_options"),
        "decisions": decided.get("decisions"),
        "overridden": planning.get("plan_overridden"),
    }


def _last_event(log) -> dict | None:
    """The last event of a log, read from its end."""
    from hdrcap.serve.events import tail_offset

    last = None
    for _pos, rec in log.read_from(tail_offset(log.path, 1)):
        if rec is not None:
            last = rec
    return last


def _iso(timestamp: float) -> str:
    return _dt.datetime.fromtimestamp(timestamp, _dt.UTC).isoformat()
