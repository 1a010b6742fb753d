"""The ``hdrcap`` command line run in a subprocess, as a user runs it."""

from __future__ import annotations

import os
import subprocess
import sys

from tests.helpers import REPO


def run_cli(*args, cwd=None, check=False, timeout=600, env=None) -> subprocess.CompletedProcess:
    """Run ``hdrcap ARGS`` in a subprocess (``python -m hdrcap``, the installed package)."""
    full_env = dict(os.environ)
    if env:
        full_env.update(env)
    proc = subprocess.run(
        [sys.executable, "-m", "hdrcap", *map(str, args)],
        cwd=cwd or REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=full_env,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"hdrcap {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
    return proc
