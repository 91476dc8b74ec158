"""Objects' outlines refined on the image's edges: a ray-traced overhead view of a box or a round
top on a textured (or plain) floor (side faces included, edges antialiased), a detection a few
centimetres off as the points give it, and the refined outline within a centimetre of the truth."""

import math
import warnings
from dataclasses import replace

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from common.arrays import F64
from services.depth.object_edges import EdgeConfig, ImageView, _Across, refine_on_edges
from services.depth.objects import Detection

WIDTH, HEIGHT, FOCAL_PX, SUPERSAMPLE = 320, 240, 277.0, 4
VIEW = ImageView(
    focal_px=FOCAL_PX,
    cx_px=WIDTH / 2 - 0.5,
    cy_px=HEIGHT / 2 - 0.5,
    R_world_rect=np.diag([1.0, -1.0, -1.0]),  # looking straight down, image rows along −y
    C_world=np.array([5.0, 4.0, 6.0]),
)
FLOOR_GREY, SIDE_GREY = 150.0, 70.0


def _texture(x: F64, y: F64, base: float) -> F64:
    grey: F64 = base + 12 * np.sin(9 * x + 2 * y) * np.cos(7 * y - x) + 6 * np.sin(31 * x - 23 * y)
    return grey


def _render(
    center: tuple[float, float],
    size: tuple[float, float],
    yaw: float,
    top_m: float,
    round_top: bool,
    top_grey: float,
    plain_floor: bool = False,
    stripe_inside_m: float | None = None,
    stripe_m: float = 0.02,
) -> npt.NDArray[np.uint8]:
    """The rectified left image of one object on the floor, ray-traced at 4× and area-averaged;
    ``plain_floor``: one grey with the sensor's noise; ``stripe_inside_m``: a dark tape
    ``stripe_m`` wide across the top, this far inside its high-x side."""
    n_u, n_v = WIDTH * SUPERSAMPLE, HEIGHT * SUPERSAMPLE
    u, v = np.meshgrid(
        (np.arange(n_u) + 0.5) / SUPERSAMPLE - 0.5, (np.arange(n_v) + 0.5) / SUPERSAMPLE - 0.5
    )
    ray = np.stack([(u - VIEW.cx_px) / FOCAL_PX, (v - VIEW.cy_px) / FOCAL_PX, np.ones_like(u)])
    ray = np.einsum("ij,jhw->ihw", VIEW.R_world_rect, ray)
    origin = VIEW.C_world
    # Into the object's frame (yaw about its centre).
    c, s = math.cos(yaw), math.sin(yaw)
    ox, oy = origin[0] - center[0], origin[1] - center[1]
    o = np.array([c * ox + s * oy, -s * ox + c * oy, origin[2]])
    d = np.stack([c * ray[0] + s * ray[1], -s * ray[0] + c * ray[1], ray[2]])
    t_top = (top_m - o[2]) / d[2]
    top_x, top_y = o[0] + t_top * d[0], o[1] + t_top * d[1]
    if round_top:
        radius = size[0] / 2
        on_top = np.hypot(top_x, top_y) <= radius
        # The side: |o + t d|_xy = r, the nearer root, at a height within the object.
        a = d[0] ** 2 + d[1] ** 2
        b = 2 * (o[0] * d[0] + o[1] * d[1])
        disc = b * b - 4 * a * (o[0] ** 2 + o[1] ** 2 - radius**2)
        t_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        on_side = (
            (disc >= 0) & ~on_top & (o[2] + t_side * d[2] >= 0) & (o[2] + t_side * d[2] <= top_m)
        )
    else:
        half = np.array([size[0] / 2, size[1] / 2])
        on_top = (np.abs(top_x) <= half[0]) & (np.abs(top_y) <= half[1])
        t_floor = -o[2] / d[2]
        on_side = np.zeros_like(on_top)
        for axis in (0, 1):
            for sign in (-1, 1):
                t = (sign * half[axis] - o[axis]) / d[axis]
                other = o[1 - axis] + t * d[1 - axis]
                z = o[2] + t * d[2]
                on_side |= (
                    (t > 0)
                    & (t < t_floor)
                    & (np.abs(other) <= half[1 - axis])
                    & (z >= 0)
                    & (z <= top_m)
                )
        on_side &= ~on_top
    t_floor = -origin[2] / ray[2]
    floor = _texture(origin[0] + t_floor * ray[0], origin[1] + t_floor * ray[1], FLOOR_GREY)
    if plain_floor:
        floor = np.full_like(floor, FLOOR_GREY)
    top = _texture(top_x, top_y, top_grey)
    if stripe_inside_m is not None:
        inside = size[0] / 2 - top_x
        top = np.where(
            (inside >= stripe_inside_m) & (inside < stripe_inside_m + stripe_m), 30.0, top
        )
    grey = np.where(on_top, top, np.where(on_side, SIDE_GREY, floor))
    small = cv2.resize(grey.astype(np.float32), (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
    if plain_floor:  # the sensor's noise, a grey level
        small = small + np.random.default_rng(0).normal(0.0, 1.0, (HEIGHT, WIDTH))
    return np.clip(small, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("yaw", [0.0, 0.4, 1.2])
def test_a_box_top_is_measured_to_a_centimetre_from_a_prior_off_by_several(yaw: float) -> None:
    center, size, top = (5.7, 4.5), (0.83, 0.47), 1.1
    image = _render(center, size, yaw, top, round_top=False, top_grey=95.0)
    # As the points give it: 4 cm long, 3 cm narrow, 2 cm off centre.
    prior = Detection((center[0] + 0.02, center[1] - 0.015), 0.87, 0.44, yaw, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    assert abs(refined.length_m - size[0]) < 0.01 and abs(refined.width_m - size[1]) < 0.01
    assert math.dist(refined.center_xy_m, center) < 0.01
    assert refined.yaw_rad == prior.yaw_rad and not refined.round


def test_a_round_top_is_a_circle_of_its_diameter() -> None:
    center, diameter, top = (4.4, 3.3), 0.41, 1.0
    image = _render(center, (diameter, diameter), 0.0, top, round_top=True, top_grey=90.0)
    # The rectangle fit to a disc's points falls short of its rim.
    prior = Detection((center[0] - 0.01, center[1] + 0.01), 0.37, 0.35, 0.3, top, 300, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    assert refined.length_m == refined.width_m and refined.round
    assert abs(refined.length_m - diameter) < 0.01
    assert math.dist(refined.center_xy_m, center) < 0.01


def test_a_side_without_contrast_keeps_the_points_place() -> None:
    # A top as grey as the floor: only the sides facing the camera show a step (to the dark side
    # faces beyond them); the far sides meet the floor unseen and stay where the points put them.
    image = _render((5.6, 4.4), (0.8, 0.5), 0.0, 1.0, round_top=False, top_grey=FLOOR_GREY)
    prior = Detection((5.61, 4.4), 0.84, 0.52, 0.0, 1.0, 400, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    x_low, x_high = (
        refined.center_xy_m[0] - refined.length_m / 2,
        refined.center_xy_m[0] + refined.length_m / 2,
    )
    y_low, y_high = (
        refined.center_xy_m[1] - refined.width_m / 2,
        refined.center_xy_m[1] + refined.width_m / 2,
    )
    assert refined.yaw_rad == 0.0
    assert abs(x_high - (5.61 + 0.42)) < 1e-9 and abs(y_high - (4.4 + 0.26)) < 1e-9
    assert abs(x_low - 5.2) < 0.01 and abs(y_low - 4.15) < 0.01


def test_an_outline_outside_the_image_is_left_as_it_is() -> None:
    image = _render((5.0, 4.0), (0.8, 0.5), 0.0, 1.0, round_top=False, top_grey=95.0)
    far = Detection((9.0, 4.0), 0.8, 0.5, 0.0, 1.0, 400, True)
    assert refine_on_edges([far], image, VIEW)[0] == far
    assert refine_on_edges([replace(far, top_m=5.99)], image, VIEW)[0] == replace(far, top_m=5.99)


def test_a_low_top_keeps_its_points_outline() -> None:
    """A pallet's deck, the openings below it and its zone's paint give steps a few centimetres
    apart: a low detection keeps the outline its points' density gave, while the same outline of
    a box as low, measured on its top's points, moves onto its edges."""
    image = _render((5.0, 4.0), (1.2, 0.8), 0.0, 0.144, round_top=False, top_grey=95.0)
    low = Detection((5.02, 4.0), 1.24, 0.82, 0.0, 0.144, 600, False, low=True)
    assert refine_on_edges([low], image, VIEW)[0] == low
    refined = refine_on_edges([replace(low, low=False)], image, VIEW)[0]
    assert abs(refined.length_m - 1.2) < 0.01 and abs(refined.width_m - 0.8) < 0.01


def test_over_a_plain_floor_a_side_is_found_where_the_matcher_carried_the_top_out() -> None:
    """With no texture beyond a side to hold it, the matcher carries a top's disparity 9 cm out
    over the floor (``--floor plain``: box_0 0.73 m wide of 0.64): the side is looked for further
    inside there and lands on the top's edge."""
    center, size, top = (5.7, 4.5), (0.64, 0.86), 1.07
    image = _render(center, size, 0.0, top, round_top=False, top_grey=110.0, plain_floor=True)
    # The high-x side (away from the camera at x = 5) 9 cm out, as the points put it.
    prior = Detection((center[0] + 0.045, center[1]), 0.86, 0.73, math.pi / 2, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    assert abs(refined.width_m - size[0]) < 0.01 and abs(refined.length_m - size[1]) < 0.01
    assert math.dist(refined.center_xy_m, center) < 0.01


def test_over_a_textured_floor_a_print_inside_the_top_is_not_its_side() -> None:
    """A dark tape 7 cm inside a side (10 cm inside the points' side) is a stronger step than a
    top about as grey as the floor: where the floor is textured (the matcher's fattening short),
    the side is not looked for that far inside and stays on the top's edge (``--floor speckle``:
    box_0 came out 0.54 m wide of 0.64 when it was)."""
    center, size, top = (5.6, 4.4), (0.64, 0.86), 1.07
    image = _render(center, size, 0.0, top, False, top_grey=FLOOR_GREY - 20, stripe_inside_m=0.07)
    prior = Detection((center[0] + 0.015, center[1]), 0.86, 0.67, math.pi / 2, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    assert abs(refined.center_xy_m[0] + refined.width_m / 2 - (center[0] + size[0] / 2)) < 0.01


def test_a_side_the_points_put_out_over_its_face_is_found_behind_the_face() -> None:
    """A tall plain box (a forklift, 1.1 m) shows the camera a face 13 cm wide below its near
    side, and the face's pixels near the top take the top's disparity: the points put that side
    at the face's foot, past the search's reach inside from there (offline, the forklift 1.34 m
    long of 1.2). The foot is the strong step nearest the points' side; the top's edge lies the
    face's width further in, as wide as the face below it, not below the points' side."""
    center, size, top = (6.3, 4.0), (1.2, 0.8), 1.1
    image = _render(center, size, 0.0, top, round_top=False, top_grey=FLOOR_GREY)
    foot_x = VIEW.C_world[0] + (center[0] - size[0] / 2 - VIEW.C_world[0]) * (
        (VIEW.C_world[2] - top) / VIEW.C_world[2]
    )
    length = center[0] + size[0] / 2 - foot_x  # 1.33 m: from the face's foot
    prior = Detection((foot_x + length / 2, center[1]), length, 0.8, 0.0, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    assert abs(refined.length_m - size[0]) < 0.01 and abs(refined.width_m - size[1]) < 0.01
    assert math.dist(refined.center_xy_m, center) < 0.01


def test_a_print_where_a_top_would_end_behind_its_face_is_not_its_side() -> None:
    """A side the points put right, its face below it: a dark tape inside the top where the
    top's edge would lie had the points put the side at the face's foot is no side, since the
    face's foot shows beyond the chosen step, where that step's face ends."""
    center, size, top = (3.7, 4.0), (1.2, 0.8), 1.1
    face_m = (VIEW.C_world[0] - (center[0] + size[0] / 2)) * top / VIEW.C_world[2]
    tape_m = face_m / (1 - top / VIEW.C_world[2])  # where the top's edge would lie
    image = _render(center, size, 0.0, top, False, top_grey=FLOOR_GREY, stripe_inside_m=tape_m)
    prior = Detection(center, 1.2, 0.8, 0.0, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    assert abs(refined.length_m - size[0]) < 0.01 and math.dist(refined.center_xy_m, center) < 0.01


def test_a_far_side_the_matcher_carried_past_the_search_is_found_further_in() -> None:
    """A low box's side facing away from the camera, over a textured floor, 10 cm inside the
    points' side (the matcher carried the top's disparity over the floor beyond it: ``--seed 5
    --pairs 6``, box_4 0.67 m wide of 0.59): no step within the search, so it is looked for
    further inside, and the step there is the top's edge (its top as grey as inside the sides
    found, floor between it and the points' side)."""
    center, size, top = (5.7, 4.5), (0.64, 0.86), 0.24
    image = _render(center, size, 0.0, top, round_top=False, top_grey=95.0)
    # The high-x side (away from the camera at x = 5) 10 cm out, as the points put it.
    prior = Detection((center[0] + 0.05, center[1]), 0.86, 0.74, math.pi / 2, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    far_side_m = refined.center_xy_m[0] + refined.width_m / 2
    assert abs(far_side_m - (center[0] + size[0] / 2)) < 0.01  # 10 cm out without the search


@pytest.mark.parametrize("print_m", [0.02, 0.12])
def test_a_print_further_in_than_the_search_is_not_a_far_side(print_m: float) -> None:
    """The points' side of a far side 9 cm inside the top's edge (a plain top matched in part), a
    dark print 8 cm inside that: a search further in meets the print's step, not the top's
    edge, and the side stays where the points put it (``--floor speckle``: box_3 0.21 m wide of
    0.40 when a print was taken). A narrow tape: the grey just inside its step is the top's
    again, whose contrast with the top beyond is nil; a wide print: its grey is not the top's
    inside the sides found."""
    center, size, top = (5.7, 4.5), (0.64, 0.86), 0.24
    image = _render(center, size, 0.0, top, False, 95.0, stripe_inside_m=0.17, stripe_m=print_m)
    prior = Detection((center[0] - 0.045, center[1]), 0.86, 0.55, math.pi / 2, top, 500, False)
    refined = refine_on_edges([prior], image, VIEW)[0]
    points_side_m = prior.center_xy_m[0] + prior.width_m / 2
    assert refined.center_xy_m[0] + refined.width_m / 2 > points_side_m - 0.01


def test_the_grey_of_no_sample_is_nan_and_says_nothing_on_stderr() -> None:
    """numpy's mean of an empty slice warned on stderr, into a depth process's structured log
    (a soak's log held 'Mean of empty slice' from object_edges)."""
    across = _Across.at(0.5, VIEW, EdgeConfig())
    profile = np.linspace(0.0, 1.0, across.offsets_m.size)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(across.grey_at(profile, 10.0, 11.0))  # beyond every sample
        assert across.grey_at(profile, -1.0, 1.0) == pytest.approx(profile.mean())
