"""``overgrid view``: the live map in a browser. An aiohttp server (one dependency that is both the
HTTP server and the WebSocket endpoint, on asyncio, no ASGI server beside it) pushes what the feed
follows to every open page: the full map once, then only the rectangles that changed. However many
tabs are open, fusion sees one follower.

Safe by default: loopback only (``--http-host`` to serve a LAN; ``--listen`` stays the Zenoh flag
every service shares), GET only, optional ``--token``, and WebSocket origins checked.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hmac
import io
import json
import logging
import threading
import time
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.typedefs import Handler, Middleware
from pydantic import Field

from common.lifecycle import stop_on_signals
from common.logs import RateLimitedLog, setup_logging
from common.mapfiles import (
    FREE_THRESH,
    OCCUPIED_THRESH,
    PICTURE_COLORS,
    map_yaml,
    pgm_bytes,
    png_bytes,
)
from common.occupancy_map import OccupancyMap
from common.sensor_model import SensorModelParams
from common.settings import ZenohSettings, parse_settings, startup_error
from common.zenoh_session import open_session
from services.viewer.address import DEFAULT_HTTP_HOST, DEFAULT_HTTP_PORT, LOOPBACK_HOSTS, page_urls
from services.viewer.feed import FeedPeriods, FeedState, MapFeed
from services.viewer.status import fusion_status
from services.viewer.wire import NO_HEIGHT_MM, MapLayers, frames_between, full_frame

log = logging.getLogger("view")
STATIC = Path(__file__).with_name("static")
MAX_QUEUED_MESSAGES = 64
"""A page further behind than this gets one full map instead of the backlog."""
HEARTBEAT_S = 1.0
"""Status goes out at least this often, so a page notices a silent server."""
MAX_PERIOD_S = 3600.0
"""The longest period of the viewer's pushes and polls: an hour is no live view any more, and
past about 3e8 s a wait overflows (``--health-period-s 1e300``: a traceback, then no health)."""


class ViewSettings(ZenohSettings):
    http_host: str = Field(
        DEFAULT_HTTP_HOST, description="address the page is served on (0.0.0.0: every interface)"
    )
    http_port: int = Field(
        DEFAULT_HTTP_PORT, ge=0, le=65535, description="port of the page (0: any)"
    )
    token: str | None = Field(
        None, min_length=8, description="access token the page needs (?token=…), none by default"
    )
    push_interval_s: float = Field(
        0.1, gt=0.0, le=MAX_PERIOD_S, description="shortest time between pushes to the pages"
    )
    stale_after_s: float = Field(
        3.0, gt=0.0, description="the page warns when fusion has not answered for this long"
    )
    height_period_s: float = Field(
        1.0, ge=0.0, le=MAX_PERIOD_S, description="how often the height layer is fetched (0: never)"
    )
    health_period_s: float = Field(
        1.0, gt=0.0, le=MAX_PERIOD_S, description="how often map/health is asked"
    )


def hello_message(settings: ViewSettings) -> str:
    """What the page needs before any map: colours and thresholds as the map files use them."""
    band = SensorModelParams()
    return json.dumps(
        {
            "type": "hello",
            "colors": {k: PICTURE_COLORS[k] for k in ("free", "occupied", "unknown")},
            "free_max": FREE_THRESH * 100,
            "occupied_min": OCCUPIED_THRESH * 100,
            "no_height_mm": NO_HEIGHT_MM,
            "height_band_m": [band.obstacle_min_m, band.obstacle_max_m],
            "stale_after_s": settings.stale_after_s,
        }
    )


def status_message(state: FeedState, now_s: float, stale_after_s: float) -> str:
    layers = state.layers
    return json.dumps(
        {
            "type": "status",
            **fusion_status(state.fusion_answered_s, state.fusion_ok, now_s, stale_after_s),
            "map": None
            if layers is None
            else {
                "version": layers.version,
                "capture_age_s": round(now_s - layers.stamp_ns / 1e9, 2)
                if layers.stamp_ns
                else None,
                "cols": layers.window.cols,
                "rows": layers.window.rows,
            },
            "tiles_rejected": (state.map_health or {}).get("tiles_rejected"),
            "pairs": state.pairs,
            "objects": state.objects,
        }
    )


class Page:
    """One open WebSocket: messages queue here and one task sends them in order."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.queue: asyncio.Queue[str | bytes] = asyncio.Queue(MAX_QUEUED_MESSAGES)

    def offer(self, message: str | bytes, catch_up: Callable[[], bytes | None]) -> None:
        """Queue a message; a page too far behind drops its backlog for one full map, made now so
        the order of what it receives stays the order of the map's versions."""
        try:
            self.queue.put_nowait(message)
        except asyncio.QueueFull:
            while not self.queue.empty():
                self.queue.get_nowait()
            full = catch_up()
            if full is not None:
                self.queue.put_nowait(full)
            if isinstance(message, str):
                self.queue.put_nowait(message)

    async def send_loop(self) -> None:
        try:
            while not self.ws.closed:
                message = await self.queue.get()
                if isinstance(message, bytes):
                    await self.ws.send_bytes(message)
                else:
                    await self.ws.send_str(message)
        except (ConnectionResetError, RuntimeError):  # the page went away mid-send
            await self.ws.close()


