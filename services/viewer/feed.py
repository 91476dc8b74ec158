"""The viewer's Zenoh side: follows fusion (``map/latest`` once, then ``map/updates`` through the
client's MapFollower), asks ``map/health``, the pairs' calibrations and depth health, the height
and last-seen layers and ``map/objects`` on their own periods, and keeps the newest of each for the page side.

Each poll runs on its own thread, so a silent key (fusion stopped, no camera source) delays no
other; every change calls ``notify`` (from any thread), which the server turns into a push.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import zenoh

from common import keys
from common.client import (
    MapFollower,
    MapUnavailable,
    calibrations,
    health,
    latest,
    objects,
    query_all,
)
from common.codec import CodecError, decode
from common.logs import RateLimitedLog
from common.messages import OBJECTS_KIND, ObjectsHeader
from common.occupancy_map import OccupancyMap
from services.viewer.footprints import Polygon, pair_footprint
from services.viewer.status import TileRates, objects_for_page, pair_states
from services.viewer.wire import CellTimes, MapLayers, height_mm

log = logging.getLogger("view")
DEPTH_HEALTH_TIMEOUT_S = 0.3
MAP_FIELDS = frozenset({"layers", "map", "cell_times"})
"""FeedState fields of the map itself: a change of only these is pushed as frames, not status."""
PER_CELL_LAYERS = ("height", "last_seen")
"""What the periodic layered query asks of map/latest (map/updates carry occupancy only)."""


@dataclass(frozen=True)
class FeedPeriods:
    health_s: float = 1.0
    height_s: float = 1.0
    calibration_s: float = 10.0
    depth_health_s: float = 2.0
    objects_s: float = 1.0
    query_timeout_s: float = 1.0


@dataclass(frozen=True)
class FeedState:
    """What the page side reads: one consistent set, replaced whole on every change."""

    layers: MapLayers | None = None
    map: OccupancyMap | None = None
    """The followed map itself (occupancy only): what the download buttons save."""
    fusion_answered_s: float | None = None
    """When map/health last answered (epoch seconds); None: never yet."""
    fusion_ok: bool = False
    """Whether the last map/health query was answered; the page's stale warning goes by
    ``fusion_answered_s`` (silent longer than --stale-after-s), not by one lost query."""
    map_health: dict[str, Any] | None = None
    pairs: list[dict[str, Any]] = field(default_factory=list)
    objects: list[dict[str, Any]] | None = None
    """None until map/objects first answers; then the newest list, kept while fusion is silent
    (the page shows it as last known)."""
    cell_times: CellTimes | None = None
    """The last_seen layer, fetched with the height layer; None until then."""
    map_revision: int = 0
    status_revision: int = 0


class MapFeed:
    def __init__(
        self,
        session: zenoh.Session,
        notify: Callable[[], None],
        periods: FeedPeriods = FeedPeriods(),
    ) -> None:
        self._session = session
        self.notify = notify
        """Called after every change, from any thread; the server sets it to wake its pushes."""
        self.periods = periods
        self._lock = threading.Lock()
        self._state = FeedState()
        self._follower: MapFollower | None = None
        self._generation = 0
        """Which follower's maps count: a closed follower's callback still in flight is ignored
        (it would bring back the lost map, and the new one's lower versions would be refused)."""
        self._rates = TileRates()
        self._footprints: dict[str, Polygon] = {}
        self._depth_health: dict[str, dict[str, Any]] = {}
        self._height_revision = (-1, -1)
        self._threads: list[threading.Thread] = []
        self._warn = RateLimitedLog(log)
        self._objects_revision = (-1, -1)
        """(epoch, version) of the objects shown: a poll's answer older than a put is dropped."""
        self._objects_subscriber: zenoh.Subscriber[None] | None = None

    def state(self) -> FeedState:
        with self._lock:
            return self._state

    def start(self, stop: threading.Event) -> None:
        # Each change of the objects as fusion puts it: polled once a second, a mover's outline
        # lagged the map (updated four times a second) by up to 3 m.
        self._objects_subscriber = self._session.declare_subscriber(
            keys.MAP_OBJECTS, self._on_objects
        )
        p = self.periods
        polls: list[tuple[str, float, Callable[[], None]]] = [
            ("health", p.health_s, self._poll_health),
            ("calibrations", p.calibration_s, self._poll_calibrations),
            ("depth-health", p.depth_health_s, self._poll_depth_health),
            ("objects", p.objects_s, self._poll_objects),
        ]
        if p.height_s > 0:
            polls.append(("height", p.height_s, self._poll_height))
        for name, period_s, poll in polls:
            thread = threading.Thread(
                target=self._loop, args=(stop, period_s, poll), name=f"view-{name}", daemon=True
            )
            thread.start()
            self._threads.append(thread)

    def join(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        if self._follower is not None:
            self._follower.close()
        if self._objects_subscriber is not None:
            self._objects_subscriber.undeclare()  # type: ignore[no-untyped-call]

    def _loop(self, stop: threading.Event, period_s: float, poll: Callable[[], None]) -> None:
        while not stop.is_set():
            started = time.monotonic()
            try:
                poll()
            except (MapUnavailable, zenoh.ZError) as error:
                log.debug("poll failed", extra={"poll": poll.__name__, "error": str(error)[:200]})
            except Exception as error:  # a poller must outlive one odd answer, and say so
                self._warn.warning(poll.__name__, "poll failed", error=repr(error)[:200])
            stop.wait(max(0.05, period_s - (time.monotonic() - started)))

    def _update(self, **changes: Any) -> None:
        self._change(lambda state: changes)

    def _change(self, make: Callable[[FeedState], dict[str, Any]]) -> None:
        """Replace the state with ``make``'s changes to it, made under the lock: the map arrives on
        Zenoh's threads and the height layer on another, and neither may undo the other."""
        with self._lock:
            state = self._state
            changes = make(state)
            if not changes:
                return
            changes["map_revision"] = state.map_revision + ("layers" in changes)
            changes["status_revision"] = state.status_revision + (not set(changes) <= MAP_FIELDS)
            self._state = replace(state, **changes)
        self.notify()

    # The map: MapFollower calls this from a Zenoh thread with each new version.
    def _on_map(self, occupancy_map: OccupancyMap, generation: int) -> None:
        def changes(state: FeedState) -> dict[str, Any]:
            if generation != self._generation:
                return {}
            layers = state.layers
            if layers is not None and layers.revision >= occupancy_map.revision:
                return {}
            return {
                "layers": MapLayers.of(occupancy_map)
                if layers is None
                else layers.with_occupancy(occupancy_map),
                "map": occupancy_map,
            }

        self._change(changes)

    def _follow(self) -> None:
        self._generation += 1
        generation = self._generation
        follower = MapFollower(
            self._session,
            timeout_s=self.periods.query_timeout_s,
            on_change=lambda occupancy_map, _arrival_s: self._on_map(occupancy_map, generation),
        )
        self._follower = follower
        self._on_map(follower.map, generation)
        log.info("following the map", extra={"version": follower.map.version})

    def _poll_health(self) -> None:
        try:
            answer = health(self._session, timeout_s=self.periods.query_timeout_s)
        except MapUnavailable:
            if self._state.fusion_ok:
                log.warning("fusion not answering")
            self._update(fusion_ok=False)  # the pairs as last known: fusion alone knows liveness
            return
        layers = self._state.layers
        if (
            self._follower is not None
            and layers is not None
            and (answer["map"].get("epoch", layers.epoch), answer["map"]["version"])
            < layers.revision
        ):
            # A fusion that came back without its saved map counts from zero: follow it anew
            # (a health answer without an epoch is taken to be of the map's own epoch).
            log.warning(
                "map version went back: following again",
                extra={"version": answer["map"]["version"]},
            )
            self._follower.close()
            self._follower = None
            self._generation += 1
            self._update(layers=None, map=None, cell_times=None)
        if self._follower is None:
            self._follow()
        self._update(
            fusion_ok=True,
            fusion_answered_s=time.time(),
            map_health=answer,
            pairs=self._pairs(answer),
        )

    def _pairs(self, answer: dict[str, Any] | None) -> list[dict[str, Any]]:
        with self._lock:
            footprints, depth_health = dict(self._footprints), dict(self._depth_health)
        return pair_states(answer, self._rates, time.time(), depth_health, footprints)

    def _poll_height(self) -> None:
        layers = self._state.layers
        if layers is None or layers.revision == self._height_revision:
            return
        layered = latest(
            self._session, layers=PER_CELL_LAYERS, timeout_s=self.periods.query_timeout_s
        )
        self._height_revision = layered.revision
        heights = height_mm(layered.height_m, layered.occupancy.shape)
        times = (
            None if layered.last_seen_s is None else CellTimes(layered.window, layered.last_seen_s)
        )

        def changes(state: FeedState) -> dict[str, Any]:
            if state.layers is None:
                return {}
            updated = state.layers.with_height(heights, layered.window, layered.resolution_m)
            return {"layers": updated, "map": state.map, "cell_times": times}

        self._change(changes)

    def _poll_calibrations(self) -> None:
        found = {
            c.pair: pair_footprint(c)
            for c in calibrations(self._session, self.periods.query_timeout_s)
        }
        footprints = {pair: polygon for pair, polygon in found.items() if polygon is not None}
        with self._lock:
            changed = footprints != self._footprints
            self._footprints = footprints
        if changed:
            self._update(pairs=self._pairs(self._state.map_health))

    def _poll_depth_health(self) -> None:
        """Every depth process's ``depth/{pair}/health`` in one query (each answers on its own key)."""
        rows: dict[str, dict[str, Any]] = {}
        try:
            payloads = query_all(self._session, keys.DEPTH_HEALTH_ALL, DEPTH_HEALTH_TIMEOUT_S)
        except MapUnavailable:
            payloads = []  # none running: fusion's liveliness says so already
        for payload in payloads:
            try:
                row = json.loads(payload)
            except json.JSONDecodeError:
                continue
            if isinstance(row, dict) and isinstance(row.get("pair"), str):
                rows[row["pair"]] = row
        with self._lock:
            self._depth_health = rows

    def _poll_objects(self) -> None:
        """The list when no put came (a viewer started after fusion's last change); a fusion
        that does not answer leaves the last list (or none: the page says not served)."""
        self._show_objects(objects(self._session, self.periods.query_timeout_s))

    def _on_objects(self, sample: zenoh.Sample) -> None:
        try:
            header = decode(sample.payload.to_bytes(), OBJECTS_KIND, ObjectsHeader).header
        except CodecError as error:
            self._warn.warning("objects", "objects put refused", error=str(error)[:200])
            return
        self._show_objects(header)

    def _show_objects(self, header: ObjectsHeader) -> None:
        with self._lock:
            if (header.epoch, header.version) <= self._objects_revision:
                return
            self._objects_revision = (header.epoch, header.version)
        self._update(objects=objects_for_page(header))
