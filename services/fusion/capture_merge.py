"""One capture's detections, every pair's, merged into observations: an object at a seam, seen
by two pairs, or a plain top matched in fragments, is one observation (its pieces joined around
what each saw), partial where any piece is cut by an image's border."""

from __future__ import annotations

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


def merge_capture(detections: list[tuple[str, DetectionRecord]], gap_m: float) -> list[Observation]:
    """Detections of one capture from every pair → one observation per object. Detections of
    different pairs whose footprints overlap (within ``gap_m``) are one object: a complete view
    wins; partial views alone are joined into the rectangle around what they all saw."""
    parent = list(range(len(detections)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    polygons = [observation_polygon(d) for _, d in detections]
    for a in range(len(detections)):
        for b in range(a + 1, len(detections)):
            if detections[a][0] != detections[b][0] and polygons_overlap(
                polygons[a], polygons[b], gap_m
            ):
                parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for k in range(len(detections)):
        groups.setdefault(root(k), []).append(k)
    out = []
    for members in groups.values():
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
