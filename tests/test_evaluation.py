"""The scoring of ``overgrid eval`` on hand-made maps whose errors are known exactly."""

import math
from typing import cast

import numpy as np
import pytest

from common.lattice import Window
from common.messages import ObjectsHeader, TruthObject
from common.occupancy_map import UNKNOWN, OccupancyMap
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.truth import footprint_mask, top_heights
from services.evaluation import metrics
from services.evaluation import objects as object_scores
from services.evaluation.service import per_minute

RES = 0.05
WINDOW = Window(0, 0, 80, 60)  # 4 m × 3 m


def _box(
    name: str, x: float, y: float, length: float, width: float, yaw: float = 0.0
) -> TruthObject:
    return TruthObject(
        name=name,
        shape="box",
        moving=False,
        center_m=(x, y, 0.5),
        yaw_rad=yaw,
        size_m=(length, width, 1.0),
    )


def test_cell_scores_count_exactly() -> None:
    truth = np.zeros(WINDOW.shape, bool)
    truth[10:20, 10:20] = True  # 100 occupied cells
    occupancy = np.zeros(WINDOW.shape, np.int8)  # all free …
    occupancy[10:20, 10:18] = 100  # 80 found
    occupancy[10:20, 18] = 50  # 10 in between (neither occupied nor free)
    occupancy[40, 40 : 20 + 40] = 100  # 20 false occupied
    occupancy[0:5, :] = UNKNOWN  # 400 unknown floor cells
    seen = np.ones(WINDOW.shape, bool)
    scores = metrics.score_cells(occupancy, truth, seen)
    assert scores.iou == pytest.approx(80 / (100 + 20))
    assert scores.precision == pytest.approx(80 / 100)
    assert scores.recall == pytest.approx(80 / 100)
    assert scores.false_free_rate == pytest.approx(10 / 100)  # column 19 reads free
    assert scores.unknown_fraction == pytest.approx(400 / (WINDOW.cols * WINDOW.rows - 100))


def test_unseen_cells_are_not_scored() -> None:
    truth = np.zeros(WINDOW.shape, bool)
    truth[10:20, 10:20] = True
    occupancy = np.full(WINDOW.shape, UNKNOWN, np.int8)
    seen = np.zeros(WINDOW.shape, bool)
    seen[30:, :] = True  # the object is outside every view
    scores = metrics.score_cells(occupancy, truth, seen)
    assert math.isnan(scores.recall) and scores.unknown_fraction == 1.0


def test_object_sizes_from_the_map() -> None:
    true_box = _box("b", 2.0, 1.5, 1.0, 0.5)
    measured_as = _box("m", 2.0, 1.5, 1.1, 0.5)  # the map shows it 10 % too long
    occupied = footprint_mask(measured_as, WINDOW, RES)
    occupied[50, 70] = True  # a speck elsewhere is not part of the object
    size = metrics.measure_object(occupied, WINDOW, RES, true_box)
    assert (size.true_length_m, size.true_width_m) == (1.0, 0.5)
    assert size.length_m == pytest.approx(1.1) and size.width_m == pytest.approx(0.5)
    assert size.errors_pct == pytest.approx((10.0, 0.0))


def test_rotated_object_is_measured_along_its_own_axes() -> None:
    box = _box("r", 2.0, 1.5, 1.6, 0.6, yaw=0.5)
    size = metrics.measure_object(footprint_mask(box, WINDOW, RES), WINDOW, RES, box)
    assert size.errors_pct[0] < 5 and size.errors_pct[1] < 10


def test_missing_object_is_reported_not_measured() -> None:
    box = _box("gone", 2.0, 1.5, 1.0, 0.5)
    size = metrics.measure_object(np.zeros(WINDOW.shape, bool), WINDOW, RES, box)
    assert not size.found


def test_seen_mask_follows_the_visible_surface() -> None:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    window = Window(-20, -20, 280, 240)
    floor = metrics.seen_by_cameras([calib], window, RES)
    tall = np.full(window.shape, 2.0)
    high = metrics.seen_by_cameras([calib], window, RES, tall)
    assert high.sum() < floor.sum() * 0.7  # a 2 m surface fills less of the view than the floor
    assert not (high & ~floor).any()
    wall = _box("w", -0.1, 5.0, 0.2, 10.0)
    heights = top_heights([wall], window, RES)
    assert heights.max() == pytest.approx(1.0)


