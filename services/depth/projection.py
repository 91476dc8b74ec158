"""Disparity → depth and its uncertainty → world points and heights (DESIGN.md, Sensor model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.sensor_model import SensorModelParams, depth_from_disparity, depth_sigma

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
    valid = np.isfinite(disparity_px)
    depth_m = depth_from_disparity(disparity_px[valid], focal_px, baseline_m)
    rays = rays_world[:, valid]
    sigma_z = depth_sigma(depth_m, focal_px * downscale, baseline_m, params)
    return WorldPoints(
        x_m=(camera_world[0] + depth_m * rays[0]).astype(np.float32),
        y_m=(camera_world[1] + depth_m * rays[1]).astype(np.float32),
        height_m=(camera_world[2] + depth_m * rays[2]).astype(np.float32),
        height_sigma_m=(np.abs(rays[2]) * sigma_z).astype(np.float32),
    )
