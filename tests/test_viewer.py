"""``overgrid view``: the pure map → message logic, the footprints and pair states, and the page in a
real browser (Debian's chromium driven by Playwright) following real fusion and depth processes."""

from __future__ import annotations

import http.client
import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from common.client import MapUnavailable, latest
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.mapfiles import PGM_FREE, PGM_OCCUPIED, PICTURE_COLORS
from common.messages import CALIB_KIND, OBJECTS_KIND, ObjectsHeader, TrackedObject
from common.occupancy_map import OccupancyMap
from common.png import decode_png
from common.settings import parse_settings
from services.camera_sim.rig import RigSpec, layout_pairs
from services.evaluation.metrics import seen_by_cameras
from services.viewer.address import available_port, lan_addresses, page_url, page_urls
from services.viewer.feed import FeedState
from services.viewer.footprints import clip_convex, pair_footprint
from services.viewer.server import ViewSettings, exposure_warning, status_message
from services.viewer.status import TileRates, objects_for_page, pair_states
from services.viewer.wire import (
    CHUNK_CELLS,
    NO_HEIGHT_MM,
    CellTimes,
    MapLayers,
    changed_windows,
    frames_between,
    height_mm,
    read_frame,
)
from tests.conftest import REPO, Bus, assert_one_line_exit_2, free_port, run_overgrid, wait_for
from tests.tiles import tile_payload

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
RESOLUTION_M = 0.05
FLOOR_SIZE_M = (6.0, 5.0)
ALIVE_RGB = (0x1F, 0x9D, 0x45)
"""The page's colours of a live pair's footprint and of tracked objects (app.js COLORS)."""
OBJECT_RGB = (0x15, 0x65, 0xC0)
LAST_KNOWN_RGB = (0x8A, 0x8F, 0x98)
"""Objects drawn while the page cannot vouch for them (fusion silent, the viewer lost)."""


def _map(occupancy: np.ndarray, i0: int = 0, j0: int = 0, version: int = 1) -> OccupancyMap:
    return OccupancyMap(occupancy.astype(np.int8), RESOLUTION_M, i0, j0, version, 0)


# ---- wire: full map once, then changed rectangles -------------------------------------------


def test_changed_windows_are_row_runs_of_changed_chunks() -> None:
    base = np.full((200, 300), -1, np.int8)
    old = MapLayers.of(_map(base, i0=-10, j0=5))
    changed = base.copy()
    changed[3, 3] = 90  # chunk (0, 0)
    changed[3, 70] = 90  # chunk (0, 1): joins the first in one run
    changed[150, 299] = 0  # chunk (2, 4), the ragged last column
    new = MapLayers.of(_map(changed, i0=-10, j0=5, version=2))
    windows = changed_windows(old, new)
    assert windows == [
        Window(-10, 5, 2 * CHUNK_CELLS, CHUNK_CELLS),
        Window(-10 + 4 * CHUNK_CELLS, 5 + 2 * CHUNK_CELLS, 300 - 4 * CHUNK_CELLS, CHUNK_CELLS),
    ]
    assert changed_windows(new, new) == []


def test_a_grown_map_or_a_mostly_changed_one_goes_whole() -> None:
    old = MapLayers.of(_map(np.full((100, 100), -1)))
    assert changed_windows(old, MapLayers.of(_map(np.full((100, 120), -1)))) is None
    assert changed_windows(old, MapLayers.of(_map(np.zeros((100, 100))))) is None
    assert [read_frame(f)[0]["type"] for f in frames_between(None, old)] == ["map"]


def test_frames_carry_exact_cells_and_heights() -> None:
    occupancy = (np.arange(100 * 100) % 102 - 1).astype(np.int8).reshape(100, 100)
    heights = np.full((100, 100), np.nan, np.float32)
    heights[2, 3] = 1.2345
    layered = OccupancyMap(occupancy, RESOLUTION_M, 4, -2, 7, 123, height_m=heights)
    header, cells, height = read_frame(frames_between(None, MapLayers.of(layered))[0])
    assert header == {
        "type": "map",
        "version": 7,
        "stamp_ns": 123,
        "resolution_m": RESOLUTION_M,
        "i0": 4,
        "j0": -2,
        "cols": 100,
        "rows": 100,
    }
    np.testing.assert_array_equal(cells, occupancy)
    assert height[2, 3] == 1234 and (height == NO_HEIGHT_MM).sum() == 100 * 100 - 1
    old = MapLayers.of(layered)
    changed = occupancy.copy()
    changed[99, 99] = 5
    new = old.with_occupancy(_map(changed, 4, -2, version=8))
    assert new.height_mm[2, 3] == 1234  # updates carry no height: the known one is kept
    (rect,) = frames_between(old, new)
    header, cells, height = read_frame(rect)
    assert header["type"] == "rect" and header["version"] == 8
    edge = 100 - CHUNK_CELLS
    assert (header["i0"], header["j0"], header["cols"], header["rows"]) == (
        4 + CHUNK_CELLS,
        -2 + CHUNK_CELLS,
        edge,
        edge,
    )
    np.testing.assert_array_equal(cells, changed[CHUNK_CELLS:, CHUNK_CELLS:])


