"""Settings of one depth process: flags and OVERGRID_* variables (common.settings)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import AfterValidator, Field, model_validator

from common import keys
from common.codec import MessageLimitMb
from common.sensor_model import SensorModelParams
from common.settings import DEFAULT_RESOLUTION_M, OvergridParams, ResolutionM, ZenohSettings
from services.depth.floor_config import FloorModelConfig
from services.depth.pipeline import PipelineConfig
from services.depth.stereo import MatcherConfig

DOWNSCALES = (1, 2, 4)


def _one_of_downscales(value: int) -> int:
    if value not in DOWNSCALES:
        raise ValueError(f"downscale must be one of {DOWNSCALES}, got {value}")
    return value


class DepthParams(OvergridParams):
    """How a depth process turns frames into tiles: the settings without the pair, its input and
    the Zenoh session, which ``overgrid up`` nests and hands to every depth process unchanged."""

    resolution_m: ResolutionM = DEFAULT_RESOLUTION_M
    downscale: Annotated[int, AfterValidator(_one_of_downscales)] = Field(
        PipelineConfig.downscale, description="process images at 1/downscale (1, 2 or 4)"
    )
    matcher: MatcherConfig = Field(default_factory=MatcherConfig)
    model: SensorModelParams = Field(default_factory=SensorModelParams)
    max_message_mb: MessageLimitMb = Field(32.0, description="reject larger frame messages")
    threads: int = Field(1, ge=0, le=64, description="OpenCV threads (0: OpenCV's default)")
    calib_timeout_s: float = Field(
        0.0, ge=0.0, description="give up waiting for calibration (0: never)"
    )
    summary_s: float = Field(10.0, gt=0.0, description="period of the summary log line")
    floor_model: bool = Field(
        FloorModelConfig.enabled,
        description="fixed-camera floor model: floor test + learned background (DESIGN.md)",
    )
    low_band: bool = Field(
        PipelineConfig.low_band,
        description="measure low raised surfaces (pallets) again at full resolution",
    )

    def pipeline_config(self) -> PipelineConfig:
        return PipelineConfig(
            resolution_m=self.resolution_m,
            downscale=self.downscale,
            matcher=self.matcher,
            model=self.model,
            floor=FloorModelConfig(enabled=self.floor_model),
            low_band=self.low_band,
        )


class DepthSettings(ZenohSettings, DepthParams):
    """One depth process: its pair, where its frames come from, and the Zenoh session."""

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

    @model_validator(mode="after")
    def _pair_id(self) -> DepthSettings:
        keys.check_pair_id(self.pair)
        return self