class Broadcaster:
    """Turns the feed's newest state into messages for every page, at most every push interval."""

    def __init__(self, feed: MapFeed, settings: ViewSettings) -> None:
        self.feed = feed
        self.settings = settings
        self.pages: set[Page] = set()
        self.wake = asyncio.Event()
        self._sent: MapLayers | None = None
        self._full: bytes | None = None
        self._status = ""
        self._status_revision = -1

    def full(self) -> bytes | None:
        if self._sent is not None and self._full is None:
            self._full = full_frame(self._sent)
        return self._full

    def join(self, page: Page) -> None:
        page.offer(hello_message(self.settings), self.full)
        full = self.full()
        if full is not None:
            page.offer(full, self.full)
        if self._status:
            page.offer(self._status, self.full)
        self.pages.add(page)

    def _send(self, message: str | bytes) -> None:
        for page in self.pages:
            page.offer(message, self.full)

    def push(self, heartbeat: bool) -> None:
        state = self.feed.state()
        if state.layers is not None and state.layers is not self._sent:
            frames = frames_between(self._sent, state.layers)
            self._sent, self._full = state.layers, None
            for frame in frames:
                self._send(frame)
        if heartbeat or state.status_revision != self._status_revision:
            self._status_revision = state.status_revision
            self._status = status_message(state, time.time(), self.settings.stale_after_s)
            self._send(self._status)

    async def run(self) -> None:
        last_status = 0.0
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.wake.wait(), HEARTBEAT_S)
            self.wake.clear()
            now = time.monotonic()
            heartbeat = now - last_status >= HEARTBEAT_S
            try:
                self.push(heartbeat)
            except Exception:  # one bad state must not stop every page's updates for good
                log.exception("push failed")
            if heartbeat:
                last_status = now
            await asyncio.sleep(self.settings.push_interval_s)


BROADCASTER = web.AppKey("broadcaster", Broadcaster)
FEED = web.AppKey("feed", MapFeed)


def token_cookie(port: int | None) -> str:
    """The cookie that carries the token, one per port: browsers keep cookies per host, not per
    port, so two viewers on one box (two `up` runs) must not overwrite each other's."""
    return f"overgrid_token_{port or 80}"


def exposure_warning(settings: ViewSettings) -> str | None:
    """What to say at start when the page is served beyond this box with no token."""
    if settings.http_host in LOOPBACK_HOSTS or settings.token is not None:
        return None
    return (
        f"serving on {settings.http_host} without --token: anyone who reaches this port sees "
        "the map; set --token (or OVERGRID_TOKEN)"
    )


