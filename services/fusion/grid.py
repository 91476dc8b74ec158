"""The fused map: named layers (clamped log-odds, top heights, observation times, …) on the global
lattice, stored in fixed square chunks (nvblox's blocks, grid_map's layers).

Why chunks: snapshots, ``map/updates``, decay and saves then visit the chunks that changed, so their
cost follows the change, not the map's size; and memory follows the area observed (a tile far away
costs one chunk, not a map grown to reach it). Pure numpy: no Zenoh, no threads. One thread of the
service owns a :class:`FusedGrid`; everyone else reads :class:`FrozenMap` copies.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from itertools import pairwise
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from common.lattice import Window
from common.mapfiles import OCCUPIED_MIN, free_cells
from common.occupancy_map import UNKNOWN, occupancy_from_logodds
from services.fusion import rules
from services.fusion.params import GridParams as GridParams  # declared there, with its settings

CHUNK_CELLS = 64
"""Side of a chunk in cells: 64×64 is nvblox's order of block size; a 5000×5000 map is 6,200 of
them, and a tile of a few hundred cells a side touches a few dozen."""
LAYER_FILLS: tuple[tuple[str, type[np.generic], float | bool], ...] = (
    ("logodds", np.float32, 0.0),
    ("height_m", np.float32, np.nan),
    ("known", np.bool_, False),
    ("last_seen_s", np.float64, 0.0),
    ("occupancy", np.int8, UNKNOWN),
    ("predicted", np.bool_, False),
    ("contested", np.bool_, False),
    ("fringe", np.bool_, False),
)
"""Every layer, its dtype and the value of a cell never observed."""
EVIDENCE_LAYERS = ("logodds", "height_m", "known", "last_seen_s")
"""What a frame measured: the layers saved (occupancy follows from them; predictions are a guess)."""
LAYER_FILL = {name: fill for name, _, fill in LAYER_FILLS}

OUTLINE_OCCUPIED_SHARE = 0.75
"""An object's footprint is served occupied only where the frames call this share of its known
cells occupied: offline, ``--seed 2``, every real object's footprint measured 0.91–0.99, a lane
line tracked as a static object 0.36 (its outline painted 154 false obstacles). Below it, the
footprint is *contested*: its cells the frames do not call occupied are served unknown."""

CellMasks = list[tuple[Window, npt.NDArray[np.bool_]]]
"""Cells on the lattice: a window each, and a mask of the cells meant in it."""
ChunkKey = tuple[int, int]
"""(ci, cj): the chunk holding cells i ∈ [ci·64, ci·64+64), j ∈ [cj·64, cj·64+64)."""


MAX_UPDATE_PARTS = 8
"""Most ``map/updates`` messages one publish sends: changed chunks far apart go as separate
rectangles (two small tiles at opposite corners of a large map are two small messages, not their
bounding box), and beyond this many groups neighbouring groups are merged."""


class TileLayers(Protocol):
    """A tile's layers on its window (``services.depth.inverse_model.Tile``, or one fusion has
    admitted): what :meth:`FusedGrid.integrate_tile` takes."""

    @property
    def window(self) -> Window: ...
    @property
    def logodds(self) -> npt.NDArray[np.float32]: ...
    @property
    def height_m(self) -> npt.NDArray[np.float32]: ...
    @property
    def count(self) -> npt.NDArray[np.uint16]: ...
    @property
    def hidden(self) -> npt.NDArray[np.bool_] | None: ...


class TileOutsideMap(ValueError):
    """A tile the map cannot take: ``reason`` is ``outside_map`` (beyond fixed bounds),
    ``outside_extent`` (beyond the site's extent around the origin) or ``growth`` (it would grow
    the map past the cell limit)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def chunk_window(key: ChunkKey) -> Window:
    return Window(key[0] * CHUNK_CELLS, key[1] * CHUNK_CELLS, CHUNK_CELLS, CHUNK_CELLS)


