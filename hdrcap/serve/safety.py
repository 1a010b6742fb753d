"""What the web server lets through: paths inside its folders only, the token, the Host header.

Every path a request names is checked here (:func:`child_path`) and every request passes
:class:`Guard` (an ASGI middleware) before any route sees it.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
from http.cookies import SimpleCookie
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

from hdrcap.pipeline.errors import InputError

__all__ = [
    "TOKEN_ENV",
    "TOKEN_COOKIE",
    "Refused",
    "is_loopback",
    "check_bind",
    "child_path",
    "Guard",
]

#: Environment variable that gives the token when ``--token`` does not.
TOKEN_ENV = "HDRCAP_SERVE_TOKEN"
#: Cookie that carries the token after a page was opened with ``?token=``.
TOKEN_COOKIE = "hdrcap_token"

#: Headers every response gets: nothing may frame the page, sniff a type or load from elsewhere.
SECURITY_HEADERS = {
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "no-referrer",
    "content-security-policy": (
        "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
        "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
    ),
    "cache-control": "no-store",
}


class Refused(Exception):
    """A request the server does not answer with content: ``status`` 404 (no such thing, or a
    name that cannot be one), 403 (it exists but lies outside the served folders) or 503 (too
    many event streams open)."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or address, IPv6 with or without brackets) is this machine only.

    Parameters
    ----------
    host : str

    Returns
    -------
    bool
        True for ``localhost`` and the loopback addresses (127.0.0.0/8, ::1).
    """
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str | None) -> str | None:
    """The token the server requires when bound to ``host``: a host other than loopback needs
    one (an empty token counts as none).

    Parameters
    ----------
    host : str
        The address to bind.
    token : str or None
        ``--token``, else the environment's :data:`TOKEN_ENV`.

    Returns
    -------
    str or None
        The token (None: no token, loopback only).

    Raises
    ------
    InputError
        A host other than loopback without a token, or a token shorter than 16 characters.
    """
    token = token or None
    if token is None and not is_loopback(host):
        raise InputError(
            f"--host {host} serves other machines: give a token with --token or {TOKEN_ENV} "
            "(e.g. python -c 'import secrets; print(secrets.token_urlsafe())')"
        )
    if token is not None and len(token) < 16:
        raise InputError("the token must have at least 16 characters")
    return token


def child_path(base: Path, *parts: str, must_exist: bool = True) -> Path:
    """``base / parts...`` when it is a path inside ``base`` the server may show.

    Each part is one name: not empty, not ``.`` or ``..``, no slash, backslash or NUL, not
    hidden (a leading dot: lock files, unfinished downloads). The result, with every symbolic
    link resolved, must lie inside ``base`` (resolved too).

    Parameters
    ----------
    base : Path
        A served folder (ROOT, a run folder, an archive).
    *parts : str
        Names below it, already percent-decoded.
    must_exist : bool
        Refuse a path that does not exist.

    Returns
    -------
    Path
        The resolved path.

    Raises
    ------
    Refused
        404 for a bad or missing name, 403 for a path that leaves ``base``.
    """
    for part in parts:
        if not part or part in (".", "..") or part.startswith(".") or any(c in part for c in "/\\\0"):
            raise Refused(404, "no such path")
    root = base.resolve()
    path = root.joinpath(*parts)
    try:
        real = path.resolve(strict=must_exist)
    except (OSError, RuntimeError):  # missing, or a symlink loop
        raise Refused(404, "no such path") from None
    if not real.is_relative_to(root):
        raise Refused(403, "outside the served folders")
    return real


def _given_token(scope: dict[str, Any], headers: dict[str, str]) -> tuple[str | None, bool]:
    """(token the request carries, whether it came in the query string)."""
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip(), False
    if "x-hdrcap-token" in headers:
        return headers["x-hdrcap-token"], False
    query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
    if query.get("token"):
        return query["token"][-1], True
    cookie = SimpleCookie()
    try:
        cookie.load(headers.get("cookie", ""))
    except Exception:
        return None, False
    return (cookie[TOKEN_COOKIE].value if TOKEN_COOKIE in cookie else None), False


class Guard:
    """ASGI middleware in front of every route.

    - With ``loopback_only`` the Host header must name this machine (``localhost``,
      ``127.x.x.x``, ``[::1]``, any port): a web page elsewhere cannot reach the server by
      pointing its own name at 127.0.0.1 (DNS rebinding). Else 400.
    - With a ``token`` every request must carry it: ``Authorization: Bearer TOKEN``, an
      ``X-Hdrcap-Token`` header, ``?token=TOKEN``, or the cookie a page opened with
      ``?token=`` gets (HttpOnly, SameSite=Strict). Else 401.
    - Every response gets :data:`SECURITY_HEADERS`.

    Parameters
    ----------
    app : ASGI application
    token : str or None
    loopback_only : bool
    """

    def __init__(self, app: Any, token: str | None, loopback_only: bool):
        self.app = app
        self.token = token
        self.loopback_only = loopback_only

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        host = headers.get("host", "")
        if self.loopback_only and not is_loopback(_host_name(host)):
            await _plain(send, 400, {"error": "this server answers requests for localhost only"})
            return
        set_cookie = False
        if self.token is not None:
            given, from_query = _given_token(scope, headers)
            if given is None or not hmac.compare_digest(given.encode(), self.token.encode()):
                await _plain(send, 401, {"error": "a token is required (see docs/serve.md)"}, bearer=True)
                return
            set_cookie = from_query

        async def send_with_headers(message: dict[str, Any]) -> None:
            if message["type"] == "http.response.start":
                extra = [(k.encode(), v.encode()) for k, v in SECURITY_HEADERS.items()]
                if set_cookie:
                    extra.append(
                        (
                            b"set-cookie",
                            f"{TOKEN_COOKIE}={self.token}; Path=/; HttpOnly; SameSite=Strict".encode(),
                        )
                    )
                have = {k.lower() for k, _v in message.get("headers", [])}
                message = dict(message)
                message["headers"] = list(message.get("headers", [])) + [e for e in extra if e[0] not in have]
            await send(message)

        await self.app(scope, receive, send_with_headers)


def _host_name(host: str) -> str:
    """The name of a Host header without its port (``[::1]:80`` -> ``::1``)."""
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


async def _plain(send: Any, status: int, body: dict[str, Any], bearer: bool = False) -> None:
    data = json.dumps(body).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode())]
    headers += [(k.encode(), v.encode()) for k, v in SECURITY_HEADERS.items()]
    if bearer:
        headers.append((b"www-authenticate", b"Bearer"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": data})
