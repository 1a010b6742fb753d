"""``hdrcap serve``: a read-only web page and JSON API over run folders and run archives.

For a rig that captures unattended: which run is going on, which failed and why, what the last
measurement looks like, and how a region of the scene evolves over the runs of an archive.
The server reads run folders through :mod:`hdrcap.acquire.capture` (manifest, event log, run
state), EXR outputs through :mod:`hdrcap.pipeline`, archives through :mod:`hdrcap.batch`; it
writes nothing and runs nothing. See docs/serve.md.

Needs the ``serve`` extra (Starlette, uvicorn, Jinja2): ``pip install 'hdrcap[serve]'``.
"""

from __future__ import annotations

import importlib.util
import socket
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from hdrcap.pipeline.errors import InputError

__all__ = ["serve", "create_app", "missing_packages", "REQUIRED"]

#: Import names of the packages the server needs (the ``serve`` extra).
REQUIRED = ("starlette", "uvicorn", "jinja2", "anyio")


def missing_packages() -> list[str]:
    """The packages of :data:`REQUIRED` that are not installed.

    Returns
    -------
    list of str
    """
    missing = []
    for name in REQUIRED:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a module blocked in sys.modules
            found = False
        if not found:
            missing.append(name)
    return missing


def _require() -> None:
    missing = missing_packages()
    if missing:
        raise InputError(f"hdrcap serve needs {', '.join(missing)} (the serve extra): pip install 'hdrcap[serve]'")


def create_app(
    root: str | Path, archives: Sequence[str | Path] = (), token: str | None = None, loopback_only: bool = True
) -> Any:
    """The ASGI application (see :func:`hdrcap.serve.app.create_app`).

    Parameters
    ----------
    root : str or Path
        Folder whose subfolders are run folders.
    archives : sequence of str or Path
        zarr archives of ``hdrcap batch``.
    token : str, optional
        Required on every request when given.
    loopback_only : bool
        Answer only requests addressed to this machine by name (``localhost``, 127.0.0.1, ::1).

    Returns
    -------
    ASGI application

    Raises
    ------
    InputError
        The serve extra is missing; ``root`` or an archive is not a folder.
    """
    _require()
    from hdrcap.serve.app import create_app as _create

    return _create(Path(root), [Path(a) for a in archives], token, loopback_only)


def serve(
    root: str | Path,
    archives: Sequence[str | Path] = (),
    host: str = "127.0.0.1",
    port: int = 8765,
    token: str | None = None,
    echo: Callable[[str], None] = print,
    log_level: str = "warning",
) -> None:
    """Serve the web page until interrupted (Ctrl-C, SIGTERM).

    Parameters
    ----------
    root : str or Path
        Folder whose subfolders are run folders.
    archives : sequence of str or Path
        zarr archives of ``hdrcap batch``.
    host : str
        Address to listen on; anything but loopback needs ``token``.
    port : int
        TCP port (0: any free port).
    token : str, optional
        Required on every request when given (at least 16 characters).
    echo : callable
        Where the address being served is announced.
    log_level : str
        uvicorn's log level.

    Raises
    ------
    InputError
        The serve extra is missing, a host other than loopback without a token, the address
        cannot be listened on, ``root`` or an archive is not a folder.
    """
    from hdrcap.serve.safety import check_bind, is_loopback

    _require()
    token = check_bind(host, token)
    app = create_app(root, archives, token, loopback_only=is_loopback(host))
    sock = _listen(host, port)
    import uvicorn

    config = uvicorn.Config(
        app, log_level=log_level, access_log=False, timeout_graceful_shutdown=2, lifespan="off", proxy_headers=False
    )
    where = sock.getsockname()
    shown = f"[{where[0]}]" if ":" in where[0] else where[0]
    echo(
        f"hdrcap serve: http://{shown}:{where[1]}/ ({Path(root)}"
        + (f"; archives {', '.join(map(str, archives))}" if archives else "")
        + ("; token required" if token else "")
        + "); Ctrl-C stops"
    )
    uvicorn.Server(config).run(sockets=[sock])


def _listen(host: str, port: int) -> socket.socket:
    """A bound TCP socket for ``host``:``port`` (the server listens on it)."""
    try:
        family, kind, proto, _name, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except OSError as err:
        raise InputError(f"--host {host}: {err}") from None
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(addr)
    except OSError as err:
        sock.close()
        raise InputError(f"cannot listen on {host}:{port}: {err.strerror or err}") from None
    sock.listen(128)  # connections wait in the backlog until the server accepts them
    return sock