def test_height_follows_the_map_window() -> None:
    assert list(height_mm(np.array([[np.nan, -0.01, 0.5, 99.0]], np.float32), (1, 4))[0]) == [
        NO_HEIGHT_MM,
        0,
        500,
        NO_HEIGHT_MM - 1,
    ]
    heights = np.full((4, 4), 0.3, np.float32)
    small = OccupancyMap(np.zeros((4, 4), np.int8), RESOLUTION_M, 0, 0, 1, 0, height_m=heights)
    small_mm = height_mm(small.height_m, (4, 4))
    layers = MapLayers.of(_map(np.zeros((4, 4)))).with_height(small_mm, small.window, RESOLUTION_M)
    grown = layers.with_occupancy(_map(np.zeros((4, 6)), i0=-2, version=2))
    assert (grown.height_mm[:, 2:] == 300).all() and (grown.height_mm[:, :2] == NO_HEIGHT_MM).all()
    older = MapLayers.of(_map(np.zeros((4, 6)), i0=-2)).with_height(
        small_mm, small.window, RESOLUTION_M
    )
    assert (older.height_mm == grown.height_mm).all()


# ---- footprints and pair states ----------------------------------------------------------------


def test_cell_times_answer_by_lattice_index() -> None:
    seen = np.zeros((2, 3), np.float64)
    seen[1, 2] = 1_700_000_000.5
    times = CellTimes(Window(-1, 4, 3, 2), seen)
    assert times.at(1, 5) == 1_700_000_000.5  # col 2, row 1
    assert times.at(-1, 4) == 0.0  # in the map, never observed
    assert times.at(2, 5) is None and times.at(0, 3) is None  # outside


def test_a_pair_footprint_is_the_floor_both_cameras_see() -> None:
    (calib,) = layout_pairs(RigSpec(pair_count=1), FLOOR_SIZE_M)
    polygon = pair_footprint(calib)
    assert polygon is not None and len(polygon) == 4
    xs, ys = zip(*polygon, strict=True)
    # 640 px at f ≈ 554 px from 6 m: 6.93 m wide, less the 0.5 m baseline; 5.2 m deep.
    assert max(xs) - min(xs) == pytest.approx(6.93 - 0.5, abs=0.02)
    assert max(ys) - min(ys) == pytest.approx(5.2, abs=0.02)
    # The same floor the evaluation counts as seen by this pair, cell for cell.
    window = Window.covering(-1.0, -1.0, 7.0, 6.0, RESOLUTION_M)
    seen = seen_by_cameras([calib], window, RESOLUTION_M)
    x, y = window.cell_centers(RESOLUTION_M)
    inside = (x > min(xs)) & (x < max(xs)) & (y > min(ys)) & (y < max(ys))
    assert (inside == seen).mean() > 0.995


def test_clipping_convex_polygons() -> None:
    square = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
    shifted = [(1.0, 1.0), (1.0, 3.0), (3.0, 3.0), (3.0, 1.0)]  # clockwise: orientation is free
    assert sorted(clip_convex(square, shifted)) == [(1.0, 1.0), (1.0, 2.0), (2.0, 1.0), (2.0, 2.0)]
    assert clip_convex(square, [(5.0, 5.0), (6.0, 5.0), (6.0, 6.0)]) == []


def test_pair_states_from_health_calibrations_and_depth_health() -> None:
    rates = TileRates()
    square = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
    answer: dict[str, Any] = {
        "pairs": {
            "p0": {"alive": True, "tiles": 10, "last_tile_age_s": 0.1, "capture_to_fused_ms": 30}
        }
    }
    pair_states(answer, rates, 100.0, {}, {})
    answer["pairs"]["p0"]["tiles"] = 20
    rows = pair_states(
        answer, rates, 102.0, {"p0": {"floor_model": {"state": "learning"}}}, {"p1": square}
    )
    assert [r["pair"] for r in rows] == ["p0", "p1"]
    assert rows[0]["frame_rate_hz"] == 5.0 and rows[0]["floor_model"] == "learning"
    assert rows[0]["alive"] and rows[0]["footprint_m"] is None
    assert not rows[1]["alive"] and not rows[1]["known_to_fusion"] and rows[1]["footprint_m"]


def _tracked(
    id_: int, velocity_mps: tuple[float, float], center_m: tuple[float, float] = (1.0, 2.0)
) -> TrackedObject:
    return TrackedObject(
        id=id_,
        object_class="moving" if any(velocity_mps) else "static",
        center_m=center_m,
        size_m=(0.8, 0.5),
        yaw_rad=0.3,
        top_m=1.1,
        velocity_mps=velocity_mps,
        velocity_cov_m2ps2=((0.01, 0.0), (0.0, 0.01)),
        first_seen_ns=1,
        last_seen_ns=2,
        pairs=["p0"],
        partial=False,
        detections=5,
    )


def test_objects_reach_the_page_with_what_it_draws() -> None:
    header = ObjectsHeader(version=1, stamp_ns=2, objects=[_tracked(7, (0.5, 0.0))])
    assert objects_for_page(header) == [
        {
            "id": 7,
            "class": "moving",
            "center_m": [1.0, 2.0],
            "size_m": [0.8, 0.5],
            "yaw_rad": 0.3,
            "top_m": 1.1,
            "velocity_mps": [0.5, 0.0],
            "partial": False,
            "size_unsure": False,
            "round": False,
        }
    ]


