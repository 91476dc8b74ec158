"""What fusion accepts: one decode function per message kind (tile, detections, liveliness) turns
bytes into a typed message or a :class:`Rejected` with a named reason, counted in ``map/health``.

Trust: a message's pair is the one in its key (``depth/{pair}/…``), so access control on a pair's
keys means something; a header naming another pair is rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common import keys
from common.arrays import F64
from common.codec import CodecError, decode
from common.lattice import Window
from common.messages import (
    DETECTIONS_KIND,
    TILE_KIND,
    DetectionRecord,
    DetectionsHeader,
    TileHeader,
)

REASONS = (
    "malformed",
    "resolution",
    "dimensions",
    "nan",
    "height",
    "footprint",
    "hidden",
    "stale",
    "future",
    "out_of_order",
    "pair",
    "camera",
    "outside_map",
    "outside_extent",
    "growth",
    "overload",
    "internal",
)
"""``internal``: fusing the message raised something unforeseen (a bug): counted and logged with
the exception, and the owner's loop goes on with the next message."""
HEIGHT_RANGE_M = (-10.0, 100.0)
"""Heights above the floor a tile's observed cell or a detection's top may claim: no overhead
camera sees a surface 100 m up or 10 m below its floor. Beyond is a forged or broken message
(tops of ±3e38 m were served on the height layer)."""
MIN_OUTLINE_M2 = 1e-6
"""An outline enclosing less (a square millimetre) is no top seen: three times one point, or
points on one line, joined into an object 0 m wide."""
FUTURE_TOLERANCE_S = 0.25
"""A capture stamp this far ahead of fusion's clock is clock skew between boxes; further is a
forged or broken clock: rejected, and its stamp not kept (it would lock the pair's later tiles
out as out of order)."""


class Rejected(ValueError):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass(frozen=True)
class AcceptedTile:
    header: TileHeader
    window: Window
    logodds: npt.NDArray[np.float32]
    height_m: npt.NDArray[np.float32]
    count: npt.NDArray[np.uint16]
    hidden: npt.NDArray[np.bool_] | None
    """Cells without an update whose floor is hidden now; None if the tile has no such layer."""


@dataclass(frozen=True)
class Presence:
    """One depth process's liveliness token appeared (``alive``) or went."""

    pair: str
    instance: str
    alive: bool


def pair_of_key(key: str) -> str:
    try:
        return keys.pair_of(key)
    except ValueError as error:
        raise Rejected("pair", str(error)) from None


def check_stamp(stamp_ns: int, now_ns: int, max_age_ns: int) -> None:
    """A capture stamp within ``max_age_ns`` before fusion's clock and FUTURE_TOLERANCE_S after
    it. Either side names the clocks: a camera box whose clock is off by seconds (no NTP) has
    every frame refused, and "N s old" alone read as a slow link."""
    if now_ns - stamp_ns > max_age_ns:
        raise Rejected(
            "stale",
            f"capture stamp is {(now_ns - stamp_ns) / 1e9:.2f} s behind this box's clock "
            "(a camera clock behind, or frames delayed: are the boxes' clocks synchronised?)",
        )
    if stamp_ns - now_ns > FUTURE_TOLERANCE_S * 1e9:
        raise Rejected(
            "future",
            f"capture stamp is {(stamp_ns - now_ns) / 1e9:.2f} s ahead of this box's clock "
            "(are the boxes' clocks synchronised?)",
        )


