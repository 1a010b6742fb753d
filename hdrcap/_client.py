"""The ``hdrcap`` console script: hands the command to a running command server, else runs it here.

A command server (``hdrcap server start``, :mod:`hdrcap.cli.server`) has imported hdrcap, numba
and the merge kernels once; each command sent to it runs in a process forked from it, so it
starts warm. This module is the client and imports only the standard library (and ``hdrcap``'s
own ``__init__``, which imports nothing), so that a command sent to a server does not pay for
click, numpy or numba in the client.

The server's socket is named by a *key* (:func:`server_key`) that hashes everything a forked
process would otherwise inherit from the server rather than from a fresh start: the
interpreter, hdrcap's version, location and sources, ``sys.path`` and the environment variables
read at import time. A client whose key names no listening socket runs the command in its own
process (:func:`hdrcap.cli.run`), as does ``HDRCAP_SERVER=0`` and every ``hdrcap server ...``
command.

Protocol (one connection per command, over an ``AF_UNIX`` stream socket in a private folder):
the client sends a 4-byte big-endian length and a JSON request (``op`` ``"run"``: argv, cwd,
environ, umask, sys.path) with its file descriptors 0, 1 and 2 attached (``SCM_RIGHTS``); the
server answers lines of JSON: ``{"pid": N}`` when the command's process is forked, then
``{"status": S, "signal": N or null}`` when it has ended (128 + N for a process ended by signal
N). ``op`` ``"status"`` and ``"stop"`` carry no descriptors and get one line each.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import struct
import sys

import hdrcap

TYPE_CHECKING = False
if TYPE_CHECKING:
    from typing import Any, NoReturn

__all__ = ["run", "server_key", "state_dir", "socket_path", "read_message", "send_message", "request"]

#: The environment variable that turns the client off: ``HDRCAP_SERVER=0`` runs every command in
#: the calling process.
ENV_SWITCH = "HDRCAP_SERVER"
#: Environment variables that a process reads at start-up or import (the interpreter, numba,
#: the BLAS and OpenMP thread pools, the locale and time zone, hdrcap's numba target), by prefix
#: or by name: a forked command behaves as a fresh process only where they match the server's.
KEY_ENV_PREFIXES = ("NUMBA_", "PYTHON", "OMP_", "MKL_", "OPENBLAS_", "GOTO_", "BLIS_", "NUMEXPR_", "LC_", "DASK_")
KEY_ENV_NAMES = ("HDRCAP_NUMBA_PREFER_256", "LANG", "LANGUAGE", "TZ", "LD_PRELOAD", "LD_LIBRARY_PATH")
#: The folders installed as hdrcap's packages (package-dir in pyproject.toml).
SUBPACKAGES = ("pipeline", "planner", "mock_camera", "acquire")
#: The exit status of a command whose server ended before the command did (EX_SOFTWARE).
EXIT_SERVER_LOST = 70
#: The signals the client passes on to the command's process while it waits.
FORWARDED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)
_MAX_SOCKET_PATH = 107  # sun_path is 108 bytes with its terminating NUL


def package_dirs() -> list[str]:
    """The folders of hdrcap's packages (``hdrcap`` and the four mapped ones), without importing
    the mapped packages."""
    from importlib.util import find_spec

    dirs = [os.path.dirname(os.path.abspath(hdrcap.__file__ or ""))]
    for name in SUBPACKAGES:
        spec = find_spec(f"hdrcap.{name}")
        dirs.extend(spec.submodule_search_locations or [] if spec else [])
    return dirs


def source_fingerprint(dirs: list[str]) -> tuple[int, int]:
    """(number of ``.py`` files, newest modification time in ns) under ``dirs``: it changes when
    a source file is edited, added or removed (under 1 ms for hdrcap's ~150 files)."""
    count, newest = 0, 0
    stack = list(dirs)
    while stack:
        try:
            entries = list(os.scandir(stack.pop()))
        except OSError:
            continue
        for entry in entries:
            if entry.name.endswith(".py") and entry.is_file():
                count += 1
                newest = max(newest, entry.stat().st_mtime_ns)
            elif entry.name != "__pycache__" and not entry.name.startswith(".") and entry.is_dir(follow_symlinks=False):
                stack.append(entry.path)
    return count, newest


def key_parts(environ: dict[str, str] | None = None) -> dict[str, Any]:
    """What must be the same in a client and a server for a command forked from the server to
    behave as in a fresh process (see the module docstring)."""
    env = os.environ if environ is None else environ
    dirs = package_dirs()
    return {
        "executable": os.path.realpath(sys.executable),
        "prefix": sys.prefix,
        "path": sys.path[1:],  # [0] is the script's folder or the cwd; the command gets the client's
        "flags": list(sys.flags),
        "version": hdrcap.__version__,
        "packages": dirs,
        "sources": source_fingerprint(dirs),
        "env": sorted((k, v) for k, v in env.items() if k.startswith(KEY_ENV_PREFIXES) or k in KEY_ENV_NAMES),
    }


def server_key(environ: dict[str, str] | None = None) -> str:
    """The server key of this interpreter and environment: 12 hex digits of a SHA-256 of
    :func:`key_parts`."""
    blob = json.dumps(key_parts(environ), sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:12]


def state_dir(environ: dict[str, str] | None = None) -> str:
    """The folder of the servers' sockets, pid files and logs: ``$XDG_RUNTIME_DIR/hdrcap``, else
    ``~/.cache/hdrcap/server`` (not created here)."""
    env = os.environ if environ is None else environ
    runtime = env.get("XDG_RUNTIME_DIR")
    if runtime:
        return os.path.join(runtime, "hdrcap")
    return os.path.join(os.path.expanduser("~"), ".cache", "hdrcap", "server")


def socket_path(key: str, environ: dict[str, str] | None = None) -> str:
    """The socket of the server of ``key``; raises ValueError when the path is too long for an
    ``AF_UNIX`` address (107 bytes)."""
    path = os.path.join(state_dir(environ), f"{key}.sock")
    if len(os.fsencode(path)) > _MAX_SOCKET_PATH:
        raise ValueError(f"{path}: too long for a Unix socket ({_MAX_SOCKET_PATH} bytes at most)")
    return path


def send_message(sock: socket.socket, message: dict[str, Any], fds: list[int] | None = None) -> None:
    """Send one length-prefixed JSON ``message`` with ``fds`` attached to its first bytes."""
    data = json.dumps(message).encode()
    data = struct.pack(">I", len(data)) + data
    sent = socket.send_fds(sock, [data], fds) if fds else sock.send(data)
    if sent < len(data):  # sendall(b"") would still send, and fail once the server has answered
        sock.sendall(data[sent:])


def read_message(sock: socket.socket, maxfds: int = 0, limit: int = 1 << 24) -> tuple[dict[str, Any], list[int]]:
    """Receive one message of :func:`send_message`: (the JSON object, the descriptors received,
    which the caller owns). Raises ConnectionError on a short or malformed message."""
    head, fds, flags, _ = socket.recv_fds(sock, 1 << 16, maxfds) if maxfds else (sock.recv(1 << 16), [], 0, None)
    try:
        if flags & getattr(socket, "MSG_CTRUNC", 0):
            raise ConnectionError("file descriptors truncated")
        if len(head) < 4:
            raise ConnectionError("short message")
        (size,) = struct.unpack(">I", head[:4])
        if size > limit:
            raise ConnectionError("message too long")
        data = bytearray(head[4:])
        while len(data) < size:
            chunk = sock.recv(size - len(data))
            if not chunk:
                raise ConnectionError("short message")
            data += chunk
        message = json.loads(bytes(data[:size]))
        if not isinstance(message, dict):
            raise ConnectionError("not a JSON object")
    except (ConnectionError, ValueError) as err:
        for fd in fds:
            os.close(fd)
        raise ConnectionError(str(err)) from None
    return message, fds


class _Lines:
    """The server's answers, one JSON object a line."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock, self.buf = sock, b""

    def next(self) -> dict[str, Any] | None:
        """The next answer, or None when the server closed the connection first."""
        while b"\n" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                return None
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        try:
            answer = json.loads(line)
        except ValueError:
            return None
        return answer if isinstance(answer, dict) else None


def connect(key: str | None = None, environ: dict[str, str] | None = None) -> socket.socket | None:
    """A connection to the server of ``key`` (default: this process's), or None when none
    listens; a socket nobody listens on (a server killed) is removed."""
    try:
        path = socket_path(key or server_key(environ), environ)
    except ValueError:
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(path)
    except ConnectionRefusedError:
        sock.close()
        try:
            os.unlink(path)  # stale: its server was killed
        except OSError:
            pass
        return None
    except OSError:  # no socket, no folder, no permission
        sock.close()
        return None
    return sock


def request(op: str, key: str | None = None, environ: dict[str, str] | None = None) -> dict[str, Any] | None:
    """Send the server of ``key`` the request ``op`` (``"status"``, ``"stop"``) and return its
    answer, or None when no server listens or it closed the connection without one."""
    sock = connect(key, environ)
    if sock is None:
        return None
    with sock:
        try:
            send_message(sock, {"op": op})
            return _Lines(sock).next()
        except OSError:
            return None


def _command_name(argv: list[str]) -> str | None:
    """The command of ``hdrcap [global options] COMMAND ...``: its first argument that is not an
    option (the global options take no value)."""
    return next((a for a in argv if not a.startswith("-")), None)


def _in_process() -> NoReturn:
    from hdrcap.cli import run as run_here

    run_here()
    raise SystemExit(0)  # not reached: run() ends the process


def run() -> None:
    """The ``hdrcap`` console script: the command runs in a process forked from the command
    server of this interpreter and environment when one listens (its exit status is this
    process's; SIGINT, SIGTERM, SIGHUP and SIGQUIT are passed on to it), else in this process.
    When the server ends before the command does: one line on stderr, exit status 70."""
    argv = sys.argv[1:]
    if os.environ.get(ENV_SWITCH) == "0" or _command_name(argv) == "server":
        _in_process()
    sock = connect()
    if sock is None:
        _in_process()
    status = _run_on_server(sock, argv)
    if status is None:  # the server took no command: nothing ran
        sock.close()
        _in_process()
    sys.exit(status)


def _run_on_server(sock: socket.socket, argv: list[str]) -> int | None:
    """The command's exit status, or None when the server refused it before starting it. SIGINT,
    SIGTERM, SIGHUP and SIGQUIT are passed on; SIGTSTP (Ctrl-Z) stops the command, then the
    client, and SIGCONT resumes both, as for a command in the client's own process."""
    pid: list[int] = []
    pending: list[int] = []

    def to_command(signum: int) -> None:
        try:
            os.kill(pid[0], signum)
        except OSError:  # it has ended
            pass

    def forward(signum: int, _frame: Any) -> None:
        if pid:
            to_command(signum)
        else:
            pending.append(signum)

    def suspend(_signum: int, _frame: Any) -> None:  # Ctrl-Z: the command stops, then the client
        if pid:
            to_command(signal.SIGSTOP)
        os.kill(os.getpid(), signal.SIGSTOP)

    def resume(_signum: int, _frame: Any) -> None:  # fg / bg: the command goes on with the client
        if pid:
            to_command(signal.SIGCONT)

    previous = {s: signal.signal(s, forward) for s in FORWARDED_SIGNALS}
    previous[signal.SIGTSTP] = signal.signal(signal.SIGTSTP, suspend)
    previous[signal.SIGCONT] = signal.signal(signal.SIGCONT, resume)
    try:
        umask = os.umask(0o022)
        os.umask(umask)
        lines = _Lines(sock)
        try:
            message = {
                "op": "run",
                "argv": argv,
                "cwd": os.getcwd(),
                "environ": dict(os.environ),
                "umask": umask,
                "path": sys.path,
            }
            send_message(sock, message, [0, 1, 2])
            started = lines.next()
        except OSError:  # no cwd, a descriptor closed, the server gone: nothing started
            return None
        if not started or not isinstance(started.get("pid"), int):
            return None
        pid.append(started["pid"])
        for signum in pending:
            forward(signum, None)
        try:
            ended = lines.next()
        except OSError:
            ended = None
        if not ended or not isinstance(ended.get("status"), int):
            print(
                f"hdrcap: error: the command server ended before the command did (pid {pid[0]})",
                file=sys.stderr,
            )
            return EXIT_SERVER_LOST
        return int(ended["status"])
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
