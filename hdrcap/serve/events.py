"""Server-sent events: a run's event log as it grows, and the runs list as it changes.

A run's stream sends each line of ``events.jsonl`` (read through
:meth:`hdrcap.acquire.capture.manifest.EventLog.read_from`) as an ``event`` message whose id
is the byte offset after the line, so a browser that reconnects (``Last-Event-ID``) continues
where it was. While the run is going on (a process holds its lock) the stream follows the
file; once it is not, the stream sends the rest, an ``end`` message with the run's state, and
closes. Comment lines keep idle connections open through proxies.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import anyio.to_thread

__all__ = ["tail_offset", "sse", "follow_events", "follow_runs", "StreamLimit"]

#: Seconds between two looks at a file that did not grow.
POLL_S = 0.5
#: Seconds between two looks at whether a run is still going on, and at the runs list.
STATE_POLL_S = 2.0
#: Seconds between keep-alive comments on an idle stream.
KEEPALIVE_S = 15.0
#: Events read from the file per batch (memory per stream stays that of one batch).
BATCH = 256


def tail_offset(path: Path, n: int) -> int:
    """Byte offset of the start of the last ``n`` whole lines of ``path`` (0 when it has fewer),
    found by reading backwards in blocks.

    Parameters
    ----------
    path : Path
    n : int
        Lines wanted (0: the end of the file).

    Returns
    -------
    int
    """
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        return 0
    with f:
        pos, seen, block = f.seek(0, os.SEEK_END), 0, 65536
        # the (n+1)-th newline from the end precedes the last n whole lines (a last line still
        # being written has no newline yet and is not one of them)
        while pos > 0:
            start = max(0, pos - block)
            f.seek(start)
            chunk = f.read(pos - start)
            i = len(chunk)
            while (i := chunk.rfind(b"\n", 0, i)) >= 0:
                seen += 1
                if seen == n + 1:
                    return start + i + 1
            pos = start
        return 0


def sse(data: Any, event: str | None = None, id: int | None = None) -> bytes:
    """One server-sent event: ``data`` as JSON on one line."""
    lines = []
    if id is not None:
        lines.append(f"id: {id}")
    if event:
        lines.append(f"event: {event}")
    lines.append("data: " + json.dumps(data, separators=(",", ":"), default=str))
    return ("\n".join(lines) + "\n\n").encode()


class StreamLimit:
    """At most ``n`` streams open at once (each holds a connection and a polling task)."""

    def __init__(self, n: int):
        self.n, self.open = n, 0

    def take(self) -> bool:
        if self.open >= self.n:
            return False
        self.open += 1
        return True

    def give(self) -> None:
        self.open -= 1


def _read_batch(path: Path, pos: int) -> tuple[list[tuple[int, dict]], int, bool]:
    """Up to :data:`BATCH` events from ``pos``: (events with their end offsets, new position,
    whether the batch was full)."""
    from hdrcap.acquire.capture.manifest import EventLog

    out: list[tuple[int, dict]] = []
    it = EventLog(path.parent).read_from(pos)
    for end, rec in it:
        pos = end
        if rec is not None:
            out.append((end, rec))
        if len(out) >= BATCH:
            it.close()
            return out, pos, True
    return out, pos, False


async def follow_events(
    events_file: Path, start: int, is_active: Callable[[], bool | None], final_state: Callable[[], dict[str, Any]]
) -> AsyncIterator[bytes]:
    """The stream of a run's events from byte ``start``.

    Parameters
    ----------
    events_file : Path
        The run's ``events.jsonl``.
    start : int
        Byte offset to start at (a line's start).
    is_active : callable
        Whether the run is going on (True: follow; False: end; None: unknown, follow).
    final_state : callable
        The run's summary, sent with the ``end`` message.

    Yields
    ------
    bytes
        Server-sent events.
    """
    pos = start
    yield b"retry: 5000\n\n"
    last_sent = last_state = time.monotonic()
    active = await anyio.to_thread.run_sync(is_active)
    while True:
        batch, pos, full = await anyio.to_thread.run_sync(_read_batch, events_file, pos)
        for end, rec in batch:
            yield sse(rec, "event", end)
            last_sent = time.monotonic()
        if full:
            continue
        if active is False:
            yield sse(await anyio.to_thread.run_sync(final_state), "end")
            return
        now = time.monotonic()
        if now - last_state >= STATE_POLL_S:
            # read the file once more after the run ends: its last events come before the lock goes
            active, last_state = await anyio.to_thread.run_sync(is_active), now
            continue
        if now - last_sent >= KEEPALIVE_S:
            yield b": keep-alive\n\n"
            last_sent = now
        await asyncio.sleep(POLL_S)


async def follow_runs(list_runs: Callable[[], Any]) -> AsyncIterator[bytes]:
    """The stream of the runs list: a ``runs`` message now and whenever the list changes.

    Parameters
    ----------
    list_runs : callable
        The list's JSON content (looked at every :data:`STATE_POLL_S` seconds).

    Yields
    ------
    bytes
        Server-sent events.
    """
    yield b"retry: 5000\n\n"
    last, last_sent = None, time.monotonic()
    while True:
        content = await anyio.to_thread.run_sync(list_runs)
        now = time.monotonic()
        if content != last:
            yield sse(content, "runs")
            last, last_sent = content, now
        elif now - last_sent >= KEEPALIVE_S:
            yield b": keep-alive\n\n"
            last_sent = now
        await asyncio.sleep(STATE_POLL_S)
