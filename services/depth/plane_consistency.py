"""The floor test: plane consistency of a stereo pair at the floor's disparity (the right image
warped onto the left by the floor): windowed ZNCC, texture along and across the baseline, and
one Lucas–Kanade step for the residual shift (a surface's height above the floor)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from common.arrays import F32, Mask
from common.compiled import compiled
from services.depth.floor_background import GAIN_SAMPLE_STEP
from services.depth.floor_config import FloorModelConfig
from services.depth.image_windows import NO_PLANE, window_means

X_ENERGY_MIN = 0.1
"""Variance of the x-gradient (gray levels² per pixel²) below which no window is x-textured (nor
a pixel's own row, over the window's width: rule 6b) …"""
X_ENERGY_SHARE = 0.06
"""… nor below this share of the y-gradient's (texture along the baseline: the aperture problem)."""


@dataclass(frozen=True)
class FloorTest:
    """Left against the floor-warped right, per pixel (see :func:`floor_test`)."""

    textured: Mask
    """Enough texture in both windows for the test to speak."""
    x_textured: Mask
    """Enough texture *along x* for any horizontal-baseline match: elsewhere (a uniform surface,
    or grain and gaps along the baseline) a disparity is the matcher's interpolation."""
    along_baseline: Mask
    """Texture, but hardly any of it along x (grain, board gaps along the baseline)."""
    matchable: Mask
    """Texture, and texture along x, in the *left* image's window alone: there the matcher's
    disparity is a measurement, at whatever height; elsewhere (a uniform surface, sensor noise,
    texture only across the baseline) the matcher carried it in from around. (``x_textured``
    needs the floor-warped right image to agree, which a raised surface's does not.)"""
    shift_px: F32
    """Disparity minus the floor's, measured to a fraction of a pixel; NaN where not measured."""
    agree: Mask
    contradict: Mask
    left_x_gray: F32
    """The left image's x-gradient (gray levels per pixel), one of the test's planes: rule 6b
    reads a pixel's own row of it."""


class FloorTestThresholds(NamedTuple):
    """The floor test's thresholds in float32, as numpy compares a float32 image with a number."""

    texture_var: np.float32
    agree_zncc: np.float32
    contradict_zncc: np.float32
    measure_zncc: np.float32
    measure_energy: np.float32
    max_shift_px: np.float32
    floor_shift_px: np.float32
    raised_shift_px: np.float32

    @staticmethod
    def of(config: FloorModelConfig) -> FloorTestThresholds:
        return FloorTestThresholds(
            *(
                np.float32(value)
                for value in (
                    config.texture_gray**2,
                    config.agree_zncc,
                    config.contradict_zncc,
                    config.measure_zncc,
                    config.measure_energy,
                    config.max_shift_px,
                    config.floor_shift_px,
                    config.raised_shift_px,
                )
            )
        )


@compiled
def _floor_decisions(
    means: F32,
    inside: Mask,
    limits: FloorTestThresholds,
    textured: Mask,
    x_textured: Mask,
    along_baseline: Mask,
    matchable: Mask,
    shift_px: F32,
    agree: Mask,
    contradict: Mask,
) -> None:
    """The floor test's verdicts at each pixel from its window means (``FLOOR_TEST_TERMS``'
    order), in float32 as the numpy expressions they replace: a few dozen whole-image passes
    cost more than the window sums."""
    x_energy_min, x_energy_share = np.float32(X_ENERGY_MIN), np.float32(X_ENERGY_SHARE)
    tiny, nan = np.float32(1e-6), np.float32(np.nan)
    rows, cols = inside.shape
    for row in range(rows):
        for col in range(cols):  # & and | rather than and, or: fewer branches
            mean_l, mean_r, mean_g = means[0, row, col], means[1, row, col], means[2, row, col]
            mean_across, mean_lx, mean_ly = (
                means[3, row, col],
                means[4, row, col],
                means[5, row, col],
            )
            var_l = means[6, row, col] - mean_l * mean_l
            var_r = means[7, row, col] - mean_r * mean_r
            covariance = means[8, row, col] - mean_l * mean_r
            energy = means[9, row, col] - mean_g * mean_g
            along = means[10, row, col] - (mean_r - mean_l) * mean_g
            energy_across = means[11, row, col] - mean_across * mean_across
            left_energy_x = means[12, row, col] - mean_lx * mean_lx
            left_energy_y = means[13, row, col] - mean_ly * mean_ly
            left_textured = var_l > limits.texture_var
            is_textured = left_textured & (var_r > limits.texture_var) & inside[row, col]
            zncc = covariance / np.sqrt(max(var_l * var_r, tiny))
            shift = along / max(energy, tiny)
            size = abs(shift)
            # Texture along x, against an absolute floor and against the texture across it: grain
            # or board gaps along the baseline have gradients, but none along x to match on.
            is_along = is_textured & (energy < energy_across * x_energy_share)
            is_x_textured = is_textured & (energy > x_energy_min) & (not is_along)
            strong = is_x_textured & (energy >= limits.measure_energy)
            measured = strong & (zncc >= limits.measure_zncc) & (size < limits.max_shift_px)
            # A shift too large for the linearisation to measure is still no floor.
            strong &= size >= limits.max_shift_px
            textured[row, col] = is_textured
            x_textured[row, col] = is_x_textured
            along_baseline[row, col] = is_along
            matchable[row, col] = (
                left_textured
                & (left_energy_x > x_energy_min)
                & (left_energy_x >= left_energy_y * x_energy_share)
            )
            shift_px[row, col] = shift if measured else nan
            agree[row, col] = (
                measured & (zncc >= limits.agree_zncc) & (size <= limits.floor_shift_px)
            )
            contradict[row, col] = is_textured & (
                (zncc < limits.contradict_zncc)
                | strong
                | (measured & (size >= limits.raised_shift_px))
            )


