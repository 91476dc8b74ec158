"""The seam join: what lies between two pieces, a group of them, and which views are one object."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.footprints import corners, polygon_cells
from common.lattice import Window
from services.fusion.grid import FusedGrid, GridParams
from services.fusion.seams import SeamConfig, SeamView, gap_cells, measured, seam_groups
from tests.tiles import measure


def test_the_gap_between_two_pieces_is_their_hulls_cells_less_their_own() -> None:
    """Two 0.3 × 0.6 m pieces 0.4 m apart along x: the gap is the 8 × 12 cells between them."""
    a = corners((2.15, 2.5), (0.3, 0.6), 0.0)
    b = corners((2.85, 2.5), (0.3, 0.6), 0.0)
    window, between = gap_cells(a, b, 0.05)
    x_m, y_m = window.cell_centers(0.05)
    assert int(np.count_nonzero(between)) == 8 * 12
    assert np.all((x_m[between] > 2.3) & (x_m[between] < 2.7))
    assert np.all((y_m[between] > 2.2) & (y_m[between] < 2.8))


def test_a_group_is_its_views_pairs_the_hull_of_their_footprints_and_the_highest_top() -> None:
    """Two 0.3 × 0.6 m views 0.4 m apart: the group's footprint is the 1.0 × 0.6 m rectangle
    around them, counter-clockwise, its cells all 20 × 12."""
    group = SeamView.around([_view("p0", 2.0, 2.3), _view("p1", 2.7, 3.0, top=0.9)])
    assert group.pairs == {"p0", "p1"} and group.top_m == 1.0
    _, own = polygon_cells(group.polygon_m, 0.05)
    assert int(np.count_nonzero(own)) == 20 * 12
    x, y = group.polygon_m[:, 0], group.polygon_m[:, 1]
    assert 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) > 0  # counter-clockwise


def test_a_view_no_join_can_hold_is_not_measured_nor_rasterised() -> None:
    """A view up to √2 racks long may be a piece of one (the rack's diagonal); a longer one is
    not measured, its cells never looked at: a forged 50 km one asked numpy for terabytes."""
    grid = _map([(1.0, 9.0)], [])  # the row y 2.2–2.8 m occupied from x 1 to 9 m
    config = SeamConfig()
    longest_m = math.sqrt(2) * config.max_length_m
    assert measured(corners((5.0, 2.5), (longest_m - 0.05, 0.6), 0.0), grid, config)
    assert not measured(corners((5.0, 2.5), (longest_m + 0.05, 0.6), 0.0), grid, config)
    assert not measured(corners((5.0, 2.5), (5e4, 5e4), 0.0), grid, config)


def _map(pieces_m: list[tuple[float, float]], free: list[tuple[float, float]]) -> FusedGrid:
    """A 10 × 5 m map whose frames saw the floor free but for the row y 2.2–2.8 m, where they saw
    the pieces (x from–to, m) occupied and ``free`` spans free; the rest of the row unknown (the
    seam's gap at the tops' height)."""
    grid = FusedGrid(GridParams(resolution_m=0.05, bounds=Window(0, 0, 200, 100)))
    for window in (Window(0, 0, 200, 44), Window(0, 56, 200, 44)):
        measure(grid, window, -2.0)
    for spans, logodds in ((pieces_m, 4.0), (free, -2.0)):
        for x0, x1 in spans:
            measure(grid, Window(round(x0 / 0.05), 44, round((x1 - x0) / 0.05), 12), logodds)
    return grid


def _view(pair: str, x0: float, x1: float, top: float = 1.0) -> SeamView:
    """A pair's partial view of a top 0.6 m wide along y = 2.5 m, from x0 to x1."""
    return SeamView(frozenset({pair}), corners(((x0 + x1) / 2, 2.5), (x1 - x0, 0.6), 0.0), top)


@pytest.mark.parametrize(
    ("case", "groups"),
    [
        ("gap unseen", [[0, 1]]),
        ("floor seen between", [[0], [1]]),
        ("half of the gap seen free", [[0], [1]]),
        ("a column of the gap seen free", [[0, 1]]),
        ("a lower top", [[0], [1]]),
        ("map not measured yet", [[0], [1]]),
        ("together longer than a rack", [[0], [1]]),
        ("a chain longer than a rack", [[0], [1, 2]]),
        ("a pair's two pieces", [[0, 1], [2]]),
        ("a diagonal longer than a rack", [[0], [1]]),
    ],
)
def test_views_a_seams_gap_keeps_apart_are_one_object(case: str, groups: list[list[int]]) -> None:
    """A 1.0 × 0.6 m box from x = 2.0 to 3.0, 1 m high, at a seam: pair p0 sees its top to
    x = 2.3, pair p1 from x = 2.7; the 0.4 m between is in neither view at that height (unknown in
    the map, the floor around it free). One object (one column of eight free, past a piece's rim,
    still joins); two where the map saw the floor between (all of it, or half), where one piece
    stands half as high, where the map has measured nothing yet, or where the pieces would make an
    object longer than a rack (a wall's pieces, one per pair along it): two pieces 1.9 m long,
    three in a row 3.2 m long (the nearer two joined, not the third, which the second alone would
    take), two along a diagonal 3.4 m long together (2.8 m along either axis). p0's two pieces
    with p1's between: p1's joins the nearer, once."""
    views = [_view("p0", 2.0, 2.3), _view("p1", 2.7, 3.0)]
    free: list[tuple[float, float]] = []
    if case == "floor seen between":
        free = [(2.3, 2.7)]
    elif case == "half of the gap seen free":
        free = [(2.3, 2.5)]  # 4 of the gap's 8 columns
    elif case == "a column of the gap seen free":
        free = [(2.3, 2.35)]
    elif case == "a lower top":
        views[1] = _view("p1", 2.7, 3.0, top=0.5)
    elif case == "together longer than a rack":
        views = [_view("p0", 0.4, 2.3), _view("p1", 2.7, 4.6)]
    elif case == "a chain longer than a rack":
        views = [_view("p0", 0.2, 1.0), _view("p1", 1.3, 2.5), _view("p2", 2.8, 3.4)]
    elif case == "a pair's two pieces":
        views = [_view("p0", 1.1, 1.7), _view("p1", 2.0, 2.3), _view("p0", 2.7, 3.3)]
    spans = [(float(v.polygon_m[:, 0].min()), float(v.polygon_m[:, 0].max())) for v in views]
    grid = _map([] if case == "map not measured yet" else spans, free)
    if case == "a diagonal longer than a rack":  # on ground measured occupied all over
        grid = _map([(0.0, 10.0)], [])
        measure(grid, Window(0, 0, 200, 100), 6.0)
        along = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4)])
        views = [
            SeamView(
                frozenset({pair}),
                corners(tuple(np.array([5.0, 2.5]) + side * 0.95 * along), (1.5, 0.6), math.pi / 4),
                1.0,
            )
            for pair, side in (("p0", -1), ("p1", 1))
        ]
    assert sorted(seam_groups(views, grid, SeamConfig())) == groups
