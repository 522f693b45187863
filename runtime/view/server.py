"""The viewer's ASGI app: its own page and assets, the scene's data as JSON, frames over a websocket.

Security: it serves the files of its static folder (listed at start, by exact name) and the
one scene it was opened on; no request names a file to open. Requests with a body, long
URLs, unknown hosts (DNS rebinding) and websockets from other origins are refused with 4xx;
a malformed or oversized websocket message closes it with 4400 or 4413.
"""

from __future__ import annotations

import asyncio
import json
import math
import mimetypes
import struct
import traceback
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import BaseRoute, Route, WebSocketRoute
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocket, WebSocketDisconnect

from rigspace.runtime.view.scene import SceneModel
from rigspace.runtime.view.viewport import MAPS, VIEWS, FrameService

LOOPBACK = ("127.0.0.1", "localhost", "::1", "[::1]")
"""Host names the server binds without --allow-remote (the server's, the command's check too)."""
STATIC = Path(__file__).parent / "static"
MAX_URL = 2048
MAX_MESSAGE = 4096
"""Bytes in one websocket message from the page: its messages are a few hundred."""
POLL_SECONDS = 0.5
LIVE_SECONDS = 0.5


class Viewer:
    """The opened scene, its frames, and the connected pages."""

    def __init__(self, scene: SceneModel, frames: FrameService) -> None:
        self.scene = scene
        self.frames = frames
        self.worker = ThreadPoolExecutor(1, thread_name_prefix="rigspace-view-render")
        """Every Engine call and reload runs here, one at a time."""
        self.sockets: set[WebSocket] = set()

    def close(self) -> None:
        self.worker.shutdown(wait=True)
        self.frames.close()

    async def run(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.worker, fn, *args)

    def reload(self) -> bool:
        """Poll the layers; rebuild the engines when a layer changed and parsed."""
        if not self.scene.poll():
            return False
        if not self.scene.load_errors:
            self.frames.open()
        return True

    async def watch(self) -> None:
        """Reload on a layer change and tell every page."""
        while True:
            await asyncio.sleep(POLL_SECONDS)
            if await self.run(self.reload):
                message = json.dumps({"type": "reload", "version": self.scene.version,
                                      "error": self.frames.error})  # fmt: skip
                for ws in list(self.sockets):
                    try:
                        await ws.send_text(message)
                    except Exception:  # a page that went away meanwhile
                        self.sockets.discard(ws)


def _static_files() -> dict[str, tuple[bytes, str]]:
    """name -> (content, media type) of every asset, read once: nothing else is ever served."""
    files = {}
    for path in sorted(STATIC.iterdir()):
        if path.is_file():
            media = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
            if path.suffix == ".js":
                media = "text/javascript"
            files[path.name] = (path.read_bytes(), media)
    return files


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


def _time(request: Request) -> float:
    text = request.query_params.get("time", "0")
    value = float(text)  # ValueError -> 400
    if not math.isfinite(value):
        raise ValueError(text)
    return value


class Guard:
    """Refuses, before any route: long URLs (414), foreign hosts (400), methods other than
    GET (405), bodies (413), and websockets from foreign origins (403)."""

    def __init__(self, app: ASGIApp, hosts: set[str]) -> None:
        self.app, self.hosts = app, hosts

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        url = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"")
        host = _hostname("//" + headers.get("host", ""))
        length = headers.get("content-length", "0") or "0"
        status = None
        if url > MAX_URL:
            status, why = 414, f"the URL is longer than {MAX_URL} bytes"
        elif host not in self.hosts:
            status, why = 400, f"host {host!r} is not this viewer's"
        elif scope["type"] == "http" and scope["method"] not in ("GET", "HEAD"):
            status, why = 405, "the viewer only answers GET"
        elif not length.isdigit():
            status, why = 400, "Content-Length is not a number"
        elif int(length) > 0 or "transfer-encoding" in headers:
            status, why = 413, "requests carry no body"
        elif scope["type"] == "websocket" and "origin" in headers:
            if _hostname(headers["origin"]) not in self.hosts:
                status, why = 403, f"websocket from origin {headers['origin']!r}"
        if status is None:
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            if "websocket.http.response" in scope.get("extensions", {}):
                # The handshake itself is answered with the 4xx (servers that support it).
                body = json.dumps({"error": why}).encode()
                await send({"type": "websocket.http.response.start", "status": status,
                            "headers": [(b"content-type", b"application/json")]})  # fmt: skip
                await send({"type": "websocket.http.response.body", "body": body})
            else:
                await send({"type": "websocket.close", "code": 4000 + status})
            return
        await _error(status, why)(scope, receive, send)


def _hostname(url: str) -> str:
    """The host name of a URL or of "//host:port" ("" when it has none or does not parse)."""
    try:
        return urlsplit(url).hostname or ""
    except ValueError:
        return ""


