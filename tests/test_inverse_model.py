"""The inverse sensor model's tile: one observation per cell, and the cells named hidden."""

import numpy as np
import pytest

from common.sensor_model import SensorModelParams
from services.depth.inverse_model import build_tile, thin_band_points
from services.depth.projection import WorldPoints

R = 0.05


def _points(cells: list[tuple[int, int, float]]) -> WorldPoints:
    """``n`` points at height ``h`` in cell (``i``, 0) for each (i, n, h)."""
    x = [i * R + R / 2 for i, n, _ in cells for _ in range(n)]
    heights = [h for _, n, h in cells for _ in range(n)]
    return WorldPoints(
        x_m=np.array(x, np.float32),
        y_m=np.full(len(x), R / 2, np.float32),
        height_m=np.array(heights, np.float32),
        height_sigma_m=np.full(len(x), 0.02, np.float32),
    )


def _hidden(per_cell: dict[int, int]) -> np.ndarray:
    x = [i * R + R / 2 for i, n in per_cell.items() for _ in range(n)]
    return np.array([x, [R / 2] * len(x)], np.float32)


def test_a_cell_is_hidden_only_where_hidden_pixels_outweigh_a_free_reading() -> None:
    """Floor points of pixels whose floor is hidden (floor model, rule 10): a cell with enough of
    them and at least as many as its measured pixels is hidden and carries no update; a cell
    measured occupied stays so; a cell better measured than hidden keeps its free reading."""
    # Cell 1's hit of five pixels: of four or fewer, with nothing occupied beside it, a lone hit.
    points = _points([(0, 4, 0.0), (1, 5, 0.8), (2, 9, 0.0), (5, 5, 0.0)])
    tile = build_tile(
        points, R, SensorModelParams(), 3, _hidden({0: 5, 1: 5, 2: 5, 3: 5, 4: 2, 5: 5})
    )
    assert (tile.window.i0, tile.window.cols) == (0, 6)
    hidden, count, update = tile.hidden[0], tile.count[0], tile.logodds[0]
    assert hidden[0] and count[0] == 0 and update[0] == 0  # 5 hidden over 4 free: hidden
    assert np.isnan(tile.height_m[0, 0])
    assert not hidden[1] and update[1] > 0  # measured occupied: kept
    assert not hidden[2] and update[2] < 0  # 9 free over 5 hidden: free
    assert hidden[3] and count[3] == 0  # hidden only
    assert not hidden[4] and count[4] == 0  # 2 hidden pixels: too few to say
    assert hidden[5]  # a tie: hidden
    assert tile.arrays()["hidden"].dtype == np.uint8


def test_a_tile_of_hidden_cells_alone_covers_them_and_a_tile_with_none_sends_no_layer() -> None:
    params = SensorModelParams()
    only_hidden = build_tile(_points([]), R, params, 3, _hidden({7: 4, 9: 3}))
    assert (only_hidden.window.i0, only_hidden.window.cols, only_hidden.window.rows) == (7, 3, 1)
    assert only_hidden.hidden[0].tolist() == [True, False, True]
    assert not only_hidden.count.any()
    measured = build_tile(_points([(0, 5, 0.0)]), R, params, 3, _hidden({}))
    assert not measured.hidden.any() and "hidden" not in measured.arrays()


def _points_2d(cells: dict[tuple[int, int], tuple[int, float]]) -> WorldPoints:
    """``n`` points at height ``h`` in cell (``i``, ``j``) for each (i, j): (n, h)."""
    spots = [(i, j, h) for (i, j), (n, h) in cells.items() for _ in range(n)]
    return WorldPoints(
        x_m=np.array([i * R + R / 2 for i, _, _ in spots], np.float32),
        y_m=np.array([j * R + R / 2 for _, j, _ in spots], np.float32),
        height_m=np.array([h for _, _, h in spots], np.float32),
        height_sigma_m=np.full(len(spots), 0.02, np.float32),
    )


def test_a_cell_of_too_few_pixels_reads_free_only_inside_open_measured_floor() -> None:
    """A cell of one or two floor pixels (where a passing mover left a hit) reads free when the
    3 × 3 cells around it are measured floor; not beside something in the band, not where its
    neighbours hold no pixels (inside a plain top), and never from a pixel in the band itself."""
    params = SensorModelParams()
    floor = {(i, j): (4, 0.0) for i in range(5) for j in range(5)}

    def centre(cells: dict[tuple[int, int], tuple[int, float]]) -> tuple[float, int]:
        tile = build_tile(_points_2d(cells), R, params, 3)
        row, col = 2 - tile.window.j0, 2 - tile.window.i0
        return float(tile.logodds[row, col]), int(tile.count[row, col])

    update, count = centre(floor | {(2, 2): (2, 0.0)})
    assert update < 0 and count == 2  # open floor: free
    assert centre(floor | {(2, 2): (2, 0.0), (3, 2): (4, 0.8)}) == (0.0, 0)  # beside an object
    assert centre(floor | {(2, 2): (1, 0.8)}) == (0.0, 0)  # its own pixel in the band
    lone = {(2, 2): (2, 0.0), (1, 2): (4, 0.0), (3, 2): (4, 0.0)}  # neighbours mostly empty
    assert centre(lone) == (0.0, 0)


def test_a_lone_hit_of_few_pixels_gives_no_update() -> None:
    """An occupied reading of four pixels or fewer with nothing occupied in the eight cells
    around (a few stray points on the floor) gives no update; with a diagonal neighbour occupied,
    or of more pixels (a post a cell wide), it stands."""
    params = SensorModelParams()
    floor = {(i, j): (6, 0.0) for i in range(5) for j in range(5)}

    def update_at(cells: dict[tuple[int, int], tuple[int, float]], i: int, j: int) -> float:
        tile = build_tile(_points_2d(cells), R, params, 3)
        return float(tile.logodds[j - tile.window.j0, i - tile.window.i0])

    assert update_at(floor | {(2, 2): (4, 0.5)}, 2, 2) == 0.0  # a lone hit
    assert update_at(floor | {(2, 2): (4, 0.5)}, 1, 2) < 0.0  # the floor beside reads free
    pair = floor | {(2, 2): (4, 0.5), (3, 3): (3, 0.5)}
    assert update_at(pair, 2, 2) > 0.0 and update_at(pair, 3, 3) > 0.0  # two, diagonal
    assert update_at(floor | {(2, 2): (5, 0.5)}, 2, 2) > 0.0  # five pixels: a post
    assert update_at({(2, 2): (4, 0.5)}, 2, 2) == 0.0  # alone in its tile too


ROW_Y_M = 3.5 * R
"""The row of cells the box edge lies in (j = 3), off the camera's line so both axes count."""


def _along_the_row(xs: list[float], heights: list[float]) -> WorldPoints:
    """Points at ``xs`` with ``heights`` along the row of cells ``ROW_Y_M``."""
    return WorldPoints(
        x_m=np.array(xs, np.float32),
        y_m=np.full(len(xs), ROW_Y_M, np.float32),
        height_m=np.array(heights, np.float32),
        height_sigma_m=np.full(len(xs), 0.02, np.float32),
    )


def _surfaces_and_row(
    surfaces: list[tuple[float, float, float, float, float]], row: list[tuple[float, float]]
) -> WorldPoints:
    """Flat surfaces (x from, x to, y from, y to, height; points 5 mm apart along x and 1 cm
    along y: surfaces, not lines, since the rays to a camera run aslant) and points (x, height)
    along the row of cells ``ROW_Y_M``."""
    xs = [x for x, _ in row]
    ys = [ROW_Y_M] * len(row)
    heights = [h for _, h in row]
    for start_m, end_m, from_y_m, to_y_m, height_m in surfaces:
        for y_m in np.arange(from_y_m, to_y_m, 0.01):
            surface = [*np.arange(start_m, end_m, 0.005)]
            xs += surface
            ys += [y_m] * len(surface)
            heights += [height_m] * len(surface)
    return WorldPoints(
        x_m=np.array(xs, np.float32),
        y_m=np.array(ys, np.float32),
        height_m=np.array(heights, np.float32),
        height_sigma_m=np.full(len(xs), 0.02, np.float32),
    )


def _box_edge(face_x_m: float, face_points: int = 30, top_from_m: float = 0.005) -> WorldPoints:
    """What a camera over the origin measures of a box standing at x > ``face_x_m``, 1 m tall,
    along one row of cells: the floor before its near face (a point a centimetre), its face
    (``face_points`` at heights 0.1 to 0.8 m on its line: a vertical face seen aslant fills many
    pixels) and its top from ``top_from_m`` beyond it (a point a centimetre)."""
    xs = [*np.arange(0.805, face_x_m, 0.01)]
    heights = [0.0] * len(xs)
    xs += [face_x_m] * face_points
    heights += list(np.linspace(0.1, 0.8, face_points))
    top_xs = [*np.arange(face_x_m + top_from_m, 1.20, 0.01)]
    xs += top_xs
    heights += [1.0] * len(top_xs)
    return _along_the_row(xs, heights)


def test_a_side_face_beyond_a_cells_centre_is_left_out_of_its_share() -> None:
    """Cell (19, 3) spans x 0.95–1.00 m (centre 0.975). A box's near face at 0.99 m leaves that
    centre on the open side: with the camera's position known the cell reads free, where its
    face's points alone made it occupied; a face at 0.96 m has the centre behind it, inside the
    box, and the cell reads occupied either way; so does one within a centimetre of the centre.
    One face point is too few to say where a face is: it counts as before."""
    params = SensorModelParams()
    camera = (0.0, 0.0, 3.0)

    def cell(points: WorldPoints, camera_m: tuple[float, float, float] | None) -> float:
        tile = build_tile(points, R, params, 3, None, camera_m)
        return float(tile.logodds[3 - tile.window.j0, 19 - tile.window.i0])

    assert cell(_box_edge(0.99), camera) < 0.0
    assert cell(_box_edge(0.99), None) > 0.0  # every point counted: the face fills the cell
    assert cell(_box_edge(0.96), camera) > 0.0
    assert cell(_box_edge(0.96), None) > 0.0
    assert cell(_box_edge(0.98), camera) > 0.0  # half a centimetre beyond: within the margin
    # Seen from x = 2 m, the same face points lie nearer the camera than the centre: they count
    # (from high above: at 3 m the box's top would hide that face from it).
    assert cell(_box_edge(0.99), (2.0, 0.0, 100.0)) > 0.0
    lone = _box_edge(0.99, face_points=1)
    assert cell(lone, camera) == cell(lone, None)


def test_a_cell_that_loses_its_face_points_shows_the_height_of_those_it_keeps() -> None:
    """The tile's top height in a cell whose face points were left out is that of the points it
    keeps (here the floor: the box's top begins in the next cell), not of the face: fusion takes
    a free reading's height as the floor's."""
    edge = _box_edge(0.99, top_from_m=0.015)
    tile = build_tile(edge, R, SensorModelParams(), 3, None, (0.0, 0.0, 3.0))
    row, col = 3 - tile.window.j0, 19 - tile.window.i0
    assert tile.logodds[row, col] < 0.0
    assert tile.height_m[row, col] == pytest.approx(0.0)
    everything = build_tile(edge, R, SensorModelParams(), 3, None, None)
    assert everything.height_m[row, col] == pytest.approx(0.8)  # the face's highest point


def _wall_foot(face_x_m: float, top_m: float | None) -> WorldPoints:
    """At the edge of the view, along one row of cells: the floor up to ``face_x_m`` and then, if
    ``top_m`` is None, a wall's face there, its lowest 10–20 cm (the rest is out of the view),
    else the top of something standing beyond it at that height (a point every 4 mm)."""
    points = _box_edge(face_x_m, top_from_m=1.0)  # the floor and a face, no top in the row
    floor = points.height_m < 0.05
    xs, heights = [*points.x_m[floor]], [*points.height_m[floor]]
    if top_m is None:
        xs += [face_x_m] * 30
        heights += [*np.linspace(0.1, 0.2, 30)]
    else:
        top_xs = [*np.arange(face_x_m, 1.1, 0.004)]
        xs += top_xs
        heights += [top_m] * len(top_xs)
    return _along_the_row(xs, heights)