def test_the_map_is_stale_only_once_fusion_is_silent_for_stale_after_s() -> None:
    def status(answered_s: float | None, ok: bool, stale_after_s: float = 3.0) -> dict[str, Any]:
        state = FeedState(fusion_answered_s=answered_s, fusion_ok=ok)
        message: dict[str, Any] = json.loads(status_message(state, 1000.0, stale_after_s))
        return message

    one_lost_query = status(999.0, False)  # answered 1 s ago, the last query went unanswered
    assert not one_lost_query["stale"] and not one_lost_query["fusion_ok"]
    assert one_lost_query["fusion_silent_s"] == 1.0
    assert status(996.5, False)["stale"] and status(996.5, True)["stale"]  # 3.5 s > 3 s
    assert not status(996.5, False, stale_after_s=10.0)["stale"]
    assert status(None, False)["stale"]  # never answered: no map to trust


def test_serving_beyond_loopback_without_a_token_is_warned_of() -> None:
    def settings(*args: str) -> ViewSettings:
        return parse_settings(ViewSettings, list(args), "overgrid view", "")

    assert exposure_warning(settings()) is None
    assert exposure_warning(settings("--http-host", "::1")) is None
    assert exposure_warning(settings("--http-host", "0.0.0.0", "--token", "long-enough")) is None
    warning = exposure_warning(settings("--http-host", "0.0.0.0"))
    assert warning is not None and "0.0.0.0" in warning and "--token" in warning


def test_address_helpers() -> None:
    assert page_url("0.0.0.0", 8470) == "http://127.0.0.1:8470/"
    assert page_url("::1", 80, "a b") == "http://[::1]:80/?token=a%20b"
    assert page_urls("127.0.0.1", 80) == ["http://127.0.0.1:80/"]
    # On every interface, the LAN's URLs too: addresses of this box (it can bind them).
    lan = lan_addresses()
    assert page_urls("0.0.0.0", 80, "t") == [
        "http://127.0.0.1:80/?token=t",
        *(f"http://{address}:80/?token=t" for address in lan),
    ]
    for address in lan:
        assert not address.startswith("127.")
        with socket.socket() as bound:
            bound.bind((address, 0))
    port = free_port()
    assert available_port("127.0.0.1", port) == port
    with socket.socket() as held:
        held.bind(("127.0.0.1", port))
        held.listen()
        assert available_port("127.0.0.1", port) != port


