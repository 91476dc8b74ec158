"""Which tiles fusion accepts: every rejection has a named reason, counted in ``map/health``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.codec import CodecError, decode
from common.lattice import Window
from common.messages import TILE_KIND, TileHeader

REASONS = ("malformed", "resolution", "dimensions", "nan", "stale", "out_of_order", "outside_map")


class TileRejected(ValueError):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass(frozen=True)
class AcceptedTile:
    header: TileHeader
    window: Window
    logodds: np.ndarray
    height_m: np.ndarray
    count: np.ndarray


class TileGate:
    """Decodes and checks tiles; remembers each pair's newest capture stamp to drop reordering."""

    def __init__(self, resolution_m: float, max_age_s: float, max_bytes: int) -> None:
        self.resolution_m = resolution_m
        self.max_age_ns = int(max_age_s * 1e9)
        self.max_bytes = max_bytes
        self.newest_stamp_ns: dict[str, int] = {}

    def admit(self, payload: bytes, now_ns: int) -> AcceptedTile:
        try:
            message = decode(payload, TILE_KIND, TileHeader, self.max_bytes)
        except CodecError as error:
            raise TileRejected("malformed", str(error)) from None
        h = message.header
        if abs(h.resolution_m - self.resolution_m) > 1e-9:
            raise TileRejected(
                "resolution",
                f"tile resolution {h.resolution_m} m ≠ map resolution {self.resolution_m} m",
            )
        layers = {}
        for name, dtype in (
            ("logodds", np.float32),
            ("height_m", np.float32),
            ("count", np.uint16),
        ):
            array = message.arrays.get(name)
            if array is None or array.dtype != dtype or array.shape != (h.rows, h.cols):
                got = "missing" if array is None else f"{array.dtype} {array.shape}"
                raise TileRejected(
                    "dimensions",
                    f"layer {name} must be {np.dtype(dtype)} {(h.rows, h.cols)}, got {got}",
                )
            layers[name] = array
        observed = layers["count"] > 0
        finite_where_observed = np.less_equal(observed, np.isfinite(layers["height_m"]))
        if not np.isfinite(layers["logodds"]).all() or not finite_where_observed.all():
            raise TileRejected(
                "nan", "tile holds NaN or infinite log-odds, or heights of observed cells"
            )
        if now_ns - h.stamp_ns > self.max_age_ns or h.stamp_ns - now_ns > self.max_age_ns:
            raise TileRejected(
                "stale", f"capture stamp is {(now_ns - h.stamp_ns) / 1e9:.2f} s from now"
            )
        if h.stamp_ns <= self.newest_stamp_ns.get(h.pair, -1):
            raise TileRejected(
                "out_of_order", f"tile of {h.pair} is not newer than the last one accepted"
            )
        self.newest_stamp_ns[h.pair] = h.stamp_ns
        return AcceptedTile(
            h,
            h.window,
            layers["logodds"],
            layers["height_m"],
            layers["count"],
        )
