"""Objects: measured from points below the cell size, merged across pairs, tracked with velocities,
movers' paths swept into the map's predicted layer."""

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import pytest

from common.footprints import corners, fit_rectangle, polygon_cells
from common.lattice import Window
from common.mapfiles import OCCUPIED_MIN
from common.messages import MAX_DETECTIONS, DetectionRecord, TrackedObject, TruthObject
from common.occupancy_map import OCCUPIED
from common.sensor_model import SensorModelParams
from services.camera_sim.scene import generate_scene
from services.depth.objects import (
    Detection,
    PixelGrid,
    detect_objects,
    detections_header,
    half_density_edges_m,
    top_outline,
)
from services.depth.projection import WorldPoints
from services.evaluation.objects import match_static, score_movers
from services.fusion.capture_merge import merge_capture
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.map_check import Outline
from services.fusion.object_layers import serve_tracks
from services.fusion.objects import ObjectTracker
from tests.tiles import dirty_window, measure

PITCH_M = 0.02
"""Floor spacing of the synthetic pixels (about a half-resolution pixel at an object's top)."""
CAMERA_HEIGHT_M = 6.0
LEFT_MARGIN_PX = 0
FRAME_NS = 500_000_000  # 2 Hz
T0_NS = 1_700_000_000 * 10**9


def _scene_points(
    center: tuple[float, float],
    size: tuple[float, float],
    yaw: float,
    top_m: float,
    rng: np.random.Generator,
    extent_m: float = 3.0,
) -> tuple[WorldPoints, PixelGrid]:
    """A pixel grid over the floor seen from overhead: the box's top where it stands, floor else."""
    n = int(extent_m / PITCH_M)
    rows, cols = np.mgrid[0:n, 0:n]
    x = center[0] - extent_m / 2 + (cols + 0.5) * PITCH_M
    y = center[1] - extent_m / 2 + (rows + 0.5) * PITCH_M
    c, s = math.cos(yaw), math.sin(yaw)
    along = c * (x - center[0]) + s * (y - center[1])
    across = -s * (x - center[0]) + c * (y - center[1])
    on_box = (np.abs(along) <= size[0] / 2) & (np.abs(across) <= size[1] / 2)
    height = np.where(on_box, top_m, 0.0) + rng.normal(0, 0.01, x.shape)
    points = WorldPoints(
        x_m=x.ravel().astype(np.float32),
        y_m=y.ravel().astype(np.float32),
        height_m=height.ravel().astype(np.float32),
        height_sigma_m=np.full(x.size, 0.02, np.float32),
    )
    return points, PixelGrid.from_valid(np.ones((n, n), np.bool_))


def _detect(
    points: WorldPoints,
    pixels: PixelGrid,
    pixel_angle_rad: float,
    baseline_yaw_rad: float = 0.0,
) -> list[Detection]:
    """The detections of a synthetic pair at ``CAMERA_HEIGHT_M`` whose rows run along
    ``baseline_yaw_rad`` on the floor."""
    return detect_objects(
        points,
        pixels,
        CAMERA_HEIGHT_M,
        pixel_angle_rad,
        LEFT_MARGIN_PX,
        SensorModelParams(),
        baseline_yaw_rad=baseline_yaw_rad,
    )


@pytest.mark.parametrize("yaw", [0.0, 0.03, 0.5, math.pi / 2])
def test_size_of_a_rotated_box_from_its_points_is_below_the_cell_size(yaw: float) -> None:
    rng = np.random.default_rng(1)
    size = (0.83, 0.47)
    points, pixels = _scene_points((5.0, 4.0), size, yaw, 1.1, rng)
    pixel_angle = PITCH_M / (CAMERA_HEIGHT_M - 1.1)  # one pixel spans PITCH_M at the top
    found = _detect(points, pixels, pixel_angle)
    assert len(found) == 1
    d = found[0]
    # Within the lattice sampling of the edges (under a pixel): a third of a 5 cm cell.
    assert abs(d.length_m - size[0]) < 0.016 and abs(d.width_m - size[1]) < 0.016
    assert abs(d.center_xy_m[0] - 5.0) < 0.01 and abs(d.center_xy_m[1] - 4.0) < 0.01
    assert 0 <= d.yaw_rad < math.pi
    assert abs(math.remainder(d.yaw_rad - yaw, math.pi)) < math.radians(
        2
    )  # a pixel over its length
    assert abs(d.top_m - 1.1) < 0.03
    assert not d.partial and not d.low


@pytest.mark.parametrize(("yaw", "baseline_yaw"), [(0.0, 0.0), (0.4, 0.0), (0.4, math.pi / 2)])
def test_a_low_objects_size_ignores_the_fringe_and_the_fattening_along_the_baseline(
    yaw: float, baseline_yaw: float
) -> None:
    """A pallet (14 cm) is half a pixel of disparity above the floor: beside a strong edge a
    quarter of the floor pixels in a 12 cm strip read its height, and along the baseline the
    matcher's window carries its height a pixel over the floor at both ends. Its sides lie where
    its points' density halves, less that pixel along the baseline: not at the fringe's outer
    points (12 cm too wide), nor a pixel out at either end."""
    rng = np.random.default_rng(4)
    size, center = (1.2, 0.8), (5.0, 4.0)
    points, pixels = _scene_points(center, size, yaw, 0.144, rng)
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = points.x_m - center[0], points.y_m - center[1]
    along, across = c * dx + s * dy, -s * dx + c * dy
    fringe = (
        (np.abs(along) <= size[0] / 2) & (across < -size[1] / 2) & (across > -size[1] / 2 - 0.12)
    )
    lifted = fringe & (rng.random(fringe.shape) < 0.25)
    points.height_m[lifted] = 0.125
    on_top = (np.abs(along) <= size[0] / 2) & (np.abs(across) <= size[1] / 2)
    bx, by = math.cos(baseline_yaw), math.sin(baseline_yaw)
    for step in (-1, 1):  # a pixel of the top's height past either end along the baseline
        shifted = _inside_box(dx - step * PITCH_M * bx, dy - step * PITCH_M * by, size, yaw)
        points.height_m[shifted & ~on_top] = 0.144
    pixel_angle = PITCH_M / (CAMERA_HEIGHT_M - 0.144)
    found = _detect(points, pixels, pixel_angle, baseline_yaw)
    assert len(found) == 1
    d = found[0]
    assert d.low
    assert abs(d.length_m - size[0]) < 0.015 and abs(d.width_m - size[1]) < 0.015
    assert math.hypot(d.center_xy_m[0] - center[0], d.center_xy_m[1] - center[1]) < 0.015


def _inside_box(
    dx: np.ndarray, dy: np.ndarray, size: tuple[float, float], yaw: float
) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    along, across = c * dx + s * dy, -s * dx + c * dy
    inside: np.ndarray = (np.abs(along) <= size[0] / 2) & (np.abs(across) <= size[1] / 2)
    return inside


@pytest.mark.parametrize("values", [[0.3] * 5, [1.0], [0.0, 0.001], list(np.arange(81) * 0.01)])
def test_half_density_edges_of_any_few_points_are_defined(values: list[float]) -> None:
    """Points on a pixel grid, a bin per pixel: the edges half a pixel past the outer centres
    (81 centres 1 cm apart span 0.81 m of pixels); a handful, or one: their extremes, no error."""
    low_m, high_m = half_density_edges_m(np.asarray(values, np.float64), 0.01)
    if len(values) == 81:
        assert abs(low_m + 0.005) < 1e-6 and abs(high_m - 0.805) < 1e-6
    else:
        assert min(values) - 0.02 <= low_m <= high_m <= max(values) + 0.02


@pytest.mark.parametrize("seen", ["corner", "pallet", "rim"])
def test_the_feet_of_two_walls_meeting_at_a_corner_are_no_object(seen: str) -> None:
    """Where an image's edge cuts two walls meeting at a corner, stereo measures only their feet: a
    strip a few centimetres wide along each inner face, up to 25 cm high. The L's rectangle
    (1.6 × 0.9 m here; ``--seed 4``'s spanned 1.9 × 0.8 m aslant) is not elongated enough for a
    strip, yet its points fill a tenth of it. A pallet in the corner fills all of its own; one
    whose deck matched only within 10 cm of its sides fills 0.4 of it, more than lines do (a
    walking person's legs filled 0.42)."""
    rng = np.random.default_rng(6)
    points, pixels = _scene_points((0.6, 9.2), (1.2, 0.8), 0.0, 0.144, rng, extent_m=2.0)
    x, y = points.x_m, points.y_m
    if seen == "corner":
        points.height_m[:] = rng.normal(0, 0.01, x.shape)  # no pallet: the floor
        feet = ((x > 0) & (x < 0.06) & (y > 8.4) & (y < 10)) | (
            (y > 9.94) & (y < 10) & (x > 0) & (x < 0.9)
        )
        points.height_m[feet] = rng.uniform(0.11, 0.25, int(np.count_nonzero(feet)))
    elif seen == "rim":
        unmatched = (np.abs(x - 0.6) < 0.5) & (np.abs(y - 9.2) < 0.3)
        points.height_m[unmatched] = rng.normal(0, 0.01, int(np.count_nonzero(unmatched)))
    found = _detect(points, pixels, PITCH_M / CAMERA_HEIGHT_M)
    if seen == "corner":
        assert found == []
    else:
        assert len(found) == 1 and found[0].low


def test_an_object_cut_by_the_image_border_is_partial() -> None:
    rng = np.random.default_rng(2)
    points, pixels = _scene_points((5.0, 4.0), (0.8, 0.5), 0.0, 1.0, rng, extent_m=1.2)
    keep = points.x_m < 5.2  # the view ends across the box
    cut = WorldPoints(
        *(getattr(points, f)[keep] for f in ("x_m", "y_m", "height_m", "height_sigma_m"))
    )
    cols = pixels.cols[keep]  # the image ends there
    cut_pixels = PixelGrid(pixels.rows[keep], cols, (pixels.shape[0], int(cols.max()) + 1))
    found = _detect(cut, cut_pixels, 0.004)
    assert len(found) == 1 and found[0].partial


