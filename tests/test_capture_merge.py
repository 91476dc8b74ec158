"""One capture's detections merged into objects (``services.fusion.capture_merge``): the groups
are those of testing every two detections of different pairs, and many detections cost little."""

from __future__ import annotations

import itertools
import math
import random
import time

import numpy as np
import pytest

from common.footprints import polygons_overlap
from common.messages import MAX_DETECTIONS, DetectionRecord
from services.fusion.capture_merge import (
    at_top,
    merge_capture,
    merge_groups,
    observation_polygon,
)

GAP_M = 0.1


def _record(
    center_m: tuple[float, float], size_m: tuple[float, float], yaw_rad: float
) -> DetectionRecord:
    return DetectionRecord(
        center_m=center_m, size_m=size_m, yaw_rad=yaw_rad, top_m=1.0, points=100, partial=True
    )


def _every_two(detections: list[tuple[str, DetectionRecord]]) -> list[list[int]]:
    """The groups of testing every two detections of different pairs (as the merge once did)."""
    polygons = [observation_polygon(d) for _, d in detections]
    groups = [{k} for k in range(len(detections))]
    for a, b in itertools.combinations(range(len(detections)), 2):
        if detections[a][0] != detections[b][0] and polygons_overlap(
            polygons[a], polygons[b], GAP_M
        ):
            group_a, group_b = (next(g for g in groups if k in g) for k in (a, b))
            if group_a is not group_b:
                group_a |= group_b
                groups.remove(group_b)
    return sorted(sorted(group) for group in groups)


def _scattered(seed: int, count: int, side_m: float) -> list[tuple[str, DetectionRecord]]:
    """``count`` detections of four pairs, of any size up to 1.5 m and any yaw, over a square."""
    rng = random.Random(seed)
    return [
        (
            f"p{rng.randrange(4)}",
            _record(
                (rng.uniform(0, side_m), rng.uniform(0, side_m)),
                (rng.uniform(0.05, 1.5), rng.uniform(0.05, 1.5)),
                rng.uniform(0, math.pi),
            ),
        )
        for _ in range(count)
    ]


def _corner_to_corner(distance_m: float) -> list[tuple[str, DetectionRecord]]:
    """Two 0.5 m squares turned 45°, corner to corner along x: no side normal lies along the line
    between them, so their sides' axes find them √2 times nearer than they are."""
    return [
        ("p0", _record((2.0, 2.0), (0.5, 0.5), math.pi / 4)),
        ("p1", _record((2.0 + distance_m, 2.0), (0.5, 0.5), math.pi / 4)),
    ]


@pytest.mark.parametrize("seed", range(4))
def test_the_groups_are_those_of_testing_every_two_detections(seed: int) -> None:
    detections = _scattered(seed, 160, 20.0)  # groups of one to ten
    assert merge_groups(detections, GAP_M) == _every_two(detections)


@pytest.mark.parametrize("beyond_m", [-1e-3, -1e-9, 1e-9, 1e-3])
def test_footprints_the_sides_axes_find_within_the_gap_are_one_object(beyond_m: float) -> None:
    touching_m = math.sqrt(2) * 0.5  # the squares' diagonals end to end
    detections = _corner_to_corner(touching_m + math.sqrt(2) * GAP_M + beyond_m)
    assert merge_groups(detections, GAP_M) == _every_two(detections)
    assert len(merge_groups(detections, GAP_M)) == (1 if beyond_m < 0 else 2)


def test_a_capture_of_many_detections_is_merged_at_once() -> None:
    """Four forged pairs of 256 detections each (the most a message holds) over a 12 × 10 m site:
    every two of them tested took 15 s a capture, the map waiting meanwhile."""
    rng = random.Random(1)
    detections = [
        (f"p{k}", _record((rng.uniform(0, 12), rng.uniform(0, 10)), (0.5, 0.4), 0.0))
        for k in range(4)
        for _ in range(MAX_DETECTIONS)
    ]
    start_s = time.perf_counter()
    merge_capture(detections, GAP_M)
    assert time.perf_counter() - start_s < 2.0


def test_a_top_measured_low_is_put_back_on_its_rays() -> None:
    """A 1.2 × 0.8 m top 1.1 m up, 0.5 m from the nadir of a camera 6 m up, measured at 0.19 m:
    its pixels' rays meet 0.19 m at (6 − 0.19) / (6 − 1.1) times the distances from the nadir.
    Put back at 1.1 m, it is the top again, outline and all."""
    camera = (3.0, 2.0, 6.0)
    scale = (6.0 - 0.19) / (6.0 - 1.1)
    true_center = (3.5, 2.0)

    def seen(point: tuple[float, float]) -> tuple[float, float]:
        return camera[0] + (point[0] - camera[0]) * scale, camera[1] + (
            point[1] - camera[1]
        ) * scale

    corners_true = [(2.9, 1.6), (4.1, 1.6), (4.1, 2.4), (2.9, 2.4)]
    low = DetectionRecord(
        center_m=seen(true_center),
        size_m=(1.2 * scale, 0.8 * scale),
        yaw_rad=0.0,
        top_m=0.19,
        points=3000,
        partial=False,
        low=True,
        outline_m=tuple(seen(c) for c in corners_true),
    )
    lifted = at_top(low, camera, 1.1)
    assert lifted.top_m == 1.1 and not lifted.low
    assert math.dist(lifted.center_m, true_center) < 1e-9
    assert lifted.size_m == pytest.approx((1.2, 0.8))
    assert np.allclose(lifted.outline_m, corners_true)
    assert at_top(low, (3.0, 2.0, 1.0), 1.1) is low  # a camera below the top: no rays to follow
    assert at_top(low, (3.0, 2.0, 1.3), 1.1) is low  # shrunk to a fifth: a wrong camera
