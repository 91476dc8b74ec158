"""Rectification (maps computed once per calibration) and SGBM disparity over a search band
derived from the geometry: from the floor's disparity to that of the tallest height of interest."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from common.arrays import F32, F64, U8
from common.camera import StereoCalibration
from common.compiled import compiled


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
    _calibrated_right: tuple[F32, F32, F32, F32]
    """The right camera's maps from the calibration alone (x, y; float) and their change per
    rectified row: what :meth:`with_row_offset` moves along."""

    @staticmethod
    def from_calibration(calib: StereoCalibration, downscale: int = 2) -> Rectifier:
        width, height = calib.image_size
        if width % downscale or height % downscale:
            raise ValueError(
                f"image {width}×{height} is not divisible by downscale {downscale} "
                "(--downscale 1 processes it at full resolution)"
            )
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
                f"pair {calib.pair}: the right camera is to the left of the left camera: swap "
                "them, or, from OpenCV's stereoCalibrate, take the right camera's pose as "
                "T_world_left · inv([R|T]) (R, T map left-camera points into the right camera)"
            )
        maps_left = cv2.initUndistortRectifyMap(
            K1, calib.left.dist_array, R1, P1, size, cv2.CV_16SC2
        )
        maps_right = cv2.initUndistortRectifyMap(
            K2, calib.right.dist_array, R2, P2, size, cv2.CV_16SC2
        )
        calibrated_right = cv2.initUndistortRectifyMap(
            K2, calib.right.dist_array, R2, P2, size, cv2.CV_32FC1
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
            _calibrated_right=(
                *calibrated_right,
                *(np.gradient(m, axis=0).astype(np.float32) for m in calibrated_right),
            ),
        )

    def with_row_offset(self, row_offset_px: F32) -> Rectifier:
        """This rectifier with the right image's row v taken from the calibration's row
        v + ``row_offset_px`` (per rectified pixel). A calibration slightly wrong about the
        cameras' relative pitch or roll leaves the rows a fraction of a pixel apart; along an
        edge at angle θ to the rows the matcher turns an offset δ into a disparity error δ/tan θ
        (0.2 px at 20°: 0.5 px, over 10 cm at the floor, a painted line read as an obstacle).
        The floor model measures the offset on the floor; folded into the maps, it costs no
        extra interpolation of the image. The maps are smooth and the offset a fraction of a
        pixel: a first-order step along the rows is exact to 10⁻⁴ px."""
        width, height = self.size
        if row_offset_px.shape != (height, width):
            raise ValueError(f"row offset is {row_offset_px.shape}, the images {(height, width)}")
        map_x, map_y, x_per_row, y_per_row = self._calibrated_right
        offset = row_offset_px.astype(np.float32)
        moved_x, moved_y = np.multiply(offset, x_per_row), np.multiply(offset, y_per_row)
        moved_x += map_x
        moved_y += map_y
        maps = cv2.convertMaps(moved_x, moved_y, cv2.CV_16SC2)
        return dataclasses.replace(self, _maps_right=maps)

    @property
    def baseline_yaw_rad(self) -> float:
        """The direction on the floor (world yaw) of the rectified rows: the cameras lie apart
        along it, and the matcher's windows run along it."""
        return math.atan2(float(self.R_world_rect[1, 0]), float(self.R_world_rect[0, 0]))

    def rectify(self, left: U8, right: U8) -> tuple[U8, U8]:
        width, height = self.size
        return self.rectify_region(left, right, (0, 0, width, height))

    def rectify_region(self, left: U8, right: U8, box: tuple[int, int, int, int]) -> tuple[U8, U8]:
        """The rectified images over ``box`` (x0, y0, x1, y1) of the rectified grid only."""
        if self.downscale != 1:
            # INTER_AREA first: remapping a full-resolution image at half density would alias.
            left = np.asarray(cv2.resize(left, self.size, interpolation=cv2.INTER_AREA))
            right = np.asarray(cv2.resize(right, self.size, interpolation=cv2.INTER_AREA))
        x0, y0, x1, y1 = box
        region = (slice(y0, y1), slice(x0, x1))
        return (
            np.asarray(
                cv2.remap(
                    left, self._maps_left[0][region], self._maps_left[1][region], cv2.INTER_LINEAR
                ),
                dtype=np.uint8,
            ),
            np.asarray(
                cv2.remap(
                    right,
                    self._maps_right[0][region],
                    self._maps_right[1][region],
                    cv2.INTER_LINEAR,
                ),
                dtype=np.uint8,
            ),
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


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid", allow_inf_nan=False))
class MatcherConfig:
    """The stereo matcher and its optional stages, declared once (the depth settings nest them as
    ``--matcher.*``)."""

    algorithm: Literal["sgbm", "bm"] = Field(default="sgbm", description="stereo matcher")
    block_size: int = Field(default=3, ge=1, le=21, description="matcher block size (odd)")
    uniqueness_ratio: int = Field(
        default=10, ge=0, le=100, description="matcher uniqueness ratio, %"
    )
    speckle_window: int = Field(
        default=100, ge=0, le=100_000, description="largest speckle removed, px (0: off)"
    )
    speckle_range: int = Field(
        default=2, ge=0, le=1000, description="disparity range within a speckle, px"
    )
    full_width: bool = Field(default=True, description="match the image's left margin too (padded)")
    """Match the left margin too (:func:`match_full_width`) instead of leaving it invalid."""
    edge_filter_px: float = Field(
        default=1.0,
        ge=0.0,
        description="drop pixels whose 3×3 disparity range exceeds this (0: off)",
    )
    """Drop pixels whose 3×3 disparity range exceeds this (:func:`invalidate_depth_edges`; 0: off)."""
    guided_median_px: int = Field(
        default=7,
        ge=0,
        le=15,
        description="radius of the image-guided weighted median near disparity edges (0: off)",
    )
    """:func:`guided_weighted_median`: near a disparity edge each pixel takes the weighted median of
    its neighbourhood, weighted by grey likeness, so an edge lies where the image's does (the
    matcher's window drags the nearer surface a few pixels over the farther one)."""
    subpixel: bool = Field(
        default=True, description="undo SGBM's pixel locking (equiangular fraction, 5×5 mean)"
    )
    """Sub-pixel disparity free of pixel locking: :func:`equiangular_fraction`, then, after the
    edge filter, a 5×5 :func:`neighbourhood_mean` where the window spans ≤ 0.5 px. The re-mapped
    fraction alone is unbiased but noisy (its slope is 2 near whole pixels): on the renders' flat
    floor it is worse than SGBM's own; a mean of SGBM's own fractions keeps their bias. A wider
    gate (1 px) mixes surfaces 25 cm apart in height at 6 m and blurs object tops. Figures: README
    ("Depth"), bench/stereo_real.py, bench/depth_pipeline.py."""

    def __post_init__(self) -> None:
        if self.block_size % 2 == 0:
            raise ValueError(f"block_size must be odd, got {self.block_size}")


OPTIONAL_STAGES = ("full_width", "guided_median_px", "edge_filter_px", "subpixel")
"""The chain's optional stages: :class:`MatcherConfig` fields that are off at False or 0."""


def stage_variants(configured: MatcherConfig) -> dict[str, MatcherConfig]:
    """What the benches compare: the configured chain, SGBM alone (every optional stage off) and
    the configured chain with each optional stage toggled ("-stage" off, "+stage" on; the edge
    filter's "on" is 1 px, the guided median's GUIDED_MEDIAN_PX)."""
    off = dataclasses.replace(
        configured, full_width=False, guided_median_px=0, edge_filter_px=0.0, subpixel=False
    )
    on = dataclasses.replace(
        configured,
        full_width=True,
        guided_median_px=configured.guided_median_px or GUIDED_MEDIAN_PX,
        edge_filter_px=configured.edge_filter_px or 1.0,
        subpixel=True,
    )
    result = {"configured": configured, "sgbm": off}
    for stage in OPTIONAL_STAGES:
        is_on = getattr(configured, stage) != getattr(off, stage)
        toggled = getattr(off if is_on else on, stage)
        result[("-" if is_on else "+") + stage] = dataclasses.replace(
            configured, **{stage: toggled}
        )
    return result


def make_matcher(
    config: MatcherConfig, min_disparity: int, num_disparities: int
) -> cv2.StereoMatcher:
    """SGBM 3WAY with preFilterCap=63 and P1/P2 ∝ blockSize²: the default preFilterCap=0 locks
    disparities to whole pixels. P1 = 2·bs², P2 = 8·bs² gave the lowest error on object tops at half
    resolution among the settings tried (bench/depth_pipeline.py), at the same speed.
    disp12MaxDiff is left off: 1 gave results identical to off on Middlebury Motorcycle."""
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
        preFilterCap=63,
        uniquenessRatio=config.uniqueness_ratio,
        speckleWindowSize=config.speckle_window,
        speckleRange=config.speckle_range,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


FULL_WIDTH_INSIDE_PX = 4
"""A margin pixel's match must lie this far inside the right image: nearer its edge, the block and
the prefilter see the black band (top errors on the renders' margins 18 → 12 cm; see README)."""


def match_full_width(matcher: Any, left: U8, right: U8, num_disparities: int) -> np.ndarray:
    """The matcher's fixed-point disparity (1/16 px) with the left margin matched as well.

    OpenCV leaves the first minDisparity + numDisparities columns invalid, because there some
    candidate disparities point left of the right image: 17 % of a 320-px image with a 32-px band
    from 21 px. With black columns in front of both images, every pixel whose match can lie inside
    the right image is matched; a match within FULL_WIDTH_INSIDE_PX of the right image's edge (or
    beyond it, in the black band) is dropped. The extra columns cost their share of SGBM's time.
    """
    pad_px = num_disparities - FULL_WIDTH_INSIDE_PX
    pad = ((0, 0), (pad_px, 0))
    raw = np.asarray(matcher.compute(np.pad(left, pad), np.pad(right, pad)))[:, pad_px:]
    # Disparity d at column x matches right column x - d; keep x - d >= FULL_WIDTH_INSIDE_PX.
    limit_16 = (np.arange(raw.shape[1], dtype=np.int32) - FULL_WIDTH_INSIDE_PX) * 16
    raw[raw > limit_16[None, :]] = (matcher.getMinDisparity() - 1) * 16
    return raw


_FRACTION_16 = np.arange(-8, 8, dtype=np.float32) / 16.0
_EQUIANGULAR_LUT = np.zeros(256, np.float32)
_EQUIANGULAR_LUT[:16] = 2.0 * _FRACTION_16 / (1.0 + 2.0 * np.abs(_FRACTION_16))
"""Index: SGBM's fraction in 1/16 px plus 8 (so 8 is a whole pixel)."""
SUBPIXEL_WINDOW_PX = 5
SUBPIXEL_MEAN_RANGE_PX = 0.5
"""0.5 px: 12 cm of height at 6 m, half resolution; 1 px measured 0.6 cm worse on the renders' tops."""


def equiangular_fraction(raw_16: np.ndarray) -> F32:
    """Disparity in pixels from the matcher's fixed-point output (1/16 px), with SGBM's fraction of
    a pixel re-mapped as an equiangular (V) fit would give it: δ = 2f / (1 + 2|f|).

    SGBM fits a parabola to three aggregated costs that are V-shaped near their minimum (absolute
    differences, plus P1 for every pixel of disparity change along a path); a parabola through a V
    of true offset δ puts its vertex at f = δ / (2 − 2|δ|), pulled toward the whole pixel. On
    Middlebury Motorcycle the ground truth's median at each of SGBM's 16 fractions follows this
    curve within 0.02 px (after a constant 0.06 px by which that set's truth and images disagree).
    A table over the 16 fractions: one lookup per pixel.
    """
    offset = np.asarray(raw_16, np.int16) + np.int16(8)
    disparity: F32 = (offset >> 4).astype(np.float32)  # nearest whole pixel (halves up)
    np.bitwise_and(offset, 15, out=offset)
    cv2.add(disparity, cv2.LUT(offset.astype(np.uint8), _EQUIANGULAR_LUT), dst=disparity)
    return disparity


def neighbourhood_mean(disparity: F32, window_px: int, max_range_px: float) -> F32:
    """Each valid pixel replaced by the mean of the valid pixels of its ``window_px`` square, where
    that square spans at most ``max_range_px`` of disparity (elsewhere it keeps its own value, so
    no mean mixes the two sides of a depth edge)."""
    window = (window_px, window_px)
    valid = disparity == disparity  # not NaN
    smooth = (_window_range_px(disparity, np.ones(window, np.uint8)) <= max_range_px) & valid
    # In place where OpenCV allows it: fresh frame-sized arrays cost page faults, not just copies.
    total = _nan_filled(disparity, 0.0)
    cv2.boxFilter(total, -1, window, dst=total, normalize=False)
    count = valid.astype(np.float32)
    cv2.boxFilter(count, -1, window, dst=count, normalize=False)
    cv2.divide(total, count, dst=total)
    result = disparity.copy()
    np.copyto(result, total, where=smooth)
    return result


def _nan_filled(disparity: F32, value: float) -> F32:
    filled = disparity.copy()
    cv2.patchNaNs(filled, value)
    return filled


def _window_range_px(disparity: F32, kernel: U8) -> F32:
    """Highest minus lowest valid (not NaN) disparity in each pixel's window; −inf where none."""
    highest = _nan_filled(disparity, -np.inf)
    cv2.dilate(highest, kernel, dst=highest)
    lowest = _nan_filled(disparity, np.inf)
    cv2.erode(lowest, kernel, dst=lowest)
    cv2.subtract(highest, lowest, dst=highest)
    return highest


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
    spread = _window_range_px(disparity, _NEIGHBOURHOOD)
    filtered = disparity.copy()
    np.copyto(filtered, np.float32(np.nan), where=spread > max_range_px)
    return filtered


GUIDED_MEDIAN_PX = 7
GUIDED_MEDIAN_STEP_PX = 3
"""The median's neighbourhood (15×15 px) is sampled every third pixel each way: 49 samples, the
same maps as every pixel at a fifth of the cost (bench/map_accuracy.py)."""
GUIDED_MEDIAN_GRAY = 6.0
"""Grey levels at which a neighbour's weight falls to exp(−½)."""
_GUIDED_WEIGHTS = np.exp(-0.5 * (np.arange(1024) / 4 / GUIDED_MEDIAN_GRAY) ** 2).astype(np.float32)
"""A neighbour's weight by its grey difference in quarter levels (a table: no exp per sample)."""
GUIDED_MEDIAN_BIN_PX = 0.5
GUIDED_MEDIAN_OUTLIER_PX = 1.0
"""Only pixels whose 7×7 neighbourhood spans more than this are looked at, and of those only the
ones further than this from their median move: surfaces keep their sub-pixel values. (Moving
smaller departures too cleared the lane lines' +0.5 px on the renders but made Motorcycle's
bad-0.5px worse than without the stage: bench/stereo_real.py.)"""
GUIDED_MEDIAN_ZONE_PX = 3


def guided_weighted_median(disparity: F32, left_gray: U8, radius_px: int) -> F32:
    """Near disparity edges, a pixel further than GUIDED_MEDIAN_OUTLIER_PX from the weighted median
    of its neighbourhood's disparities takes that median, each neighbour weighted by how alike its
    grey is to the pixel's (exp(−Δ²/2σ²)): the standard refinement of window stereo (a weighted
    median filter guided by the image, e.g. Ma et al. 2013), which puts a disparity edge on the
    image edge between the two surfaces where the matcher's window had dragged the nearer one
    a few pixels over the farther (a ring of false obstacles around every object)."""
    zone = np.ones((2 * GUIDED_MEDIAN_ZONE_PX + 1,) * 2, np.uint8)
    near_edge = _window_range_px(disparity, zone) > GUIDED_MEDIAN_OUTLIER_PX
    out = disparity.copy()
    _guided_median_kernel(
        disparity,
        left_gray.astype(np.float32),
        near_edge,
        radius_px,
        GUIDED_MEDIAN_STEP_PX,
        _GUIDED_WEIGHTS,
        np.float32(GUIDED_MEDIAN_BIN_PX),
        np.float32(GUIDED_MEDIAN_OUTLIER_PX),
        out,
    )
    return out


@compiled
def _guided_median_kernel(
    disparity: F32,
    gray: F32,
    near_edge: npt.NDArray[np.bool_],
    radius: int,
    step: int,
    weight_of_difference: F32,
    bin_px: np.float32,
    outlier_px: np.float32,
    out: F32,
) -> None:
    """The weighted median of each near-edge pixel by a histogram of its neighbours' disparities
    in bins of ``bin_px`` (O(neighbours + bins), no sort): the median bin's weighted mean."""
    rows, cols = disparity.shape
    reach = radius // step
    samples = (2 * reach + 1) ** 2
    values = np.empty(samples, np.float32)
    weights = np.empty(samples, np.float32)
    bins = 512
    weight_of_bin = np.zeros(bins, np.float32)
    sum_of_bin = np.zeros(bins, np.float32)
    for row in range(rows):
        for col in range(cols):
            own = disparity[row, col]
            if not near_edge[row, col] or np.isnan(own):
                continue
            grey = gray[row, col]
            count = 0
            lowest, highest = own, own
            for dr in range(-reach, reach + 1):
                r = row + dr * step
                if r < 0 or r >= rows:
                    continue
                for dc in range(-reach, reach + 1):
                    c = col + dc * step
                    if c < 0 or c >= cols:
                        continue
                    value = disparity[r, c]
                    if np.isnan(value):
                        continue
                    difference = min(int(abs(gray[r, c] - grey) * 4.0), 1023)
                    values[count] = value
                    weights[count] = weight_of_difference[difference]
                    lowest, highest = min(lowest, value), max(highest, value)
                    count += 1
            if count == 0:
                continue
            used = min(int((highest - lowest) / bin_px) + 1, bins)
            total = np.float32(0.0)
            for k in range(count):
                b = min(int((values[k] - lowest) / bin_px), used - 1)
                weight_of_bin[b] += weights[k]
                sum_of_bin[b] += weights[k] * values[k]
                total += weights[k]
            half, running, median_bin = total * np.float32(0.5), np.float32(0.0), used - 1
            for b in range(used):
                running += weight_of_bin[b]
                if running >= half:
                    median_bin = b
                    break
            median = sum_of_bin[median_bin] / weight_of_bin[median_bin]
            if abs(own - median) > outlier_px:
                out[row, col] = median
            for b in range(used):
                weight_of_bin[b] = 0.0
                sum_of_bin[b] = 0.0


class DisparityChain:
    """The configured depth chain on rectified images: matcher, then each optional stage.

    One object per search band, so the matcher is made once; :func:`compute_disparity` is the same
    chain for callers that run it once (bench/stereo_real.py)."""

    def __init__(self, config: MatcherConfig, min_disparity: int, num_disparities: int) -> None:
        self.config = config
        self.min_disparity = min_disparity
        self.num_disparities = num_disparities
        self.matcher = make_matcher(config, min_disparity, num_disparities)

    def __call__(self, left_gray: U8, right_gray: U8) -> F32:
        if self.config.full_width:
            raw = match_full_width(self.matcher, left_gray, right_gray, self.num_disparities)
        else:
            raw = np.asarray(self.matcher.compute(left_gray, right_gray))
        if self.config.subpixel:
            disparity = equiangular_fraction(raw)
        else:
            disparity = raw.astype(np.float32) * np.float32(1.0 / 16.0)
        np.copyto(disparity, np.float32(np.nan), where=raw < self.min_disparity * 16)
        if self.config.guided_median_px:
            disparity = guided_weighted_median(disparity, left_gray, self.config.guided_median_px)
        disparity = invalidate_depth_edges(disparity, self.config.edge_filter_px)
        if self.config.subpixel:
            disparity = neighbourhood_mean(disparity, SUBPIXEL_WINDOW_PX, SUBPIXEL_MEAN_RANGE_PX)
        return disparity


def compute_disparity(
    left_gray: U8, right_gray: U8, min_disparity: int, num_disparities: int, config: MatcherConfig
) -> F32:
    """Disparity in pixels of a rectified pair (float32, NaN where invalid), exactly as the depth
    service computes it."""
    return DisparityChain(config, min_disparity, num_disparities)(left_gray, right_gray)
