"""Hand-made tiles for fusion tests."""

from __future__ import annotations

import time

import numpy as np
import zenoh

from common import keys
from common.client import MapUnavailable, latest
from common.codec import encode
from common.lattice import Window
from common.messages import TILE_KIND, TileHeader
from services.fusion.grid import FusedGrid


def tile_arrays(
    window: Window, logodds: float, height_m: float = 0.0, count: int = 5
) -> dict[str, np.ndarray]:
    return {
        "logodds": np.full(window.shape, logodds, np.float32),
        "height_m": np.full(window.shape, height_m, np.float32),
        "count": np.full(window.shape, count, np.uint16),
    }


def tile_payload(
    pair: str,
    window: Window,
    logodds: float,
    seq: int = 0,
    stamp_ns: int | None = None,
    resolution_m: float = 0.05,
    height_m: float = 0.0,
    arrays: dict[str, np.ndarray] | None = None,
) -> bytes:
    header = TileHeader(
        pair=pair,
        seq=seq,
        stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns,
        resolution_m=resolution_m,
        i0=window.i0,
        j0=window.j0,
        cols=window.cols,
        rows=window.rows,
    )
    return encode(
        TILE_KIND, header, arrays if arrays is not None else tile_arrays(window, logodds, height_m)
    )


def dirty_window(grid: FusedGrid) -> Window:
    """The bounding window of the cells ``grid`` changed since they were last taken (taking them)."""
    bounding = Window(0, 0, 0, 0)
    for cells in grid.take_dirty_parts().values():
        bounding = bounding.union(cells)
    return bounding


def measure(grid: FusedGrid, window: Window, logodds: float, stamp_ns: int = 0) -> None:
    """One tile of ``logodds`` over ``window`` into ``grid`` (20 pixels a cell, 1 m tops)."""
    arrays = tile_arrays(window, logodds, height_m=1.0, count=20)
    grid.integrate(window, arrays["logodds"], arrays["height_m"], arrays["count"], stamp_ns)


def put_until_fused(writer: zenoh.Session, reader: zenoh.Session, timeout_s: float = 30) -> None:
    """A tile of p0 put by ``writer`` until ``reader`` sees a map built from one: fusion may not
    be subscribed yet, and it compiles its update at its first tile."""

    def fused() -> bool:
        writer.put(keys.tile("p0"), tile_payload("p0", Window(0, 0, 20, 20), 1.0))
        try:
            return latest(reader, timeout_s=1).version >= 1
        except MapUnavailable:
            return False

    deadline = time.monotonic() + timeout_s
    while not fused():
        if time.monotonic() > deadline:
            raise AssertionError(f"no tile fused within {timeout_s} s")
