"""Message headers, declared once and used by both sides of every key (DESIGN.md, Key space)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from common.keys import check_pair_id
from common.lattice import Window

STEREO_KIND = "stereo"
CALIB_KIND = "calib"
TILE_KIND = "tile"
TRUTH_KIND = "truth"

MAX_TILE_CELLS = 4000 * 4000
"""A tile larger than this is not from any camera we know: rejected as impossible."""


class _Header(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


SERVED = ConfigDict(extra="ignore", frozen=True)
"""What fusion serves robots (the map, its updates, the objects) takes fields it does not know:
a fleet's robots are not upgraded with the map box, and an old client must read a newer
service's messages. What services send each other stays strict: a field there that nobody
reads is a mistake to refuse where it enters."""


class _OnLattice(_Header):
    """A header describing arrays over lattice window (i0, j0, cols, rows) at ``resolution_m``."""

    resolution_m: float = Field(gt=0)
    i0: int
    j0: int
    cols: int = Field(ge=0)
    rows: int = Field(ge=0)

    @property
    def window(self) -> Window:
        return Window(self.i0, self.j0, self.cols, self.rows)


class StereoFrameHeader(_Header):
    """``cam/{pair}/stereo``: arrays ``left``/``right`` (raw) or blobs (png/jpeg)."""

    pair: str
    seq: int = Field(ge=0)
    stamp_ns: int = Field(ge=0, description="capture time, ns since the Unix epoch")
    encoding: Literal["raw", "png", "jpeg"] = "raw"

    @field_validator("pair")
    @classmethod
    def _pair_id(cls, pair: str) -> str:
        return check_pair_id(pair)


class TileHeader(_OnLattice):
    """``depth/{pair}/tile``: arrays ``logodds`` (f4), ``height_m`` (f4, NaN unseen), ``count`` (u2)
    and, optionally, ``hidden`` (u1: 1 where a cell without an update has its floor hidden now).

    The arrays cover lattice window (i0, j0, cols, rows); ``[row, col] = [j - j0, i - i0]``.
    """

    pair: str
    seq: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    stage_ms: dict[str, float] = Field(default_factory=dict)

    @field_validator("pair")
    @classmethod
    def _pair_id(cls, pair: str) -> str:
        return check_pair_id(pair)

    @field_validator("resolution_m")
    @classmethod
    def _finite_resolution(cls, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError("resolution must be finite")
        return value

    @model_validator(mode="after")
    def _not_huge(self) -> TileHeader:
        if self.rows * self.cols > MAX_TILE_CELLS:
            raise ValueError(
                f"tile of {self.cols}×{self.rows} cells exceeds {MAX_TILE_CELLS} cells"
            )
        return self


class TruthObject(BaseModel):
    """A ground-truth object: oriented box (``size_m`` full extents) or upright cylinder."""

    name: str
    shape: Literal["box", "cylinder"]
    moving: bool
    center_m: tuple[float, float, float]
    yaw_rad: float
    size_m: tuple[float, float, float]
    velocity_mps: tuple[float, float] = (0.0, 0.0)

    @property
    def top_m(self) -> float:
        return self.center_m[2] + self.size_m[2] / 2

    @property
    def bottom_m(self) -> float:
        return self.center_m[2] - self.size_m[2] / 2


class TruthHeader(_OnLattice):
    """``sim/truth`` reply: objects at ``stamp_ns``; array ``occupied`` (u1) over window i0, j0."""

    stamp_ns: int
    height_band_m: tuple[float, float]
    floor_size_m: tuple[float, float]
    objects: list[TruthObject]
    light_level: float = 1.0
    """The site's light at ``stamp_ns``, relative to nominal: its mean over the floor."""
    light_steps_ns: list[int] = Field(default_factory=list)
    """Lighting switch instants in the two minutes before ``stamp_ns`` (and just after it)."""


MAP_KIND = "map"
MAP_UPDATE_KIND = "map_update"
EPOCH_DESCRIPTION = (
    "start time (ns since the Unix epoch) of the fusion run that counted the version: the map's "
    "version is (epoch, version), compared in that order, so it never goes backwards even when a "
    "restarted fusion restores a counter lower than one it served before a crash"
)


class MapHeader(_OnLattice):
    """``map/latest`` reply: array ``occupancy`` (i1, nav_msgs/OccupancyGrid: -1 unknown, 0..100),
    row-major from the origin cell; optional ``logodds`` (f4) and ``height_m`` (f4) layers."""

    model_config = SERVED
    version: int = Field(ge=0, description="change counter within the epoch")
    epoch: int = Field(0, ge=0, description=EPOCH_DESCRIPTION)
    stamp_ns: int = Field(ge=0, description="newest capture stamp fused into the map")
    pairs: list[str] = Field(default_factory=list, description="pairs whose tiles built the map")


class MapUpdateHeader(_OnLattice):
    """``map/updates``: the changed rectangle (i0, j0, cols, rows) of the map (like nav2's
    OccupancyGridUpdate), plus the whole map's window so a follower can grow its copy."""

    model_config = SERVED
    version: int = Field(ge=0, description="change counter within the epoch")
    previous_version: int = Field(ge=0, description="the version this update applies to")
    final_version: int | None = Field(
        None,
        ge=0,
        description="the version the chain of updates of one publish ends at, map/latest's: a "
        "copy at an earlier version of the chain is part new, part old (None: every version "
        "is whole, as fusions before this field sent)",
    )
    epoch: int = Field(0, ge=0, description=EPOCH_DESCRIPTION)
    stamp_ns: int = Field(ge=0)
    map_i0: int
    map_j0: int
    map_cols: int = Field(ge=0)
    map_rows: int = Field(ge=0)

    @property
    def map_window(self) -> Window:
        return Window(self.map_i0, self.map_j0, self.map_cols, self.map_rows)

    @property
    def revision(self) -> tuple[int, int]:
        """(epoch, version), as :attr:`OccupancyMap.revision`."""
        return (self.epoch, self.version)


