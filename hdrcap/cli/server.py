"""The command server: one warm process that forks a process for each ``hdrcap`` command.

A fresh ``hdrcap merge`` spends most of a small bracket's time before the work: importing numba
and setting up its CPU target (about half a second of CPU). The server does that once
(:func:`prepare`), then waits on an ``AF_UNIX`` socket in a private folder for the console
script (:mod:`hdrcap._client`, which holds the protocol and the key that names the socket).
Each command is run by a process forked from the server with the client's descriptors 0-2,
working folder, environment, umask, ``sys.path`` and arguments, and ends as a command's
process does (:func:`hdrcap.cli.finish`). This module is the only place that forks.

The server runs one thread: no thread of its own, none of numba's thread pool (no parallel
kernel runs in it) is alive when it forks, and each command's process starts its own.
"""

from __future__ import annotations

import gc
import io
import json
import os
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from hdrcap import __version__, _client
from hdrcap.pipeline.errors import InputError

__all__ = ["check_peer", "ensure_state_dir", "prepare", "serve", "spawn", "stop", "status"]

#: Seconds ``hdrcap server start`` waits for a new server's socket to accept.
START_TIMEOUT = 60.0
#: Seconds a client has to send its request once connected.
REQUEST_TIMEOUT = 5.0


def ensure_state_dir(environ: dict[str, str] | None = None) -> str:
    """Create the servers' folder (:func:`hdrcap._client.state_dir`) with mode 0700 and return
    it; raises InputError when it belongs to another user or its sockets' paths would be too
    long for a Unix socket."""
    path = _client.state_dir(environ)
    try:
        _client.socket_path("0" * 12, environ)  # a key's length: checked before any folder is made
    except ValueError:
        raise InputError(
            f"{path}: too long a folder for the server's Unix socket; set XDG_RUNTIME_DIR to a shorter one"
        ) from None
    os.makedirs(path, mode=0o700, exist_ok=True)
    st = os.stat(path)
    if st.st_uid != os.getuid():
        raise InputError(f"{path}: belongs to another user; the command server needs a folder of its own")
    if st.st_mode & 0o077:
        os.chmod(path, 0o700)
    return path


def peer_uid(sock: socket.socket) -> int:
    """The user id of the process at the other end of the ``AF_UNIX`` socket (``SO_PEERCRED``)."""
    creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    _pid, uid, _gid = struct.unpack("3i", creds)
    return uid


def check_peer(sock: socket.socket, uid: int | None = None) -> bool:
    """Whether the peer of ``sock`` runs as ``uid`` (default: this process's user)."""
    return peer_uid(sock) == (os.getuid() if uid is None else uid)


#: Modules a command imports lazily that the server imports ahead (a merge of raw files to an
#: EXR: about 0.04 s of imports less in each command's process).
WARM_MODULES = (
    "hdrcap.cli",
    "hdrcap.pipeline.merge.files",
    "hdrcap.pipeline.merge.tiled",
    "hdrcap.pipeline.header",
    "hdrcap.pipeline.calibration.archive",
    "hdrcap.pipeline.io.raw",
    "hdrcap.pipeline.io.dngread",
    "hdrcap.pipeline.io.dngwrite",
    "hdrcap.pipeline.io.exr",
    "hdrcap.pipeline.io.results",
    "hdrcap.acquire.camera.model",
    "concurrent.futures.thread",
    "multiprocessing.synchronize",
    "OpenEXR",
    "tifffile",
    "hdrcap.batch.driver",
    "hdrcap.batch.archive",
    "hdrcap.acquire.capture.manifest",
    "hdrcap.pipeline.merge.weighting",
    "pebble",
    "multiprocessing.popen_spawn_posix",
    "distributed",
    "filelock",
    "tqdm",
)


def prepare() -> dict[str, float]:
    """Import what the commands use (:data:`WARM_MODULES`: hdrcap's commands, the readers and
    writers of a merge; numba and the merge kernels) and set up numba's CPU target, in this
    thread, running no kernel and loading none (loading a cached parallel kernel starts numba's
    thread pool, which a fork must not inherit).

    Returns
    -------
    dict
        Seconds of each step (``imports``, ``numba_target``).
    """
    import importlib

    t0 = time.perf_counter()
    for name in WARM_MODULES:
        try:
            importlib.import_module(name)
        except ImportError:  # an optional library missing: the command reports it, if it needs it
            pass
    from hdrcap.pipeline.merge.accumulator import import_kernels

    set_up = import_kernels()
    t1 = time.perf_counter()
    set_up()
    t2 = time.perf_counter()
    return {"imports": round(t1 - t0, 3), "numba_target": round(t2 - t1, 3)}


