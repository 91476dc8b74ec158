"""Settings of one depth process: flags and OVERGRID_* variables (common.settings)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from common import keys
from common.lattice import MAX_RESOLUTION_M, MIN_RESOLUTION_M
from common.sensor_model import SensorModelParams
from common.settings import ZenohSettings
from services.depth.floor_model import FloorModelConfig
from services.depth.pipeline import PipelineConfig
from services.depth.stereo import MatcherConfig


class DepthSettings(ZenohSettings):
    pair: str = Field(description="stereo pair id this process serves (e.g. p0)")
    calib: Path | None = Field(
        None, description="calibration file (YAML/JSON); default: query cam/{pair}/calib"
    )
    images: Path | None = Field(
        None, description="recorded input: folder of image pairs or side-by-side video"
    )
    rate_hz: float = Field(
        0.0, ge=0.0, description="pace for recorded input (0: as fast as processed)"
    )
    resolution_m: float = Field(
        0.05, ge=MIN_RESOLUTION_M, le=MAX_RESOLUTION_M, description="lattice cell size"
    )
    downscale: Literal[1, 2, 4] = Field(2, description="process images at 1/downscale resolution")
    matcher: Literal["sgbm", "bm"] = Field("sgbm", description="stereo matcher")
    block_size: int = Field(
        MatcherConfig.block_size, ge=1, le=21, description="matcher block size (odd)"
    )
    full_width: bool = Field(
        MatcherConfig.full_width, description="match the image's left margin too (padded)"
    )
    edge_filter_px: float = Field(
        MatcherConfig.edge_filter_px,
        ge=0.0,
        description="drop pixels whose 3×3 disparity range exceeds this (0: off)",
    )
    subpixel: bool = Field(
        MatcherConfig.subpixel,
        description="undo SGBM's pixel locking (equiangular fraction, 5×5 mean) instead of its own",
    )
    disparity_sigma_px: float = Field(0.25, gt=0.0, description="Δd, disparity noise")
    calibration_sigma_m: float = Field(0.01, ge=0.0, description="ε, calibration error term")
    obstacle_min_m: float = Field(0.10, ge=0.0, description="lowest height that blocks a robot")
    obstacle_max_m: float = Field(2.0, gt=0.0, description="highest height that blocks a robot")
    p_hit: float = Field(0.9, gt=0.5, lt=1.0, description="occupied evidence bound")
    p_miss: float = Field(0.1, gt=0.0, lt=0.5, description="free evidence bound")
    max_message_mb: float = Field(32.0, gt=0.0, description="reject larger frame messages")
    threads: int = Field(1, ge=0, le=64, description="OpenCV threads (0: OpenCV's default)")
    calib_timeout_s: float = Field(
        0.0, ge=0.0, description="give up waiting for calibration (0: never)"
    )
    summary_s: float = Field(10.0, gt=0.0, description="period of the summary log line")
    floor_model: bool = Field(
        True, description="fixed-camera floor model: floor test + learned background (DESIGN.md)"
    )

    @model_validator(mode="after")
    def _checks(self) -> DepthSettings:
        keys.check_pair_id(self.pair)
        if self.block_size % 2 == 0:
            raise ValueError(f"--block-size must be odd, got {self.block_size}")
        if self.obstacle_min_m >= self.obstacle_max_m:
            raise ValueError("--obstacle-min-m must be below --obstacle-max-m")
        return self

    def pipeline_config(self) -> PipelineConfig:
        return PipelineConfig(
            resolution_m=self.resolution_m,
            downscale=self.downscale,
            matcher=MatcherConfig(
                algorithm=self.matcher,
                block_size=self.block_size,
                full_width=self.full_width,
                edge_filter_px=self.edge_filter_px,
                subpixel=self.subpixel,
            ),
            model=SensorModelParams(
                disparity_sigma_px=self.disparity_sigma_px,
                calibration_sigma_m=self.calibration_sigma_m,
                obstacle_min_m=self.obstacle_min_m,
                obstacle_max_m=self.obstacle_max_m,
                p_hit=self.p_hit,
                p_miss=self.p_miss,
            ),
            floor=FloorModelConfig(enabled=self.floor_model),
        )
