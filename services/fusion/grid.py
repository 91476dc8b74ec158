"""The fused map: clamped log-odds, top heights and observation times on the global lattice.

Pure numpy: no Zenoh, no threads. The service holds one :class:`FusedGrid` behind a lock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from common.lattice import Window
from common.occupancy_map import UNKNOWN, occupancy_from_logodds
from services.fusion import rules

GROWTH_CHUNK_CELLS = 64
LAYER_FILLS = (
    ("logodds", 0.0),
    ("height_m", np.nan),
    ("known", False),
    ("last_seen_s", 0.0),
    ("occupancy", UNKNOWN),
    ("predicted", False),
)
"""Every per-cell array of the grid and the value of a cell never observed."""
"""The map grows in chunks so a stream of tiles at its edge does not reallocate every time."""


@dataclass(frozen=True)
class GridParams:
    resolution_m: float = 0.05
    logodds_min: float = -1.5
    logodds_max: float = 2.5
    """Narrower than OctoMap's −2 … 3.5: with the depth model's p_hit/p_miss of 0.9/0.1, one
    conclusive observation moves a cell across the occupied (0.65) or free (0.25) threshold, so a
    moved object appears and clears within a frame; ambiguous observations still accumulate."""
    decay_after_s: float = 5.0
    """Cells unobserved this long start drifting back toward unknown."""
    decay_time_constant_s: float = 2.0
    unknown_below: float = 0.05
    """|L| under which a decaying cell is unknown again."""
    max_cells: int = 25_000_000
    bounds: Window | None = None
    """Fixed map window; None grows the map to cover the tiles."""

    def __post_init__(self) -> None:
        if not self.logodds_min < 0 < self.logodds_max:
            raise ValueError(
                f"need logodds_min < 0 < logodds_max, got {self.logodds_min}, {self.logodds_max}"
            )
        if self.decay_after_s <= 0 or self.decay_time_constant_s <= 0:
            raise ValueError("decay times must be positive")


class TileOutsideMap(ValueError):
    """The tile would make the map larger than allowed, or lies outside fixed bounds."""


def _chunked(window: Window) -> Window:
    c = GROWTH_CHUNK_CELLS
    i0, j0 = math.floor(window.i0 / c) * c, math.floor(window.j0 / c) * c
    i1, j1 = math.ceil(window.i1 / c) * c, math.ceil(window.j1 / c) * c
    return Window(i0, j0, i1 - i0, j1 - j0)


class FusedGrid:
    def __init__(self, params: GridParams) -> None:
        self.params = params
        self.window = params.bounds or Window(0, 0, 0, 0)
        self.logodds = np.zeros(self.window.shape, np.float32)
        self.height_m = np.full(self.window.shape, np.nan, np.float32)
        self.known = np.zeros(self.window.shape, np.bool_)
        self.last_seen_s = np.zeros(self.window.shape, np.float64)
        self.occupancy = np.full(self.window.shape, UNKNOWN, np.int8)
        """nav_msgs view of ``logodds``/``known``, kept current cell by cell as they change."""
        self.predicted = np.zeros(self.window.shape, np.bool_)
        """Cells a moving object's path covers (its own layer, not evidence: never saved)."""
        self.predicted_any = False
        self.version = 0
        self.stamp_ns = 0
        self.dirty = Window(0, 0, 0, 0)
        """Cells changed since :meth:`take_dirty` was last called."""

    def _grow_to(self, needed: Window) -> None:
        if self.window.contains(needed):
            return
        target = _chunked(self.window.union(needed))
        if target.cols * target.rows > self.params.max_cells:
            raise TileOutsideMap(
                f"covering {needed} needs a map of {target.cols}×{target.rows} cells, over the limit of {self.params.max_cells}"
            )
        old_slices = self.window.slices_in(target)
        for name, fill in LAYER_FILLS:
            old = getattr(self, name)
            grown = np.full(target.shape, fill, dtype=old.dtype)
            grown[old_slices] = old
            setattr(self, name, grown)
        self.window = target

    def integrate(
        self,
        tile_window: Window,
        logodds_update: npt.NDArray[np.float32],
        tile_height_m: npt.NDArray[np.float32],
        count: npt.NDArray[np.uint16],
        stamp_ns: int,
    ) -> Window:
        """Add one tile's evidence; returns the map cells it touched."""
        if self.params.bounds is None:
            self._grow_to(tile_window)
        part = tile_window.intersect(self.window)
        if part.empty:
            raise TileOutsideMap(f"tile {tile_window} lies outside the map bounds {self.window}")
        in_tile = part.slices_in(tile_window)
        in_map = part.slices_in(self.window)
        rules.combine_tile(
            self.logodds[in_map],
            self.height_m[in_map],
            self.known[in_map],
            self.last_seen_s[in_map],
            self.occupancy[in_map],
            logodds_update[in_tile],
            tile_height_m[in_tile],
            count[in_tile],
            stamp_ns / 1e9,
            self.params.logodds_min,
            self.params.logodds_max,
        )
        self.stamp_ns = max(self.stamp_ns, stamp_ns)
        self.version += 1
        self.dirty = self.dirty.union(part)
        return part

    def decay(self, now_s: float, elapsed_s: float) -> int:
        """Cells unobserved for ``decay_after_s`` drift toward unknown; returns how many changed."""
        stale = self.known & (now_s - self.last_seen_s > self.params.decay_after_s)
        if not stale.any():
            return 0
        self.logodds[stale] *= np.float32(math.exp(-elapsed_s / self.params.decay_time_constant_s))
        forgotten = stale & (np.abs(self.logodds) < self.params.unknown_below)
        self.logodds[forgotten] = 0.0
        self.height_m[forgotten] = np.nan
        self.known[forgotten] = False
        changed = self._bounds_of(stale)
        box = changed.slices_in(self.window)
        self.occupancy[box] = occupancy_from_logodds(self.logodds[box], self.known[box])
        self.dirty = self.dirty.union(changed)
        self.version += 1
        return int(stale.sum())

    def _bounds_of(self, cells: npt.NDArray[np.bool_]) -> Window:
        """The lattice window bounding the true cells of a map-sized mask (at least one)."""
        rows, cols = np.nonzero(cells)
        return Window(
            self.window.i0 + int(cols.min()),
            self.window.j0 + int(rows.min()),
            int(cols.max() - cols.min()) + 1,
            int(rows.max() - rows.min()) + 1,
        )

    def set_predicted(self, swept: list[tuple[Window, npt.NDArray[np.bool_]]]) -> bool:
        """Replace the predicted layer by these swept cells (those outside the map are dropped);
        True if it changed. The cells it no longer covers show the frames' evidence again."""
        if not swept and not self.predicted_any:
            return False  # the usual case without movers: no pass over the whole map
        predicted = np.zeros(self.window.shape, np.bool_)
        for window, mask in swept:
            part = window.intersect(self.window)
            if not part.empty:
                predicted[part.slices_in(self.window)] |= mask[part.slices_in(window)]
        changed = predicted != self.predicted
        if not changed.any():
            return False
        self.dirty = self.dirty.union(self._bounds_of(changed))
        self.predicted = predicted
        self.predicted_any = bool(swept) and bool(predicted.any())
        self.version += 1
        return True

    def served_occupancy(self) -> npt.NDArray[np.int8]:
        """What clients read: the evidence, with the predicted layer's cells occupied."""
        return rules.occupied_where_predicted(self.occupancy, self.predicted)

    def take_dirty(self) -> Window:
        dirty, self.dirty = self.dirty, Window(0, 0, 0, 0)
        return dirty


def compile_rules() -> None:
    """Compile (or load from numba's cache) the combine kernel for the layouts real tiles bring —
    read-only decoded tile arrays into views of a larger map — so the first tile does not wait."""
    grid = FusedGrid(GridParams())
    window = Window(0, 0, 2, 2)

    def decoded(dtype: type[np.generic]) -> npt.NDArray[Any]:
        return np.frombuffer(bytes(4 * np.dtype(dtype).itemsize), dtype).reshape(window.shape)

    grid.integrate(window, decoded(np.float32), decoded(np.float32), decoded(np.uint16), 0)
