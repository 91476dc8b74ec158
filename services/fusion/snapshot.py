"""Immutable map snapshots served by ``map/latest``: each format is encoded once per version."""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, replace

from common.codec import WIRE_ENCODING
from common.mapfiles import map_yaml, pgm_bytes, png_bytes
from common.occupancy_map import OccupancyMap

FORMATS = ("msgpack", "png", "pgm", "yaml")
LAYERS = ("logodds", "height", "predicted", "last_seen")
CONTENT_TYPES = {
    "msgpack": WIRE_ENCODING,
    "png": "image/png",
    "pgm": "image/x-portable-graymap",
    "yaml": "text/yaml",
}
MAX_CACHED_ENCODINGS = 32

Region = tuple[float, float, float, float]


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
    region = None
    if "region" in parameters:
        try:
            x0, y0, x1, y1 = (float(v) for v in parameters["region"].split(","))
        except ValueError:
            raise ValueError(
                f"region must be x0,y0,x1,y1 in metres, got {parameters['region']!r}"
            ) from None
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"region needs x1 > x0 and y1 > y0, got {parameters['region']!r}")
        region = (x0, y0, x1, y1)
    layers = tuple(sorted(v for v in parameters.get("layers", "").split(",") if v))
    if set(layers) - set(LAYERS):
        raise ValueError(f"layers must be among {', '.join(LAYERS)}, got {parameters['layers']!r}")
    return MapQuery(fmt, region, layers)


class MapSnapshot:
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
        view = self.map.crop(query.region) if query.region else self.map
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