def create_app(viewer: Viewer, host: str = "127.0.0.1") -> ASGIApp:
    """The viewer's app behind its Guard: the page and its assets, the scene's data as JSON,
    the frames' websocket; while it runs, a task reloads the scene when a layer changes."""
    routes: list[BaseRoute] = []
    _add_page_routes(routes, _static_files())
    _add_data_routes(routes, viewer)
    _add_prim_routes(routes, viewer)
    routes.append(WebSocketRoute("/ws", lambda ws: _socket(viewer, ws)))

    @asynccontextmanager
    async def lifespan(app):
        watcher = asyncio.create_task(viewer.watch())
        try:
            yield
        finally:
            watcher.cancel()

    app = Starlette(routes=routes, lifespan=lifespan)
    hosts = {*LOOPBACK, host.strip("[]")}
    return Guard(app, hosts)


def _add_page_routes(routes: list[BaseRoute], files: dict[str, tuple[bytes, str]]) -> None:
    """Add the page (/) and its assets (/static/NAME, exact names of `files` only)."""

    async def page(request: Request) -> Response:
        return Response(files["index.html"][0], media_type="text/html",
                        headers={"Cache-Control": "no-store"})  # fmt: skip

    async def static(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in files:  # exact names only: "..", "/" or "%2f" never reach the disk
            return _error(404, f"no asset {name!r}")
        content, media = files[name]
        return Response(content, media_type=media)

    routes += [Route("/", page), Route("/static/{name:path}", static)]


def _add_data_routes(routes: list[BaseRoute], viewer: Viewer) -> None:
    """Add the scene's JSON: /api/summary, /api/tree, /api/findings and /api/live."""

    def live_error() -> str | None:
        if viewer.frames.error:
            return "Live sources are not opened: the Engine refuses this scene (see the viewport)."
        return viewer.frames.live_error

    def summary() -> dict[str, Any]:
        frames = viewer.frames
        return {
            **viewer.scene.summary(),
            "render_error": frames.error,
            "camera": frames.camera,
            "reference": frames.with_reference,
            "live": frames.live,
            "maps": MAPS,
            "views": VIEWS,
            "size": [frames.width, frames.height],
        }

    routes += [
        Route("/api/summary", _data(lambda r: JSONResponse(summary()))),
        Route("/api/tree", _data(lambda r: JSONResponse(viewer.scene.tree()))),
        Route("/api/findings", _data(lambda r: JSONResponse(viewer.scene.findings()))),
        Route(
            "/api/live",
            _data(
                lambda r: JSONResponse(
                    {"bindings": viewer.frames.live_status(), "error": live_error()}
                )
            ),
        ),
    ]


def _add_prim_routes(routes: list[BaseRoute], viewer: Viewer) -> None:
    """Add one prim's JSON (?path=): /api/prim (its properties at ?time=), /api/composition."""

    def prim_of(request: Request):
        path = request.query_params.get("path", "")
        if len(path) > 1024:
            raise ValueError("path is too long")
        prim = viewer.scene.prim(path)
        if prim is None:
            raise LookupError(path)
        return prim

    def with_prim(handler):
        def endpoint(request: Request) -> Response:
            try:
                return JSONResponse(handler(prim_of(request), request))
            except LookupError as exc:
                return _error(404, f"no prim at {str(exc)!r}")

        return _data(endpoint)

    routes += [
        Route("/api/prim", with_prim(lambda p, r: viewer.scene.properties(p, _time(r)))),
        Route("/api/composition", with_prim(lambda p, r: viewer.scene.composition(p))),
    ]


def _data(handler):
    """An endpoint answering a bad parameter (a ValueError from `handler`) with a 400."""

    def endpoint(request: Request) -> Response:
        try:
            return handler(request)
        except ValueError as exc:
            return _error(400, f"bad parameter: {exc}")

    return endpoint


def parse_request(text: str, cameras: list[str]) -> dict[str, Any]:
    """A frame request from the page, checked field by field (ValueError: malformed)."""
    message = json.loads(text)
    if not isinstance(message, dict) or message.get("op") != "frame":
        raise ValueError("expected {op: 'frame', ...}")
    time = message.get("time")
    if not isinstance(time, int | float) or isinstance(time, bool) or not math.isfinite(time):
        raise ValueError("time must be a finite number")
    if message.get("map", "beauty") not in MAPS:
        raise ValueError(f"map must be one of {MAPS}")
    if message.get("view", "neural") not in VIEWS:
        raise ValueError(f"view must be one of {VIEWS}")
    if message.get("quality", "auto") not in ("auto", "preview", "full"):
        raise ValueError("quality must be auto, preview or full")
    camera = message.get("camera")
    if camera is not None and camera not in cameras:
        raise ValueError("camera must be one of the stage's cameras")
    request_id = message.get("id", 0)
    if not isinstance(request_id, int) or isinstance(request_id, bool):
        raise ValueError("id must be a whole number")
    return {"id": request_id, "time": float(time), "map": message.get("map", "beauty"),
            "view": message.get("view", "neural"), "quality": message.get("quality", "auto"),
            "camera": camera, "weights": _weights(message.get("weights", {}),
                                                  message.get("controls", {}))}  # fmt: skip


MAX_WEIGHTS = 256
"""Blend shape weights and control values a request may set (per request, over all
characters)."""
MAX_CONTROL = 1e6
"""A control's value in a request is at most this far from 0 (its own units; the control's
range is the slider's, docs/point_caches.md)."""


def _weights(value: Any, controls: Any = None) -> dict[str, dict[str, float]]:
    """The sliders' weights: {character path: {shape: number in [-2, 2]}}, and the control
    sliders' values {character path: {control: finite number}}, merged per character (the
    engine takes both as overrides: Engine.set_weights), at most MAX_WEIGHTS numbers in all
    (ValueError: malformed; the names are checked by the engine)."""
    out: dict[str, dict[str, float]] = {}
    kinds = (("blend shape", "weights", value, 2.0), ("control", "values", controls, MAX_CONTROL))
    for kind, plural, given, limit in kinds:
        given = {} if given is None else given
        if not isinstance(given, dict) or not all(isinstance(w, dict) for w in given.values()):
            raise ValueError(f"{kind} {plural} must be {{character path: {{{kind}: number}}}}")
        for path, shapes in given.items():
            for name, number in shapes.items():
                if (
                    not isinstance(number, int | float)
                    or isinstance(number, bool)
                    or not math.isfinite(number)
                    or abs(number) > limit
                ):
                    if kind == "control":
                        raise ValueError(
                            f"a control value must be a finite number within ±{limit:g}"
                        )
                    raise ValueError("a blend shape weight must be a number in [-2, 2]")
                out.setdefault(str(path), {})[str(name)] = float(number)
    if sum(len(w) for w in out.values()) > MAX_WEIGHTS:
        raise ValueError(f"at most {MAX_WEIGHTS} weights")
    return out


def _packet(header: dict[str, Any], data: bytes) -> bytes:
    """One binary message: header length (4 bytes, big-endian), JSON header, JPEG."""
    text = json.dumps(header).encode()
    return struct.pack(">I", len(text)) + text + data


async def _socket(viewer: Viewer, ws: WebSocket) -> None:
    await ws.accept()
    viewer.sockets.add(ws)
    latest: dict[str, Any] = {}
    wake = asyncio.Event()
    tasks = [
        asyncio.create_task(_render_requests(viewer, ws, latest, wake)),
        asyncio.create_task(_send_live_status(viewer, ws)),
    ]
    try:
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                break
            text = message.get("text")
            if text is None:
                await ws.close(4400, "binary messages are not accepted")
                break
            if len(text.encode()) > MAX_MESSAGE:
                await ws.close(4413, f"messages are at most {MAX_MESSAGE} bytes")
                break
            try:
                latest["request"] = parse_request(text, viewer.scene.cameras())
            except ValueError as exc:  # json's errors are ValueErrors too
                await ws.close(4400, f"malformed message: {exc}"[:120])
                break
            wake.set()
    except WebSocketDisconnect:
        pass
    finally:
        viewer.sockets.discard(ws)
        for task in tasks:
            task.cancel()
        for result in await asyncio.gather(*tasks, return_exceptions=True):
            # A page that left mid-send is normal; anything else is a bug and is shown.
            if isinstance(result, Exception) and not _closed(result):
                traceback.print_exception(result)


async def _render_requests(
    viewer: Viewer, ws: WebSocket, latest: dict[str, Any], wake: asyncio.Event
) -> None:
    """Each time `wake` is set, render the latest request (`latest["request"]`) and send its
    frames: a preview then the full frame for "auto", unless a newer request is waiting."""
    while True:
        await wake.wait()
        wake.clear()
        request = latest.pop("request", None)
        if request is None:
            continue
        if request["camera"] and request["camera"] != viewer.frames.camera:
            await viewer.run(viewer.frames.open, request["camera"])
        steps = {"auto": ("preview", "full"), "preview": ("preview",), "full": ("full",)}
        for quality in steps[request["quality"]]:
            if quality == "full" and "request" in latest:
                break  # a newer request waits: refining this one would only delay it
            header, data = await viewer.run(
                viewer.frames.frame, request["time"], request["map"], request["view"],
                quality, request["weights"],
            )  # fmt: skip
            header["id"] = request["id"]
            await ws.send_bytes(_packet(header, data))
            if header.get("quality") == "full" or "error" in header:
                break


async def _send_live_status(viewer: Viewer, ws: WebSocket) -> None:
    """Every LIVE_SECONDS while the stage is live, send the live bindings' status."""
    while True:
        await asyncio.sleep(LIVE_SECONDS)
        if viewer.frames.live:
            rows = await asyncio.to_thread(viewer.frames.live_status)
            await ws.send_text(json.dumps({"type": "live", "bindings": rows}))


def _closed(exc: Exception) -> bool:
    """Whether `exc` says the websocket was closed under a send."""
    return isinstance(exc, WebSocketDisconnect | RuntimeError) or type(exc).__name__.startswith(
        ("ConnectionClosed", "ClientDisconnected")
    )
