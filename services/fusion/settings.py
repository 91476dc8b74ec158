"""Settings of the fusion process: flags and OVERGRID_* variables (common.settings)."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, field_validator

from common.lattice import MAX_RESOLUTION_M, MIN_RESOLUTION_M, Window
from common.settings import CommaList, ZenohSettings
from services.fusion.grid import GridParams


def default_state_dir() -> Path:
    base = Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state"))
    return base / "overgrid" / "fusion"


class FusionSettings(ZenohSettings):
    resolution_m: float = Field(
        0.05,
        ge=MIN_RESOLUTION_M,
        le=MAX_RESOLUTION_M,
        description="map cell size; tiles must match",
    )
    logodds_min: float = Field(
        -1.5,
        lt=0.0,
        description="lower log-odds clamp (OctoMap: -2; here one conclusive hit flips it)",
    )
    logodds_max: float = Field(
        2.5,
        gt=0.0,
        description="upper log-odds clamp (OctoMap: 3.5; here one conclusive miss clears it)",
    )
    decay_after_s: float = Field(
        5.0, gt=0.0, description="unobserved this long, a cell drifts to unknown"
    )
    decay_time_constant_s: float = Field(2.0, gt=0.0, description="time constant of that drift")
    bounds: CommaList = Field(
        default_factory=list, description="fixed map bounds x0,y0,x1,y1 in metres (default: grow)"
    )
    max_cells: int = Field(25_000_000, gt=0, description="largest map allowed, in cells")
    max_tile_age_s: float = Field(
        2.0, gt=0.0, description="drop tiles captured longer ago than this"
    )
    max_message_mb: float = Field(64.0, gt=0.0, description="reject larger tile messages")
    publish_interval_s: float = Field(
        0.02,
        gt=0.0,
        description="shortest time between map snapshots (and map/updates) while tiles arrive",
    )
    state_dir: Path = Field(
        default_factory=default_state_dir, description="where the map is saved and loaded"
    )
    save_interval_s: float = Field(10.0, gt=0.0, description="period of state saves")
    predict_movers: bool = Field(
        False,
        description="serve the cells moving objects' paths cover up to the next frame as occupied "
        "(off by default: with today's mover tracks it paints false streaks and lowers no false-free)",
    )
    summary_s: float = Field(10.0, gt=0.0, description="period of the summary log line")

    @field_validator("bounds")
    @classmethod
    def _four_numbers(cls, bounds: list[str]) -> list[str]:
        if bounds:
            values = [float(v) for v in bounds]
            if len(values) != 4 or values[2] <= values[0] or values[3] <= values[1]:
                raise ValueError("bounds must be x0,y0,x1,y1 with x1 > x0 and y1 > y0")
        return bounds

    def grid_params(self) -> GridParams:
        window = None
        if self.bounds:
            x0, y0, x1, y1 = (float(v) for v in self.bounds)
            window = Window.covering(x0, y0, x1, y1, self.resolution_m)
        return GridParams(
            resolution_m=self.resolution_m,
            logodds_min=self.logodds_min,
            logodds_max=self.logodds_max,
            decay_after_s=self.decay_after_s,
            decay_time_constant_s=self.decay_time_constant_s,
            max_cells=self.max_cells,
            bounds=window,
        )
