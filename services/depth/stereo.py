"""Rectification (maps computed once per calibration) and SGBM disparity over a search band
derived from the geometry: from the floor's disparity to that of the tallest height of interest."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt

from common.camera import StereoCalibration

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def scale_intrinsics(K: F64, factor: float) -> F64:
    """K of the image resized by ``factor`` (< 1 shrinks), keeping pixel centres consistent."""
    scaled = K.copy()
    scaled[0, 0] *= factor
    scaled[1, 1] *= factor
    scaled[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
    scaled[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
    return scaled


def stereo_rectify(
    calib: StereoCalibration, K_left: F64, K_right: F64, size: tuple[int, int]
) -> tuple[F64, F64, F64, F64, F64]:
    """OpenCV's R1, R2, P1, P2, Q for the pair, principal points aligned (zero-disparity)."""
    T = calib.T_right_left
    R1, R2, P1, P2, Q, _roi1, _roi2 = cv2.stereoRectify(
        K_left,
        calib.left.dist_array,
        K_right,
        calib.right.dist_array,
        size,
        T[:3, :3].copy(),
        T[:3, 3].reshape(3, 1).copy(),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0,
    )
    R1, R2, P1, P2, Q = (np.asarray(m, dtype=np.float64) for m in (R1, R2, P1, P2, Q))
    return R1, R2, P1, P2, Q


