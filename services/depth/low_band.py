"""Low raised surfaces measured again at full resolution.

A EUR pallet's deck is 14 cm up: at half resolution, 6 m below the cameras, half a pixel of
disparity above the floor, and the matcher's 3-px windows straddle its boards and the floor seen
between them (on ``--seed 1`` its deck read 9 cm at the median, two thirds of it under the obstacle
band: free). At full resolution the deck is a pixel above the floor and a board is 9–13 px wide.

Where the half-resolution chain read a low raised surface (:data:`RAISED_MIN_M` to
:data:`LOW_BAND_TOP_M` above the floor, in regions of at least :data:`MIN_REGION_PX`), the
full-resolution images are matched again over that region's box only and over a band of
disparities only that deep; each low half-resolution reading in the box (those under the raised
band too: a deck's boards the matcher read a few centimetres up) takes the mean of the
full-resolution pixels it covers when they agree with it within :data:`AGREE_PX` (a board read
right at the floor, 0.55 px below the deck, stays). The half-resolution reading chooses *where*
(anything taller is out of the fine search's band), the full-resolution one says *how high*.
Pure OpenCV/numpy, no I/O: the depth pipeline owns one per pair.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from common.arrays import F32, U8
from common.camera import StereoCalibration
from services.depth.floor_geometry import FloorGeometry
from services.depth.stereo import DisparityChain, MatcherConfig, Rectifier

RAISED_MIN_M = 0.05
LOW_BAND_TOP_M = 0.4
"""Readings between these heights are measured again (the floor itself is not: it gains nothing)."""
SEARCH_MARGIN_M = 0.15
"""The fine search reaches this far below the floor and above the band's top."""
MIN_REGION_PX = 150
"""Smaller regions of low raised readings (processing pixels, after a closing that joins a deck's
boards) are noise or an edge's fringe, not a surface (a pallet is 2000; 150 is 0.07 m²)."""
CLOSING = np.ones((5, 5), np.uint8)
TEXTURE_ENERGY = 1.0
"""A low raised reading is matched again only where the half-resolution left image has x-gradient
energy (gray levels² per pixel², 5 × 5) above this: on a plain floor the matcher's interpolation
reads low raised surfaces over most of the image, and no finer match can measure untextured paint
(it cost 37–46 ms a frame there)."""
REGION_PAD_PX = 4
"""Each region is matched with this margin around it (processing pixels)."""
AGREE_PX = 0.5
"""The fine reading replaces the coarse one within this (processing pixels, 13 cm at the floor):
beyond, the fine search matched something out of its band."""
BLOCK_RANGE_PX = 1.0
"""Full-resolution pixels of one processing pixel spanning more than this (full pixels) straddle an
edge: their mean is no surface, the coarse reading stays."""


