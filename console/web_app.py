"""The console's web app (Starlette): the page, its live feed (server-sent events) and the JSON API.

    GET  /api/state                       zones, nodes, robots, blocks (session cookie or HTTP Basic)
    GET  /api/events                      the same, live: a snapshot, then updates as messages arrive (SSE)
    GET  /api/site                        the site's geometry: map bounds, zones, nodes, points, robots
    POST /api/blocks                      {"zone": Z} or {"polygon": [[x, y], ...]}, "for_s", "reason", "id"
    DELETE /api/blocks/{id}               lift a block
    POST /api/blocks/{id}/extend          {"for_s": S}: the same block, expiring S later (never lifted meanwhile)
    POST /api/alerts/{id}/ack             acknowledge an alert (kept across reloads and restarts)
    POST /api/alerts/ack-all              acknowledge every alert in force (a mass outage)
    POST /api/robots/{id}/goal            {"point": NAME} or {"pose": [x, y, yaw]}
    POST /api/robots/{id}/cancel
    POST /api/login, /api/logout          {"username", "password"}: the operator's

Writes need JSON, and from a browser the session's CSRF token in `X-CSRF-Token` (scripts may use Basic auth
instead); a request from another origin is refused. A refused request gets a 4xx and `{"error": "..."}`, and
nothing is published.
"""

from __future__ import annotations

import asyncio
import io
import json
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
from PIL import Image
from starlette.applications import Starlette
from starlette.datastructures import MutableHeaders
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from wsnav.console import operator_commands as commands
from wsnav.console.auth import COOKIE, Authenticator, Session
from wsnav.console.live_state import LiveState, resync_event
from wsnav.console.operator_commands import CommandError, Publication
from wsnav.runtime.bus import Bus
from wsnav.runtime.clock import Clock
from wsnav.schemas.messages import PayloadError, parse_json
from wsnav.schemas.site import Site

STATIC = Path(__file__).parent / "static"
MAX_BODY = 16_384
KEEPALIVE_S = 15.0
WRONG_PASSWORD_DELAY_S = 1.0
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; frame-ancestors 'none'",
}

Handler = Callable[[Request], Awaitable[Response]]


