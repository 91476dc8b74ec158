"""The one global lattice of DESIGN.md: cell (i, j) covers x ∈ [i·r, (i+1)·r), y ∈ [j·r, (j+1)·r).

Arrays over the lattice are indexed ``[row, col] = [j - j0, i - i0]`` (rows along y, columns along
x), as nav_msgs/OccupancyGrid stores them: row-major from the origin cell. Stitching tiles is exact
integer arithmetic on windows; nothing is resampled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

# Guards floor() against x = i·r landing a hair below the edge in floating point.
_EDGE_EPS = 1e-9


MIN_RESOLUTION_M = 0.005
"""Finer cells than 5 mm are below what overhead cameras resolve (about 1 cm a pixel), and integer
cell indices of a site would overflow long before the resolution reaches 1e-300."""
MAX_RESOLUTION_M = 1.0


def check_resolution(resolution_m: float) -> float:
    if not (math.isfinite(resolution_m) and MIN_RESOLUTION_M <= resolution_m <= MAX_RESOLUTION_M):
        raise ValueError(
            f"lattice resolution must be {MIN_RESOLUTION_M}–{MAX_RESOLUTION_M} m, got {resolution_m}"
        )
    return float(resolution_m)


def cell_of(xy_world: npt.ArrayLike, resolution_m: float) -> npt.NDArray[np.int64]:
    """Integer (i, j) of the cells holding world points (..., 2)."""
    xy = np.asarray(xy_world, dtype=np.float64)
    return np.floor(xy / resolution_m + _EDGE_EPS).astype(np.int64)


def cell_center(ij_cell: npt.ArrayLike, resolution_m: float) -> npt.NDArray[np.float64]:
    return (np.asarray(ij_cell, dtype=np.float64) + 0.5) * resolution_m


@dataclass(frozen=True)
class Window:
    """A rectangle of the lattice: columns i0..i0+cols-1 (x), rows j0..j0+rows-1 (y)."""

    i0: int
    j0: int
    cols: int
    rows: int

    def __post_init__(self) -> None:
        if self.cols < 0 or self.rows < 0:
            raise ValueError(f"window size must be non-negative, got {self.cols}×{self.rows}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def i1(self) -> int:
        return self.i0 + self.cols

    @property
    def j1(self) -> int:
        return self.j0 + self.rows

    @property
    def empty(self) -> bool:
        return self.cols == 0 or self.rows == 0

    def origin_m(self, resolution_m: float) -> tuple[float, float]:
        """World coordinates of the window's lower-left corner (the map_server ``origin``)."""
        return (self.i0 * resolution_m, self.j0 * resolution_m)

    def bounds_m(self, resolution_m: float) -> tuple[float, float, float, float]:
        """World rectangle the window's cells cover: x0, y0, x1, y1."""
        r = resolution_m
        return (self.i0 * r, self.j0 * r, self.i1 * r, self.j1 * r)

    def intersect(self, other: Window) -> Window:
        i0, j0 = max(self.i0, other.i0), max(self.j0, other.j0)
        i1, j1 = min(self.i1, other.i1), min(self.j1, other.j1)
        return Window(i0, j0, max(0, i1 - i0), max(0, j1 - j0))

    def union(self, other: Window) -> Window:
        if self.empty:
            return other
        if other.empty:
            return self
        i0, j0 = min(self.i0, other.i0), min(self.j0, other.j0)
        return Window(i0, j0, max(self.i1, other.i1) - i0, max(self.j1, other.j1) - j0)

    def contains(self, other: Window) -> bool:
        return other.empty or self.intersect(other) == other

    def slices_in(self, outer: Window) -> tuple[slice, slice]:
        """Row and column slices that address this window inside an array covering ``outer``."""
        if not outer.contains(self):
            raise ValueError(f"{self} is not inside {outer}")
        if self.empty:
            return (slice(0, 0), slice(0, 0))
        dj, di = self.j0 - outer.j0, self.i0 - outer.i0
        return (slice(dj, dj + self.rows), slice(di, di + self.cols))

    @staticmethod
    def covering(
        x_min: float, y_min: float, x_max: float, y_max: float, resolution_m: float
    ) -> Window:
        """Smallest window whose cells cover the metric rectangle [min, max)."""
        i0, j0 = (int(v) for v in cell_of((x_min, y_min), resolution_m))
        i1, j1 = (int(v) + 1 for v in cell_of((x_max - _EDGE_EPS, y_max - _EDGE_EPS), resolution_m))
        return Window(i0, j0, max(0, i1 - i0), max(0, j1 - j0))

    def cell_centers(
        self, resolution_m: float
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """x and y of every cell centre, each of shape (rows, cols)."""
        xs = cell_center(np.arange(self.i0, self.i1), resolution_m)
        ys = cell_center(np.arange(self.j0, self.j1), resolution_m)
        x_grid, y_grid = np.meshgrid(xs, ys)
        return x_grid, y_grid


A = TypeVar("A", bound=np.generic)


def reframe(
    array: npt.NDArray[A], window: Window, onto: Window, fill: float | bool
) -> npt.NDArray[A]:
    """``array`` (covering ``window``) seen on window ``onto``: shared cells copied, others ``fill``."""
    out = np.full(onto.shape, fill, dtype=array.dtype)
    part = window.intersect(onto)
    if not part.empty:
        out[part.slices_in(onto)] = array[part.slices_in(window)]
    return out