DETECTIONS_KIND = "detections"
OBJECTS_KIND = "objects"


class Footprint(BaseModel):
    """An oriented rectangle on the floor: centre, length ≥ width, yaw of the long side (world
    frame, metres, radians in [0, π)); a round one is the circle inscribed in it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    center_m: tuple[float, float]
    size_m: tuple[float, float] = Field(description="length, width")
    yaw_rad: float
    round: bool = Field(
        default=False,
        description="a round top (a cylinder's): the circle inscribed in the rectangle",
    )

    @field_validator("center_m", "size_m", "yaw_rad")
    @classmethod
    def _finite(cls, value: float | tuple[float, float]) -> float | tuple[float, float]:
        values = value if isinstance(value, tuple) else (value,)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("footprint values must be finite")
        return value

    @field_validator("size_m")
    @classmethod
    def _positive(cls, size_m: tuple[float, float]) -> tuple[float, float]:
        if min(size_m) <= 0:
            raise ValueError("a footprint's length and width must be positive")
        return size_m


class DetectionRecord(Footprint):
    """One object as one pair's frame shows it (``depth/{pair}/objects``)."""

    top_m: float = Field(allow_inf_nan=False)
    points: int = Field(ge=0, description="world points the object was measured from")
    partial: bool = Field(description="reaches the edge of what the pair can match")
    low: bool = Field(
        default=False,
        description="all top (a pallet): its sides stand within a few centimetres either way",
    )
    outline_m: tuple[tuple[float, float], ...] = Field(
        default=(),
        max_length=64,
        description="the part of its top the pair saw, a convex polygon (x, y); empty: the "
        "rectangle. Pairs that each see part of an object are joined on these",
    )

    @field_validator("outline_m")
    @classmethod
    def _finite_outline(
        cls, outline: tuple[tuple[float, float], ...]
    ) -> tuple[tuple[float, float], ...]:
        if not all(math.isfinite(v) for vertex in outline for v in vertex):
            raise ValueError("outline values must be finite")
        return outline


MAX_DETECTIONS = 256
"""Objects one frame may report: a pair's view of a few tens of square metres holds tens; the
fusion's tracker pairs every detection with every track, so thousands in one message (a broken or
forged pair) would stall it for minutes."""


class DetectionsHeader(_Header):
    """``depth/{pair}/objects``: the objects of one frame, with the tile's pair, seq and stamp."""

    pair: str
    seq: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    detections: list[DetectionRecord] = Field(max_length=MAX_DETECTIONS)
    camera_m: tuple[float, float, float] | None = Field(
        default=None,
        description="where the camera the points were measured from stands (world x, y, z): a "
        "top measured too low lies on its pixels' rays, larger about this camera's nadir",
    )

    @field_validator("pair")
    @classmethod
    def _pair_id(cls, pair: str) -> str:
        return check_pair_id(pair)

    @field_validator("camera_m")
    @classmethod
    def _finite_camera(
        cls, camera_m: tuple[float, float, float] | None
    ) -> tuple[float, float, float] | None:
        if camera_m is not None and not all(math.isfinite(v) for v in camera_m):
            raise ValueError("camera position values must be finite")
        return camera_m


class TrackedObject(Footprint):
    """One tracked obstacle of ``map/objects``. ``class`` is ``static`` or ``moving``; a track is
    static until it is seen to move, and ``settled`` once it has stood still for the tracker's
    ``static_after_s``: a settled object never becomes moving (a moved one ends and a new track
    begins), while one not yet settled may (a mover entering a view reads static for its first
    second). The footprint is where it was last measured (``last_seen_ns``): for a mover a frame
    missed since, its velocity says where it has gone (one missed longer is not listed)."""

    model_config = ConfigDict(**SERVED, validate_by_name=True, serialize_by_alias=True)

    id: int = Field(ge=0)
    object_class: Literal["static", "moving"] = Field(alias="class")
    top_m: float
    velocity_mps: tuple[float, float]
    velocity_cov_m2ps2: tuple[tuple[float, float], tuple[float, float]]
    first_seen_ns: int = Field(ge=0)
    last_seen_ns: int = Field(ge=0)
    pairs: list[str] = Field(description="pairs whose frames saw it last")
    partial: bool = Field(
        description="no pair has seen all of it, or the map's cells show it larger: its size is "
        "a lower bound; or pieces across a seam's gap joined: the rectangle around them"
    )
    size_unsure: bool = Field(
        default=False,
        description="its complete views are too few or disagree: the size is their median, no "
        "confident measure",
    )
    detections: int = Field(ge=0, description="frames it was measured in")
    settled: bool = Field(
        default=False, description="static for good: stood still for the tracker's static_after_s"
    )


class ObjectsHeader(_Header):
    """``map/objects`` reply and put: every current track at ``stamp_ns`` (newest capture), the
    pieces of one object across a seam's gap as one. Its revision is (``epoch``, ``version``), as
    the map's: a restarted fusion service starts a new epoch, with versions and track ids from 1
    again (an id names one object within an epoch)."""

    model_config = SERVED

    epoch: int = Field(default=0, ge=0, description="the map's epoch (ns) this list belongs to")
    version: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    objects: list[TrackedObject]