def _same_origin(request: web.Request) -> bool:
    """A page of another site must not read the map through the visitor's browser."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    return origin.split("://", 1)[-1] == request.host


def guard(settings: ViewSettings) -> Middleware:
    """Read-only, the token if one is set, and on loopback only loopback host names (a DNS name
    rebound to 127.0.0.1 gets nothing)."""
    loopback = settings.http_host in LOOPBACK_HOSTS

    @web.middleware
    async def middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.method not in ("GET", "HEAD"):
            raise web.HTTPMethodNotAllowed(request.method, ["GET", "HEAD"])
        if loopback and (request.url.host or "") not in LOOPBACK_HOSTS:
            raise web.HTTPForbidden(text="this viewer answers on its loopback address only")
        cookie = token_cookie(request.url.port)
        if settings.token is not None:
            given = (
                request.query.get("token")
                or request.cookies.get(cookie)
                or request.headers.get("Authorization", "").removeprefix("Bearer ")
            )
            # Bytes as sent (surrogate escapes kept): a header of bytes no text encodes is a
            # wrong token too, never a server error.
            if not hmac.compare_digest(
                given.encode("utf-8", "surrogateescape"), settings.token.encode()
            ):
                raise web.HTTPUnauthorized(
                    text="access token missing or wrong: open the URL `overgrid view` printed"
                )
        response = await handler(request)
        if not isinstance(response, web.WebSocketResponse):
            response.headers["Content-Security-Policy"] = (
                "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'"
            )
            response.headers["X-Content-Type-Options"] = "nosniff"
            response.headers["Referrer-Policy"] = "no-referrer"
            if settings.token is not None and request.query.get("token"):
                response.set_cookie(cookie, settings.token, httponly=True, samesite="Strict")
        return response

    return middleware


async def index(request: web.Request) -> web.StreamResponse:
    return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})


async def websocket(request: web.Request) -> web.StreamResponse:
    if not _same_origin(request):
        raise web.HTTPForbidden(text="cross-origin WebSocket refused")
    ws = web.WebSocketResponse(heartbeat=10.0)
    await ws.prepare(request)
    broadcaster = request.app[BROADCASTER]
    page = Page(ws)
    broadcaster.join(page)
    sender = asyncio.create_task(page.send_loop())
    try:
        async for message in ws:  # read-only: whatever a page sends is ignored
            if message.type == WSMsgType.ERROR:
                break
    finally:
        broadcaster.pages.discard(page)
        sender.cancel()
    return ws


def _current_map(request: web.Request) -> OccupancyMap:
    occupancy_map = request.app[FEED].state().map
    if occupancy_map is None or occupancy_map.window.empty:
        raise web.HTTPServiceUnavailable(text="no map yet: fusion has not answered")
    return occupancy_map


def _attachment(body: bytes, name: str, content_type: str) -> web.Response:
    return web.Response(
        body=body,
        content_type=content_type,
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )


async def download(request: web.Request) -> web.StreamResponse:
    """The map as the page shows it now, in the files `overgrid map get` writes."""
    occupancy_map = _current_map(request)
    stem = f"overgrid-map-v{occupancy_map.version}"
    kind = request.match_info["kind"]
    if kind == "png":
        return _attachment(png_bytes(occupancy_map), f"{stem}.png", "image/png")
    if kind == "pgm":
        return _attachment(pgm_bytes(occupancy_map), f"{stem}.pgm", "image/x-portable-graymap")
    if kind == "yaml":
        return _attachment(
            map_yaml(occupancy_map, f"{stem}.pgm").encode(), f"{stem}.yaml", "text/yaml"
        )
    if kind == "zip":  # PGM + YAML in one file, as map_server reads them
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            archive.writestr(f"{stem}.pgm", pgm_bytes(occupancy_map))
            archive.writestr(f"{stem}.yaml", map_yaml(occupancy_map, f"{stem}.pgm"))
        return _attachment(buffer.getvalue(), f"{stem}.zip", "application/zip")
    raise web.HTTPNotFound(text=f"no download {kind!r}: png, pgm, yaml or zip")


async def cell(request: web.Request) -> web.StreamResponse:
    """When cell (i, j) was last observed, for the page's readout: answered from the layer the
    feed fetched, never by asking fusion (a pointer moving in ten tabs must not reach it)."""
    try:
        i, j = int(request.query["i"]), int(request.query["j"])
    except (KeyError, ValueError):
        raise web.HTTPBadRequest(text="cell?i=I&j=J with integer lattice indices") from None
    times = request.app[FEED].state().cell_times
    return web.json_response(
        {
            "i": i,
            "j": j,
            "last_seen_s": None if times is None else times.at(i, j),
            "now_s": time.time(),
        },
        headers={"Cache-Control": "no-store"},
    )


class RefusedRequestLog(logging.LoggerAdapter[logging.Logger]):
    """aiohttp's server log, with a request its parser refuses (a URL or a header past 8 KB, a NUL
    in the path: answered 400) as one warning line, rate-limited and counted: each was also an
    error line with a traceback. Any other error (a handler's 500) keeps its traceback."""

    def __init__(self) -> None:
        super().__init__(logging.getLogger("aiohttp.server"))
        self.refused = 0
        self._warn = RateLimitedLog(log)

    def exception(self, msg: object, *args: object, exc_info: Any = True, **kwargs: Any) -> None:
        if not isinstance(exc_info, HttpProcessingError):
            super().exception(msg, *args, exc_info=exc_info, **kwargs)
            return
        self.refused += 1
        # The message's first clause: what follows quotes the request, a token perhaps.
        reason = f"{type(exc_info).__name__}: {exc_info.message.split(':')[0]}"[:120]
        self._warn.warning(
            "refused",
            "bad HTTP request refused",
            status=exc_info.code,
            reason=reason,
            refused=self.refused,
        )


def make_app(feed: MapFeed, settings: ViewSettings) -> web.Application:
    app = web.Application(middlewares=[guard(settings)])
    app[FEED] = feed
    app[BROADCASTER] = Broadcaster(feed, settings)
    app.router.add_get("/", index)
    app.router.add_get("/ws", websocket)
    app.router.add_get("/download/map.{kind}", download)
    app.router.add_get("/cell", cell)
    app.router.add_static("/static/", STATIC)

    async def close_pages(app: web.Application) -> None:
        for page in list(app[BROADCASTER].pages):
            await page.ws.close(code=1001, message=b"viewer stopping")

    app.on_shutdown.append(close_pages)
    return app


async def serve(settings: ViewSettings, feed: MapFeed, stop: threading.Event) -> None:
    app = make_app(feed, settings)
    broadcaster = app[BROADCASTER]
    loop = asyncio.get_running_loop()

    def notify() -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed: the viewer is stopping
            loop.call_soon_threadsafe(broadcaster.wake.set)

    feed.notify = notify
    runner = web.AppRunner(app, shutdown_timeout=1.0, access_log=None, logger=RefusedRequestLog())
    await runner.setup()
    site = web.TCPSite(runner, settings.http_host, settings.http_port)
    try:
        await site.start()
    except OSError as error:  # a start-up error: the setting it comes from, one line, exit 2
        await runner.cleanup()
        where = f"{settings.http_host}:{settings.http_port}"
        if error.errno == errno.EADDRINUSE:
            startup_error(
                f"--http-port {settings.http_port}: {where} is in use; choose another with "
                "--http-port / OVERGRID_HTTP_PORT"
            )
        startup_error(
            f"--http-host {settings.http_host}: cannot serve on {where}: {error.strerror or error}"
        )
    port = int(runner.addresses[0][1])  # the one asked for, or the free one the system chose
    url, *lan = page_urls(settings.http_host, port, settings.token)
    log.info("serving", extra={"url": url, "lan_urls": ",".join(lan)})
    print(f"overgrid view: {url}" + "".join(f"\n  from the LAN: {u}" for u in lan), flush=True)
    pushing = asyncio.create_task(broadcaster.run())
    try:
        await asyncio.to_thread(stop.wait)
    finally:
        pushing.cancel()
        await runner.cleanup()


def main(settings: ViewSettings) -> None:
    setup_logging("view", settings.log_level)
    if (warning := exposure_warning(settings)) is not None:
        log.warning(warning)
    stop = stop_on_signals()
    periods = FeedPeriods(health_s=settings.health_period_s, height_s=settings.height_period_s)
    with open_session(settings, wait_for_router=True) as session:
        feed = MapFeed(session, lambda: None, periods)
        feed.start(stop)
        try:
            asyncio.run(serve(settings, feed, stop))
        finally:
            stop.set()
            feed.join(timeout_s=2.0)
    log.info("stopped")


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            ViewSettings,
            argv,
            "overgrid view",
            "Serve the live map to browsers (loopback only unless --http-host says otherwise).",
        )
    )
