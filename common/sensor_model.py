"""Stereo depth uncertainty and the inverse sensor model for overhead cameras (DESIGN.md).

All functions are vectorised over numpy arrays and free of I/O, so the same math serves the depth
service, the fusion service and the tests.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass

FloatArray = npt.NDArray[np.float64] | npt.NDArray[np.float32]


@dataclass(frozen=True, config=ConfigDict(extra="forbid", allow_inf_nan=False))
class SensorModelParams:
    """Parameters of the inverse sensor model, declared once (the depth settings nest them as
    ``--model.*``); defaults follow DESIGN.md and OctoMap."""

    disparity_sigma_px: float = Field(default=0.25, gt=0.0, description="Δd, disparity noise, px")
    calibration_sigma_m: float = Field(
        default=0.01, ge=0.0, description="ε, calibration error term, m"
    )
    obstacle_min_m: float = Field(
        default=0.10, ge=0.0, description="lowest height that blocks a robot"
    )
    obstacle_max_m: float = Field(
        default=2.0, gt=0.0, description="highest height that blocks a robot"
    )
    p_hit: float = Field(default=0.9, gt=0.5, lt=1.0, description="occupied evidence bound")
    p_miss: float = Field(default=0.1, gt=0.0, lt=0.5, description="free evidence bound")
    """One cell observation aggregates ~20 pixels, far stronger evidence than the single beam
    OctoMap's 0.7/0.4 stand for: a conclusive one (``edge_fraction`` ± ``evidence_ramp`` passed)
    turns a cell from clamped free to occupied, or back, in one frame (with the fusion clamps)."""
    edge_fraction: float = Field(
        default=0.6,
        gt=0.0,
        lt=1.0,
        description="share of a cell's pixels in the band that is neutral",
    )
    """Share of a cell's pixels in the band at which its observation is neutral (p = 0.5). A cell is
    occupied by an object when its centre is (how nav2 rasterises, and how ``overgrid eval``
    scores), so an edge through the centre covers half the cell; but a rim cell's share reads high:
    the matcher's fattening and a side face's points (tens of pixels on one line) add band pixels
    that no top covers. Measured (default scene, 8 frames of 4 pairs): cells an object covers
    0.2–0.6 of read a median share of 0.46–0.65, those it covers 0.9 or more 0.93. At 0.5 the rims
    came out a cell too large; at 0.6, offline over 13 scenes, IoU +0.003 to +0.015
    (docs/accuracy-journal.md, "A rim cell's share"). The cost: a rim cell reading 0.5–0.6 keeps its belief (the floor's, free,
    where an object was put down or a mover came), and one reading 0.65 needs about seven frames
    from clamped free to occupied, not two; a static track's rim is served unknown, never free,
    for it (``services.fusion.objects.Outline.rim``), walls and movers' rims are not."""
    evidence_ramp: float = Field(
        default=0.25,
        gt=0.0,
        description="shares beyond edge_fraction ± this give full p_hit / p_miss",
    )
    """Shares beyond ``edge_fraction`` ± this give full p_hit / p_miss; p is linear in between
    (on the free side up to ``free_share_max`` only)."""
    free_share_max: float = Field(
        default=0.25,
        ge=0.0,
        le=1.0,
        description="a cell with at least this share of its pixels in the band is no free evidence",
    )
    """From this share (or ``edge_fraction``, if lower: :attr:`free_share_limit`) up to
    ``edge_fraction`` an observation is neutral: a cell whose centre an object covers but whose
    pixels are mostly the floor beside it (an object's rim: side faces hide part of its top, the
    floor in front is seen whole) read weakly free frame after frame and added up to free;
    offline, static false-free 1.0 → 0.6 % for 0.007 of IoU (0.4–0.6 % on other seeds and
    floors)."""

    @property
    def free_share_limit(self) -> float:
        """The share of band pixels from which a cell gives no free evidence."""
        return min(self.free_share_max, self.edge_fraction)

    def __post_init__(self) -> None:
        if self.obstacle_min_m >= self.obstacle_max_m:
            raise ValueError(
                f"obstacle band [{self.obstacle_min_m}, {self.obstacle_max_m}] m is empty: "
                "obstacle_min_m must be below obstacle_max_m"
            )


def logodds(probability: npt.ArrayLike) -> npt.NDArray[np.float64]:
    p = np.asarray(probability, dtype=np.float64)
    return np.log(p / (1.0 - p))