def _check_single_threaded() -> None:
    """Raise RuntimeError unless this process runs one Python thread and no numba thread pool."""
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    if threading.active_count() != 1 or getattr(parallel, "_is_initialized", False):
        raise RuntimeError("the command server must not fork with threads running")


@dataclass
class _State:
    """The server's bookkeeping."""

    key: str
    path: str
    pid_file: str
    idle_timeout: float
    started: str = field(default_factory=lambda: datetime.now(UTC).isoformat(timespec="seconds"))
    requests: int = 0
    children: dict[int, socket.socket] = field(default_factory=dict)
    last_activity: float = field(default_factory=time.monotonic)
    stopping: bool = False

    def describe(self) -> dict[str, Any]:
        return {
            "pid": os.getpid(),
            "key": self.key,
            "socket": self.path,
            "started": self.started,
            "requests": self.requests,
            "commands_running": len(self.children),
            "idle_timeout": self.idle_timeout,
            "version": __version__,
        }


def serve(idle_timeout: float = 3600.0, on_ready: Callable[[dict[str, Any]], None] | None = None) -> int:
    """Run the command server of this process's key until it is stopped (``hdrcap server
    stop``, SIGTERM, SIGINT) or idle for ``idle_timeout`` s (0: never); returns 0, or 1 when a
    server of the same key already listens. Removes its socket and pid file when it ends."""
    folder = ensure_state_dir()
    key = _client.server_key()
    path = _client.socket_path(key)
    if _client.request("status", key) is not None:
        return 1
    prepare()
    _check_single_threaded()
    # What the server imported moves to the collector's permanent generation: a command's
    # collections no longer walk it, so they neither cost its time nor write to (and copy) the
    # pages it shares with the server (the gc.freeze recipe for servers that fork)
    gc.collect()
    gc.freeze()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        os.unlink(path)  # a stale socket (the status request found nobody listening)
    except FileNotFoundError:
        pass
    listener.bind(path)
    os.chmod(path, 0o600)
    listener.listen(64)
    listener.setblocking(False)
    state = _State(key, path, os.path.join(folder, f"{key}.pid"), idle_timeout)
    _write_pid_file(state)
    server_pid = os.getpid()
    wake_r, wake_w = socket.socketpair()
    wake_r.setblocking(False)
    wake_w.setblocking(False)
    previous_wakeup = signal.set_wakeup_fd(wake_w.fileno())
    handlers = {s: signal.signal(s, _on_signal(state)) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    handlers[signal.SIGCHLD] = signal.signal(signal.SIGCHLD, lambda *_: None)
    sel = selectors.DefaultSelector()
    sel.register(listener, selectors.EVENT_READ, "accept")
    sel.register(wake_r, selectors.EVENT_READ, "wake")
    closing = [listener, wake_r, wake_w]
    try:
        if on_ready is not None:
            on_ready(state.describe())
        while True:
            _reap(state, sel)
            if state.stopping and not state.children:
                break
            timeout = None
            if state.idle_timeout > 0 and not state.children:
                timeout = state.last_activity + state.idle_timeout - time.monotonic()
                if timeout <= 0:
                    break
            for item, _ in sel.select(timeout):
                if item.data == "wake":
                    _drain(wake_r)
                elif isinstance(item.data, int):  # a running command's client wrote or went
                    _client_gone(item.fileobj, item.data, sel)  # type: ignore[arg-type]
                elif not state.stopping:
                    _accept(listener, state, sel, closing + [sel])
    finally:
        if os.getpid() == server_pid:  # never in a command's process unwinding (h5py's ending)
            for p in (path, state.pid_file):
                try:
                    os.unlink(p)
                except FileNotFoundError:
                    pass
            sel.close()
            for s in closing:
                s.close()
            signal.set_wakeup_fd(previous_wakeup)
            for signum, handler in handlers.items():
                signal.signal(signum, handler)
    return 0


def _on_signal(state: _State) -> Callable[[int, Any], None]:
    def handler(_signum: int, _frame: Any) -> None:
        state.stopping = True

    return handler


def _drain(sock: socket.socket) -> None:
    try:
        while sock.recv(4096):
            pass
    except BlockingIOError:
        pass


def _write_pid_file(state: _State) -> None:
    tmp = state.pid_file + ".tmp"
    with open(tmp, "w") as f:
        json.dump(state.describe() | {"executable": sys.executable}, f)
    os.replace(tmp, state.pid_file)


def _reap(state: _State, sel: selectors.BaseSelector) -> None:
    """Collect the ended commands' processes and send each client its exit status."""
    while state.children:
        try:
            pid, wstatus = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            pid = 0
        if pid == 0:
            return
        conn = state.children.pop(pid, None)
        if conn is None:
            continue
        try:
            sel.unregister(conn)
        except (KeyError, ValueError):  # unregistered when its client went
            pass
        signum = os.WTERMSIG(wstatus) if os.WIFSIGNALED(wstatus) else None
        code = 128 + signum if signum is not None else os.waitstatus_to_exitcode(wstatus)
        try:
            conn.sendall(json.dumps({"status": code, "signal": signum}).encode() + b"\n")
        except OSError:  # the client is gone
            pass
        conn.close()
        state.last_activity = time.monotonic()


def _client_gone(conn: socket.socket, pid: int, sel: selectors.BaseSelector) -> None:
    """The client of the running command ``pid`` closed its connection: it died without passing
    a signal on (SIGKILL, a crash). The command is killed as it would have been in the client's
    own process, rather than go on writing files nobody waits for."""
    try:
        data = conn.recv(4096)
    except BlockingIOError:
        return
    except OSError:
        data = b""
    if data:  # a client sends nothing once the command runs
        return
    sel.unregister(conn)
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _accept(listener: socket.socket, state: _State, sel: selectors.BaseSelector, closing: list[Any]) -> None:
    """Take one connection: a status or stop request, or a command to fork."""
    try:
        conn, _ = listener.accept()
    except BlockingIOError:
        return
    fds: list[int] = []
    try:
        conn.setblocking(True)
        conn.settimeout(REQUEST_TIMEOUT)
        if not check_peer(conn):
            conn.close()
            return
        message, fds = _client.read_message(conn, maxfds=3)
        op = message.get("op")
        if op == "run" and len(fds) == 3:
            state.requests += 1
            state.last_activity = time.monotonic()
            _check_single_threaded()
            for stream in (sys.stdout, sys.stderr):
                stream.flush()
            pid = os.fork()
            if pid == 0:
                _child(message, fds, [conn, *closing, *state.children.values()])
            state.children[pid] = conn
            conn.sendall(json.dumps({"pid": pid}).encode() + b"\n")
            conn.setblocking(False)
            sel.register(conn, selectors.EVENT_READ, pid)
            return
        if op == "stop":
            state.stopping = True
        if op in ("status", "stop"):
            conn.sendall(json.dumps(state.describe()).encode() + b"\n")
        conn.close()
    except (OSError, ConnectionError):  # a client gone or speaking nonsense: the server goes on
        conn.close()
    finally:
        for fd in fds:
            os.close(fd)


def _child(message: dict[str, Any], fds: list[int], closing: list[Any]) -> None:
    """The command's process: the client's descriptors, folder, environment, umask, path and
    arguments, then :func:`hdrcap.cli.main` and :func:`hdrcap.cli.finish`. Never returns."""
    status = 70
    try:
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.set_wakeup_fd(-1)
        for obj in closing:
            obj.close()
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        fds.clear()
        _new_stdio()
        os.chdir(message["cwd"])
        os.environ.clear()
        os.environ.update(message["environ"])
        from hdrcap.pipeline.io.files import set_umask

        set_umask(int(message["umask"]))
        sys.path[:] = list(message["path"])
        argv = [str(a) for a in message["argv"]]
        sys.argv = ["hdrcap", *argv]
        _fresh_process_state()
        import hdrcap.cli

        status = hdrcap.cli.main(argv)
        hdrcap.cli.finish(status)
    except SystemExit:  # finish() with h5py loaded: the interpreter ends the usual way
        raise
    except BaseException as err:  # noqa: BLE001  (a command's process never returns to the loop)
        try:
            print(f"hdrcap: internal error: {type(err).__name__}: {err}", file=sys.stderr, flush=True)
        finally:
            os._exit(70)
    os._exit(status)


def _new_stdio() -> None:
    """sys.stdin, stdout and stderr anew on descriptors 0-2, as the interpreter makes them at
    start-up (the server's encoding; line buffering on a terminal, stderr always)."""
    unbuffered = bool(getattr(sys.stdout, "write_through", False))  # -u or PYTHONUNBUFFERED
    streams = []
    for fd, like in ((0, sys.stdin), (1, sys.stdout), (2, sys.stderr)):
        tty = os.isatty(fd)
        raw = io.FileIO(fd, "rb" if fd == 0 else "wb", closefd=False)
        buffered: Any = io.BufferedReader(raw) if fd == 0 else (raw if unbuffered else io.BufferedWriter(raw))
        streams.append(
            io.TextIOWrapper(
                buffered,
                encoding=getattr(like, "encoding", None) or "utf-8",
                errors=getattr(like, "errors", None) or ("backslashreplace" if fd == 2 else "strict"),
                newline="\n",
                line_buffering=(tty or fd == 2) and fd != 0,
                write_through=unbuffered and fd != 0,
            )
        )
    sys.stdin, sys.stdout, sys.stderr = streams
    sys.__stdin__, sys.__stdout__, sys.__stderr__ = streams  # type: ignore[misc]


def _fresh_process_state() -> None:
    """Undo what a command's process would otherwise inherit from the server: the log handler on
    the server's stderr, the temporary folder found from the server's environment, numpy's
    global random state."""
    import logging
    import tempfile

    from hdrcap.cli import _HANDLER_NAME

    logger = logging.getLogger("hdrcap")
    for handler in list(logger.handlers):
        if handler.get_name() == _HANDLER_NAME:
            logger.removeHandler(handler)
    logger.setLevel(logging.NOTSET)
    tempfile.tempdir = None
    config = sys.modules.get("dask.config")
    if config is not None:  # read at import: the YAML files and DASK_* variables as they are now
        config.refresh()
    random = sys.modules.get("numpy.random")
    if random is not None:
        random.seed()


def spawn(idle_timeout: float, timeout: float = START_TIMEOUT) -> dict[str, Any]:
    """Start a server of this process's key in a new session, detached, its output in
    ``KEY.log`` in the state folder; wait until it answers and return its status. Raises
    InputError when it ends or does not answer within ``timeout`` s."""
    folder = ensure_state_dir()
    key = _client.server_key()
    log_path = os.path.join(folder, f"{key}.log")
    cmd = [
        sys.executable,
        *subprocess._args_from_interpreter_flags(),  # type: ignore[attr-defined]
        "-m",
        "hdrcap",
        "server",
        "start",
        "--foreground",
        "--idle-timeout",
        repr(float(idle_timeout)),
    ]
    with open(log_path, "ab") as log, open(os.devnull, "rb") as null:
        proc = subprocess.Popen(cmd, stdin=null, stdout=log, stderr=log, start_new_session=True, cwd=folder)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        answer = _client.request("status", key)
        if answer is not None and answer.get("pid") == proc.pid:
            return answer
        if proc.poll() is not None:
            answer = _client.request("status", key)
            if answer is not None:  # another start won the race
                return answer
            raise InputError(f"the command server ended at start (exit {proc.returncode}); see {log_path}")
        time.sleep(0.02)
    proc.terminate()
    proc.wait()
    raise InputError(f"the command server did not answer within {timeout:g} s; see {log_path}")


def status() -> dict[str, Any] | None:
    """The status of the server of this process's key (pid, key, socket, start time, requests
    served, commands running), or None when none runs."""
    return _client.request("status")


def stop(timeout: float = 60.0) -> dict[str, Any] | None:
    """Ask the server of this process's key to end once its running commands have ended, and
    wait up to ``timeout`` s for it to go; returns its last status, or None when none ran."""
    answer = _client.request("stop")
    if answer is None:
        return None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.kill(int(answer["pid"]), 0)
        except ProcessLookupError:
            return answer
        except PermissionError:  # another process has the pid now
            return answer
        if not os.path.exists(str(answer["socket"])):
            return answer
        time.sleep(0.02)
    raise InputError(f"the command server (pid {answer['pid']}) did not end within {timeout:g} s")
