"""The command server (`hdrcap server`, hdrcap/cli/server.py) and its client (hdrcap/_client.py):
a command forked from the server gives what the same command gives in its own process (files
bit for bit, stdout, stderr, exit status), in the client's folder, environment and umask;
signals reach it; a killed, idle or different server leaves the command to run in-process."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from hdrcap import _client
from hdrcap.cli.server import check_peer
from hdrcap.pipeline.io.exr import read_exr, stored_precisions


def _run(args, env, cwd=None, umask=None, timeout=120) -> subprocess.CompletedProcess:
    """``hdrcap ARGS`` as the console script runs it (``python -m hdrcap``: the client)."""
    return subprocess.run(
        [sys.executable, "-m", "hdrcap", *map(str, args)],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=(lambda: os.umask(umask)) if umask is not None else None,
    )


def _env(runtime: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != _client.ENV_SWITCH}
    return env | {"XDG_RUNTIME_DIR": str(runtime)} | extra


def _status(env) -> dict:
    return json.loads(_run(["server", "status", "--json"], env).stdout)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(entry.name))
            except (OSError, IndexError, ValueError):
                pass
    return out


def _wait(condition, timeout=15.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


@contextmanager
def _server(env, idle_timeout=120):
    """A server of ``env``'s key (its pid and socket, as `server start` prints them), stopped (or
    killed) afterwards, with every process it forked."""
    proc = _run(["server", "start", "--idle-timeout", idle_timeout], env)
    found = re.search(r"\(pid (\d+)\) listening at (\S+)", proc.stdout)
    assert proc.returncode == 0 and found, (proc.stdout, proc.stderr)
    info = {"pid": int(found[1]), "socket": found[2]}
    try:
        yield info
    finally:
        _run(["server", "stop"], env, timeout=30)
        for pid in [info["pid"], *_children(info["pid"])]:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@contextmanager
def _runtime_dir():
    path = Path(tempfile.mkdtemp(prefix="hdrcap-srv-"))  # short: a socket path has 107 bytes at most
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="module")
def runtime():
    with _runtime_dir() as path:
        yield path


@pytest.fixture
def own_env():
    """The environment of a test's own server (a folder of its own)."""
    with _runtime_dir() as path:
        yield _env(path)


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    sim = tmp_path_factory.mktemp("sim")
    proc = subprocess.run(
        [sys.executable, "-m", "hdrcap", "simulate", "--camera", "camera-A", "--out", sim, "--size", "64x48"]
        + ["--darks", "--seed", "3"],
        env=dict(os.environ, HDRCAP_SERVER="0"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return sim


@pytest.fixture(scope="module")
def served(runtime):
    env = _env(runtime)
    with _server(env) as info:
        yield env, info


def _merge(bracket: Path, out: str, env, **kw) -> subprocess.CompletedProcess:
    frames = sorted(p.name for p in bracket.glob("frame_*.dng"))
    darks = sorted(p.name for p in bracket.glob("dark_*.dng"))
    return _run(["merge", *frames, "--darks", *darks, "--camera", "camera-A", "-o", out, "--json"], env, bracket, **kw)


def test_a_merge_through_the_server_is_the_merge_in_process(served, bracket):
    """Same file bit for bit (channels, storage, header), same stdout JSON and exit status; the
    relative paths are the client's (frames read and output written in its folder)."""
    env, _ = served
    before = _status(env)["requests"]
    a = _merge(bracket, "served.exr", env)
    assert _status(env)["requests"] == before + 1  # it did run on the server
    b = _merge(bracket, "alone.exr", env | {"HDRCAP_SERVER": "0"})
    assert _status(env)["requests"] == before + 1
    assert a.returncode == b.returncode == 0, (a.stderr, b.stderr)
    assert a.stderr == b.stderr == ""
    ja, jb = json.loads(a.stdout), json.loads(b.stdout)
    assert ja.pop("output") == "served.exr" and jb.pop("output") == "alone.exr"
    ja.pop("seconds"), jb.pop("seconds")
    assert ja == jb
    fa, fb = read_exr(bracket / "served.exr"), read_exr(bracket / "alone.exr")
    assert stored_precisions(bracket / "served.exr") == stored_precisions(bracket / "alone.exr")
    assert fa.header == fb.header
    assert set(fa.channels) == set(fb.channels)
    for name in fb.channels:
        assert fa.channels[name].tobytes() == fb.channels[name].tobytes(), name


def test_an_error_gives_the_same_line_and_status(served, tmp_path):
    env, _ = served
    args = ["merge", "missing.dng", "-o", "x.exr"]
    a = _run(args, env, tmp_path)
    b = _run(args, env | {"HDRCAP_SERVER": "0"}, tmp_path)
    assert (a.returncode, a.stdout, a.stderr) == (b.returncode, b.stdout, b.stderr)
    assert a.returncode == 2 and a.stderr == "hdrcap: error: missing.dng: no such file\n"


def test_the_command_has_the_clients_environment_and_umask(served, bracket, tmp_path):
    env, _ = served
    before = _status(env)["requests"]
    proc = _run(["calibrations", "list", "--json"], env | {"HDRCAP_DATA_DIR": str(tmp_path)}, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["folder"] == str(tmp_path / "calibrations")
    for umask, mode in ((0o077, 0o600), (0o022, 0o644)):
        out = f"umask{umask:o}.exr"
        proc = _merge(bracket, out, env, umask=umask)
        assert proc.returncode == 0, proc.stderr
        assert (bracket / out).stat().st_mode & 0o777 == mode
    assert _status(env)["requests"] == before + 3


@contextmanager
def _long_command(env, folder: Path, server_pid: int):
    """A client running `hdrcap serve` (a command that runs until stopped) on the server, once
    the command has started: (the client, the command's pid); both killed afterwards."""
    client = subprocess.Popen(
        [sys.executable, "-m", "hdrcap", "serve", folder, "--port", "0"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    children: list[int] = []
    try:
        assert "hdrcap serve: http://" in client.stderr.readline()  # the forked command's own stderr
        children = _children(server_pid)
        assert len(children) == 1
        yield client, children[0]
    finally:
        for pid in children:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        if client.poll() is None:
            client.kill()
        client.wait()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_to_the_client_ends_the_command(served, tmp_path, signum):
    env, info = served
    with _long_command(env, tmp_path, info["pid"]) as (client, child):
        client.send_signal(signum)
        client.wait(timeout=20)
        assert _wait(lambda: not _alive(child))
        assert not _children(info["pid"])


def test_a_different_key_runs_in_process(served):
    env, _ = served
    before = _status(env)["requests"]
    other = env | {"NUMBA_OPT": "2"}
    assert _client.server_key(other) != _client.server_key(env)
    proc = _run(["--version"], other)
    assert proc.returncode == 0 and "version" in proc.stdout
    assert _status(env)["requests"] == before


def test_status_start_twice_and_stop(own_env):
    env = own_env
    assert _status(env) == {"running": False, "key": _client.server_key(env)}
    with _server(env) as info:
        status = _status(env)
        assert status["key"] == _client.server_key(env) and status["requests"] == 0 and status["pid"] == info["pid"]
        assert Path(info["socket"]).exists() and Path(info["socket"]).parent.stat().st_mode & 0o777 == 0o700
        again = _run(["server", "start"], env)
        assert again.returncode == 0 and f"already running (pid {info['pid']})" in again.stdout
        stop = _run(["server", "stop"], env)
        assert stop.returncode == 0 and f"pid {info['pid']}" in stop.stdout
        assert _wait(lambda: not _alive(info["pid"]))
        assert not Path(info["socket"]).exists()
        assert not Path(info["socket"]).with_suffix(".pid").exists()
        assert _status(env)["running"] is False


def test_a_killed_server_leaves_a_socket_the_next_command_removes(own_env):
    env = own_env
    with _server(env) as info:
        os.kill(info["pid"], signal.SIGKILL)
        assert _wait(lambda: not _alive(info["pid"]))
        assert Path(info["socket"]).exists()
        proc = _run(["--version"], env)
        assert proc.returncode == 0 and "version" in proc.stdout
        assert not Path(info["socket"]).exists()


def test_a_server_ending_before_the_command_is_one_line_and_70(own_env, tmp_path):
    env = own_env
    with _server(env) as info, _long_command(env, tmp_path, info["pid"]) as (client, _child):
        os.kill(info["pid"], signal.SIGKILL)
        assert client.wait(timeout=20) == _client.EXIT_SERVER_LOST
        line = client.stderr.readline()  # the command itself goes on (it holds the pipe)
        assert line.startswith("hdrcap: error: the command server ended before the command"), line


def test_an_idle_server_ends_and_removes_its_socket(own_env):
    env = own_env
    with _server(env, idle_timeout=1) as info:
        assert _wait(lambda: not _alive(info["pid"]), timeout=20)
        assert not Path(info["socket"]).exists()


def test_the_peer_check():
    a, b = socket.socketpair(socket.AF_UNIX)
    with a, b:
        assert check_peer(a)
        assert not check_peer(a, uid=os.getuid() + 1)


def test_the_console_script_imports_no_click_numpy_or_cli(runtime):
    """The client decides where to run before it imports anything heavy."""
    code = (
        "import sys; from hdrcap import _client; _client.connect(); "
        "print(sorted(m for m in ('click', 'numpy', 'numba', 'hdrcap.cli') if m in sys.modules))"
    )
    proc = subprocess.run([sys.executable, "-c", code], env=_env(runtime), capture_output=True, text=True)
    assert proc.stdout.strip() == "[]", proc.stderr


def test_a_client_killed_outright_takes_its_command_with_it(served, tmp_path):
    """SIGKILL cannot be passed on: the server sees the client's connection close and kills the
    command, as the kernel would have in a command run in the client's own process."""
    env, info = served
    with _long_command(env, tmp_path, info["pid"]) as (client, child):
        client.kill()
        client.wait(timeout=20)
        assert _wait(lambda: not _alive(child))
        assert not _children(info["pid"])


def test_too_long_a_socket_folder_is_one_line_and_creates_nothing(tmp_path):
    runtime = tmp_path / ("x" * 100)
    proc = _run(["server", "start"], _env(runtime))
    assert proc.returncode == 2 and proc.stdout == ""
    assert (
        proc.stderr
        == f"hdrcap: error: {runtime}/hdrcap: too long a folder for the server's Unix socket; set XDG_RUNTIME_DIR to a shorter one\n"
    )
    assert not runtime.exists()


def test_a_batch_through_the_server_is_the_batch_in_process(served, bracket, tmp_path):
    """`hdrcap batch` forked from the server (its local workers spawned by the command) writes
    the archive the command writes in its own process."""
    import xarray as xr

    env, info = served
    runs = []
    for name in ("r1", "r2"):
        shutil.copytree(bracket, tmp_path / name)
        runs.append(tmp_path / name)
    args = ["batch", *runs, "--camera", "camera-A", "--workers", "1", "--threads", "1", "--json"]
    before = _status(env)["requests"]
    served_proc = _run([*args, "-o", tmp_path / "served.zarr"], env, timeout=300)
    own = _run([*args, "-o", tmp_path / "own.zarr"], env | {"HDRCAP_SERVER": "0"}, timeout=300)
    assert served_proc.returncode == own.returncode == 0, (served_proc.stderr, own.stderr)
    assert _status(env)["requests"] == before + 1
    reports = [json.loads(p.stdout.strip().splitlines()[-1]) for p in (served_proc, own)]
    assert [r["committed"] for r in reports] == [2, 2]
    a, b = xr.open_zarr(tmp_path / "served.zarr"), xr.open_zarr(tmp_path / "own.zarr")
    assert set(a.data_vars) == set(b.data_vars) and a.sizes == b.sizes
    for name in a.data_vars:
        assert np.array_equal(a[name].values, b[name].values, equal_nan=True), name


def test_a_command_starts_with_dask_config_as_it_is_now(monkeypatch):
    """dask reads its YAML files and DASK_* variables once, at import (in the server): a command's
    process reads them again (the variables are in the key; files can change meanwhile)."""
    import dask

    from hdrcap.cli.server import _fresh_process_state

    dask.config.set({"hdrcap-test-left-over": 1})  # as if set in the server, not by the command
    monkeypatch.setattr("tempfile.tempdir", None)
    _fresh_process_state()
    assert dask.config.get("hdrcap-test-left-over", None) is None
    assert dask.config.get("distributed.scheduler.work-stealing") is True  # distributed's defaults kept


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_ctrl_z_stops_the_command_and_fg_resumes_it(served, tmp_path):
    env, info = served
    with _long_command(env, tmp_path, info["pid"]) as (client, child):
        client.send_signal(signal.SIGTSTP)
        assert _wait(lambda: _state(child) == "T" and _state(client.pid) == "T")
        client.send_signal(signal.SIGCONT)
        assert _wait(lambda: _state(child) != "T" and _state(client.pid) != "T")
        client.send_signal(signal.SIGINT)
        client.wait(timeout=20)
        assert _wait(lambda: not _alive(child))
