"""The console script's end (`hdrcap.cli.run`): exit status, flushed output, exit handlers run,
the interpreter's teardown skipped (os._exit) unless h5py is loaded."""

from __future__ import annotations

import subprocess
import sys

from hdrcap import __version__


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_exit_handlers_run_and_output_is_flushed_before_the_process_ends():
    code = (
        "import atexit, sys, tempfile, weakref\n"
        "from hdrcap.cli import run\n"
        "tmp = tempfile.TemporaryDirectory()\n"
        "print(tmp.name)\n"
        "atexit.register(lambda: print('handler ran'))\n"
        "sys.stdout.write('unflushed ')\n"
        "sys.argv = ['hdrcap', '--version']\n"
        "run()\n"
        "print('not reached')\n"
    )
    proc = _run(code)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert __version__ in proc.stdout and "unflushed" in proc.stdout
    assert lines[-1] == "handler ran" and "not reached" not in proc.stdout
    from pathlib import Path

    assert not Path(lines[0]).exists()  # TemporaryDirectory's finalizer is an exit handler too


def test_exit_status_of_an_error_is_kept():
    code = "import sys; from hdrcap.cli import run; sys.argv = ['hdrcap', 'merge', '/nonexistent/a.dng', '-o', 'x.exr']; run()"
    proc = _run(code)
    assert proc.returncode == 2  # bad input (EXIT_CODES)
    assert proc.stderr == "hdrcap: error: /nonexistent/a.dng: no such file\n"


def test_a_non_daemon_thread_is_waited_for():
    code = (
        "import sys, threading, time\n"
        "from hdrcap.cli import run\n"
        "threading.Thread(target=lambda: (time.sleep(0.5), print('thread done', flush=True))).start()\n"
        "sys.argv = ['hdrcap', '--version']\n"
        "run()\n"
    )
    proc = _run(code)
    assert proc.returncode == 0 and "thread done" in proc.stdout


def test_teardown_is_skipped_but_not_with_h5py():
    code = (
        "import sys, weakref\n"
        "from hdrcap.cli import run\n"
        "class Probe:\n"
        "    def __del__(self): print('teardown', flush=True)\n"
        "keep = Probe()\n"
        "{h5}\n"
        "sys.argv = ['hdrcap', '--version']\n"
        "run()\n"
    )
    assert "teardown" not in _run(code.format(h5="")).stdout
    assert "teardown" in _run(code.format(h5="import h5py")).stdout
