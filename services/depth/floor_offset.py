"""The floor's disparity offset: robust affine fits of the calibration residual and the matcher's
offset over the image, and the coarse blockwise fit that captures a poor calibration's offset."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.arrays import F32, Mask
from services.depth.floor_background import fast_median

RESIDUAL_SCALE_PX = 0.1
"""Scale of the robust weights in the calibration-residual fit."""
RESIDUAL_RIDGE = 0.1
"""Slopes need the pixels spread over the image (variance of u', v' over this) to count fully."""
MAX_RESIDUAL_PX = 1.0
"""A good calibration's residual is a fraction of this; a fit beyond it is not believed."""
MIN_FIT_PIXELS = 200
"""Fewer pixels than this fit no residual, and a share of fewer modelled pixels decides nothing."""


def robust_affine_fit(basis: npt.NDArray[np.float32], values: F32) -> npt.NDArray[np.float64]:
    """a + b·u' + c·v' by least squares with Cauchy weights (scale ``RESIDUAL_SCALE_PX``), the
    slopes held toward zero (ridge): the floor's residual is a fraction of a pixel, pixels on low
    objects or mismatches must not pull it, and pixels bunched in one corner of the image must
    not tilt it across the rest."""
    weights = np.ones(values.size, np.float64)
    a = basis.astype(np.float64)
    coef: npt.NDArray[np.float64] = np.zeros(basis.shape[1], np.float64)
    for _ in range(3):
        ridge = np.diag([0.0] + [RESIDUAL_RIDGE * float(weights.sum())] * (basis.shape[1] - 1))
        weighted = (a * weights[:, None]).T
        normal = weighted @ a + ridge
        coef = np.asarray(np.linalg.solve(normal, weighted @ values), np.float64)
        weights = 1.0 / (1.0 + ((values - a @ coef) / RESIDUAL_SCALE_PX) ** 2)
    clipped: npt.NDArray[np.float64] = np.clip(coef, -MAX_RESIDUAL_PX, MAX_RESIDUAL_PX)
    return clipped


OFFSET_CAPTURE_PX = 1.5
"""The coarse offset fit looks for the floor this far either side of the calibration's floor
disparity (a poor calibration is off by ±1 px at the image's edges: ``--seed 2``'s p0)."""
OFFSET_BLOCKS = (4, 3)
"""Columns × rows of image blocks the coarse fit takes one floor offset from each."""
OFFSET_BIN_PX = 0.05
OFFSET_OUTLIER_PX = 0.3
"""A block whose mode lies further than this from the floor's plane is not the floor's (a
pallet)."""
BELOW_FLOOR_COST = 4.0
"""A block's mode further than OFFSET_OUTLIER_PX below a plane costs this many times one as far
above (nothing stands below the floor; a plane through low tops leaves the floor below it)."""
MIN_FLOOR_BLOCKS = 4
"""The coarse fit needs this many blocks on its plane: the three that make it and one more."""
MIN_TRIO_SPAN = 0.1
"""Three blocks whose modes' places span less than this (twice their triangle's area in
(u', v'), the image 2 × 2; two blocks side by side and one below span 0.33) make no plane: with
one row of blocks measuring, they lie in a line but for the scatter of their pixels (0.02), and a
plane through them took its slope across the row from that scatter (1.0 px, the clip, 1.7 px off
at a corner; a review)."""


@dataclass(frozen=True)
class CoarseOffset:
    """The floor's disparity offset found without a starting guess (:func:`coarse_floor_offset`)."""

    coef: npt.NDArray[np.float64]
    """Affine a + b·u' + c·v' through the blocks' modes."""
    modes_px: npt.NDArray[np.float64]
    """Each block's mode (the floor's offset there), and where it is in (u', v')."""
    basis: npt.NDArray[np.float64]
    blocks: tuple[tuple[slice, slice], ...]
    """Each block's rows and columns in the offsets the fit was given."""


