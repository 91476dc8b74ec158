"""The map as a robot sees it: nav_msgs/OccupancyGrid conventions, on the global lattice."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from common.codec import decode, encode
from common.lattice import Window, cell_of
from common.messages import MAP_KIND, MapHeader

UNKNOWN = -1
"""nav_msgs/OccupancyGrid: unknown cell; known cells hold the occupancy probability in 0..100."""
OCCUPIED = 100
"""nav_msgs/OccupancyGrid: certainly occupied."""


OCCUPANCY_LUT_RANGE = 16.0
"""Log-odds beyond ±16 are 0 % / 100 % at int8 resolution."""
OCCUPANCY_LUT_SCALE = 256.0
"""Table entries per unit of log-odds."""
OCCUPANCY_LUT_OFFSET = OCCUPANCY_LUT_RANGE * OCCUPANCY_LUT_SCALE + 0.5
"""Index of log-odds L is ⌊L·scale + offset⌋ (in float64: exact, rounds half up), after clipping L."""
OCCUPANCY_LUT = np.rint(
    100.0
    / (
        1.0
        + np.exp(
            -np.linspace(
                -OCCUPANCY_LUT_RANGE,
                OCCUPANCY_LUT_RANGE,
                int(2 * OCCUPANCY_LUT_RANGE * OCCUPANCY_LUT_SCALE) + 1,
            )
        )
    )
).astype(np.int8)
"""nav_msgs occupancy 0..100 of log-odds by table lookup: maps are converted often and whole. The
fusion kernel indexes the same table the same way, so both give identical cells."""


def occupancy_from_logodds(
    logodds: npt.NDArray[np.float32], known: npt.NDArray[np.bool_]
) -> npt.NDArray[np.int8]:
    """nav_msgs occupancy 0..100, unknown -1, of whole layers."""
    clipped = np.clip(logodds, -OCCUPANCY_LUT_RANGE, OCCUPANCY_LUT_RANGE).astype(np.float64)
    index = (clipped * OCCUPANCY_LUT_SCALE + OCCUPANCY_LUT_OFFSET).astype(np.intp)
    occupancy: npt.NDArray[np.int8] = OCCUPANCY_LUT[index]
    occupancy[~known] = UNKNOWN
    return occupancy


OPTIONAL_LAYER_DTYPES = {
    "logodds": np.dtype(np.float32),
    "height_m": np.dtype(np.float32),
    "predicted": np.dtype(np.bool_),
    "last_seen_s": np.dtype(np.float64),
}
"""The layers a map message may carry beside ``occupancy``, each on the occupancy's cells."""


Region = tuple[float, float, float, float]
"""A metric rectangle x0, y0, x1, y1 in the world frame (metres)."""


def region_of(values: Sequence[str] | Sequence[float]) -> Region:
    """x0,y0,x1,y1 as four finite numbers with x1 > x0 and y1 > y0; a ValueError says which rule
    ``values`` breaks (an infinite or NaN bound would otherwise give a silent empty crop)."""
    text = ",".join(str(v) for v in values)
    try:
        x0, y0, x1, y1 = (float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(
            f"region must be four numbers x0,y0,x1,y1 in metres, got {text!r}"
        ) from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise ValueError(f"region bounds must be finite numbers of metres, got {text!r}")
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"region needs x1 > x0 and y1 > y0, got {text!r}")
    return (x0, y0, x1, y1)


