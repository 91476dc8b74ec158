"""Oriented rectangles on the floor (a round one: the circle inscribed in it, as a polygon):
fitting them to points, their corners, overlap, and the lattice cells a convex polygon covers.
Pure numpy: depth measures objects with it, fusion merges, tracks and sweeps them, eval scores
them."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from common.arrays import F64
from common.lattice import Window, cell_center

ANGLE_STEP_RAD = math.radians(1.0)
ANGLE_REFINE_RAD = math.radians(0.1)
COARSE_POINTS = 400

Rectangle = tuple[float, float, float, float, float]
"""(centre x, centre y, length, width, yaw of the long side in [0, π)), metres and radians."""


def fit_rectangle(xy_m: F64, trim: float = 0.0) -> Rectangle:
    """Smallest-area oriented rectangle around the points, after trimming ``trim`` of them at each
    end of each axis (stray matches), scaled back by 1/(1 − 2·trim) as if they spread uniformly."""
    mean = xy_m.mean(axis=0)
    centred = xy_m - mean

    def extents(points: F64, angles: F64) -> tuple[F64, F64, F64, F64, F64]:
        n = len(points)
        k = round(trim * (n - 1))  # order statistics by partition: a sort per angle is 4× slower
        c, s = np.cos(angles), np.sin(angles)
        along = points[:, :1] * c + points[:, 1:] * s
        across = -points[:, :1] * s + points[:, 1:] * c
        lo_a, hi_a = np.partition(along, (k, n - 1 - k), axis=0)[[k, n - 1 - k]]
        lo_b, hi_b = np.partition(across, (k, n - 1 - k), axis=0)[[k, n - 1 - k]]
        return lo_a, hi_a, lo_b, hi_b, (hi_a - lo_a) * (hi_b - lo_b)

    # The orientation from a subsample (every point is not needed to find it), the extents at the
    # refined angles from all points.
    sample = centred[:: max(1, len(centred) // COARSE_POINTS)]
    coarse = np.arange(0.0, np.pi / 2, ANGLE_STEP_RAD)
    best = float(coarse[int(np.argmin(extents(sample, coarse)[4]))])
    fine = best + np.arange(-ANGLE_STEP_RAD, ANGLE_STEP_RAD, ANGLE_REFINE_RAD)
    lo_a, hi_a, lo_b, hi_b, area = extents(centred, fine)
    k = int(np.argmin(area))
    angle = float(fine[k])
    scale = 1.0 / (1.0 - 2.0 * trim)
    size_a, size_b = (hi_a[k] - lo_a[k]) * scale, (hi_b[k] - lo_b[k]) * scale
    mid_a, mid_b = (hi_a[k] + lo_a[k]) / 2, (hi_b[k] + lo_b[k]) / 2
    c, s = math.cos(angle), math.sin(angle)
    cx, cy = mean[0] + c * mid_a - s * mid_b, mean[1] + s * mid_a + c * mid_b
    length, width, yaw = long_side_first(float(size_a), float(size_b), angle)
    return float(cx), float(cy), length, width, yaw


def long_side_first(size_a: float, size_b: float, yaw_rad: float) -> tuple[float, float, float]:
    """(length, width, yaw of the long side in [0, π)) of a rectangle given by its side along
    ``yaw_rad`` and the side across it."""
    if size_b > size_a:
        size_a, size_b, yaw_rad = size_b, size_a, yaw_rad + math.pi / 2
    yaw = yaw_rad % math.pi
    return size_a, size_b, 0.0 if yaw >= math.pi - 1e-9 else yaw


def corners(center_m: tuple[float, float], size_m: tuple[float, float], yaw_rad: float) -> F64:
    """The rectangle's four corners (4, 2), counter-clockwise."""
    half = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64) * np.asarray(size_m) / 2
    return _placed(half, center_m, yaw_rad)


def _placed(local_m: F64, center_m: tuple[float, float], yaw_rad: float) -> F64:
    """Points given along a footprint's yaw and across it (N, 2), in the world."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    rotation = np.array([[c, -s], [s, c]])
    out: F64 = local_m @ rotation.T + np.asarray(center_m)
    return out


ROUND_VERTICES = 32
"""A round footprint's polygon: its sides touch the ellipse (it holds all of it, and reaches
0.5 % of the radius past it between them)."""


def footprint_polygon(
    center_m: tuple[float, float], size_m: tuple[float, float], yaw_rad: float, round_: bool
) -> F64:
    """The rectangle's corners, or for a round footprint the polygon around the ellipse inscribed
    in it (a circle when length = width), counter-clockwise."""
    if not round_:
        return corners(center_m, size_m, yaw_rad)
    angle = np.arange(ROUND_VERTICES) * (2 * math.pi / ROUND_VERTICES)
    around = 1.0 / math.cos(math.pi / ROUND_VERTICES)
    unit = np.column_stack([np.cos(angle), np.sin(angle)])
    return _placed(unit * (around * np.asarray(size_m) / 2), center_m, yaw_rad)


def vertices(polygon_m: F64) -> tuple[tuple[float, float], ...]:
    """A polygon (N, 2) as the messages carry it."""
    return tuple((float(x), float(y)) for x, y in polygon_m)


def polygons_overlap(a: F64, b: F64, gap_m: float = 0.0) -> bool:
    """Whether two convex polygons (N, 2) come within ``gap_m`` of each other (separating axes)."""
    for polygon in (a, b):
        edges = np.roll(polygon, -1, axis=0) - polygon
        normals = np.column_stack([edges[:, 1], -edges[:, 0]])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        pa, pb = a @ normals.T, b @ normals.T
        if np.any(
            (pa.max(axis=0) + gap_m < pb.min(axis=0)) | (pb.max(axis=0) + gap_m < pa.min(axis=0))
        ):
            return False
    return True


def convex_hull(xy_m: F64) -> F64:
    """Counter-clockwise convex hull (Andrew's monotone chain) of a few points."""
    points = sorted({(float(x), float(y)) for x, y in xy_m})
    if len(points) <= 2:
        return np.asarray(points, np.float64)

    def half(sequence: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for p in sequence:
            while (
                len(out) >= 2
                and (
                    (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                    - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])
                )
                <= 0
            ):
                out.pop()
            out.append(p)
        return out

    lower, upper = half(points), half(points[::-1])
    return np.asarray(lower[:-1] + upper[:-1], np.float64)


def polygon_cells(polygon_m: F64, resolution_m: float) -> tuple[Window, npt.NDArray[np.bool_]]:
    """Cells whose centre lies inside a convex counter-clockwise polygon (the rule a map cell is
    judged by), on the smallest window around it."""
    window = Window.covering(
        float(polygon_m[:, 0].min()),
        float(polygon_m[:, 1].min()),
        float(polygon_m[:, 0].max()),
        float(polygon_m[:, 1].max()),
        resolution_m,
    )
    x = cell_center(np.arange(window.i0, window.i1), resolution_m)
    y = cell_center(np.arange(window.j0, window.j1), resolution_m)
    (ax, ay), (bx, by) = (
        corner[:, :, None, None] for corner in (polygon_m.T, np.roll(polygon_m, -1, axis=0).T)
    )
    # Every edge at once (edge, row, col): fusion rasterises some fifty footprints a capture, and
    # a round one has 32 edges.
    cross = (bx - ax) * (y[None, :, None] - ay) - (by - ay) * (x[None, None, :] - ax)
    inside: npt.NDArray[np.bool_] = (cross >= 0).all(axis=0)
    return window, inside
