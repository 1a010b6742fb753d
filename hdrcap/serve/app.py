"""The Starlette application of ``hdrcap serve``: pages, API routes and their errors.

Every route reads; none writes or runs anything (GET and HEAD only). Paths are checked by
:func:`hdrcap.serve.safety.child_path`, requests by :class:`hdrcap.serve.safety.Guard`.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

import anyio.to_thread
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.templating import Jinja2Templates

from hdrcap.pipeline.errors import InputError
from hdrcap.serve.cache import StampCache, file_stamp
from hdrcap.serve.events import StreamLimit, follow_events, follow_runs, tail_offset
from hdrcap.serve.runs import MAX_PAGE, RENDER_LOCK, RunIndex
from hdrcap.serve.safety import Guard, Refused, child_path
from hdrcap.serve.series import ArchiveSet

__all__ = ["create_app", "MAX_STREAMS"]

HERE = Path(__file__).resolve().parent
#: Event streams open at once, at most (more get 503).
MAX_STREAMS = 32
#: Rendered PNGs kept, bytes.
PNG_CACHE_BYTES = 64 * 2**20
#: Files sent inline with these types; any other file is sent as a download.
INLINE_TYPES = {
    ".png": "image/png",
    ".json": "application/json",
    ".jsonl": "text/plain; charset=utf-8",
    ".txt": "text/plain; charset=utf-8",
    ".log": "text/plain; charset=utf-8",
    ".toml": "text/plain; charset=utf-8",
    ".csv": "text/plain; charset=utf-8",
}


#: The images of a run page and their captions (app.js has the same).
CAPTIONS = {
    "preview": "tone-mapped preview (for looking at only)",
    "snr": "SNR, dB: 20 log10(irradiance / sigma); grey: not measured (nexp = 0)",
    "sigma": "log10 sigma; grey: not measured (nexp = 0)",
    "quality": "quality flags (the lowest flag of each photosite)",
}


def create_app(root: Path, archives: Sequence[Path] = (), token: str | None = None, loopback_only: bool = True) -> Any:
    """The web application over the run folders in ``root`` and the ``archives``.

    Parameters
    ----------
    root : Path
        Folder whose subfolders are run folders (``hdrcap run``'s ``[output] folder``).
    archives : sequence of Path
        zarr archives of ``hdrcap batch``.
    token : str, optional
        Required on every request when given (header, query parameter or cookie).
    loopback_only : bool
        Answer only requests whose Host header names this machine (serving on loopback).

    Returns
    -------
    ASGI application
        The Starlette application wrapped in :class:`hdrcap.serve.safety.Guard`.

    Raises
    ------
    InputError
        ``root`` or an archive is not a folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    for a in archives:
        if not Path(a).is_dir():
            raise InputError(f"{a}: not a zarr archive folder")
    state = _State(RunIndex(root), ArchiveSet(list(archives)))
    templates = Jinja2Templates(directory=str(HERE / "templates"))
    templates.env.globals.update(archives=list(state.archives.paths), root=str(state.runs.root))
    templates.env.filters["q"] = lambda s: quote(str(s), safe="")

    def page(request: Request, name: str, **context: Any) -> Response:
        return templates.TemplateResponse(request, name, context)

    # ------------------------------------------------------------------ pages
    def runs_page(request: Request) -> Response:
        limit, offset = _paging(request, 100)
        total, runs = state.runs.page(limit, offset)
        return page(request, "runs.html", title="Runs", runs=runs, total=total, limit=limit, offset=offset)

    def run_page(request: Request) -> Response:
        name = request.path_params["name"]
        detail = state.runs.detail(name)
        files = state.runs.files(name, "", 0, 100)
        return page(request, "run.html", title=name, run=detail, files=files, captions=CAPTIONS.items())

    def archive_page(request: Request) -> Response:
        info = state.archives.describe(request.path_params["name"])
        return page(request, "archive.html", title=info["name"], archive=info)

    # ------------------------------------------------------------------ API
    def api_runs(request: Request) -> Response:
        limit, offset = _paging(request, 100)
        total, runs = state.runs.page(limit, offset)
        headers = {"X-Total-Count": str(total)}
        if offset + limit < total:
            headers["Link"] = f'</api/runs?limit={limit}&offset={offset + limit}>; rel="next"'
        return JSONResponse(runs, headers=headers)

    def api_run(request: Request) -> Response:
        return JSONResponse(state.runs.detail(request.path_params["name"]))

    def api_image(request: Request) -> Response:
        name, kind = request.path_params["name"], request.path_params["kind"]
        if kind not in ("preview", "snr", "sigma", "quality"):
            raise Refused(404, "no such image")
        if kind == "preview":
            try:
                return FileResponse(state.runs.png_path(name), media_type="image/png")
            except Refused as err:
                if err.status != 404:
                    raise
        exr = state.runs.exr_path(name)
        return Response(state.png(name, kind, exr), media_type="image/png")

    async def api_events(request: Request) -> Response:
        from hdrcap.acquire.capture.manifest import EVENTS_NAME
        from hdrcap.acquire.capture.runfolder import run_is_active

        name = request.path_params["name"]
        folder = state.runs.folder(name)
        events = child_path(folder, EVENTS_NAME, must_exist=False)
        start = _int(request.headers.get("last-event-id"), "Last-Event-ID", 0, None, None)
        if start is None:
            tail = _int(request.query_params.get("tail"), "tail", 0, 100_000, None)
            start = 0 if tail is None else await anyio.to_thread.run_sync(tail_offset, events, tail)
        return _stream(
            state,
            follow_events(events, start, lambda: run_is_active(folder), lambda: state.runs.summary(name)),
        )

    async def api_stream(request: Request) -> Response:
        limit, offset = _paging(request, 100)

        def content() -> dict[str, Any]:
            total, runs = state.runs.page(limit, offset)
            return {"total": total, "offset": offset, "runs": runs}

        return _stream(state, follow_runs(content))

    def api_files(request: Request) -> Response:
        limit, offset = _paging(request, 100)
        folder = request.query_params.get("folder", "")
        return JSONResponse(state.runs.files(request.path_params["name"], folder, offset, limit))

    def api_file(request: Request) -> Response:
        path = state.runs.file(request.path_params["name"], request.path_params["path"])
        kind = INLINE_TYPES.get(path.suffix.lower())
        if kind is None:
            return FileResponse(path, media_type="application/octet-stream", filename=path.name)
        return FileResponse(path, media_type=kind)

    def api_archives(request: Request) -> Response:
        return JSONResponse(state.archives.list())

    def api_series(request: Request) -> Response:
        q = request.query_params
        y = _int(q.get("y"), "y", 0, None, None)
        x = _int(q.get("x"), "x", 0, None, None)
        size = _int(q.get("size"), "size", 1, None, 4)
        if y is None or x is None:
            raise InputError("y and x are required (the region's top left photosite)")
        return JSONResponse(state.archives.series(q.get("archive"), y, x, size or 4))

    def api_archive_preview(request: Request) -> Response:
        q = request.query_params
        run = _int(q.get("run"), "run", 0, None, None)
        name, path = state.archives.path(q.get("archive"))
        key = (name, run, file_stamp(path / ".zmetadata"))
        data = state.pngs.get(("archive", name, run), key, lambda: _locked(state.archives.preview, name, run))
        return Response(data, media_type="image/png")

    routes = [
        Route("/", runs_page),
        Route("/runs/{name}", run_page),
        Route("/archives/{name}", archive_page),
        Route("/api/runs", api_runs),
        Route("/api/runs/{name}", api_run),
        Route("/api/runs/{name}/{kind}.png", api_image),
        Route("/api/runs/{name}/events", api_events),
        Route("/api/runs/{name}/files", api_files),
        Route("/api/runs/{name}/files/{path:path}", api_file),
        Route("/api/archives", api_archives),
        Route("/api/archive/series", api_series),
        Route("/api/archive/preview.png", api_archive_preview),
        Route("/api/stream", api_stream),
        Mount("/static", StaticFiles(directory=str(HERE / "static")), name="static"),
    ]

    def refused(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, Refused)
        return _error(request, templates, exc.status, str(exc))

    def bad_input(request: Request, exc: Exception) -> Response:
        return _error(request, templates, 400, str(exc))

    def http_error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, HTTPException)
        return _error(request, templates, exc.status_code, str(exc.detail), exc.headers)

    app = Starlette(
        routes=routes,
        exception_handlers={Refused: refused, InputError: bad_input, HTTPException: http_error},
    )
    app.state.hdrcap = state
    return Guard(app, token, loopback_only)