def test_a_face_whose_top_is_out_of_the_view_is_judged_without_it() -> None:
    """A wall's foot at the edge of a view: its face at 0.99 m leaves cell (19, 3)'s centre
    (0.975) on the open side, but no top is seen above it, so without the flag its points count
    and the cell reads occupied. Flagged out of view, they are judged as a face and the cell reads
    free. A top flagged so is judged by the same majority: one from 0.96 m covers the centre and
    keeps the cell occupied, one from 0.99 m does not."""
    params = SensorModelParams()

    def cell(points: WorldPoints, flagged: bool) -> float:
        out_of_view = np.full(points.x_m.size, flagged)
        tile = build_tile(points, R, params, 3, None, (0.0, 0.0, 3.0), out_of_view)
        return float(tile.logodds[3 - tile.window.j0, 19 - tile.window.i0])

    assert cell(_wall_foot(0.99, None), flagged=False) > 0.0
    assert cell(_wall_foot(0.99, None), flagged=True) < 0.0
    assert cell(_wall_foot(0.96, 0.3), flagged=True) > 0.0
    assert cell(_wall_foot(0.99, 0.3), flagged=True) < 0.0


def test_points_a_taller_top_hides_from_the_camera_give_no_reading() -> None:
    """A camera 3 m over the origin; along one row, floor, a 1 m tall top over x 0.6–1.0 m, and
    its shadow beyond it to x = 1.5 m, where the camera sees nothing. The matcher's mixed pixels
    at the top's edge put points there at 0.3 m (cell 22: x 1.10–1.15, with a few floor points):
    every point counted, the cell reads occupied; with the camera known, they lie behind the top
    along their rays and the cell gives no reading, neither occupied nor free. A 0.3 m box at x
    1.6–1.8, past the shadow, and the top itself read occupied either way; a stray point at 1.2 m
    just before the box (a face's scatter) is one cell, no surface, and hides nothing."""
    floor = [*np.arange(0.3, 0.6, 0.01), *np.arange(1.5, 1.6, 0.01), *np.arange(1.8, 2.0, 0.01)]
    row = [(float(x), 0.0) for x in floor]
    row += [(1.11 + 0.003 * k, 0.3) for k in range(10)] + [(1.12, 0.0), (1.13, 0.0), (1.14, 0.0)]
    row.append((1.57, 1.2))  # one stray point at 1.2 m
    points = _surfaces_and_row([(0.6, 1.0, 0.0, 0.3, 1.0), (1.6, 1.8, 0.0, 0.3, 0.3)], row)
    params = SensorModelParams()

    def cells(camera_m: tuple[float, float, float] | None) -> dict[int, tuple[float, int]]:
        tile = build_tile(points, R, params, 3, None, camera_m)
        row = 3 - tile.window.j0
        return {
            i: (
                float(tile.logodds[row, i - tile.window.i0]),
                int(tile.count[row, i - tile.window.i0]),
            )
            for i in (16, 22, 32)
        }

    everything = cells(None)
    assert everything[22][0] > 0.0
    seen = cells((0.0, 0.0, 3.0))
    assert seen[22] == (0.0, 0)
    assert seen[16][0] > 0.0
    assert seen[32] == everything[32]  # every point of the box's cell kept


def test_mixed_pixels_whose_rays_graze_a_taller_top_give_no_reading() -> None:
    """A camera 3 m over the origin; a 1 m tall top over x 2.0–2.6 m (y 0–0.8 m), floor before it.
    Past the top's shadow the matcher's mixed pixels put points at 0.5 m at x 3.30–3.34 (cell 66,
    0.7 m beyond the top's edge): their rays pass 3–5 cm over that edge. Those points are on no
    surface (the pixels see the floor beyond, at a disparity between the floor's and the top's),
    and their cell gives no reading. A 0.8 m top at x 3.0–3.2 (y 0.5–0.8 m), whose rays pass
    about 0.15 m over the 1 m top but which stands only 0.2 m lower (a low top's own scatter
    stands that high beside it), and the 1 m top itself read occupied."""
    surfaces = [(1.5, 2.0, 0.0, 0.8, 0.0), (2.0, 2.6, 0.0, 0.8, 1.0), (3.0, 3.2, 0.5, 0.8, 0.8)]
    mixed = [(3.302 + 0.003 * k, 0.5) for k in range(12)]
    points = _surfaces_and_row(surfaces, mixed)
    tile = build_tile(points, R, SensorModelParams(), 3, None, (0.0, 0.0, 3.0))

    def update(i: int, j: int) -> tuple[float, int]:
        cell = j - tile.window.j0, i - tile.window.i0
        return float(tile.logodds[cell]), int(tile.count[cell])

    assert update(66, 3) == (0.0, 0)
    assert update(50, 3)[0] > 0.0  # the 1 m top
    assert all(update(i, 13)[0] > 0.0 for i in (60, 61, 62, 63))  # the 0.8 m top, every cell


