"""Inverse sensor model: world points of one frame → one occupancy observation per cell (a tile).

Pixels falling in one cell are aggregated into a single Bayesian update; they are never counted as
independent evidence. Pixels above the obstacle band give no update (they hide what lies below). A
cell of fewer than ``min_cell_pixels`` gets no update of its own, unless it lies inside open floor
measured around it (then it reads free); nor does an occupied cell of few pixels with nothing
occupied around it (a lone hit).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from common.compiled import compiled
from common.lattice import Window, cell_center, cell_of
from common.sensor_model import (
    SensorModelParams,
    cell_occupancy_probability,
    in_model_range,
    logodds,
    obstacle_likelihood,
)
from services.depth.projection import WorldPoints

COUNT_MAX = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class Tile:
    """Occupancy evidence on lattice ``window``; arrays are ``[row, col] = [j - j0, i - i0]``."""

    window: Window
    resolution_m: float
    logodds: npt.NDArray[np.float32]
    height_m: npt.NDArray[np.float32]
    """Top height seen in the cell; NaN where the cell got no update."""
    count: npt.NDArray[np.uint16]
    """Pixels aggregated into the cell's update; 0 means no update."""
    hidden: npt.NDArray[np.bool_]
    """No update, but the floor there is hidden by something standing in the view (a pixel that
    measures it, or one the floor model finds departed: rule 10): a free belief there is out of
    date."""

    def arrays(self) -> dict[str, np.ndarray]:
        """The layers on the wire; ``hidden`` only where some cell is (a byte a cell otherwise)."""
        layers: dict[str, np.ndarray] = {
            "logodds": self.logodds,
            "height_m": self.height_m,
            "count": self.count,
        }
        if self.hidden.any():
            layers["hidden"] = self.hidden.view(np.uint8)
        return layers


SPARSE_NEIGHBOURHOOD_CELLS = 7
"""A cell of too few pixels of its own reads free when at least this many of the 3 × 3 cells
around it (itself included) hold pixels …"""
SPARSE_NEIGHBOURHOOD_PIXELS = 12
"""… together at least this many, fewer than half a pixel of them expected in the obstacle band."""