def _gradient(image: F32, dx: int, dy: int, out: F32 | None = None) -> F32:
    """Sobel derivative along x (dx) or y (dy), in gray levels per pixel of a smoothed image
    (into ``out`` if given)."""
    gradient: F32 = np.asarray(
        cv2.Sobel(image, cv2.CV_32F, dx, dy, dst=out, ksize=3, scale=1.0 / 16.0), np.float32
    )
    return gradient


FLOOR_TEST_PLANES = ("left", "warped", "gradient", "across", "left_x", "left_y", "error")
"""The floor test's planes: both images (the right one floor-warped, at the left one's gain), the
x- and y-gradients of their sum and of the left image, and the right minus the left."""
_LEFT, _WARPED, _GRADIENT, _ACROSS, _LEFT_X, _LEFT_Y, _ERROR = range(len(FLOOR_TEST_PLANES))


# The terms whose window means it takes (:func:`_floor_decisions` reads them in this order).
FLOOR_TEST_TERMS = np.array(
    [
        (_LEFT, NO_PLANE),
        (_WARPED, NO_PLANE),
        (_GRADIENT, NO_PLANE),
        (_ACROSS, NO_PLANE),
        (_LEFT_X, NO_PLANE),
        (_LEFT_Y, NO_PLANE),
        (_LEFT, _LEFT),
        (_WARPED, _WARPED),
        (_LEFT, _WARPED),
        (_GRADIENT, _GRADIENT),
        (_ERROR, _GRADIENT),
        (_ACROSS, _ACROSS),
        (_LEFT_X, _LEFT_X),
        (_LEFT_Y, _LEFT_Y),
    ],
    np.int64,
)


def floor_test(left: F32, warped: F32, inside: Mask, config: FloorModelConfig) -> FloorTest:
    """Zero-mean normalised cross-correlation of ``left`` and ``warped`` (the right image remapped
    at the floor's disparity) over a small window, and the residual shift between them.

    The shift is one Lucas–Kanade step along x: where the surface has disparity d = d_floor + δ,
    left(u) = warped(u − δ) ≈ warped(u) − δ·∂warped/∂u, so δ = ⟨(warped − left)·g⟩ / ⟨g²⟩ over the
    window with g the x-gradient, means removed, after one global gain between the cameras.
    """
    step = GAIN_SAMPLE_STEP
    left_sample, right_sample = left[::step, ::step], warped[::step, ::step]
    seen = right_sample >= 0
    ratio = float(left_sample[seen].mean()) / max(float(right_sample[seen].mean()), 1.0)
    planes = np.empty((len(FLOOR_TEST_PLANES), *left.shape), np.float32)
    np.copyto(planes[_LEFT], left)
    warped = np.multiply(warped, np.float32(ratio), out=planes[_WARPED])
    both = left + warped
    _gradient(both, 1, 0, out=planes[_GRADIENT])
    _gradient(both, 0, 1, out=planes[_ACROSS])
    _gradient(left, 1, 0, out=planes[_LEFT_X])
    _gradient(left, 0, 1, out=planes[_LEFT_Y])
    np.subtract(warped, left, out=planes[_ERROR])
    means = window_means(planes, FLOOR_TEST_TERMS, config.window_px)
    shape = left.shape
    test = FloorTest(
        textured=np.empty(shape, np.bool_),
        x_textured=np.empty(shape, np.bool_),
        along_baseline=np.empty(shape, np.bool_),
        matchable=np.empty(shape, np.bool_),
        shift_px=np.empty(shape, np.float32),
        agree=np.empty(shape, np.bool_),
        contradict=np.empty(shape, np.bool_),
        left_x_gray=planes[_LEFT_X],
    )
    _floor_decisions(
        means,
        inside,
        FloorTestThresholds.of(config),
        test.textured,
        test.x_textured,
        test.along_baseline,
        test.matchable,
        test.shift_px,
        test.agree,
        test.contradict,
    )
    return test


def floor_shift_2d(left: F32, warped: F32, config: FloorModelConfig) -> tuple[F32, F32]:
    """Residual shift (x, y) between ``left`` and ``warped`` per pixel: the 2-D Lucas–Kanade step
    (x alone is what :func:`floor_test` measures every frame; y shows the rows' misalignment).
    NaN where the window's gradients leave a component undetermined."""
    k = (config.window_px, config.window_px)
    both = left + warped
    gx = np.asarray(cv2.Sobel(both, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 16.0), np.float32)
    gy = np.asarray(cv2.Sobel(both, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 16.0), np.float32)
    error = warped - left
    # Zero-mean in each window, as the correlation is: a gain or offset between cameras is no shift.
    error -= np.asarray(cv2.blur(error, k), np.float32)
    gx -= np.asarray(cv2.blur(gx, k), np.float32)
    gy -= np.asarray(cv2.blur(gy, k), np.float32)
    xx, xy, yy = cv2.blur(gx * gx, k), cv2.blur(gx * gy, k), cv2.blur(gy * gy, k)
    ex, ey = cv2.blur(error * gx, k), cv2.blur(error * gy, k)
    det = xx * yy - xy * xy
    floor = config.texture_gray**2
    determined = (det > floor * np.maximum(xx, yy)) & (np.minimum(xx, yy) > floor / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        shift_x = np.where(determined, (yy * ex - xy * ey) / det, np.nan).astype(np.float32)
        shift_y = np.where(determined, (xx * ey - xy * ex) / det, np.nan).astype(np.float32)
    return shift_x, shift_y