def test_the_robot_client_never_imports_the_web_server() -> None:
    code = (
        "import sys, common.client, common.mapfiles, services.client_cli, services.cli, services.up;"
        "heavy = [m for m in ('aiohttp', 'playwright') if m in sys.modules];"
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stdout + result.stderr


# ---- the server, without a browser ---------------------------------------------------------------


def _request(
    port: int, path: str, method: str = "GET", headers: dict[str, str] | None = None
) -> http.client.HTTPResponse:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    connection.request(method, path, headers=headers or {})
    response = connection.getresponse()
    response.read()
    return response


def _wait_http(port: int) -> None:
    def up() -> bool:
        try:
            _request(port, "/static/app.js", headers={"Authorization": "Bearer secret-token"})
        except OSError:
            return False
        return True

    wait_for(up, 30, "the viewer to serve")


@pytest.mark.process
def test_token_loopback_and_read_only(bus: Bus, tmp_path: Path) -> None:
    port = free_port()
    bus.start(
        "view", "--http-port", str(port), "--token", "secret-token", log_path=tmp_path / "v.log"
    )
    _wait_http(port)
    assert _request(port, "/").status == 401
    assert _request(port, "/?token=wrong-token").status == 401
    # Bytes no text encodes: a wrong token too (it was a 500 and a traceback).
    assert _request(port, "/", headers={"Authorization": "Bearer \xff"}).status == 401
    good = _request(port, "/?token=secret-token")
    # One cookie per port: a viewer on another port of this host keeps its own.
    cookie = {"Cookie": f"overgrid_token_{port}=secret-token"}
    assert good.status == 200 and cookie["Cookie"] in good.getheader("Set-Cookie", "")
    assert "default-src 'self'" in good.getheader("Content-Security-Policy", "")
    assert _request(port, "/", headers=cookie).status == 200
    other_port = {"Cookie": f"overgrid_token_{port + 1}=secret-token"}
    assert _request(port, "/", headers=other_port).status == 401
    assert _request(port, "/", "POST", cookie).status == 405
    assert _request(port, "/", headers={**cookie, "Host": "rebound.example:80"}).status == 403
    upgrade = {
        **cookie,
        "Connection": "Upgrade",
        "Upgrade": "websocket",
        "Sec-WebSocket-Version": "13",
        "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
    }
    assert _request(port, "/ws", headers={**upgrade, "Origin": "http://evil.example"}).status == 403
    assert (
        _request(port, "/ws", headers={**upgrade, "Origin": f"http://127.0.0.1:{port}"}).status
        == 101
    )
    assert _request(port, "/download/map.png", headers=cookie).status == 503  # no fusion: no map


@pytest.mark.parametrize("flag", ["--health-period-s", "--height-period-s", "--push-interval-s"])
def test_a_period_past_what_a_wait_takes_is_one_line(flag: str) -> None:
    """1e300 s: an OverflowError traceback in the poll's thread, which then polled no more."""
    done = run_overgrid("view", flag, "1e300", "--no-multicast-scouting")
    assert_one_line_exit_2(done, flag)


def _raw_status(port: int, request: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as connection:
        connection.sendall(request)
        return connection.recv(200).split(b"\r\n")[0]


@pytest.mark.process
def test_requests_the_parser_refuses_are_a_quiet_line(bus: Bus, tmp_path: Path) -> None:
    """A URL or a cookie past 8 KB, a NUL in the path: each got its 400, and also an error line
    with aiohttp's traceback in the log. Now one warning line, counted; the viewer serves on."""
    port = free_port()
    log = tmp_path / "v.log"
    bus.start("view", "--http-port", str(port), "--token", "secret-token", log_path=log)
    _wait_http(port)
    bad = [
        b"GET /?token=" + b"x" * 100_000 + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
        b"GET /\x00 HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
        b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nCookie: " + b"a" * 100_000 + b"\r\n\r\n",
    ]
    for request in bad:
        assert b" 400 " in _raw_status(port, request)
    wait_for(lambda: b"bad HTTP request refused" in log.read_bytes(), 10, "the refusal, said")
    assert _request(port, "/?token=secret-token").status == 200
    text = log.read_text()
    assert "Traceback" not in text and "Error handling request" not in text, text
    (line,) = [line for line in text.splitlines() if "refused" in line]
    assert "level=warning" in line and "LineTooLong" in line and "xxxx" not in line


@pytest.mark.process
def test_view_stops_on_sigterm_within_2_s(bus: Bus, tmp_path: Path) -> None:
    port = free_port()
    command = [sys.executable, "-m", "services.cli", "view", "--http-port", str(port), *bus.flags()]
    with open(tmp_path / "view.log", "wb") as log:
        process = subprocess.Popen(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: b"overgrid view: http" in (tmp_path / "view.log").read_bytes(), 30, "view")
        # A second viewer on the port taken: the setting named, one line, exit 2.
        busy = run_overgrid("view", "--http-port", str(port), *bus.flags())
        assert_one_line_exit_2(busy, "--http-port", "is in use")
        started = time.monotonic()
        process.send_signal(signal.SIGTERM)
        assert process.wait(10) == 0
        assert time.monotonic() - started < 2.0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_up_starts_the_viewer_and_prints_its_url() -> None:
    from services.up import UpSettings, child_commands

    commands = dict(child_commands(UpSettings(view_port=8471)))
    assert commands["viewer"] == ["view", "--http-port", "8471"]
    assert "viewer" not in dict(child_commands(UpSettings(view=False)))


# ---- the page in a real browser ------------------------------------------------------------------


def _chromium() -> str:
    path = shutil.which("chromium")
    if path is None:
        pytest.fail("the browser tests need Debian's chromium: run scripts/setup.sh")
    return path


@contextmanager
def _browser(tmp_path: Path, **device: Any) -> Iterator[Any]:
    """A page of a fresh chromium profile; ``device``: Playwright's viewport, pixel ratio, touch."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"),
            executable_path=_chromium(),
            args=CHROMIUM_ARGS,
            headless=True,
            **{"viewport": {"width": 1280, "height": 800}, **device},
        )
        context.set_default_timeout(20_000)
        try:
            yield context.new_page()
        finally:
            context.close()


@pytest.fixture
def browser_page(tmp_path: Path) -> Iterator[Any]:
    with _browser(tmp_path) as page:
        yield page


def _serve_calibrations(session: zenoh.Session) -> list[Any]:
    """The camera source's part: cam/{pair}/calib answered, as camera_sim does, without a render."""
    queryables = []
    for calib in layout_pairs(RigSpec(pair_count=1), FLOOR_SIZE_M):
        key, payload = f"cam/{calib.pair}/calib", encode(CALIB_KIND, calib)

        def answer(query: zenoh.Query, key: str = key, payload: bytes = payload) -> None:
            query.reply(key, payload, encoding=WIRE_ENCODING)

        queryables.append(session.declare_queryable(key, answer))
    return queryables


def _value_at(session: zenoh.Session, x_m: float, y_m: float) -> int | None:
    """The map's value at (x, y) as fusion serves it; None while fusion does not answer (on a
    loaded machine it may take a while to start)."""
    try:
        return latest(session, timeout_s=2).value_at(x_m, y_m)
    except MapUnavailable:
        return None


def _window_m(x0: float, y0: float, x1: float, y1: float) -> Window:
    return Window.covering(x0, y0, x1, y1, RESOLUTION_M)


Lander = Callable[..., None]
"""``land(window, logodds, height_m=0.0)``: one tile of p0 over ``window``, in order."""


def _lander(bus: Bus) -> Lander:
    tiles = bus.session.declare_publisher(
        "depth/p0/tile", encoding=WIRE_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
    )
    seq = iter(range(10_000))

    def land(window: Window, logodds: float, height_m: float = 0.0) -> None:
        tiles.put(tile_payload("p0", window, logodds, seq=next(seq), height_m=height_m))

    return land


def _box_on_free_floor(bus: Bus, land: Lander) -> bool:
    """Free floor over 0.5–5.5 × 0.5–4.5 m and a 1.2 m box at 2.0–2.6 m, landed; whether fusion
    shows the box (until fusion's subscription reaches the router, puts go nowhere)."""
    land(_window_m(0.5, 0.5, 5.5, 4.5), -2.0)
    land(_window_m(2.0, 2.0, 2.6, 2.6), 3.0, height_m=1.2)
    time.sleep(0.2)
    return (_value_at(bus.session, 2.3, 2.3) or 0) > 65


def _rgb(page: Any, x_m: float, y_m: float) -> tuple[int, int, int]:
    r, g, b, _ = page.evaluate(f"window.overgridView.pixelAt({x_m}, {y_m})")
    return (r, g, b)


def _drawn_as(page: Any, x_m: float, y_m: float, color: str) -> str:
    """A JS predicate: the canvas pixel over world point (x, y) has the map files' colour."""
    r, g, b = PICTURE_COLORS[color]
    return (
        f"() => {{ const p = window.overgridView.pixelAt({x_m}, {y_m});"
        f" return Math.abs(p[0] - {r}) + Math.abs(p[1] - {g}) + Math.abs(p[2] - {b}) < 12; }}"
    )


def _drawn_near(
    page: Any, x_m: float, y_m: float, rgb: tuple[int, int, int], radius_px: int = 2
) -> bool:
    """Whether a canvas pixel within ``radius_px`` of world point (x, y) has colour ``rgb``: for
    lines, which are thin and antialiased."""
    pixels = page.evaluate(f"window.overgridView.pixelsNear({x_m}, {y_m}, {radius_px})")
    return any(sum(abs(a - b) for a, b in zip(p, rgb, strict=True)) < 30 for p in pixels)


def _service_pid(process: subprocess.Popen[bytes]) -> int:
    """The service itself under the ``timeout`` that Bus.start wraps it in."""
    found = subprocess.run(["pgrep", "-P", str(process.pid)], capture_output=True, text=True)
    (pid,) = found.stdout.split()
    return int(pid)


def _readout_at(page: Any, corner: dict[str, float], x_m: float, y_m: float) -> str:
    sx, sy = page.evaluate(f"window.overgridView.worldToScreen({x_m}, {y_m})")
    page.mouse.move(corner["x"] + sx, corner["y"] + sy)
    return str(page.inner_text("#readout"))


def _screenshot(page: Any, tmp_path: Path, name: str) -> None:
    """A test artefact under the test's directory, and a copy where OVERGRID_SCREENSHOT_DIR says."""
    path = tmp_path / name
    page.screenshot(path=str(path))
    if os.environ.get("OVERGRID_SCREENSHOT_DIR"):
        target = Path(os.environ["OVERGRID_SCREENSHOT_DIR"])
        target.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target / name)


@pytest.mark.process
def test_the_page_follows_the_live_map(bus: Bus, tmp_path: Path, browser_page: Any) -> None:
    page = browser_page
    problems: list[str] = []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda error: problems.append(str(error)))
    asked: list[str] = []  # every URL the page asks for: its own origin only (sites are offline)
    page.on("request", lambda request: asked.append(request.url))
    page.on("websocket", lambda socket: asked.append(socket.url))
    queryables = _serve_calibrations(bus.session)
    fusion_args = (
        "fusion",
        "--state-dir",
        str(tmp_path / "state"),
        "--decay-after-s",
        "600",
        "--save-interval-s",
        "1",
    )
    fusion = bus.start(*fusion_args, log_path=tmp_path / "fusion.log")
    depth = bus.start("depth", "--pair", "p0", log_path=tmp_path / "depth.log")
    port = free_port()
    bus.start("view", "--http-port", str(port), log_path=tmp_path / "view.log")
    land = _lander(bus)
    wait_for(lambda: _value_at(bus.session, 0.0, 0.0) is not None, 60, "fusion")
    wait_for(lambda: _box_on_free_floor(bus, land), 20, "the box in the map")

    page.goto(f"http://127.0.0.1:{port}/")
    page.wait_for_function(_drawn_as(page, 2.3, 2.3, "occupied"))
    page.wait_for_function(_drawn_as(page, 1.0, 3.5, "free"))
    page.wait_for_selector('#pairs li[data-pair="p0"][data-state="alive"]')
    page.wait_for_selector('#pairs li[data-pair="p0"]:has-text("floor model")')  # depth health
    assert page.is_hidden("#banner")
    assert page.inner_text("#summary").endswith("1/1 pairs alive")

    # While tiles flow, the pair's frame rate (tiles/s at fusion) and capture → map latency.
    detail = page.locator('#pairs li[data-pair="p0"] .detail')

    def rates_shown() -> bool:
        land(_window_m(0.5, 3.0, 1.5, 4.5), -2.0)  # more free floor, away from the box
        time.sleep(0.1)
        rates = r"frame rate (?!0\.0)\d+\.\d\sHz · latency \d+\sms"
        return re.search(rates, detail.inner_text()) is not None

    wait_for(rates_shown, 15, "the pair's frame rate and latency in the panel")

    # Zoom keeps the point under the pointer in place; a drag pans; "fit" shows the whole map.
    corner = page.locator("#map").bounding_box()
    sx, sy = page.evaluate("window.overgridView.worldToScreen(2.3, 2.3)")
    fitted = page.evaluate("window.overgridView.state.view.pxPerM")
    page.mouse.move(corner["x"] + sx, corner["y"] + sy)
    page.mouse.wheel(0, -400)
    page.wait_for_function(f"() => window.overgridView.state.view.pxPerM > {1.5 * fitted}")
    assert page.evaluate("window.overgridView.worldToScreen(2.3, 2.3)") == pytest.approx(
        [sx, sy], abs=1
    )
    page.mouse.down()
    page.mouse.move(corner["x"] + sx + 50, corner["y"] + sy, steps=5)
    page.mouse.up()
    assert page.evaluate("window.overgridView.worldToScreen(2.3, 2.3)")[0] == pytest.approx(
        sx + 50, abs=1
    )
    page.click("#fit")
    page.wait_for_function(_drawn_as(page, 2.3, 2.3, "occupied"))
    assert page.evaluate("window.overgridView.state.view.pxPerM") == pytest.approx(fitted)

    # The pair's footprint outlined in the live colour (zoomed out: it reaches past the map).
    page.mouse.move(corner["x"] + corner["width"] / 2, corner["y"] + corner["height"] / 2)
    page.mouse.wheel(0, 400)
    page.wait_for_function(f"() => window.overgridView.state.view.pxPerM < {0.8 * fitted}")
    footprint = page.evaluate("window.overgridView.state.status.pairs[0].footprint_m")
    (ax, ay), (bx, by) = sorted(footprint, key=lambda point: point[1])[:2]  # its edge of least y
    assert _drawn_near(page, (ax + bx) / 2, (ay + by) / 2, ALIVE_RGB)
    assert not _drawn_near(page, (ax + bx) / 2, (ay + by) / 2 + 0.3, ALIVE_RGB)  # a line, no fill
    page.click("#fit")

    # A tile lands: the open page shows it within a second, no reload, from a changed rectangle
    # (whole maps go when the page connects and when most of the map changed: the first height
    # layer).
    frames_before = page.evaluate("({...window.overgridView.state.frames})")
    before = _rgb(page, 4.3, 1.3)
    land(_window_m(4.0, 1.0, 4.6, 1.6), 3.0, height_m=0.8)
    page.wait_for_function(_drawn_as(page, 4.3, 1.3, "occupied"), timeout=1000)
    assert before == PICTURE_COLORS["free"]
    frames = page.evaluate("window.overgridView.state.frames")
    assert frames["map"] == frames_before["map"] >= 1, (frames_before, frames)
    assert frames["rect"] > frames_before["rect"], (frames_before, frames)
    _screenshot(page, tmp_path, "viewer-live.png")

    # The cell under the pointer, with the height layer the viewer fetches beside the updates.

    def readout_shows(x_m: float, y_m: float, height: str) -> bool:
        sx, sy = page.evaluate(f"window.overgridView.worldToScreen({x_m}, {y_m})")
        page.mouse.move(corner["x"] + sx, corner["y"] + sy)
        text = page.inner_text("#readout")
        return "p(occ) " in text and f"height {height}" in text

    wait_for(lambda: readout_shows(2.3, 2.3, "1.20 m"), 10, "the readout to show the box's top")
    wait_for(lambda: readout_shows(4.3, 1.3, "0.80 m"), 10, "the readout to show the new top")

    # … and when the cell was last observed (fusion's last-seen layer, via the viewer): the box's
    # cell moments ago; a cell of the map no tile covered, never.
    def observed_ago_s(x_m: float, y_m: float) -> float | None:
        found = re.search(r"last observed (\d+\.\d) s ago", _readout_at(page, corner, x_m, y_m))
        return None if found is None else float(found.group(1))

    wait_for(lambda: observed_ago_s(4.3, 1.3) is not None, 10, "the readout's last observed")
    assert 0.0 <= (observed_ago_s(4.3, 1.3) or -1) < 30.0
    wait_for(lambda: "never observed" in _readout_at(page, corner, 0.2, 0.2), 10, "never observed")
    page.check("#height-mode")
    assert _rgb(page, 2.3, 2.3) not in (PICTURE_COLORS["occupied"], PICTURE_COLORS["free"])
    assert _rgb(page, 1.0, 3.5) == PICTURE_COLORS["free"]
    _screenshot(page, tmp_path, "viewer-height.png")
    page.uncheck("#height-mode")

    # The download buttons give the map as the page shows it.
    served = latest(bus.session)
    zipped = page.request.get(f"http://127.0.0.1:{port}/download/map.zip")
    with zipfile.ZipFile(io.BytesIO(zipped.body())) as archive:
        names = sorted(archive.namelist())
        assert [Path(n).suffix for n in names] == [".pgm", ".yaml"]
        pgm = archive.read(names[0])
    cols, rows = served.occupancy.shape[1], served.occupancy.shape[0]
    pixels = np.frombuffer(pgm.split(b"\n", 3)[3], np.uint8).reshape(rows, cols)[::-1]

    def pgm_at(x_m: float, y_m: float) -> int:
        return int(pixels[int(y_m / RESOLUTION_M) - served.j0, int(x_m / RESOLUTION_M) - served.i0])

    assert pgm_at(2.3, 2.3) == PGM_OCCUPIED and pgm_at(1.0, 3.5) == PGM_FREE
    picture = decode_png(page.request.get(f"http://127.0.0.1:{port}/download/map.png").body())
    assert picture.shape[1] >= 800

    # A depth process dies: its pair shows dead.
    bus.kill(depth)
    page.wait_for_selector('#pairs li[data-pair="p0"][data-state="dead"]', timeout=10_000)
    assert page.inner_text("#summary").endswith("0/1 pairs alive")

    # Fusion stops: the page warns that the map is stale, then recovers when fusion is back.
    fusion.send_signal(signal.SIGINT)
    fusion.wait(15)
    page.wait_for_selector('#banner[data-kind="stale"]', state="visible", timeout=10_000)
    assert "stale" in page.inner_text("#banner")
    # What the panel knows of the pairs is as fusion last told it: greyed, and not counted alive.
    page.wait_for_selector('#pairs li.stale[data-pair="p0"][data-state="unknown"]')
    assert page.inner_text("#summary").endswith("1 pair, state unknown")
    _screenshot(page, tmp_path, "viewer-stale.png")
    # "Last observed" never asks fusion: with fusion gone the viewer still answers it.
    box_i, box_j = int(4.3 / RESOLUTION_M), int(1.3 / RESOLUTION_M)
    answer = page.request.get(f"http://127.0.0.1:{port}/cell?i={box_i}&j={box_j}").json()
    assert answer["i"] == box_i and 0 < answer["last_seen_s"] <= answer["now_s"]
    assert page.request.get(f"http://127.0.0.1:{port}/cell?i=x&j=1").status == 400
    bus.start(*fusion_args, log_path=tmp_path / "fusion-again.log")
    page.wait_for_selector("#banner", state="hidden", timeout=30_000)
    assert _rgb(page, 2.3, 2.3) == PICTURE_COLORS["occupied"]  # the restored map
    land(_window_m(1.0, 1.0, 1.4, 1.4), 3.0)
    page.wait_for_function(_drawn_as(page, 1.2, 1.2, "occupied"), timeout=5000)
    assert problems == []
    origin = f"127.0.0.1:{port}"
    assert f"ws://{origin}/ws" in asked
    assert [
        url for url in asked if not url.startswith((f"http://{origin}/", f"ws://{origin}/"))
    ] == []
    for queryable in queryables:
        queryable.undeclare()


@pytest.mark.process
def test_objects_and_a_rejected_token(bus: Bus, tmp_path: Path, browser_page: Any) -> None:
    page = browser_page
    port = free_port()
    viewer = bus.start("view", "--http-port", str(port), log_path=tmp_path / "view.log")
    _wait_http(port)
    page.goto(f"http://127.0.0.1:{port}/")
    page.wait_for_selector('#banner[data-kind="stale"]')  # no fusion on this bus: never answered
    assert "not answered yet" in page.inner_text("#banner")
    assert "not served" in page.inner_text("#objects")
    # Objects appear once map/objects answers (here the test answers it, as fusion does): in the
    # panel, and on the canvas outlined, with an arrow for the one that moves; greyed and said to
    # be the last known, as fusion (its health) does not answer on this bus.
    moving, standing = _tracked(7, (0.5, 0.0)), _tracked(8, (0.0, 0.0), center_m=(3.0, 1.0))
    payload = encode(OBJECTS_KIND, ObjectsHeader(version=1, stamp_ns=2, objects=[moving, standing]))
    queryable = bus.session.declare_queryable(
        "map/objects", lambda query: query.reply("map/objects", payload)
    )
    page.wait_for_selector('#objects:has-text("as last known: 2 tracked, 1 moving: 7 (0.5 m/s)")')
    queryable.undeclare()  # type: ignore[no-untyped-call]
    for tracked in (moving, standing):
        (x, y), (length, _), yaw = tracked.center_m, tracked.size_m, tracked.yaw_rad
        back_x, back_y = x - length / 2 * np.cos(yaw), y - length / 2 * np.sin(yaw)
        assert _drawn_near(page, back_x, back_y, LAST_KNOWN_RGB), tracked.id  # the back edge
    assert _drawn_near(page, 1.2, 2.0, LAST_KNOWN_RGB, radius_px=1)  # 7's arrow, in its outline
    assert not _drawn_near(page, 3.2, 1.0, LAST_KNOWN_RGB, radius_px=1)  # 8 stands: no arrow
    # A put that is no object list is refused (the viewer goes on); a change put by fusion
    # reaches the page at once, not at the next poll: 7 has moved.
    bus.session.put("map/objects", b"\x00\x01garbage")
    moved = _tracked(7, (0.5, 0.0), center_m=(2.0, 3.0))
    bus.session.put(
        "map/objects",
        encode(OBJECTS_KIND, ObjectsHeader(version=2, stamp_ns=3, objects=[moved, standing])),
    )
    back_x, back_y = 2.0 - 0.4 * np.cos(moved.yaw_rad), 3.0 - 0.4 * np.sin(moved.yaw_rad)
    wait_for(lambda: _drawn_near(page, back_x, back_y, LAST_KNOWN_RGB), 2, "7 drawn where it moved")
    assert "objects put refused" in (tmp_path / "view.log").read_text()
    _screenshot(page, tmp_path, "viewer-objects.png")
    # The viewer comes back wanting another token: the page says so, not "reconnecting".
    bus.kill(viewer)
    page.wait_for_selector('#banner[data-kind="disconnected"]', timeout=10_000)
    assert "reconnecting" in page.inner_text("#banner")
    assert page.inner_text("#objects").startswith("as last known: ")
    bus.start(
        "view", "--http-port", str(port), "--token", "another-token", log_path=tmp_path / "v2.log"
    )
    page.wait_for_selector('#banner[data-kind="rejected"]', timeout=15_000)
    assert "token rejected" in page.inner_text("#banner")