class TileGate:
    """Decodes and checks tiles; remembers each pair's newest capture stamp to drop reordering."""

    def __init__(
        self,
        resolution_m: float,
        max_age_s: float,
        max_bytes: int,
        site: Window | None = None,
        bounded: bool = False,
    ) -> None:
        self.resolution_m = resolution_m
        self.max_age_ns = int(max_age_s * 1e9)
        self.max_bytes = max_bytes
        self.site = site
        """Where a tile may land (GridParams.site_window); None: anywhere (tools)."""
        self.bounded = bounded
        """The site is the fixed ``--bounds`` (a tile beyond is ``outside_map``), else the extent
        around the origin (``outside_extent``)."""
        self.newest_stamp_ns: dict[str, int] = {}

    def admit(self, payload: bytes, now_ns: int, key: str) -> AcceptedTile:
        """The tile of ``payload`` received on ``key``, or :class:`Rejected`."""
        key_pair = pair_of_key(key)
        try:
            message = decode(payload, TILE_KIND, TileHeader, self.max_bytes)
        except CodecError as error:
            raise Rejected("malformed", str(error)) from None
        h = message.header
        if h.pair != key_pair:
            raise Rejected("pair", f"header names pair {h.pair}, the key {key_pair}")
        if abs(h.resolution_m - self.resolution_m) > 1e-9:
            raise Rejected(
                "resolution",
                f"tile resolution {h.resolution_m} m ≠ map resolution {self.resolution_m} m",
            )
        if self.site is not None and not h.window.empty and h.window.intersect(self.site).empty:
            raise Rejected(
                "outside_map" if self.bounded else "outside_extent",
                f"tile at cells {h.window} lies beyond the site {self.site}"
                + ("" if self.bounded else " (--max-extent-m around the origin)"),
            )
        layers = {}
        for name, dtype, required in (
            ("logodds", np.float32, True),
            ("height_m", np.float32, True),
            ("count", np.uint16, True),
            ("hidden", np.uint8, False),  # sent only where a cell is hidden
        ):
            array = message.arrays.get(name)
            if array is None and not required:
                continue
            if array is None or array.dtype != dtype or array.shape != (h.rows, h.cols):
                got = "missing" if array is None else f"{array.dtype} {array.shape}"
                raise Rejected(
                    "dimensions",
                    f"layer {name} must be {np.dtype(dtype)} {(h.rows, h.cols)}, got {got}",
                )
            layers[name] = array
        hidden = layers.get("hidden")
        if hidden is not None and int(hidden.max(initial=0)) > 1:
            raise Rejected("hidden", "layer hidden holds values other than 0 and 1")
        observed = layers["count"] > 0
        finite_where_observed = np.less_equal(observed, np.isfinite(layers["height_m"]))
        if not np.isfinite(layers["logodds"]).all() or not finite_where_observed.all():
            raise Rejected(
                "nan", "tile holds NaN or infinite log-odds, or heights of observed cells"
            )
        lowest_m, highest_m = HEIGHT_RANGE_M
        plausible = (layers["height_m"] >= lowest_m) & (layers["height_m"] <= highest_m)
        if not np.less_equal(observed, plausible).all():
            raise Rejected("height", f"tile claims heights beyond {lowest_m:g} … {highest_m:g} m")
        check_stamp(h.stamp_ns, now_ns, self.max_age_ns)
        if h.stamp_ns <= self.newest_stamp_ns.get(h.pair, -1):
            raise Rejected(
                "out_of_order", f"tile of {h.pair} is not newer than the last one accepted"
            )
        return AcceptedTile(
            h,
            h.window,
            layers["logodds"],
            layers["height_m"],
            layers["count"],
            None if hidden is None else hidden.view(np.bool_),
        )

    def accepted(self, tile: AcceptedTile) -> None:
        """Record the stamp of a tile taken, as it is held for its capture: a tile the map then
        refuses (``growth``, ``outside_*``) still counts, so its pair's next tile must be newer."""
        self.newest_stamp_ns[tile.header.pair] = tile.header.stamp_ns


def decode_detections(payload: bytes, key: str, now_ns: int, gate: TileGate) -> DetectionsHeader:
    """One pair's objects of one frame (``depth/{pair}/objects``), or :class:`Rejected`. A
    footprint longer than the tracker's largest object is taken (a trailer, a rack row under a
    high camera) and only never rasterised (its wake, outline and seams); one longer than the
    site is a broken detection."""
    key_pair = pair_of_key(key)
    try:
        header = decode(payload, DETECTIONS_KIND, DetectionsHeader, gate.max_bytes).header
    except CodecError as error:
        raise Rejected("malformed", str(error)) from None
    if header.pair != key_pair:
        raise Rejected("pair", f"header names pair {header.pair}, the key {key_pair}")
    site, longest_m = gate.site, math.inf
    if site is not None:
        longest_m = max(site.cols, site.rows) * gate.resolution_m
    for detection in header.detections:
        if site is not None:
            check_on_site(detection, site, gate.resolution_m, gate.bounded)
        check_footprint(detection, longest_m)
    if header.camera_m is not None:
        check_camera(header.camera_m, site, gate.resolution_m, longest_m)
    check_stamp(header.stamp_ns, now_ns, gate.max_age_ns)
    return header


def check_camera(
    camera_m: tuple[float, float, float], site: Window | None, resolution_m: float, reach_m: float
) -> None:
    """A pair's camera above the floor (up to :data:`HEIGHT_RANGE_M`) and over the site or
    within ``reach_m`` of it: the tracker moves a view measured too low along the rays from it
    (``ObjectTracker._at_mover_top``), and one forged 1e30 m away would carry a mover there."""
    x, y, z = camera_m
    if not 0.0 < z <= HEIGHT_RANGE_M[1]:
        raise Rejected(
            "camera", f"a camera {z:.6g} m up is not 0 … {HEIGHT_RANGE_M[1]:g} m above the floor"
        )
    if site is None:
        return
    x0, y0, x1, y1 = site.bounds_m(resolution_m)
    off_m = math.hypot(max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1))
    if off_m > reach_m:
        raise Rejected(
            "camera", f"a camera at ({x:.6g}, {y:.6g}) m stands {off_m:.6g} m off the site"
        )


def check_on_site(
    detection: DetectionRecord, site: Window, resolution_m: float, bounded: bool
) -> None:
    """A detection's centre on the site the tiles may land on: elsewhere it is a forged or broken
    one that would only start tracks the map never shows (as a tile there is rejected). Its
    outline may reach past the site's edge (a box against the bounds), no farther from the
    centre than the site is long (:func:`check_footprint`)."""
    x0, y0, x1, y1 = site.bounds_m(resolution_m)
    x, y = detection.center_m
    if not (x0 <= x < x1 and y0 <= y < y1):
        raise Rejected(
            "outside_map" if bounded else "outside_extent",
            f"a detection at ({x:.6g}, {y:.6g}) m lies beyond the site {site}",
        )


def check_footprint(detection: DetectionRecord, longest_m: float) -> None:
    """A footprint the tracker can take: no longer than ``longest_m``, nor its outline reaching
    farther from its centre; its yaw in [0, π); its outline, if any, enclosing an area; its top
    within :data:`HEIGHT_RANGE_M`. A yaw of 1e308 averaged to NaN in the tracker, an outline of
    one point joined into an object 0 m wide, a footprint of 2 km was rasterised into GiBs."""
    length_m = max(detection.size_m)
    outline = np.asarray(detection.outline_m, np.float64).reshape(-1, 2)
    reach_m = float(np.hypot(*(outline - detection.center_m).T).max(initial=0.0))
    if length_m > longest_m:
        raise Rejected(
            "dimensions",
            f"a detection {length_m:.6g} m long exceeds the {longest_m:g} m a footprint may span",
        )
    if reach_m > longest_m:
        raise Rejected(
            "dimensions",
            f"a detection's outline reaches {reach_m:.6g} m from its centre, past the "
            f"{longest_m:g} m a footprint may span",
        )
    if not 0.0 <= detection.yaw_rad < math.pi:
        raise Rejected(
            "footprint", f"a detection's yaw {detection.yaw_rad:.6g} rad is not in [0, π)"
        )
    if len(outline) and enclosed_m2(outline) < MIN_OUTLINE_M2:
        raise Rejected("footprint", "a detection's outline encloses no area")
    lowest_m, highest_m = HEIGHT_RANGE_M
    if not lowest_m <= detection.top_m <= highest_m:
        raise Rejected(
            "height",
            f"a detection's top at {detection.top_m:.6g} m is beyond {lowest_m:g} … "
            f"{highest_m:g} m",
        )


def enclosed_m2(polygon_m: F64) -> float:
    """A lower bound of the area a polygon's vertices enclose: the largest triangle on the chord
    from its first vertex to the vertex farthest from it (no hull to build: one array operation)."""
    offsets = polygon_m - polygon_m[0]
    far = offsets[np.argmax(np.hypot(*offsets.T))]
    return float(np.abs(offsets[:, 0] * far[1] - offsets[:, 1] * far[0]).max()) / 2


def decode_presence(key: str, alive: bool) -> Presence:
    """A ``depth/{pair}/alive/{instance}`` token's change, or :class:`Rejected` (``liveliness``)."""
    try:
        return Presence(keys.pair_of(key), keys.instance_of(key), alive)
    except ValueError as error:
        raise Rejected("liveliness", str(error)) from None
