"""The run manifest (append-only JSON lines) and the event log.

A run folder holds ``manifest.jsonl``: a first ``{"type": "run", ...}`` record with the plan's
fingerprint, then one ``{"type": "frame", ...}`` record per verified frame (file, sha256,
requested and applied settings, timestamps, temperature, camera identity), and a last
``{"type": "complete", "summary": ...}`` once the outputs are written (``--resume`` on such a
run only re-reports the summary). Lines are only
ever appended, each written whole (a short ``write`` is continued; one that cannot finish is
cut back) and flushed to disk (fsync) before the session goes on, so a crash loses at most
the line being written; a torn last line is ignored on
reading and the next append starts a fresh line. ``events.jsonl`` logs everything that
happened (retries, reconnects, light blocking), also as JSON lines.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import logging
import os
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import Any, NamedTuple

__all__ = ["Manifest", "ManifestScan", "EventLog", "utc_now", "jsonable", "MANIFEST_NAME", "EVENTS_NAME"]

MANIFEST_NAME = "manifest.jsonl"
EVENTS_NAME = "events.jsonl"


def utc_now() -> str:
    """Current UTC time, ISO 8601 with microseconds."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="microseconds")


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON types: numpy scalars as Python numbers, anything else unknown as
    its ``str``.

    >>> jsonable({"n": 2, "path": Path("a")})
    {'n': 2, 'path': 'a'}
    """
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def _json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))


def _append_line(path: Path, record: dict) -> None:
    data = (_json(record) + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        if size:
            # a torn last line from a crash: start a fresh line rather than extending it
            with open(path, "rb") as f:
                f.seek(size - 1)
                if f.read(1) != b"\n":
                    data = b"\n" + data
        _write_all(fd, data, size)
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_all(fd: int, data: bytes, size: int) -> None:
    """Write all of ``data`` (``os.write`` may write less than asked: a full disk, a signal);
    when the rest cannot be written the file is cut back to ``size`` bytes, so no torn record
    stays behind, and the error is raised."""
    view, done = memoryview(data), 0
    try:
        while done < len(data):
            n = os.write(fd, view[done:])
            if n <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            done += n
    except OSError:
        if done:
            try:
                os.ftruncate(fd, size)
            except OSError:
                pass
        raise


def _parse_line(raw: bytes) -> dict | None:
    """The JSON object of one line (None: torn, not JSON, or not an object)."""
    try:
        rec = json.loads(raw)
    except ValueError:
        return None
    return rec if isinstance(rec, dict) else None


def _read_lines(path: Path) -> Iterator[tuple[int, dict | None]]:
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, 1):
            raw = raw.strip()
            if raw:
                yield lineno, _parse_line(raw)


class ManifestScan(NamedTuple):
    """One pass over a manifest (:meth:`Manifest.scan`).

    Attributes
    ----------
    header : dict or None
        The ``run`` record.
    keys : frozenset of str
        Plan keys of the frames recorded (voided ones taken out).
    completion : dict or None
        The last ``complete`` record.
    """

    header: dict | None
    keys: frozenset[str]
    completion: dict | None


def _fold_frame(out: dict, rec: dict, value: Any) -> None:
    """Apply one record to the frames recorded so far: a ``frame`` record adds its key (the last
    one wins), a ``void`` record takes it out again."""
    if rec["type"] == "frame":
        out[rec["key"]] = value
    elif rec["type"] == "void":
        out.pop(rec["key"], None)


class Manifest:
    """``manifest.jsonl`` of one run folder."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / MANIFEST_NAME
        self.torn_lines = 0

    def exists(self) -> bool:
        return self.path.exists() and self.path.stat().st_size > 0

    def iter_records(self) -> Iterator[dict]:
        """The intact records, in order, read one line at a time (torn or foreign lines are
        counted in ``torn_lines`` as they are passed)."""
        self.torn_lines = 0
        if not self.path.exists():
            return
        for _lineno, rec in _read_lines(self.path):
            if (
                rec is None
                or "type" not in rec
                or (rec["type"] in ("frame", "void") and not isinstance(rec.get("key"), str))
            ):
                self.torn_lines += 1
            else:
                yield rec

    def records(self) -> list[dict]:
        """All intact records, in order (torn or foreign lines are counted in ``torn_lines``)."""
        return list(self.iter_records())

    def header(self) -> dict | None:
        """The ``run`` record (the first line: the plan), read without the lines after it."""
        return next((r for r in self.iter_records() if r["type"] == "run"), None)

    def frames(self) -> dict[str, dict]:
        """The frame record of each plan key (the last one wins if a frame was re-recorded)."""
        out: dict[str, dict] = {}
        for rec in self.iter_records():
            _fold_frame(out, rec, rec)
        return out

    def completion(self) -> dict | None:
        """The last ``{"type": "complete"}`` record (written once the run's outputs exist), or None."""
        done = None
        for rec in self.iter_records():
            if rec["type"] == "complete":
                done = rec
        return done

    def scan(self) -> ManifestScan:
        """Header, the keys of the frames recorded and the completion in one pass, one line at
        a time: what a run's state needs, in memory bounded by its number of keys (not by its
        frame records).

        Returns
        -------
        ManifestScan
        """
        head: dict | None = None
        done: dict | None = None
        keys: dict[str, dict] = {}
        for rec in self.iter_records():
            if rec["type"] == "run" and head is None:
                head = rec
            elif rec["type"] == "complete":
                done = rec
            _fold_frame(keys, rec, None)
        return ManifestScan(head, frozenset(keys), done)

    def append(self, record: dict) -> None:
        if "type" not in record:
            raise ValueError("a manifest record needs a type")
        _append_line(self.path, record)

    def verify_hashes(self) -> list[str]:
        """Keys whose file is missing or whose sha256 differs from the manifest's."""
        from hdrcap.pipeline.io.files import sha256_file

        bad = []
        for key, rec in self.frames().items():
            f = self.path.parent / rec["file"]
            if not f.is_file() or sha256_file(f) != rec["sha256"]:
                bad.append(key)
        return bad