def test_rig_coverage_narrows_with_height_as_the_views_do() -> None:
    rig = RigSpec(pair_count=1)
    focal_px = rig.width_px / 2 / math.tan(math.radians(rig.hfov_deg) / 2)
    floor = (rig.width_px * rig.height_m / focal_px, rig.height_px * rig.height_m / focal_px)
    heights = (0.0, 1.0, 2.0)
    coverage = metrics.coverage_by_height(layout_pairs(rig, floor), floor, RES, heights)
    assert list(coverage) == ["0", "1", "2"]
    for height, share in zip(heights, coverage.values(), strict=True):
        # The floor is one camera's footprint: at a height, both views narrowed toward the
        # nadir, the baseline apart across.
        scale = (rig.height_m - height) / rig.height_m
        expected = (floor[0] * scale - rig.baseline_m) * floor[1] * scale / (floor[0] * floor[1])
        assert share == pytest.approx(expected, abs=0.02), height


@pytest.mark.parametrize("shape", ["box", "cylinder"])
def test_sight_lines_through_an_object_are_blocked(shape: str) -> None:
    eye = np.array([0.0, 0.0, 6.0])
    # An object 1 m tall, 0.4 m across, centred 1.2 m from the camera's nadir (x 1.0 … 1.4).
    obj = TruthObject(
        name="o",
        shape=shape,
        moving=False,
        center_m=(1.2, 0.0, 0.5),
        yaw_rad=0.0,
        size_m=(0.4, 0.4, 1.0),
    )
    starts = np.array(
        [
            [1.6, 0.0, 0.01],  # floor behind it: the line passes x = 1.4 at z ≈ 0.76 m
            [0.5, 0.0, 0.01],  # floor between the nadir and the object
            [1.2, 0.0, 1.01],  # its own top
            [1.6, 0.6, 0.01],  # floor beside its shadow
            [3.0, 0.0, 0.01],  # far behind: the line passes above it (z ≈ 3.2 m at x = 1.4)
        ]
    )
    blocked = metrics.sight_line_blocked(starts, eye, obj)
    assert blocked.tolist() == [True, False, False, False, False]


def test_floor_in_an_objects_shadow_is_not_seen() -> None:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    window = Window(0, 0, 240, 200)
    tower = _box("tower", 8.0, 5.0, 0.6, 0.6)  # 1 m tall, 2 m off the pair's nadir
    surface = top_heights([tower], window, RES)
    open_view = metrics.seen_by_cameras([calib], window, RES, surface)
    with_shadows = metrics.seen_by_cameras([calib], window, RES, surface, blockers=[tower])
    hidden = open_view & ~with_shadows
    assert not (with_shadows & ~open_view).any()
    assert 20 < hidden.sum() < 400  # its shadow, a few dozen cells
    assert not (hidden & footprint_mask(tower, window, RES)).any()  # its own top stays seen
    x, _ = window.cell_centers(RES)
    assert np.all(x[hidden] > 7.7)  # behind its near face, away from the cameras at x ≈ 6 m


def _line_world(cells_inside: list[int]) -> np.ndarray:
    mask = np.zeros((1, 10), bool)
    mask[0, cells_inside] = True
    return mask


def test_moving_latencies_from_capture_less_camera_time() -> None:
    """A mover steps right one cell per capture (every 0.5 s); the map shows each change 0.3 s
    after the capture, of which 0.1 s is the camera's own."""
    camera = np.full((1, 10), 0.1, np.float32)
    ticks = [metrics.Tick(k * 0.5, _line_world([k, k + 1]), camera) for k in range(6)]
    samples = [metrics.MapSample(k * 0.5 + 0.3, _line_world([k, k + 1])) for k in range(6)]
    latencies = metrics.moving_latencies(ticks, samples)
    assert latencies.appear_s == pytest.approx([0.2] * 5)
    assert latencies.clear_s == pytest.approx([0.2] * 5)
    assert latencies.missed_appear == 0