def coarse_floor_offset(
    offset_px: F32, usable: Mask, basis: npt.NDArray[np.float32]
) -> CoarseOffset | None:
    """The floor's disparity offset (measured minus the calibration's floor disparity) over the
    image, with no starting guess: in each block the mode of the offsets within
    ±``OFFSET_CAPTURE_PX``, placed where the pixels that make the mode are; then the plane
    through three blocks' modes that explains them best, one vote a block (a pallet's strongly
    textured deck must not outweigh sparse concrete): a block costs its squared distance, at most
    ``OFFSET_OUTLIER_PX``² (something standing on the floor), and ``BELOW_FLOOR_COST`` times that
    where it lies further below (nothing stands below the floor); and the affine fit through the
    blocks within ``OFFSET_OUTLIER_PX`` of it (at least ``MIN_FLOOR_BLOCKS``). Blocks whose modes
    lie coherently a pixel below the floor (not seen on the renders: a reflection on a glossy
    floor could) would tilt it: two of twelve did by 1.2 px in a review's test. A block's mode is
    the floor only where the floor is most of what the matcher measures there; on a plain floor
    the textured tops of low boxes are, in most blocks: grown from the modes' median, the fit went
    through them (``--floor plain --seed 4``: a pair's floor 1 px high, a 0.3 m box 86 % free).
    The fine fits start from it: they only see pixels near their current estimate, and from a
    wrong start they creep (0.02 px a fit) or never begin."""
    height, width = offset_px.shape
    cols, rows = OFFSET_BLOCKS
    edges = np.arange(-OFFSET_CAPTURE_PX, OFFSET_CAPTURE_PX + OFFSET_BIN_PX / 2, OFFSET_BIN_PX)
    modes, where, slices = [], [], []
    with np.errstate(invalid="ignore"):
        near = usable & (np.abs(offset_px) < OFFSET_CAPTURE_PX)
    for j in range(rows):
        for i in range(cols):
            block = (
                slice(j * height // rows, (j + 1) * height // rows),
                slice(i * width // cols, (i + 1) * width // cols),
            )
            chosen = near[block]
            values = offset_px[block][chosen]
            if values.size < MIN_FIT_PIXELS // 4:
                continue
            # np.histogram's counts (edges[k] <= value < edges[k + 1]; every value lies within them)
            # without its sort.
            histogram = np.bincount(
                np.searchsorted(edges, values, side="right") - 1, minlength=edges.size - 1
            )
            smooth = np.convolve(histogram, np.ones(3), mode="same")
            peak = int(np.argmax(smooth))
            centre = (edges[peak] + edges[peak + 1]) / 2
            around = np.abs(values - centre) <= 2 * OFFSET_BIN_PX
            modes.append(fast_median(values[around]))
            where.append(basis[:, block[0], block[1]][:, chosen][:, around].mean(axis=1))
            slices.append(block)
    if len(modes) < MIN_FLOOR_BLOCKS:
        return None
    a = np.asarray(where, np.float64)
    b = np.asarray(modes, np.float64)
    # Every plane through three blocks, scored at once: the cheapest is the floor's.
    trios = np.array(list(itertools.combinations(range(len(b)), 3)), np.intp)
    trio_basis = a[trios]  # (trios, 3 blocks, 3 terms)
    planar = np.abs(np.linalg.det(trio_basis)) > MIN_TRIO_SPAN
    if not planar.any():
        return None
    trios, trio_basis = trios[planar], trio_basis[planar]
    planes = np.linalg.solve(trio_basis, b[trios][..., None])[..., 0]  # (trios, 3 terms)
    residual_px = b[None, :] - planes @ a.T  # (trios, blocks)
    limit_px2 = OFFSET_OUTLIER_PX**2
    cost = np.where(
        residual_px < -OFFSET_OUTLIER_PX,
        BELOW_FLOOR_COST * limit_px2,
        np.minimum(residual_px**2, limit_px2),
    )
    keep = np.abs(residual_px[int(np.argmin(cost.sum(axis=1)))]) <= OFFSET_OUTLIER_PX
    if int(keep.sum()) < MIN_FLOOR_BLOCKS:
        return None
    coef = np.linalg.lstsq(a[keep], b[keep], rcond=None)[0]
    clipped = np.clip(coef, -MAX_RESIDUAL_PX, MAX_RESIDUAL_PX)
    blocks = tuple(slices[k] for k in np.flatnonzero(keep))
    return CoarseOffset(coef=clipped, modes_px=b[keep], basis=a[keep], blocks=blocks)


FLOOR_STILL_SEEN_SHARE = 0.5
"""A block whose mode lies off the current floor still shows that floor where at least this share
as many of its offsets lie near the floor as near its mode."""


def restarts_from_blocks(
    coarse: CoarseOffset,
    current_coef: npt.NDArray[np.float64],
    current_px: F32,
    offset_px: F32,
    usable: Mask,
    tolerance_px: float,
    started: bool,
) -> bool:
    """Whether the fine fits begin again from the coarse fit's plane: where a quarter of its
    blocks (two at least) lie further than ``tolerance_px`` from the current floor
    (``current_coef``; ``current_px`` at each of ``offset_px``'s pixels). Eager: the blocks'
    fit is robust, and starting again from it beat waiting for a third of the blocks by 0.02 of
    IoU on the poorly calibrated seeds 2, 4 and 5.

    But not, once ``started`` (the blocks have been compared with the current floor before: at
    first it is no estimate), where those blocks all lie above the current floor and are half
    the blocks or fewer, or where each of them still shows it (FLOOR_STILL_SEEN_SHARE as many of
    its ``offset_px`` near it as near its mode): what made their modes stands on that floor, the
    floor has not moved. On a plain floor a pallet's textured deck made two of the five blocks
    that measured, and the plane through the decks and the other three took that pair's floor
    0.5 px up, through the deck (``--floor plain --seed 2``: 0.97 of the deck's cells read as floor
    in a frame, 347 of its 384 free in the map, until the next restart 3.5 s on). Either test
    alone missed cases the other caught on the plain floors (the floor beside a plain top has no
    texture to show). A camera knocked askew restarts where its floor fell in a block or rose in
    most of them and left them; where it rose in half the blocks or fewer and fell in none, this
    declines, and the fine fits, which see only pixels within ``floor_tolerance_px`` of their
    floor, follow no rise beyond it: a limit, untested (telling a deck from a risen floor by where
    its pixels lie, a compact patch or spread over the block, is untried)."""
    off_px = coarse.modes_px - coarse.basis @ current_coef
    off = np.abs(off_px) > tolerance_px
    off_count = int(np.count_nonzero(off))
    if off_count < max(2, off.size // 4):
        return False
    if not started:
        return True
    if not np.any(off_px < -tolerance_px) and 2 * off_count <= off.size:
        return False
    with np.errstate(invalid="ignore"):
        for k in np.flatnonzero(off):
            rows, cols = coarse.blocks[k]
            chosen = usable[rows, cols]
            values = offset_px[rows, cols][chosen]
            near_floor = np.count_nonzero(
                np.abs(values - current_px[rows, cols][chosen]) <= tolerance_px
            )
            near_mode = np.count_nonzero(np.abs(values - coarse.modes_px[k]) <= tolerance_px)
            if near_floor < FLOOR_STILL_SEEN_SHARE * near_mode:
                return True
    return False
