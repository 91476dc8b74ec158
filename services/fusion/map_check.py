"""The tracks checked against the map's occupied cells (DESIGN.md, Objects): a static track's
outline (the cells its footprint holds, its edge and rim), the connected occupied cells around a
footprint, and what the grid serves from them (contested, fringe)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.ndimage import label

from common.arrays import F64, Mask
from common.footprints import (
    Rectangle,
    corners,
    footprint_polygon,
    polygon_cells,
)
from common.lattice import Window
from services.fusion.seams import MapEvidence


class OccupiedCells(MapEvidence, Protocol):
    """The map's evidence as the tracker checks objects against it (``FusedGrid``)."""

    def agrees(self, window: Window, mask: Mask) -> bool: ...


@dataclass(frozen=True)
class Outline:
    """A static track's footprint on the lattice (:meth:`ObjectTracker.outlines`)."""

    window: Window
    cells: Mask
    """The cells whose centres the footprint holds."""
    edge: Mask
    """Those of them whose centres lie within half a cell inside its edge (all of them for a
    footprint under a cell across): the object's or the floor's by the footprint's error of a
    centimetre or more (the pallets' sides up to 3 cm, a piece joined from two pairs' views
    more), and the frames' belief tells the two no better. Fusion serves those the frames call
    free unknown, not occupied (docs/accuracy-journal.md, "An outline's edge the frames call
    free")."""
    rim: tuple[Window, Mask]
    """The cells whose centres the footprint grown by a margin (``fringe_margin_m``) holds and the
    footprint does not. A footprint is measured to a centimetre or so, so such a cell is the
    object's as often as not, and its pixels (a rim's top, side face and floor) decide it either
    way: with the band share neutral at ``SensorModelParams.edge_fraction`` (0.6), one whose
    centre the object holds may keep the free belief of the floor seen there before. Fusion
    serves these unknown where the frames do not call them occupied (the contested layer). (Empty
    for a round or low track, whose outline is grown by as much or more already.)"""

    @classmethod
    def of(
        cls,
        center_m: tuple[float, float],
        size_m: tuple[float, float],
        yaw_rad: float,
        round_: bool,
        resolution_m: float,
        rim_m: float = 0.0,
    ) -> Outline:
        """The outline of a footprint (``round_``: the circle inscribed in it), with a rim
        ``rim_m`` wide."""

        def cells_of(grown_m: float) -> tuple[Window, Mask]:
            size = (size_m[0] + 2 * grown_m, size_m[1] + 2 * grown_m)
            return polygon_cells(footprint_polygon(center_m, size, yaw_rad, round_), resolution_m)

        window, cells = cells_of(0.0)
        edge = cells.copy()
        if min(size_m) > resolution_m:  # a point's polygon would hold the cell it lies in
            subtract_cells([(window, edge)], cells_of(-resolution_m / 2))
        rim_window, rim = cells_of(rim_m) if rim_m > 0 else (window, np.zeros_like(cells))
        subtract_cells([(rim_window, rim)], (window, cells))
        return cls(window, cells, edge, (rim_window, rim))


def subtract_cells(cells: list[tuple[Window, Mask]], cut: tuple[Window, Mask]) -> None:
    """Clear ``cut``'s cells from each of ``cells`` (in place)."""
    cut_window, cut_mask = cut
    for window, mask in cells:
        both = window.intersect(cut_window)
        if not both.empty:
            mask[both.slices_in(window)] &= ~cut_mask[both.slices_in(cut_window)]


@dataclass(frozen=True)
class MapCheck:
    """What the map's cells say of the tracks (:meth:`ObjectTracker.check_against`)."""

    pieces: frozenset[int] = frozenset()
    """Ids of tracks the cells show larger than measured: their size is a lower bound."""
    enclosures: list[tuple[Window, Mask]] = field(default_factory=list)
    """Cells the static tracks' measured rims enclose, for the contested layer."""
    fringes: list[tuple[Window, Mask]] = field(default_factory=list)
    """Occupied cells just outside static tracks' footprints (a partial one's: with free floor
    beyond), for the fringe layer."""


