"""The console's web server: a static page, two WebSockets (state, JPEG frames) and the control actions.

Starlette app served by uvicorn in the main thread (or a thread in tests); the loop runs in its own
thread (:class:`~targetlock.console.session.ConsoleSession`). Frames go newest-only: one encoder task
JPEG-encodes the newest tracked frame (in a worker thread) whenever at least one page watches, and
each page gets the next frame only after it acknowledged drawing the previous one, so a slow or
vanished browser delays nobody but itself.

Security: on loopback no token is needed; bound to any other address a token is required on every
HTTP request and WebSocket (query ``token=``, header ``X-Targetlock-Token`` or the cookie the page
gets on its first load). WebSockets and POSTs whose ``Origin`` is not this server are refused.
"""
from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import secrets
import socket
import struct
import threading
from dataclasses import dataclass
from http.cookies import SimpleCookie
from pathlib import Path
from urllib.parse import parse_qs

import cv2
import numpy as np
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from ..config import ConfigError
from .session import PLOT_COLUMNS, ConsoleSession, Frame

__all__ = ["ConsoleServer", "make_app", "is_loopback", "new_token", "TOKEN_HEADER", "TOKEN_COOKIE"]

log = logging.getLogger("targetlock.console")

STATIC = Path(__file__).parent / "static"
TOKEN_HEADER = "x-targetlock-token"
TOKEN_COOKIE = "targetlock_token"
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def is_loopback(host: str) -> bool:
    return host in LOOPBACK or host.startswith("127.")


def new_token() -> str:
    return secrets.token_urlsafe(24)


