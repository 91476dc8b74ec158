"""An ``OccupancyMap`` as the fields of nav_msgs/OccupancyGrid, map_msgs/OccupancyGridUpdate and a
height image, and the world → map pose as a static transform, independent of any ROS library: the rclpy node and the rosbags CDR writer build their
own message objects from these, so the geometry is worked out once.

nav_msgs/OccupancyGrid stores cells row-major from the origin cell, rows along +y: exactly the
layout of ``OccupancyMap.occupancy`` (common/lattice.py), so the data is the array flattened as is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from common.lattice import Window
from common.mapfiles import FREE_MAX, OCCUPIED_MIN, free_cells, occupied_cells
from common.occupancy_map import OccupancyMap

NS_PER_S = 1_000_000_000
INT32_MAX = 2**31 - 1
"""ROS's int32 fields: builtin_interfaces/Time's ``sec`` (ROS 2 time ends 2038-01-19), a
visualization_msgs/Marker's ``id``."""


@dataclass(frozen=True)
class PlanarPose:
    """Pose of overgrid's world frame in the robots' map frame (x, y in metres, yaw in radians):
    T_map_world, applied to the grid's origin, as a site survey would give it."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0

    def apply(self, xy_world: tuple[float, float]) -> tuple[float, float]:
        """A world point in the map frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        x, y = xy_world
        return (self.x_m + c * x - s * y, self.y_m + s * x + c * y)

    @property
    def quaternion_xyzw(self) -> tuple[float, float, float, float]:
        """The rotation about z, as geometry_msgs/Quaternion orders it."""
        return (0.0, 0.0, math.sin(self.yaw_rad / 2), math.cos(self.yaw_rad / 2))


@dataclass(frozen=True)
class GridInfo:
    """nav_msgs/MapMetaData plus the header: what /map, its updates and the height layer share."""

    stamp_ns: int
    frame_id: str
    resolution_m: float
    width: int
    height: int
    origin_xyz_m: tuple[float, float, float]
    origin_xyzw: tuple[float, float, float, float]


@dataclass(frozen=True)
class GridMessage:
    """nav_msgs/OccupancyGrid: ``data`` int8, -1 unknown, 0..100 (common.occupancy_map)."""

    info: GridInfo
    data: npt.NDArray[np.int8]


@dataclass(frozen=True)
class GridUpdate:
    """map_msgs/OccupancyGridUpdate: a rectangle at cell offset (x, y) of the current /map."""

    stamp_ns: int
    frame_id: str
    x: int
    y: int
    width: int
    height: int
    data: npt.NDArray[np.int8]


@dataclass(frozen=True)
class HeightImage:
    """sensor_msgs/Image 32FC1: top height in metres per cell, NaN unobserved, on /map's cells
    (same width, height and row order: row 0 is the origin row, so the image is upside down when
    drawn as a picture, as /map is)."""

    stamp_ns: int
    frame_id: str
    width: int
    height: int
    data: npt.NDArray[np.float32]

    ENCODING = "32FC1"

    @property
    def step_bytes(self) -> int:
        return self.width * 4


@dataclass(frozen=True)
class StaticTransform:
    """geometry_msgs/TransformStamped: the pose of ``child_frame_id`` in ``frame_id``, as
    /tf_static carries it (tf2_msgs/TFMessage), so tf2 relates overgrid's world to the map."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    translation_xyz_m: tuple[float, float, float]
    rotation_xyzw: tuple[float, float, float, float]


def world_transform(
    world_in_map: PlanarPose, frame_id: str, world_frame_id: str, stamp_ns: int
) -> StaticTransform:
    """T_map_world as a static transform: the same pose the grid's origin is moved by."""
    return StaticTransform(
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        child_frame_id=world_frame_id,
        translation_xyz_m=(world_in_map.x_m, world_in_map.y_m, 0.0),
        rotation_xyzw=world_in_map.quaternion_xyzw,
    )


def stamp_parts(stamp_ns: int) -> tuple[int, int]:
    """builtin_interfaces/Time (sec, nanosec) of a stamp in ns since the Unix epoch; a ValueError
    for one past ROS time: rosbags' CDR raised struct.error mid-message (the native output died),
    rclpy wrapped it to another time without a word. Not clamped: a robot reads a stamp as the
    capture time (tf lookups, how fresh the data is), and 2038 is no capture time."""
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    if not -INT32_MAX - 1 <= sec <= INT32_MAX:
        raise ValueError(f"stamp {stamp_ns} ns is outside ROS time (int32 seconds: up to 2038)")
    return sec, nanosec


