"""Named rules that combine a tile into the map, one cell each (after nav2 costmap_2d's
``updateWithAddition``/``updateWithMax``/``updateWithOverwrite``), and :func:`combine_tile`, which
applies them in one compiled pass over a tile.

Why compiled: numpy needs a pass per rule and layer, and over a tile-sized window of a larger map each
pass costs more in per-row overhead and masking than in arithmetic; one numba loop visits each cell
once (bench/fusion.py measures it)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from common.compiled import compiled
from common.mapfiles import OCCUPIED_MIN
from common.occupancy_map import (
    OCCUPANCY_LUT,
    OCCUPANCY_LUT_OFFSET,
    OCCUPANCY_LUT_RANGE,
    OCCUPANCY_LUT_SCALE,
    OCCUPIED,
    UNKNOWN,
)


@compiled
def add_logodds_clamped(logodds: float, update: float, low: float, high: float) -> float:
    """Bayesian update L ← clamp(L + ΔL, L_min, L_max) (OctoMap's clamping)."""
    return min(max(logodds + update, low), high)


@compiled
def height_with_max(height: float, tile_height: float) -> float:
    """Highest top seen over pairs: the seed's "pixel-wise minimum depth" stitching (NaN: none yet)."""
    return height if height >= tile_height else tile_height


@compiled
def occupancy_of(logodds: float) -> int:
    """nav_msgs occupancy of one cell: the table and index of ``occupancy_from_logodds``."""
    clipped = min(max(float(logodds), -OCCUPANCY_LUT_RANGE), OCCUPANCY_LUT_RANGE)
    return int(OCCUPANCY_LUT[int(clipped * OCCUPANCY_LUT_SCALE + OCCUPANCY_LUT_OFFSET)])


@compiled
def combine_tile(
    logodds: npt.NDArray[np.float32],
    height_m: npt.NDArray[np.float32],
    known: npt.NDArray[np.bool_],
    last_seen_s: npt.NDArray[np.float64],
    occupancy: npt.NDArray[np.int8],
    update: npt.NDArray[np.float32],
    tile_height_m: npt.NDArray[np.float32],
    count: npt.NDArray[np.uint16],
    hidden: npt.NDArray[np.bool_],
    stamp_s: float,
    logodds_min: float,
    logodds_max: float,
    hidden_grace_s: float,
) -> None:
    """Every rule on every observed cell, in place on the map layers' views of the tile window.
    A hidden cell (no update, its floor hidden by something standing there now: the floor model's
    rule 10) that the map believes free is forgotten, unknown, unless a tile measured it within
    ``hidden_grace_s`` of this capture (another pair sees that floor now); a cell believed
    occupied keeps its belief."""
    for row in range(update.shape[0]):
        # Row views: numba then steps through each row as a plain strided vector, about a third faster.
        logodds_row, height_row, known_row = logodds[row], height_m[row], known[row]
        seen_row, occupancy_row = last_seen_s[row], occupancy[row]
        update_row, tile_height_row, count_row = update[row], tile_height_m[row], count[row]
        hidden_row = hidden[row]
        for col in range(update_row.shape[0]):
            if count_row[col] == 0:
                if (
                    hidden_row[col]
                    and known_row[col]
                    and logodds_row[col] < 0
                    and stamp_s - seen_row[col] > hidden_grace_s
                ):
                    logodds_row[col] = 0.0
                    height_row[col] = np.nan
                    known_row[col] = False
                    occupancy_row[col] = UNKNOWN
                continue  # no pixel fell here: no evidence, the cell keeps what it had
            logodds_row[col] = add_logodds_clamped(
                logodds_row[col], update_row[col], logodds_min, logodds_max
            )
            if update_row[col] > 0:
                height_row[col] = height_with_max(height_row[col], tile_height_row[col])
            else:  # overwrite: a free observation shows the floor, an old object's top there is gone
                height_row[col] = tile_height_row[col]
            known_row[col] = True
            seen_row[col] = stamp_s
            occupancy_row[col] = occupancy_of(logodds_row[col])  # of the stored float32 value


def occupied_where_predicted(
    occupancy: npt.NDArray[np.int8], predicted: npt.NDArray[np.bool_]
) -> npt.NDArray[np.int8]:
    """Overwrite with occupied where the predicted layer holds the cell (a copy): a static
    object's footprint the frames agree with (less its edge cells they call free), a moving
    object's top no frame measured, or (with ``predict_movers``) its path, so the map a robot
    reads covers where a mover is by the time the map is read, not where a frame saw it. Applied
    to the served map only; the evidence layers stay as measured."""
    return np.where(predicted, np.int8(OCCUPIED), occupancy)


def unknown_where_contested(
    occupancy: npt.NDArray[np.int8], contested: npt.NDArray[np.bool_]
) -> npt.NDArray[np.int8]:
    """Unknown where the contested layer holds the cell and the frames do not call it occupied
    (a copy; served map only): a static object stands there whose footprint the frames call
    mostly free. A top of the floor's grey, held up by its measured edge, that the floor model
    took for floor; or a floor marking tracked as an object: unknown either way, never free
    floor under an object nor a false obstacle. So is a rim cell whose centre lies within a
    static footprint's error outside it, an edge cell within half a cell inside it that the
    frames call free, and a mover's footprint now."""
    return np.where(contested & (occupancy < OCCUPIED_MIN), np.int8(UNKNOWN), occupancy)


def unknown_where_fringe(
    occupancy: npt.NDArray[np.int8], fringe: npt.NDArray[np.bool_]
) -> npt.NDArray[np.int8]:
    """Unknown where the fringe layer holds the cell (a copy; served map only): just outside a
    static object's footprint, measured below the cell size, where its side faces and the
    matcher's fattening make the frames call the cell occupied. Unknown, not free: the evidence says
    occupied, the object's measured outline says not; a client that treats unknown as an
    obstacle keeps its old margin."""
    return np.where(fringe, np.int8(UNKNOWN), occupancy)