def probability(logodds_value: npt.ArrayLike) -> npt.NDArray[np.float64]:
    return 1.0 / (1.0 + np.exp(-np.asarray(logodds_value, dtype=np.float64)))


def depth_from_disparity(
    disparity_px: FloatArray, focal_px: float, baseline_m: float
) -> npt.NDArray[np.float32]:
    """z = f·b/d; non-positive disparities give NaN (no measurement)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        depth_m = (focal_px * baseline_m) / disparity_px
    return np.where(disparity_px > 0, depth_m, np.nan).astype(np.float32)


def depth_sigma(
    depth_m: FloatArray, focal_px: float, baseline_m: float, params: SensorModelParams
) -> FloatArray:
    """Δz = z²/(b·f)·Δd + ε: quadratic in depth, plus a calibration floor."""
    return depth_m * depth_m * (params.disparity_sigma_px / (baseline_m * focal_px)) + (
        params.calibration_sigma_m
    )


def _normal_cdf(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    # erf from the standard library: numpy has no erf and scipy is not a dependency.
    return np.array([0.5 * (1.0 + math.erf(v / math.sqrt(2.0))) for v in x], dtype=np.float64)


_CDF_LIMIT = 6.0
_CDF_STEPS = 4800
_CDF_VALUES = _normal_cdf(np.linspace(-_CDF_LIMIT, _CDF_LIMIT, _CDF_STEPS + 1))
_CDF_SLOPES = np.diff(_CDF_VALUES)


def normal_cdf(x: FloatArray) -> npt.NDArray[np.float32]:
    """Φ(x) by linear interpolation in a uniform table (max error ≈ 1e-6): per-pixel speed matters
    here, and a uniform table is indexed directly where ``np.interp`` searches."""
    clipped = np.clip(np.asarray(x, dtype=np.float64), -_CDF_LIMIT, _CDF_LIMIT)
    position = (clipped + _CDF_LIMIT) * (_CDF_STEPS / (2 * _CDF_LIMIT))
    index = np.minimum(position.astype(np.intp), _CDF_STEPS - 1)
    cdf: npt.NDArray[np.float32] = (
        _CDF_VALUES[index] + (position - index) * _CDF_SLOPES[index]
    ).astype(np.float32)
    return cdf


def obstacle_likelihood(
    height_m: FloatArray, height_sigma_m: FloatArray, params: SensorModelParams
) -> npt.NDArray[np.float32]:
    """P(the surface seen is at or above the obstacle band's floor), under N(height, σ_h²).

    Monotone non-decreasing in height. Surfaces above the band are excluded upstream (see
    :func:`in_model_range`): they hide what lies under them, so they give no evidence at all.
    """
    return normal_cdf((height_m - params.obstacle_min_m) / height_sigma_m)


def in_model_range(
    height_m: FloatArray, height_sigma_m: FloatArray, params: SensorModelParams
) -> npt.NDArray[np.bool_]:
    """Heights the model speaks for: from below the floor (noise) up to the band's top."""
    margin = 3.0 * height_sigma_m
    return (height_m >= -margin) & (height_m <= params.obstacle_max_m + margin)


def cell_occupancy_probability(
    obstacle_pixels: FloatArray, observed_pixels: FloatArray, params: SensorModelParams
) -> npt.NDArray[np.float64]:
    """One observation per cell from its pixels, bounded in [p_miss, p_hit].

    ``obstacle_pixels`` is the expected number of the cell's pixels in the band (Σ of
    :func:`obstacle_likelihood`); pixels are aggregated, never counted as independent evidence. The
    share of band pixels is neutral at ``edge_fraction``: a cell an object edge only clips says
    "free", or the map grows a ring of false obstacles around every object; but only below
    ``free_share_max``, so that an object's rim does not add up to free.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(observed_pixels > 0, obstacle_pixels / observed_pixels, 0.0)
    low = params.edge_fraction - params.evidence_ramp
    toward_hit = np.clip((share - low) / (2.0 * params.evidence_ramp), 0.0, 1.0)
    toward_miss = np.where(
        share >= params.free_share_limit,
        0.5,
        params.p_miss + (0.5 - params.p_miss) * 2.0 * toward_hit,
    )
    return np.where(
        toward_hit >= 0.5, 0.5 + (params.p_hit - 0.5) * (2.0 * toward_hit - 1.0), toward_miss
    )