@pytest.mark.process
def test_the_page_recovers_from_a_viewer_that_stopped_answering(
    bus: Bus, tmp_path: Path, browser_page: Any
) -> None:
    """A dead link: the viewer's process is stopped, so its sockets stay open and say nothing. The
    page gives up on its socket and tries anew at once (a socket closed on a silent peer stays
    CLOSING for tens of seconds), and follows the viewer started in its place."""
    page = browser_page
    port = free_port()
    hung = bus.start("view", "--http-port", str(port), log_path=tmp_path / "view.log")
    _wait_http(port)
    page.goto(f"http://127.0.0.1:{port}/")
    page.wait_for_selector('#banner[data-kind="stale"]')  # connected (no fusion on this bus)
    try:
        # Silent for 3.5 s: the page's watchdog gives up on the socket, a new one follows at once.
        with page.expect_websocket(timeout=8_000):
            os.kill(_service_pid(hung), signal.SIGSTOP)
            page.wait_for_selector('#banner[data-kind="disconnected"]', timeout=8_000)
    finally:
        bus.kill(hung)  # SIGKILL ends a stopped process too, and frees the port
    bus.start("view", "--http-port", str(port), log_path=tmp_path / "view-again.log")
    _wait_http(port)
    page.wait_for_selector('#banner[data-kind="stale"]', timeout=8_000)  # connected again
    assert page.evaluate("window.overgridView.state.connected")


