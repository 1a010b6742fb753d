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
    from hdrcap.planner.meter import MeterReport

__all__ = ["meter_fn", "refuse_unlit_metering", "METER_MIN_LIT_FRACTION"]

#: Metering whose frames show signal in fewer than this fraction of the photosites (saturated
#: or above the detection limit of the longest metering frame, 3 sigma of the read noise) saw
#: no light: the read noise alone crosses that limit in 0.1-0.3 % of them.
METER_MIN_LIT_FRACTION = 0.01


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
    from hdrcap.acquire.capture.session import RetryPolicy, SessionError, watch_stop

    policy = retry or RetryPolicy()
    watch_stop(camera, stop)
    if stop is not None and sleep is time.sleep:
        sleep = stop.wait  # a stop ends the wait
    meter_dir = run_dir / "meter"
    meter_dir.mkdir(parents=True, exist_ok=True)
    counter = itertools.count(1)

    def capture(t: float) -> np.ndarray:
        stem = f"meter_{next(counter):02d}_{t:.6g}s"
        last = ""
        for attempt in range(1, policy.max_attempts + 1):
            _stop_if_asked(stop, run_dir)
            try:
                return _meter_frame(camera, _free_name(meter_dir, stem, ".dng"), t, policy)
            except Exception as err:
                kind = fault_kind(err)
                if kind is None or kind == "fatal":
                    raise
                last = str(err)  # not the error: its traceback would keep the attempt's frames (open files) alive
                if attempt < policy.max_attempts:
                    _recover(camera, kind, attempt, policy, sleep, lambda: _stop_if_asked(stop, run_dir))
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
    from hdrcap.acquire.capture.session import check_applied_exposure
    from hdrcap.pipeline.io.raw import read_frame

    applied = float(camera.set_exposure(t))
    check_applied_exposure(t, applied, f"metering frame {dest.name}")
    timeout = None if retry.timeout_s is None else applied + retry.timeout_s
    res = camera.capture(dest, timeout=timeout)
    try:
        return read_frame(res.path).data
    except (InputError, ValueError) as err:
        from hdrcap.acquire.camera import CorruptFrameError

        raise CorruptFrameError(f"metering frame {Path(res.path).name}: {err}") from None


def _recover(
    camera: Camera,
    kind: str,
    attempt: int,
    retry: RetryPolicy,
    sleep: Callable[[float], object],
    stop_if_asked: Callable[[], None],
) -> None:
    """Before the next attempt: wait when the camera was busy, wait and reconnect when it was
    lost (not when the run was asked to stop meanwhile: ``stop_if_asked`` raises)."""
    if kind in ("busy", "reconnect"):
        sleep(retry.wait(attempt))
    stop_if_asked()
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


def refuse_unlit_metering(report: MeterReport, run_dir: Path) -> None:
    """Refuse metering that saw no light (the light still blocked by a lens cap or a cover
    command, a shutter closed): a plan from it would be of long exposures of darkness.

    Parameters
    ----------
    report : planner.meter.MeterReport
        What metering measured.
    run_dir : Path
        The run folder, for the message.

    Raises
    ------
    acquire.capture.session.VerificationError
        Fewer than :data:`METER_MIN_LIT_FRACTION` of the photosites show signal (exit status 7).
    """
    from hdrcap.acquire.capture.session import VerificationError

    lit = 1.0 - report.n_dark / max(report.n_pixels, 1)
    if lit < METER_MIN_LIT_FRACTION:
        raise VerificationError(
            f"{run_dir}: metering saw no light: {lit:.2%} of the photosites show signal even at "
            f"{max(report.times):g} s (detection limit {report.dark_limit or 0:.3g} e-/s); is the light still "
            "blocked (lens cap, cover command)? Unblock it, then run again with --resume"
        )