#: Log level of each event on the ``hdrcap.run`` logger (others, also ``stop``, whose error the
#: command prints anyway: INFO).
EVENT_LEVELS = {"fault": logging.WARNING, "void": logging.WARNING, "reject": logging.WARNING, "frame": logging.INFO}
_LOG = logging.getLogger("hdrcap.run")


class EventLog:
    """``events.jsonl``: one JSON object per event, always written, and logged on the
    ``hdrcap.run`` logger (level :data:`EVENT_LEVELS`; ``hdrcap -v`` shows them all)."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / EVENTS_NAME

    def emit(self, event: str, **fields: Any) -> dict:
        """Append one event and log it.

        Parameters
        ----------
        event : str
            Its name (``start``, ``frame``, ``fault``, ``stop``, ...).
        **fields
            JSON-serialisable details.

        Returns
        -------
        dict
            The record written.
        """
        rec = {"time": utc_now(), "event": event, **fields}
        level = EVENT_LEVELS.get(event, logging.INFO)
        if event == "reconnect" and not fields.get("ok", True):
            level = logging.WARNING
        if _LOG.isEnabledFor(level):
            _LOG.log(level, "%s %s %s", self.path.parent.name, event, _json(fields))
        _append_line(self.path, rec)
        return rec

    def events(self) -> list[dict]:
        if not self.path.exists():
            return []
        return [r for _n, r in _read_lines(self.path) if r is not None]

    def read_from(self, offset: int = 0) -> Generator[tuple[int, dict | None], None, None]:
        """The events written from byte ``offset`` on, one whole line at a time, for a reader
        that follows the log while a run appends to it.

        Parameters
        ----------
        offset : int
            Byte offset of a line's start (0, or an offset this method gave).

        Yields
        ------
        (int, dict or None)
            The byte offset after the line, and its event (None for a torn or foreign line).
            A last line without its newline (being written) is not read.
        """
        try:
            f = open(self.path, "rb")
        except FileNotFoundError:
            return
        with f:
            f.seek(offset)
            pos = offset
            for raw in f:
                if not raw.endswith(b"\n"):
                    return
                pos += len(raw)
                if raw.strip():
                    yield pos, _parse_line(raw.strip())
