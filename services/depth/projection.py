"""Disparity → depth and its uncertainty → world points and heights (DESIGN.md, Sensor model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.arrays import F32
from common.compiled import compiled
from common.sensor_model import SensorModelParams, depth_from_disparity, depth_sigma


@dataclass(frozen=True)
class WorldPoints:
    """Valid pixels only, flattened: position, height and its standard deviation, metres."""

    x_m: F32
    y_m: F32
    height_m: F32
    height_sigma_m: F32


def project_to_world(
    disparity_px: F32,
    rays_world: F32,
    camera_world: npt.NDArray[np.float64],
    focal_px: float,
    baseline_m: float,
    params: SensorModelParams,
    downscale: int = 1,
) -> WorldPoints:
    """P_w = C + z·ray; σ_h = |ray_z|·Δz with Δz = z²/(b·f)·Δd + ε.

    Δd is a property of the sensor, in full-resolution pixels: images processed at 1/downscale
    resolution use the sensor's focal length (f·downscale) for Δz.
    """
    disparity = np.empty(disparity_px.size, np.float32)
    rays = np.empty((3, disparity_px.size), np.float32)
    count = _gather_valid(disparity_px, rays_world, disparity, rays)
    rays = rays[:, :count]
    depth_m = depth_from_disparity(disparity[:count], focal_px, baseline_m)
    sigma_z = depth_sigma(depth_m, focal_px * downscale, baseline_m, params)
    return WorldPoints(
        x_m=(camera_world[0] + depth_m * rays[0]).astype(np.float32),
        y_m=(camera_world[1] + depth_m * rays[1]).astype(np.float32),
        height_m=(camera_world[2] + depth_m * rays[2]).astype(np.float32),
        height_sigma_m=(np.abs(rays[2]) * sigma_z).astype(np.float32),
    )


@compiled
def _gather_valid(disparity_px: F32, rays_world: F32, disparity: F32, rays: F32) -> int:
    """Every pixel with a disparity, in row order: its disparity and its ray; returns how many.
    One pass: boolean indexing of the three ray planes cost most of the stage."""
    rows, cols = disparity_px.shape
    count = 0
    for row in range(rows):
        for col in range(cols):
            value = disparity_px[row, col]
            if np.isnan(value) or np.isinf(value):
                continue
            disparity[count] = value
            for axis in range(3):
                rays[axis, count] = rays_world[axis, row, col]
            count += 1
    return count
