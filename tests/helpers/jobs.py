"""Job files of the simulated camera (camera-B, an 'hdr' scene over 3 decades, matched dark
frames) and the retry policy the capture tests share."""

from __future__ import annotations

from pathlib import Path

from hdrcap.acquire.capture.session import RetryPolicy

#: Retries fast enough for tests (the session's policy otherwise waits seconds).
FAST = RetryPolicy(max_attempts=30, backoff_s=0.0005, max_backoff_s=0.002, timeout_s=0.02)

_JOB = """\
[job]
name = "{name}"

[camera]
backend = "mock"
preset = "camera-B"
size = "{size}"
seed = {seed}
{camera}

[scene]
name = "hdr"
decades = 3.0
x_max = 2e4

[exposure]
{exposure}

[darks]
{darks}

[session]
{session}
{calibration}
[output]
folder = "{folder}"
{output}
"""


def mock_job(
    path: Path,
    *,
    name: str = "job",
    size: str = "32x24",
    seed: int = 1,
    camera: str = "",
    times: str = "[0.004, 0.064, 0.5]",
    exposure: str | None = None,
    darks: str = 'strategy = "matched"',
    session: str = "backoff_s = 0.001\nmax_backoff_s = 0.001",
    calibration: str | None = None,
    folder: str | Path = "runs/{job}-{n}",
    output: str = "",
) -> Path:
    """Write a job file for the simulated camera at ``path`` and return ``path``. The strings
    are TOML lines of their section (``camera`` after its preset, size and seed; ``exposure``
    the whole section, default a bracket of ``times``; ``calibration`` a ``[calibration]``
    section's lines, none by default; ``output`` after the folder, also further sections)."""
    text = _JOB.format(
        name=name,
        size=size,
        seed=seed,
        camera=camera,
        exposure=exposure if exposure is not None else f'mode = "bracket"\ntimes = {times}',
        darks=darks,
        session=session,
        calibration="" if calibration is None else f"\n[calibration]\n{calibration}\n",
        folder=folder,
        output=output,
    )
    path.write_text(text)
    return path
