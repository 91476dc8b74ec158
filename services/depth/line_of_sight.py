"""Line of sight over the floor: the pixels whose ray passes through the column under a measured
obstacle point, and the closed runs outward of a top's edge, on polar bins about the nadir."""

from __future__ import annotations

import math
from typing import TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from common.arrays import F32, U8, Mask
from common.compiled import compiled

ScalarT = TypeVar("ScalarT", np.uint8, np.float32)
LINE_OF_SIGHT_MARGIN_PX = 1.5
"""An obstacle's foot within this of a pixel does not block it (the floor at an object's base)."""
LINE_OF_SIGHT_BIN_PX = 2.0
"""Polar bins of the line-of-sight test, in radius and in arc at the image's rim."""


class LineOfSight:
    """Pixels whose ray to the floor passes through the column under a measured obstacle point.

    A vertical segment (an obstacle point and the floor below it) images as a segment toward the
    nadir: from the point's pixel inward to its foot, at a radius (1 − h/C_z) times the point's
    from the nadir. In polar coordinates about the nadir that is a run along the radius, so "is any
    column over me" is a cumulative minimum of the feet's radii from the rim inward.
    """

    def __init__(self, shape: tuple[int, int], nadir_px: tuple[float, float]) -> None:
        height, width = shape
        cx, cy = nadir_px
        corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], np.float64)
        max_radius = float(np.max(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy)))
        step = LINE_OF_SIGHT_BIN_PX
        radii = max(2, math.ceil(max_radius / step))
        angles = max(8, math.ceil(2 * math.pi * max_radius / step))
        # Rows run from the rim inward, so the cumulative minimum runs down the rows.
        radius = (np.arange(radii, dtype=np.float64)[::-1] * step)[:, None]
        theta = np.linspace(0, 2 * math.pi, angles, endpoint=False, dtype=np.float64)[None, :]
        self._to_polar = (
            (cx + radius * np.cos(theta)).astype(np.float32),
            (cy + radius * np.sin(theta)).astype(np.float32),
        )
        self._inner_radius = np.ascontiguousarray(
            np.broadcast_to((radius - LINE_OF_SIGHT_MARGIN_PX).astype(np.float32), (radii, angles))
        )
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        self.pixel_radius_px = np.hypot(u - cx, v - cy).astype(np.float32)
        back_theta = np.mod(np.arctan2(v - cy, u - cx), 2 * math.pi)
        self._from_polar = (
            np.mod(np.round(back_theta * angles / (2 * math.pi)), angles).astype(np.float32),
            (radii - 1 - np.minimum(np.round(self.pixel_radius_px / step), radii - 1)).astype(
                np.float32
            ),
        )
        self._spread = np.ones((2 * math.ceil(step) + 1,) * 2, np.uint8)
        no_runs = np.zeros((1, 1), np.uint8)
        _top_runs(no_runs, no_runs, 1, 1, no_runs)  # compiled (or loaded) now, not in a frame

    def top_runs(self, start: Mask, passable: Mask, reach_px: float, grace_px: float) -> Mask:
        """Pixels on a closed run of ``passable`` ones outward (away from the nadir) of a ``start``
        pixel: one that ends within ``reach_px`` at pixels that are not passable or at the image's
        edge (an open run is floor, or a top too large to tell from it). The first ``grace_px``
        need not be passable (the start's own window holds texture)."""
        step = LINE_OF_SIGHT_BIN_PX
        polar_start = self._polar(
            np.asarray(cv2.dilate(start.view(np.uint8), self._spread), np.uint8), 0
        )
        polar_passable = self._polar(passable.view(np.uint8), 0)
        runs = np.zeros_like(polar_start)
        _top_runs(polar_start, polar_passable, round(reach_px / step), round(grace_px / step), runs)
        return self._image(runs)

    def blocked(self, foot_radius_px: F32) -> Mask:
        """``foot_radius_px``: per pixel, the radius of its obstacle point's foot (inf: none)."""
        # A minimum over the polar bins' spacing first, so no column falls between two rays.
        polar = self._polar(np.asarray(cv2.erode(foot_radius_px, self._spread), np.float32), np.inf)
        inward = np.minimum.accumulate(polar, axis=0)
        return self._image((inward < self._inner_radius).view(np.uint8))

    def _polar(self, image: npt.NDArray[ScalarT], outside: float) -> npt.NDArray[ScalarT]:
        """``image`` on the polar bins (rows from the rim inward, a column per angle); bins past
        the image's edge take ``outside``."""
        polar: npt.NDArray[ScalarT] = np.asarray(
            cv2.remap(
                image,
                *self._to_polar,
                cv2.INTER_NEAREST,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=outside,
            ),
            image.dtype,
        )
        return polar

    def _image(self, polar: U8) -> Mask:
        """A mask on the polar bins back on the image's pixels."""
        mask: Mask = cv2.remap(polar, *self._from_polar, cv2.INTER_NEAREST) > 0
        return mask


@compiled
def _top_runs(start: U8, passable: U8, reach_bins: int, grace_bins: int, runs: U8) -> None:
    """Per polar column (an angle about the nadir; rows run from the rim inward), from the nadir
    outward: a start opens a run, which goes on over passable bins (any bin for the first
    ``grace_bins``, and a lone other one: sensor noise passes for texture now and then on a plain
    surface) and ends at two others in a row; a run still open after ``reach_bins`` is taken
    back."""
    radii, angles = start.shape
    for angle in range(angles):
        left, grace, first = 0, 0, 0
        for row in range(radii - 1, -1, -1):
            goes_on = passable[row, angle] or (row > 0 and passable[row - 1, angle])
            if start[row, angle]:
                left, grace, first = reach_bins, grace_bins, row - 1
            elif left > 0 and (goes_on or grace > 0):
                runs[row, angle] = 1
                left -= 1
                grace = max(grace - 1, 0)
                if left == 0 and row > 0 and passable[row - 1, angle]:  # it would go on
                    runs[row : first + 1, angle] = 0
            else:
                left = 0
