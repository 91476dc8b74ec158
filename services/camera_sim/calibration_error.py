"""The calibration a site really has: the true cameras, off by a good calibration's residual error.

The simulator renders with the true cameras and publishes this one, so the depth service works from
a calibration as wrong as a real one. Each camera's error is drawn from (seed, pair, side): small
rotations about each axis, a position offset (which moves the baseline), a focal-length scale and a
principal-point offset. The vertical part of the relative rotation is what the seed paper calls
misalignment error (0.11–0.31 px there); at the defaults it is 0.1–0.6 px RMS at full resolution,
median 0.3 px (over 5 seeds × 4 pairs).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import astuple, dataclass

import numpy as np
import numpy.typing as npt

from common.camera import PinholeCamera, StereoCalibration


@dataclass(frozen=True)
class CalibrationError:
    rotation_sigma_deg: float = 0.015
    """Per axis, per camera (≈0.03° in all)."""
    position_sigma_mm: float = 0.7
    """Per axis, per camera (the baseline's length is off by ≈1 mm)."""
    focal_sigma_pct: float = 0.2
    principal_point_sigma_px: float = 0.1

    def __post_init__(self) -> None:
        values = astuple(self)
        if min(values) < 0 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"calibration error sizes must be finite and ≥ 0, got {values}")

    @property
    def exact(self) -> bool:
        return not any(astuple(self))


def rotation_from_vector(rotation_rad: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rodrigues' formula (the sim install has no OpenCV)."""
    angle = float(np.linalg.norm(rotation_rad))
    if angle < 1e-15:
        return np.eye(3)
    kx, ky, kz = rotation_rad / angle
    K = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    rotation: npt.NDArray[np.float64] = (
        np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
    )
    return rotation


def _perturbed(
    camera: PinholeCamera, error: CalibrationError, rng: np.random.Generator
) -> PinholeCamera:
    rotation = rotation_from_vector(np.radians(error.rotation_sigma_deg) * rng.standard_normal(3))
    pose = camera.T_world_cam_array.copy()
    pose[:3, :3] = pose[:3, :3] @ rotation  # a rotation of the camera about its own centre
    pose[:3, 3] += error.position_sigma_mm / 1000.0 * rng.standard_normal(3)
    K = camera.K_array.copy()
    K[:2, :2] *= 1.0 + error.focal_sigma_pct / 100.0 * rng.standard_normal()
    K[:2, 2] += error.principal_point_sigma_px * rng.standard_normal(2)
    return PinholeCamera(
        width=camera.width,
        height=camera.height,
        K=K.tolist(),
        dist=camera.dist,
        T_world_cam=pose.tolist(),
    )


def published_calibration(
    calib: StereoCalibration, error: CalibrationError, seed: int
) -> StereoCalibration:
    """``calib`` as a calibration procedure would have measured it; exact when ``error`` is 0."""
    if error.exact:
        return calib
    cameras = {
        side: _perturbed(
            getattr(calib, side),
            error,
            np.random.default_rng([seed & 0xFFFFFFFF, zlib.crc32(f"{calib.pair}/{side}".encode())]),
        )
        for side in ("left", "right")
    }
    return StereoCalibration(pair=calib.pair, left=cameras["left"], right=cameras["right"])
