"""Immutable map snapshots served by ``map/latest``: each format is encoded once per version."""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, replace

from common.codec import WIRE_ENCODING
from common.mapfiles import map_yaml, pgm_bytes, png_bytes
from common.occupancy_map import OccupancyMap, Region, region_of

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
        (x0, y0), r = self.map.origin_m, self.map.resolution_m
        x1, y1 = x0 + self.map.window.cols * r, y0 + self.map.window.rows * r
        raise MapQueryError(
            "region {:g},{:g},{:g},{:g} does not overlap the map, which covers x {:g}…{:g} m, "
            "y {:g}…{:g} m".format(*(query.region or ()), x0, x1, y0, y1)
        )
