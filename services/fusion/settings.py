"""Settings of the fusion process: flags and OVERGRID_* variables (common.settings)."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

from pydantic import Field, field_validator, model_validator

from common.codec import MessageLimitMb
from common.lattice import Window
from common.settings import CommaList, OvergridParams, ZenohSettings
from services.fusion.captures import CaptureGroups
from services.fusion.params import GridParams


def default_state_dir() -> Path:
    base = Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state"))
    return base / "overgrid" / "fusion"


class FusionParams(OvergridParams):
    """How fusion builds and serves the map: the settings without the state directory and the
    Zenoh session, which ``overgrid up`` nests and hands to its fusion process unchanged."""

    grid: GridParams = Field(default_factory=GridParams)
    bounds: CommaList = Field(
        default_factory=list, description="fixed map bounds x0,y0,x1,y1 in metres (default: grow)"
    )
    max_tile_age_s: float = Field(
        2.0, gt=0.0, le=3600.0, description="drop tiles captured longer ago than this"
    )
    """An hour at most: no measurement of now (1e300 s overflowed the clock's nanoseconds)."""
    max_message_mb: MessageLimitMb = Field(64.0, description="reject larger tile messages")
    capture_wait_s: float = Field(
        CaptureGroups.wait_s,
        ge=0.0,
        description="how long a capture's tiles wait for the rest of the live pairs' before they "
        "are fused without them: each map then shows one instant (0: fuse each tile as it comes, "
        "sooner, but a map stamped with the newest capture shows the other pairs' older frames)",
    )
    publish_interval_s: float = Field(
        0.02,
        gt=0.0,
        le=10.0,
        description="shortest time between map snapshots (and map/updates) while tiles arrive",
    )
    """Ten seconds at most: a map served less often is no live map (1e300 s served none)."""
    save_interval_s: float = Field(
        0.5,
        gt=0.0,
        le=3600.0,
        description="period of state saves: a crash loses at most this much (and the tiles waiting "
        "for the rest of their capture)",
    )
    outline_static: bool = Field(
        True,
        description="serve the cells inside static objects' measured footprints as occupied "
        "where the frames agree (the rim cells their pixels decide either way), but for the "
        "cells within half a cell inside a footprint's edge that the frames call free (unknown); "
        "where the frames "
        "call under 3/4 of a footprint occupied, its cells not occupied are served unknown (a "
        "plain top the floor model took for floor), and so are those of the rectangle a plain "
        "or piecewise-measured top's occupied rim encloses, the cells within 1 cm outside a "
        "footprint the frames do not call occupied, and the occupied cells just outside a whole "
        "object's footprint (its side faces' and fattening's)",
    )
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
            if (
                len(values) != 4
                or not all(math.isfinite(v) for v in values)
                or values[2] <= values[0]
                or values[3] <= values[1]
            ):
                raise ValueError("bounds must be x0,y0,x1,y1 (finite, m) with x1 > x0 and y1 > y0")
        return bounds

    @model_validator(mode="after")
    def _wait_within_tile_age(self) -> FusionParams:
        if self.capture_wait_s > self.max_tile_age_s:
            raise ValueError(
                f"capture_wait_s {self.capture_wait_s:g} s must not exceed max_tile_age_s "
                f"{self.max_tile_age_s:g} s: a tile held longer would be older than tiles refused"
            )
        return self

    @model_validator(mode="after")
    def _bounds_within_cell_limit(self) -> FusionParams:
        if not self.bounds:
            return self
        # In floats, before any lattice index: 1e300 m would wrap int64 cell indices into a
        # window of 0×0 cells, which passes any limit.
        x0, y0, x1, y1 = (float(v) / self.grid.resolution_m for v in self.bounds)
        if (x1 - x0) * (y1 - y0) > self.grid.max_cells or max(map(abs, (x0, y0, x1, y1))) > 2**62:
            raise ValueError(
                f"--bounds cover {x1 - x0:.4g}×{y1 - y0:.4g} cells at {self.grid.resolution_m} m "
                f"(corner cells {x0:.4g}, {y0:.4g}), over --max-cells {self.grid.max_cells} or "
                "the lattice's reach"
            )
        return self

    @property
    def resolution_m(self) -> float:
        return self.grid.resolution_m

    def bounds_window(self) -> Window | None:
        """The fixed bounds on the lattice; None: the map grows (up to ``grid.max_cells``)."""
        if not self.bounds:
            return None
        x0, y0, x1, y1 = (float(v) for v in self.bounds)
        return Window.covering(x0, y0, x1, y1, self.grid.resolution_m)

    def grid_params(self) -> GridParams:
        return dataclasses.replace(self.grid, bounds=self.bounds_window())


class FusionSettings(ZenohSettings, FusionParams):
    """The fusion process: the map's parameters, where it is saved, and the Zenoh session."""

    state_dir: Path = Field(
        default_factory=default_state_dir, description="where the map is saved and loaded"
    )
