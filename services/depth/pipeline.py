"""Frame → tile for one pair, with per-stage times. Everything per calibration is done once here,
but for the right image's rectification, moved by the row offset the floor model fits (a few times
after start-up, and when the fit moves by the maps' resolution).

Stages (their names are the tile's ``stage_ms`` keys): ``rectify``, ``disparity`` (the matcher and
its optional stages, then low raised surfaces measured again at full resolution, see
:mod:`services.depth.low_band`), ``floor`` (the fixed-camera floor model: fattening removed, floor
observations where stereo has none, see :mod:`services.depth.floor_model`), ``projection``,
``model``."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from common.camera import StereoCalibration
from common.lattice import check_resolution
from common.sensor_model import SensorModelParams
from services.depth.floor_config import FloorModelConfig
from services.depth.floor_geometry import FloorGeometry
from services.depth.floor_model import FloorModel
from services.depth.inverse_model import Tile, build_tile, thin_band_points
from services.depth.low_band import LowBand
from services.depth.object_edges import ImageView, refine_on_edges
from services.depth.objects import Detection, PixelGrid, detect_objects
from services.depth.projection import WorldPoints, project_to_world
from services.depth.stereo import DisparityChain, MatcherConfig, Rectifier

SEARCH_MARGIN_M = 0.15
"""Search a little below the floor and above the band's top so their disparities are not clipped."""
VIEW_EDGE_SHARE = 0.05
"""Pixels this share of the image's shorter side from the edge of what the matcher measures may
see a surface whose top is out of the view (a wall's foot, a shelf cut by the border): the tile
judges their points as side faces without a top above them (``build_tile``'s
``top_out_of_view``). Offline, thirteen scenes (20 s): IoU +0.0002 to +0.0059 (default +0.0046),
false-free within 0.01 points; 0.025 gained a little less, 0.1 as much; asking no pixel for a top
−0.004 to +0.002 against 0.05, false-free up to 0.05 points more."""


def view_edge(shape_px: tuple[int, int], left_margin_px: int) -> npt.NDArray[np.bool_]:
    """The pixels within ``VIEW_EDGE_SHARE`` of the edge of what the matcher measures: the image's
    border, and on the left the columns it has no disparity for (``left_margin_px``)."""
    rows, cols = shape_px
    band = max(1, round(VIEW_EDGE_SHARE * min(rows, cols)))
    edge = np.ones(shape_px, np.bool_)
    edge[band : rows - band, left_margin_px + band : cols - band] = False
    return edge


TUNED_SIZE_PX = (320, 240)
"""The processing resolution the matcher's and the floor model's windows (in pixels) are tuned for:
640 × 480 cameras at the default ``--downscale 2``. Below it the map is coarse and mostly unknown
(offline, default scene, 8 s: 320 × 240 cameras at ``--downscale 2`` gave IoU 0.39 with 58 % of
the seen floor unknown, against 0.86 and 4 % at 640 × 480; at ``--downscale 1``, 0.52 and 21 %,
with 8.8 % of the objects' cells free)."""