@pytest.mark.process
def test_a_fusion_that_lost_its_map_is_followed_anew(
    bus: Bus, tmp_path: Path, browser_page: Any
) -> None:
    page = browser_page
    land = _lander(bus)

    def fused(x0: float, y0: float, logodds: float, versions: int) -> bool:
        for _ in range(versions):
            land(_window_m(x0, y0, x0 + 0.5, y0 + 0.5), logodds)
            time.sleep(0.05)
        return (_value_at(bus.session, x0 + 0.25, y0 + 0.25) or 0) > 65

    first = bus.start("fusion", "--state-dir", str(tmp_path / "a"), log_path=tmp_path / "a.log")
    port = free_port()
    bus.start("view", "--http-port", str(port), log_path=tmp_path / "view.log")
    wait_for(lambda: fused(1.0, 1.0, 3.0, 30), 30, "the first fusion's map")
    page.goto(f"http://127.0.0.1:{port}/")
    page.wait_for_function(_drawn_as(page, 1.25, 1.25, "occupied"))
    first.send_signal(signal.SIGINT)
    first.wait(15)
    page.wait_for_selector('#banner[data-kind="stale"]', timeout=10_000)
    # A fusion with no saved map starts again at version 0, below what the page has seen.
    bus.start("fusion", "--state-dir", str(tmp_path / "b"), log_path=tmp_path / "b.log")
    wait_for(lambda: fused(2.0, 1.0, 3.0, 2), 30, "the second fusion's map")
    page.wait_for_function(_drawn_as(page, 2.25, 1.25, "occupied"), timeout=10_000)
    page.wait_for_selector("#banner", state="hidden")
    assert page.evaluate("window.overgridView.state.map.version") < 30
    # The lost map is gone from view (once the page has drawn the new map: a frame may be pending).
    page.wait_for_function(f"() => !({_drawn_as(page, 1.25, 1.25, 'occupied')})()", timeout=5_000)
    assert _rgb(page, 1.25, 1.25) != PICTURE_COLORS["occupied"]