@dataclass(frozen=True)
class OccupancyMap:
    occupancy: npt.NDArray[np.int8]
    """[row, col] = [j - j0, i - i0]: row 0 is the lowest y (the origin side)."""
    resolution_m: float
    i0: int
    j0: int
    version: int
    stamp_ns: int
    pairs: list[str] = field(default_factory=list)
    epoch: int = 0
    """Start (ns since the Unix epoch) of the fusion run that counted ``version``: the map's
    version is (epoch, version), compared in that order (common.messages.MapHeader)."""
    logodds: npt.NDArray[np.float32] | None = None
    height_m: npt.NDArray[np.float32] | None = None
    predicted: npt.NDArray[np.bool_] | None = None
    """Cells served occupied because a static object's measured footprint or a moving object's
    path covers them, not because a frame saw it."""
    last_seen_s: npt.NDArray[np.float64] | None = None
    """Capture time (Unix seconds) of each cell's newest observation, 0 where never observed: what
    decay and a person judging a cell's age go by."""

    @property
    def revision(self) -> tuple[int, int]:
        """(epoch, version): what tells a newer map from an older one, across fusion restarts."""
        return (self.epoch, self.version)

    @property
    def window(self) -> Window:
        return Window(self.i0, self.j0, self.occupancy.shape[1], self.occupancy.shape[0])

    @property
    def origin_m(self) -> tuple[float, float]:
        """World position of the lower-left corner of cell (0, 0), as map_server's ``origin``."""
        return self.window.origin_m(self.resolution_m)

    def crop(self, region_m: Region) -> OccupancyMap:
        """The part of the map covering the metric rectangle (x0, y0, x1, y1); no cells when
        the rectangle lies outside the map."""
        x0, y0, x1, y1 = region_of(region_m)
        # Within a cell of the map first: 1e308 m is a region holding the map, whose cell index
        # overflowed (answered "does not overlap the map").
        r = self.resolution_m
        mx0, my0, mx1, my1 = self.window.bounds_m(r)
        x0, x1 = max(x0, mx0 - r), min(x1, mx1 + r)
        y0, y1 = max(y0, my0 - r), min(y1, my1 + r)
        part = (
            Window.covering(x0, y0, x1, y1, r).intersect(self.window)
            if x1 > x0 and y1 > y0
            else Window(self.window.i0, self.window.j0, 0, 0)
        )
        rows, cols = part.slices_in(self.window)
        return replace(
            self,
            occupancy=self.occupancy[rows, cols],
            i0=part.i0,
            j0=part.j0,
            logodds=None if self.logodds is None else self.logodds[rows, cols],
            height_m=None if self.height_m is None else self.height_m[rows, cols],
            predicted=None if self.predicted is None else self.predicted[rows, cols],
            last_seen_s=None if self.last_seen_s is None else self.last_seen_s[rows, cols],
        )

    def value_at(self, x_m: float, y_m: float) -> int:
        """Occupancy of the cell holding world point (x, y); unknown outside the map (and at a
        point that is not finite)."""
        if not (math.isfinite(x_m) and math.isfinite(y_m)):
            return UNKNOWN
        i, j = (int(v) for v in cell_of((x_m, y_m), self.resolution_m))
        row, col = j - self.j0, i - self.i0
        if 0 <= row < self.occupancy.shape[0] and 0 <= col < self.occupancy.shape[1]:
            return int(self.occupancy[row, col])
        return UNKNOWN

    def to_msgpack(self) -> bytes:
        header = MapHeader(
            version=self.version,
            epoch=self.epoch,
            stamp_ns=self.stamp_ns,
            resolution_m=self.resolution_m,
            i0=self.i0,
            j0=self.j0,
            cols=self.occupancy.shape[1],
            rows=self.occupancy.shape[0],
            pairs=self.pairs,
        )
        arrays: dict[str, np.ndarray] = {"occupancy": self.occupancy}
        if self.logodds is not None:
            arrays["logodds"] = self.logodds
        if self.height_m is not None:
            arrays["height_m"] = self.height_m
        if self.predicted is not None:
            arrays["predicted"] = self.predicted
        if self.last_seen_s is not None:
            arrays["last_seen_s"] = self.last_seen_s
        return encode(MAP_KIND, header, arrays, compress=True)

    @staticmethod
    def from_msgpack(payload: bytes, max_bytes: int = 512 * 1024 * 1024) -> OccupancyMap:
        message = decode(payload, MAP_KIND, MapHeader, max_bytes)
        h = message.header
        occupancy = message.arrays.get("occupancy")
        if occupancy is None or occupancy.dtype != np.int8 or occupancy.shape != (h.rows, h.cols):
            raise ValueError("map message lacks an int8 occupancy array of the header's shape")
        for name, dtype in OPTIONAL_LAYER_DTYPES.items():
            layer = message.arrays.get(name)
            if layer is not None and (layer.dtype != dtype or layer.shape != occupancy.shape):
                raise ValueError(f"map layer {name!r} is not {dtype} of the occupancy's shape")
        return OccupancyMap(
            occupancy=occupancy,
            resolution_m=h.resolution_m,
            i0=h.i0,
            j0=h.j0,
            version=h.version,
            stamp_ns=h.stamp_ns,
            pairs=list(h.pairs),
            epoch=h.epoch,
            logodds=message.arrays.get("logodds"),
            height_m=message.arrays.get("height_m"),
            predicted=message.arrays.get("predicted"),
            last_seen_s=message.arrays.get("last_seen_s"),
        )
