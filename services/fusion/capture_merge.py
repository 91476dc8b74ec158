"""One capture's detections, every pair's, merged into observations: an object at a seam, seen
by two pairs, or a plain top matched in fragments, is one observation (its pieces joined around
what each saw), partial where any piece is cut by an image's border."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from common.arrays import F64
from common.footprints import (
    convex_hull,
    corners,
    fit_rectangle,
    polygons_overlap,
    vertices,
)
from common.messages import DetectionRecord

NEAR_BLOCK = 256
"""Rows of detections compared with all at once (:func:`_near_pairs`)."""
ROUNDING_M = 1e-6
"""Far more than the rounding of footprints' corners on any site (within 10⁶ m of the origin):
a pair of footprints this much beyond the bound is still tested."""


@dataclass(frozen=True)
class Observation:
    """One object in one capture, after merging the pairs' detections of it."""

    center_m: tuple[float, float]
    size_m: tuple[float, float]
    yaw_rad: float
    top_m: float
    partial: bool
    pairs: tuple[str, ...]
    points: int = 0
    """The world points it was measured on (all its pieces')."""
    outline_m: tuple[tuple[float, float], ...] = ()
    """What of its top was seen (``DetectionRecord.outline_m``): empty, the rectangle."""
    round: bool = False
    """Its complete view's top is round (``DetectionRecord.round``)."""
    low: bool = False
    """Every view of it in this capture is all top (``DetectionRecord.low``)."""


def observation_polygon(record: DetectionRecord | Observation) -> F64:
    return corners(record.center_m, record.size_m, record.yaw_rad)


def _seen(record: DetectionRecord | Observation) -> F64:
    """What of an object's top a view saw: its outline, else its rectangle."""
    if len(record.outline_m) >= 3:
        return np.asarray(record.outline_m, np.float64)
    return observation_polygon(record)


def _around(views: list[F64]) -> tuple[tuple[float, float], tuple[float, float], float, F64]:
    """The smallest rectangle around what several partial views saw (centre, size, yaw), and
    the outline of it all: their outlines' hull, not their rectangles' (a box cut aslant by an
    image's border is fitted a rectangle along the cut, wider than the box)."""
    hull = convex_hull(np.vstack(views))
    cx, cy, length, width, yaw = fit_rectangle(hull)
    return (cx, cy), (length, width), yaw, hull


def at_top(
    record: DetectionRecord, camera_m: tuple[float, float, float], top_m: float
) -> DetectionRecord:
    """``record`` with its top put at ``top_m`` on the same rays from the camera at ``camera_m``
    that measured it: a top measured too low lies farther along them, larger about the camera's
    nadir by (camera height − ``top_m``) / (camera height − its top). Unchanged if the camera
    is not above both heights, or if that would shrink it by more than half (no top is measured
    so far off: a wrong camera, or a wrong track)."""
    x, y, z = camera_m
    if z <= max(top_m, record.top_m):
        return record
    scale = (z - top_m) / (z - record.top_m)
    if scale < 0.5:
        return record

    def moved(point: tuple[float, float]) -> tuple[float, float]:
        return x + (point[0] - x) * scale, y + (point[1] - y) * scale

    return record.model_copy(
        update={
            "center_m": moved(record.center_m),
            "size_m": (record.size_m[0] * scale, record.size_m[1] * scale),
            "top_m": top_m,
            "low": False,
            "outline_m": tuple(moved(vertex) for vertex in record.outline_m),
        }
    )


