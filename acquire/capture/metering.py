"""Metering frames for the planner: ``capture_fn(t)`` that takes one quick frame into the run
folder's ``meter/`` with the capture session's retries."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hdrcap.pipeline.errors import InputError

if TYPE_CHECKING:
    from hdrcap.acquire.camera import Camera
    from hdrcap.acquire.capture.session import RetryPolicy, StopEvent

__all__ = ["meter_fn"]


def meter_fn(
    camera: Camera,
    run_dir: Path,
    retry: RetryPolicy | None = None,
    stop: StopEvent | None = None,
    sleep: Callable[[float], object] = time.sleep,
) -> Callable[[float], np.ndarray]:
    """``capture_fn(t)`` for :func:`planner.meter`: one metering frame into ``RUN/meter/``, with
    the session's retries (busy: wait; disconnect or hang: reconnect; a bad file: capture again).
    Files of an earlier, interrupted metering stay; new ones never reuse their names.

    Parameters
    ----------
    camera : Camera
    run_dir : Path
        The run folder.
    retry : acquire.capture.session.RetryPolicy, optional
        Attempts, waits and the capture timeout (default: the session's).
    stop : threading.Event, optional
        Stops metering before the next attempt (:class:`acquire.capture.session.RunInterrupted`).
    sleep : callable
        How to wait between attempts.

    Returns
    -------
    callable
        ``capture_fn(t)``: exposure time in s -> the frame's raw values (DN).
    """
    from hdrcap.acquire.camera import fault_kind
    from hdrcap.acquire.capture.session import RetryPolicy, SessionError

    policy = retry or RetryPolicy()
    meter_dir = run_dir / "meter"
    meter_dir.mkdir(parents=True, exist_ok=True)
    counter = itertools.count(1)

    def capture(t: float) -> np.ndarray:
        stem = f"meter_{next(counter):02d}_{t:.6g}s"
        last = None
        for attempt in range(1, policy.max_attempts + 1):
            _stop_if_asked(stop, run_dir)
            try:
                return _meter_frame(camera, _free_name(meter_dir, stem, ".dng"), t, policy)
            except Exception as err:
                kind = fault_kind(err)
                if kind is None or kind == "fatal":
                    raise
                last = err
                if attempt < policy.max_attempts:
                    _recover(camera, kind, attempt, policy, sleep)
        raise SessionError(
            f"metering at {t:g} s: gave up after {policy.max_attempts} attempts (last: {last}); run again with --resume"
        )

    return capture


def _stop_if_asked(stop: StopEvent | None, run_dir: Path) -> None:
    if stop is not None and stop.is_set():
        from hdrcap.acquire.capture.session import RunInterrupted

        reason = getattr(stop, "reason", f"stopped by signal {stop.signum}")
        raise RunInterrupted(f"{run_dir}: {reason} while metering; run again with --resume", stop.signum)


def _meter_frame(camera: Camera, dest: Path, t: float, retry: RetryPolicy) -> np.ndarray:
    """One metering frame at ``t`` s into ``dest``: its raw values (a bad file: CorruptFrameError)."""
    from hdrcap.pipeline.io.raw import read_frame

    applied = float(camera.set_exposure(t))
    timeout = None if retry.timeout_s is None else applied + retry.timeout_s
    res = camera.capture(dest, timeout=timeout)
    try:
        return read_frame(res.path).data
    except (InputError, ValueError) as err:
        from hdrcap.acquire.camera import CorruptFrameError

        raise CorruptFrameError(f"metering frame {Path(res.path).name}: {err}") from None


def _recover(camera: Camera, kind: str, attempt: int, retry: RetryPolicy, sleep: Callable[[float], object]) -> None:
    """Before the next attempt: wait when the camera was busy, wait and reconnect when it was lost."""
    if kind in ("busy", "reconnect"):
        sleep(retry.wait(attempt))
    if kind == "reconnect":
        _reconnect_quietly(camera)


def _reconnect_quietly(camera: Camera) -> None:
    """Reconnect after a metering fault; a failed reconnect is one more fault for the retry loop
    (a fatal one stops)."""
    from hdrcap.acquire.camera import fault_kind

    try:
        camera.reconnect()
    except Exception as err:
        if fault_kind(err) in (None, "fatal"):
            raise


def _free_name(folder: Path, stem: str, suffix: str) -> Path:
    """``folder/stem+suffix``, or ``stem.2+suffix``, ... : the first name that does not exist."""
    path = folder / f"{stem}{suffix}"
    k = 1
    while path.exists():
        k += 1
        path = folder / f"{stem}.{k}{suffix}"
    return path
