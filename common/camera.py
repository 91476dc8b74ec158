"""Pinhole camera and stereo-pair calibration: intrinsics, distortion, pose in the world frame.

Camera frame follows OpenCV: x right, y down, z forward. ``T_world_cam`` maps camera coordinates to
world coordinates (metres, z up, floor at z = 0): P_w = R·P_c + C.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from common.keys import check_pair_id

Matrix = list[list[float]]

MAX_IMAGE_PIXELS = 4096 * 4096
"""Larger than any stereo camera we know (12 MP machine-vision sensors fit): a calibration of a
16384×16384 image would have the depth process allocate gigabytes of rectification maps."""
ROTATION_TOLERANCE = 1e-3
"""How far a pose's rotation may be from orthonormal (largest entry of R·Rᵀ − I): a rotation
typed to four decimals is off by about 1e-4; it is taken to the nearest rotation."""
MAX_FIELD_OF_VIEW_DEG = 170.0
"""A pinhole model cannot see 180° across; a focal length of 1e-9 px claims it does."""
RAY_SAMPLES = 4096
"""Ray angles sampled between the axis and half the widest field of view when checking that the
distortion is invertible: a step of 0.02°, finer than any fold a real lens model has."""


def _flat_row(value: Any) -> Any:
    """OpenCV's distortion as written by ``D.tolist()``: one row, ``[[k1, k2, …]]``, or a
    column ``[[k1], [k2], …]``."""
    if isinstance(value, list) and value and all(isinstance(v, list) for v in value):
        rows = [len(v) for v in value]
        if len(value) == 1 or set(rows) == {1}:
            return [x for row in value for x in row]
    return value


def radial_distortion_fold(dist: npt.ArrayLike, corner_radius: float) -> str | None:
    """Why the radial distortion (OpenCV's k1 k2 k3 over k4 k5 k6) is not invertible over an image
    whose farthest corner lies ``corner_radius`` from the principal point (normalised units), or
    None. Undistortion (what rectification does) inverts r ↦ r_d = r·(1 + k1 r² + k2 r⁴ + k3 r⁶)
    / (1 + k4 r² + k5 r⁴ + k6 r⁶) over the image: r_d must grow with r until it reaches the corner,
    within half the widest field of view. Otherwise pixels near the corner have no ray or two
    (k1 = −100 folds at r_d = 0.04, well inside a 60° camera's 0.72: the maps come out empty).
    Tangential and thin-prism terms are left out: they are small beside the radial ones in any
    lens a calibration fits."""
    k = np.zeros(8)
    given = np.asarray(dist, dtype=np.float64)[:8]
    k[: given.size] = given
    k1, k2, _p1, _p2, k3, k4, k5, k6 = k
    r = np.tan(np.radians(np.linspace(0.0, MAX_FIELD_OF_VIEW_DEG / 2.0, RAY_SAMPLES)))
    r2 = r * r
    denominator = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(divide="ignore", invalid="ignore"):
        r_distorted = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / denominator
    growing = (np.diff(r_distorted) > 0) & (denominator[1:] > 0)
    fold = int(np.argmin(growing)) if not growing.all() else RAY_SAMPLES - 1
    reached = np.flatnonzero(r_distorted[: fold + 1] >= corner_radius)
    if reached.size:
        return None
    where = (
        f"stops growing at {r_distorted[fold]:.3g} (a ray {math.degrees(math.atan(r[fold])):.1f}° "
        "off the axis)"
        if fold < RAY_SAMPLES - 1
        else f"reaches only {r_distorted[fold]:.3g} within {MAX_FIELD_OF_VIEW_DEG / 2:g}° of the axis"
    )
    return (
        f"distortion {given.tolist()} is not invertible over the image: the distorted radius "
        f"{where}, short of the image corner at {corner_radius:.3g}"
    )


MAX_SKEW_SHARE = 1e-3
"""A calibration's skew (K[0][1]) up to this share of fx (pixel axes 0.06° off square) is a
fitting residual; beyond it, a K for another model or a typing error."""


def _finite(values: npt.ArrayLike, what: str) -> None:
    if not np.all(np.isfinite(np.asarray(values, dtype=np.float64))):
        raise ValueError(f"{what} holds NaN or infinity")


class PinholeCamera(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    width: int = Field(gt=0, le=16384)
    height: int = Field(gt=0, le=16384)
    K: Matrix
    dist: Annotated[list[float], BeforeValidator(_flat_row)] = Field(
        default_factory=lambda: [0.0] * 5
    )
    T_world_cam: Matrix

    @field_validator("K")
    @classmethod
    def _check_k(cls, k: Matrix) -> Matrix:
        arr = np.asarray(k, dtype=np.float64)
        if arr.shape != (3, 3):
            raise ValueError(f"K must be 3×3, got shape {arr.shape}")
        _finite(arr, "K")
        if arr[0, 0] <= 0 or arr[1, 1] <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={arr[0, 0]}, fy={arr[1, 1]}")
        if not np.allclose(arr[2], (0.0, 0.0, 1.0), rtol=0.0, atol=1e-9) or arr[1, 0] != 0:
            raise ValueError(
                f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got rows {arr[1].tolist()}, "
                f"{arr[2].tolist()}"
            )
        if abs(arr[0, 1]) > MAX_SKEW_SHARE * arr[0, 0]:
            raise ValueError(
                f"skew {arr[0, 1]:g} px is over {MAX_SKEW_SHARE:g} of fx: OpenCV's calibration "
                "and rectification assume square pixels"
            )
        return k

    @model_validator(mode="after")
    def _geometry_of_a_camera(self) -> PinholeCamera:
        cx, cy = self.K[0][2], self.K[1][2]
        if not (-0.5 <= cx <= self.width - 0.5 and -0.5 <= cy <= self.height - 0.5):
            raise ValueError(
                f"principal point ({cx:g}, {cy:g}) lies outside the {self.width}×{self.height} image"
            )
        if self.width * self.height > MAX_IMAGE_PIXELS:
            raise ValueError(
                f"image {self.width}×{self.height} exceeds {MAX_IMAGE_PIXELS} pixels: "
                "no stereo camera has so many"
            )
        for axis, focal_px, extent_px in (
            ("x", self.K[0][0], self.width),
            ("y", self.K[1][1], self.height),
        ):
            fov_deg = math.degrees(2.0 * math.atan(extent_px / (2.0 * focal_px)))
            if fov_deg > MAX_FIELD_OF_VIEW_DEG:
                raise ValueError(
                    f"focal length f{axis}={focal_px:g} px gives a {fov_deg:.1f}° field of view over "
                    f"{extent_px} px; a pinhole camera sees less than {MAX_FIELD_OF_VIEW_DEG:g}°"
                )
        fold = radial_distortion_fold(self.dist, self.corner_radius)
        if fold is not None:
            raise ValueError(fold)
        return self

    @property
    def corner_radius(self) -> float:
        """How far the farthest image corner lies from the principal point, in normalised image
        coordinates ((u − cx)/fx, (v − cy)/fy)."""
        (fx, _, cx), (_, fy, cy) = self.K[0], self.K[1]
        return max(
            math.hypot((u - cx) / fx, (v - cy) / fy)
            for u in (-0.5, self.width - 0.5)
            for v in (-0.5, self.height - 0.5)
        )

    @field_validator("dist")
    @classmethod
    def _check_dist(cls, dist: list[float]) -> list[float]:
        if len(dist) not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"distortion needs 0, 4, 5, 8, 12 or 14 coefficients, got {len(dist)}")
        _finite(dist, "distortion")
        return dist

    @field_validator("T_world_cam")
    @classmethod
    def _check_pose(cls, pose: Matrix) -> Matrix:
        arr = np.asarray(pose, dtype=np.float64)
        if arr.shape != (4, 4):
            raise ValueError(f"T_world_cam must be 4×4, got shape {arr.shape}")
        _finite(arr, "T_world_cam")
        rotation = arr[:3, :3]
        residual = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
        if residual > ROTATION_TOLERANCE or np.linalg.det(rotation) < 0:
            raise ValueError(
                "T_world_cam rotation is not a proper rotation matrix "
                f"(|R·Rᵀ − I| {residual:.2g}, at most {ROTATION_TOLERANCE:g}; det {np.linalg.det(rotation):.3g})"
            )
        if not np.allclose(arr[3], [0, 0, 0, 1]):
            raise ValueError("T_world_cam last row must be [0, 0, 0, 1]")
        if residual < 1e-9:
            return pose
        # The nearest rotation (SVD): a rotation typed to four decimals is one, to 1e-4.
        u, _, vt = np.linalg.svd(rotation)
        arr[:3, :3] = u @ vt
        return [[float(value) for value in row] for row in arr]

    @cached_property
    def K_array(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.K, dtype=np.float64)

    @cached_property
    def dist_array(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.dist, dtype=np.float64)

    @cached_property
    def T_world_cam_array(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.T_world_cam, dtype=np.float64)

    @property
    def focal_px(self) -> float:
        return float(self.K_array[0, 0])

    @property
    def position_world(self) -> npt.NDArray[np.float64]:
        return self.T_world_cam_array[:3, 3]

    def project(self, points_world: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Pixel (u, v) and depth z of world points (N, 3), ignoring distortion; returns (N, 3)."""
        points = np.atleast_2d(np.asarray(points_world, dtype=np.float64))
        T_cam_world = np.linalg.inv(self.T_world_cam_array)
        p_cam = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        uvw = p_cam @ self.K_array.T
        return np.column_stack([uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2], p_cam[:, 2]])


class StereoCalibration(BaseModel):
    """A stereo pair: the right camera sits to the right of the left one (OpenCV's convention).
    A key it does not know is refused: ``distortion:`` for ``dist:`` ran with none."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    pair: Annotated[str, AfterValidator(check_pair_id)]
    left: PinholeCamera
    right: PinholeCamera

    @model_validator(mode="after")
    def _check_pair(self) -> StereoCalibration:
        if (self.left.width, self.left.height) != (self.right.width, self.right.height):
            raise ValueError(
                f"left image {self.left.width}×{self.left.height} and right image "
                f"{self.right.width}×{self.right.height} differ in size"
            )
        if self.baseline_m < 1e-3:
            raise ValueError(f"stereo baseline is {self.baseline_m:.4g} m: cameras coincide")
        return self

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height), the order OpenCV takes."""
        return (self.left.width, self.left.height)

    @property
    def T_right_left(self) -> npt.NDArray[np.float64]:
        """Maps left-camera coordinates to right-camera coordinates (OpenCV's R, T of stereoRectify)."""
        return np.linalg.inv(self.right.T_world_cam_array) @ self.left.T_world_cam_array

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.right.position_world - self.left.position_world))


def look_down_pose(x: float, y: float, z: float, yaw_rad: float = 0.0) -> npt.NDArray[np.float64]:
    """T_world_cam of a camera at (x, y, z) looking straight down; image x along world (cos, sin)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    x_axis = np.array([c, s, 0.0])
    z_axis = np.array([0.0, 0.0, -1.0])
    y_axis = np.cross(z_axis, x_axis)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x_axis, y_axis, z_axis])
    pose[:3, 3] = (x, y, z)
    return pose


def intrinsics_from_hfov(width: int, height: int, hfov_deg: float) -> npt.NDArray[np.float64]:
    """K of an ideal pinhole with square pixels; principal point at the image centre."""
    focal_px = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array(
        [[focal_px, 0.0, (width - 1) / 2.0], [0.0, focal_px, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )
