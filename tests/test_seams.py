"""The seam join's geometry: what lies between two pieces, and a piece as the wire sends it."""

from __future__ import annotations

import numpy as np

from common.footprints import corners, polygon_cells
from services.fusion.seams import Piece, gap_cells


def test_the_gap_between_two_pieces_is_their_hulls_cells_less_their_own() -> None:
    """Two 0.3 × 0.6 m pieces 0.4 m apart along x: the gap is the 8 × 12 cells between them."""
    a = corners((2.15, 2.5), (0.3, 0.6), 0.0)
    b = corners((2.85, 2.5), (0.3, 0.6), 0.0)
    window, between = gap_cells(a, b, 0.05)
    x_m, y_m = window.cell_centers(0.05)
    assert int(np.count_nonzero(between)) == 8 * 12
    assert np.all((x_m[between] > 2.3) & (x_m[between] < 2.7))
    assert np.all((y_m[between] > 2.2) & (y_m[between] < 2.8))


def test_a_piece_sent_notched_and_clockwise_is_its_convex_hull() -> None:
    """An outline another publisher sends clockwise with a notch is read as its convex hull
    (counter-clockwise), so its own cells are all those of its rectangle."""
    outline = np.array([(2.7, 2.2), (2.7, 2.8), (3.0, 2.8), (2.85, 2.5), (3.0, 2.2)])
    piece = Piece.of([outline], top_m=1.0)
    _, own = polygon_cells(piece.polygon_m, 0.05)
    assert int(np.count_nonzero(own)) == 6 * 12
    x, y = piece.polygon_m[:, 0], piece.polygon_m[:, 1]
    assert 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) > 0  # counter-clockwise
