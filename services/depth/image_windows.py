"""Windowed image operations the floor model runs every frame: box means of planes and their
products, maxima over a square at a few pixels, a probe's gather, the blur before comparisons.
Compiled loops where whole-image numpy passes cost milliseconds."""

from __future__ import annotations

from typing import Any, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from common.arrays import F32, U8, Mask
from common.compiled import compiled

NO_PLANE = -1
"""A term of :func:`window_means` that is one plane, not a product of two."""


def window_means(planes: F32, terms: npt.NDArray[np.int64], window_px: int) -> F32:
    """The mean over a ``window_px`` square about every pixel of each term, a row of ``terms``:
    ``planes[i]``, or the float32 product ``planes[i] * planes[j]``, (i, j) or (i, NO_PLANE). Equal
    to ``cv2.blur`` of each term to the bit (sums in float64 in its order, borders reflected
    without the edge pixel), in one pass without the products' images: a dozen blurs and their
    products as numpy passes were the floor test's main cost."""
    if window_px % 2 != 1:
        raise ValueError(f"window_means needs an odd window, not {window_px}")
    means = np.empty((len(terms), *planes.shape[1:]), np.float32)
    _window_means(np.ascontiguousarray(planes, np.float32), terms, window_px // 2, means)
    return means


@compiled
def _reflected(index: int, length: int) -> int:
    """``index`` reflected into [0, length) without repeating the edge (cv2.BORDER_REFLECT_101)."""
    if length == 1:
        return 0
    while index < 0 or index >= length:
        index = -index if index < 0 else 2 * length - 2 - index
    return index


@compiled
def _window_means(planes: F32, terms: npt.NDArray[np.int64], half_px: int, means: F32) -> None:
    """cv2.blur's box filter for float32, term by term: each row's sums along x (left to right),
    then a running sum of the last rows' sums down each column, scaled once."""
    _, rows, cols = planes.shape
    size = 2 * half_px + 1
    scale = 1.0 / (size * size)
    padded = np.empty(cols + 2 * half_px, np.float64)
    row_sums = np.empty((size, cols), np.float64)  # the last ``size`` rows' sums, a ring
    column = np.empty(cols, np.float64)
    for term in range(terms.shape[0]):
        first, product = planes[terms[term, 0]], terms[term, 1] != NO_PLANE
        second = planes[max(terms[term, 1], 0)]
        column[:] = 0.0
        for step in range(rows + 2 * half_px):  # the window's rows from its top, reflected
            row = _reflected(step - half_px, rows)
            # Loops over rows' views (not 2-D indexing): so they vectorise.
            values, first_row, second_row = (
                padded[half_px : half_px + cols],
                first[row],
                second[row],
            )
            if product:
                for col in range(cols):
                    values[col] = first_row[col] * second_row[col]
            else:
                for col in range(cols):
                    values[col] = first_row[col]
            for k in range(half_px):
                padded[half_px - 1 - k] = padded[half_px + _reflected(-1 - k, cols)]
                padded[half_px + cols + k] = padded[half_px + _reflected(cols + k, cols)]
            sums = row_sums[step % size]
            if size == 5:  # the windows this module uses: unrolled, the loop vectorises
                for col in range(cols):
                    sums[col] = (
                        padded[col]
                        + padded[col + 1]
                        + padded[col + 2]
                        + padded[col + 3]
                        + padded[col + 4]
                    )
            else:
                sums[:] = padded[:cols]
                for k in range(1, size):
                    shifted = padded[k : k + cols]
                    for col in range(cols):
                        sums[col] += shifted[col]
            if step < size - 1:
                for col in range(cols):
                    column[col] += sums[col]
                continue
            out, oldest = means[term, step - size + 1], row_sums[(step + 1) % size]
            for col in range(cols):
                total = column[col] + sums[col]
                out[col] = np.float32(total * scale)
                column[col] = total - oldest[col]


ProbedT = TypeVar("ProbedT", np.bool_, np.float32)


def probed(
    image: npt.NDArray[ProbedT], probe: npt.NDArray[np.int64], outside: ProbedT
) -> npt.NDArray[ProbedT]:
    """``image`` at each pixel's probe (:meth:`FloorModel.__init__`), ``outside`` beyond the
    image: cv2.remap's nearest neighbour without its per-call map decoding (a third of a
    millisecond each)."""
    if image.shape != probe.shape:  # the kernel reads wherever an index points
        raise ValueError(f"probe of shape {probe.shape} for an image of {image.shape}")
    picked = np.empty_like(image)
    _gather(image.ravel(), probe.ravel(), outside, picked.ravel())
    return picked


@compiled
def _gather(
    values: npt.NDArray[Any], index: npt.NDArray[np.int64], outside: Any, out: npt.NDArray[Any]
) -> None:
    """``out[i] = values[index[i]]``, ``outside`` where the index is negative."""
    for pixel in range(index.size):
        out[pixel] = values[index[pixel]] if index[pixel] >= 0 else outside


WindowT = TypeVar("WindowT", np.int32, np.float32)


def window_max_at(values: npt.NDArray[WindowT], half_px: int, at: Mask) -> npt.NDArray[WindowT]:
    """The maximum of ``values`` over the (2·half_px + 1)² square about each pixel of ``at``,
    in order, pixels beyond the image not counted: ``cv2.dilate``'s figures at a few pixels,
    without dilating the whole image."""
    maxima = np.empty(np.count_nonzero(at), values.dtype)
    _window_max(values, half_px, at, maxima)
    return maxima


@compiled
def _window_max(values: npt.NDArray[Any], half_px: int, at: Mask, maxima: npt.NDArray[Any]) -> None:
    """:func:`window_max_at`'s loop."""
    rows, cols = values.shape
    found = 0
    for row in range(rows):
        for col in range(cols):
            if not at[row, col]:
                continue
            top = values[row, col]
            for near_row in range(max(row - half_px, 0), min(row + half_px + 1, rows)):
                for near_col in range(max(col - half_px, 0), min(col + half_px + 1, cols)):
                    top = max(top, values[near_row, near_col])
            maxima[found] = top
            found += 1


def blur(image: U8 | F32, sigma_px: float) -> F32:
    blurred: F32 = np.asarray(
        cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma_px), dtype=np.float32
    )
    return blurred
