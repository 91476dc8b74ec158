"""The background of the empty floor: each camera's gain field against its background (exposure,
gain, lighting over the image), and whether an image still shows its background's texture."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from common.arrays import F32, F64, Mask
from common.compiled import compiled
from services.depth.image_windows import NO_PLANE, window_means

GAIN_SAMPLE_STEP = 6
"""Gains are taken from every this-many-th pixel in each direction (the gain field against the
background; the floor test's one gain between the cameras)."""
GAIN_BLOCKS = 4
"""The gain field starts from the median ratio in each of this many × this many blocks …"""
GAIN_BLOCK_MIN = 12
"""… holding at least this many sampled pixels …"""
GAIN_AGREE = 0.05
"""… and is one gain, their overall median, while every block's lies within this share of it;
else a quadratic surface, fitted to the blocks less those it misses by more than this share (an
object covers them; one at a time, the worst first) …"""
GAIN_BLOCKS_KEPT = 8
"""… keeping at least this many …"""
GAIN_OUTLIER = 0.1
"""… then to the sampled pixels within this share of that fit (a mover: not the light) …"""
GAIN_EXTRAPOLATION = 1.25
"""… and held within this factor of the kept blocks' medians (beyond their centres the surface
extrapolates)."""
GAIN_MIN_SAMPLES = 6 * GAIN_BLOCK_MIN
"""With fewer modelled samples than this the gain is fitted over every pixel with a background;
with fewer of those, it is 1."""
GAIN_RATIO_MAX = 64.0
"""A ratio to the background beyond this is taken as this, for the blocks' medians only."""
QUADRATIC_TERMS = 6
UNIT_GAIN = np.ones((1, 1), np.float32)
"""One gain of 1, as a field that broadcasts (read-only: shared)."""
UNIT_GAIN.setflags(write=False)


def fast_median(values: npt.NDArray[np.floating[Any]]) -> float:
    """``np.median`` of finite values (the middle one, or the float32 mean of the middle two),
    without its general machinery: on the few thousand values of a block or a gain sample that
    was most of its cost."""
    middle = values.size // 2
    if values.size % 2:
        return float(np.partition(values, middle)[middle])
    return float(np.mean(np.partition(values, (middle - 1, middle))[middle - 1 : middle + 1]))


def gain_fields(ratios: list[F32], valid: Mask, step: int, shape: tuple[int, int]) -> list[F32]:
    """The gain of each camera against its background over the image (``shape``), from its
    ``ratios`` (image over background) at every ``step``-th pixel where ``valid``. A lighting
    circuit switched off over part of a hall darkens the floor by a factor that varies over metres
    (0.26–0.51 across one view in the simulation), which no single gain takes off: where the
    blocks' medians spread wider than ``GAIN_AGREE`` about the overall median, a quadratic surface
    in the pixel (to 2.5 % on that light, :func:`_gain_surface`); else the overall median, one
    gain (exposure, a uniform change), as a 1 × 1 field that broadcasts."""
    rows, cols = shape
    v_sample, u_sample = np.nonzero(valid)
    if v_sample.size < GAIN_MIN_SAMPLES:
        return [UNIT_GAIN for _ in ratios]
    u_norm = (u_sample * (2.0 * step / max(cols - 1, 1)) - 1.0).astype(np.float64)
    v_norm = (v_sample * (2.0 * step / max(rows - 1, 1)) - 1.0).astype(np.float64)
    band_v = np.minimum(v_sample * GAIN_BLOCKS // valid.shape[0], GAIN_BLOCKS - 1)
    band_u = np.minimum(u_sample * GAIN_BLOCKS // valid.shape[1], GAIN_BLOCKS - 1)
    block = band_v * GAIN_BLOCKS + band_u
    counts = np.bincount(block, minlength=GAIN_BLOCKS * GAIN_BLOCKS)
    full = counts >= GAIN_BLOCK_MIN
    centre_u = (np.bincount(block, u_norm, counts.size) / np.maximum(counts, 1))[full]
    centre_v = (np.bincount(block, v_norm, counts.size) / np.maximum(counts, 1))[full]
    fields = []
    for ratio in ratios:
        values: F64 = ratio[v_sample, u_sample].astype(np.float64)
        overall = max(fast_median(values), 1e-3)  # at least: a covered lens, the lights all out
        medians = block_medians(values, block, counts)[full]
        if medians.size < QUADRATIC_TERMS or np.all(np.abs(medians / overall - 1.0) <= GAIN_AGREE):
            fields.append(np.full((1, 1), overall, np.float32))
            continue
        coef, kept = _gain_surface(centre_u, centre_v, medians, u_norm, v_norm, values)
        across, down = np.linspace(-1.0, 1.0, cols), np.linspace(-1.0, 1.0, rows)
        along_u = coef[0] + coef[1] * across + coef[3] * across * across
        along_v = coef[2] * down + coef[5] * down * down
        field = np.outer(coef[4] * down, across) + along_u[None, :] + along_v[:, None]
        lowest = float(medians[kept].min()) / GAIN_EXTRAPOLATION
        highest = float(medians[kept].max()) * GAIN_EXTRAPOLATION
        fields.append(np.clip(field, lowest, highest).astype(np.float32))
    return fields


def gain_normalised(image: F32, gain: F32) -> F32:
    """``image`` on its background's scale: divided by its gain field (a gain held at 1e-3 at
    least: a covered lens gives no infinities)."""
    return (image / np.maximum(gain, np.float32(1e-3))).astype(np.float32, copy=False)


def block_medians(values: F64, block: npt.NDArray[np.intp], counts: npt.NDArray[np.intp]) -> F64:
    """The median of ``values`` in each block (``block`` is each value's, ``counts`` the blocks'
    sizes; NaN for an empty block), from one sort: values clipped to [0, GAIN_RATIO_MAX) and
    offset by their block's index times it sort by block, then by value."""
    if values.size == 0:
        return np.full(counts.size, np.nan)
    keyed = np.sort(block * GAIN_RATIO_MAX + np.clip(values, 0.0, GAIN_RATIO_MAX * 0.999))
    starts = np.cumsum(counts) - counts
    middle_low = np.clip(starts + (counts - 1) // 2, 0, keyed.size - 1)
    middle_high = np.clip(starts + counts // 2, 0, keyed.size - 1)
    offsets = np.arange(counts.size) * GAIN_RATIO_MAX
    medians: F64 = (keyed[middle_low] + keyed[middle_high]) / 2.0 - offsets
    return np.where(counts > 0, medians, np.nan)


def _gain_surface(
    centre_u: F64, centre_v: F64, medians: F64, u_norm: F64, v_norm: F64, values: F64
) -> tuple[F64, Mask]:
    """The quadratic a + b·u + c·v + d·u² + e·u·v + f·v² through the blocks' medians, less the
    block it misses most while it misses one by over ``GAIN_AGREE`` (``GAIN_BLOCKS_KEPT`` kept),
    then through the sampled pixels within ``GAIN_OUTLIER`` of that; and the blocks kept."""

    def basis(u: F64, v: F64) -> F64:
        return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1).astype(np.float64)

    def fit(a: F64, y: F64) -> F64:
        # The normal equations: 25 µs a call here, lstsq's SVD 90 µs.
        normal = a.T @ a + 1e-9 * np.eye(QUADRATIC_TERMS)
        return np.linalg.solve(normal, a.T @ y).astype(np.float64)

    at = basis(centre_u, centre_v)
    blocks = np.ones(medians.size, np.bool_)
    while True:
        coef = fit(at[blocks], medians[blocks])
        missed = np.abs(medians / np.maximum(at @ coef, 1e-3) - 1.0)
        worst = int(np.argmax(np.where(blocks, missed, -1.0)))
        if missed[worst] <= GAIN_AGREE or np.count_nonzero(blocks) <= GAIN_BLOCKS_KEPT:
            break
        blocks[worst] = False
    pixels = basis(u_norm, v_norm)
    near = np.abs(values / np.maximum(pixels @ coef, 1e-3) - 1.0) <= GAIN_OUTLIER
    if np.count_nonzero(near) >= GAIN_MIN_SAMPLES:
        coef = fit(pixels[near], values[near])
    return coef, blocks


BACKGROUND_TEXTURE_WINDOW_PX = 10
TEXTURE_SAMPLE_STEP = 2
TEXTURE_WINDOW_SIDES = (0, 1, 0)
"""The texture checks' weighted windows (:meth:`FloorModel._texture_checks`), by camera: the
background's texture kept in either camera (over its pixels alike their background), and gone in
the left one (over the modelled pixels)."""
_KEPT_WINDOWS, _GONE_WINDOW = (0, 1), 2
"""Which of those windows each check reads (:func:`_texture_verdicts`)."""
_MEAN_PLANES, _IMAGE_PLANES = (0, 1), (2, 3)
"""The texture checks' planes on the sampled grid: each camera's background mean and image; then,
per window, its weight and the background and image where weighted (zero elsewhere)."""


def _window_planes(window: int) -> tuple[int, int, int]:
    """The weight, weighted background and weighted image planes of a texture window."""
    first = len(_MEAN_PLANES) + len(_IMAGE_PLANES) + 3 * window
    return first, first + 1, first + 2


def _window_terms(window: int, side: int) -> tuple[tuple[int, int], ...]:
    """A texture window's terms: its weight, weighted background and image, and their products
    with the camera's background and image (:func:`_window_moments` reads them in this order)."""
    weight, background, now = _window_planes(window)
    return (
        (weight, NO_PLANE),
        (background, NO_PLANE),
        (now, NO_PLANE),
        (background, _MEAN_PLANES[side]),
        (now, _IMAGE_PLANES[side]),
        (now, _MEAN_PLANES[side]),
    )


TERMS_PER_TEXTURE_WINDOW = len(_window_terms(0, 0))
TEXTURE_PLANE_COUNT = _window_planes(len(TEXTURE_WINDOW_SIDES))[0]
TEXTURE_TERMS = np.array(
    [
        term
        for window, side in enumerate(TEXTURE_WINDOW_SIDES)
        for term in _window_terms(window, side)
    ],
    np.int64,
)
"""Every texture window's terms, window after window."""
BACKGROUND_TEXTURE_GRAY = 1.5
"""Local standard deviation (gray levels) of a background below which it has no texture to check."""
COVERED_ZNCC = 0.3
"""Correlation of image and background below which the background's texture is gone (a shadow
scales it: about 1; another surface: about 0)."""
MODELLED_WINDOW_SHARE = 0.95
"""A window less modelled than this holds something that was never floor: its texture check fails."""
TEXTURE_KEPT = 0.5
"""Share of the background's texture (regression slope) a pixel must still show to match it."""


@compiled
def _window_moments(
    means: F32, window: int, row: int, col: int
) -> tuple[np.float32, np.float32, np.float32, np.float32]:
    """A texture window's weighted share, background and image variances and their covariance at
    one pixel of the sampled grid, in float32 as numpy computes them; NaN where the window holds
    no weighted pixel."""
    first = TERMS_PER_TEXTURE_WINDOW * window
    share = means[first, row, col]
    if share == 0:  # every weighted sum is 0 too: numpy's 0 / 0
        nan = np.float32(np.nan)
        return share, nan, nan, nan
    mean_bg = means[first + 1, row, col] / share
    mean_now = means[first + 2, row, col] / share
    var_bg = means[first + 3, row, col] / share - mean_bg * mean_bg
    var_now = means[first + 4, row, col] / share - mean_now * mean_now
    covariance = means[first + 5, row, col] / share - mean_now * mean_bg
    return share, var_bg, var_now, covariance


@compiled
def _texture_verdicts(means: F32, kept: Mask, gone: Mask) -> None:
    """Per pixel of the sampled grid, from the windows' means (``TEXTURE_TERMS``): both cameras'
    background texture kept, and the left one's gone (:meth:`FloorModel._texture_checks`)."""
    textured_var = np.float32(BACKGROUND_TEXTURE_GRAY**2)
    kept_slope, covered_zncc = np.float32(TEXTURE_KEPT), np.float32(COVERED_ZNCC)
    modelled_share, tiny = np.float32(MODELLED_WINDOW_SHARE), np.float32(1e-6)
    rows, cols = kept.shape
    for row in range(rows):
        for col in range(cols):
            both_kept = True
            for window in _KEPT_WINDOWS:  # a plain background (or none: NaN): nothing to check
                _, var_bg, _, covariance = _window_moments(means, window, row, col)
                if var_bg >= textured_var and not covariance / var_bg >= kept_slope:
                    both_kept = False
            kept[row, col] = both_kept
            share, var_bg, var_now, covariance = _window_moments(means, _GONE_WINDOW, row, col)
            is_gone = share < modelled_share
            if var_bg >= textured_var:
                zncc = covariance / np.sqrt(max(var_bg * var_now, tiny))
                is_gone |= zncc < covered_zncc
            gone[row, col] = is_gone


def texture_checks(
    background_mean: F32, normalised: list[F32], alike: list[Mask], modelled: Mask
) -> tuple[Mask, Mask]:
    """Whether both cameras' images still show their background's texture, and where the
    left one's is gone, from windowed moments on every other pixel of each axis (a window's
    statistics hardly change from one pixel to the next), on that sampled grid. ``background_mean``:
    each camera's background (left, right floor-warped).

    *Kept*: the slope of the image regressed on the background over a window of the pixels
    whose grey matches it (``alike``: an object's own pixels beside the floor do not count)
    is about 1 on the floor and about 0 on a plain surface whose grey lies within the
    background's tolerance (a plain orange forklift over grey concrete: the same luma).
    Where the background has no texture (a plain floor), there is nothing to check.

    *Gone*: the windowed correlation of image and background over the modelled pixels is
    under COVERED_ZNCC where the background has texture. A shadow scales the floor's texture
    and keeps it; something standing over the floor hides it. Where under
    MODELLED_WINDOW_SHARE of the window is modelled, something that was never floor stands
    within it (an object beside the pixel): a floor reading there is no more believed
    (offline, default scene: false-free overall 0.9 → 0.7 %, the person's cells)."""
    step = TEXTURE_SAMPLE_STEP
    grid = modelled[::step, ::step]
    planes = np.empty((TEXTURE_PLANE_COUNT, *grid.shape), np.float32)
    for side in (0, 1):
        planes[_MEAN_PLANES[side]] = background_mean[side, ::step, ::step]
        planes[_IMAGE_PLANES[side]] = normalised[side][::step, ::step]
    weights = (alike[0], alike[1], modelled)
    for window, side in enumerate(TEXTURE_WINDOW_SIDES):
        weight, background, now = _window_planes(window)
        planes[weight] = weights[window][::step, ::step]
        np.multiply(planes[_MEAN_PLANES[side]], planes[weight], out=planes[background])
        np.multiply(planes[_IMAGE_PLANES[side]], planes[weight], out=planes[now])
    means = window_means(planes, TEXTURE_TERMS, BACKGROUND_TEXTURE_WINDOW_PX // step)
    kept, gone = np.empty(grid.shape, np.bool_), np.empty(grid.shape, np.bool_)
    _texture_verdicts(means, kept, gone)
    return kept, gone
