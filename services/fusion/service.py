"""Fusion process: tiles in from every pair, one log-odds map out through queryables and updates."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np
import zenoh

from common import keys
from common.codec import WIRE_ENCODING, CodecError, decode, encode
from common.lattice import Window
from common.lifecycle import stop_on_signals
from common.logs import RateLimitedLog, setup_logging
from common.messages import (
    DETECTIONS_KIND,
    MAP_UPDATE_KIND,
    OBJECTS_KIND,
    DetectionsHeader,
    MapUpdateHeader,
    ObjectsHeader,
)
from common.occupancy_map import OccupancyMap
from common.settings import parse_settings
from common.zenoh_session import open_session
from services.fusion.grid import FusedGrid, TileOutsideMap, compile_rules
from services.fusion.intake import TileGate, TileRejected
from services.fusion.objects import ObjectTracker
from services.fusion.persistence import load_grid, save_grid
from services.fusion.settings import FusionSettings
from services.fusion.snapshot import CONTENT_TYPES, MapQuery, MapSnapshot, parse_map_query

log = logging.getLogger("fusion")
DEFAULT_QUERY = MapQuery()
REFRESH_COST_SHARE = 0.2
MAINTENANCE_PERIOD_S = 0.5
"""Decay, saves and summaries are checked this often even when no tile arrives."""


class FusionState:
    """The grid and its bookkeeping, shared by Zenoh callbacks and the maintenance loop."""

    def __init__(
        self, settings: FusionSettings, grid: FusedGrid, changed: threading.Event | None = None
    ) -> None:
        self.settings = settings
        self.grid = grid
        self.lock = threading.Lock()
        self.gate = TileGate(
            settings.resolution_m,
            settings.max_tile_age_s,
            int(settings.max_message_mb * 1024 * 1024),
        )
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.last_tile_s: dict[str, float] = {}
        self.capture_to_fused_ms: dict[str, float] = {}
        self.alive: set[str] = set()
        self.contributors: set[str] = set()
        self.snapshot = MapSnapshot(self._build_map())
        self._layered: MapSnapshot | None = None
        self.warn = RateLimitedLog(log)
        self.changed = changed or threading.Event()
        """Set by each accepted tile: the publishing loop wakes at once instead of polling."""
        self.refresh_cost_s = 0.0
        """Time the last refresh took (copy, encode): it bounds how often one is made."""
        self.tracker = ObjectTracker()
        self.objects_rejected: Counter[str] = Counter()
        self.objects_header = ObjectsHeader(version=0, stamp_ns=0, objects=[])

    def on_detections(self, sample: zenoh.Sample) -> None:
        """One pair's objects of one frame: held until the rest of the capture arrives."""
        now_ns = time.time_ns()
        try:
            message = decode(
                sample.payload.to_bytes(), DETECTIONS_KIND, DetectionsHeader, self.gate.max_bytes
            )
        except CodecError as error:
            self._reject_objects("malformed", str(error), str(sample.key_expr))
            return
        h = message.header
        try:
            key_pair = keys.pair_of(str(sample.key_expr))
        except ValueError:
            key_pair = ""
        if key_pair != h.pair:
            self._reject_objects("pair", f"header pair {h.pair} ≠ key", str(sample.key_expr))
            return
        if abs(now_ns - h.stamp_ns) > self.gate.max_age_ns:
            self._reject_objects("stale", "detections too old", str(sample.key_expr))
            return
        with self.lock:
            self.tracker.add(h.pair, h.stamp_ns, list(h.detections), now_ns / 1e9)
        self.changed.set()

    def _reject_objects(self, reason: str, detail: str, key: str) -> None:
        with self.lock:
            self.objects_rejected[reason] += 1
        self.warn.warning(
            f"objects_{reason}", "detections rejected", reason=reason, key=key, error=detail[:200]
        )

    def refresh_objects(self) -> ObjectsHeader | None:
        """Merge and track the captures that are complete, and sweep the moving tracks' paths
        into the predicted layer up to one frame interval past now (the map's visible time);
        returns the new object list if the tracks changed."""
        now_ns = time.time_ns()
        with self.lock:
            changed = self.tracker.flush(now_ns / 1e9, self.alive)
            until_ns = now_ns + int(self.tracker.ahead_s() * 1e9)
            if self.settings.predict_movers:
                swept = self.tracker.sweep(
                    self.grid.params.resolution_m, self.grid.stamp_ns, until_ns
                )
                self.grid.set_predicted(swept)
            if not changed:
                return None
            self.objects_header = ObjectsHeader(
                version=self.tracker.version,
                stamp_ns=self.tracker.stamp_ns,
                objects=self.tracker.objects(),
            )
            return self.objects_header

    def on_tile(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        now_ns = time.time_ns()
        try:
            with self.lock:
                tile = self.gate.admit(payload, now_ns)
                self.grid.integrate(
                    tile.window, tile.logodds, tile.height_m, tile.count, tile.header.stamp_ns
                )
                pair = tile.header.pair
                self.accepted[pair] += 1
                self.contributors.add(pair)
                self.last_tile_s[pair] = time.time()
                self.capture_to_fused_ms[pair] = (time.time_ns() - tile.header.stamp_ns) / 1e6
            self.changed.set()
        except TileRejected as rejection:
            self._reject(rejection.reason, str(rejection), str(sample.key_expr))
        except TileOutsideMap as error:
            self._reject("outside_map", str(error), str(sample.key_expr))

    def _reject(self, reason: str, detail: str, key: str) -> None:
        with self.lock:
            self.rejected[reason] += 1
            total = sum(self.rejected.values())
        self.warn.warning(
            reason, "tile rejected", reason=reason, key=key, error=detail[:200], rejected=total
        )

    def on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            pair = keys.pair_of(str(sample.key_expr))
        except ValueError:
            return
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(pair)
            else:
                self.alive.discard(pair)
        log.info(
            "pair joined" if sample.kind == zenoh.SampleKind.PUT else "pair left",
            extra={"pair": pair},
        )

    def _build_map(self, with_layers: bool = False) -> OccupancyMap:
        """Copy of the grid's occupancy (and, if asked, its layers); call with the lock held."""
        grid = self.grid
        return OccupancyMap(
            occupancy=grid.served_occupancy(),
            resolution_m=grid.params.resolution_m,
            i0=grid.window.i0,
            j0=grid.window.j0,
            version=grid.version,
            stamp_ns=grid.stamp_ns,
            pairs=sorted(self.contributors),
            logodds=grid.logodds.copy() if with_layers else None,
            height_m=grid.height_m.copy() if with_layers else None,
            predicted=grid.predicted.copy() if with_layers else None,
        )

    def snapshot_for(self, query: MapQuery) -> MapSnapshot:
        """The current snapshot; one with layers (rarely asked: a tool, not a robot) is built from
        the grid when asked, once per map version."""
        if not query.layers:
            return self.snapshot
        with self.lock:
            if self._layered is None or self._layered.version != self.grid.version:
                self._layered = MapSnapshot(self._build_map(with_layers=True))
            return self._layered

    def next_refresh_in(self, since_last_s: float) -> float:
        """Seconds to wait before the next snapshot: at least the configured interval, and at
        least REFRESH_COST_SHARE⁻¹ times what the last one cost, so a huge map under a stream of
        tiles never spends more than that share of the time encoding snapshots."""
        interval = max(self.settings.publish_interval_s, self.refresh_cost_s / REFRESH_COST_SHARE)
        return max(0.0, interval - since_last_s)

    def refresh(self) -> tuple[MapSnapshot, Window, int] | None:
        """A new snapshot if the grid changed since the last one, with the changed window."""
        started = time.perf_counter()
        with self.lock:
            if self.grid.version == self.snapshot.version:
                return None
            previous = self.snapshot.version
            snapshot = MapSnapshot(self._build_map())
            dirty = self.grid.take_dirty()
        # Encode the default answer here, off the query path and outside the lock, before clients
        # can see this snapshot: no query waits for a compression.
        snapshot.encoded(DEFAULT_QUERY)
        self.snapshot = snapshot
        self.refresh_cost_s = time.perf_counter() - started
        return snapshot, dirty, previous

    def decay(self, elapsed_s: float) -> None:
        with self.lock:
            self.grid.decay(time.time(), elapsed_s)

    def health(self) -> dict[str, Any]:
        now = time.time()
        with self.lock:
            pairs = sorted(set(self.accepted) | self.alive)
            grid = self.grid
            return {
                "pairs": {
                    p: {
                        "alive": p in self.alive,
                        "tiles": self.accepted[p],
                        "last_tile_age_s": round(now - self.last_tile_s[p], 3)
                        if p in self.last_tile_s
                        else None,
                        "capture_to_fused_ms": self.capture_to_fused_ms.get(p),
                    }
                    for p in pairs
                },
                "tiles_accepted": sum(self.accepted.values()),
                "tiles_rejected": dict(self.rejected),
                "detections_rejected": dict(self.objects_rejected),
                "objects": len(self.objects_header.objects),
                "map": {
                    "version": grid.version,
                    "cols": grid.window.cols,
                    "rows": grid.window.rows,
                    "resolution_m": grid.params.resolution_m,
                    "origin_m": list(grid.window.origin_m(grid.params.resolution_m)),
                    "known_cells": int(grid.known.sum()),
                },
            }


def update_payload(snapshot: MapSnapshot, dirty: Window, previous_version: int) -> bytes:
    full = snapshot.map
    part = dirty.intersect(full.window)
    rows, cols = part.slices_in(full.window)
    header = MapUpdateHeader(
        version=full.version,
        previous_version=previous_version,
        stamp_ns=full.stamp_ns,
        resolution_m=full.resolution_m,
        i0=part.i0,
        j0=part.j0,
        cols=part.cols,
        rows=part.rows,
        map_i0=full.i0,
        map_j0=full.j0,
        map_cols=full.window.cols,
        map_rows=full.window.rows,
    )
    arrays = {"occupancy": np.ascontiguousarray(full.occupancy[rows, cols])}
    return encode(MAP_UPDATE_KIND, header, arrays)


OBJECT_FORMATS = {"msgpack": WIRE_ENCODING, "json": "application/json"}


def objects_payload(header: ObjectsHeader, fmt: str) -> bytes:
    """``map/objects`` as msgpack (the codec's envelope) or, for people, plain JSON."""
    if fmt == "json":
        return json.dumps(header.model_dump(mode="json")).encode()
    return encode(OBJECTS_KIND, header)


def main(settings: FusionSettings) -> None:
    setup_logging("fusion", settings.log_level)
    changed = threading.Event()
    stop = stop_on_signals(changed)  # before loading the state: a stop during a long load is clean
    params = settings.grid_params()
    compile_rules()
    grid = load_grid(params, settings.state_dir) or FusedGrid(params)
    state = FusionState(settings, grid, changed)
    if grid.version:
        log.info(
            "map restored",
            extra={"version": grid.version, "cols": grid.window.cols, "rows": grid.window.rows},
        )

    def on_map_query(query: zenoh.Query) -> None:
        try:
            request = parse_map_query(dict(query.parameters))
        except ValueError as error:
            query.reply_err(f"map/latest: {error}")
            return
        snapshot = state.snapshot_for(request)
        query.reply(
            query.key_expr, snapshot.encoded(request), encoding=CONTENT_TYPES[request.format]
        )

    def on_objects_query(query: zenoh.Query) -> None:
        fmt = dict(query.parameters).get("format", "msgpack")
        if fmt not in OBJECT_FORMATS:
            query.reply_err(f"map/objects: format {fmt!r} not one of {', '.join(OBJECT_FORMATS)}")
            return
        with state.lock:
            header = state.objects_header
        query.reply(query.key_expr, objects_payload(header, fmt), encoding=OBJECT_FORMATS[fmt])

    def on_health_query(query: zenoh.Query) -> None:
        query.reply(query.key_expr, json.dumps(state.health()), encoding="application/json")

    with open_session(settings) as session:
        subscriber = session.declare_subscriber(keys.TILES_ALL, state.on_tile)
        liveliness = session.liveliness().declare_subscriber(
            keys.DEPTH_ALIVE_ALL, state.on_liveliness, history=True
        )
        map_queryable = session.declare_queryable(keys.MAP_LATEST, on_map_query)
        health_queryable = session.declare_queryable(keys.MAP_HEALTH, on_health_query)
        detections = session.declare_subscriber(keys.OBJECTS_ALL, state.on_detections)
        objects_queryable = session.declare_queryable(keys.MAP_OBJECTS, on_objects_query)
        # DROP, as map/updates: a query of map/objects always gives the current list.
        objects_publisher = session.declare_publisher(
            keys.MAP_OBJECTS,
            encoding=WIRE_ENCODING,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        # DROP: a robot on a slow link must never stall fusion; a follower that misses an update sees
        # the version gap and fetches map/latest instead.
        updates = session.declare_publisher(
            keys.MAP_UPDATES,
            encoding=WIRE_ENCODING,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        log.info(
            "started",
            extra={"resolution_m": settings.resolution_m, "state_dir": str(settings.state_dir)},
        )
        started = time.monotonic()
        last = {"decay": started, "save": started, "summary": started, "refresh": 0.0}
        saved_version = grid.version
        while not stop.is_set():
            # Publish a change as soon as it lands, but no sooner than the refresh interval.
            state.changed.wait(MAINTENANCE_PERIOD_S)
            if stop.wait(state.next_refresh_in(time.monotonic() - last["refresh"])):
                break
            state.changed.clear()
            objects = state.refresh_objects()
            if objects is not None:
                objects_publisher.put(objects_payload(objects, "msgpack"))
            refreshed = state.refresh()
            now = time.monotonic()
            if refreshed is not None:  # the interval runs from the last snapshot actually made
                last["refresh"] = now
                snapshot, dirty, previous = refreshed
                if not dirty.empty:
                    updates.put(update_payload(snapshot, dirty, previous))
            if now - last["decay"] >= 1.0:
                state.decay(now - last["decay"])
                last["decay"] = now
            if (
                now - last["save"] >= settings.save_interval_s
                and state.snapshot.version != saved_version
            ):
                with state.lock:
                    save_grid(state.grid, settings.state_dir)
                    saved_version = state.grid.version
                last["save"] = now
            if now - last["summary"] >= settings.summary_s:
                health = state.health()
                log.info(
                    "summary",
                    extra={
                        "version": health["map"]["version"],
                        "tiles": health["tiles_accepted"],
                        "rejected": sum(health["tiles_rejected"].values()),
                        "alive": ",".join(p for p, v in health["pairs"].items() if v["alive"]),
                    },
                )
                last["summary"] = now
        subscriber.undeclare()
        liveliness.undeclare()
        map_queryable.undeclare()
        health_queryable.undeclare()
        detections.undeclare()
        objects_queryable.undeclare()
    with state.lock:
        path = save_grid(state.grid, settings.state_dir)
    log.info("stopped", extra={"version": state.grid.version, "saved": str(path)})


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            FusionSettings,
            argv,
            "overgrid fusion",
            "Fuses every pair's tiles into one occupancy map.",
        )
    )
