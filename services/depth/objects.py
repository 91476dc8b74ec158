"""One pair's frame → object detections: oriented footprints measured on the per-pixel world points,
below the lattice's cell size (DESIGN.md, Objects).

Why points, not the raster: a 5 cm cell is 5–16 % of a box's width, and an object's cells come out a
cell too large where a depth edge fattens it. Seen from overhead, an object's top face is the part
measured best: its pixels are the nearest to the cameras and at one height, so points within a
band below the object's top height are its top face; the sides, the fattening at depth edges and
the floor do not reach that band. The rectangle fitted to those points spans pixel centres, which
fall short of the edges by up to half a pixel's footprint (at that height): see
:func:`edge_deficit_m`.

A detection whose pixels reach the edge of what the pair can match (the image border, or the left
margin stereo cannot match) is ``partial``: the object may extend past it, so its size is a lower
bound, never a confident wrong size. Pure numpy + OpenCV (connected components).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from common.arrays import F64
from common.footprints import corners, fit_rectangle, long_side_first, vertices
from common.messages import MAX_DETECTIONS, DetectionRecord, DetectionsHeader
from common.sensor_model import SensorModelParams
from services.depth.projection import WorldPoints


@dataclass(frozen=True)
class DetectionConfig:
    grid_m: float = 0.025
    """Segmentation grid: half a map cell, so objects 0.5 m apart never touch."""
    close_cells: int = 5
    """Gaps up to this many grid cells are closed before labelling (a plain top matches little)."""
    min_points: int = 40
    min_area_m2: float = 0.03
    min_width_m: float = 0.12
    """Narrower blobs are strips along depth edges and floor markings, not objects."""
    low_strip_top_m: float = 0.3
    low_strip_aspect: float = 4.0
    """A blob lower than ``low_strip_top_m`` and this elongated is a floor marking or a shadow's
    edge that stereo lifted off the floor, not an object."""
    low_min_fill: float = 0.35
    """… and one whose closed grid cells cover less than this share of its rectangle is lines, not
    a top (a low object is all top: its points fill its footprint): the feet of two walls where
    they meet at a corner the image cuts, whose L the rectangle spans aslant, or a marking's bend.
    Offline, ten scenes (concrete, plain, plain objects; 4 and 6 pairs; 3487 detections): the low
    detections of objects filled 0.42 (a walking person's legs) to 1.1 of their rectangles, those
    of the walls' corner feet 0.05 to 0.3, a fused track of which spanned 1.9 × 0.8 m of free
    floor that fusion then served unknown."""
    top_band_m: float = 0.06
    """Points this far below an object's top height belong to its top face."""
    top_quantile: float = 0.9
    """An object's top height: this quantile of its points' heights (robust to a few high outliers)."""
    trim_points: int = 3
    """Top-face points trimmed at each end of each axis (stray matches): a few, not a share, since
    pixel centres on a grid are not spread uniformly enough near an edge to undo a share's cut."""
    border_px: int = 2
    """A detection within this many pixels of the image border is partial."""
    low_fattening_px: float = 1.0
    """How far (processed pixels) the matcher carries a low top's disparity over the floor beside
    it, along the baseline only: half its 3-px window (the low band's 5-px window at full
    resolution is the same). A pallet is half a pixel of disparity above the floor, too little for
    the edge filter or the image's edges to put its sides back, so its density's sides stand this
    far out along the baseline. Offline (20 s of the 4-pair scenes, nine pallets measured with
    confidence), their tracks were 4.6 cm too long along the baseline on average (0.5–7.1 cm) and
    0.8 cm across it (−2.2 to +3.0 cm)."""
    margin_slack_px: int = 8
    """…or within this many pixels of the left margin stereo cannot match: measured on the
    simulated site, a top face next to it stays unmatched up to 7 pixels further in."""


@dataclass(frozen=True)
class Detection:
    """An object as one pair's frame shows it: oriented footprint (length ≥ width, yaw of the long
    side in [0, π)), top height, metres."""

    center_xy_m: tuple[float, float]
    length_m: float
    width_m: float
    yaw_rad: float
    top_m: float
    points: int
    partial: bool
    low: bool = False
    """All top (a pallet): its sides are where its points' density halves (:func:`half_density_box`),
    which the image's edges do not improve (:func:`services.depth.object_edges.refine_on_edges`)."""
    outline_m: tuple[tuple[float, float], ...] = ()
    """What of its top the pair saw (:func:`top_outline`): pairs that each see part of it are
    joined on these, not on their rectangles."""
    round: bool = False
    """A round top (its image edges fit a circle better than a rectangle): the footprint is the
    circle of diameter ``length_m``."""


@dataclass(frozen=True)
class PixelGrid:
    """Where each of the frame's points came from: its image row and column (processed image),
    and the image's size. ``WorldPoints`` hold valid pixels only, in row-major order of ``valid``."""

    rows: npt.NDArray[np.intp]
    cols: npt.NDArray[np.intp]
    shape: tuple[int, int]

    @staticmethod
    def from_valid(valid: npt.NDArray[np.bool_]) -> PixelGrid:
        rows, cols = np.nonzero(valid)
        return PixelGrid(rows, cols, (int(valid.shape[0]), int(valid.shape[1])))


def edge_deficit_m(edge_m: float, yaw_rad: float, pixel_m: float) -> float:
    """How much shorter than the object its pixel centres span along one axis, across the two
    edges of length ``edge_m`` that end that axis. An edge along the pixel grid (camera axes are
    the world's here) leaves on average half a pixel uncovered on each side, one pixel in all; an
    edge crossing n pixel rows has a pixel centre near it in one of them, so the gap shrinks
    about as 1/(1 + n)."""
    off_axis_rad = abs(((yaw_rad + math.pi / 4) % (math.pi / 2)) - math.pi / 4)
    crossings = edge_m * math.sin(off_axis_rad) / max(pixel_m, 1e-9)
    return pixel_m / (1.0 + crossings)


def half_density_edges_m(along_m: F64, bin_m: float) -> tuple[float, float]:
    """Where the points' density along one axis falls to half of its middle's, at either end:
    the edges of evenly sampled points (interpolated between bins that start half a bin before
    the first point, so a pixel grid's edge, half a pixel past its last centre, needs no deficit),
    past a fringe sparser than that. A low object (a pallet, 14 cm) is half a pixel of disparity
    above the floor, and floor pixels beside a strong edge read that high now and then: a fringe
    5–15 cm wide at a quarter of the deck's density (the default scene's pallet_0 from p2: 1.27 ×
    0.95 m by its extreme points, 1.25 × 0.82 by this; 1.2 × 0.8 true)."""
    first_m, last_m = float(along_m.min()), float(along_m.max())
    start_m = first_m - 1.5 * bin_m  # an empty bin before the first point, and after the last
    edges = start_m + bin_m * np.arange(math.ceil((last_m - start_m) / bin_m) + 3)
    counts = np.histogram(along_m, edges)[0].astype(np.float64)
    centres = (edges[:-1] + edges[1:]) / 2
    quarter_m = (last_m - first_m) / 4
    middle = (centres > first_m + quarter_m) & (centres < last_m - quarter_m)
    level = 0.5 * float(np.median(counts[middle])) if middle.any() else 0.0
    if level <= 0.0:  # too few points for a density: their extremes
        return first_m, last_m
    above = np.flatnonzero(counts >= level)

    def crossing(inner: int, outer: int) -> float:
        outer = min(max(outer, 0), counts.size - 1)
        share = (counts[inner] - level) / max(counts[inner] - counts[outer], 1e-9)
        return float(centres[inner] + (centres[outer] - centres[inner]) * min(max(share, 0.0), 1.0))

    return crossing(int(above[0]), int(above[0]) - 1), crossing(int(above[-1]), int(above[-1]) + 1)


def half_density_box(
    xy_m: F64, center_m: tuple[float, float], yaw_rad: float, pixel_m: float
) -> tuple[float, float, float, float]:
    """Centre and size (along ``yaw_rad``, across it) of the box whose sides lie where the
    points' density halves (:func:`half_density_edges_m`, bins of a pixel's footprint)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    dx, dy = xy_m[:, 0] - center_m[0], xy_m[:, 1] - center_m[1]
    bin_m = max(pixel_m, 0.01)
    low_a, high_a = half_density_edges_m(c * dx + s * dy, bin_m)
    low_b, high_b = half_density_edges_m(-s * dx + c * dy, bin_m)
    mid_a, mid_b = (low_a + high_a) / 2, (low_b + high_b) / 2
    return (
        center_m[0] + c * mid_a - s * mid_b,
        center_m[1] + s * mid_a + c * mid_b,
        high_a - low_a,
        high_b - low_b,
    )


def top_outline(
    xy_m: F64,
    rectangle: tuple[float, float, float, float, float],
    pixel_m: float,
    max_vertices: int = 32,
) -> tuple[tuple[float, float], ...]:
    """The convex hull of a top face's points, grown by half a pixel's footprint (pixel centres
    fall short of the edges) and clipped to the ``rectangle`` fitted to them (centre x, y, length,
    width, yaw; before the image's edges refine it), which has its stray points trimmed. Of a
    view cut by the image's border it is the part seen, where the rectangle is not: the smallest
    rectangle around a box cut aslant lies along the cut (offline, ``--seed 4``: box_0's halves
    1.14 × 0.57 m from one pair, 1.08 × 0.5 from the other; 0.96 × 0.82 true, and 1.25 × 1.2
    around both)."""
    hull = cv2.convexHull(xy_m.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if len(hull) < 3:
        return ()
    centroid = hull.mean(axis=0)
    away = hull - centroid
    hull += 0.5 * pixel_m * away / np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-9)
    cx, cy, length, width, yaw = rectangle
    box = corners((cx, cy), (length, width), yaw)
    area, clipped = cv2.intersectConvexConvex(hull.astype(np.float32), box.astype(np.float32))
    if clipped is None or area <= 0.0:
        return ()
    polygon = clipped.reshape(-1, 1, 2)
    tolerance_m = 0.1 * pixel_m + 1e-3  # vertices a pixel grid's hull has along a straight side
    while len(polygon) > max_vertices:
        polygon = cv2.approxPolyDP(polygon, tolerance_m, closed=True)
        tolerance_m *= 2
    return vertices(polygon.reshape(-1, 2).astype(np.float64)) if len(polygon) >= 3 else ()


def _cut_by_view(
    rows: npt.NDArray[np.intp],
    cols: npt.NDArray[np.intp],
    shape: tuple[int, int],
    left_margin_px: float,
    config: DetectionConfig,
) -> bool:
    """Whether an object's pixels reach the edge of what the pair can match: the image border, or
    the left image's first ``left_margin_px`` columns, whose match would lie left of the right
    image (the floor model may still fill them with floor, so valid pixels do not show it)."""
    height, width = shape
    border = config.border_px
    return bool(
        rows.min() <= border
        or rows.max() >= height - 1 - border
        or cols.min() <= left_margin_px + config.margin_slack_px
        or cols.max() >= width - 1 - border
    )


def detect_objects(
    points: WorldPoints,
    pixels: PixelGrid,
    camera_height_m: float,
    pixel_angle_rad: float,
    left_margin_px: float,
    params: SensorModelParams,
    baseline_yaw_rad: float,
    config: DetectionConfig = DetectionConfig(),
) -> list[Detection]:
    """Objects of one frame. ``pixel_angle_rad``: the angle one processed pixel subtends (its
    footprint at distance d is d·angle, the focal length is its inverse); ``camera_height_m``: the
    pair's height above the floor; ``left_margin_px``: the left image's columns the disparity
    search cannot match (its highest disparity); ``baseline_yaw_rad``: the direction on the floor
    of the rectified images' rows (the baseline), along which the matcher fattens."""
    band_floor = params.obstacle_min_m
    band = (points.height_m >= band_floor) & (points.height_m <= params.obstacle_max_m)
    if np.count_nonzero(band) < config.min_points:
        return []
    x, y = points.x_m[band].astype(np.float64), points.y_m[band].astype(np.float64)
    height = points.height_m[band].astype(np.float64)
    rows, cols = pixels.rows[band], pixels.cols[band]
    i = np.floor(x / config.grid_m).astype(np.int64)
    j = np.floor(y / config.grid_m).astype(np.int64)
    i0, j0 = int(i.min()), int(j.min())
    occupied = np.zeros((int(j.max()) - j0 + 1, int(i.max()) - i0 + 1), np.uint8)
    occupied[j - j0, i - i0] = 1
    # Close gaps (unmatched pixels across a plain top) before labelling.
    kernel = np.ones((config.close_cells, config.close_cells), np.uint8)
    closed = cv2.morphologyEx(occupied, cv2.MORPH_CLOSE, kernel)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(closed, connectivity=8)
    label_of_point = labels[j - j0, i - i0]
    detections = []
    order = np.argsort(label_of_point, kind="stable")
    bounds = np.searchsorted(label_of_point[order], np.arange(1, labels.max() + 2))
    for label, (start, stop) in enumerate(itertools.pairwise(bounds), start=1):
        members = order[start:stop]
        if members.size < config.min_points:
            continue
        if np.unique(i[members] * 1_000_003 + j[members]).size * config.grid_m**2 < (
            config.min_area_m2
        ):
            continue
        top_m = float(np.quantile(height[members], config.top_quantile))
        # A low object (a pallet) is all top: its points' spread is its height noise.
        face_from_m = top_m - config.top_band_m
        low = face_from_m <= 2 * band_floor
        face = members if low else members[height[members] >= face_from_m]
        if face.size < config.min_points // 2:
            continue
        xy = np.column_stack([x[face], y[face]])
        cx, cy, length, width, yaw = fit_rectangle(xy, config.trim_points / face.size)
        pixel_m = max(camera_height_m - top_m, 0.0) * pixel_angle_rad
        if low:  # its sides where its points' density halves, less the matcher's fattening
            cx, cy, length, width = half_density_box(xy, (cx, cy), yaw, pixel_m)
            fattening_m = 2.0 * config.low_fattening_px * pixel_m
            length -= fattening_m * abs(math.cos(yaw - baseline_yaw_rad))
            width -= fattening_m * abs(math.sin(yaw - baseline_yaw_rad))
            length, width, yaw = long_side_first(length, width, yaw)
        else:
            length, width = (
                length + edge_deficit_m(width, yaw, pixel_m),
                width + edge_deficit_m(length, yaw, pixel_m),
            )
        if width < config.min_width_m or (
            top_m < config.low_strip_top_m
            and (
                length > config.low_strip_aspect * width
                or stats[label, cv2.CC_STAT_AREA] * config.grid_m**2
                < config.low_min_fill * length * width
            )
        ):
            continue
        partial = _cut_by_view(rows[members], cols[members], pixels.shape, left_margin_px, config)
        outline = top_outline(xy, (cx, cy, length, width, yaw), pixel_m)
        detections.append(
            Detection(
                center_xy_m=(cx, cy),
                length_m=length,
                width_m=width,
                yaw_rad=yaw,
                top_m=top_m,
                points=int(members.size),
                partial=partial,
                low=low,
                outline_m=outline,
            )
        )
    return detections


def detections_header(
    detections: list[Detection],
    pair: str,
    seq: int,
    stamp_ns: int,
    camera_m: tuple[float, float, float] | None = None,
) -> DetectionsHeader:
    """``depth/{pair}/objects`` of one frame: the tile's pair, seq and capture stamp, and where
    its camera stands; beyond MAX_DETECTIONS objects, those measured from the most points."""
    if len(detections) > MAX_DETECTIONS:
        detections = sorted(detections, key=lambda d: d.points, reverse=True)[:MAX_DETECTIONS]
    return DetectionsHeader(
        pair=pair,
        seq=seq,
        stamp_ns=stamp_ns,
        camera_m=camera_m,
        detections=[
            DetectionRecord(
                center_m=d.center_xy_m,
                size_m=(d.length_m, d.width_m),
                yaw_rad=d.yaw_rad,
                top_m=d.top_m,
                points=d.points,
                partial=d.partial,
                outline_m=d.outline_m,
                round=d.round,
                low=d.low,
            )
            for d in detections
        ],
    )