def undersampled(image_size_px: tuple[int, int], downscale: int) -> str | None:
    """Why cameras of ``image_size_px`` (width, height) processed at 1/``downscale`` give a poor
    map, or None: said once at start-up, as nothing else tells a site why its map is mostly
    unknown. Both the cameras' pixels and those processed count (half of TUNED_SIZE_PX's, or
    more, each): 320 × 240 cameras mapped poorly at ``--downscale 1`` too."""
    tuned_width, tuned_height = TUNED_SIZE_PX
    tuned_px = tuned_width * tuned_height
    width, height = image_size_px
    if width * height < 2 * tuned_px:  # a quarter of 640 × 480's 4 × tuned_px, measured poor
        return (
            f"the cameras' images are {width}×{height} px, under half the pixels of the "
            f"{2 * tuned_width}×{2 * tuned_height} overgrid is tuned for: expect a coarse map, "
            f"much of it unknown (cameras of {2 * tuned_width}×{2 * tuned_height} px or more)"
        )
    if (width // downscale) * (height // downscale) < tuned_px // 2:
        return (
            f"images are processed at {width // downscale}×{height // downscale} px "
            f"(--downscale {downscale}), under half the pixels of the {tuned_width}×"
            f"{tuned_height} overgrid is tuned for: expect a coarse map, much of it unknown "
            "(--downscale 2)"
        )
    return None


@dataclass(frozen=True)
class PipelineConfig:
    resolution_m: float = 0.05
    downscale: int = 2
    matcher: MatcherConfig = field(default_factory=MatcherConfig)
    model: SensorModelParams = field(default_factory=SensorModelParams)
    min_cell_pixels: int = 3
    floor: FloorModelConfig = field(default_factory=FloorModelConfig)
    low_band: bool = True
    """Measure low surfaces again at full resolution (:mod:`services.depth.low_band`)."""


@dataclass(frozen=True)
class FrameResult:
    tile: Tile
    points: WorldPoints
    disparity_px: npt.NDArray[np.float32]
    """The disparity chain's own output (what stereo measured)."""
    stage_ms: dict[str, float]
    evidence_disparity_px: npt.NDArray[np.float32]
    """What the tile was built from: ``disparity_px`` under the floor model's evidence rules."""
    left_rect: npt.NDArray[np.uint8]
    """The rectified left image (objects' outlines are refined on it)."""


def to_gray(image: np.ndarray) -> npt.NDArray[np.uint8]:
    if image.dtype != np.uint8:
        raise ValueError(f"image dtype is {image.dtype}, expected uint8")
    if image.ndim == 3 and image.shape[2] == 3:
        return np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    if image.ndim != 2:
        raise ValueError(f"image shape {image.shape} is neither H×W gray nor H×W×3 colour")
    return image


SWAP_MIN_TEXTURED = 0.05
"""A swap is judged only where at least this share of the view has texture in both images …"""
SWAP_MIN_AGREEMENT = 0.002
SWAP_RATIO = 5.0
"""… and the floor agrees in the other order over SWAP_RATIO times the share it does in this one
(and SWAP_RATIO times SWAP_MIN_AGREEMENT at least)."""

ROW_ALIGN_STEP_PX = 1.0 / 32.0
"""The rectifiers are aligned again once the fitted row offset has moved this far somewhere: the
resolution of OpenCV's fixed-point maps. Each time costs 0.6 ms at the processing resolution and
2–3 ms at full (the low band's); over 30 s of the default scene (four pairs, 60 fits in all) they
were rebuilt 21 times (at 1/64 px and with an earlier form of the fit, 41: ``bench/floor_model.py``,
the ``floor`` stage)."""


class DepthPipeline:
    def __init__(self, calib: StereoCalibration, config: PipelineConfig) -> None:
        check_resolution(config.resolution_m)
        self.calib = calib
        self.config = config
        self.calibrated_rectifier = Rectifier.from_calibration(calib, config.downscale)
        """The calibration's rectification; :attr:`rectifier` adds the fitted row offset."""
        self.rectifier = self.calibrated_rectifier
        self.rays_world = self.rectifier.pixel_rays_world()
        floor_depth_m = -self.rectifier.C_world[2] / self.rays_world[2]
        self.floor_xy_m = (
            self.rectifier.C_world[:2, None, None] + floor_depth_m * self.rays_world[:2]
        ).astype(np.float32)
        """Where each pixel's ray meets the floor (2 × H × W): the floor cell a hidden pixel
        speaks for (the cameras never move, so once)."""
        self.meets_floor = (np.isfinite(floor_depth_m) & (floor_depth_m > 0)).ravel()
        """Per pixel (flat): its ray meets the floor ahead; only those can hide it."""
        self.image_view = ImageView(
            self.rectifier.focal_px,
            self.rectifier.cx_px,
            self.rectifier.cy_px,
            self.rectifier.R_world_rect,
            self.rectifier.C_world,
        )
        self.min_disparity, self.num_disparities = self.rectifier.disparity_band(
            -SEARCH_MARGIN_M, config.model.obstacle_max_m + SEARCH_MARGIN_M
        )
        self.disparity_chain = DisparityChain(
            config.matcher, self.min_disparity, self.num_disparities
        )
        geometry = FloorGeometry.from_rectifier(self.rectifier, self.rays_world)
        self.floor_model = (
            FloorModel(
                geometry,
                (config.model.obstacle_min_m, config.model.obstacle_max_m),
                config.floor,
            )
            if config.floor.enabled
            else None
        )
        self.left_margin_px = self.min_disparity + self.num_disparities
        """Columns on the left the matcher has no disparity for (the right image holds no match)."""
        self.top_out_of_view = view_edge(self.rays_world.shape[1:], self.left_margin_px).ravel()
        """Per pixel (flat): at the edge of the view, where a surface may rise out of it."""
        self.low_band = (
            LowBand(calib, config.downscale, config.matcher, geometry)
            if config.low_band and config.downscale > 1
            else None
        )

    def _align_rows(self, floor_model: FloorModel) -> None:
        """Rectify the next frames with the row offset the floor model has fitted (the matcher
        and the low band alike), whenever the fit has moved."""
        coef = floor_model.residual_coef[1]
        # |Δa| + |Δb| + |Δc| bounds the offset's change anywhere (u', v' in [-1, 1]).
        if float(np.abs(coef - floor_model.aligned_row_coef).sum()) < ROW_ALIGN_STEP_PX:
            return
        floor_model.aligned_row_coef = coef.copy()
        offset_px = floor_model.row_offset_px
        self.rectifier = self.calibrated_rectifier.with_row_offset(offset_px)
        if self.low_band is not None:
            self.low_band.align_rows(offset_px)

    def check_frame(self, left: np.ndarray, right: np.ndarray) -> None:
        width, height = self.calib.image_size
        for side, image in (("left", left), ("right", right)):
            if image.shape[:2] != (height, width):
                raise ValueError(
                    f"{side} image of pair {self.calib.pair} is {image.shape[1]}×{image.shape[0]}, "
                    f"calibration says {width}×{height}"
                )

    def process(self, left: np.ndarray, right: np.ndarray) -> FrameResult:
        self.check_frame(left, right)
        times = [time.perf_counter()]
        left_gray, right_gray = to_gray(left), to_gray(right)
        left_rect, right_rect = self.rectifier.rectify(left_gray, right_gray)
        times.append(time.perf_counter())
        disparity = self.disparity_chain(left_rect, right_rect)
        if self.low_band is not None:
            # The band as the matcher reads it (its fitted offset on the floor).
            offset = 0.0 if self.floor_model is None else self.floor_model.matcher_offset_px
            disparity = self.low_band.refine(left_gray, right_gray, left_rect, disparity, offset)
        times.append(time.perf_counter())
        evidence = disparity
        if self.floor_model is not None:
            evidence = self.floor_model.update(left_rect, right_rect, disparity)
            self._align_rows(self.floor_model)
        times.append(time.perf_counter())
        valid_px = np.flatnonzero(np.isfinite(evidence))  # the points' pixels, in their order
        points = project_to_world(
            evidence,
            self.rays_world,
            self.rectifier.C_world,
            self.rectifier.focal_px,
            self.rectifier.baseline_m,
            self.config.model,
            self.config.downscale,
        )
        times.append(time.perf_counter())
        tile = build_tile(
            points,
            self.config.resolution_m,
            self.config.model,
            self.config.min_cell_pixels,
            self._hidden_floor_xy(valid_px, points),
            self.camera_m,
            self.top_out_of_view[valid_px],
            None if self.floor_model is None else self.floor_model.inferred.ravel()[valid_px],
            thin_band_points(
                valid_px, points.height_m, evidence.shape, self.config.model.obstacle_min_m
            ),
        )
        times.append(time.perf_counter())
        # "disparity" is the whole chain: matcher and its optional stages (stereo.DisparityChain).
        names = ("rectify", "disparity", "floor", "projection", "model")
        stage_ms = {
            name: (b - a) * 1e3
            for name, a, b in zip(names, times[:-1], times[1:], strict=True)
            if name != "floor" or self.floor_model is not None
        }
        return FrameResult(
            tile=tile,
            points=points,
            disparity_px=disparity,
            stage_ms=stage_ms,
            evidence_disparity_px=evidence,
            left_rect=left_rect,
        )

    def swapped(self, left: np.ndarray, right: np.ndarray) -> str | bool | None:
        """Why ``left`` and ``right`` look swapped (the images, or the calibration's cameras):
        the floor agrees at its disparity in the other order and not in this one; False when they
        do not; None when this frame cannot tell (no floor model, or too little texture: a dark
        first frame). A recording played with its folders swapped gave a map of phantom
        obstacles and exit 0."""
        if self.floor_model is None:
            return None
        agreements = []
        for first, second in ((left, right), (right, left)):
            rectified = self.rectifier.rectify(to_gray(first), to_gray(second))
            agreements.append(self.floor_model.floor_agreement(*rectified))
        (textured, given), (_, other) = agreements
        if textured < SWAP_MIN_TEXTURED:
            return None
        if other < SWAP_RATIO * max(given, SWAP_MIN_AGREEMENT):
            return False
        return (
            f"the floor matches with left and right the other way round ({other:.1%} of the "
            f"textured view against {given:.1%}): are the left and right images, or the "
            "calibration's left and right cameras, swapped?"
        )

    def _hidden_floor_xy(
        self, valid_px: npt.NDArray[np.intp], points: WorldPoints
    ) -> npt.NDArray[np.float32]:
        """Floor points (2 × N) this frame does not see: those of the pixels that measure something
        standing (their ray stops above the floor), and those the floor model finds hidden."""
        # Points are the finite pixels in row order; index the few standing ones only (indexing
        # both floor planes by the whole mask cost 1 ms a frame).
        standing = valid_px[points.height_m >= self.config.model.obstacle_min_m]
        if self.floor_model is not None:
            standing = np.concatenate([standing, np.flatnonzero(self.floor_model.hidden)])
        standing = standing[self.meets_floor[standing]]
        hidden: npt.NDArray[np.float32] = self.floor_xy_m.reshape(2, -1)[:, standing]
        return hidden

    def detect_objects(self, result: FrameResult) -> list[Detection]:
        """The frame's objects: measured on its points (objects.detect_objects), each outline but
        a low object's then refined on the left image's edges (object_edges.refine_on_edges)."""
        rectifier = self.rectifier
        found = detect_objects(
            result.points,
            PixelGrid.from_valid(np.isfinite(result.evidence_disparity_px)),
            camera_height_m=float(rectifier.C_world[2]),
            pixel_angle_rad=1.0 / rectifier.focal_px,
            left_margin_px=self.left_margin_px,
            params=self.config.model,
            baseline_yaw_rad=rectifier.baseline_yaw_rad,
        )
        return refine_on_edges(found, result.left_rect, self.image_view)

    @property
    def camera_m(self) -> tuple[float, float, float]:
        """Where the camera the points are measured from stands (world x, y, z): sent with the
        frame's objects (``DetectionsHeader.camera_m``)."""
        x, y, z = (float(v) for v in self.rectifier.C_world)
        return x, y, z

    def floor_health(self) -> dict[str, object]:
        """The floor model's state for ``depth/{pair}/health``."""
        model = self.floor_model
        if model is None:
            return {"state": "off"}
        return {
            "state": model.state(),
            "modelled_share": round(model.modelled_share(), 4),
            "frames": model.frames,
            "relearned": model.relearned,
            "blank_frames": model.blank_frames,
            "restarted_px": model.restarted,
            "disagreed_px": model.disagreed,
            "disparity_offset_px": round(float(model.residual_coef[0, 0]), 3),
            "row_offset_px": round(float(model.residual_coef[1, 0]), 3),
            "matcher_offset_px": round(float(model.matcher_offset_coef[0]), 3),
        }
