"""The floor plane of a rectified pair: its disparity at each pixel, heights from disparities and
back, and where the floor below a raised point shows."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.arrays import F32, Mask
from services.depth.stereo import Rectifier


@dataclass(frozen=True)
class FloorGeometry:
    """What the floor model needs of a pair's rectified geometry."""

    floor_disparity_px: F32
    """Disparity of the plane z = 0 at every rectified pixel."""
    ray_down: F32
    """−ray_z of every pixel's ray (scaled so that depth z multiplies it): height = C_z − z·ray_down."""
    camera_height_m: float
    focal_baseline_px_m: float
    """f·b: depth z = f·b / d."""
    nadir_px: tuple[float, float]
    """Where vertical lines vanish in the rectified left image (the point below the camera)."""
    floor_px_per_m: float
    """Pixels a metre of floor spans below the camera (focal length over camera height)."""
    depth_per_m_down: float
    """Depth (along the optical axis) a point gains per metre it moves straight down: 0 for rays
    that are all vertical (the point below shows at the same pixel)."""

    @staticmethod
    def from_rectifier(rectifier: Rectifier, rays_world: F32) -> FloorGeometry:
        down = np.maximum(-rays_world[2].astype(np.float64), 1e-9)
        height_m = float(rectifier.C_world[2])
        focal_baseline = rectifier.focal_px * rectifier.baseline_m
        below = rectifier.R_world_rect.T @ np.array([0.0, 0.0, -1.0])
        if below[2] <= 1e-6:
            raise ValueError("the camera does not look down: no floor model")
        nadir = (
            rectifier.cx_px + rectifier.focal_px * below[0] / below[2],
            rectifier.cy_px + rectifier.focal_px * below[1] / below[2],
        )
        return FloorGeometry(
            floor_disparity_px=(focal_baseline * down / height_m).astype(np.float32),
            ray_down=down.astype(np.float32),
            camera_height_m=height_m,
            focal_baseline_px_m=focal_baseline,
            nadir_px=(float(nadir[0]), float(nadir[1])),
            floor_px_per_m=rectifier.focal_px / height_m,
            depth_per_m_down=float(below[2]),
        )

    @property
    def foot_terms(self) -> tuple[F32, float, float, float, float]:
        """What :func:`foot_px` needs of the geometry: ray_down, the camera's height, the depth a
        metre down adds, the nadir's row and column."""
        return (
            self.ray_down,
            self.camera_height_m,
            self.depth_per_m_down,
            self.nadir_px[1],
            self.nadir_px[0],
        )

    def height_m(self, disparity_px: F32, at: Mask | None = None) -> F32:
        """The height of the surface at ``disparity_px`` at every pixel, or with ``at`` at those
        pixels only (``disparity_px`` holds their values, in order): the same figures, without the
        passes over the rest of the image."""
        ray_down = self.ray_down if at is None else self.ray_down[at]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.float32(self.focal_baseline_px_m) / disparity_px
        height: F32 = (np.float32(self.camera_height_m) - depth * ray_down).astype(np.float32)
        return height

    def disparity_px(self, height_m: F32, at: Mask | None = None) -> F32:
        """The disparity of a surface at ``height_m`` at every pixel (inverse of :meth:`height_m`),
        or with ``at`` at those pixels only (``height_m`` holds their values, in order)."""
        ray_down = self.ray_down if at is None else self.ray_down[at]
        with np.errstate(divide="ignore", invalid="ignore"):
            disparity: F32 = (
                np.float32(self.focal_baseline_px_m)
                * ray_down
                / (np.float32(self.camera_height_m) - height_m)
            ).astype(np.float32)
        return disparity
