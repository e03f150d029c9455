"""``lp3d serve``'s web app (Starlette): the page, the photo API and the live WebSocket.

Routes (every one needs the access token when the server has one: ``?token=`` or the
``X-LP3D-Token`` header):

* ``GET /``: the page (:mod:`lp3d.serve.page`), with ``lp3d share``'s content-security policy;
* ``POST /api/photo?detect=1&name=NAME``: the photo as the request body (at most
  :data:`~lp3d.serve.lifting.MAX_UPLOAD_BYTES`); answers one triplane message (its header: ``id``,
  ``description``, ``notes``, ``pose``, ``timings_ms``), or ``{"error": ...}`` with 400 (not a usable
  image), 413 (too large) or 503 (busy);
* ``GET /api/photo/ID.npz``, ``.html``, ``.glb`` and ``.gif``: the lifted photo's triplane file, its
  share page, a mesh and an orbit GIF, made in memory (:mod:`lp3d.serve.downloads`; results are kept
  in memory only, the last :data:`KEPT_PHOTOS`);
* ``POST /api/photo/ID/refine?steps=N``, ``GET /api/photo/ID/refine`` (progress, JSON) and
  ``GET /api/photo/ID/triplane`` (the current planes as a triplane message) (:mod:`lp3d.serve.jobs`);
* ``WS /ws/live``: the webcam stream (:mod:`lp3d.serve.live`).

Nothing is written to disk. Requests from another origin (a page elsewhere driving the local
server) and, on loopback, requests naming another host (DNS rebinding) are refused.
"""

from __future__ import annotations

import asyncio
import secrets
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from starlette.applications import Starlette
from starlette.requests import HTTPConnection, Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route, WebSocketRoute

from lp3d.photo import PhotoError
from lp3d.serve.downloads import DOWNLOADS, download_bytes
from lp3d.serve.jobs import PhotoStore, RefineJobs
from lp3d.serve.lifting import MAX_UPLOAD_BYTES, Lifter, triplane_message
from lp3d.serve.live import LiveLimits, live_endpoint
from lp3d.serve.page import PAGE_POLICY

__all__ = ["CONTENT_SECURITY_POLICY", "KEPT_PHOTOS", "LOOPBACK_HOSTS", "ServeState", "create_app"]

#: The page's policy (:data:`lp3d.serve.page.PAGE_POLICY`) as a header, where it can also forbid framing.
CONTENT_SECURITY_POLICY = PAGE_POLICY + "; frame-ancestors 'none'"
#: Lifted photos kept in memory for their downloads and refinement (the oldest go first).
KEPT_PHOTOS = 8
#: The names a loopback server answers to (anything else is a rebound DNS name).
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")


@dataclass
class ServeState:
    """What the app's handlers share: the lifter, the page, the token (None: none needed), whether
    the server is on loopback, the worker threads and the stores."""

    lifter: Lifter
    page: str
    script_hash: str
    token: str | None
    loopback: bool
    workers: ThreadPoolExecutor
    live_limits: LiveLimits = field(default_factory=LiveLimits)
    photos: PhotoStore = field(default_factory=lambda: PhotoStore(KEPT_PHOTOS))
    refine: RefineJobs | None = None
    max_upload_bytes: int = MAX_UPLOAD_BYTES
    busy_photos: int = 0
    max_busy_photos: int = 2
    live_clients: int = 0

    def headers(self) -> dict[str, str]:
        return {
            "Content-Security-Policy": CONTENT_SECURITY_POLICY.format(script_hash=self.script_hash),
            "X-Content-Type-Options": "nosniff",
            "Referrer-Policy": "no-referrer",
            "Cross-Origin-Opener-Policy": "same-origin",
            "Cache-Control": "no-store",
        }


def _error(message: str, status: int, state: ServeState) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status, headers=state.headers())


def refusal(conn: HTTPConnection, state: ServeState) -> str | None:
    """Why ``conn`` (a request or a WebSocket) is refused, or None: a wrong or missing token, a Host
    that a loopback server does not answer to, an Origin other than the page's own."""
    host = conn.headers.get("host", "")
    if state.loopback and urlsplit(f"//{host}").hostname not in {h.strip("[]") for h in LOOPBACK_HOSTS}:
        return f"this server answers to loopback names only, not {host!r}"
    origin = conn.headers.get("origin")
    if origin is not None and urlsplit(origin).netloc != host:
        return "requests from other sites are refused"
    if state.token is not None:
        given = conn.query_params.get("token") or conn.headers.get("x-lp3d-token") or ""
        if not secrets.compare_digest(given.encode(), state.token.encode()):
            return "this server needs its access token (printed when it started): open the address it printed"
    return None


