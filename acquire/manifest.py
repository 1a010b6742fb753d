"""The run manifest (append-only JSON lines) and the event log.

A run folder holds ``manifest.jsonl``: a first ``{"type": "run", ...}`` record with the plan's
fingerprint, then one ``{"type": "frame", ...}`` record per verified frame (file, sha256,
requested and applied settings, timestamps, temperature, camera identity). Lines are only
ever appended, each written in one ``write`` and flushed to disk (fsync) before the session
goes on, so a crash loses at most the line being written; a torn last line is ignored on
reading and the next append starts a fresh line. ``events.jsonl`` logs everything that
happened (retries, reconnects, light blocking), also as JSON lines.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from pathlib import Path
from typing import Any, Iterator


__all__ = ["Manifest", "EventLog", "utc_now", "MANIFEST_NAME", "EVENTS_NAME"]

MANIFEST_NAME = "manifest.jsonl"
EVENTS_NAME = "events.jsonl"


def utc_now() -> str:
    """Current UTC time, ISO 8601 with microseconds."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")


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
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


def _read_lines(path: Path) -> Iterator[tuple[int, dict | None]]:
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, 1):
            raw = raw.strip()
            if not raw:
                continue
            try:
                rec = json.loads(raw)
            except ValueError:
                yield lineno, None
                continue
            yield lineno, rec if isinstance(rec, dict) else None


class Manifest:
    """``manifest.jsonl`` of one run folder."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / MANIFEST_NAME
        self.torn_lines = 0

    def exists(self) -> bool:
        return self.path.exists() and self.path.stat().st_size > 0

    def records(self) -> list[dict]:
        """All intact records, in order (torn or foreign lines are counted in ``torn_lines``)."""
        if not self.path.exists():
            return []
        out, self.torn_lines = [], 0
        for _lineno, rec in _read_lines(self.path):
            if rec is None or "type" not in rec or (rec["type"] in ("frame", "void")
                                                     and not isinstance(rec.get("key"), str)):
                self.torn_lines += 1
            else:
                out.append(rec)
        return out

    def header(self) -> dict | None:
        return next((r for r in self.records() if r["type"] == "run"), None)

    def frames(self) -> dict[str, dict]:
        """The frame record of each plan key (the last one wins if a frame was re-recorded)."""
        out: dict[str, dict] = {}
        for rec in self.records():
            if rec["type"] == "frame":
                out[rec["key"]] = rec
            elif rec["type"] == "void":
                out.pop(rec["key"], None)
        return out

    def append(self, record: dict) -> None:
        if "type" not in record:
            raise ValueError("a manifest record needs a type")
        _append_line(self.path, record)

    def verify_hashes(self) -> list[str]:
        """Keys whose file is missing or whose sha256 differs from the manifest's."""
        from hdrcap.pipeline.io import sha256_file

        bad = []
        for key, rec in self.frames().items():
            f = self.path.parent / rec["file"]
            if not f.is_file() or sha256_file(f) != rec["sha256"]:
                bad.append(key)
        return bad


class EventLog:
    """``events.jsonl``: one JSON object per event, always written."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / EVENTS_NAME

    def emit(self, event: str, **fields: Any) -> dict:
        rec = {"time": utc_now(), "event": event, **fields}
        _append_line(self.path, rec)
        return rec

    def events(self) -> list[dict]:
        if not self.path.exists():
            return []
        return [r for _n, r in _read_lines(self.path) if r is not None]

