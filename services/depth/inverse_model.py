"""Inverse sensor model: world points of one frame → one occupancy observation per cell (a tile).

Pixels falling in one cell are aggregated into a single Bayesian update; they are never counted as
independent evidence. Pixels above the obstacle band give no update (they hide what lies below).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.lattice import Window, cell_of
from common.sensor_model import (
    SensorModelParams,
    cell_occupancy_probability,
    in_model_range,
    logodds,
    obstacle_likelihood,
)
from services.depth.projection import WorldPoints

COUNT_MAX = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class Tile:
    """Occupancy evidence on lattice ``window``; arrays are ``[row, col] = [j - j0, i - i0]``."""

    window: Window
    resolution_m: float
    logodds: npt.NDArray[np.float32]
    height_m: npt.NDArray[np.float32]
    """Top height seen in the cell; NaN where the cell got no update."""
    count: npt.NDArray[np.uint16]
    """Pixels aggregated into the cell's update; 0 means no update."""

    def arrays(self) -> dict[str, np.ndarray]:
        return {"logodds": self.logodds, "height_m": self.height_m, "count": self.count}


def build_tile(
    points: WorldPoints, resolution_m: float, params: SensorModelParams, min_cell_pixels: int = 3
) -> Tile:
    keep = in_model_range(points.height_m, points.height_sigma_m, params)
    x, y = points.x_m[keep], points.y_m[keep]
    height, sigma = points.height_m[keep], points.height_sigma_m[keep]
    if x.size == 0:
        empty = Window(0, 0, 0, 0)
        return Tile(
            empty,
            resolution_m,
            np.zeros((0, 0), np.float32),
            np.zeros((0, 0), np.float32),
            np.zeros((0, 0), np.uint16),
        )
    i, j = cell_of(x, resolution_m), cell_of(y, resolution_m)  # 1-D each: contiguous min/max
    window = Window(
        int(i.min()), int(j.min()), int(i.max() - i.min()) + 1, int(j.max() - j.min()) + 1
    )
    rows, cols = window.shape
    flat = (j - window.j0) * cols + (i - window.i0)
    size = rows * cols

    pixels = np.bincount(flat, minlength=size)
    weights = obstacle_likelihood(height, sigma, params)
    obstacle = np.bincount(flat, weights=weights, minlength=size).astype(np.float64)
    top = np.full(size, -np.inf, dtype=np.float32)
    np.maximum.at(top, flat, height)

    updated = pixels >= min_cell_pixels
    update = np.where(
        updated,
        logodds(cell_occupancy_probability(obstacle, pixels.astype(np.float64), params)),
        0.0,
    )
    return Tile(
        window=window,
        resolution_m=resolution_m,
        logodds=update.astype(np.float32).reshape(rows, cols),
        height_m=np.where(updated, top, np.nan).astype(np.float32).reshape(rows, cols),
        count=np.where(updated, np.minimum(pixels, COUNT_MAX), 0)
        .astype(np.uint16)
        .reshape(rows, cols),
    )