def _finite(v):
    """JSON has no NaN: None instead (drawn as a gap in the plots)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _json_clean(obj):
    if isinstance(obj, dict):
        return {k: _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        obj = obj.item()
    return _finite(obj)


# ------------------------------------------------------------------------------------------ security
class Guard:
    """ASGI middleware: token (when one is set) on every request, same-origin WebSockets and POSTs."""

    def __init__(self, app, token: str | None) -> None:
        self.app = app
        self.token = token

    def _token_ok(self, scope) -> tuple[bool, bool]:
        """(allowed, came in the query string: set the cookie)."""
        if self.token is None:
            return True, False
        headers = dict(scope.get("headers") or [])
        given = headers.get(TOKEN_HEADER.encode(), b"").decode("latin-1")
        from_query = False
        if not given:
            q = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
            if q:
                given, from_query = q[0], True
        if not given:
            cookie = SimpleCookie(headers.get(b"cookie", b"").decode("latin-1"))
            if TOKEN_COOKIE in cookie:
                given = cookie[TOKEN_COOKIE].value
        return bool(given) and hmac.compare_digest(given.encode(), self.token.encode()), from_query

    @staticmethod
    def _origin_ok(scope) -> bool:
        headers = dict(scope.get("headers") or [])
        origin = headers.get(b"origin")
        if origin is None:
            return True   # not a browser (curl, scripts): nothing cross-site to fear
        host = headers.get(b"host", b"").decode("latin-1")
        return origin.decode("latin-1") in (f"http://{host}", f"https://{host}")

    async def __call__(self, scope, receive, send):
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        ok, from_query = self._token_ok(scope)
        client = scope.get("client") or ("?", 0)
        if not ok:
            log.warning("console: refused %s %s from %s: missing or wrong token", kind, scope.get("path"), client[0])
            return await self._refuse(kind, send, 401, "token required")
        if (kind == "websocket" or scope.get("method") == "POST") and not self._origin_ok(scope):
            log.warning("console: refused %s %s from %s: foreign origin", kind, scope.get("path"), client[0])
            return await self._refuse(kind, send, 403, "foreign origin")
        if from_query and kind == "http":
            cookie = f"{TOKEN_COOKIE}={self.token}; Path=/; HttpOnly; SameSite=Strict".encode()

            async def send_with_cookie(message):
                if message["type"] == "http.response.start":
                    message = dict(message, headers=list(message.get("headers", [])) + [(b"set-cookie", cookie)])
                await send(message)
            return await self.app(scope, receive, send_with_cookie)
        return await self.app(scope, receive, send)

    @staticmethod
    async def _refuse(kind: str, send, status: int, text: str) -> None:
        if kind == "websocket":
            await send({"type": "websocket.close", "code": 1008})   # before accept: HTTP 403 to the client
            return
        body = text.encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"text/plain"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


# ------------------------------------------------------------------------------------------ frames
def encode_frame(frame: Frame, camera, quality: int = 80) -> bytes:
    """Binary message: 4-byte big-endian header length, JSON header, JPEG."""
    ok, jpg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    r = frame.result
    pos = [_finite(float(r.position_px[0])), _finite(float(r.position_px[1]))]
    head = json.dumps({"seq": frame.seq, "wall_ms": frame.wall_time * 1e3, "x": pos[0], "y": pos[1],
                       "valid": bool(r.valid), "lost": bool(r.lost), "confidence": float(r.confidence),
                       "window": frame.window_px, "width": int(frame.image.shape[1]), "height": int(frame.image.shape[0]),
                       "cx": float(camera.cx), "cy": float(camera.cy)}).encode()
    return struct.pack(">I", len(head)) + head + jpg.tobytes()


@dataclass
class _Message:
    seq: int = 0
    payload: bytes | str = b""


class _NewestHub:
    """A message produced once for all pages, only while at least one watches; a page that is slow to
    take one skips to the newest. Subclasses produce in :meth:`_produce` and hand over with :meth:`_publish`."""

    def __init__(self) -> None:
        self.current = _Message()
        self.watchers = 0
        self._new = asyncio.Event()
        self._task: asyncio.Task | None = None

    async def _produce(self) -> None:
        raise NotImplementedError

    def _publish(self, seq: int, payload: bytes | str) -> None:
        self.current = _Message(seq, payload)
        self._new.set()
        self._new = asyncio.Event()

    async def _run(self) -> None:
        try:
            await self._produce()
        finally:
            self._task = None

    def watch(self) -> None:
        self.watchers += 1
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run())

    def unwatch(self) -> None:
        self.watchers -= 1

    async def newer_than(self, seq: int) -> _Message:
        while self.current.seq <= seq:
            await self._new.wait()
        return self.current


class FrameHub(_NewestHub):
    """The newest tracked frame as a binary message (:func:`encode_frame`), JPEG-encoded in a worker thread."""

    def __init__(self, session: ConsoleSession, quality: int = 80, poll: float = 0.005) -> None:
        super().__init__()
        self.session = session
        self.quality = quality
        self.poll = poll             # s between looks at the tracker's slot
        self.encode_seconds = 0.0
        self.encoded_frames = 0

    async def _produce(self) -> None:
        tap = self.session.tap
        if tap is None:
            return                   # a rig without a camera: no frames
        cam = self.session.cfg.twin.camera
        while self.watchers > 0:
            frame = tap.newest()
            if frame is not None and frame.seq > self.current.seq:
                t0 = asyncio.get_running_loop().time()
                payload = await run_in_threadpool(encode_frame, frame, cam, self.quality)
                self.encode_seconds += asyncio.get_running_loop().time() - t0
                self.encoded_frames += 1
                self._publish(frame.seq, payload)
            await asyncio.sleep(self.poll)


class StateHub(_NewestHub):
    """Status and the plot rows since the previous message, every ``period`` s (a slow page's plot has a gap)."""

    def __init__(self, session: ConsoleSession, period: float) -> None:
        super().__init__()
        self.session = session
        self.period = period

    async def _produce(self) -> None:
        last, _, _ = self.session.rows_since(1 << 62)
        while self.watchers > 0:
            last, rows, sig = self.session.rows_since(last)
            msg = {"status": self.session.status(), "columns": PLOT_COLUMNS, "rows": rows, "signals": sig}
            self._publish(self.current.seq + 1, json.dumps(_json_clean(msg)))
            await asyncio.sleep(self.period)


# ------------------------------------------------------------------------------------------ app
def make_app(session: ConsoleSession, *, token: str | None = None, hub: FrameHub | None = None,
             state_period: float = 0.1) -> Guard:
    """The console's ASGI app (wrapped in the token/origin guard); ``state_period`` (s) between state messages."""
    hub = hub or FrameHub(session)
    states = StateHub(session, state_period)

    async def index(request: Request):
        return FileResponse(STATIC / "index.html", headers={"cache-control": "no-store"})

    async def state(request: Request):
        return JSONResponse(_json_clean(session.status()))

    def who(request) -> str:
        c = request.client
        return f"{c.host}:{c.port}" if c else "?"

    async def act(request: Request):
        name = request.path_params["action"]
        try:
            body = await request.json() if (await request.body()) else {}
        except ValueError:
            return JSONResponse({"error": "request body is not JSON"}, status_code=400)
        w = who(request)
        actions = {
            "select": lambda: session.select(float(body["x"]), float(body["y"]),
                                             None if body.get("window") is None else int(body["window"]), who=w),
            "engage": lambda: session.engage(who=w),
            "release": lambda: session.release(who=w),
            "stop": lambda: session.stop(who=w),
            "enable": lambda: session.enable(who=w),
            "tune": lambda: {"controller": session.tune(dict(body), who=w)},
            "record-start": lambda: {"folder": session.record_start(who=w)},
            "record-stop": lambda: {"summary": session.record_stop(who=w)},
            "target-path": lambda: session.set_target_path(str(body["path"]), who=w),
            "target-move": lambda: session.nudge_target(float(body["dx"]), float(body["dy"]), who=w),
        }
        if name not in actions:
            return JSONResponse({"error": f"unknown action {name!r}"}, status_code=404)
        if not isinstance(body, dict):
            return JSONResponse({"error": "request body must be a JSON object"}, status_code=400)
        try:
            out = await run_in_threadpool(actions[name]) or {}   # recording plots: off the event loop
        except (ConfigError, KeyError, TypeError, ValueError) as exc:
            msg = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
            return JSONResponse({"error": msg}, status_code=400)
        return JSONResponse(_json_clean({"ok": True, **out}))

    async def ws_state(ws: WebSocket):
        await ws.accept()
        states.watch()
        try:
            _, rows, sig = session.rows_since(0)        # the history first, then what every page gets
            seq = states.current.seq
            msg = {"status": session.status(), "columns": PLOT_COLUMNS, "rows": rows, "signals": sig}
            await ws.send_text(json.dumps(_json_clean(msg)))
            while True:
                m = await states.newer_than(seq)
                seq = m.seq
                await ws.send_text(str(m.payload))
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            states.unwatch()

    async def ws_frames(ws: WebSocket):
        await ws.accept()
        h = hub
        h.watch()
        seq = 0
        try:
            while True:
                enc = await h.newer_than(seq)
                seq = enc.seq
                payload = enc.payload
                await ws.send_bytes(payload.encode() if isinstance(payload, str) else payload)
                await ws.receive_text()       # the page drew it: only then the next (newest) one
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            h.unwatch()

    async def health(request: Request):
        return PlainTextResponse("ok")

    app = Starlette(routes=[
        Route("/", index),
        Route("/health", health),
        Route("/api/state", state),
        Route("/api/{action}", act, methods=["POST"]),
        WebSocketRoute("/ws/state", ws_state),
        WebSocketRoute("/ws/frames", ws_frames),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ])
    return Guard(app, token)


class ConsoleServer:
    """uvicorn serving :func:`make_app`; :meth:`serve` blocks, :meth:`start_in_thread` for tests and benchmarks."""

    def __init__(self, session: ConsoleSession, host: str = "127.0.0.1", port: int = 8765, token: str | None = None) -> None:
        import uvicorn

        if not is_loopback(host) and not token:
            raise ConfigError(f"host = {host!r} is not loopback: a token is required (give --token or let one be generated)")
        self.session = session
        self.host = host
        self.token = token
        self.hub = FrameHub(session)
        self.app = make_app(session, token=token, hub=self.hub)
        self.server = uvicorn.Server(uvicorn.Config(self.app, host=host, port=port, log_level="warning",
                                                    ws="websockets-sansio", lifespan="off"))
        try:   # bound now: the address is known (port 0 = any free port) and a busy port fails here, clearly
            self.socket = socket.create_server((host, port), family=socket.AF_INET6 if ":" in host else socket.AF_INET)
        except OSError as exc:
            raise ConfigError(f"--host {host} --port {port}: cannot listen there ({exc.strerror})") from None
        self.port: int = self.socket.getsockname()[1]
        self._thread: threading.Thread | None = None

    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        base = f"http://{host}:{self.port}/"
        return base + (f"?token={self.token}" if self.token else "")

    def serve(self) -> None:
        self.server.run(sockets=[self.socket])

    def start_in_thread(self, timeout: float = 10.0) -> None:
        self._thread = threading.Thread(target=self.serve, name="targetlock-console-http", daemon=True)
        self._thread.start()
        deadline = threading.Event()
        for _ in range(int(timeout / 0.02)):
            if self.server.started:
                return
            deadline.wait(0.02)
        raise RuntimeError("console server did not start")

    def stop(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=5.0)