class _State:
    """What the routes share: the run index, the archives, rendered PNGs, open streams."""

    def __init__(self, runs: RunIndex, archives: ArchiveSet):
        self.runs = runs
        self.archives = archives
        self.pngs: StampCache[bytes] = StampCache(512, PNG_CACHE_BYTES, size=len)
        self.streams = StreamLimit(MAX_STREAMS)

    def png(self, name: str, kind: str, exr: Path) -> bytes:
        """The run's preview or map drawn from its EXR (cached while the EXR is unchanged)."""

        def make() -> bytes:
            from hdrcap.pipeline.io.results import read_result
            from hdrcap.serve.images import map_png, preview_png

            with RENDER_LOCK:
                result = read_result(exr)
                if kind == "preview":
                    cfa = result.header.get("cfa_pattern")
                    return preview_png(result.irradiance, cfa if isinstance(cfa, str) and len(cfa) == 4 else None)
                return map_png(result, kind)

        return self.pngs.get(("run", name, kind), file_stamp(exr), make)


def _locked(fn: Any, *args: Any) -> Any:
    with RENDER_LOCK:
        return fn(*args)


def _stream(state: _State, body: AsyncIterator[bytes]) -> Response:
    """A ``text/event-stream`` response of ``body`` (503 when :data:`MAX_STREAMS` are open)."""
    if not state.streams.take():
        raise Refused(503, f"{MAX_STREAMS} event streams are open already; try again later")

    async def counted() -> AsyncIterator[bytes]:
        try:
            async for chunk in body:
                yield chunk
        except asyncio.CancelledError:
            raise
        finally:
            state.streams.give()

    return StreamingResponse(counted(), media_type="text/event-stream", headers={"X-Accel-Buffering": "no"})


def _int(value: str | None, name: str, lo: int, hi: int | None, default: int | None) -> int | None:
    """A query parameter as an integer in ``lo`` .. ``hi`` (InputError otherwise)."""
    if value is None or value == "":
        return default
    try:
        out = int(value)
    except ValueError:
        raise InputError(f"{name} must be a whole number, got {value!r}") from None
    if out < lo or (hi is not None and out > hi):
        raise InputError(f"{name} must be {lo} .. {hi if hi is not None else ''}, got {out}")
    return out


def _paging(request: Request, default: int) -> tuple[int, int]:
    q = request.query_params
    limit = _int(q.get("limit"), "limit", 1, MAX_PAGE, default)
    offset = _int(q.get("offset"), "offset", 0, None, 0)
    return int(limit or default), int(offset or 0)


def _error(
    request: Request, templates: Any, status: int, message: str, headers: Mapping[str, str] | None = None
) -> Response:
    """JSON ``{"error": message}`` for the API, a small page otherwise."""
    if request.url.path.startswith("/api/") or request.url.path.startswith("/static/"):
        return JSONResponse({"error": message}, status_code=status, headers=headers)
    return templates.TemplateResponse(
        request, "error.html", {"title": f"{status}", "status": status, "message": message}, status_code=status
    )
