"""How good a map is against ground truth: cell scores, object sizes, moving-object latencies.

Pure numpy/OpenCV over lattice arrays: the same code scores a live system (``overgrid eval``) and
hand-made maps in the tests. Every array here lies on one lattice window (``[row, col] = [j, i]``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from common.arrays import Mask
from common.camera import StereoCalibration
from common.lattice import Window, reframe
from common.mapfiles import OCCUPIED_MIN, free_cells
from common.messages import TruthObject
from common.occupancy_map import UNKNOWN, OccupancyMap
from common.sensor_model import SensorModelParams
from services.camera_sim.truth import footprint_mask

_MODEL = SensorModelParams()
OBSTACLE_BAND_M = (_MODEL.obstacle_min_m, _MODEL.obstacle_max_m)
"""Truth is judged on the band the depth service's sensor model calls an obstacle."""


def occupancy_on(occupancy_map: OccupancyMap, window: Window) -> npt.NDArray[np.int8]:
    """The map's nav_msgs occupancy over ``window``; cells the map does not cover are unknown."""
    return reframe(occupancy_map.occupancy, occupancy_map.window, window, UNKNOWN)


SURFACE_LIFT_M = 0.01
"""Sight lines start this far above a surface, so the object it belongs to does not block them."""


def seen_by_cameras(
    calibrations: Sequence[StereoCalibration],
    window: Window,
    resolution_m: float,
    surface_m: npt.NDArray[np.float64] | None = None,
    blockers: Sequence[TruthObject] = (),
) -> Mask:
    """Cells whose visible surface (height ``surface_m``, else the floor) lies inside both images of
    some pair and in the line of sight of both its cameras: what stereo can measure. A tall top
    near the edge of a view can leave it while the floor beside it stays in, and the floor in an
    object's shadow is in the images but hidden by ``blockers``, so both matter."""
    x, y = window.cell_centers(resolution_m)
    z = np.zeros(x.size) if surface_m is None else surface_m.ravel()
    surface = np.column_stack([x.ravel(), y.ravel(), z])
    start = surface + np.array([0.0, 0.0, SURFACE_LIFT_M])
    seen = np.zeros(x.size, np.bool_)
    for calib in calibrations:
        in_both = np.ones(x.size, np.bool_)
        for camera in (calib.left, calib.right):
            uvz = camera.project(surface)
            in_both &= (
                (uvz[:, 2] > 0)
                & (uvz[:, 0] >= 0)
                & (uvz[:, 0] <= camera.width - 1)
                & (uvz[:, 1] >= 0)
                & (uvz[:, 1] <= camera.height - 1)
            )
            for blocker in blockers:
                in_both &= ~sight_line_blocked(start, camera.position_world, blocker)
        seen |= in_both
    return seen.reshape(window.shape)


COVERAGE_HEIGHTS_M = (OBSTACLE_BAND_M[0], 0.5, 1.0, 1.5, OBSTACLE_BAND_M[1])
"""Heights over the obstacle band at which ``overgrid eval`` reports how much of the floor the rig
sees (:func:`coverage_by_height`)."""


def coverage_by_height(
    calibrations: Sequence[StereoCalibration],
    floor_size_m: tuple[float, float],
    resolution_m: float,
    heights_m: Sequence[float] = COVERAGE_HEIGHTS_M,
) -> dict[str, float]:
    """Share of the floor whose point at each height lies inside both images of some pair (keys:
    the heights, in metres). A pair's view narrows with height, toward its nadir, so a rig that
    sees its whole floor can leave blind bands between pairs where a tall top stands: such a top
    is measured in part or not at all, and the object under it cannot be sized or found whole
    (the default rig sees 75 % of its floor at 1 m and 47 % at 2 m)."""
    window = Window(
        0, 0, round(floor_size_m[0] / resolution_m), round(floor_size_m[1] / resolution_m)
    )
    return {
        f"{height:g}": float(
            seen_by_cameras(
                calibrations, window, resolution_m, np.full(window.shape, height)
            ).mean()
        )
        for height in heights_m
    }