def _view_of(
    points: WorldPoints, pixels: PixelGrid, keep: npt.NDArray[np.bool_], pair: str
) -> tuple[str, DetectionRecord]:
    """What one pair whose image holds only the ``keep`` pixels detects of them (one object)."""
    rows, cols = pixels.rows[keep], pixels.cols[keep]
    rows, cols = rows - rows.min(), cols - cols.min()  # the image is the part kept
    seen = WorldPoints(
        *(getattr(points, f)[keep] for f in ("x_m", "y_m", "height_m", "height_sigma_m"))
    )
    view = PixelGrid(rows, cols, (int(rows.max()) + 1, int(cols.max()) + 1))
    found = detect_objects(
        seen,
        view,
        CAMERA_HEIGHT_M,
        0.004,
        LEFT_MARGIN_PX,
        SensorModelParams(),
        baseline_yaw_rad=0.0,
    )
    (record,) = detections_header(found, pair, 0, T0_NS).detections
    return pair, record


def test_two_pairs_each_seeing_part_of_a_box_cut_aslant_give_its_size() -> None:
    """Two pairs' images end across a box turned 116°, 8 cm apart (a seam; ``--seed 4``'s box_0
    is seen so): the smaller piece's smallest rectangle lies along the cut, wider than the box,
    and the rectangle around both views is 1.27 × 0.98 m; what the views saw, joined, is the
    box."""
    rng = np.random.default_rng(4)
    size, yaw = (0.96, 0.82), 2.03
    points, pixels = _scene_points((5.0, 5.0), size, yaw, 0.3, rng)
    views = [
        _view_of(points, pixels, points.y_m < 4.8, "p0"),
        _view_of(points, pixels, points.y_m > 4.88, "p1"),
    ]
    assert all(record.partial for _, record in views)
    (merged,) = merge_capture(views, gap_m=0.1)
    assert merged.partial and merged.pairs == ("p0", "p1")
    assert np.allclose(merged.size_m, size, atol=0.03), merged.size_m
    assert np.allclose(merged.center_m, (5.0, 5.0), atol=0.02)


