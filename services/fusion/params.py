"""Parameters of the fused grid, declared once: :class:`services.fusion.grid.FusedGrid` takes them,
and the fusion settings nest them (``--grid.logodds-min`` / ``OVERGRID_GRID__LOGODDS_MIN``)."""

from __future__ import annotations

import math

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass
from pydantic_settings import CliSuppress

from common.lattice import Window
from common.settings import DEFAULT_RESOLUTION_M, ResolutionM


@dataclass(frozen=True, config=ConfigDict(extra="forbid", allow_inf_nan=False))
class GridParams:
    resolution_m: ResolutionM = Field(
        default=DEFAULT_RESOLUTION_M, description="map cell size; tiles must match"
    )
    logodds_min: float = Field(
        default=-1.5,
        lt=0.0,
        description="lower log-odds clamp (OctoMap: -2; here one conclusive hit flips it)",
    )
    logodds_max: float = Field(
        default=2.5,
        gt=0.0,
        description="upper log-odds clamp (OctoMap: 3.5; here one conclusive miss clears it)",
    )
    """Narrower than OctoMap's −2 … 3.5: with the depth model's p_hit/p_miss of 0.9/0.1, one
    conclusive observation moves a cell across the occupied (0.65) or free (0.25) threshold, so a
    moved object appears and clears within a frame; ambiguous observations still accumulate."""
    hidden_grace_s: float = Field(
        default=0.1,
        ge=0.0,
        description="a cell measured this close before a tile's capture keeps its belief where "
        "that tile names it hidden",
    )
    """A pair's hidden cells are the floor behind something as that pair sees it; another pair
    may measure that floor free in the same capture (stamps a few ms apart). Shorter than a frame
    interval, so the free cells under an arriving mover, last measured a frame ago, are forgotten."""
    decay_after_s: float = Field(
        default=5.0, gt=0.0, description="unobserved this long, a cell drifts back toward unknown"
    )
    decay_time_constant_s: float = Field(
        default=2.0, gt=0.0, description="time constant of that drift"
    )
    unknown_below: float = Field(
        default=0.05, gt=0.0, description="|log-odds| under which a decaying cell is unknown again"
    )
    max_cells: int = Field(default=25_000_000, gt=0, description="largest map allowed, in cells")
    max_extent_m: float = Field(
        default=1000.0,
        gt=0.0,
        le=1e6,
        description="without --bounds, tiles must lie within this distance (x and y) of the world "
        "origin; the rest are rejected as outside_extent",
    )
    """The site's reach, in the world frame the cameras are calibrated in (a site's origin lies on
    it): 1 km each way is a generous site, and a tile beyond is a broken or forged header (a cell
    at 2**62, or at 500 km), never a place to grow the map to. Anchored at the origin, not at the
    first tile, so a far first tile cannot lock the real site out."""
    bounds: CliSuppress[Window | None] = None
    """Fixed map window; None grows the map to cover the tiles, up to ``max_cells``. Given in
    metres as the fusion setting ``--bounds`` (a window needs the resolution)."""

    def site_window(self) -> Window:
        """Where tiles may land: the fixed bounds, or ±``max_extent_m`` around the origin."""
        if self.bounds is not None:
            return self.bounds
        extent_cells = math.ceil(self.max_extent_m / self.resolution_m)
        return Window(-extent_cells, -extent_cells, 2 * extent_cells, 2 * extent_cells)
