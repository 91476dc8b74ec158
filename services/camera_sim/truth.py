"""Ground-truth occupancy: objects whose vertical extent meets the obstacle band, rasterised on the
lattice by cell centre (the same rule a map cell is judged by)."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from common.lattice import Window
from common.messages import TruthObject


def footprint_mask(obj: TruthObject, window: Window, resolution_m: float) -> npt.NDArray[np.bool_]:
    """Cells of ``window`` whose centre lies inside the object's footprint."""
    x, y = window.cell_centers(resolution_m)
    dx, dy = x - obj.center_m[0], y - obj.center_m[1]
    if obj.shape == "cylinder":
        radius = obj.size_m[0] / 2
        return np.asarray(dx * dx + dy * dy <= radius * radius)
    c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
    along, across = c * dx + s * dy, -s * dx + c * dy
    return np.asarray((np.abs(along) <= obj.size_m[0] / 2) & (np.abs(across) <= obj.size_m[1] / 2))


def occupancy(
    objects: list[TruthObject], window: Window, resolution_m: float, band_m: tuple[float, float]
) -> npt.NDArray[np.uint8]:
    """1 where some object spans part of the height band [band_m[0], band_m[1]], else 0."""
    grid = np.zeros(window.shape, dtype=np.uint8)
    for obj in objects:
        if obj.top_m >= band_m[0] and obj.bottom_m <= band_m[1]:
            grid |= footprint_mask(obj, window, resolution_m).astype(np.uint8)
    return grid


def top_heights(
    objects: list[TruthObject], window: Window, resolution_m: float
) -> npt.NDArray[np.float64]:
    """Per cell, the highest object top over it (0: bare floor): the surface an overhead camera sees."""
    heights = np.zeros(window.shape, dtype=np.float64)
    for obj in objects:
        heights = np.where(
            footprint_mask(obj, window, resolution_m), np.maximum(heights, obj.top_m), heights
        )
    return heights