def test_a_complete_view_much_smaller_than_the_partial_views_is_a_piece() -> None:
    """One pair sees all of a box's top but for the image's edge (4 000 points); once, another
    pair matched only a strip of it (57 points, a taller neighbour hiding the rest): that capture
    takes the complete strip, but the box is the partial views' size, a lower bound, not the
    strip's confident 0.49 × 0.15 m (offline, ``--seed 1 --pairs 6``'s box_3)."""
    most = _record((5.0, 5.0), (1.18, 0.97), partial=True, points=4000)
    strip = _record((5.0, 4.6), (0.49, 0.15), points=57)
    tracker = ObjectTracker()
    for k in range(6):
        tracker.add("p1", T0_NS + k * FRAME_NS, [most], now_s=0.0)
        tracker.add("p0", T0_NS + k * FRAME_NS, [strip] if k == 3 else [], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0", "p1"})
    (found,) = tracker.objects()
    assert found.partial and np.allclose(found.size_m, (1.18, 0.97))


def test_complete_views_outnumbering_larger_partial_ones_keep_the_size() -> None:
    """A cylinder seen whole every frame, whose track once took a neighbour's partial view: the
    partial view is what is wrong, not the cylinder's complete views."""
    whole = _record((7.3, 6.1), (0.46, 0.46), points=450)
    neighbour = _record((7.5, 5.3), (1.19, 0.97), partial=True, points=4000)
    tracker = ObjectTracker()
    for k in range(6):
        tracker.add("p3", T0_NS + k * FRAME_NS, [neighbour if k == 2 else whole], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p3"})
    (found,) = tracker.objects()
    assert not found.partial and np.allclose(found.size_m, (0.46, 0.46))


def test_stale_partial_views_do_not_outvote_newer_complete_ones() -> None:
    """A box at a seam seen only in two oversized partial halves for 8 s, then whole from a pair
    that took over: the complete views are measured against the partial views of their own time
    (none), not against the 16 older ones, and give the size from the fourth of them on."""
    halves = _record((5.0, 5.0), (1.3, 1.2), partial=True, points=2000)
    whole = _record((5.0, 5.0), (0.6, 0.5), points=900)
    tracker = ObjectTracker()
    for k in range(22):
        tracker.add("p0", T0_NS + k * FRAME_NS, [halves if k < 16 else whole], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (found,) = tracker.objects()
    assert not found.partial and np.allclose(found.size_m, (0.6, 0.5))


def test_complete_views_older_than_twenty_partial_ones_and_too_few_to_agree_are_stale() -> None:
    """``--floor plain --seed 5 --pairs 6``: a drum seen in the first two frames, while the floor
    model still learned, as "complete" views of 1.10 × 0.87 m (3265 points: merged with what stood
    by), then every frame whole but flagged partial (0.48 m: near a pair's left margin). The
    cameras stand still, so a pair that saw a standing object whole would see it so again: once
    twenty partial views came since, two views that never agreed on a size are stale and the size
    is the partial views' (a lower bound)."""
    merged = _record((7.2, 6.1), (1.1, 0.87), points=3265)
    seen = _record((7.2, 6.1), (0.48, 0.47), partial=True, points=800)
    tracker = ObjectTracker()
    for k in range(24):
        tracker.add("p3", T0_NS + k * FRAME_NS, [merged if k < 2 else seen], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p3"})
        if k == 20:  # 19 partial views since: the complete ones still count
            (found,) = tracker.objects()
            assert np.allclose(found.size_m, (1.1, 0.87))
    (found,) = tracker.objects()
    assert found.partial and np.allclose(found.size_m, (0.48, 0.47))


@pytest.mark.parametrize("moving", [False, True])
def test_complete_views_that_agreed_keep_the_size_through_partial_ones(moving: bool) -> None:
    """A box measured whole for 15 s, then half hidden by a parked forklift for 12.5 s (partial
    views of its other half); a forklift seen whole for 4 s, then only at an image's edge: their
    complete views agreed, so they keep the size (a stale view is one no frame repeated)."""
    whole_size, part_size = ((2.4, 1.2), (1.1, 0.8)) if moving else ((1.2, 0.8), (0.6, 0.8))
    whole_frames = 8 if moving else 30
    tracker = ObjectTracker()
    for k in range(whole_frames + 25):
        x = 2.0 + 0.5 * k if moving else 5.0
        view = (
            _record((x, 5.0), whole_size, points=2000)
            if k < whole_frames
            else _record((x + 0.3, 5.0), part_size, partial=True, points=900)
        )
        tracker.add("p0", T0_NS + k * FRAME_NS, [view], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (found,) = tracker.objects()
    assert found.object_class == ("moving" if moving else "static")
    assert np.allclose(found.size_m, whole_size) and not found.partial


def test_a_top_outline_is_what_the_points_saw_within_their_rectangle() -> None:
    """The hull of a square's pixel centres, grown half a pixel: the square, to the pixel; a stray
    point outside the fitted rectangle is clipped off; too few points give no outline; a round
    top's many hull vertices are thinned to the cap, and still hold its area."""
    grid = np.mgrid[0:20, 0:20].reshape(2, -1).T * 0.02 + 0.01  # a 0.4 m square's pixel centres
    rectangle = (0.2, 0.2, 0.4, 0.4, 0.0)
    square = np.array(top_outline(grid, rectangle, 0.02))
    assert np.allclose(square.min(axis=0), 0.0, atol=0.005)
    assert np.allclose(square.max(axis=0), 0.4, atol=0.005)
    stray = np.vstack([grid, [[0.2, 0.6]]])
    assert np.array(top_outline(stray, rectangle, 0.02))[:, 1].max() <= 0.4 + 1e-6
    assert top_outline(grid[:2], rectangle, 0.02) == ()
    angles = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    disc = np.column_stack([np.cos(angles), np.sin(angles)]) * 0.25 + 0.25
    outline = np.array(top_outline(disc, (0.25, 0.25, 0.5, 0.5, 0.0), 0.02, max_vertices=12))
    assert 3 <= len(outline) <= 12
    x, y = outline[:, 0], outline[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    assert area == pytest.approx(np.pi * 0.25**2, rel=0.08)


def test_fit_rectangle_recovers_a_known_rectangle() -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.5, 0.5, (4000, 2)) * [1.2, 0.6]
    yaw = 2.0
    rotation = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    cx, cy, length, width, fitted_yaw = fit_rectangle(xy @ rotation.T + [3.0, 2.0])
    assert abs(length - 1.2) < 0.01 and abs(width - 0.6) < 0.01
    assert abs(cx - 3.0) < 0.01 and abs(cy - 2.0) < 0.01
    assert abs(fitted_yaw - yaw % math.pi) < math.radians(1)


def _record(
    center: tuple[float, float],
    size: tuple[float, float],
    partial: bool = False,
    yaw: float = 0.0,
    top: float = 1.0,
    points: int = 500,
    round_: bool = False,
    low: bool = False,
) -> DetectionRecord:
    return DetectionRecord(
        center_m=center,
        size_m=size,
        yaw_rad=yaw,
        top_m=top,
        points=points,
        partial=partial,
        round=round_,
        low=low,
    )


def test_two_pairs_each_seeing_half_of_an_object_give_one_object() -> None:
    # A 1.0 × 0.6 m box from x = 2.0 to 3.0; pair p0 sees x < 2.55, pair p1 sees x > 2.45.
    halves = [
        ("p0", _record((2.275, 5.0), (0.55, 0.6), partial=True)),
        ("p1", _record((2.725, 5.0), (0.55, 0.6), partial=True)),
    ]
    merged = merge_capture(halves, gap_m=0.1)
    assert len(merged) == 1
    assert merged[0].pairs == ("p0", "p1")
    assert abs(merged[0].size_m[0] - 1.0) < 1e-6 and abs(merged[0].center_m[0] - 2.5) < 1e-6

    tracker = ObjectTracker()
    for k in range(4):
        for pair, record in halves:
            tracker.add(pair, T0_NS + k * FRAME_NS, [record], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0", "p1"})
    objects = tracker.objects()
    assert len(objects) == 1 and objects[0].pairs == ["p0", "p1"]


def test_the_object_list_joins_static_pieces_a_seams_gap_keeps_apart() -> None:
    """A 1.0 × 0.6 m box from x = 2.0 to 3.0, 1 m high, at a seam: pair p0 sees its top to
    x = 2.3, pair p1 from x = 2.7, four frames running; the 0.4 m between is in neither view at
    that height (unknown in the map, the floor around it free). Given the map, ``map/objects``
    says one partial object 1 m long, with the older track's id, seen by both pairs; the tracks,
    and so the map's outlines, stay two. Without the map, two objects. A box beside it that p2
    sees whole is no part of it."""
    grid = FusedGrid(GridParams(resolution_m=0.05, bounds=Window(0, 0, 200, 100)))
    for window, logodds in (
        (Window(0, 0, 200, 44), -2.0),
        (Window(0, 56, 200, 44), -2.0),
        (Window(40, 44, 6, 12), 4.0),  # p0's piece
        (Window(54, 44, 6, 12), 4.0),  # p1's piece
        (Window(66, 44, 6, 12), 4.0),  # a box x 3.3–3.6 m, seen whole by p2
    ):
        measure(grid, window, logodds, T0_NS)
    tracker = ObjectTracker()
    for k in range(4):
        stamp = T0_NS + k * FRAME_NS
        tracker.add("p0", stamp, [_record((2.15, 2.5), (0.3, 0.6), partial=True)], now_s=0.0)
        piece = [_record((2.85, 2.5), (0.3, 0.6), partial=True)]
        tracker.add("p2", stamp, [_record((3.45, 2.5), (0.3, 0.6))], now_s=0.0)
        tracker.add("p1", stamp, piece if k else [], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0", "p1", "p2"})
    joined, whole = sorted(tracker.objects(cells=grid), key=lambda o: o.center_m[0])
    assert joined.partial and joined.pairs == ["p0", "p1"] and joined.id == 1
    assert abs(joined.size_m[0] - 1.0) < 1e-6 and abs(joined.center_m[0] - 2.5) < 1e-6
    assert abs(joined.size_m[1] - 0.6) < 1e-6 and joined.last_seen_ns == T0_NS + 3 * FRAME_NS
    assert len(tracker.objects()) == 3 and len(tracker.tracks) == 3
    assert not whole.partial and abs(whole.center_m[0] - 3.45) < 1e-6


def test_a_complete_view_wins_over_a_partial_one() -> None:
    merged = merge_capture(
        [
            ("p0", _record((2.5, 5.0), (1.0, 0.6))),
            ("p1", _record((2.8, 5.0), (0.4, 0.6), partial=True)),
        ],
        gap_m=0.1,
    )
    assert len(merged) == 1 and not merged[0].partial and merged[0].size_m == (1.0, 0.6)


def test_a_track_that_began_on_pieces_takes_its_size_from_its_best_measured_views() -> None:
    """Seven early views of a pallet's deck in pieces (a few hundred points, half its size), then
    five whole (1500 points): the size is the whole views', not a median over both."""
    tracker = ObjectTracker()
    views = [((0.5, 0.2), 150)] * 7 + [((1.22, 0.79), 1500)] * 5
    for k, (size, points) in enumerate(views):
        record = DetectionRecord(
            center_m=(4.0, 3.0), size_m=size, yaw_rad=0.0, top_m=0.18, points=points, partial=False
        )
        tracker.add("p0", T0_NS + k * FRAME_NS, [record], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (found,) = tracker.objects()
    assert found.size_m == (1.22, 0.79)


def _run_mover(
    tracker: ObjectTracker,
    start: tuple[float, float],
    velocity: tuple[float, float],
    frames: int,
    rng: np.random.Generator,
    seam_x_m: float | None = None,
) -> list[list[TrackedObject]]:
    """A 1.2 × 0.8 m box moving at constant velocity; with a seam, pair p0 sees x < seam + 0.3 and
    p1 x > seam − 0.3, each partially near its edge."""
    history = []
    size = (1.2, 0.8)
    for k in range(frames):
        t_s = k * FRAME_NS / 1e9
        x = start[0] + velocity[0] * t_s + rng.normal(0, 0.02)
        y = start[1] + velocity[1] * t_s + rng.normal(0, 0.02)
        stamp = T0_NS + k * FRAME_NS
        if seam_x_m is None:
            tracker.add("p0", stamp, [_record((x, y), size)], now_s=0.0)
            pairs = {"p0"}
        else:
            pairs = {"p0", "p1"}
            views = {"p0": (-math.inf, seam_x_m + 0.3), "p1": (seam_x_m - 0.3, math.inf)}
            for pair, (lo, hi) in views.items():
                x0, x1 = max(x - 0.6, lo), min(x + 0.6, hi)
                seen = []
                if x1 - x0 > 0.2:
                    partial = x0 > x - 0.6 or x1 < x + 0.6
                    seen.append(_record(((x0 + x1) / 2, y), (x1 - x0, 0.8), partial))
                tracker.add(pair, stamp, seen, now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs=pairs)
        history.append(tracker.objects())
    return history


def test_a_constant_velocity_track_has_the_velocity() -> None:
    tracker = ObjectTracker()
    history = _run_mover(tracker, (1.0, 1.0), (1.6, 0.5), 12, np.random.default_rng(4))
    (track,) = history[-1]
    assert track.object_class == "moving"
    assert math.hypot(track.velocity_mps[0] - 1.6, track.velocity_mps[1] - 0.5) < 0.12
    assert track.velocity_cov_m2ps2[0][0] > 0


def test_a_mover_crossing_a_seam_keeps_its_id() -> None:
    tracker = ObjectTracker()
    history = _run_mover(
        tracker, (3.0, 1.5), (2.0, 0.0), 14, np.random.default_rng(5), seam_x_m=6.0
    )
    ids = {o.id for objects in history for o in objects}
    assert len(ids) == 1
    assert {"p0", "p1"} <= {p for objects in history for o in objects for p in o.pairs}
    assert history[-1][0].object_class == "moving"


def test_a_static_objects_track_never_gains_velocity() -> None:
    tracker = ObjectTracker()
    rng = np.random.default_rng(6)
    for k in range(40):
        jitter = rng.normal(0, 0.03, 2)
        # Now and then only a partial view, whose centre is off by a lot.
        partial = k % 5 == 3
        center = (4.0 + jitter[0] + (0.2 if partial else 0.0), 3.0 + jitter[1])
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record(center, (0.8, 0.5), partial)], 0.0)
        tracker.flush(0.0, {"p0"})
        for obj in tracker.objects():
            assert obj.object_class == "static" and obj.velocity_mps == (0.0, 0.0)
    (obj,) = tracker.objects()
    assert abs(obj.size_m[0] - 0.8) < 1e-6 and not obj.partial


def test_a_moved_static_object_ends_its_track_and_starts_a_new_one() -> None:
    tracker = ObjectTracker()
    for k in range(10):
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record((4.0, 3.0), (0.8, 0.5))], 0.0)
        tracker.flush(0.0, {"p0"})
    (before,) = tracker.objects()
    for k in range(10, 16):
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record((6.0, 3.0), (0.8, 0.5))], 0.0)
        tracker.flush(0.0, {"p0"})
    (after,) = tracker.objects()
    assert after.id != before.id and after.object_class == "static"


def test_the_predicted_layer_covers_a_mover_ahead_and_clears_behind() -> None:
    resolution = 0.05
    tracker = ObjectTracker()
    _run_mover(tracker, (2.0, 2.0), (2.0, 0.0), 6, np.random.default_rng(7))
    (track,) = tracker.objects()
    seen_ns = track.last_seen_ns
    ahead_ns = seen_ns + int(0.6e9)  # latency + one frame interval
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    shape = grid.window.shape
    grid.integrate(  # every cell seen free
        grid.window,
        np.full(shape, -2.0, np.float32),
        np.full(shape, np.nan, np.float32),
        np.full(shape, 20, np.uint16),
        seen_ns,
    )
    evidence = grid.layer("occupancy")
    assert grid.set_predicted(tracker.sweep(resolution, seen_ns, ahead_ns))
    served, predicted = grid.served_occupancy(), grid.layer("predicted")
    x_now = track.center_m[0]

    def cell(x: float, y: float) -> tuple[int, int]:
        return int(y / resolution), int(x / resolution)

    ahead = cell(x_now + 0.6 + 2.0 * 0.5, 2.0)  # its front edge 0.5 s ahead
    behind = cell(x_now - 0.8, 2.0)
    assert served[ahead] == OCCUPIED and predicted[ahead]
    assert served[behind] == evidence[behind] < OCCUPIED and not predicted[behind]
    assert grid.layer("occupancy")[ahead] == evidence[ahead]  # the evidence is not touched

    # The next frame sees it 1 m further on: the sweep starts there, the cells it left are clear.
    version = grid.version
    later_ns = seen_ns + FRAME_NS
    grid.set_predicted(tracker.sweep(resolution, later_ns, later_ns + int(0.6e9)))
    left = cell(x_now - 0.3, 2.0)
    assert not grid.layer("predicted")[left]
    assert grid.served_occupancy()[left] == evidence[left]
    assert grid.version > version and not dirty_window(grid).empty
    # The mover gone: the layer empties once, then costs nothing.
    assert grid.set_predicted([]) and not grid.layer("predicted").any()
    assert not grid.set_predicted([])


def test_a_broken_movers_footprint_is_not_swept() -> None:
    """A moving track 50 km across (detections merged across a forged capture) is a broken
    detection: it sweeps nothing, as it leaves no wake (its cells asked numpy for terabytes)."""
    tracker = ObjectTracker()
    for k in range(8):
        broken = _record((2.0 + 0.5 * k, 2.0), (5e4, 5e4))
        tracker.add("p0", T0_NS + k * FRAME_NS, [broken], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (track,) = tracker.objects()
    assert track.object_class == "moving"
    seen_ns = track.last_seen_ns
    assert tracker.sweep(0.05, seen_ns, seen_ns + FRAME_NS) == []


def test_a_movers_wake_forgets_the_hits_no_frame_has_shown_since() -> None:
    """The cells a moving track stood on and left, occupied and not shown by the newest capture,
    become unknown (floor too sparse in pixels to be measured free again keeps a hit for seconds);
    where it stands now (even unmeasured since), a static object beside its path that frames keep
    measuring, one whose plain top was measured once (where its track stands), and cells away from
    its path are kept. A broken detection 10⁶ km long costs nothing."""
    resolution = 0.05
    tracker = ObjectTracker()
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    shape = grid.window.shape
    hit = np.full(shape, 2.0, np.float32)
    heights = np.full(shape, 1.0, np.float32)
    counts = np.full(shape, 20, np.uint16)
    for k in range(8):
        stamp = T0_NS + k * FRAME_NS
        x = 2.0 + 1.0 * k * FRAME_NS / 1e9
        crate = _record((4.0, 2.7), (0.8, 0.5))  # beside the path, its plain top measured once
        tracker.add("p0", stamp, [_record((x, 2.0), (1.2, 0.8)), crate], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
        if k == 0:
            grid.integrate(Window(72, 49, 16, 10), hit[:10, :16], heights, counts, stamp)
        if k < 7:  # the last two frames measure nothing where the mover stands
            where, _ = polygon_cells(corners((x, 2.0), (1.2, 0.8), 0.0), resolution)
            grid.integrate(where, hit[: where.rows, : where.cols], heights, counts, stamp)
        beside = Window(40, 48, 60, 1)  # a static object along the path's edge, 0.05 m off it
        grid.integrate(beside, hit[:1, :60], heights, counts, stamp)
    grid.integrate(Window(20, 80, 10, 1), hit[:1, :10], heights, counts, T0_NS)  # elsewhere
    broken = _record((3.0, 60.0), (1e9, 0.8))  # apart from the rest
    tracker.add("p0", T0_NS + 8 * FRAME_NS, [_record((6.0, 2.0), (1.2, 0.8)), broken], now_s=0.0)
    grid.integrate(beside, hit[:1, :60], heights, counts, T0_NS + 8 * FRAME_NS)
    tracker.flush(now_s=0.0, live_pairs={"p0"})
    track = next(t for t in tracker.objects() if t.object_class == "moving")
    before = grid.served_occupancy().copy()
    assert grid.forget_occupied(*tracker.wake(resolution)) > 0
    after = grid.served_occupancy()

    def cell(x: float, y: float) -> tuple[int, int]:
        return int(y / resolution), int(x / resolution)

    occupied = 65  # map.yaml's occupied_thresh
    left = cell(3.5, 2.0)  # where it stood 2.5 s before the last frame
    now = cell(track.center_m[0] - 0.5, 2.0)  # last hit 1 s before the last frame
    assert before[left] > occupied and after[left] == -1
    assert before[now] > occupied and after[now] > occupied
    assert after[48, 70] > occupied and after[80, 25] > occupied
    assert before[49, 80] > occupied and after[49, 80] > occupied  # the crate's edge in the wake


def test_a_wake_cell_the_newest_capture_did_not_show_is_forgotten() -> None:
    """A mover at 2 m/s, 1 m a frame: the floor it stood on a frame ago and the newest capture did
    not show (its own shadow for the camera) is forgotten now, not a frame later; a wake cell the
    newest capture showed occupied is kept."""
    resolution = 0.05
    tracker = ObjectTracker()
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    hit = np.full(grid.window.shape, 2.0, np.float32)
    heights = np.full(grid.window.shape, 1.0, np.float32)
    counts = np.full(grid.window.shape, 20, np.uint16)
    last = 6
    for k in range(last + 1):
        stamp = T0_NS + k * FRAME_NS
        x = 2.0 + 1.0 * k
        tracker.add("p0", stamp, [_record((x, 2.0), (1.2, 0.8))], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
        where, _ = polygon_cells(corners((x, 2.0), (1.2, 0.8), 0.0), resolution)
        grid.integrate(where, hit[: where.rows, : where.cols], heights, counts, stamp)
    shown = Window(130, 40, 2, 2)  # (6.5, 2.0) m: in the wake, and occupied in the newest capture
    grid.integrate(shown, hit[:2, :2], heights, counts, T0_NS + last * FRAME_NS)
    assert next(t for t in tracker.objects()).object_class == "moving"
    before = grid.served_occupancy().copy()
    grid.forget_occupied(*tracker.wake(resolution))
    after = grid.served_occupancy()
    trailing = (40, 136)  # (6.8, 2.0) m: under it a frame ago, not now
    kept = (shown.j0, shown.i0)
    occupied = 65  # map.yaml's occupied_thresh
    assert before[trailing] > occupied and after[trailing] == -1
    assert after[kept] > occupied


def test_only_static_objects_are_outlined() -> None:
    """A box seen whole and in place for the static time gives the cells whose centres its
    footprint holds, and so does one only ever seen partly (its footprint a lower bound, inside
    the object); before that, and a mover and a broken detection 10⁶ km long, give none."""
    resolution = 0.05
    tracker = ObjectTracker()
    box = _record((3.0, 2.0), (0.8, 0.5), yaw=0.3)
    part = _record((6.0, 5.0), (0.5, 0.4), partial=True)
    broken = _record((3.0, 60.0), (1e9, 0.8))
    for k in range(9):  # 4 s at 2 Hz
        mover = _record((8.0 + 1.0 * k * FRAME_NS / 1e9, 2.0), (1.2, 0.8))
        tracker.add("p0", T0_NS + k * FRAME_NS, [box, part, broken, mover], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
        if k == 2:
            assert tracker.outlines(resolution) == []  # confirmed, not yet static
    outlines = sorted(tracker.outlines(resolution), key=lambda outline: outline.window.i0)
    assert len(outlines) == 2
    for outline, (center, size, yaw) in zip(
        outlines, [((3.0, 2.0), (0.8, 0.5), 0.3), ((6.0, 5.0), (0.5, 0.4), 0.0)], strict=True
    ):
        track = next(t for t in tracker.objects() if abs(t.center_m[0] - center[0]) < 0.5)
        assert track.center_m == pytest.approx(center, abs=1e-6)
        expected_window, expected = polygon_cells(corners(center, size, yaw), resolution)
        assert outline.window == expected_window and np.array_equal(outline.cells, expected)
        # Its edge: the cells whose centres lie within half a cell inside a side.
        x, y = outline.window.cell_centers(resolution)
        c, s = math.cos(yaw), math.sin(yaw)
        along, across = (
            (x - center[0]) * c + (y - center[1]) * s,
            (y - center[1]) * c - (x - center[0]) * s,
        )
        inside_m = np.minimum(size[0] / 2 - np.abs(along), size[1] / 2 - np.abs(across))
        clear = np.abs(inside_m - resolution / 2) > 1e-6
        assert np.array_equal(outline.edge[clear], (expected & (inside_m < resolution / 2))[clear])
        assert outline.edge.any() and (outline.cells & ~outline.edge).any()


def test_an_outline_under_a_cell_across_is_all_edge() -> None:
    """A footprint smaller than a cell both ways holds at most the cell its centre lies in, and
    that cell is its edge: the footprint's error decides it."""
    outline = Outline.of((1.025, 1.025), (0.04, 0.04), 0.3, False, 0.05)
    assert outline.cells.sum() == 1 and np.array_equal(outline.edge, outline.cells)
    wide = Outline.of((1.0, 1.025), (0.3, 0.04), 0.0, False, 0.05)
    assert wide.cells.sum() == 6 and np.array_equal(wide.edge, wide.cells)


def test_polygon_cells_are_the_cells_whose_centres_it_holds() -> None:
    window, mask = polygon_cells(corners((1.0, 1.0), (0.5, 0.3), 0.0), 0.05)
    assert mask.sum() == 10 * 6
    assert window.cols >= 10 and window.rows >= 6


@pytest.mark.parametrize("partial", [False, True])
def test_partial_flag_reaches_the_object(partial: bool) -> None:
    tracker = ObjectTracker()
    for k in range(4):  # enough views to be sure of a size
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record((4.0, 3.0), (0.8, 0.5), partial)], 0.0)
        tracker.flush(0.0, {"p0"})
    (obj,) = tracker.objects()
    assert obj.partial is partial


@pytest.mark.parametrize(
    ("widths", "unsure"),
    [
        ((0.17, 0.23, 0.22, 0.31, 0.32, 0.30, 0.22, 0.25), True),  # a top matched in part
        ((0.40, 0.41, 0.40, 0.39, 0.40, 0.41, 0.40, 0.40), False),
        ((0.40, 0.40, 0.40), True),  # too few views to tell
    ],
)
def test_views_too_few_or_that_disagree_on_the_size_say_size_unsure(
    widths: tuple[float, ...], unsure: bool
) -> None:
    """Complete views of one box whose widths spread (interquartile range) over 5 % of their
    median give no confident size, nor do three views: the object says ``size_unsure`` (not
    ``partial``: the median is no lower bound); eight views within a centimetre do not."""
    tracker = ObjectTracker()
    for k, width in enumerate(widths):
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record((4.0, 3.0), (0.48, width))], 0.0)
        tracker.flush(0.0, {"p0"})
    (obj,) = tracker.objects()
    assert obj.size_unsure is unsure and not obj.partial
    assert obj.size_m[1] == pytest.approx(float(np.median(widths)))


def test_a_view_of_a_piece_of_what_the_map_shows_occupied_says_partial() -> None:
    """A box of 0.9 × 0.6 m whose cells the frames show occupied (and the ring of cells its edges
    touch), measured whole by every view at 0.45 × 0.3 (a strip of a plain top): the map's cells
    say it is larger, so the object says partial. Measured at its size it stays complete, and so
    does the piece without the map to check against; a neighbour's cells do not count, and a broken
    detection 10⁶ km long costs nothing."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    box_window, _ = polygon_cells(corners((3.0, 2.0), (0.9, 0.6), 0.0), resolution)
    ring = Window(box_window.i0 - 1, box_window.j0 - 1, box_window.cols + 2, box_window.rows + 2)
    neighbour = Window(ring.i1 + 1, ring.j0, 20, ring.rows)  # a cell apart: not connected
    for window in (ring, neighbour):
        shape = window.shape
        grid.integrate(
            window,
            np.full(shape, 2.0, np.float32),
            np.full(shape, 1.0, np.float32),
            np.full(shape, 20, np.uint16),
            T0_NS,
        )
    for size, piece in (((0.45, 0.3), True), ((0.9, 0.6), False)):
        tracker = ObjectTracker()
        for k in range(4):  # enough views to be sure of a size
            broken = _record((5.0, 4.2), (1e9, 0.8))  # over the map
            tracker.add("p0", T0_NS + k * FRAME_NS, [_record((3.0, 2.0), size), broken], 0.0)
            tracker.flush(now_s=0.0, live_pairs={"p0"})
        checked, _ = sorted(
            tracker.objects(tracker.check_against(grid).pieces), key=lambda o: o.size_m[0]
        )
        unchecked, _ = sorted(tracker.objects(), key=lambda o: o.size_m[0])
        assert checked.partial is piece
        assert not unchecked.partial and checked.size_m == unchecked.size_m


def test_the_cells_a_plain_tops_measured_rim_encloses_are_not_served_free() -> None:
    """The frames call the floor free, and measure plain tops of the floor's grey at their edges
    alone (the rest of each top free, like the floor):
    - a top measured whole, its rim all round: its footprint the frames do not agree with;
    - a box measured on one half (all occupied, so the frames agree with that footprint), its
      other half's rim reaching 0.7 m further: a piece of what the map shows.
    The cells each encloses are served unknown, not free, and the floor beyond stays free. A
    textured box measured whole keeps the free floor beside a strip of hits that touches it (a
    lane line's fattening): its footprint is neither."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))

    def put(window: Window, logodds: float) -> None:
        measure(grid, window, logodds, T0_NS)

    put(Window(0, 0, 200, 100), -2.0)  # the floor: free
    for rim in (Window(140, 56, 12, 1), Window(140, 63, 12, 1)):  # x 7.0–7.6 m, y 2.8–3.2 m
        put(rim, 4.0)
    for rim in (Window(140, 57, 1, 6), Window(151, 57, 1, 6)):
        put(rim, 4.0)
    put(Window(60, 40, 10, 12), 4.0)  # a box's near half: x 3.0–3.5 m, y 2.0–2.6 m …
    for rim in (Window(70, 40, 14, 1), Window(70, 51, 14, 1), Window(83, 41, 1, 10)):
        put(rim, 4.0)  # … and its far half's rim, to x = 4.2 m
    put(Window(20, 24, 12, 8), 4.0)  # a textured box, x 1.0–1.6 m, y 1.2–1.6 m …
    put(Window(32, 24, 1, 10), 4.0)  # … and a strip touching it, x 1.6–1.65 m, y 1.2–1.7 m
    tracker = ObjectTracker()
    views = [
        _record((7.3, 3.0), (0.6, 0.4)),
        _record((3.25, 2.3), (0.6, 0.5), yaw=math.pi / 2),
        _record((1.3, 1.4), (0.6, 0.4)),
    ]
    for k in range(9):  # 4 s at 2 Hz: static
        tracker.add("p0", T0_NS + k * FRAME_NS, views, now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})

    def served(x: float, y: float) -> int:
        return int(grid.served_occupancy()[int(y / resolution), int(x / resolution)])

    free_max = 25  # map.yaml's free_thresh
    tops = [(7.3, 3.0), (3.9, 2.3)]
    floor = [(7.3, 3.4), (7.8, 3.0), (4.4, 2.3), (3.9, 2.8), (1.5, 1.65)]
    assert all(0 <= served(*cell) <= free_max for cell in tops + floor)  # the frames' verdict
    grid.set_contested(tracker.check_against(grid).enclosures)
    assert [served(*cell) for cell in tops] == [-1, -1]
    assert all(0 <= served(*cell) <= free_max for cell in floor)


def test_the_cells_just_outside_a_static_objects_footprint_are_its_fringe() -> None:
    """The frames call a cell occupied all round each of three boxes (side faces, fattening):
    a box measured whole, a small box standing against its side (touching, it is a piece of what
    the map shows: ``partial``), and a box every view of which is cut by the image border at its
    right side (its size a lower bound), which the map shows going on past that side. The whole
    box's ring is its fringe, served unknown, out to ``fringe_reach_m`` (a streak of fattening 25
    cm long, a stray hit apart from it, and the small box's ring within that reach) less the
    small box's cells; the cut box's ring is its fringe only where free floor lies beyond it
    within its shorter reach, not past its cut side; the floor two cells out stays free and the
    boxes' own cells stay occupied, as do the streak and the hits beyond the reach."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))

    def put(window: Window, logodds: float) -> None:
        measure(grid, window, logodds, T0_NS)

    put(Window(0, 0, 200, 100), -2.0)  # the floor: free
    put(Window(19, 23, 14, 10), 4.0)  # whole box x 1.0–1.6, y 1.2–1.6, and a cell round it
    put(Window(31, 25, 6, 6), 4.0)  # a small box against it: x 1.6–1.8, y 1.3–1.5, and ring
    put(Window(99, 23, 14, 10), 4.0)  # partial box x 5.0–5.6, y 1.2–1.6, and a cell round it
    put(Window(113, 24, 3, 8), 4.0)  # … going on past its cut side to x = 5.8
    put(Window(22, 17, 1, 6), 4.0)  # a streak below the whole box at x 1.1–1.15, y 0.85–1.15
    put(Window(26, 35, 1, 1), 4.0)  # stray hits above it, free floor between: 17.5 cm out …
    put(Window(26, 38, 1, 1), 4.0)  # … and 32.5 cm out
    tracker = ObjectTracker()
    views = [
        _record((1.3, 1.4), (0.6, 0.4)),
        _record((1.7, 1.4), (0.2, 0.2)),
        _record((5.3, 1.4), (0.6, 0.4), partial=True),
    ]
    for k in range(9):  # 4 s at 2 Hz: static
        tracker.add("p0", T0_NS + k * FRAME_NS, views, now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})

    def served(x: float, y: float) -> int:
        return int(grid.served_occupancy()[int(y / resolution), int(x / resolution)])

    fringe = [(0.975, 1.4), (1.3, 1.175), (1.3, 1.625), (0.975, 1.175), (1.625, 1.225)]
    fringe += [(1.125, 1.125), (1.125, 0.975), (1.825, 1.4)]  # 7.5, 22.5 cm out; the small box's
    fringe += [(1.325, 1.775)]  # a stray hit, not connected to the box
    fringe += [(4.975, 1.4), (5.3, 1.625), (4.975, 1.175)]  # the cut box's, free floor beyond
    # Past the cut side; the streak 27.5 and 32.5 cm out; a stray hit 32.5 cm out.
    beyond = [(5.625, 1.4), (1.125, 0.925), (1.125, 0.875), (1.325, 1.925)]
    tops = [(1.3, 1.4), (1.625, 1.4), (1.7, 1.4), (5.3, 1.4)]  # (1.625, 1.4): the small box's
    floor = [(0.925, 1.4), (1.3, 1.675)]
    assert all(served(*cell) >= OCCUPIED_MIN for cell in fringe)  # the frames' verdict
    assert grid.set_fringe(tracker.check_against(grid).fringes)
    assert [served(*cell) for cell in fringe] == [-1] * len(fringe)
    assert all(served(*cell) >= OCCUPIED_MIN for cell in tops + beyond)
    assert all(0 <= served(*cell) <= 25 for cell in floor)


@pytest.mark.parametrize("unsure", [False, True])
def test_an_unsure_objects_fringe_starts_half_its_views_spread_outside_it(unsure: bool) -> None:
    """A box at x 1.0–1.6, y 1.2–1.6 m whose frames call three rings of cells round it occupied
    (their centres 2.5, 7.5 and 12.5 cm out). Its views agree on 0.6 × 0.4 m, or their widths
    spread 8 cm (interquartile range: ``size_unsure``, the median still 0.4): a sure size's
    fringe starts 1 cm out, all three rings served unknown; an unsure one's 4 cm out, half the
    spread, the inner ring left to the frames (occupied), the outer two served unknown."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 60, 60)))
    measure(grid, Window(0, 0, 60, 60), -2.0, T0_NS)  # the floor: free
    measure(grid, Window(17, 21, 18, 14), 4.0, T0_NS)  # x 0.85–1.75, y 1.05–1.75
    widths = (0.30, 0.50, 0.40, 0.36, 0.44, 0.40, 0.32, 0.48, 0.40) if unsure else (0.40,) * 9
    tracker = ObjectTracker()
    for k, width in enumerate(widths):  # 4 s at 2 Hz: static
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record((1.3, 1.4), (0.6, width))], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (obj,) = tracker.objects()
    assert obj.size_unsure is unsure and obj.size_m[1] == pytest.approx(0.4)
    assert grid.set_fringe(tracker.check_against(grid).fringes)

    def served(x: float, y: float) -> int:
        return int(grid.served_occupancy()[int(y / resolution), int(x / resolution)])

    inner, outer = [(0.975, 1.4), (1.3, 1.625)], [(0.925, 1.4), (1.3, 1.725), (1.725, 1.4)]
    assert all(served(*cell) == -1 for cell in outer)
    assert all((served(*cell) >= OCCUPIED_MIN) is unsure for cell in inner)
    assert all(served(*cell) == -1 for cell in inner) is not unsure
    assert served(1.3, 1.4) >= OCCUPIED_MIN  # the box


def _static_box_served(
    center: tuple[float, float],
    size: tuple[float, float],
    evidence: list[tuple[Window, float]],
) -> Callable[..., int]:
    """A map of free floor with x 1.0–1.6, y 1.2–1.6 occupied and then ``evidence`` (windows and
    log-odds), and a box static there with the footprint ``center`` × ``size``: the cell served
    at (x, y), before serving its track's layers (``serve`` false) or after."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 100, 100)))
    measure(grid, Window(0, 0, 100, 100), -2.0, T0_NS)  # the floor: free
    measure(grid, Window(20, 24, 12, 8), 4.0, T0_NS)  # x 1.0–1.6, y 1.2–1.6
    for window, logodds in evidence:
        measure(grid, window, logodds, T0_NS)
    tracker = ObjectTracker()
    for k in range(9):  # 4 s at 2 Hz: static
        tracker.add("p0", T0_NS + k * FRAME_NS, [_record(center, size)], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})

    def served(x: float, y: float, serve: bool = True) -> int:
        if serve:
            outlined, tops, _ = serve_tracks(grid, tracker, outline_static=True)
            grid.set_predicted(outlined + tops)
        return int(grid.served_occupancy()[int(y / resolution), int(x / resolution)])

    return served


def test_a_cell_within_a_static_footprints_error_outside_it_is_never_served_free() -> None:
    """A box stands at x 1.0–1.63 m; the frames call its cells occupied up to x = 1.6 and the
    column beyond free (its rim cells, whose centres at x 1.625 the box holds, read mostly floor)
    but for two cells of it; its views measure it to x = 1.62. That column's centres lie 0.5 cm
    outside the footprint, within its error: served unknown where free, occupied where occupied.
    The floor 5.5 cm out (x 1.675) and the cell beside the box's long side 2.5 cm out (y 1.625)
    stay free; the box's cells stay occupied."""
    served = _static_box_served(
        (1.31, 1.4),
        (0.62, 0.4),
        [(Window(32, 24, 1, 2), 4.0)],  # x 1.6–1.65, y 1.2–1.3
    )
    rim, floor, top = (1.625, 1.4), [(1.675, 1.4), (1.3, 1.625)], (1.3, 1.4)
    assert 0 <= served(*rim, serve=False) <= 25  # the frames' verdict
    assert served(*rim) == -1
    assert all(0 <= served(*cell) <= 25 for cell in floor)
    assert all(served(*cell) >= OCCUPIED_MIN for cell in (top, (1.625, 1.225), (1.625, 1.275)))


def test_an_edge_cell_of_a_static_footprint_the_frames_call_free_is_served_unknown() -> None:
    """A box measured 4 cm too long at x 1.0–1.64 m (a piece joined from two pairs' views),
    whose frames call x 1.0–1.6 occupied and the column beyond free: that column's cells, whose
    centres (x 1.625) lie within half a cell inside the footprint's edge, are the box's or the
    floor's by the footprint's error; the frames saw floor there, so they are served unknown,
    not occupied. An edge cell the frames call occupied stays occupied; so does a cell deep
    inside that they call free (a plain top the floor model took for floor), which the outline
    holds up."""
    served = _static_box_served(
        (1.32, 1.4),
        (0.64, 0.4),
        [
            (Window(26, 28, 1, 1), -6.0),  # x 1.3–1.35, y 1.4–1.45: read as floor
            (Window(32, 24, 1, 1), 4.0),  # x 1.6–1.65, y 1.2–1.25
        ],
    )
    free_edge, occupied_edge, plain_top = (1.625, 1.4), (1.625, 1.225), (1.325, 1.425)
    assert all(0 <= served(*cell, serve=False) <= 25 for cell in (free_edge, plain_top))
    assert served(*free_edge) == -1
    assert all(served(*cell) >= OCCUPIED_MIN for cell in (occupied_edge, plain_top, (1.3, 1.3)))
    assert 0 <= served(1.675, 1.4) <= 25  # the floor beyond the footprint


@pytest.mark.parametrize("cut", [False, True])
def test_the_cells_just_outside_a_movers_measured_footprint_are_its_fringe(cut: bool) -> None:
    """A forklift at 2 m/s, seen whole, a person walking beside it against its flank: the
    frames call occupied their footprints, a band 0.15 m deep behind the forklift (its plain rear
    face's pixels take its top's disparity) and a few cells past 0.2 m. The band is its fringe,
    served unknown, out to ``wake_margin_m`` past its footprint as the newest capture measured
    it, but not where the person stands; the cells further out, the movers' own and the floor
    are as the frames say. A view cut by the image's border (``partial``: a lower bound) gives
    no fringe."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    tracker = ObjectTracker()
    for k in range(7):
        x = 2.0 + 1.0 * k
        forklift = _record((x, 2.0), (1.2, 0.8), partial=k == 6 and cut)
        person = _record((x, 1.325), (0.55, 0.55), partial=k == 6 and cut)
        tracker.add("p0", T0_NS + k * FRAME_NS, [forklift, person], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    assert [t.object_class for t in tracker.objects()] == ["moving", "moving"]
    measure(grid, Window(0, 0, 200, 100), -2.0, T0_NS)  # the floor: free
    measure(grid, Window(148, 32, 24, 16), 4.0, T0_NS)  # the forklift: x 7.4–8.6, y 1.6–2.4
    measure(grid, Window(145, 32, 3, 16), 4.0, T0_NS)  # its rear face's hits: x 7.25–7.4
    measure(grid, Window(143, 38, 2, 2), 4.0, T0_NS)  # x 7.15–7.25, y 1.9–2.0: past 0.2 m behind
    measure(grid, Window(155, 21, 11, 11), 4.0, T0_NS)  # the person: x 7.75–8.3, y 1.05–1.6

    def served(x: float, y: float) -> int:
        return int(grid.served_occupancy()[int(y / resolution), int(x / resolution)])

    band = [(7.325, 1.7), (7.375, 2.3), (7.325, 2.35), (7.275, 1.65)]
    movers = [(8.0, 1.575), (8.0, 1.3), (7.425, 2.0), (8.0, 2.0)]  # their own
    beyond, floor = [(7.175, 1.925)], [(6.5, 2.0), (8.0, 2.6), (7.0, 1.25)]
    assert all(served(*cell) >= OCCUPIED_MIN for cell in band)  # the frames' verdict
    grid.set_fringe(tracker.check_against(grid).fringes)
    if cut:
        assert all(served(*cell) >= OCCUPIED_MIN for cell in band)
    else:
        assert [served(*cell) for cell in band] == [-1] * len(band)
    assert all(served(*cell) >= OCCUPIED_MIN for cell in movers + beyond)
    assert all(0 <= served(*cell) <= 25 for cell in floor)


@pytest.mark.parametrize("merged", [False, True])
def test_a_movers_top_no_frame_measured_is_served_occupied(merged: bool) -> None:
    """A forklift at 1 m/s whose frames measured its rim (a cell wide) but nothing on its plain
    top, and one cell of the top as floor: the cells 10 cm or more inside its newest view that no
    frame measured are its top, served occupied; those nearer its sides stay unknown, as does the
    cell read as floor (its footprint now is contested). A view 2.5 m long (a mover merged with
    something) has no top: unknown."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    tracker = ObjectTracker()
    size = (2.5, 0.8) if merged else (1.2, 0.8)
    for k in range(7):
        view = _record((2.0 + 1.0 * k, 2.0), size)
        tracker.add("p0", T0_NS + k * FRAME_NS, [view], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    assert [t.object_class for t in tracker.objects()] == ["moving"]
    # The floor around x 7.4–8.6, y 1.6–2.4 (the forklift's cells now), its rim, a floor reading.
    for window in (Window(0, 0, 148, 100), Window(172, 0, 28, 100)):
        measure(grid, window, -2.0, T0_NS)
    for window in (Window(148, 0, 24, 32), Window(148, 48, 24, 52), Window(155, 40, 1, 1)):
        measure(grid, window, -2.0, T0_NS)
    for window in (Window(148, 32, 24, 1), Window(148, 47, 24, 1)):
        measure(grid, window, 4.0, T0_NS)
    for window in (Window(148, 33, 1, 14), Window(171, 33, 1, 14)):
        measure(grid, window, 4.0, T0_NS)

    def served(x: float, y: float) -> int:
        return int(grid.served_occupancy()[int(y / resolution), int(x / resolution)])

    top, near_side, read_free = [(8.025, 2.025), (7.525, 1.725)], (7.475, 2.025), (7.775, 2.025)
    assert all(served(*cell) == -1 for cell in [*top, near_side])  # no frame measured them
    outlined, tops, _ = serve_tracks(grid, tracker, outline_static=True)
    grid.set_predicted(outlined + tops)
    assert [served(*cell) for cell in top] == ([-1, -1] if merged else [100, 100])
    assert served(*near_side) == -1 and served(*read_free) == -1
    assert served(8.0, 1.625) >= OCCUPIED_MIN and 0 <= served(6.5, 2.0) <= 25


@pytest.mark.parametrize("round_", [True, False])
def test_a_round_objects_outline_and_fringe_follow_its_circle(round_: bool) -> None:
    """A drum 0.5 m across whose frames call the whole square around it occupied (its side
    faces and fattening): seen round, its outline is the circle's cells and the square's corner
    cells outside the circle are its fringe, served unknown; seen as a box, the corners are its
    own cells and stay occupied."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 100, 100)))
    measure(grid, Window(0, 0, 100, 100), -2.0, T0_NS)  # the floor: free
    measure(grid, Window(35, 35, 10, 10), 4.0, T0_NS)  # x, y 1.75–2.25: the square round the drum
    tracker = ObjectTracker()
    for k in range(9):  # 4 s at 2 Hz: static
        view = _record((2.0, 2.0), (0.5, 0.5), round_=round_)
        tracker.add("p0", T0_NS + k * FRAME_NS, [view], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (obj,) = tracker.objects()
    assert obj.round is round_
    (cells,) = tracker.outlines(resolution)
    window, outline = cells.window, cells.cells
    if round_:  # the circle, grown by a centimetre (its radius is measured to about one)
        x, y = window.cell_centers(resolution)
        distance = np.hypot(x - 2.0, y - 2.0)
        clear = np.abs(distance - 0.26) > 0.002  # the polygon's sides leave a millimetre or two
        assert np.array_equal(outline[clear], (distance <= 0.26)[clear])
        # Its edge: the ring of cells whose centres lie within half a cell inside the circle.
        ring = (distance > 0.26 - resolution / 2) & (distance <= 0.26)
        clear &= np.abs(distance - (0.26 - resolution / 2)) > 0.002
        assert np.array_equal(cells.edge[clear], ring[clear]) and ring.any()
    centre, corner = (40, 40), (35, 35)  # cells (i, j): x, y 2.025 and 1.775
    assert outline[centre[1] - window.j0, centre[0] - window.i0]
    corner_in_outline = 0 <= corner[1] - window.j0 < window.rows and bool(
        outline[corner[1] - window.j0, corner[0] - window.i0]
    )
    assert corner_in_outline is not round_
    grid.set_fringe(tracker.check_against(grid).fringes)
    served = grid.served_occupancy()
    assert bool(served[corner[1], corner[0]] == -1) is round_
    assert served[centre[1], centre[0]] >= OCCUPIED_MIN


def test_a_track_is_round_where_most_of_its_views_are_and_takes_their_diameter() -> None:
    """Five round views of a drum 0.5 m across and three box views of it (0.56 × 0.44: a
    rectangle fitted where its rim had few steps) make a round track of the round views'
    diameter; a partial view is never round (a circle cut by the image's border is not one)."""
    tracker = ObjectTracker()
    views = [_record((2.0, 2.0), (0.5, 0.5), round_=True)] * 5 + [
        _record((2.0, 2.0), (0.56, 0.44), yaw=0.3)
    ] * 3
    for k, view in enumerate(views):
        tracker.add("p0", T0_NS + k * FRAME_NS, [view], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (obj,) = tracker.objects()
    assert obj.round and obj.size_m == (0.5, 0.5) and obj.yaw_rad == 0.0
    cut = merge_capture([("p0", _record((2.0, 2.0), (0.5, 0.3), partial=True, round_=True))], 0.1)
    assert not cut[0].round


def _truth(
    name: str, center: tuple[float, float], moving: bool, v: tuple[float, float] = (0.0, 0.0)
) -> TruthObject:
    return TruthObject(
        name=name,
        shape="box",
        moving=moving,
        center_m=(center[0], center[1], 0.5),
        yaw_rad=0.0,
        size_m=(0.8, 0.5, 1.0),
        velocity_mps=v,
    )


def _track(
    id_: int, center: tuple[float, float], moving: bool, v: tuple[float, float] = (0.0, 0.0)
) -> TrackedObject:
    return TrackedObject(
        id=id_,
        object_class="moving" if moving else "static",
        center_m=center,
        size_m=(0.82, 0.5),
        yaw_rad=0.0,
        top_m=1.0,
        velocity_mps=v,
        velocity_cov_m2ps2=((0.0, 0.0), (0.0, 0.0)),
        first_seen_ns=0,
        last_seen_ns=0,
        pairs=["p0"],
        partial=False,
        detections=5,
    )


def test_eval_matches_static_objects_and_counts_splits_and_id_switches() -> None:
    truth = [_truth("a", (1.0, 1.0), False), _truth("b", (4.0, 1.0), False)]
    matches = match_static(
        [_track(1, (1.0, 1.0), False), _track(2, (4.1, 1.0), False), _track(3, (3.8, 1.1), False)],
        truth,
    )
    assert [m.tracks for m in matches] == [1, 2]
    assert abs(matches[0].errors_pct[0] - 2.5) < 1e-9

    mover = [_truth("m", (2.0, 2.0), True, (1.0, 0.0))]
    history = [([_track(7, (2.1, 2.0), True, (1.1, 0.0))], mover) for _ in range(3)]
    history.append(([_track(8, (2.0, 2.1), True, (1.0, 0.0))], mover))
    scores = score_movers(history)
    assert scores.id_switches == {"m": 1} and scores.tracked_share == {"m": 1.0}
    assert max(scores.velocity_error_mps) < 0.11
    assert scores.phantom_share == 0.0
    # A moving track 1.5 m from the mover, in one list of five: a phantom mover.
    history.append(([_track(8, (2.0, 2.0), True), _track(9, (3.5, 2.0), True)], mover))
    assert score_movers(history).phantom_share == 0.2


def test_a_mover_missed_by_the_last_frames_is_neither_swept_nor_reported() -> None:
    """Where it went is a guess: the map does not sweep it and ``map/objects`` does not list it
    (a fleet planner would steer around a person who reversed a second ago at the place it
    turned); the tracker keeps it, and it comes back under its id when seen again."""
    tracker = ObjectTracker()
    _run_mover(tracker, (2.0, 2.0), (2.0, 0.0), 6, np.random.default_rng(8))
    seen_ns = tracker.stamp_ns
    assert tracker.sweep(0.05, seen_ns, seen_ns + FRAME_NS)
    (mover,) = [o for o in tracker.objects() if o.object_class == "moving"]
    tracker.add("p0", seen_ns + FRAME_NS, [], 0.0)  # one capture without it: still followed
    tracker.flush(0.0, {"p0"})
    assert [o.id for o in tracker.objects()] == [mover.id]
    tracker.add("p0", seen_ns + 2 * FRAME_NS, [], 0.0)  # two
    tracker.flush(0.0, {"p0"})
    assert tracker.sweep(0.05, tracker.stamp_ns, tracker.stamp_ns + FRAME_NS) == []
    assert tracker.objects() == []
    x = 2.0 + 2.0 * 8 * FRAME_NS / 1e9  # seen again where its motion carried it
    tracker.add("p0", seen_ns + 3 * FRAME_NS, [_record((x, 2.0), (1.2, 0.8))], 0.0)
    tracker.flush(0.0, {"p0"})
    assert [(o.id, o.object_class) for o in tracker.objects()] == [(mover.id, "moving")]


@pytest.mark.parametrize(
    ("camera", "partial", "lifted"),
    [(True, False, True), (False, False, False), (True, True, False)],
)
def test_a_movers_view_measured_low_under_a_camera_is_put_back_at_its_top(
    camera: bool, partial: bool, lifted: bool
) -> None:
    """Near a pair's nadir a plain top is matched nowhere and filled at the fattened floor's
    height: a forklift (1.2 × 0.8 m, 1 m up) measured at 0.19 m lies 1.16 times as large about
    that nadir. Its moving track, measured whole at 1 m, puts the view back on its rays, to its
    size and place; not without the camera's place, nor a partial view (a view's edge may have
    cut the top off)."""
    tracker = ObjectTracker()
    _run_mover(tracker, (2.0, 2.0), (2.0, 0.0), 8, np.random.default_rng(11))
    (track,) = tracker.tracks
    assert track.moving
    stamp = T0_NS + 8 * FRAME_NS
    true_xy = (2.0 + 2.0 * 8 * FRAME_NS / 1e9, 2.0)
    nadir = (true_xy[0] + 0.4, true_xy[1] - 0.2, 6.0)
    scale = (6.0 - 0.19) / (6.0 - 1.0)
    seen_xy = (
        nadir[0] + (true_xy[0] - nadir[0]) * scale,
        nadir[1] + (true_xy[1] - nadir[1]) * scale,
    )
    low = _record(seen_xy, (1.2 * scale, 0.8 * scale), partial=partial, top=0.19, low=True)
    tracker.add("p0", stamp, [low], 0.0, nadir if camera else None)
    tracker.flush(0.0, {"p0"})
    view = tracker.wake_footprints[-1]
    assert view.stamp_ns == stamp
    x, y, length, width, _ = view.rectangle
    if lifted:
        assert math.dist((x, y), true_xy) < 1e-6
        assert (length, width) == pytest.approx((1.2, 0.8))
    else:
        assert length == pytest.approx(1.2 * scale)
    assert ("p0" in tracker.cameras_m) is camera
    tracker.flush(0.0, set())  # the pair left: where its camera stood is forgotten
    assert tracker.cameras_m == {}


def test_a_track_faster_than_a_mover_drives_is_not_reported() -> None:
    """A track whose velocity no warehouse mover reaches joined two objects (or pieces of
    things) frame to frame: it is not swept, nor reported as an object."""
    tracker = ObjectTracker()
    _run_mover(tracker, (1.0, 2.0), (2.0, 0.0), 6, np.random.default_rng(9))
    assert [o.object_class for o in tracker.objects()] == ["moving"]
    (track,) = tracker.tracks
    track.state[2] = tracker.config.sweep_max_speed_mps + 0.5
    assert tracker.objects() == []
    assert tracker.sweep(0.05, tracker.stamp_ns, tracker.stamp_ns + FRAME_NS) == []


def _warehouse_at_one_hertz(
    seconds: int, seed: int
) -> list[tuple[list[TrackedObject], list[TruthObject]]]:
    """The default scene's movers (a forklift at 2 m/s on a loop whose ends are 1 m legs, a person
    at 1.2 m/s reversing at each end of a 5.3 m walk) and static objects, each seen once a second,
    as the live simulator delivers frames on two cores: centres jitter by 3 cm, and the movers'
    sizes by 10 %. Returns the tracker's objects with the truth at every capture."""
    scene = generate_scene(seed)
    rng = np.random.default_rng(seed)
    tracker = ObjectTracker()
    history = []
    for k in range(seconds):
        stamp_ns = T0_NS + k * 10**9
        truth = scene.truth_objects(stamp_ns / 1e9)
        records = []
        for obj in truth:
            size = np.array(obj.size_m[:2]) * (rng.uniform(0.9, 1.1, 2) if obj.moving else 1.0)
            center = np.array(obj.center_m[:2]) + rng.normal(0.0, 0.03, 2)
            records.append(
                DetectionRecord(
                    center_m=(float(center[0]), float(center[1])),
                    size_m=(float(size[0]), float(size[1])),
                    yaw_rad=obj.yaw_rad,
                    top_m=obj.top_m,
                    points=500,
                    partial=False,
                )
            )
        tracker.add("p0", stamp_ns, records, now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
        history.append((tracker.objects(), truth))
    return history


@pytest.mark.parametrize("seed", [0, 2])
def test_movers_keep_their_ids_through_turns_at_one_frame_a_second(seed: int) -> None:
    """A forklift runs 2 m between frames, farther than its length, and reverses at each end of
    its loop within one frame; the person reverses within one: each keeps one id, is tracked as
    moving most of the time, and static objects beside their paths keep theirs."""
    history = _warehouse_at_one_hertz(60, seed)
    scores = score_movers(history[5:])
    assert scores.id_switches == {"mover_forklift": 0, "mover_person": 0}
    assert min(scores.tracked_share.values()) >= 0.8
    assert float(np.median(scores.velocity_error_mps)) < 0.3
    # Every static object is one track from its lock on, and no track is two objects.
    ever = {o.id: o for objects, _ in history[10:] for o in objects if o.object_class == "static"}
    matches = match_static(list(ever.values()), [o for o in history[-1][1] if not o.moving])
    assert all(m.tracks == 1 and not m.merged for m in matches)
    assert len(ever) == len(matches)


def test_a_standing_objects_track_takes_its_object_before_a_passer_by() -> None:
    """Seen live at a frame a second: a box seen thrice (not yet locked static), a one-frame ghost
    1.1 m off it, then a forklift 1.8 m off it. One assignment over all gave the box's track the
    forklift (both within its gate) and the ghost's the box; the box's track must take the box."""
    tracker = ObjectTracker()
    box = _record((7.49, 3.68), (0.61, 0.45))
    ghost = _record((8.04, 4.64), (0.5, 0.3))
    forklift = _record((8.52, 2.15), (1.2, 0.8))
    for k, records in enumerate([[box], [box], [box, ghost], [box, forklift]]):
        tracker.add("p0", T0_NS + k * 10**9, records, now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (box_track,) = [t for t in tracker.tracks if t.id == 1]
    assert math.dist(box_track.center_m, box.center_m) < 0.05


def test_a_track_begun_off_its_object_is_static_once_it_stood_there() -> None:
    """A track begun on a one-frame ghost 1.1 m off an object that then takes the object's
    detections is locked static once it stood on it for ``static_after_s``."""
    tracker = ObjectTracker()
    records = [_record((8.04, 4.64), (0.5, 0.3))] + [_record((7.49, 3.68), (0.61, 0.45))] * 9
    for k, record in enumerate(records):
        tracker.add("p0", T0_NS + k * FRAME_NS, [record], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (track,) = tracker.objects()
    assert track.object_class == "static" and tracker.tracks[0].static


def test_a_track_turns_at_most_two_frames_in_a_row() -> None:
    """A forklift-sized track runs straight, then its object seems to turn at each of three
    frames in a row (pieces of other things on its way): it follows two turns (a U-turn at an
    aisle's end), not the third, which starts a track of its own."""
    tracker = ObjectTracker()
    path = [(1.0 + 2.0 * k, 2.0) for k in range(5)]
    path += [(9.5, 3.5), (8.0, 2.0), (9.5, 0.5)]  # three turns in a row
    for k, centre in enumerate(path):
        tracker.add("p0", T0_NS + k * 10**9, [_record(centre, (1.2, 0.8))], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
        if k == 4:
            (mover,) = tracker.tracks
            assert mover.moving
        if k == 6:
            assert [t.id for t in tracker.tracks] == [mover.id]
            assert math.dist(mover.center_m, centre) < 0.1
    assert math.dist(mover.center_m, path[-2]) < 0.1  # not the third turn
    assert any(math.dist(t.center_m, path[-1]) < 0.1 for t in tracker.tracks if t is not mover)


@pytest.mark.parametrize("low", [True, False])
def test_a_low_tracks_outline_is_grown_by_its_sides_uncertainty(low: bool) -> None:
    """A pallet's sides are measured to a few centimetres either way: its outline, the cells fusion
    serves occupied where the frames agree (but for its edge cells they call free, unknown), is
    its footprint grown by ``low_margin_m``, so a rim cell whose centre lies just outside the
    measured side is not served free on the frames' free readings. A box's outline is its
    footprint."""
    tracker = ObjectTracker()
    margin = tracker.config.low_margin_m
    for k in range(9):  # 4 s at 2 Hz: static
        view = _record((2.03, 2.0), (1.18, 0.78), top=0.15, low=low)
        tracker.add("p0", T0_NS + k * FRAME_NS, [view], now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    (cells,) = tracker.outlines(0.05)
    window, outline = cells.window, cells.cells
    x, y = window.cell_centers(0.05)
    half = np.array([0.59, 0.39]) + (margin if low else 0.0)
    inside = (np.abs(x - 2.03) <= half[0]) & (np.abs(y - 2.0) <= half[1])
    assert np.array_equal(outline, inside)
    # x 2.625: 0.5 cm past the measured end (2.62), inside the true pallet's (2.63)
    assert bool(inside[np.argmin(np.abs(y[:, 0] - 2.0)), np.argmin(np.abs(x[0] - 2.625))]) is low


def test_a_track_is_low_where_most_of_its_views_are() -> None:
    """Two low views of four (a pallet's deck once taken with a box on it) make no low track;
    three of four do."""
    for lows, expected in ((2, False), (3, True)):
        tracker = ObjectTracker()
        for k in range(4):
            view = _record((2.0, 2.0), (1.2, 0.8), top=0.15, low=k < lows)
            tracker.add("p0", T0_NS + k * FRAME_NS, [view], now_s=0.0)
            tracker.flush(now_s=0.0, live_pairs={"p0"})
        (track,) = tracker.tracks
        assert track.low is expected


def test_free_cells_under_a_mover_now_are_served_unknown() -> None:
    """A forklift (1.2 × 0.8 m) moving at 1 m/s over floor the frames still call free (the floor before it came,
    or a plain side the floor model took for floor): the cells of its footprint at the newest
    capture are served unknown, the floor around it stays free, and a standing box's cells are
    not touched."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    measure(grid, Window(0, 0, 200, 100), -2.0, T0_NS)  # the floor: free
    tracker = ObjectTracker()
    _run_mover(tracker, (1.0, 2.0), (1.0, 0.0), 8, np.random.default_rng(3))
    (mover,) = [t for t in tracker.objects() if t.object_class == "moving"]
    grid.set_contested(tracker.movers_now(resolution))
    served = grid.served_occupancy()
    x, y = mover.center_m
    at = (round(y / resolution - 0.5), round(x / resolution - 0.5))
    assert served[at] == -1
    assert served[at[0], at[1] + 11] == -1  # 0.55 m ahead of its centre: its front edge's cells
    assert 0 <= served[at[0], at[1] + 20] <= 25  # 1 m ahead: floor
    assert 0 <= served[at[0] + 20, at[1]] <= 25  # 1 m beside it


def test_free_cells_under_a_track_starting_off_are_served_unknown() -> None:
    """A person (0.5 × 0.4 m) that has just turned or started: seen three times 0.6 m apart,
    too few to call it moving, over floor the frames call free (``--floor plain``: its blue side
    has the floor's grey). Its newest view's cells are served unknown; where it was before, a box
    seen three times in one place (standing) and a 3 m view (several objects merged in one
    detection) keep the frames' verdict."""
    resolution = 0.05
    grid = FusedGrid(GridParams(resolution_m=resolution, bounds=Window(0, 0, 200, 100)))
    measure(grid, Window(0, 0, 200, 100), -2.0, T0_NS)  # the floor: free
    tracker = ObjectTracker()
    for k in range(3):
        views = [
            _record((2.0 + 0.6 * k, 2.0), (0.5, 0.4)),
            _record((6.0, 2.0), (0.5, 0.4)),
            _record((8.0 + 0.6 * k, 3.5), (3.0, 0.6)),
        ]
        tracker.add("p0", T0_NS + k * FRAME_NS, views, now_s=0.0)
        tracker.flush(now_s=0.0, live_pairs={"p0"})
    assert len(tracker.tracks) == 3 and not any(t.moving for t in tracker.tracks)
    grid.set_contested(tracker.movers_now(resolution))
    served = grid.served_occupancy()

    def at(x: float, y: float) -> int:
        return int(served[int(y / resolution), int(x / resolution)])

    assert [at(3.2, 2.0), at(3.4, 2.15), at(3.0, 1.85)] == [-1, -1, -1]  # its newest view
    for x, y in ((2.0, 2.0), (2.6, 2.0), (6.0, 2.0), (9.2, 3.5)):
        assert 0 <= at(x, y) <= 25, (x, y)


def test_a_frame_of_more_objects_than_a_message_holds_keeps_the_best_measured() -> None:
    """The message would be refused whole (``MAX_DETECTIONS``): the pair reports those measured
    from the most points instead."""
    many = [
        Detection((0.1 * k, 0.0), 0.2, 0.15, 0.0, 1.0, points=k, partial=False)
        for k in range(MAX_DETECTIONS + 10)
    ]
    header = detections_header(many, "p0", 1, 10**9)
    assert len(header.detections) == MAX_DETECTIONS
    assert min(d.points for d in header.detections) == 10


def test_forgotten_tracks_leave_the_frame_interval_as_it_was() -> None:
    """Fusion forgets every track when no capture comes for long (the pairs stopped); the pause
    until the next capture was taken as a frame interval (60 s: paths swept seconds ahead)."""
    tracker = ObjectTracker()
    box = DetectionRecord(
        center_m=(1.0, 1.0), size_m=(0.5, 0.4), yaw_rad=0.0, top_m=1.0, points=500, partial=False
    )
    for k in range(4):
        tracker.update(1 + k * 500_000_000, merge_capture([("p0", box)], 0.1))
    assert tracker.tracks and tracker.frame_interval_s == pytest.approx(0.5)
    version = tracker.version
    tracker.forget()
    assert not tracker.tracks and tracker.version == version + 1
    tracker.update(60 * 10**9, merge_capture([("p0", box)], 0.1))
    assert len(tracker.tracks) == 1 and tracker.frame_interval_s == pytest.approx(0.5)