@dataclass(frozen=True)
class ConnectedCells:
    """The map's occupied cells connected (8-neighbours) to occupied cells inside a footprint,
    within ``raster_reach_m`` of it: every frame of every pair that saw the object, to a cell."""

    window: Window
    connected: Mask
    occupied: Mask
    """Every occupied cell of the window, connected or not."""
    along_m: F64
    across_m: F64
    """Every cell's centre along the footprint's yaw and across it, from its centre."""
    footprint_cells: tuple[Window, Mask]
    """The cells whose centres the footprint holds (``polygon_cells``)."""
    round: bool = False
    """The footprint is the circle inscribed in its rectangle."""

    def outside_m(self, footprint: Rectangle) -> F64:
        """Every cell centre's distance outside the footprint (0 inside): the rectangle's, or for
        a round footprint the circle's (of the mean of length and width)."""
        _, _, length, width, _ = footprint
        if self.round:
            radius_m = (length + width) / 4
            return np.asarray(
                np.maximum(np.hypot(self.along_m, self.across_m) - radius_m, 0.0), np.float64
            )
        beyond_length = np.maximum(np.abs(self.along_m) - length / 2, 0.0)
        beyond_width = np.maximum(np.abs(self.across_m) - width / 2, 0.0)
        return np.asarray(np.hypot(beyond_length, beyond_width), np.float64)

    def overflow(self, footprint: Rectangle, margin_m: float) -> float:
        """The connected cells more than ``margin_m`` outside the footprint, counted against the
        cells inside it: a view that saw a piece of a top (a strip of a plain top, a corner a
        neighbour hides) measures it small while the cells show all of it."""
        outside = self.connected & (self.outside_m(footprint) > margin_m)
        return int(np.count_nonzero(outside)) / max(
            int(np.count_nonzero(self.footprint_cells[1])), 1
        )

    def fringe(
        self,
        footprint: Rectangle,
        margin_m: float,
        reach_m: float,
        free_beyond: Mask | None = None,
    ) -> tuple[Window, Mask]:
        """The occupied cells whose centres lie more than ``margin_m`` and at most ``reach_m``
        outside the footprint. A cell is the object's by its centre; the frames make one occupied
        by a share of its pixels, which its side faces (tens of points on one line) and a pixel
        or two of fattening reach from beside it, and the scatter of its faces' points a cell or
        two off its ring (connected to it or not). Given ``free_beyond`` (the cells the frames
        call free, over the window: for a footprint that is a lower bound), only the cells with
        free floor beyond them, outward through other such cells: where the object goes on past
        its footprint (a side cut by the image's border, the rest of it seen by another pair)
        the cells beyond are occupied or unknown, but for the ring's cells at that side's ends,
        which can reach free floor beside the part that goes on."""
        outside_m = self.outside_m(footprint)
        fringe = self.occupied & (outside_m > margin_m) & (outside_m <= reach_m)
        if free_beyond is not None:
            fringe &= _open_outward(free_beyond, fringe, outside_m)
        return self.window, fringe

    def enclosure(self, footprint: Rectangle, resolution_m: float) -> tuple[Window, Mask]:
        """The cells of the rectangle, along the footprint's yaw, through the footprint and the
        outermost connected cells."""
        x, y, length, width, yaw = footprint
        along, across = self.along_m[self.connected], self.across_m[self.connected]
        a0, a1 = min(float(along.min()), -length / 2), max(float(along.max()), length / 2)
        b0, b1 = min(float(across.min()), -width / 2), max(float(across.max()), width / 2)
        c, s = math.cos(yaw), math.sin(yaw)
        middle_along, middle_across = (a0 + a1) / 2, (b0 + b1) / 2
        center = (
            x + middle_along * c - middle_across * s,
            y + middle_along * s + middle_across * c,
        )
        return polygon_cells(corners(center, (a1 - a0, b1 - b0), yaw), resolution_m)


def _open_outward(free: Mask, candidates: Mask, outside_m: F64) -> Mask:
    """The ``candidates`` from which a chain of candidates, each farther out (``outside_m``) than
    the one before and 8-connected to it, reaches a ``free`` cell."""
    rows, cols = free.shape
    padded_out = np.pad(outside_m, 1, constant_values=-np.inf)
    offsets = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    farther = [
        padded_out[1 + dy : 1 + dy + rows, 1 + dx : 1 + dx + cols] > outside_m for dy, dx in offsets
    ]
    reached, open_ = free.copy(), np.zeros_like(free)
    while True:
        padded = np.pad(reached, 1)
        step = np.zeros_like(free)
        for (dy, dx), out in zip(offsets, farther, strict=True):
            step |= padded[1 + dy : 1 + dy + rows, 1 + dx : 1 + dx + cols] & out
        grown = candidates & ~open_ & step
        if not grown.any():
            return open_
        open_ |= grown
        reached |= grown


def connected_cells(
    cells: OccupiedCells,
    footprint: Rectangle,
    max_size_m: float,
    reach_m: float,
    round_: bool = False,
) -> ConnectedCells | None:
    """:class:`ConnectedCells` of a footprint (``round_``: the circle inscribed in it), labelled
    on its reach alone (the cost follows the object, not the map); None where none of its cells
    is occupied, or it is longer than ``max_size_m`` (a broken detection); the cells looked at
    lie within ``reach_m`` of its outline (``TrackerConfig.raster_reach_m``)."""
    x, y, length, width, yaw = footprint
    if max(length, width) > max_size_m:
        return None
    resolution_m = cells.resolution_m
    outline = footprint_polygon((x, y), (length, width), yaw, round_)
    inner_window, inner = polygon_cells(outline, resolution_m)
    reach = reach_m
    (x0, y0), (x1, y1) = outline.min(axis=0) - reach, outline.max(axis=0) + reach
    window = Window.covering(float(x0), float(y0), float(x1), float(y1), resolution_m)
    occupied = cells.occupied_in(window)
    labels, _ = label(occupied, structure=np.ones((3, 3), np.int8))
    part = inner_window.intersect(window)
    touched = labels[part.slices_in(window)][inner[part.slices_in(inner_window)]]
    touched = np.unique(touched[touched > 0])
    if touched.size == 0:
        return None
    x_m, y_m = window.cell_centers(resolution_m)
    c, s = math.cos(yaw), math.sin(yaw)
    return ConnectedCells(
        window=window,
        connected=np.isin(labels, touched),
        occupied=occupied,
        along_m=(x_m - x) * c + (y_m - y) * s,
        across_m=(y_m - y) * c - (x_m - x) * s,
        footprint_cells=(inner_window, inner),
        round=round_,
    )