@dataclass(frozen=True)
class Rectifier:
    """Undistort + rectify maps of one calibration at the processing resolution."""

    size: tuple[int, int]
    """(width, height) of the rectified images."""
    downscale: int
    focal_px: float
    cx_px: float
    cy_px: float
    baseline_m: float
    R_world_rect: F64
    """Rotation from the rectified left camera frame to the world frame."""
    C_world: F64
    """Left camera centre in the world."""
    _maps_left: tuple[np.ndarray, np.ndarray]
    _maps_right: tuple[np.ndarray, np.ndarray]

    @staticmethod
    def from_calibration(calib: StereoCalibration, downscale: int = 2) -> Rectifier:
        width, height = calib.image_size
        if width % downscale or height % downscale:
            raise ValueError(f"image {width}×{height} is not divisible by downscale {downscale}")
        size = (width // downscale, height // downscale)
        K1 = scale_intrinsics(calib.left.K_array, 1.0 / downscale)
        K2 = scale_intrinsics(calib.right.K_array, 1.0 / downscale)
        R1, R2, P1, P2, _Q = stereo_rectify(calib, K1, K2, size)
        if abs(P2[1, 3]) > abs(P2[0, 3]):
            raise ValueError(
                f"pair {calib.pair}: cameras are stacked vertically; overgrid needs a horizontal baseline"
            )
        if P2[0, 3] >= 0:
            raise ValueError(
                f"pair {calib.pair}: the right camera is to the left of the left camera; swap them"
            )
        maps_left = cv2.initUndistortRectifyMap(
            K1, calib.left.dist_array, R1, P1, size, cv2.CV_16SC2
        )
        maps_right = cv2.initUndistortRectifyMap(
            K2, calib.right.dist_array, R2, P2, size, cv2.CV_16SC2
        )
        R_world_left = calib.left.T_world_cam_array[:3, :3]
        return Rectifier(
            size=size,
            downscale=downscale,
            focal_px=float(P1[0, 0]),
            cx_px=float(P1[0, 2]),
            cy_px=float(P1[1, 2]),
            baseline_m=float(-P2[0, 3] / P2[0, 0]),
            R_world_rect=R_world_left @ R1.T,
            C_world=calib.left.position_world.copy(),
            _maps_left=maps_left,
            _maps_right=maps_right,
        )

    def rectify(self, left: U8, right: U8) -> tuple[U8, U8]:
        if self.downscale != 1:
            # INTER_AREA first: remapping a full-resolution image at half density would alias.
            left = np.asarray(cv2.resize(left, self.size, interpolation=cv2.INTER_AREA))
            right = np.asarray(cv2.resize(right, self.size, interpolation=cv2.INTER_AREA))
        return (
            np.asarray(cv2.remap(left, *self._maps_left, cv2.INTER_LINEAR), dtype=np.uint8),
            np.asarray(cv2.remap(right, *self._maps_right, cv2.INTER_LINEAR), dtype=np.uint8),
        )

    def pixel_rays_world(self) -> F32:
        """World direction of every rectified pixel's ray, scaled so that depth z multiplies it:
        P_world = C + z·ray. Shape (3, H, W)."""
        width, height = self.size
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays_rect = np.stack(
            [(u - self.cx_px) / self.focal_px, (v - self.cy_px) / self.focal_px, np.ones_like(u)]
        )
        rays: F32 = np.einsum("ij,jhw->ihw", self.R_world_rect, rays_rect).astype(np.float32)
        return rays

    def disparity_band(self, height_low_m: float, height_high_m: float) -> tuple[int, int]:
        """(minDisparity, numDisparities) covering surfaces from ``height_low_m`` to ``height_high_m``
        anywhere in the image; numDisparities is a multiple of 16 as SGBM requires."""
        rays = self.pixel_rays_world()[:, ::8, ::8].reshape(3, -1)
        down = -rays[2]
        if np.any(down <= 1e-6):
            raise ValueError("some pixels look at or above the horizon: not an overhead camera")
        disparities = []
        for height_m in (height_low_m, height_high_m):
            depth_m = (self.C_world[2] - height_m) / down
            if np.any(depth_m <= 0):
                raise ValueError(
                    f"height {height_m} m is at or above the camera ({self.C_world[2]:.2f} m)"
                )
            disparities.append(self.focal_px * self.baseline_m / depth_m)
        d_min = max(0, math.floor(float(disparities[0].min())) - 1)
        d_max = math.ceil(float(disparities[1].max())) + 1
        return d_min, 16 * math.ceil((d_max - d_min) / 16)


@dataclass(frozen=True)
class MatcherConfig:
    algorithm: Literal["sgbm", "bm"] = "sgbm"
    block_size: int = 3
    uniqueness_ratio: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    edge_filter_px: float = 0.75
    subpixel: bool = True
    """Re-estimate the fraction of a pixel (:func:`refine_subpixel`) instead of SGBM's own."""


def make_matcher(
    config: MatcherConfig, min_disparity: int, num_disparities: int
) -> cv2.StereoMatcher:
    """SGBM 3WAY with preFilterCap=63 and P1/P2 ∝ blockSize²: the default preFilterCap=0 locks
    disparities to whole pixels. P1 = 2·bs², P2 = 8·bs² gave the lowest error on object tops at half
    resolution among the settings tried (bench/depth_pipeline.py), at the same speed."""
    bs = config.block_size
    if config.algorithm == "bm":
        matcher = cv2.StereoBM.create(numDisparities=num_disparities, blockSize=max(5, bs | 1))
        matcher.setMinDisparity(min_disparity)
        matcher.setUniquenessRatio(config.uniqueness_ratio)
        matcher.setSpeckleWindowSize(config.speckle_window)
        matcher.setSpeckleRange(config.speckle_range)
        matcher.setTextureThreshold(10)
        return matcher
    return cv2.StereoSGBM.create(
        minDisparity=min_disparity,
        numDisparities=num_disparities,
        blockSize=bs,
        P1=2 * bs * bs,
        P2=8 * bs * bs,
        disp12MaxDiff=1,
        preFilterCap=63,
        uniquenessRatio=config.uniqueness_ratio,
        speckleWindowSize=config.speckle_window,
        speckleRange=config.speckle_range,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


def disparity_px(matcher: Any, left: U8, right: U8, min_disparity: int) -> F32:
    """Disparity in pixels (float32); invalid pixels are NaN."""
    raw = np.asarray(matcher.compute(left, right))
    disparity: F32 = raw.astype(np.float32) * np.float32(1.0 / 16.0)
    disparity[raw < min_disparity * 16] = np.nan
    return disparity


SUBPIXEL_BLUR_SIGMA_PX = 1.0
SUBPIXEL_WINDOW_PX = 5
SUBPIXEL_MEDIAN_PX = 5


def refine_subpixel(left: U8, right: U8, disparity: F32) -> F32:
    """Disparity with its fraction of a pixel measured again, free of SGBM's pixel locking.

    SGBM fits a parabola to costs aggregated along paths; on weakly textured surfaces that fit is
    pulled toward whole pixels by up to ⅛ px, which is 2 cm of depth at 5 m at half resolution (one
    bias for a whole flat box top: it does not average out). Here, per pixel, the sum of squared
    differences is taken at the rounded disparity and one pixel either side, with exact whole-pixel
    shifts (no interpolation), on images blurred so that SSD is close to a parabola in the shift; the
    parabola's vertex is the new fraction. A 5×5 median then removes the noise of the small window
    while keeping depth edges. Pixels whose fit fails (no curvature, vertex more than a pixel off, or
    mostly invalid neighbours) become NaN. Sizes: bench/depth_pipeline.py.
    """
    height, width = disparity.shape
    valid = np.isfinite(disparity)
    whole = np.round(np.where(valid, disparity, 0.0)).astype(np.float32)
    left_f = cv2.GaussianBlur(left.astype(np.float32), (0, 0), SUBPIXEL_BLUR_SIGMA_PX)
    right_f = cv2.GaussianBlur(right.astype(np.float32), (0, 0), SUBPIXEL_BLUR_SIGMA_PX)
    # Channel k holds right(x + 1 - k), so one remap at x - whole fetches the shifts whole-1, whole,
    # whole+1 together.
    padded = cv2.copyMakeBorder(right_f, 0, 0, 1, 1, cv2.BORDER_REPLICATE)
    shifts = cv2.merge([padded[:, 2:], padded[:, 1:-1], padded[:, :-2]])
    map_x = np.arange(width, dtype=np.float32) - whole
    map_y = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    difference = cv2.subtract(
        cv2.merge([left_f, left_f, left_f]), cv2.remap(shifts, map_x, map_y, cv2.INTER_NEAREST)
    )
    squared = cv2.multiply(difference, difference)
    squared[~valid] = 0.0  # no disparity, no meaningful cost at its shifts
    window = (SUBPIXEL_WINDOW_PX, SUBPIXEL_WINDOW_PX)
    before, at, after = cv2.split(cv2.boxFilter(squared, -1, window, normalize=False))
    curvature = before - 2.0 * at + after
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = (before - after) / (2.0 * curvature)
    fitted = valid & (curvature > 0) & (np.abs(fraction) <= 1.0)
    refined = np.where(fitted, whole + fraction, 0.0).astype(np.float32)
    k = SUBPIXEL_MEDIAN_PX
    smoothed = np.asarray(cv2.medianBlur(refined, k))
    support = cv2.boxFilter(fitted.astype(np.float32), -1, (k, k), normalize=False)
    keep = fitted & (support > k * k / 2) & (np.abs(smoothed - whole) <= 1.0)
    result: F32 = np.where(keep, smoothed, np.float32(np.nan)).astype(np.float32)
    return result


_NEIGHBOURHOOD = np.ones((3, 3), np.uint8)


def invalidate_depth_edges(disparity: F32, max_range_px: float) -> F32:
    """NaN where the 3×3 neighbourhood spans more than ``max_range_px`` of disparity.

    At a depth discontinuity block matching returns mixed foreground/background values ("flying
    pixels") and fattens the foreground; they would put obstacles in the floor around every object.
    Dropping them costs a pixel of coverage each side of an edge, and the cell stays unknown rather
    than wrong. ``max_range_px <= 0`` disables the filter.
    """
    if max_range_px <= 0:
        return disparity
    invalid = np.isnan(disparity)
    highest = cv2.dilate(np.where(invalid, -np.inf, disparity).astype(np.float32), _NEIGHBOURHOOD)
    lowest = cv2.erode(np.where(invalid, np.inf, disparity).astype(np.float32), _NEIGHBOURHOOD)
    filtered = disparity.copy()
    with np.errstate(over="ignore", invalid="ignore"):  # all-invalid neighbourhoods: -inf - inf
        filtered[highest - lowest > max_range_px] = np.nan
    return filtered


class DisparityChain:
    """The configured depth chain on rectified images: matcher, then each optional stage.

    One object per search band, so the matcher is made once; :func:`compute_disparity` is the same
    chain for callers that run it once (bench/stereo_real.py)."""

    def __init__(self, config: MatcherConfig, min_disparity: int, num_disparities: int) -> None:
        self.config = config
        self.min_disparity = min_disparity
        self.matcher = make_matcher(config, min_disparity, num_disparities)

    def __call__(self, left_gray: U8, right_gray: U8) -> F32:
        disparity = disparity_px(self.matcher, left_gray, right_gray, self.min_disparity)
        if self.config.subpixel:
            disparity = refine_subpixel(left_gray, right_gray, disparity)
        return invalidate_depth_edges(disparity, self.config.edge_filter_px)


def compute_disparity(
    left_gray: U8, right_gray: U8, min_disparity: int, num_disparities: int, config: MatcherConfig
) -> F32:
    """Disparity in pixels of a rectified pair (float32, NaN where invalid), exactly as the depth
    service computes it."""
    return DisparityChain(config, min_disparity, num_disparities)(left_gray, right_gray)