class LowBand:
    """The full-resolution rectifier and narrow-band chain of one pair, and the band's bounds at
    every processing pixel (from ``geometry``, the processing resolution's floor geometry)."""

    def __init__(
        self,
        calib: StereoCalibration,
        downscale: int,
        matcher: MatcherConfig,
        geometry: FloorGeometry,
    ) -> None:
        self.downscale = downscale
        self.raised_px, self.low_px = (
            geometry.disparity_px(np.full(geometry.ray_down.shape, height_m, np.float32))
            for height_m in (RAISED_MIN_M, LOW_BAND_TOP_M)
        )
        """The disparities of RAISED_MIN_M and LOW_BAND_TOP_M at each pixel."""
        self.calibrated_rectifier = Rectifier.from_calibration(calib, 1)
        self.rectifier = self.calibrated_rectifier
        min_disparity, num_disparities = self.rectifier.disparity_band(
            -SEARCH_MARGIN_M, LOW_BAND_TOP_M + SEARCH_MARGIN_M
        )
        # Regions are small and padded on the left for the search: no full-width padding, and no
        # guided median (its cost is per pixel, its gain at depth edges these regions avoid).
        lean = dataclasses.replace(matcher, full_width=False, guided_median_px=0)
        self.chain = DisparityChain(lean, min_disparity, num_disparities)
        self.search_px = min_disparity + num_disparities
        self.min_rows = 4 * max(5, matcher.block_size)
        """A region is matched over at least this many rows (StereoBM refuses fewer than its block)."""
        self.regions = 0
        """Regions matched again in the last frame."""

    def align_rows(self, row_offset_px: F32) -> None:
        """Rectify with the floor model's row offset (``row_offset_px`` at the processing
        resolution, as :meth:`DepthPipeline._align_rows` applies it there): the same offset in
        full-resolution pixels."""
        width, height = self.calibrated_rectifier.size
        full_px = cv2.resize(row_offset_px, (width, height), interpolation=cv2.INTER_LINEAR)
        self.rectifier = self.calibrated_rectifier.with_row_offset(
            (full_px * np.float32(self.downscale)).astype(np.float32)
        )

    def refine(
        self,
        left_gray: U8,
        right_gray: U8,
        left_rect: U8,
        coarse_px: F32,
        offset_px: F32 | float,
    ) -> F32:
        """``coarse_px`` (processing pixels, of the rectified ``left_rect``) with its low raised
        readings on texture (RAISED_MIN_M to LOW_BAND_TOP_M up, their disparities shifted by
        ``offset_px``, the matcher's offset on the floor) measured again on the full-resolution
        images."""
        raised_px, low_px = self.raised_px + offset_px, self.low_px + offset_px
        gradient = cv2.Sobel(left_rect, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
        textured = cv2.blur(gradient * gradient, (5, 5)) >= TEXTURE_ENERGY
        with np.errstate(invalid="ignore"):
            raised = (textured & (coarse_px >= raised_px) & (coarse_px <= low_px)).view(np.uint8)
        joined = cv2.morphologyEx(raised, cv2.MORPH_CLOSE, CLOSING)
        count, _labels, stats, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
        boxes = [stats[k] for k in range(1, count) if stats[k][cv2.CC_STAT_AREA] >= MIN_REGION_PX]
        self.regions = len(boxes)
        if not boxes:
            return coarse_px
        s = self.downscale
        height, width = coarse_px.shape
        fine = np.full((height * s, width * s), np.nan, np.float32)
        for x, y, w, h, _area in boxes:
            x0, y0 = max(0, x - REGION_PAD_PX) * s, max(0, y - REGION_PAD_PX) * s
            x1 = min(width, x + w + REGION_PAD_PX) * s
            y1 = min(height, y + h + REGION_PAD_PX) * s
            short = self.min_rows - (y1 - y0)  # a strip at the image's edge: the matcher's block
            if short > 0:
                y0 = max(0, y0 - short)
                y1 = min(height * s, y0 + self.min_rows)
            fine[y0:y1, x0:x1] = self._match(left_gray, right_gray, (x0, y0, x1, y1))
        # The rectified grids are consistent (pixel centres): processing pixel (u, v) is covered
        # by full-resolution pixels s·u … s·u + s − 1 (and rows alike). NaN anywhere: no mean.
        # (Strided views, not a reduction over a reshape's inner axes: 7× faster.)
        covering = [fine[i::s, j::s] for i in range(s) for j in range(s)]
        spread = np.maximum.reduce(covering) - np.minimum.reduce(covering)
        mean_px = (np.add.reduce(covering) / np.float32(s * s * s)).astype(np.float32)
        with np.errstate(invalid="ignore"):
            # Every low reading in a matched region, not only the raised ones (a deck's boards
            # the coarse reading put a few centimetres up): the fine one lifts them.
            replace = (
                (coarse_px <= low_px)
                & (spread <= BLOCK_RANGE_PX)
                & (np.abs(mean_px - coarse_px) <= AGREE_PX)
            )
        return np.where(replace, mean_px, coarse_px).astype(np.float32)

    def _match(self, left_gray: U8, right_gray: U8, box: tuple[int, int, int, int]) -> F32:
        """Full-resolution disparity over ``box`` (x0, y0, x1, y1): the region's rows of both
        images rectified, matched from ``search_px`` columns further left."""
        x0, y0, x1, y1 = box
        start = max(0, x0 - self.search_px)
        left_rect, right_rect = self.rectifier.rectify_region(
            left_gray, right_gray, (start, y0, x1, y1)
        )
        # The matcher leaves its first search_px columns invalid: those before x0, or the image's
        # own left margin.
        region: F32 = self.chain(left_rect, right_rect)[:, x0 - start :]
        return region