def sight_line_blocked(
    start_m: npt.NDArray[np.float64], eye_m: npt.NDArray[np.float64], obj: TruthObject
) -> Mask:
    """Whether each segment start → eye passes through the object (slab test on its box or on its
    upright cylinder's height and circle)."""
    direction = eye_m - start_m
    cx, cy, cz = obj.center_m
    half_height = obj.size_m[2] / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        z_enter, z_leave = _slab(start_m[:, 2] - cz, direction[:, 2], half_height)
        if obj.shape == "cylinder":
            enter, leave = _circle(
                start_m[:, 0] - cx,
                start_m[:, 1] - cy,
                direction[:, 0],
                direction[:, 1],
                obj.size_m[0] / 2,
            )
        else:
            c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
            dx, dy = start_m[:, 0] - cx, start_m[:, 1] - cy
            along_enter, along_leave = _slab(
                c * dx + s * dy, c * direction[:, 0] + s * direction[:, 1], obj.size_m[0] / 2
            )
            across_enter, across_leave = _slab(
                -s * dx + c * dy, -s * direction[:, 0] + c * direction[:, 1], obj.size_m[1] / 2
            )
            enter, leave = (
                np.maximum(along_enter, across_enter),
                np.minimum(along_leave, across_leave),
            )
    enter, leave = np.maximum(enter, z_enter), np.minimum(leave, z_leave)
    return np.asarray((enter <= leave) & (leave > 0.0) & (enter < 1.0))


