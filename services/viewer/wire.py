"""What the page receives: the map as layers on one lattice window, sent whole once and then as the
rectangles that changed. Binary frames the browser reads with typed arrays, no library needed:

    u32 little-endian n | n bytes of JSON header | occupancy int8 rows×cols | [height u16 LE rows×cols]

rows from the origin side (row 0 = lowest y), as nav_msgs stores them. The pure part of the viewer:
no network, no event loop.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from common.lattice import Window, reframe
from common.occupancy_map import OccupancyMap

NO_HEIGHT_MM = 0xFFFF
"""Height layer value of a cell with no observed top (unseen, or the layer not fetched yet)."""
MAX_HEIGHT_MM = NO_HEIGHT_MM - 1
CHUNK_CELLS = 64
"""Changes are found per square chunk of this many cells a side, then sent as row runs of chunks."""
FULL_BEYOND_SHARE = 0.5
"""When the changed chunks cover more than this share of the map, one full frame is cheaper."""
_LENGTH = struct.Struct("<I")


def height_mm(
    height_m: npt.NDArray[np.float32] | None, shape: tuple[int, int]
) -> npt.NDArray[np.uint16]:
    """Top heights in whole millimetres (2 bytes a cell on the wire); NaN or absent → NO_HEIGHT_MM."""
    if height_m is None:
        return np.full(shape, NO_HEIGHT_MM, np.uint16)
    seen = np.isfinite(height_m)
    millimetres = np.clip(np.where(seen, height_m, 0.0) * 1000.0, 0.0, MAX_HEIGHT_MM)
    return np.where(seen, np.rint(millimetres), NO_HEIGHT_MM).astype(np.uint16)


@dataclass(frozen=True)
class MapLayers:
    """The map as the page shows it. Arrays are never written after construction."""

    window: Window
    resolution_m: float
    version: int
    stamp_ns: int
    occupancy: npt.NDArray[np.int8]
    height_mm: npt.NDArray[np.uint16]
    epoch: int = 0

    @property
    def revision(self) -> tuple[int, int]:
        """As ``OccupancyMap.revision``: (epoch, version), newer maps compare greater."""
        return (self.epoch, self.version)

    @staticmethod
    def of(occupancy_map: OccupancyMap) -> MapLayers:
        return MapLayers(
            window=occupancy_map.window,
            resolution_m=occupancy_map.resolution_m,
            version=occupancy_map.version,
            stamp_ns=occupancy_map.stamp_ns,
            occupancy=occupancy_map.occupancy,
            height_mm=height_mm(occupancy_map.height_m, occupancy_map.occupancy.shape),
            epoch=occupancy_map.epoch,
        )

    def with_occupancy(self, occupancy_map: OccupancyMap) -> MapLayers:
        """A newer occupancy (``map/updates`` carry no height); the height known so far is kept on
        the cells both windows share."""
        if occupancy_map.height_m is not None or occupancy_map.resolution_m != self.resolution_m:
            return MapLayers.of(occupancy_map)
        window = occupancy_map.window
        kept = (
            self.height_mm
            if window == self.window
            else reframe(self.height_mm, self.window, window, NO_HEIGHT_MM)
        )
        return replace(
            self,
            window=window,
            version=occupancy_map.version,
            stamp_ns=occupancy_map.stamp_ns,
            occupancy=occupancy_map.occupancy,
            height_mm=kept,
            epoch=occupancy_map.epoch,
        )

    def with_height(
        self, heights_mm: npt.NDArray[np.uint16], window: Window, resolution_m: float
    ) -> MapLayers:
        """The height layer (from :func:`height_mm`) of a possibly older or differently sized
        map, on this window."""
        if resolution_m != self.resolution_m:
            return self
        if window != self.window:
            heights_mm = reframe(heights_mm, window, self.window, NO_HEIGHT_MM)
        return replace(self, height_mm=heights_mm)


@dataclass(frozen=True)
class CellTimes:
    """Each cell's newest capture time (Unix s, 0 never observed) on a lattice window, fetched
    with the height layer: the viewer answers a page's "last observed" from it, so hovering in
    any number of tabs costs fusion nothing beyond that one periodic query."""

    window: Window
    last_seen_s: npt.NDArray[np.float64]

    def at(self, i: int, j: int) -> float | None:
        """The time of cell (i, j); None outside the window."""
        row, col = j - self.window.j0, i - self.window.i0
        if 0 <= row < self.window.rows and 0 <= col < self.window.cols:
            return float(self.last_seen_s[row, col])
        return None


def changed_windows(
    old: MapLayers, new: MapLayers, chunk_cells: int = CHUNK_CELLS
) -> list[Window] | None:
    """Rectangles of ``new`` that differ from ``old`` (each a row run of changed chunks); None when
    only a full frame will do: another window or resolution, or most of the map changed."""
    if old.window != new.window or old.resolution_m != new.resolution_m:
        return None
    differs = (old.occupancy != new.occupancy) | (old.height_mm != new.height_mm)
    rows, cols = differs.shape
    chunk_rows, chunk_cols = -(-rows // chunk_cells), -(-cols // chunk_cells)
    padded = np.zeros((chunk_rows * chunk_cells, chunk_cols * chunk_cells), np.bool_)
    padded[:rows, :cols] = differs
    chunks = np.any(padded.reshape(chunk_rows, chunk_cells, chunk_cols, chunk_cells), axis=(1, 3))
    if chunks.sum() * chunk_cells * chunk_cells > FULL_BEYOND_SHARE * max(rows * cols, 1):
        return None
    windows = []
    for chunk_row in range(chunk_rows):
        flags = np.concatenate([[False], chunks[chunk_row], [False]])
        edges = np.flatnonzero(flags[1:] != flags[:-1])
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            row0, col0 = chunk_row * chunk_cells, int(start) * chunk_cells
            windows.append(
                Window(
                    new.window.i0 + col0,
                    new.window.j0 + row0,
                    min(int(stop) * chunk_cells, cols) - col0,
                    min(row0 + chunk_cells, rows) - row0,
                )
            )
    return windows


def _frame(header: dict[str, Any], *arrays: npt.NDArray[Any]) -> bytes:
    head = json.dumps(header, separators=(",", ":")).encode()
    body = [
        np.ascontiguousarray(a).astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        for a in arrays
    ]
    return b"".join([_LENGTH.pack(len(head)), head, *body])


def _geometry(window: Window) -> dict[str, int]:
    return {"i0": window.i0, "j0": window.j0, "cols": window.cols, "rows": window.rows}


def full_frame(layers: MapLayers) -> bytes:
    """The whole map: the page (re)builds its picture from this."""
    header = {
        "type": "map",
        "version": layers.version,
        "stamp_ns": layers.stamp_ns,
        "resolution_m": layers.resolution_m,
        **_geometry(layers.window),
    }
    return _frame(header, layers.occupancy, layers.height_mm)


def rect_frame(layers: MapLayers, window: Window) -> bytes:
    """One changed rectangle of the map the page already holds (lattice indices, not offsets)."""
    rows, cols = window.slices_in(layers.window)
    header = {
        "type": "rect",
        "version": layers.version,
        "stamp_ns": layers.stamp_ns,
        **_geometry(window),
    }
    return _frame(header, layers.occupancy[rows, cols], layers.height_mm[rows, cols])


def frames_between(old: MapLayers | None, new: MapLayers) -> list[bytes]:
    """What brings a page showing ``old`` to ``new``: changed rectangles, else one full frame."""
    windows = None if old is None else changed_windows(old, new)
    if windows is None:
        return [full_frame(new)]
    return [rect_frame(new, window) for window in windows]


def read_frame(
    data: bytes,
) -> tuple[dict[str, Any], npt.NDArray[np.int8], npt.NDArray[np.uint16]]:
    """Header, occupancy and height of a frame: what the page's reader does, for tests and tools."""
    (length,) = _LENGTH.unpack_from(data)
    header: dict[str, Any] = json.loads(data[_LENGTH.size : _LENGTH.size + length])
    shape = (header["rows"], header["cols"])
    start = _LENGTH.size + length
    cells = shape[0] * shape[1]
    occupancy = np.frombuffer(data, np.int8, cells, start).reshape(shape)
    height = np.frombuffer(data, np.dtype("<u2"), cells, start + cells).reshape(shape)
    return header, occupancy, height.astype(np.uint16)
