"""Rule 6's row and column scans: whether a pixel's row (or column, beside an edge along the
baseline) holds measurements that agree with its height within reach."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.arrays import F32, Mask
from common.compiled import compiled


@dataclass(frozen=True)
class RowSupport:
    """What the measurements bounding each pixel along its row say of it (evidence rules 6, 7)."""

    anchored: Mask
    """A measurement lies within reach on at least one side."""
    consistent: Mask
    """Every measurement within reach on either side agrees with the pixel's height."""
    bridge_m: F32
    """Where measurements within reach on both sides agree with each other: the height between
    them, interpolated along the row; NaN elsewhere."""
    one_sided_run: npt.NDArray[np.int64] | None
    """Where a measurement lies within reach on one side only: how many measurements in a row
    the nearest one belongs to (a textured top's many, a plain top's edge a few: rule 6c); 0
    elsewhere. None unless asked for (it costs 0.4 ms a frame)."""


def row_support(
    height_m: F32, anchors: Mask, reach_px: int, tolerance_m: float, runs: bool = False
) -> RowSupport:
    """The nearest anchor (measured pixel) left and right of every pixel in its row, and how their
    heights relate to the pixel's and to each other (and with ``runs``, the one-sided run)."""
    anchored = np.empty(height_m.shape, np.bool_)
    consistent = np.empty(height_m.shape, np.bool_)
    bridge = np.empty(height_m.shape, np.float32)
    one_sided_run = np.empty(height_m.shape if runs else (0, 0), np.int64)
    _scan_rows(
        height_m, anchors, reach_px, tolerance_m, anchored, consistent, bridge, one_sided_run
    )
    return RowSupport(anchored, consistent, bridge, one_sided_run if runs else None)


@compiled
def _scan_rows(
    height_m: F32,
    anchors: Mask,
    reach_px: int,
    tolerance_m: float,
    anchored: Mask,
    consistent: Mask,
    bridge: F32,
    one_sided_run: npt.NDArray[np.int64],
) -> None:
    """Per row, two passes, the nearest anchor to the left then to the right (a sequential scan:
    a dozen whole-frame numpy passes cost 3 ms, this 0.2 ms); first the anchors' run lengths,
    where ``one_sided_run`` is not empty."""
    rows, cols = height_m.shape
    tolerance = np.float32(tolerance_m)
    left_col = np.empty(cols, np.int64)
    left_height = np.empty(cols, np.float32)
    run = np.empty(cols, np.int64)
    runs = one_sided_run.shape[0] > 0
    for row in range(rows):
        col = 0
        while runs and col < cols:
            start = col
            while col < cols and anchors[row, col]:
                col += 1
            run[start:col] = col - start
            if col == start:
                run[col] = 0
                col += 1
        last, last_height = -reach_px - 1, np.float32(np.nan)
        for col in range(cols):
            if anchors[row, col]:
                last, last_height = col, height_m[row, col]
            left_col[col], left_height[col] = last, last_height
        nearest, nearest_height = cols + reach_px + 1, np.float32(np.nan)
        for col in range(cols - 1, -1, -1):
            if anchors[row, col]:
                nearest, nearest_height = col, height_m[row, col]
            height, start, start_height = height_m[row, col], left_col[col], left_height[col]
            near_left, near_right = col - start <= reach_px, nearest - col <= reach_px
            anchored[row, col] = near_left or near_right
            if runs:
                one_sided = near_left != near_right
                nearest_run = run[start] if near_left else run[min(nearest, cols - 1)]
                one_sided_run[row, col] = nearest_run if one_sided else 0
            agrees = True  # NaN never agrees
            if near_left and not abs(height - start_height) <= tolerance:
                agrees = False
            if near_right and not abs(height - nearest_height) <= tolerance:
                agrees = False
            consistent[row, col] = agrees
            if near_left and near_right and abs(start_height - nearest_height) <= tolerance:
                along = np.float32(col - start) / np.float32(max(nearest - start, 1))
                bridge[row, col] = start_height + (nearest_height - start_height) * along
            else:
                bridge[row, col] = np.float32(np.nan)


@compiled
def column_support(
    gradient_x: F32,
    height_m: F32,
    anchors: Mask,
    candidates: Mask,
    half_px: int,
    energy_min: float,
    reach_px: int,
    tolerance_m: float,
    held: Mask,
) -> None:
    """Rule 6b at the ``candidates``: texture along x in the pixel's own row (the x-gradient's
    variance over ``2·half_px + 1`` columns above ``energy_min``: the floor test's
    ``X_ENERGY_MIN``, an argument because numba's cache does not see another file's constants
    change), and a measurement (``anchors``)
    within ``reach_px`` up or down its column, every such nearest one agreeing with its height
    (as :func:`_scan_rows` along a row; NaN never agrees). At the candidates alone: over the
    whole image (the row's variance by blurs, the row scan on the transpose) the rule cost 0.87
    ms a frame, so 0.14 ms."""
    height, width = height_m.shape
    tolerance = np.float32(tolerance_m)
    for row in range(height):
        for col in range(width):
            if candidates[row, col]:
                held[row, col] = _row_textured(
                    gradient_x, row, col, half_px, energy_min
                ) and _column_agrees(height_m, anchors, row, col, reach_px, tolerance)


@compiled
def _row_textured(gradient_x: F32, row: int, col: int, half_px: int, energy_min: float) -> bool:
    """The x-gradient's variance over the pixel's row, ``half_px`` either side (fewer at the
    image's edges), is above ``energy_min``."""
    first, last = max(col - half_px, 0), min(col + half_px, gradient_x.shape[1] - 1)
    total, squares = np.float32(0.0), np.float32(0.0)
    for c in range(first, last + 1):
        g = gradient_x[row, c]
        total += g
        squares += g * g
    count = np.float32(last - first + 1)
    mean = total / count
    return bool(squares / count - mean * mean > np.float32(energy_min))


@compiled
def _column_agrees(
    height_m: F32, anchors: Mask, row: int, col: int, reach_px: int, tolerance_m: np.float32
) -> bool:
    """An anchor lies within ``reach_px`` up or down the pixel's column, and the nearest on each
    side agrees with its height within ``tolerance_m`` (NaN never agrees)."""
    value, anchored = height_m[row, col], False
    for step in (-1, 1):
        r = row + step
        while 0 <= r < height_m.shape[0] and abs(r - row) <= reach_px:
            if anchors[r, col]:
                anchored = True
                if not abs(value - height_m[r, col]) <= tolerance_m:
                    return False
                break
            r += step
    return anchored
