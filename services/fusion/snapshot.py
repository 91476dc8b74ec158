"""Immutable map snapshots served by ``map/latest``: each format is encoded once per version, and
the builder that makes them from the owner's newest :class:`View` at the pace queries ask."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from common.codec import WIRE_ENCODING
from common.mapfiles import map_yaml, pgm_bytes, png_bytes
from common.occupancy_map import OccupancyMap, Region, region_of
from services.fusion.grid import ServedAssembler
from services.fusion.state import View

FORMATS = ("msgpack", "png", "pgm", "yaml")
LAYERS = ("logodds", "height", "predicted", "last_seen")
CONTENT_TYPES = {
    "msgpack": WIRE_ENCODING,
    "png": "image/png",
    "pgm": "image/x-portable-graymap",
    "yaml": "text/yaml",
}
MAX_CACHED_ENCODINGS = 32


class MapQueryError(ValueError):
    """A well-formed query the map cannot answer (nothing to draw, or a region off the map): the
    service replies with this error, naming why, rather than with an empty or broken payload."""


@dataclass(frozen=True)
class MapQuery:
    format: str = "msgpack"
    region: Region | None = None
    layers: tuple[str, ...] = ()


def parse_map_query(parameters: dict[str, str]) -> MapQuery:
    """Selector parameters of ``map/latest``; a ValueError says what is accepted."""
    unknown = set(parameters) - {"format", "region", "layers"}
    if unknown:
        raise ValueError(f"unknown parameters {sorted(unknown)}; accepted: format, region, layers")
    fmt = parameters.get("format", "msgpack")
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r} not one of {', '.join(FORMATS)}")
    region = region_of(parameters["region"].split(",")) if "region" in parameters else None
    layers = tuple(sorted(v for v in parameters.get("layers", "").split(",") if v))
    if set(layers) - set(LAYERS):
        raise ValueError(f"layers must be among {', '.join(LAYERS)}, got {parameters['layers']!r}")
    return MapQuery(fmt, region, layers)


class MapSnapshot:
    """One map version and its encodings. :meth:`encoded` raises :class:`MapQueryError` for a
    query that version cannot answer."""

    def __init__(self, full_map: OccupancyMap) -> None:
        self.map = full_map
        self._lock = threading.Lock()
        self._encoded: OrderedDict[MapQuery, bytes] = OrderedDict()

    @property
    def version(self) -> int:
        return self.map.version

    def encoded(self, query: MapQuery) -> bytes:
        """Bytes for ``query``, encoded at most once per snapshot however many clients ask."""
        with self._lock:
            if query in self._encoded:
                self._encoded.move_to_end(query)
                return self._encoded[query]
            payload = self._encode(query)
            self._encoded[query] = payload
            if len(self._encoded) > MAX_CACHED_ENCODINGS:
                self._encoded.popitem(last=False)
            return payload

    def _encode(self, query: MapQuery) -> bytes:
        view = self._view(query)
        if query.format == "msgpack":
            return replace(
                view,
                logodds=view.logodds if "logodds" in query.layers else None,
                height_m=view.height_m if "height" in query.layers else None,
                predicted=view.predicted if "predicted" in query.layers else None,
                last_seen_s=view.last_seen_s if "last_seen" in query.layers else None,
            ).to_msgpack()
        if query.format == "png":
            return png_bytes(view)
        if query.format == "pgm":
            return pgm_bytes(view)
        return map_yaml(view, "map.pgm").encode()

    def _view(self, query: MapQuery) -> OccupancyMap:
        """The cells ``query`` asks for. None at all is an error for a region or an image (an
        image of no pixels is no image); the whole map as msgpack may be empty: a follower that
        starts before the first tile still learns the version and resolution."""
        view = self.map if query.region is None else self.map.crop(query.region)
        if view.occupancy.size > 0 or (query.region is None and query.format == "msgpack"):
            return view
        if self.map.occupancy.size == 0:
            raise MapQueryError("the map has no cells yet (no tile fused): nothing to serve")
        x0, y0, x1, y1 = self.map.window.bounds_m(self.map.resolution_m)
        raise MapQueryError(
            "region {:g},{:g},{:g},{:g} does not overlap the map, which covers x {:g}…{:g} m, "
            "y {:g}…{:g} m".format(*(query.region or ()), x0, x1, y0, y1)
        )


SNAPSHOT_COST_SHARE = 0.2
QUERIED_RECENTLY_S = 2.0
STALE_LIMIT_S = 1.0
"""A query finding a snapshot older than this (and than two paces) waits for a new one."""
DEFAULT_QUERY = MapQuery()


def occupancy_map_of(
    view: View, with_layers: bool, assembler: ServedAssembler | None = None
) -> OccupancyMap:
    """The whole map of a View, assembled from its chunks (on a query thread, not the owner)."""
    frozen = view.frozen

    def layer(name: str) -> Any:
        return frozen.layer(name) if with_layers else None

    return OccupancyMap(
        occupancy=frozen.layer("served") if assembler is None else assembler.occupancy(frozen),
        resolution_m=frozen.resolution_m,
        i0=frozen.window.i0,
        j0=frozen.window.j0,
        version=frozen.version,
        stamp_ns=frozen.stamp_ns,
        pairs=list(view.pairs),
        epoch=frozen.epoch_ns,
        logodds=layer("logodds"),
        height_m=layer("height_m"),
        predicted=layer("predicted"),
        last_seen_s=layer("last_seen_s"),
    )


class SnapshotBuilder:
    """The ``map/latest`` snapshots, assembled from the newest View's chunks and encoded once
    however many clients ask, on a thread of their own, so a query does not wait for one. While
    clients ask (within QUERIED_RECENTLY_S), each map change makes a new one, no sooner than a pace
    after the last: the publish interval, or SNAPSHOT_COST_SHARE⁻¹ times what the last cost. So an
    unqueried map costs nothing, a huge map under a stream of tiles and of queries spends at most
    that share of the time on snapshots, and ``map/latest`` may be about a pace older than
    ``map/updates`` (followers replay the updates since). A query finding only a snapshot older
    than STALE_LIMIT_S (the first after a quiet spell) waits for a new one. Layered snapshots (a tool's,
    rarely asked) are made when asked, once per version."""

    def __init__(self, newest: Callable[[], View], min_interval_s: float) -> None:
        self._newest = newest
        self.min_interval_s = min_interval_s
        self._lock = threading.Lock()
        self._changed = threading.Event()
        self._closing = False
        self._queried_s = 0.0
        self._current: tuple[tuple[int, int], MapSnapshot, bytes, float] | None = None
        """(map version, snapshot, its plain msgpack answer, when it was made (monotonic s))."""
        self._layered: tuple[tuple[int, int], MapSnapshot] | None = None
        self._cost_s = 0.0
        self._assembler = ServedAssembler()
        self._thread = threading.Thread(target=self._run, name="fusion-snapshots", daemon=True)
        self._thread.start()

    def changed(self) -> None:
        """The owner published a new version."""
        self._changed.set()

    def _pace_s(self) -> float:
        return max(self.min_interval_s, self._cost_s / SNAPSHOT_COST_SHARE)

    def _usable(self) -> tuple[tuple[int, int], MapSnapshot, bytes, float] | None:
        now_s = time.monotonic()
        self._queried_s = now_s
        current = self._current
        if current is None or (
            current[0] != self._newest().frozen.key
            and now_s - current[3] >= max(STALE_LIMIT_S, 2 * self._pace_s())
        ):
            return None
        return current

    def plain(self) -> bytes | None:
        """Ready bytes for a plain ``map/latest`` (what robots ask), or None: ask :meth:`get`."""
        current = self._usable()
        return None if current is None else current[2]

    def get(self, with_layers: bool) -> MapSnapshot:
        if with_layers:
            with self._lock:
                view = self._newest()
                if self._layered is None or self._layered[0] != view.frozen.key:
                    self._layered = (view.frozen.key, MapSnapshot(occupancy_map_of(view, True)))
                return self._layered[1]
        current = self._usable()
        return current[1] if current is not None else self._build()

    def _build(self) -> MapSnapshot:
        with self._lock:
            view = self._newest()
            if self._current is not None and self._current[0] == view.frozen.key:
                return self._current[1]
            started = time.perf_counter()
            snapshot = MapSnapshot(occupancy_map_of(view, False, self._assembler))
            plain = snapshot.encoded(DEFAULT_QUERY)  # the answer most clients want, made once
            self._cost_s = time.perf_counter() - started
            self._current = (view.frozen.key, snapshot, plain, time.monotonic())
            return snapshot

    def _run(self) -> None:
        while True:
            self._changed.wait()
            if self._closing:
                return
            self._changed.clear()
            if time.monotonic() - self._queried_s > QUERIED_RECENTLY_S:
                continue  # nobody asks: the next query makes one
            self._build()
            time.sleep(self._pace_s())

    def close(self) -> None:
        self._closing = True
        self._changed.set()
        self._thread.join(5.0)