def _touch(cdp: Any, *fingers: tuple[float, float], kind: str = "touchMove") -> None:
    """One touch event of real input (Chromium's DevTools protocol), fingers in page CSS pixels."""
    points = [{"x": x, "y": y, "id": k} for k, (x, y) in enumerate(fingers)]
    cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})


@pytest.mark.process
def test_a_phone_shows_a_sharp_map_and_pinches_it(bus: Bus, tmp_path: Path) -> None:
    """On a phone (390 CSS px wide, three device pixels to one, touch): the canvas holds a device
    pixel per pixel of the screen, the panel goes under the map, two fingers zoom about their
    midpoint and one drags, a tap reads the cell out."""
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), log_path=tmp_path / "fusion.log")
    port = free_port()
    bus.start("view", "--http-port", str(port), log_path=tmp_path / "view.log")
    land = _lander(bus)
    wait_for(lambda: _box_on_free_floor(bus, land), 60, "the box in the map")
    phone = {"width": 390, "height": 844}
    with _browser(
        tmp_path, viewport=phone, device_scale_factor=3, is_mobile=True, has_touch=True
    ) as page:
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function(_drawn_as(page, 2.3, 2.3, "occupied"))
        page.wait_for_function(_drawn_as(page, 1.0, 3.5, "free"))
        css_width, backing_width = page.evaluate(
            "[document.getElementById('map').clientWidth, document.getElementById('map').width]"
        )
        assert backing_width == 3 * css_width  # not a third of the pixels, stretched (blurred)
        assert css_width == phone["width"]  # the panel is under the map, not beside it
        _screenshot(page, tmp_path, "viewer-phone.png")

        corner = page.locator("#map").bounding_box()
        sx, sy = page.evaluate("window.overgridView.worldToScreen(2.3, 2.3)")
        x, y = corner["x"] + sx, corner["y"] + sy
        fitted = page.evaluate("window.overgridView.state.view.pxPerM")
        cdp = page.context.new_cdp_session(page)
        _touch(cdp, (x - 30, y), (x + 30, y), kind="touchStart")
        for step in range(1, 6):  # fingers 60 → 150 px apart, about the box
            _touch(cdp, (x - 30 - 9 * step, y), (x + 30 + 9 * step, y))
        _touch(cdp, kind="touchEnd")
        page.wait_for_function(f"() => window.overgridView.state.view.pxPerM > {2 * fitted}")
        assert page.evaluate("window.overgridView.state.view.pxPerM") == pytest.approx(
            2.5 * fitted, rel=0.02
        )
        assert page.evaluate("window.overgridView.worldToScreen(2.3, 2.3)") == pytest.approx(
            [sx, sy], abs=1
        )
        page.wait_for_function(_drawn_as(page, 2.3, 2.3, "occupied"))

        _touch(cdp, (x, y), kind="touchStart")
        for step in range(1, 5):
            _touch(cdp, (x + 10 * step, y))
        _touch(cdp, kind="touchEnd")
        assert page.evaluate("window.overgridView.worldToScreen(2.3, 2.3)") == pytest.approx(
            [sx + 40, sy], abs=1
        )
        page.tap("#map", position={"x": sx + 40, "y": sy})
        assert "height 1.20 m" in page.inner_text("#readout")