class Refused(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def _error(status: int, message: str, **headers: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status, headers=headers or None)


def map_png(site: Site) -> bytes:
    """The occupancy grid as a picture: free white, walls black, unknown grey; row 0 (origin y) at the bottom."""
    data = site.grid.data
    img = np.full(data.shape, 205, dtype=np.uint8)
    img[data == 0] = 254
    img[data >= 65] = 40
    buf = io.BytesIO()
    Image.fromarray(np.flipud(img)).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def site_geometry(site: Site) -> dict[str, Any]:
    spec = site.spec
    x0, y0, x1, y1 = site.grid.bounds

    def centre(poly: list[tuple[float, float]]) -> tuple[float, float]:
        return sum(p[0] for p in poly) / len(poly), sum(p[1] for p in poly) / len(poly)

    zones = {z.id: z for z in spec.zones}
    return {
        "site": spec.name,
        "bounds": [x0, y0, x1, y1],
        "zones": [{"id": z.id, "name": z.name, "polygon": z.polygon} for z in spec.zones],
        "nodes": [
            {"id": n.id, "zone": n.zone, "position": n.position or centre(zones[n.zone].polygon)}
            for n in spec.nodes
        ],
        "points": {name: p for name, p in spec.points.items()},
        "robots": [r.id for r in spec.robots],
        "heartbeat_s": spec.heartbeat_s,
    }


class SecurityHeaders:
    """Every response: no sniffing, no framing, scripts and styles from this origin only, nothing cached."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for k, v in SECURITY_HEADERS.items():
                    headers.setdefault(k, v)
                headers.setdefault("Cache-Control", "no-store")
            await send(message)

        await self.app(scope, receive, with_headers)


class ConsoleApp:
    def __init__(self, site: Site, live: LiveState, bus: Bus, clock: Clock, auth: Authenticator) -> None:
        self.site, self.live, self.bus, self.clock, self.auth = site, live, bus, clock, auth
        self._map = map_png(site)
        self._geometry = json.dumps(site_geometry(site)).encode()
        self.app = Starlette(
            routes=[
                Route("/", self.index),
                Route("/login", self.login_page),
                Route("/favicon.ico", lambda _r: Response(status_code=204)),
                Route("/static/{name}", self.static),
                Route("/map.png", self.guarded(self.map_image)),
                Route("/api/login", self.login, methods=["POST"]),
                Route("/api/logout", self.logout, methods=["POST"]),
                Route("/api/session", self.guarded(self.session_info)),
                Route("/api/site", self.guarded(self.geometry)),
                Route("/api/state", self.guarded(self.state)),
                Route("/api/events", self.guarded(self.events)),
                Route("/api/blocks", self.guarded(self.add_block, write=True), methods=["POST"]),
                Route(
                    "/api/blocks/{block_id}", self.guarded(self.lift_block, write=True), methods=["DELETE"]
                ),
                Route(
                    "/api/blocks/{block_id}/extend",
                    self.guarded(self.extend_block, write=True),
                    methods=["POST"],
                ),
                Route(
                    "/api/alerts/{alert_id}/ack", self.guarded(self.ack_alert, write=True), methods=["POST"]
                ),
                Route("/api/alerts/ack-all", self.guarded(self.ack_all_alerts, write=True), methods=["POST"]),
                Route("/api/robots/{robot}/goal", self.guarded(self.send_goal, write=True), methods=["POST"]),
                Route(
                    "/api/robots/{robot}/cancel", self.guarded(self.cancel_goal, write=True), methods=["POST"]
                ),
            ]
        )
        self.app.add_exception_handler(Refused, self._refused)  # type: ignore[arg-type]
        self.app.add_middleware(SecurityHeaders)

    async def _refused(self, _request: Request, exc: Refused) -> Response:
        extra = {"WWW-Authenticate": 'Basic realm="wsnav console"'} if exc.status == 401 else {}
        return _error(exc.status, str(exc), **extra)

    # -- who is asking -------------------------------------------------------------------------------------

    def _session(self, request: Request) -> Session | None:
        return self.auth.session(request.cookies.get(COOKIE))

    def guarded(self, handler: Handler, *, write: bool = False) -> Handler:
        """A session cookie (and for writes its CSRF token) or HTTP Basic with the operator's password."""

        async def wrapped(request: Request) -> Response:
            session = self._session(request)
            basic = request.headers.get("authorization")
            if basic is not None:  # checked whenever given: it also stands in for the CSRF token below
                if not self.auth.check_basic(basic):
                    await asyncio.sleep(WRONG_PASSWORD_DELAY_S)
                    raise Refused(401, "wrong username or password")
                session = None
            elif session is None:
                raise Refused(
                    401, "log in first (a session cookie or HTTP Basic auth with the operator's password)"
                )
            if write:
                self._check_write(request, session)
            return await handler(request)

        return wrapped

    def _check_write(self, request: Request, session: Session | None) -> None:
        origin = request.headers.get("origin")
        if origin is not None and urlsplit(origin).netloc != request.headers.get("host"):
            raise Refused(403, f"a request from another origin ({origin}) is refused")
        if session is not None and request.headers.get("x-csrf-token") != session.csrf:
            raise Refused(403, "missing or wrong X-CSRF-Token (reload the page)")
        ctype = request.headers.get("content-type", "").split(";")[0].strip()
        if request.method == "POST" and ctype != "application/json":
            raise Refused(415, "send JSON (Content-Type: application/json)")

    async def _json(self, request: Request) -> dict[str, Any]:
        """The body as a JSON object, read only up to MAX_BODY bytes (a declared or streamed larger body is
        refused before it is read) and parsed by the message contract's rules (no key twice)."""
        body = await read_bounded(request, MAX_BODY)
        if not body:
            return {}
        try:
            data = parse_json(body)
        except PayloadError as exc:
            raise Refused(400, f"the body is not accepted: {exc}") from None
        if not isinstance(data, dict):
            raise Refused(400, "the body must be a JSON object")
        return data

    def _publish(self, pub: Publication) -> None:
        if not self.bus.connected:
            raise Refused(503, "the broker is not reachable: nothing was sent, try again when it is back")
        self.bus.publish(pub.topic, pub.payload, qos=1, retain=pub.retain)

    # -- pages ---------------------------------------------------------------------------------------------

    async def index(self, request: Request) -> Response:
        if self._session(request) is None:
            return RedirectResponse("/login", status_code=303)
        return FileResponse(STATIC / "index.html")

    async def login_page(self, _request: Request) -> Response:
        return FileResponse(STATIC / "login.html")

    async def static(self, request: Request) -> Response:
        name = request.path_params["name"]
        path = STATIC / name
        if name not in {"console.js", "console.css", "login.js"} or not path.is_file():
            raise Refused(404, "no such file")
        return FileResponse(path)

    async def map_image(self, _request: Request) -> Response:
        return Response(self._map, media_type="image/png")

    async def login(self, request: Request) -> Response:
        data = await self._json(request)
        user, password = data.get("username"), data.get("password")
        if not isinstance(user, str) or not isinstance(password, str):
            raise Refused(400, "give 'username' and 'password'")
        if not self.auth.check_password(user, password):
            await asyncio.sleep(WRONG_PASSWORD_DELAY_S)
            return _error(401, "wrong username or password")
        sid, _ = self.auth.open_session()
        response = JSONResponse({"ok": True})
        response.set_cookie(COOKIE, sid, httponly=True, samesite="strict", path="/")
        return response

    async def logout(self, request: Request) -> Response:
        self.auth.close_session(request.cookies.get(COOKIE))
        response = JSONResponse({"ok": True})
        response.delete_cookie(COOKIE, path="/")
        return response

    async def session_info(self, request: Request) -> Response:
        session = self._session(request)
        return JSONResponse({"csrf": session.csrf if session else None, "site": self.site.name})

    async def geometry(self, _request: Request) -> Response:
        return Response(self._geometry, media_type="application/json")

    async def state(self, _request: Request) -> Response:
        return JSONResponse(self.live.snapshot())

    async def events(self, request: Request) -> Response:
        loop = asyncio.get_running_loop()
        feed = self.live.open_feed(loop)
        snapshot = resync_event(self.live)

        async def stream() -> AsyncIterator[str]:
            try:
                yield f"data: {snapshot()}\n\n"
                while True:
                    try:
                        text = await asyncio.wait_for(feed.queue.get(), KEEPALIVE_S)
                    except TimeoutError:
                        if await request.is_disconnected():
                            return
                        yield ": keepalive\n\n"
                        continue
                    if feed.resync:
                        feed.resync = False
                        while not feed.queue.empty():
                            feed.queue.get_nowait()
                        text = snapshot()
                    yield f"data: {text}\n\n"
            finally:
                self.live.close_feed(feed)

        return StreamingResponse(
            stream(), media_type="text/event-stream", headers={"X-Accel-Buffering": "no"}
        )

    # -- steering ------------------------------------------------------------------------------------------

    async def add_block(self, request: Request) -> Response:
        data = await self._json(request)
        unknown = set(data) - {"zone", "polygon", "for_s", "reason", "id"}
        if unknown:
            raise Refused(400, f"unknown field(s): {', '.join(sorted(unknown))}")
        try:
            block_id, pub = commands.block(
                self.site,
                now=self.clock.now(),
                duration_s=_number(data.get("for_s"), "for_s", optional=True),
                zone=_text(data.get("zone"), "zone"),
                polygon=_polygon(data.get("polygon")),
                reason=_text(data.get("reason"), "reason"),
                block_id=_text(data.get("id"), "id"),
            )
        except CommandError as exc:
            raise Refused(400, str(exc)) from None
        self._publish(pub)
        return JSONResponse(
            {"id": block_id, "topic": pub.topic, "block": json.loads(pub.payload)}, status_code=201
        )

    async def lift_block(self, request: Request) -> Response:
        block_id = request.path_params["block_id"]
        with self.live.lock:
            known = block_id in self.live.view.blocks
        if not known:
            raise Refused(404, f"no active block {block_id!r}")
        try:
            pub = commands.unblock(self.site, block_id)
        except CommandError as exc:
            raise Refused(400, str(exc)) from None
        self._publish(pub)
        return JSONResponse({"id": block_id, "lifted": True})

    async def extend_block(self, request: Request) -> Response:
        block_id = request.path_params["block_id"]
        data = await self._json(request)
        unknown = set(data) - {"for_s"}
        if unknown:
            raise Refused(400, f"unknown field(s): {', '.join(sorted(unknown))}")
        by_s = _number(data.get("for_s"), "for_s")
        assert by_s is not None
        with self.live.lock:
            view = self.live.view.blocks.get(block_id)
        if view is None:
            raise Refused(404, f"no active block {block_id!r}")
        try:
            pub = commands.extend(self.site, block_id, view.block, now=self.clock.now(), by_s=by_s)
        except CommandError as exc:
            raise Refused(400, str(exc)) from None
        self._publish(pub)
        return JSONResponse({"id": block_id, "block": json.loads(pub.payload)})

    async def ack_alert(self, request: Request) -> Response:
        alert_id = request.path_params["alert_id"]
        await self._json(request)
        with self.live.lock:
            known = self.live.alerts.acknowledge(alert_id, self.clock.now())
        if not known:
            raise Refused(404, f"no alert {alert_id!r} in force (over already?)")
        return JSONResponse({"id": alert_id, "acknowledged": True})

    async def ack_all_alerts(self, request: Request) -> Response:
        await self._json(request)
        with self.live.lock:
            now = self.clock.now()
            ids = [a.id for a in self.live.alerts.alerts.values() if not a.acknowledged]
            for alert_id in ids:
                self.live.alerts.acknowledge(alert_id, now)
        return JSONResponse({"acknowledged": ids})

    async def send_goal(self, request: Request) -> Response:
        data = await self._json(request)
        robot = request.path_params["robot"]
        point, pose = data.get("point"), data.get("pose")
        try:
            if isinstance(point, str) and pose is None:
                pub = commands.goal(self.site, robot, point)
            elif point is None and isinstance(pose, list) and len(pose) in (2, 3):
                xs = [_number(v, "pose") for v in pose]
                pub = commands.goal(
                    self.site,
                    robot,
                    (xs[0] or 0.0, xs[1] or 0.0, xs[2] if len(xs) == 3 and xs[2] is not None else 0.0),
                )
            else:
                raise Refused(400, "give 'point' (a named point) or 'pose' ([x, y] or [x, y, yaw])")
        except CommandError as exc:
            raise Refused(400, str(exc)) from None
        self._publish(pub)
        return JSONResponse({"robot": robot, "goal": json.loads(pub.payload)["goal"]}, status_code=202)

    async def cancel_goal(self, request: Request) -> Response:
        robot = request.path_params["robot"]
        try:
            pub = commands.cancel(self.site, robot)
        except CommandError as exc:
            raise Refused(400, str(exc)) from None
        self._publish(pub)
        return JSONResponse({"robot": robot, "cancelled": True}, status_code=202)


async def read_bounded(request: Request, limit: int) -> bytes:
    """At most `limit` bytes of the body: a Content-Length above it is refused unread, a streamed body as soon
    as it passes it (a 300 MB login used to be read whole before it was refused)."""
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.isdigit():
            raise Refused(400, "Content-Length is not a number")
        if int(declared) > limit:
            raise Refused(413, f"request body of {int(declared)} bytes exceeds {limit}")
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise Refused(413, f"request body exceeds {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _text(value: object, name: str) -> str | None:
    if value is None or isinstance(value, str):
        return value
    raise Refused(400, f"'{name}' must be a string")


def _number(value: object, name: str, *, optional: bool = False) -> float | None:
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise Refused(400, f"'{name}' must be a finite number")
    try:
        number = float(value)  # an int of 400 digits is valid JSON and no float
    except OverflowError:
        raise Refused(400, f"'{name}' must be a finite number") from None
    if not math.isfinite(number):
        raise Refused(400, f"'{name}' must be a finite number")
    return number


def _polygon(value: object) -> list[tuple[float, float]] | None:
    if value is None:
        return None
    if not isinstance(value, list) or not 3 <= len(value) <= 64:
        raise Refused(400, "'polygon' must be a list of 3 to 64 [x, y] points")
    out: list[tuple[float, float]] = []
    for p in value:
        if not isinstance(p, list) or len(p) != 2:
            raise Refused(400, "'polygon' points must be [x, y]")
        x, y = _number(p[0], "polygon"), _number(p[1], "polygon")
        assert x is not None and y is not None
        out.append((x, y))
    return out