def test_a_mover_the_map_never_shows_is_missed() -> None:
    camera = np.zeros((1, 10), np.float32)
    ticks = [
        metrics.Tick(k * 0.5, _line_world([3]) if k else _line_world([]), camera) for k in range(8)
    ]
    samples = [metrics.MapSample(k * 0.5 + 0.1, _line_world([])) for k in range(8)]
    latencies = metrics.moving_latencies(ticks, samples)
    assert latencies.appear_s == [] and latencies.missed_appear == 1


def test_occupancy_on_another_window_fills_unknown() -> None:
    m = OccupancyMap(np.full((2, 3), 100, np.int8), RES, i0=5, j0=5, version=1, stamp_ns=0)
    out = metrics.occupancy_on(m, Window(4, 4, 5, 5))
    assert (out[1:3, 1:4] == 100).all() and (out == UNKNOWN).sum() == 25 - 6


def test_error_breakdown_tells_an_edge_ring_from_floor_errors_and_names_the_objects() -> None:
    window = Window(0, 0, 40, 40)
    box = TruthObject(
        name="box",
        shape="box",
        moving=False,
        center_m=(1.0, 1.0, 0.5),
        yaw_rad=0.0,
        size_m=(0.5, 0.5, 1.0),
    )
    truth = footprint_mask(box, window, 0.05)
    seen = np.ones(window.shape, np.bool_)
    occupancy = np.zeros(window.shape, np.int8)
    occupancy[truth] = 100
    rows, cols = np.nonzero(truth)
    occupancy[rows.min() - 1, cols.min() : cols.max() + 1] = 100  # a one-cell ring on one side
    occupancy[35, 35] = 100  # a false obstacle on the open floor
    occupancy[rows[0], cols[0]] = 0  # one cell of the box free
    occupancy[rows[1], cols[1]] = UNKNOWN
    result = metrics.error_breakdown(occupancy, truth, seen, [box], window, 0.05)
    assert result["false_occupied_cells"] == {
        "edge": int(cols.max() - cols.min() + 1),
        "near": 0,
        "far": 1,
    }
    shares = cast(dict[str, dict[str, float]], result["objects"])["box"]
    assert shares["cells"] == int(truth.sum())
    assert shares["free"] == pytest.approx(1 / truth.sum())
    assert shares["unknown"] == pytest.approx(1 / truth.sum())


def test_sizes_in_view_are_over_the_objects_whose_top_the_cameras_see_whole() -> None:
    whole, cut = _box("whole", 1.0, 1.0, 0.6, 0.4), _box("cut", 3.0, 1.0, 0.6, 0.4)
    seen = np.ones(WINDOW.shape, bool)
    seen[:, 61:] = False  # the view ends at x = 3.05 m: the cut box's far half is unseen
    in_view = object_scores.seen_whole([whole, cut], seen, WINDOW, RES)
    assert in_view == {"whole"}
    matches = [
        object_scores.ObjectMatch("whole", 0.6, 0.4, 1, 0.606, 0.4, False, False, False),
        object_scores.ObjectMatch("cut", 0.6, 0.4, 1, 0.35, 0.4, True, False, False),
    ]
    errors = object_scores.size_errors(matches, in_view)
    assert errors["objects_in_view"] == 1
    assert errors["length_error_max_pct_in_view"] == pytest.approx(1.0)
    assert errors["length_error_max_pct"] == pytest.approx(100 * 0.25 / 0.6)


def test_id_switches_are_per_minute_of_the_lists_they_were_counted_over() -> None:
    """A 32-minute run's switches were counted over its last two minutes (the recorder's
    history) and divided by all 32: sixteen times too few."""
    lists = [ObjectsHeader(version=v, stamp_ns=v * 30 * 10**9, objects=[]) for v in range(5)]
    assert per_minute({"mover_person": 1}, lists) == {"mover_person": 0.5}  # 1 in 2 minutes
    assert per_minute({"mover_person": 1}, lists[:1]) == {"mover_person": 60.0}  # no span: 1 s