def merge_capture(detections: list[tuple[str, DetectionRecord]], gap_m: float) -> list[Observation]:
    """Detections of one capture from every pair → one observation per object
    (:func:`merge_groups`): a complete view wins; partial views alone are joined into the
    rectangle around what they all saw."""
    out = []
    for members in merge_groups(detections, gap_m):
        pairs = tuple(sorted({detections[k][0] for k in members}))
        complete = [detections[k][1] for k in members if not detections[k][1].partial]
        top = max(detections[k][1].top_m for k in members)
        low = all(detections[k][1].low for k in members)
        if complete or len(members) == 1:  # the best complete view, or the one partial view
            d = max(complete or [detections[members[0]][1]], key=lambda r: r.points)
            out.append(
                Observation(
                    d.center_m,
                    d.size_m,
                    d.yaw_rad,
                    top,
                    not complete,
                    pairs,
                    d.points,
                    d.outline_m,
                    d.round and bool(complete),
                    low,
                )
            )
            continue
        points = sum(detections[k][1].points for k in members)
        center, size, yaw, hull = _around([_seen(detections[k][1]) for k in members])
        out.append(
            Observation(center, size, yaw, top, True, pairs, points, vertices(hull), low=low)
        )
    return out


def merge_groups(detections: list[tuple[str, DetectionRecord]], gap_m: float) -> list[list[int]]:
    """The detections (indices) of each object: those of different pairs whose footprints come
    within ``gap_m`` of each other (``polygons_overlap``), joined through any chain of such;
    each group in index order, the groups by their first. Only the pairs :func:`_near_pairs`
    finds, not yet in one group, are tested: every two tested, four forged pairs of 256
    detections each stalled fusion's owner 15 s a capture (0.2 s so)."""
    parent = list(range(len(detections)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    polygons = [observation_polygon(d) for _, d in detections]
    for a, b in _near_pairs(detections, gap_m):
        if root(a) != root(b) and polygons_overlap(polygons[a], polygons[b], gap_m):
            parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for k in range(len(detections)):
        groups.setdefault(root(k), []).append(k)
    return list(groups.values())


def _near_pairs(
    detections: list[tuple[str, DetectionRecord]], gap_m: float
) -> Iterator[tuple[int, int]]:
    """Every two detections (a < b) of different pairs whose footprints may come within
    ``gap_m``: their centres within √2 × (the sum of their circumradii and ``gap_m``). Centres
    d apart, the rectangles lie d/√2 − r_a − r_b apart or more along the side normal of one of
    them nearest the line between the centres (45° off it at most): farther, that axis
    separates them by more than ``gap_m`` in ``polygons_overlap``. In blocks of rows: memory
    follows the detections, not their square."""
    centres_m = np.array([d.center_m for _, d in detections], np.float64).reshape(-1, 2)
    radii_m = np.array([0.5 * math.hypot(*d.size_m) for _, d in detections], np.float64)
    pair_ids = np.unique([pair for pair, _ in detections], return_inverse=True)[1]
    count = len(detections)
    for start in range(0, count, NEAR_BLOCK):
        rows = slice(start, start + NEAR_BLOCK)
        offsets_m = centres_m[None, :, :] - centres_m[rows, None, :]
        reach_m = math.sqrt(2) * (radii_m[rows, None] + radii_m[None, :] + gap_m) + ROUNDING_M
        near = np.hypot(offsets_m[..., 0], offsets_m[..., 1]) <= reach_m
        near &= pair_ids[rows, None] != pair_ids[None, :]
        near &= np.arange(start, min(start + NEAR_BLOCK, count))[:, None] < np.arange(count)
        a, b = np.nonzero(near)
        yield from zip((a + start).tolist(), b.tolist(), strict=True)


def join_pieces(pieces: list[Observation]) -> Observation:
    """Pieces of one object in one capture → one partial observation around what they saw."""
    if len(pieces) == 1:
        return pieces[0]
    center, size, yaw, hull = _around([_seen(p) for p in pieces])
    pairs = tuple(sorted({pair for p in pieces for pair in p.pairs}))
    top = max(p.top_m for p in pieces)
    points = sum(p.points for p in pieces)
    low = all(p.low for p in pieces)
    return Observation(center, size, yaw, top, True, pairs, points, vertices(hull), low=low)
