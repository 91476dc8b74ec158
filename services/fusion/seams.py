"""Pieces of one object that a seam's blind gap keeps apart.

Two pairs' views overlap on the floor but shrink toward the ceiling, so a tall object at a seam
can have part of its top in neither view: each pair sees a piece cut by its image's border, with
a gap between the pieces that no pair saw. Two objects side by side at a seam leave floor between
them that some camera sees free; one object leaves none. So two cut pieces of different pairs in
one capture, as high as each other, whose gap holds (almost) no free cell of the map's evidence,
are one object (:func:`one_object_across`).

Pure numpy: the map's evidence comes in as an :class:`services.fusion.objects.OccupiedCells`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from common.footprints import convex_hull, polygon_cells, polygons_overlap
from common.lattice import Window

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


class FreeCells(Protocol):
    """The map's free evidence, as the seam test reads it (``FusedGrid``)."""

    @property
    def resolution_m(self) -> float: ...

    def free_in(self, window: Window) -> Mask: ...


@dataclass(frozen=True)
class SeamConfig:
    reach_m: float = 1.5
    """The widest gap joined. Offline (20 s), the gaps of tall objects at the default rig's seams:
    a 0.68 m box 0.3 m (``--seed 2``), a 1.6 m shelf 1.2 m (``--seed 4 --floor plain``)."""
    top_share: float = 0.15
    top_min_m: float = 0.15
    """The pieces' tops differ by at most this share of the higher, or ``top_min_m``: a piece's
    top is where its points end, a few centimetres either way."""
    free_share: float = 0.2
    """At most this share of the gap's cells may read free (the map's evidence): floor seen past
    a piece's aslant cut or noisy rim (a 0.68 m box: 13 of 114 cells; the gaps between distinct
    objects on the same scenes, 40–80 %)."""
    max_length_m: float = 3.0
    """The longest object joined (a rack, a truck): a wall's pieces, one per pair along it, stay
    pieces, each outlined (joined, ``--seed 1 --pairs 6``'s 12 m walls were served 18 % unknown
    instead of 2 %)."""


@dataclass(frozen=True)
class Piece:
    """What one pair saw of an object's top: a convex polygon (N, 2) and the top's height."""

    polygon_m: F64
    top_m: float


def gap_cells(a_m: F64, b_m: F64, resolution_m: float) -> tuple[Window, Mask]:
    """The cells between two convex polygons: their hull's cells less their own."""
    window, between = polygon_cells(convex_hull(np.vstack([a_m, b_m])), resolution_m)
    for polygon in (a_m, b_m):
        own_window, own = polygon_cells(polygon, resolution_m)
        part = own_window.intersect(window)
        if not part.empty:
            between[part.slices_in(window)] &= ~own[part.slices_in(own_window)]
    return window, between


def one_object_across(a: Piece, b: Piece, cells: FreeCells, config: SeamConfig) -> bool:
    """Whether two cut pieces of different pairs' views are one object across a seam's gap:
    within ``reach_m`` of each other, as high, no longer together than ``max_length_m``, and
    nothing between them seen free."""
    higher = max(a.top_m, b.top_m)
    if abs(a.top_m - b.top_m) > max(config.top_min_m, config.top_share * higher):
        return False
    if not polygons_overlap(a.polygon_m, b.polygon_m, config.reach_m):
        return False
    hull = np.vstack([a.polygon_m, b.polygon_m])
    if float(np.ptp(hull, axis=0).max()) > config.max_length_m:
        return False
    window, between = gap_cells(a.polygon_m, b.polygon_m, cells.resolution_m)
    gap = int(np.count_nonzero(between))
    free = int(np.count_nonzero(cells.free_in(window) & between))
    return free <= config.free_share * gap
