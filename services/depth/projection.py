"""Disparity → depth and its uncertainty → world points and heights (DESIGN.md, Sensor model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.compiled import compiled
from common.sensor_model import SensorModelParams, depth_sigma

F32 = npt.NDArray[np.float32]


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
    depth_m = np.empty(disparity_px.size, np.float32)
    xyz = np.empty((3, disparity_px.size), np.float32)
    ray_down = np.empty(disparity_px.size, np.float32)
    count = _project_valid(
        disparity_px,
        rays_world,
        camera_world.astype(np.float32),
        np.float32(focal_px * baseline_m),
        depth_m,
        xyz,
        ray_down,
    )
    depth_m, ray_down = depth_m[:count], ray_down[:count]
    sigma_z = depth_sigma(depth_m, focal_px * downscale, baseline_m, params)
    return WorldPoints(
        x_m=xyz[0, :count],
        y_m=xyz[1, :count],
        height_m=xyz[2, :count],
        height_sigma_m=(ray_down * sigma_z).astype(np.float32),
    )


@compiled
def _project_valid(
    disparity_px: F32,
    rays_world: F32,
    camera_world: F32,
    focal_baseline: np.float32,
    depth_m: F32,
    xyz: F32,
    ray_down: F32,
) -> int:
    """Every pixel with a disparity, in row order: its depth z = f·b/d (NaN for d ≤ 0, as
    :func:`common.sensor_model.depth_from_disparity`), world point C + z·ray and |ray_z|; returns
    how many. One pass (boolean indexing of the three ray planes cost most of the stage)."""
    rows, cols = disparity_px.shape
    count = 0
    for row in range(rows):
        for col in range(cols):
            disparity = disparity_px[row, col]
            if np.isnan(disparity) or np.isinf(disparity):
                continue
            depth = focal_baseline / disparity if disparity > 0 else np.float32(np.nan)
            depth_m[count] = depth
            for axis in range(3):
                xyz[axis, count] = camera_world[axis] + depth * rays_world[axis, row, col]
            ray_down[count] = abs(rays_world[2, row, col])
            count += 1
    return count
