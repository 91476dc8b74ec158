"""Ceiling grid of downward-looking stereo pairs whose floor footprints overlap and cover the floor."""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from common.camera import PinholeCamera, StereoCalibration, intrinsics_from_hfov, look_down_pose


class RigSpec(BaseModel):
    """The simulated ceiling rig, declared once (the camera_sim settings nest it as ``--rig.*``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    pair_count: int = Field(4, ge=1, le=256, description="stereo pairs on the ceiling grid")
    height_m: float = Field(6.0, gt=0.5, le=50.0, description="ceiling height of the cameras")
    baseline_m: float = Field(0.5, gt=0.0, le=5.0, description="stereo baseline")
    width_px: int = Field(640, ge=64, le=4096, description="image width")
    height_px: int = Field(480, ge=48, le=4096, description="image height")
    hfov_deg: float = Field(60.0, gt=5.0, lt=170.0, description="horizontal field of view")


def pair_name(index: int) -> str:
    return f"p{index}"


def _grid_shape(
    count: int, floor_size_m: tuple[float, float], footprint_m: tuple[float, float]
) -> tuple[int, int]:
    """Columns × rows of the ceiling grid that best covers the floor with ``count`` pairs."""
    best: tuple[float, int, int] = (math.inf, 1, count)
    for cols in range(1, count + 1):
        rows = math.ceil(count / cols)
        stretch = max(
            floor_size_m[0] / cols / footprint_m[0], floor_size_m[1] / rows / footprint_m[1]
        )
        if stretch < best[0]:
            best = (stretch, cols, rows)
    return best[1], best[2]


def layout_pairs(rig: RigSpec, floor_size_m: tuple[float, float]) -> list[StereoCalibration]:
    """Calibrations of every pair: the pair's midpoint at a grid cell centre, baseline along x."""
    K = intrinsics_from_hfov(rig.width_px, rig.height_px, rig.hfov_deg)
    focal_px = float(K[0, 0])
    footprint = (rig.width_px * rig.height_m / focal_px, rig.height_px * rig.height_m / focal_px)
    cols, rows = _grid_shape(rig.pair_count, floor_size_m, footprint)
    calibrations = []
    for index in range(rig.pair_count):
        col, row = index % cols, index // cols
        cx = (col + 0.5) * floor_size_m[0] / cols
        cy = (row + 0.5) * floor_size_m[1] / rows
        cameras = [
            PinholeCamera(
                width=rig.width_px,
                height=rig.height_px,
                K=K.tolist(),
                dist=[0.0] * 5,
                T_world_cam=look_down_pose(cx + dx, cy, rig.height_m).tolist(),
            )
            for dx in (-rig.baseline_m / 2, rig.baseline_m / 2)
        ]
        calibrations.append(
            StereoCalibration(pair=pair_name(index), left=cameras[0], right=cameras[1])
        )
    return calibrations


def mujoco_camera_axes(camera: PinholeCamera) -> tuple[np.ndarray, float]:
    """MuJoCo ``xyaxes`` (image right, image up in world) and vertical fov of an OpenCV camera."""
    rotation = camera.T_world_cam_array[:3, :3]
    xyaxes = np.concatenate([rotation[:, 0], -rotation[:, 1]])
    fovy_deg = math.degrees(2.0 * math.atan(camera.height / 2.0 / camera.K_array[1, 1]))
    return xyaxes, fovy_deg


def floor_points_xy_m(camera: PinholeCamera, width: int, height: int) -> np.ndarray:
    """Where each pixel's ray (of an image ``width`` × ``height``, the camera's scaled) meets the
    floor z = 0, (…, 2) in metres; a ray at or above the horizon gives the camera's nadir."""
    u, v = np.meshgrid(
        (np.arange(width) + 0.5) * camera.width / width - 0.5,
        (np.arange(height) + 0.5) * camera.height / height - 0.5,
    )
    rays_cam = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(camera.K_array).T
    pose = camera.T_world_cam_array
    rays_world = rays_cam @ pose[:3, :3].T
    center_world_m = pose[:3, 3]
    down = rays_world[..., 2] < -1e-6
    reach = -center_world_m[2] / np.where(down, rays_world[..., 2], -1.0)
    floor_xy_m = center_world_m[:2] + rays_world[..., :2] * reach[..., None]
    return np.where(down[..., None], floor_xy_m, center_world_m[:2])