async def read_body(request: Request, limit: int) -> bytes | None:
    """The request's body, or None once it passes ``limit`` bytes (the rest is not read)."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        return None
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            return None
        chunks.append(chunk)
    return b"".join(chunks)


def _photo_header(pid: str, result: Any) -> dict[str, Any]:
    return {
        "kind": "photo",
        "id": pid,
        "name": result.name,
        "description": result.description,
        "notes": result.notes,
        "pose": None if result.pose is None else list(result.pose),
        "timings_ms": result.timings_ms,
    }


def _name(request: Request) -> str:
    """The upload's name for messages: printable, short (it is the user's file name, shown as text)."""
    raw = request.query_params.get("name") or "upload"
    return "".join(ch for ch in raw if ch.isprintable())[:80] or "upload"


async def upload_photo(request: Request) -> Response:
    state: ServeState = request.app.state.serve
    body = await read_body(request, state.max_upload_bytes)
    name = _name(request)
    if body is None:
        limit = state.max_upload_bytes
        return _error(f"{name}: larger than the {limit / 2**20:.3g} MiB upload limit", 413, state)
    if state.busy_photos >= state.max_busy_photos:
        return _error("the server is lifting other photos; try again in a moment", 503, state)
    detect_flag = request.query_params.get("detect", "1")
    if detect_flag not in ("0", "1"):
        return _error("detect: must be 0 or 1", 400, state)
    detect = detect_flag == "1"
    state.busy_photos += 1
    try:
        loop = asyncio.get_running_loop()
        result = await loop.run_in_executor(
            state.workers, lambda: state.lifter.photo(body, name, detect=detect)
        )
    except (PhotoError, ValueError) as e:
        return _error(str(e), 400, state)
    finally:
        state.busy_photos -= 1
    pid = state.photos.add(result)
    message = triplane_message(result.triplane.planes, _photo_header(pid, result))
    return Response(message, media_type="application/octet-stream", headers=state.headers())


def _photo_or_404(request: Request, state: ServeState) -> tuple[str, Any] | Response:
    pid = request.path_params["pid"]
    result = state.photos.get(pid)
    if result is None:
        return _error("no such photo (the server keeps the last few only)", 404, state)
    return pid, result


async def download(request: Request) -> Response:
    state: ServeState = request.app.state.serve
    found = _photo_or_404(request, state)
    if isinstance(found, Response):
        return found
    _, result = found
    kind = request.path_params["kind"]
    if kind not in DOWNLOADS:
        kinds = ", ".join(f"ID.{k} ({what})" for k, (_, what) in DOWNLOADS.items())
        return _error(f"downloads are {kinds}", 404, state)
    stem = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in result.name.rsplit(".", 1)[0])[:60]
    title = f"{result.name} (lp3d serve)"
    try:
        # The mesh and the orbit take seconds: off the event loop, as the lifting is.
        body = await asyncio.get_running_loop().run_in_executor(
            state.workers, lambda: download_bytes(result.triplane, kind, title)
        )
    except ValueError as e:
        return _error(f"{result.name}: {DOWNLOADS[kind][1]}: {e}", 400, state)
    disposition = {"Content-Disposition": f'attachment; filename="{stem or "head"}.{kind}"'}
    return Response(body, media_type=DOWNLOADS[kind][0], headers={**state.headers(), **disposition})


async def current_triplane(request: Request) -> Response:
    state: ServeState = request.app.state.serve
    found = _photo_or_404(request, state)
    if isinstance(found, Response):
        return found
    pid, result = found
    message = triplane_message(result.triplane.planes, _photo_header(pid, result))
    return Response(message, media_type="application/octet-stream", headers=state.headers())


async def refine(request: Request) -> Response:
    state: ServeState = request.app.state.serve
    found = _photo_or_404(request, state)
    if isinstance(found, Response):
        return found
    pid, result = found
    if state.refine is None:
        return _error("refinement needs PyTorch on the server (pip install torch)", 501, state)
    if request.method == "GET":
        return JSONResponse(state.refine.progress(pid), headers=state.headers())
    try:
        steps = int(request.query_params.get("steps", "30"))
    except ValueError:
        return _error("steps: a whole number", 400, state)
    try:
        state.refine.start(pid, result, steps)
    except ValueError as e:
        return _error(str(e), 409 if "already" in str(e) else 400, state)
    return JSONResponse(state.refine.progress(pid), status_code=202, headers=state.headers())


async def page(request: Request) -> Response:
    state: ServeState = request.app.state.serve
    return Response(state.page, media_type="text/html; charset=utf-8", headers=state.headers())


class Guard:
    """ASGI middleware: every HTTP request and WebSocket passes :func:`refusal` first."""

    def __init__(self, app: Any, state: ServeState) -> None:
        self.app, self.state = app, state

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket"):
            why = refusal(HTTPConnection(scope), self.state)
            if why is not None:
                if scope["type"] == "websocket":
                    await send({"type": "websocket.close", "code": 1008, "reason": why[:120]})
                    return
                await _error(why, 403, self.state)(scope, receive, send)
                return
        await self.app(scope, receive, send)


def create_app(state: ServeState) -> Any:
    """The ASGI app of ``state`` (the Starlette app behind :class:`Guard`)."""
    routes = [
        Route("/", page),
        Route("/api/photo", upload_photo, methods=["POST"]),
        Route("/api/photo/{pid:str}.{kind:str}", download),
        Route("/api/photo/{pid:str}/refine", refine, methods=["GET", "POST"]),
        Route("/api/photo/{pid:str}/triplane", current_triplane),
        WebSocketRoute("/ws/live", live_endpoint),
    ]
    app = Starlette(routes=routes)
    app.state.serve = state
    return Guard(app, state)