def _slab(
    offset: npt.NDArray[np.float64], step: npt.NDArray[np.float64], half: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Parameter interval in which offset + t·step lies in [-half, half] (empty: enter > leave)."""
    a, b = (-half - offset) / step, (half - offset) / step
    inside = np.abs(offset) <= half  # a segment parallel to the slab: all or nothing
    parallel = step == 0
    enter = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(a, b))
    leave = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(a, b))
    return enter, leave


def _circle(
    x: npt.NDArray[np.float64],
    y: npt.NDArray[np.float64],
    dx: npt.NDArray[np.float64],
    dy: npt.NDArray[np.float64],
    radius: float,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Parameter interval in which (x, y) + t·(dx, dy) lies inside the circle of ``radius``."""
    a = dx * dx + dy * dy
    b = 2.0 * (x * dx + y * dy)
    c = x * x + y * y - radius * radius
    discriminant = b * b - 4.0 * a * c
    misses = discriminant < 0
    root = np.sqrt(np.maximum(discriminant, 0.0))
    vertical = a == 0  # straight up: inside for all t or never
    enter = np.where(vertical, np.where(c <= 0, -np.inf, np.inf), (-b - root) / (2.0 * a))
    leave = np.where(vertical, np.where(c <= 0, np.inf, -np.inf), (-b + root) / (2.0 * a))
    return np.where(misses, np.inf, enter), np.where(misses, -np.inf, leave)


@dataclass(frozen=True)
class CellScores:
    iou: float
    precision: float
    recall: float
    false_free_rate: float
    """Truth occupied, map free: the error that drives a robot into an obstacle."""
    unknown_fraction: float
    """Share of the seen free floor the map still calls unknown."""
    truth_cells: int
    map_cells: int


def _ratio(numerator: int, denominator: int) -> float:
    return numerator / denominator if denominator else math.nan


def score_cells(occupancy: npt.NDArray[np.int8], truth: Mask, seen: Mask) -> CellScores:
    """Scores over the cells some camera sees; ``occupancy`` and ``truth`` share one window."""
    occupied = (occupancy >= OCCUPIED_MIN) & seen
    free = free_cells(occupancy) & seen
    truth_seen = truth & seen
    hits = int(np.count_nonzero(occupied & truth_seen))
    union = int(np.count_nonzero(occupied | truth_seen))
    floor = seen & ~truth
    return CellScores(
        iou=_ratio(hits, union),
        precision=_ratio(hits, int(np.count_nonzero(occupied))),
        recall=_ratio(hits, int(np.count_nonzero(truth_seen))),
        false_free_rate=_ratio(
            int(np.count_nonzero(free & truth_seen)), int(np.count_nonzero(truth_seen))
        ),
        unknown_fraction=_ratio(
            int(np.count_nonzero(floor & (occupancy == UNKNOWN))), int(np.count_nonzero(floor))
        ),
        truth_cells=int(np.count_nonzero(truth_seen)),
        map_cells=int(np.count_nonzero(occupied)),
    )


MOVER_CLEARANCE_M = 2.5
"""Floor this far from a mover's footprint (centre distance less half its diagonal) is out of
its occlusion shadow from cameras 6–8 m up: the floor that a change of the light alone moves."""
MOVER_TRAIL_S = 2.0
"""… and this far from where it was over the last seconds (by its velocity): the map shows a
mover a frame interval and its latency late, and at 1 Hz (two pairs on a loaded machine) the
forklift's contested footprint lay 4 m behind it."""


def unknown_away_from_movers(
    occupancy: npt.NDArray[np.int8],
    truth: Mask,
    seen: Mask,
    objects: Sequence[TruthObject],
    window: Window,
    resolution_m: float,
) -> float:
    """The unknown cells of the seen floor farther than MOVER_CLEARANCE_M from every mover and
    its trail over MOVER_TRAIL_S, as a
    share of all the seen floor (a fixed measure, wherever the movers are): a mover's occlusion
    shadow swings the whole floor's share by 2–3 points as it walks (two pairs), which read as a
    lighting step's unknown floor when it fell after one."""
    x_m, y_m = window.cell_centers(resolution_m)
    floor = seen & ~truth
    away = floor.copy()
    for obj in objects:
        if obj.moving:
            reach_m = MOVER_CLEARANCE_M + math.hypot(obj.size_m[0], obj.size_m[1]) / 2
            # The segment it came along over MOVER_TRAIL_S: the closest point of it to each cell.
            back_x, back_y = (-v * MOVER_TRAIL_S for v in obj.velocity_mps)
            length2 = back_x**2 + back_y**2
            dx, dy = x_m - obj.center_m[0], y_m - obj.center_m[1]
            along = np.clip((dx * back_x + dy * back_y) / length2, 0.0, 1.0) if length2 else 0.0
            away &= (dx - along * back_x) ** 2 + (dy - along * back_y) ** 2 > reach_m**2
    return _ratio(
        int(np.count_nonzero(away & (occupancy == UNKNOWN))), int(np.count_nonzero(floor))
    )


def cell_shares(occupancy: npt.NDArray[np.int8], cells: Mask) -> dict[str, float]:
    """Share of ``cells`` the map calls occupied, free and unknown (e.g. static objects' seen
    cells: on uniform objects over a uniform floor, unknown is the honest answer, free is not)."""
    total = int(np.count_nonzero(cells))
    values = occupancy[cells]
    return {
        "occupied": _ratio(int(np.count_nonzero(values >= OCCUPIED_MIN)), total),
        "free": _ratio(int(np.count_nonzero(free_cells(values))), total),
        "unknown": _ratio(int(np.count_nonzero(values == UNKNOWN)), total),
        "cells": total,
    }


EDGE_RING_CELLS = 1.5
NEAR_RING_CELLS = 3.5
"""Distances (cells, from the nearest truth cell's centre) that split false-occupied cells into an
object's edge ring, its neighbourhood and the open floor."""


def error_breakdown(
    occupancy: npt.NDArray[np.int8],
    truth: Mask,
    seen: Mask,
    objects: Sequence[TruthObject],
    window: Window,
    resolution_m: float,
) -> dict[str, object]:
    """Where the map is wrong, by cause: false-occupied seen cells by their distance from the
    truth (``edge``: the ring an object grows by, from side faces and fattening; ``near``;
    ``far``: the floor itself, e.g. markings or a pair whose floor reads raised), and per object
    its seen cells mapped occupied, free and unknown (free is the error a robot drives into)."""
    occupied = (occupancy >= OCCUPIED_MIN) & seen
    distance = cv2.distanceTransform((~truth).astype(np.uint8), cv2.DIST_L2, 3)
    false_occupied = occupied & ~truth
    rings = {
        "edge": false_occupied & (distance <= EDGE_RING_CELLS),
        "near": false_occupied & (distance > EDGE_RING_CELLS) & (distance <= NEAR_RING_CELLS),
        "far": false_occupied & (distance > NEAR_RING_CELLS),
    }
    per_object = {}
    for obj in objects:
        cells = footprint_mask(obj, window, resolution_m) & seen
        if cells.any():
            per_object[obj.name] = cell_shares(occupancy, cells)
    return {
        "false_occupied_cells": {name: int(np.count_nonzero(m)) for name, m in rings.items()},
        "objects": per_object,
    }


ANGLE_STEPS = np.deg2rad(np.arange(0.0, 90.0, 0.25))


def oriented_extent(points_xy: npt.NDArray[np.float64]) -> tuple[float, float, float]:
    """Smallest-area rectangle around the points over all orientations: (length, width, yaw)."""
    c, s = np.cos(ANGLE_STEPS), np.sin(ANGLE_STEPS)
    along = points_xy[:, :1] * c + points_xy[:, 1:] * s  # (N, angles)
    across = -points_xy[:, :1] * s + points_xy[:, 1:] * c
    extent_a = along.max(axis=0) - along.min(axis=0)
    extent_b = across.max(axis=0) - across.min(axis=0)
    best = int(np.argmin(extent_a * extent_b))
    a, b = float(extent_a[best]), float(extent_b[best])
    return max(a, b), min(a, b), float(ANGLE_STEPS[best])


@dataclass(frozen=True)
class ObjectSize:
    name: str
    true_length_m: float
    true_width_m: float
    length_m: float
    width_m: float

    @property
    def found(self) -> bool:
        return self.length_m > 0

    @property
    def errors_pct(self) -> tuple[float, float]:
        return (
            100 * abs(self.length_m - self.true_length_m) / self.true_length_m,
            100 * abs(self.width_m - self.true_width_m) / self.true_width_m,
        )


def true_extent(obj: TruthObject) -> tuple[float, float]:
    if obj.shape == "cylinder":
        return obj.size_m[0], obj.size_m[0]
    return max(obj.size_m[:2]), min(obj.size_m[:2])


def measure_object(
    occupied: Mask, window: Window, resolution_m: float, obj: TruthObject, margin_m: float = 0.2
) -> ObjectSize:
    """The object's size as the map shows it: the connected components of occupied cells that meet
    its true footprint, kept within ``margin_m`` of it (so a neighbour touching it is not measured
    too), then the oriented bounding box of those cells (cell centres ± half a cell)."""
    length_true, width_true = true_extent(obj)
    grown = obj.model_copy(
        update={"size_m": (obj.size_m[0] + 2 * margin_m, obj.size_m[1] + 2 * margin_m, 0.0)}
    )
    candidates = occupied & footprint_mask(grown, window, resolution_m)
    count, labels = cv2.connectedComponents(candidates.astype(np.uint8), connectivity=8)
    touching = np.unique(labels[candidates & footprint_mask(obj, window, resolution_m)])
    touching = touching[touching > 0]
    if count <= 1 or touching.size == 0:
        return ObjectSize(obj.name, length_true, width_true, 0.0, 0.0)
    rows, cols = np.nonzero(np.isin(labels, touching))
    x, y = window.cell_centers(resolution_m)
    points = np.column_stack([x[rows, cols], y[rows, cols]])
    length, width, _ = oriented_extent(points)
    return ObjectSize(
        obj.name, length_true, width_true, length + resolution_m, width + resolution_m
    )


@dataclass(frozen=True)
class MapSample:
    """The map as a client saw it: when it became visible (s since the epoch), occupied cells."""

    visible_s: float
    occupied: Mask


@dataclass(frozen=True)
class Tick:
    """One capture of the scene: its stamp, where the movers were, and per cell the time from
    capture until the frame that saw the cell reached its depth process (NaN: no pair saw it)."""

    stamp_s: float
    mover_cells: Mask
    camera_s: npt.NDArray[np.float32]


@dataclass(frozen=True)
class Latencies:
    appear_s: list[float]
    clear_s: list[float]
    missed_appear: int
    """Cells a mover entered that never turned occupied while it stayed (given ``settle_s``)."""
    missed_clear: int


def moving_latencies(
    ticks: Sequence[Tick], samples: Sequence[MapSample], settle_s: float = 2.0
) -> Latencies:
    """For each cell a mover enters at a capture, the time until the map shows it occupied; for each
    cell it leaves (that the map showed occupied), the time until the map no longer does. Counted
    from the capture that first shows the change, less that frame's camera time (the sim's render),
    and only while the cell stays as it became. A cell whose change never showed within
    ``settle_s`` (or before it changed back) is counted as missed."""
    appear: list[float] = []
    clear: list[float] = []
    missed = {True: 0, False: 0}
    if not samples or len(ticks) < 2:
        return Latencies(appear, clear, 0, 0)
    visible = np.array([s.visible_s for s in samples])
    shown = np.stack([s.occupied for s in samples])
    stamps = np.array([t.stamp_s for t in ticks])
    inside = np.stack([t.mover_cells for t in ticks])
    for k in range(1, len(ticks)):
        before = np.nonzero(visible < stamps[k])[0]  # the map as it stood at this capture
        for row, col in zip(*np.nonzero(inside[k] != inside[k - 1]), strict=True):
            now_inside = bool(inside[k, row, col])
            camera_s = float(ticks[k].camera_s[row, col])
            if math.isnan(camera_s):
                continue  # no pair saw the cell at this capture
            if not now_inside and (before.size == 0 or not shown[before[-1], row, col]):
                continue  # the map never showed it occupied: nothing to clear
            changes_back = np.nonzero(inside[k + 1 :, row, col] != now_inside)[0]
            until = stamps[k + 1 + changes_back[0]] if changes_back.size else math.inf
            hit = np.nonzero(
                (visible >= stamps[k]) & (visible < until) & (shown[:, row, col] == now_inside)
            )[0]
            if hit.size:
                latency = float(visible[hit[0]] - stamps[k]) - camera_s
                (appear if now_inside else clear).append(latency)
            elif min(until, visible[-1]) - stamps[k] >= settle_s:
                missed[now_inside] += 1
    return Latencies(appear, clear, missed[True], missed[False])


def percentiles(values: Sequence[float]) -> dict[str, float]:
    if not values:
        return {"p50": math.nan, "p99": math.nan, "n": 0}
    array = np.asarray(values, dtype=np.float64)
    return {
        "p50": float(np.percentile(array, 50)),
        "p99": float(np.percentile(array, 99)),
        "n": int(array.size),
    }