def grid_info(occupancy_map: OccupancyMap, frame_id: str, world_in_map: PlanarPose) -> GridInfo:
    rows, cols = occupancy_map.occupancy.shape
    x_m, y_m = world_in_map.apply(occupancy_map.origin_m)
    return GridInfo(
        stamp_ns=occupancy_map.stamp_ns,
        frame_id=frame_id,
        resolution_m=occupancy_map.resolution_m,
        width=cols,
        height=rows,
        origin_xyz_m=(x_m, y_m, 0.0),
        origin_xyzw=world_in_map.quaternion_xyzw,
    )


MapMode = Literal["trinary", "scale", "raw"]


def map_values(occupancy: npt.NDArray[np.int8], mode: MapMode) -> npt.NDArray[np.int8]:
    """The map's occupancy (-1 never seen, else its probability 0..100: free floor reads about
    18, at the belief's clamp) sorted as the map files sort it (common.mapfiles: free up to
    FREE_MAX, occupied from OCCUPIED_MIN), in map_server's modes: ``trinary`` 0 free, 100
    occupied, -1 unknown or undecided (AMCL and the costmap's static layer take only 0 and 100
    at their word); ``scale`` the undecided cells as map_server scales them between the
    thresholds (``rint(100 · share of the way)``); ``raw`` the probability."""
    if mode == "raw":
        return occupancy
    free, occupied = free_cells(occupancy), occupied_cells(occupancy)
    values = np.full(occupancy.shape, -1, np.int8)
    if mode == "scale":
        between = (occupancy >= 0) & ~free & ~occupied
        share = (occupancy[between] - FREE_MAX) / (OCCUPIED_MIN - FREE_MAX)
        values[between] = np.rint(100.0 * share).astype(np.int8)
    values[free] = 0
    values[occupied] = 100
    return values


def grid_message(
    occupancy_map: OccupancyMap, frame_id: str, world_in_map: PlanarPose, mode: MapMode
) -> GridMessage:
    return GridMessage(
        grid_info(occupancy_map, frame_id, world_in_map),
        np.ascontiguousarray(map_values(occupancy_map.occupancy, mode)).reshape(-1),
    )


def changed_window(before: OccupancyMap, after: OccupancyMap) -> Window | None:
    """The smallest rectangle holding every cell that differs, in lattice indices; ``None`` when
    the map itself moved or grew (an update cannot say that: a whole /map is due)."""
    if before.window != after.window or before.resolution_m != after.resolution_m:
        return None
    differs = before.occupancy != after.occupancy
    rows = np.flatnonzero(differs.any(axis=1))
    if rows.size == 0:
        return Window(after.i0, after.j0, 0, 0)
    cols = np.flatnonzero(differs.any(axis=0))
    return Window(
        after.i0 + int(cols[0]),
        after.j0 + int(rows[0]),
        int(cols[-1] - cols[0]) + 1,
        int(rows[-1] - rows[0]) + 1,
    )


def grid_update(
    occupancy_map: OccupancyMap, changed: Window, frame_id: str, mode: MapMode
) -> GridUpdate:
    rows, cols = changed.slices_in(occupancy_map.window)
    return GridUpdate(
        stamp_ns=occupancy_map.stamp_ns,
        frame_id=frame_id,
        x=changed.i0 - occupancy_map.i0,
        y=changed.j0 - occupancy_map.j0,
        width=changed.cols,
        height=changed.rows,
        data=np.ascontiguousarray(map_values(occupancy_map.occupancy[rows, cols], mode)).reshape(
            -1
        ),
    )


def height_image(occupancy_map: OccupancyMap, frame_id: str) -> HeightImage:
    if occupancy_map.height_m is None:
        raise ValueError("the map carries no height layer: ask map/latest with layers=height")
    rows, cols = occupancy_map.height_m.shape
    return HeightImage(
        stamp_ns=occupancy_map.stamp_ns,
        frame_id=frame_id,
        width=cols,
        height=rows,
        data=np.ascontiguousarray(occupancy_map.height_m, dtype=np.float32).reshape(-1),
    )
