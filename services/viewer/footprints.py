"""Where each pair sees the floor: the polygon of z = 0 inside both of its images, from the
calibration alone (image corners cast onto the floor plane, the two views intersected). Pure."""

from __future__ import annotations

import numpy as np

from common.camera import PinholeCamera, StereoCalibration

Point = tuple[float, float]
Polygon = list[Point]


def floor_polygon(camera: PinholeCamera) -> Polygon | None:
    """The image's corners cast onto the floor (distortion ignored, as ``project`` does); None when
    a corner's ray never meets the floor (a camera looking at the horizon or up)."""
    w, h = camera.width, camera.height
    corners_px = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], np.float64)
    T = camera.T_world_cam_array
    rays_world = (corners_px @ np.linalg.inv(camera.K_array).T) @ T[:3, :3].T
    eye = T[:3, 3]
    if eye[2] <= 0 or np.any(rays_world[:, 2] >= 0):
        return None
    t = -eye[2] / rays_world[:, 2]
    floor = eye[:2] + rays_world[:, :2] * t[:, None]
    return [(float(x), float(y)) for x, y in floor]


def _signed_area(polygon: Polygon) -> float:
    return 0.5 * sum(
        x0 * y1 - x1 * y0
        for (x0, y0), (x1, y1) in zip(polygon, polygon[1:] + polygon[:1], strict=True)
    )


def _counter_clockwise(polygon: Polygon) -> Polygon:
    return polygon if _signed_area(polygon) >= 0 else polygon[::-1]


def _left_of(a: Point, b: Point, p: Point) -> bool:
    """Whether ``p`` lies on the inner (left) side of edge a → b of a counter-clockwise polygon."""
    return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) >= 0


def _crossing(a: Point, b: Point, p: Point, q: Point) -> Point:
    """Where segment p → q crosses the line through a → b."""
    dx, dy = q[0] - p[0], q[1] - p[1]
    ex, ey = b[0] - a[0], b[1] - a[1]
    t = (ex * (p[1] - a[1]) - ey * (p[0] - a[0])) / (ey * dx - ex * dy)
    return (p[0] + t * dx, p[1] + t * dy)


def clip_convex(subject: Polygon, clip: Polygon) -> Polygon:
    """Sutherland–Hodgman: the part of ``subject`` inside the convex polygon ``clip``."""
    output = _counter_clockwise(subject)
    clip = _counter_clockwise(clip)
    for a, b in zip(clip, clip[1:] + clip[:1], strict=True):
        points, output = output, []
        for k, current in enumerate(points):
            previous = points[k - 1]
            if _left_of(a, b, current):
                if not _left_of(a, b, previous):
                    output.append(_crossing(a, b, previous, current))
                output.append(current)
            elif _left_of(a, b, previous):
                output.append(_crossing(a, b, previous, current))
    return output


def pair_footprint(calib: StereoCalibration) -> Polygon | None:
    """The floor both cameras of the pair see: where stereo can measure the floor at all."""
    left, right = floor_polygon(calib.left), floor_polygon(calib.right)
    if left is None or right is None:
        return None
    both = clip_convex(left, right)
    return both if len(both) >= 3 else None