def test_an_inferred_height_over_floor_the_frame_measures_gives_no_hit() -> None:
    """Band points whose height the floor model carried in (rules 7 and 8: a plain face below a
    top's edge takes the top's height and lands out over the floor in front of it) are left out
    of a cell where the frame measures two floor points or more, and no fewer than them: that
    cell reads free (the floor a mover left, which the face's points held at best neutral). A
    plain top's many inferred points with a few stray floor points among them, or with one, keep
    their cell occupied, and measured band points are never left out."""
    params = SensorModelParams()
    # Cells 0–1: a plain top inferred whole; 2: a face's inferred points over as much measured
    # floor; 3: inferred points with one floor point; 4: a top's inferred points with three stray
    # floor points; 5: measured band points beside measured floor.
    spots = [(0, 6, 1.1, True), (1, 6, 1.1, True), (2, 3, 1.1, True), (2, 3, 0.0, False)]
    spots += [(3, 4, 1.1, True), (3, 1, 0.0, False), (4, 9, 1.1, True), (4, 3, 0.0, False)]
    spots += [(5, 6, 1.1, False), (5, 3, 0.0, False)]
    points = _points([(i, n, h) for i, n, h, _ in spots])
    inferred = np.array([flag for _, n, _, flag in spots for _ in range(n)])
    with_rule = build_tile(points, R, params, 3, inferred=inferred).logodds[0]
    without = build_tile(points, R, params, 3).logodds[0]
    assert without[2] >= 0  # the face's points held the mover's old hit there …
    assert with_rule[2] < 0  # … and without them the floor there reads free
    assert min(with_rule[[0, 1, 3, 4, 5]]) > 0  # tops, strays and measured points stand
    assert with_rule[4] == pytest.approx(without[4]) and with_rule[5] == pytest.approx(without[5])


def test_band_pixels_in_a_line_one_or_two_pixels_wide_are_thin() -> None:
    """An image of 20 × 30 pixels: floor, a 1 m top 6 pixels square, a 3-pixel square at 0.3 m
    (the smallest thing standing the map keeps), two low lines in the band, one pixel wide
    (diagonal, a box's silhouette mixed against the floor beyond) and two wide (along a row, a
    wall's foot), and a line one pixel wide at 1.2 m (a plain top's edge). The low lines' pixels
    are thin; the top's, the square's and the high line's are not, nor is any floor pixel."""
    height_m = np.zeros((20, 30), np.float32)
    height_m[2:8, 2:8] = 1.0
    height_m[12:15, 3:6] = 0.3
    for k in range(8):
        height_m[3 + k, 12 + k] = 0.3
    height_m[16:18, 10:28] = 0.4
    height_m[1:12, 26] = 1.2
    valid = np.ones(height_m.shape, np.bool_)
    valid[0, :] = False  # a row the matcher left without a disparity
    valid_px = np.flatnonzero(valid)
    thin = thin_band_points(valid_px, height_m.ravel()[valid_px], height_m.shape, 0.1)
    expected = np.zeros(height_m.shape, np.bool_)
    expected[[3 + k for k in range(8)], [12 + k for k in range(8)]] = True
    expected[16:18, 10:28] = True
    assert np.array_equal(thin, expected.ravel()[valid_px])


def test_thin_band_points_give_no_reading() -> None:
    """A cell of floor points and a line's band points (thin) reads occupied on all its points;
    with the thin points left out it gives no reading at all, not free: its floor points are
    the same depth edge's floor. A cell of band points that are not thin reads occupied either
    way."""
    points = _points([(0, 3, 0.0), (0, 6, 0.3), (1, 8, 0.0), (2, 6, 0.5)])
    thin = np.array([False] * 3 + [True] * 6 + [False] * 8 + [False] * 6)
    params = SensorModelParams()
    everything = build_tile(points, R, params, 3)
    without_lines = build_tile(points, R, params, 3, thin=thin)
    assert everything.logodds[0, 0] > 0.0
    assert without_lines.logodds[0, 0] == 0.0 and without_lines.count[0, 0] == 0
    assert without_lines.logodds[0, 1] < 0.0  # floor alone
    assert everything.logodds[0, 2] > 0.0
    assert without_lines.logodds[0, 2] == pytest.approx(everything.logodds[0, 2])