def chunk_keys(window: Window) -> Iterator[ChunkKey]:
    """Keys of the chunks a window overlaps."""
    if window.empty:
        return
    c = CHUNK_CELLS
    for cj in range(window.j0 // c, (window.j1 - 1) // c + 1):
        for ci in range(window.i0 // c, (window.i1 - 1) // c + 1):
            yield (ci, cj)


def chunk_aligned(window: Window) -> Window:
    """The smallest window of whole chunks covering ``window``. Integer arithmetic: a float
    division rounds cell 2**62 + 1 to 2**62 and made that 1×1 window a 0×0 one."""
    c = CHUNK_CELLS
    i0, j0 = window.i0 // c * c, window.j0 // c * c
    i1, j1 = -(-window.i1 // c) * c, -(-window.j1 // c) * c
    return Window(i0, j0, i1 - i0, j1 - j0)


def update_parts(dirty: Mapping[ChunkKey, Window], limit: int = MAX_UPDATE_PARTS) -> list[Window]:
    """Rectangles covering the changed cells ``dirty`` (per chunk), each to be one ``map/updates``
    message: runs of adjacent changed chunks along a chunk row, stacked while the next row has the
    same run (a tile's chunks make one rectangle), each cut down to the cells that changed in it.
    More than ``limit`` of them are merged by quadtree cells of doubling size, so the count stays
    bounded and what is merged lies close. Rectangles may overlap: every one carries the cells'
    values of the same version, so overlap costs bytes, never correctness."""
    if limit < 4:
        raise ValueError("at least 4 parts: the coarsest quadtree level has 4 cells")
    rows: dict[int, list[int]] = {}
    for ci, cj in dirty:
        rows.setdefault(cj, []).append(ci)
    blocks: list[list[int]] = []
    """[ci0, ci1, cj0, cj1) in chunks."""
    above: dict[tuple[int, int], int] = {}
    for cj in sorted(rows):
        cis = sorted(rows[cj])
        runs, start = [], cis[0]
        for previous, ci in pairwise(cis):
            if ci != previous + 1:
                runs.append((start, previous + 1))
                start = ci
        runs.append((start, cis[-1] + 1))
        here = {}
        for run in runs:
            k = above.get(run)
            if k is None or blocks[k][3] != cj:
                k = len(blocks)
                blocks.append([run[0], run[1], cj, cj])
            blocks[k][3] = cj + 1
            here[run] = k
        above = here
    parts: list[tuple[int, int, Window]] = []
    for ci0, ci1, cj0, cj1 in blocks:
        cells = Window(0, 0, 0, 0)
        for cj in range(cj0, cj1):
            for ci in range(ci0, ci1):
                cells = cells.union(dirty[(ci, cj)])
        parts.append((ci0, cj0, cells))
    scale = 1
    while len(parts) > limit:
        scale *= 2
        merged: dict[tuple[int, int], Window] = {}
        for ci, cj, cells in parts:
            cell = (ci // scale * scale, cj // scale * scale)
            merged[cell] = merged.get(cell, Window(0, 0, 0, 0)).union(cells)
        parts = [(ci, cj, cells) for (ci, cj), cells in merged.items()]
    return [cells for _, _, cells in parts if not cells.empty]


class Chunk:
    """One chunk's layers, each a CHUNK_CELLS² array ([row, col] = [j - j0, i - i0])."""

    __slots__ = (*(name for name, _, _ in LAYER_FILLS), "decay_check_s", "shared")
    logodds: npt.NDArray[np.float32]
    height_m: npt.NDArray[np.float32]
    known: npt.NDArray[np.bool_]
    last_seen_s: npt.NDArray[np.float64]
    occupancy: npt.NDArray[np.int8]
    predicted: npt.NDArray[np.bool_]
    contested: npt.NDArray[np.bool_]
    fringe: npt.NDArray[np.bool_]
    decay_check_s: float
    """Observation time of its oldest known cell (or earlier): decay looks here only once that is
    ``decay_after_s`` old, so a pass costs the chunks that may be stale, not the whole map."""
    shared: bool
    """A :class:`FrozenMap` holds these arrays: copy before writing (copy-on-write)."""

    def __init__(self, layers: Mapping[str, npt.NDArray[Any]] | None = None) -> None:
        shape = (CHUNK_CELLS, CHUNK_CELLS)
        for name, dtype, fill in LAYER_FILLS:
            given = None if layers is None else layers.get(name)
            setattr(self, name, np.full(shape, fill, dtype) if given is None else given)
        known_seen = self.last_seen_s[self.known]
        self.decay_check_s = float(known_seen.min()) if known_seen.size else math.inf
        self.shared = False

    def copy(self) -> Chunk:
        chunk = Chunk({name: getattr(self, name).copy() for name, _, _ in LAYER_FILLS})
        chunk.decay_check_s = self.decay_check_s
        return chunk

    def forget(self, cells: npt.NDArray[np.bool_]) -> None:
        """These cells back to never observed (unknown)."""
        self.logodds[cells] = 0.0
        self.height_m[cells] = np.nan
        self.known[cells] = False
        self.occupancy[cells] = UNKNOWN

    def served(self) -> npt.NDArray[np.int8]:
        """What clients read: the evidence, with the fringe layer's cells and the contested layer's
        not called occupied unknown, and the predicted layer's occupied."""
        occupancy = self.occupancy
        if self.fringe.any():
            occupancy = rules.unknown_where_fringe(occupancy, self.fringe)
        if self.contested.any():
            occupancy = rules.unknown_where_contested(occupancy, self.contested)
        return rules.occupied_where_predicted(occupancy, self.predicted)


@dataclass(frozen=True)
class FrozenChunk:
    """A read-only copy of a chunk, shared by every snapshot until the chunk changes again."""

    layers: Mapping[str, npt.NDArray[Any]]
    served: npt.NDArray[np.int8]
    known_cells: int

    @staticmethod
    def of(chunk: Chunk) -> FrozenChunk:
        """Shares the chunk's arrays (read-only views); the grid copies the chunk before its next
        write, so memory is the map's once plus the chunks changed since."""
        layers = {name: getattr(chunk, name).view() for name, _, _ in LAYER_FILLS}
        served = chunk.served()
        for array in (*layers.values(), served):
            array.setflags(write=False)
        chunk.shared = True
        return FrozenChunk(MappingProxyType(layers), served, int(layers["known"].sum()))


@dataclass(frozen=True)
class FrozenMap:
    """The map at one version, immutable: queries and the state writer read it from their own
    threads while the owner goes on changing the grid. Copy-on-write: a new one takes the chunks
    changed since the last and shares the rest; a chunk is copied when the grid next writes it."""

    epoch_ns: int
    version: int
    stamp_ns: int
    resolution_m: float
    window: Window
    chunks: Mapping[ChunkKey, FrozenChunk]

    @property
    def key(self) -> tuple[int, int]:
        """(epoch, version): compared in that order, it never goes backwards."""
        return (self.epoch_ns, self.version)

    def layer(self, name: str) -> npt.NDArray[Any]:
        """One layer over the whole window (``served`` for the occupancy clients read)."""
        if name == "served":
            return self.assemble(lambda chunk: chunk.served, np.int8, UNKNOWN)
        dtype = next(d for n, d, _ in LAYER_FILLS if n == name)
        return self.assemble(lambda chunk: chunk.layers[name], dtype, LAYER_FILL[name])

    def assemble(self, pick: Any, dtype: type[np.generic], fill: float | bool) -> npt.NDArray[Any]:
        out = np.full(self.window.shape, fill, dtype)
        for key, chunk in self.chunks.items():
            _paste(out, self.window, pick(chunk), key)
        return out

    def known_cells(self) -> int:
        return sum(chunk.known_cells for chunk in self.chunks.values())


class ServedAssembler:
    """The served occupancy of whole frozen maps, kept in one array and brought up to date by
    pasting only the chunks that differ from the last map it saw (copy-on-write keeps unchanged
    chunks the same objects): a snapshot of a large map costs its changes and one copy."""

    def __init__(self) -> None:
        self._served: npt.NDArray[np.int8] | None = None
        self._from: FrozenMap | None = None

    def occupancy(self, frozen: FrozenMap) -> npt.NDArray[np.int8]:
        last = self._from
        if self._served is None or last is None or last.window != frozen.window:
            self._served = frozen.layer("served")
        else:
            for key, chunk in frozen.chunks.items():
                if last.chunks.get(key) is not chunk:
                    _paste(self._served, frozen.window, chunk.served, key)
        self._from = frozen
        return self._served.copy()


def _paste(out: npt.NDArray[Any], window: Window, array: npt.NDArray[Any], key: ChunkKey) -> None:
    """Copy a chunk's array into ``out`` (covering ``window``) where they overlap."""
    cw = chunk_window(key)
    part = cw.intersect(window)
    if not part.empty:
        out[part.slices_in(window)] = array[part.slices_in(cw)]


class FusedGrid:
    def __init__(self, params: GridParams, epoch_ns: int = 0) -> None:
        self.params = params
        self.window = params.bounds or Window(0, 0, 0, 0)
        """The map's extent: the fixed bounds, or the chunks observed so far."""
        self.chunks: dict[ChunkKey, Chunk] = {}
        self.epoch_ns = epoch_ns
        self.version = 0
        """Change counter within the epoch; restored from the saved state at start."""
        self.stamp_ns = 0
        self.dirty: dict[ChunkKey, Window] = {}
        """Cells changed since they were last taken (the next ``map/updates``), per chunk."""
        self.changed: set[ChunkKey] = set()
        """Chunks changed since the last :meth:`freeze`."""
        self._marked: dict[str, set[ChunkKey]] = {
            "predicted": set(),
            "contested": set(),
            "fringe": set(),
        }
        """Per mask layer, the chunks where it holds cells."""
        self._frozen = FrozenMap(epoch_ns, 0, 0, params.resolution_m, self.window, {})

    def _admit(self, tile_window: Window) -> Window:
        """The part of a tile the map takes: what lies in the fixed bounds, or within the site's
        extent; grows the window (chunk-aligned) within the cell limit."""
        bounds = self.params.bounds
        site = self.params.site_window()
        part = tile_window.intersect(site)
        if part.empty:
            if bounds is not None:
                raise TileOutsideMap(
                    "outside_map", f"tile {tile_window} lies outside the map bounds {bounds}"
                )
            raise TileOutsideMap(
                "outside_extent",
                f"tile {tile_window} lies beyond the site extent {site} "
                f"(±{self.params.max_extent_m:g} m around the origin, --max-extent-m)",
            )
        if bounds is not None:
            return part
        target = chunk_aligned(self.window.union(part))
        if target.cols * target.rows > self.params.max_cells:
            raise TileOutsideMap(
                "growth",
                f"covering {tile_window} needs a map of {target.cols}×{target.rows} cells, "
                f"over the limit of {self.params.max_cells}",
            )
        self.window = target
        return part

    def integrate(
        self,
        tile_window: Window,
        logodds_update: npt.NDArray[np.float32],
        tile_height_m: npt.NDArray[np.float32],
        count: npt.NDArray[np.uint16],
        stamp_ns: int,
        hidden: npt.NDArray[np.bool_] | None = None,
    ) -> Window:
        """Add one tile's evidence; returns the map cells it touched. A refused tile changes
        nothing (no chunk, no growth). ``hidden``: cells without an update whose floor is hidden
        now (see ``rules.combine_tile``). A tile of no cell (a frame that measured nothing: a
        camera gone dark) touches none."""
        if tile_window.empty:
            return tile_window
        part = self._admit(tile_window)
        stamp_s = stamp_ns / 1e9
        if hidden is None:
            hidden = np.zeros(tile_window.shape, np.bool_)
            hidden.flags.writeable = False  # the layout compile_rules warms the kernel for
        for key in chunk_keys(part):
            cw = chunk_window(key)
            sub = part.intersect(cw)
            in_tile, in_chunk = sub.slices_in(tile_window), sub.slices_in(cw)
            chunk = self._writable(key)
            rules.combine_tile(
                chunk.logodds[in_chunk],
                chunk.height_m[in_chunk],
                chunk.known[in_chunk],
                chunk.last_seen_s[in_chunk],
                chunk.occupancy[in_chunk],
                logodds_update[in_tile],
                tile_height_m[in_tile],
                count[in_tile],
                hidden[in_tile],
                stamp_s,
                self.params.logodds_min,
                self.params.logodds_max,
                self.params.hidden_grace_s,
            )
            chunk.decay_check_s = min(chunk.decay_check_s, stamp_s)
            self.changed.add(key)
            self._mark(key, sub)
        self.stamp_ns = max(self.stamp_ns, stamp_ns)
        self.version += 1
        return part

    def integrate_tile(self, tile: TileLayers, stamp_ns: int) -> Window:
        """:meth:`integrate` of a tile's layers (a depth pipeline's tile, or one fusion admitted)."""
        return self.integrate(
            tile.window, tile.logodds, tile.height_m, tile.count, stamp_ns, tile.hidden
        )

    def _mark(self, key: ChunkKey, cells: Window) -> None:
        self.dirty[key] = self.dirty.get(key, Window(0, 0, 0, 0)).union(cells)

    def decay(self, now_s: float, elapsed_s: float) -> int:
        """Cells unobserved for ``decay_after_s`` drift toward unknown; returns how many changed.
        Visits only chunks whose oldest known cell is that old."""
        p = self.params
        factor = np.float32(math.exp(-elapsed_s / p.decay_time_constant_s))
        changed = 0
        for key, chunk in self.chunks.items():
            if now_s - chunk.decay_check_s <= p.decay_after_s:
                continue
            stale = chunk.known & (now_s - chunk.last_seen_s > p.decay_after_s)
            count = int(stale.sum())
            if count:
                chunk = self._writable(key)
                chunk.logodds[stale] *= factor
                chunk.occupancy[stale] = occupancy_from_logodds(
                    chunk.logodds[stale], chunk.known[stale]
                )
                chunk.forget(stale & (np.abs(chunk.logodds) < p.unknown_below))
                self.changed.add(key)
                self._mark(key, chunk_window(key).intersect(self.window))
                changed += count
            known_seen = chunk.last_seen_s[chunk.known]
            chunk.decay_check_s = float(known_seen.min()) if known_seen.size else math.inf
        if changed:
            self.version += 1
        return changed

    def shift_time(self, step_s: float) -> None:
        """Every time the map holds moved by ``step_s`` (the newest capture's stamp and each
        cell's last observation): after a clock stepped back, the map's times are those of a
        clock that no longer runs, and nothing would decay until it caught up (an hour, after an
        hour's correction)."""
        for key in list(self.chunks):
            chunk = self._writable(key)
            chunk.last_seen_s[chunk.known] += step_s
            chunk.decay_check_s += step_s
            self.changed.add(key)
        self.stamp_ns = max(0, self.stamp_ns + round(step_s * 1e9))
        self.version += 1

    def forget_occupied(self, cells: CellMasks, seen_before_s: float) -> int:
        """Occupied cells among ``cells`` last observed before ``seen_before_s`` become unknown;
        returns how many. A mover's wake: what put them there has gone, and no frame since has
        shown them (a floor cell with too few pixels of its own keeps a hit for seconds)."""
        forgotten = 0
        for key, mask in self._chunk_masks(cells).items():
            chunk = self.chunks.get(key)
            if chunk is None:
                continue
            stale = mask & chunk.known & (chunk.logodds > 0.0) & (chunk.last_seen_s < seen_before_s)
            count = int(np.count_nonzero(stale))
            if not count:
                continue
            self._writable(key).forget(stale)
            self.changed.add(key)
            self._mark(key, chunk_window(key).intersect(self.window))
            forgotten += count
        if forgotten:
            self.version += 1
        return forgotten

    def _chunk_masks(self, cells: CellMasks) -> dict[ChunkKey, npt.NDArray[np.bool_]]:
        """``cells`` (masks on windows) as one mask per chunk they touch; cells outside the map
        are dropped."""
        masks: dict[ChunkKey, npt.NDArray[np.bool_]] = {}
        for window, mask in cells:
            part = window.intersect(self.window)
            for key in chunk_keys(part):
                cw = chunk_window(key)
                sub = part.intersect(cw)
                target = masks.setdefault(key, np.zeros((CHUNK_CELLS, CHUNK_CELLS), np.bool_))
                target[sub.slices_in(cw)] |= mask[sub.slices_in(window)]
        return masks

    def set_predicted(self, cells: CellMasks) -> bool:
        """Replace the predicted layer by these cells (static outlines, movers' tops, swept paths;
        those outside the map are dropped); True if it changed. The cells it no longer covers show
        the frames' evidence again."""
        return self._set_mask_layer("predicted", cells)

    def set_contested(self, footprints: CellMasks) -> bool:
        """Replace the contested layer by these cells: static objects' footprints the frames'
        evidence does not agree with (see :meth:`agrees`) and, of those it agrees with, the edge
        cells it calls free, their rims, the movers' footprints; True if it changed."""
        return self._set_mask_layer("contested", footprints)

    def set_fringe(self, fringes: CellMasks) -> bool:
        """Replace the fringe layer by these cells: just outside static objects' measured footprints
        (``ObjectTracker.check_against``); True if it changed."""
        return self._set_mask_layer("fringe", fringes)

    def _set_mask_layer(self, name: str, cells: CellMasks) -> bool:
        marked = self._marked[name]
        if not cells and not marked:
            return False  # the usual case: nothing to visit
        masks = self._chunk_masks(cells)
        changed = False
        for key in marked | set(masks):
            new = masks.get(key)
            if new is None:
                new = np.zeros((CHUNK_CELLS, CHUNK_CELLS), np.bool_)
            chunk = self.chunks.get(key)
            old = None if chunk is None else getattr(chunk, name)
            unchanged = not new.any() if old is None else np.array_equal(new, old)
            if unchanged:
                continue
            setattr(self._writable(key), name, new)
            self.changed.add(key)
            self._mark(key, chunk_window(key).intersect(self.window))
            changed = True
        self._marked[name] = {key for key, mask in masks.items() if mask.any()}
        if changed:
            self.version += 1
        return changed

    def agrees(self, window: Window, mask: npt.NDArray[np.bool_]) -> bool:
        """Whether the frames' evidence calls OUTLINE_OCCUPIED_SHARE or more of the known cells of
        an object's footprint (``mask`` on ``window``) occupied."""
        occupancy = self.window_of("occupancy", window)
        known = mask & (occupancy != UNKNOWN)
        total = int(np.count_nonzero(known))
        occupied = int(np.count_nonzero(known & (occupancy >= OCCUPIED_MIN)))
        return total > 0 and occupied >= OUTLINE_OCCUPIED_SHARE * total

    def _writable(self, key: ChunkKey) -> Chunk:
        """The chunk to write into: created when new, copied when a frozen map shares it."""
        chunk = self.chunks.get(key)
        if chunk is None:
            chunk = self.chunks[key] = Chunk()
        elif chunk.shared:
            chunk = self.chunks[key] = chunk.copy()
        return chunk

    def window_of(self, name: str, window: Window) -> npt.NDArray[Any]:
        """One layer (``served``: the occupancy clients read) over a window of the map, from the
        chunks it overlaps only."""
        dtype = np.int8 if name == "served" else next(d for n, d, _ in LAYER_FILLS if n == name)
        fill = UNKNOWN if name == "served" else LAYER_FILL[name]
        out = np.full(window.shape, fill, dtype)
        for key in chunk_keys(window):
            chunk = self.chunks.get(key)
            if chunk is not None:
                _paste(
                    out, window, chunk.served() if name == "served" else getattr(chunk, name), key
                )
        return out

    @property
    def resolution_m(self) -> float:
        return self.params.resolution_m

    def occupied_in(self, window: Window) -> npt.NDArray[np.bool_]:
        """Cells the frames' evidence calls occupied (not the served layers), over a window."""
        occupied: npt.NDArray[np.bool_] = self.window_of("occupancy", window) >= OCCUPIED_MIN
        return occupied

    def free_in(self, window: Window) -> npt.NDArray[np.bool_]:
        """Cells the frames' evidence calls free (not the served layers), over a window."""
        return free_cells(self.window_of("occupancy", window))

    def unknown_in(self, window: Window) -> npt.NDArray[np.bool_]:
        """Cells no frame has measured (or whose measurement was forgotten), over a window."""
        unknown: npt.NDArray[np.bool_] = self.window_of("occupancy", window) == UNKNOWN
        return unknown

    def layer(self, name: str) -> npt.NDArray[Any]:
        """One layer over the whole map (a copy: for tools and tests; the service uses snapshots)."""
        return self.window_of(name, self.window)

    def served_occupancy(self) -> npt.NDArray[np.int8]:
        """What clients read (:meth:`Chunk.served`)."""
        return self.layer("served")

    def take_dirty_parts(self) -> dict[ChunkKey, Window]:
        """The cells changed since last taken, per chunk (see :func:`update_parts`)."""
        dirty, self.dirty = self.dirty, {}
        return dirty

    def freeze(self) -> tuple[FrozenMap, set[ChunkKey]]:
        """An immutable copy of the map now, and the chunks changed since the last one; costs
        those chunks only."""
        changed, self.changed = self.changed, set()
        chunks = dict(self._frozen.chunks)
        for key in changed:
            chunks[key] = FrozenChunk.of(self.chunks[key])
        self._frozen = FrozenMap(
            self.epoch_ns,
            self.version,
            self.stamp_ns,
            self.params.resolution_m,
            self.window,
            MappingProxyType(chunks),
        )
        return self._frozen, changed

    def restore(self, chunks: Mapping[ChunkKey, Mapping[str, npt.NDArray[Any]]]) -> int:
        """Put saved evidence layers back; returns how many chunks were left out. Left out: cells
        outside the fixed bounds or the site's extent (a state saved before the limit, or under
        other settings); and, when what remains needs a map over ``max_cells``, the chunks
        farthest from the median chunk (the bulk of the map: a stray far chunk goes, the site
        stays). Never the whole state for a few bad chunks."""
        site = self.params.site_window()
        keys = sorted(k for k in chunks if not chunk_window(k).intersect(site).empty)
        if self.params.bounds is None and keys:
            keys = _within_cell_limit(keys, self.params.max_cells)
            window = Window(0, 0, 0, 0)
            for key in keys:
                window = window.union(chunk_window(key))
            self.window = chunk_aligned(window)
        for key in keys:
            # The evidence only: the mask layers are rebuilt from the tracks (a frozen snapshot's
            # would come back read-only, and unrecorded in ``_marked``).
            layers = {name: chunks[key][name] for name in EVIDENCE_LAYERS if name in chunks[key]}
            cw = chunk_window(key)
            if not site.contains(cw):  # cells beyond the site are not part of this map
                inside = np.zeros((CHUNK_CELLS, CHUNK_CELLS), np.bool_)
                inside[cw.intersect(site).slices_in(cw)] = True
                layers["known"] = layers["known"] & inside
            known = layers["known"]
            layers["logodds"] = np.where(known, layers["logodds"], np.float32(0.0))
            layers["occupancy"] = occupancy_from_logodds(layers["logodds"], known)
            self.chunks[key] = Chunk(layers)
            self.changed.add(key)
        return len(chunks) - len(keys)


def _within_cell_limit(keys: list[ChunkKey], max_cells: int) -> list[ChunkKey]:
    """The chunks kept when their map must not exceed ``max_cells``: nearest the median first
    (Chebyshev distance in chunks), each kept if the map still fits."""
    ci_median = sorted(k[0] for k in keys)[len(keys) // 2]
    cj_median = sorted(k[1] for k in keys)[len(keys) // 2]
    kept: list[ChunkKey] = []
    window = Window(0, 0, 0, 0)
    for key in sorted(keys, key=lambda k: (max(abs(k[0] - ci_median), abs(k[1] - cj_median)), k)):
        grown = window.union(chunk_window(key))
        if grown.cols * grown.rows <= max_cells:
            kept.append(key)
            window = grown
    return sorted(kept)


def compile_rules() -> None:
    """Compile (or load from numba's cache) the combine kernel for the layouts real tiles bring —
    read-only decoded tile arrays into views of a chunk — so the first tile does not wait."""
    grid = FusedGrid(GridParams())
    window = Window(0, 0, 2, 2)

    def decoded(dtype: type[np.generic]) -> npt.NDArray[Any]:
        return np.frombuffer(bytes(4 * np.dtype(dtype).itemsize), dtype).reshape(window.shape)

    grid.integrate(
        window,
        decoded(np.float32),
        decoded(np.float32),
        decoded(np.uint16),
        0,
        decoded(np.uint8).view(np.bool_),
    )