def _sparse_free(
    pixels: npt.NDArray[np.int64],
    obstacle: npt.NDArray[np.float64],
    min_cell_pixels: int,
    free_share_limit: float,
) -> npt.NDArray[np.bool_]:
    """Cells of 1 to ``min_cell_pixels`` − 1 pixels inside open, measured floor: the 3 × 3 cells
    around them are nearly all measured and (almost) nothing in them reads in the band. Without
    this, a cell a passing mover made occupied keeps that reading for seconds where the floor
    gives it one or two pixels a frame (the forklift's trail of specks); a cell inside a plain
    top, whose neighbours hold no pixels, or beside an object, whose neighbours read in the band,
    never qualifies."""

    def around(values: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        summed = cv2.boxFilter(values, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        return np.asarray(summed, np.float64)

    filled = around((pixels > 0).astype(np.float64))
    total = around(pixels.astype(np.float64))
    in_band = around(obstacle)
    # Its own share under the free limit too: no reading of its own may be neutral or better.
    sparse = (pixels > 0) & (pixels < min_cell_pixels) & (obstacle < free_share_limit * pixels)
    return np.asarray(
        sparse
        & (filled >= SPARSE_NEIGHBOURHOOD_CELLS)
        & (total >= SPARSE_NEIGHBOURHOOD_PIXELS)
        & (in_band < 0.5),
        np.bool_,
    )


LONE_HIT_MAX_PIXELS = 4
"""An occupied reading from this many pixels or fewer whose eight neighbours the frame reads
nothing occupied in is a lone hit, and gives no update (:func:`_lone_hits`)."""


def _lone_hits(
    occupied: npt.NDArray[np.bool_], pixels: npt.NDArray[np.int64]
) -> npt.NDArray[np.bool_]:
    """The occupied readings of ``LONE_HIT_MAX_PIXELS`` pixels or fewer with no occupied reading
    in the eight cells around them. An object 0.1 m across or more fills two cells or more in a
    frame that sees it; a lone hit is a few stray points where the floor gives a cell few pixels
    a frame (beyond a top's shadow, at a wall's foot at a view's edge), and there one hit stays
    for the run: the next frames give that cell no reading, free or occupied. Measured per tile
    (default scene, 12 frames of 4 pairs): 392 such hits, 44 % on an object, 40 % more than a cell
    and a half from any (``--seed 3``: 25 % and 67 %); a lone hit of more pixels is no likelier
    true (42 %, 36 %), but stays: a post a cell wide near the camera gives its cell that many.
    Offline, thirteen scenes (20 s): IoU +0.0012 to +0.0055, false-free the same but for
    ``--seed 4``'s static 0.09 → 0.10 %; every lone hit dropped, +0.0018 to +0.0076, but such a
    post would never be mapped (docs/accuracy-journal.md, "A lone hit")."""
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0  # the eight cells around, not the cell itself
    beside = cv2.dilate(
        occupied.astype(np.uint8), ring, borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    return np.asarray(occupied & (beside == 0) & (pixels <= LONE_HIT_MAX_PIXELS), np.bool_)


SIDE_FACE_DROP_M = 0.1
"""A point in the band this far below the highest surface in the 3 × 3 cells around it lies on a
side face (or on a low surface beside a taller one: a pallet's deck by a shelf)."""
SIDE_FACE_BEYOND_M = 0.01
"""A face point lies beyond a cell's centre only this much farther from the camera's nadir: a
face within a centimetre of the centre keeps the cell occupied (the error it leaves is a detour,
not a collision; docs/accuracy-journal.md, for the figures with and without it)."""
SIDE_FACE_MIN_POINTS = 2
"""A cell's face points are judged only when it holds this many: a face crossing a cell fills it
with tens, and its scatter spills a few into the cells beside; one alone says nothing of where a
face is (a cell inside a box, of floor the matcher dragged in and one face point, read free
without this). Offline, nine scenes: 2 keeps all but 0.1 point of the IoU gained at 1, 4 lost half
of it, at the same false-free to 0.02 points."""


def _faces_beyond_centre(
    flat: npt.NDArray[np.int64],
    x_m: npt.NDArray[np.float32],
    y_m: npt.NDArray[np.float32],
    height_m: npt.NDArray[np.float32],
    top_m: npt.NDArray[np.float32],
    window: Window,
    resolution_m: float,
    band_min_m: float,
    camera_xy_m: tuple[float, float],
    top_out_of_view: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.bool_]:
    """The side-face points of the cells whose centre their face does not cover. A side face is
    vertical: it has no area seen from above, and a camera sees it over many pixels (tens for a
    face a cell wide) that all land on its line, so in the cell it crosses it outnumbers the
    floor and top there whichever side of the cell's centre it lies. The face a camera sees faces
    that camera, so the object stands beyond it: where most of a cell's face points lie farther
    from the camera's nadir than the cell's centre, the centre is on the open side and the face
    says nothing of it (the edge ring around objects). Where most lie nearer (or within
    ``SIDE_FACE_BEYOND_M``), the centre is behind the face, inside the object, and they count.
    A majority per cell (of ``SIDE_FACE_MIN_POINTS`` or more), not a test per point: the matcher
    scatters a face's points a few centimetres along the rays.
    A point whose top may lie out of the view (``top_out_of_view``: its pixel is at the image's
    edge) is judged as a face point without the top: a wall's foot at the edge of a view shows
    its lowest 10–20 cm, no top to fall below, and half its points spill into the floor cells
    along it (the walls' ring: 63 of the default scene's 278 false-occupied cells at the last
    offline map, 50 with this). A top is judged by the same majority, so one at the edge keeps
    the cells whose centre it covers."""
    rows, cols = window.shape
    highest_around_m = np.asarray(
        cv2.dilate(top_m.reshape(rows, cols), np.ones((3, 3), np.uint8))
    ).ravel()
    below_top = height_m < highest_around_m[flat] - SIDE_FACE_DROP_M
    if top_out_of_view is not None:
        below_top |= top_out_of_view
    face = np.flatnonzero((height_m >= band_min_m) & below_top)
    cell, x, y = flat[face], x_m[face], y_m[face]
    centre_x = cell_center(cell % cols + window.i0, resolution_m)
    centre_y = cell_center(cell // cols + window.j0, resolution_m)
    outward_x, outward_y = x - camera_xy_m[0], y - camera_xy_m[1]
    along_m = ((x - centre_x) * outward_x + (y - centre_y) * outward_y) / np.maximum(
        np.hypot(outward_x, outward_y), 1e-6
    )
    faces = np.bincount(cell, minlength=rows * cols)
    faces_beyond = np.bincount(cell[along_m > SIDE_FACE_BEYOND_M], minlength=rows * cols)
    left_out = np.zeros(flat.size, np.bool_)
    left_out[face] = (faces[cell] >= SIDE_FACE_MIN_POINTS) & (2 * faces_beyond[cell] > faces[cell])
    return left_out


BEHIND_MARGIN_M = 0.05
"""A band point lies behind a surface of its own frame where, walking back along its ray toward
the camera, the highest points of two cells or more (not its own) stand more than this above the
ray (the matcher's scatter on a top, a few centimetres; one cell is a stray: a face's upper
points scattered a few centimetres in front of it hid its lower points, and live runs read more
false-free) …"""
GRAZE_M = 0.3
"""… or where the ray passes less than this over a surface that stands …"""
GRAZE_TALLER_M = 0.3
"""… this much or more above the point (a depth edge that tall; below it, a low top's own scatter
of 0.1–0.2 m, a pallet's deck beside its raised edge cells, took its points) …"""
BEHIND_FROM_M = 0.05
"""… from this far back along the ray …"""
BEHIND_REACH_M = 1.0
"""… to this far at most (a bound on the walk's cost: a depth edge's mixed pixels lie within a
few tens of centimetres of the edge that made them; a surface farther back is not looked for)."""


@compiled
def _behind_taller(
    flat: npt.NDArray[np.int64],
    x_m: npt.NDArray[np.float32],
    y_m: npt.NDArray[np.float32],
    height_m: npt.NDArray[np.float32],
    top_m: npt.NDArray[np.float32],
    window_ij: tuple[int, int, int, int],
    resolution_m: float,
    camera_m: tuple[float, float, float],
    band_min_m: float,
) -> npt.NDArray[np.bool_]:
    """The band points that a taller surface of the same frame hides from the camera, or whose
    ray grazes one. A camera cannot see a point its own measurement of a surface nearer along the
    ray blocks; such points are a depth edge's mixed pixels: the matcher's window straddles a
    top's edge and the floor beyond it and returns a disparity between the two, a point part way
    down the ray into the top's shadow (a forklift's rear edge put them 15–20 cm behind it, at
    0.3 m). The same edge's mixed pixels just past the shadow, which see the floor beyond, have
    rays that pass over the top's edge (by 0.1–0.3 m where traced), and their points stand on no
    surface: a line of false-occupied cells along the shadow's edge beyond a 1.46 m box on a
    plain floor, at 0.3–0.45 m. Walks back along each point's ray, half a cell a step, over the
    cells' highest points (``top_m``: of the points the model keeps, so a surface above the band,
    out of its range, hides nothing). Offline, thirteen scenes (20 s): IoU −0.0001 to +0.0027 for
    hidden points, precision up to +0.3 points, false-free the same or lower; one blocking cell
    enough, +0.0000 to +0.0051 offline but live more false-free (docs/accuracy-journal.md, "Points
    a taller top hides from the camera"); grazed ones as well, +0.0003 to +0.0054, false-free the
    same (docs/accuracy-journal.md, "Rays that graze a top")."""
    i0, j0, cols, rows = window_ij
    camera_x, camera_y, camera_z = camera_m
    behind = np.zeros(flat.size, np.bool_)
    step_m = resolution_m / 2
    highest_m = top_m.max() if top_m.size else -np.inf
    for k in range(flat.size):
        height = height_m[k]
        if height < band_min_m:
            continue
        to_x, to_y = camera_x - x_m[k], camera_y - y_m[k]
        distance_m = np.sqrt(to_x * to_x + to_y * to_y)
        if distance_m < resolution_m or camera_z <= height:
            continue
        rise = (camera_z - height) / distance_m
        # Past where the ray clears the frame's highest point, nothing can stand above it.
        reach_m = min(BEHIND_REACH_M, distance_m, (highest_m + GRAZE_M - height) / rise)
        along_m = BEHIND_FROM_M
        first_cell = -1  # a surface hides the point from two cells on: one is a stray point
        while along_m < reach_m:
            i = int(np.floor((x_m[k] + to_x / distance_m * along_m) / resolution_m)) - i0
            j = int(np.floor((y_m[k] + to_y / distance_m * along_m) / resolution_m)) - j0
            if i < 0 or j < 0 or i >= cols or j >= rows:
                break
            cell = j * cols + i
            if cell == flat[k]:  # its own cell holds its own object's top
                along_m += step_m
                continue
            ray_m = height + rise * along_m
            # Hidden (the surface stands over the ray), or grazed: the ray passes just over a
            # surface taller than the point, a mixed pixel of that surface's edge.
            over_m = min(ray_m + BEHIND_MARGIN_M, max(ray_m - GRAZE_M, height + GRAZE_TALLER_M))
            if top_m[cell] > over_m and cell != first_cell:
                if first_cell >= 0:
                    behind[k] = True
                    break
                first_cell = cell
            along_m += step_m
    return behind


THIN_BAND_PX = 3
"""A band point whose pixel lies in no square of this many pixels a side of band pixels …"""
THIN_BELOW_M = 0.5
"""… and that stands lower than this is left out (:func:`thin_band_points`)."""


def thin_band_points(
    valid_px: npt.NDArray[np.intp],
    height_m: npt.NDArray[np.float32],
    shape_px: tuple[int, int],
    band_min_m: float,
) -> npt.NDArray[np.bool_]:
    """The band points (heights ``height_m``, pixels ``valid_px``, flat in an image of
    ``shape_px``) whose pixel lies in no ``THIN_BAND_PX`` square of band pixels (a morphological
    opening of the image's band mask removes them) and that stand lower than ``THIN_BELOW_M``.
    Something standing fills an area of the image (an object 5 cm across or more covers 3 pixels
    at 5 m at the processing resolution); a low line one or two pixels wide in the band is a
    depth edge's mixed pixels: along the silhouette of a box against the floor beyond it, where
    the matcher's window straddles both and its disparity lies between them (a diagonal line of
    points at 0.1–0.45 m beside a 1.46 m box on a plain floor, in the map for the whole run), or
    along a wall's foot at the view's edge (0.1–0.25 m). Higher up, such a line is more often a
    plain top's edge, all the matcher measures of it (a plain wall 1.2 m tall lost a quarter of
    its occupied cells to unknown without the height limit). Offline, thirteen scenes:
    docs/accuracy-journal.md, "Lines of band pixels", for the figures and for what it costs (a
    low thing under 3 pixels wide is not mapped)."""
    rows, cols = shape_px
    band = np.zeros(rows * cols, np.uint8)
    band[valid_px] = height_m >= band_min_m
    image = band.reshape(rows, cols)
    square = np.ones((THIN_BAND_PX, THIN_BAND_PX), np.uint8)
    opened = cv2.morphologyEx(image, cv2.MORPH_OPEN, square)
    thin: npt.NDArray[np.bool_] = ((image > opened).ravel())[valid_px] & (height_m < THIN_BELOW_M)
    return thin


def _tops(
    flat: npt.NDArray[np.int64], height_m: npt.NDArray[np.float32], size: int
) -> npt.NDArray[np.float32]:
    """Each cell's highest point (−inf where none)."""
    top = np.full(size, -np.inf, dtype=np.float32)
    np.maximum.at(top, flat, height_m)
    return top


INFERRED_FLOOR_MIN_POINTS = 2
"""A cell where the frame measures this many floor points or more, and no fewer than its inferred
band points, takes none of the latter (:func:`inferred_over_floor`)."""


def inferred_over_floor(
    cell_ij: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]],
    height_m: npt.NDArray[np.float32],
    inferred: npt.NDArray[np.bool_],
    kept: npt.NDArray[np.bool_],
    band_min_m: float,
) -> npt.NDArray[np.bool_]:
    """Of the ``kept`` points (their cells ``cell_ij`` and heights), the inferred band points
    (``inferred``: a height the floor model carried over a hole from its edges, rules 7 and 8) that
    land in a cell where the same frame measures at least INFERRED_FLOOR_MIN_POINTS floor points,
    and no fewer than those: the frame sees the floor there, so nothing stands on it. A plain face
    below a top's edge takes the top's height and lands out over the floor in front of it, toward
    the camera (the forklift's detections ran 1.3–1.5 m long for 1.2; offline, default scene, of the
    cells its inferred points reached 5–25 cm outside it, 70 % held floor the frame measured; of
    those inside it, 1.6 %). A few stray floor points among a plain top's many inferred ones leave
    it standing (with two floor points enough, such cells read free: static false-free +0.03 points
    on one scene). ``FloorModel._keep_standing`` lowers such a pixel where its image shows floor all
    around straight below it; this asks the cell the point lands in."""
    candidates = inferred & kept & (height_m >= band_min_m)
    if not candidates.any():
        return candidates
    i, j = cell_ij
    cell = (j - j.min()) * (i.max() - i.min() + 1) + (i - i.min())
    size = int(cell.max()) + 1
    floor = kept & ~inferred & (height_m < band_min_m)
    floor_points = np.bincount(cell[floor], minlength=size)[cell]
    inferred_points = np.bincount(cell[candidates], minlength=size)[cell]
    enough = (floor_points >= INFERRED_FLOOR_MIN_POINTS) & (floor_points >= inferred_points)
    dropped: npt.NDArray[np.bool_] = candidates & enough
    return dropped


def build_tile(
    points: WorldPoints,
    resolution_m: float,
    params: SensorModelParams,
    min_cell_pixels: int = 3,
    hidden_xy_m: npt.NDArray[np.float32] | None = None,
    camera_m: tuple[float, float, float] | None = None,
    top_out_of_view: npt.NDArray[np.bool_] | None = None,
    inferred: npt.NDArray[np.bool_] | None = None,
    thin: npt.NDArray[np.bool_] | None = None,
) -> Tile:
    """The frame's tile. ``hidden_xy_m`` (2 × N): floor points of the pixels whose floor is
    hidden; a cell holding at least ``min_cell_pixels`` of them, and at least as many as its
    measured pixels, is *hidden* and its reading dropped, unless that reading says occupied (a
    free one there is the matcher's window dragging the floor onto what hides it).
    ``camera_m``: where the camera that measured the points stands (x, y and height); with it,
    the points a taller surface of the frame hides from it are left out (:func:`_behind_taller`),
    and the cells that held them give no free reading (what reads floor there is the same depth
    edge's floor, not the cell seen empty); and a side face lying beyond a cell's centre is left
    out of that cell's share and pixel count (:func:`_faces_beyond_centre`), judged so without a
    top seen above it for the points flagged in ``top_out_of_view`` (one per point). The points
    flagged in ``inferred`` (one per point: a height the floor model carried in, not measured) are
    left out of a cell where the frame measures the floor (:func:`inferred_over_floor`). The
    points flagged in ``thin`` (one per point: :func:`thin_band_points`) are left out as hidden
    ones are, and the cells that held them give no free reading either."""
    keep = in_model_range(points.height_m, points.height_sigma_m, params)
    cell_ij = cell_of(points.x_m, resolution_m), cell_of(points.y_m, resolution_m)  # 1-D each
    if inferred is not None:
        keep &= ~inferred_over_floor(
            cell_ij, points.height_m, inferred, keep, params.obstacle_min_m
        )
    x, y = points.x_m[keep], points.y_m[keep]
    height, sigma = points.height_m[keep], points.height_sigma_m[keep]
    out_of_view = None if top_out_of_view is None else top_out_of_view[keep]
    thin_kept = None if thin is None else thin[keep]
    hidden_x, hidden_y = np.zeros((2, 0), np.float32) if hidden_xy_m is None else hidden_xy_m
    i, j = cell_ij[0][keep], cell_ij[1][keep]
    hidden_i, hidden_j = cell_of(hidden_x, resolution_m), cell_of(hidden_y, resolution_m)
    all_i, all_j = np.concatenate([i, hidden_i]), np.concatenate([j, hidden_j])
    if all_i.size == 0:
        empty = Window(0, 0, 0, 0)
        return Tile(
            empty,
            resolution_m,
            np.zeros((0, 0), np.float32),
            np.zeros((0, 0), np.float32),
            np.zeros((0, 0), np.uint16),
            np.zeros((0, 0), np.bool_),
        )
    window = Window(
        int(all_i.min()),
        int(all_j.min()),
        int(all_i.max() - all_i.min()) + 1,
        int(all_j.max() - all_j.min()) + 1,
    )
    rows, cols = window.shape
    flat = (j - window.j0) * cols + (i - window.i0)
    size = rows * cols

    weights = obstacle_likelihood(height, sigma, params)
    top = _tops(flat, height, size)
    # Points left out, their cells giving no free reading: thin ones, and those a top hides.
    dropped = np.zeros(flat.size, np.bool_) if thin_kept is None else thin_kept.copy()
    if camera_m is not None:
        dropped |= _behind_taller(
            flat,
            x,
            y,
            height,
            top,
            (window.i0, window.j0, cols, rows),
            resolution_m,
            camera_m,
            params.obstacle_min_m,
        )
    dropped_in = np.zeros(size, np.bool_)
    if dropped.any():
        dropped_in[flat[dropped]] = True
        seen = ~dropped
        flat, x, y, height, weights = flat[seen], x[seen], y[seen], height[seen], weights[seen]
        out_of_view = None if out_of_view is None else out_of_view[seen]
        top = _tops(flat, height, size)
    if camera_m is not None:
        left_out = _faces_beyond_centre(
            flat,
            x,
            y,
            height,
            top,
            window,
            resolution_m,
            params.obstacle_min_m,
            camera_m[:2],
            out_of_view,
        )
        # The top seen in the cells that lost points: of the points they keep (a free reading
        # shows the floor there, not the face beside it).
        lost = np.zeros(size, np.bool_)
        lost[flat[left_out]] = True
        kept_there = lost[flat] & ~left_out
        top[lost] = -np.inf
        np.maximum.at(top, flat[kept_there], height[kept_there])
        flat, weights = flat[~left_out], weights[~left_out]
    pixels = np.bincount(flat, minlength=size)
    obstacle = np.bincount(flat, weights=weights, minlength=size).astype(np.float64)

    updated = pixels >= min_cell_pixels
    update = np.where(
        updated,
        logodds(cell_occupancy_probability(obstacle, pixels.astype(np.float64), params)),
        0.0,
    )
    sparse_free = _sparse_free(
        pixels.reshape(rows, cols),
        obstacle.reshape(rows, cols),
        min_cell_pixels,
        params.free_share_limit,
    ).ravel()
    update = np.where(sparse_free, logodds(params.p_miss), update)
    updated |= sparse_free
    updated &= ~(dropped_in & (update < 0.0))
    updated &= ~_lone_hits(
        (updated & (update > 0.0)).reshape(rows, cols), pixels.reshape(rows, cols)
    ).ravel()
    hidden_pixels = np.bincount(
        (hidden_j - window.j0) * cols + (hidden_i - window.i0), minlength=size
    )
    hidden = (hidden_pixels >= min_cell_pixels) & (hidden_pixels >= pixels) & (update <= 0.0)
    updated &= ~hidden
    return Tile(
        window=window,
        resolution_m=resolution_m,
        logodds=np.where(updated, update, 0.0).astype(np.float32).reshape(rows, cols),
        height_m=np.where(updated, top, np.nan).astype(np.float32).reshape(rows, cols),
        count=np.where(updated, np.minimum(pixels, COUNT_MAX), 0)
        .astype(np.uint16)
        .reshape(rows, cols),
        hidden=hidden.reshape(rows, cols),
    )
