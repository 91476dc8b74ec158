"""Settings of both ROS 2 outputs: topic names, frame, QoS and the world → map pose."""

from __future__ import annotations

import math
import os
import re
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator

from common.client import MAX_TIMEOUT_S
from common.settings import CommaList, ZenohSettings, startup_error
from services.ros2.cdr import Distro
from services.ros2.grid_message import INT32_MAX, MapMode, PlanarPose
from services.ros2.rmw_zenoh import Durability, History, Reliability, TopicQos

NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
TOPIC_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
"""ROS 2's rules for a node's and a topic's name (absolute or relative; no substitutions): rclpy
raised on others only once the node started (a traceback), rmw_zenoh's key took a space."""
FRAME_ID = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_/]*")
"""tf2 frame ids carry no leading slash (tf2 refuses those) and no spaces."""
TOPIC_FIELDS = (
    "map_topic",
    "updates_topic",
    "height_topic",
    "objects_topic",
    "detections_topic",
    "tf_static_topic",
)
_TOPIC = (
    TOPIC_NAME,
    "ROS 2 topic name (/-separated tokens of letters, digits and _, none first a digit)",
)
_FRAME = (FRAME_ID, "tf2 frame id (letters, digits, _ and /, no leading /, not empty)")
NAME_RULES: dict[str, tuple[re.Pattern[str], str]] = {
    "node_name": (NODE_NAME, "ROS 2 node name (letters, digits and _, not starting with a digit)"),
    **dict.fromkeys(TOPIC_FIELDS, _TOPIC),
    "frame_id": _FRAME,
    "world_frame_id": _FRAME,
}
"""Each name setting's rule and what it is, for the one-line error."""

HISTORY_DEPTH_MAX = INT32_MAX
"""A history depth DDS and rclpy take (an int32; rclpy refused more with a TypeError traceback)."""
DurabilityName = Literal["transient_local", "volatile"]
ReliabilityName = Literal["reliable", "best_effort"]


class Ros2Settings(ZenohSettings):
    node_name: str = Field("overgrid_map", description="ROS 2 node name")
    frame_id: str = Field("map", description="frame_id of /map, its updates and the height layer")
    map_topic: str = Field("/map", description="nav_msgs/OccupancyGrid topic")
    updates_topic: str = Field(
        "/map_updates", description="map_msgs/OccupancyGridUpdate topic (changed rectangles)"
    )
    height_topic: str = Field(
        "/map_height", description="sensor_msgs/Image 32FC1 topic: top height in m per /map cell"
    )
    objects_topic: str = Field(
        "/map_objects",
        description="visualization_msgs/MarkerArray topic: a box per tracked object",
    )
    detections_topic: str = Field(
        "/map_detections",
        description="vision_msgs/Detection3DArray topic: the tracked objects, typed",
    )
    tf_static_topic: str = Field(
        "/tf_static", description="tf2_msgs/TFMessage topic of the world → map static transform"
    )
    world_frame_id: str = Field(
        "overgrid_world", description="frame_id of overgrid's world frame on /tf_static"
    )
    map_durability: DurabilityName = Field(
        "transient_local", description="/map durability (transient_local: late joiners get it)"
    )
    map_reliability: ReliabilityName = Field("reliable", description="/map reliability")
    map_depth: int = Field(1, ge=1, le=HISTORY_DEPTH_MAX, description="/map history depth")
    map_mode: MapMode = Field(
        "trinary",
        description="/map and /map_updates values, as nav2's map_server gives them by the map "
        "files' thresholds (free ≤ 25, occupied ≥ 65): trinary 0 / 100 / -1 (what AMCL and the "
        "static layer take), scale (undecided cells scaled between the thresholds), raw (the "
        "belief: -1 never seen, free floor about 18)",
    )
    height_durability: DurabilityName = Field(
        "transient_local", description="height layer durability (transient_local: late joiners)"
    )
    height_reliability: ReliabilityName = Field("reliable", description="height layer reliability")
    height_depth: int = Field(
        1, ge=1, le=HISTORY_DEPTH_MAX, description="height layer history depth"
    )
    objects_durability: DurabilityName = Field(
        "transient_local",
        description="durability of both objects topics (transient_local: late joiners get the "
        "last objects)",
    )
    objects_reliability: ReliabilityName = Field(
        "reliable", description="reliability of both objects topics"
    )
    objects_depth: int = Field(
        1, ge=1, le=HISTORY_DEPTH_MAX, description="history depth of both objects topics"
    )
    updates_depth: int = Field(
        10, ge=1, le=HISTORY_DEPTH_MAX, description="/map_updates history depth"
    )
    world_in_map: CommaList = Field(
        default_factory=lambda: ["0", "0", "0"],
        description="pose x,y,yaw (m, m, rad) of overgrid's world frame in the robots' map frame",
    )
    map_interval_s: float = Field(
        1.0,
        gt=0.0,
        description="shortest time between whole /map messages while updates stream",
    )
    height_interval_s: float = Field(
        1.0, gt=0.0, description="period of the height layer (fetched from map/latest)"
    )
    timeout_s: float = Field(
        2.0,
        gt=0.0,
        le=MAX_TIMEOUT_S,
        description="how long one map/latest query waits for the fusion service",
    )

    @field_validator("world_in_map")
    @classmethod
    def _three_numbers(cls, values: list[str]) -> list[str]:
        if len(values) != 3 or not all(math.isfinite(float(v)) for v in values):
            raise ValueError("world_in_map must be x,y,yaw, three finite numbers")
        return values

    @field_validator(*NAME_RULES)
    @classmethod
    def _ros_name(cls, name: str, info: ValidationInfo) -> str:
        pattern, what = NAME_RULES[str(info.field_name)]
        if not pattern.fullmatch(name) or "//" in name:
            raise ValueError(f"{name!r} is no {what}")
        return name

    @property
    def pose(self) -> PlanarPose:
        x_m, y_m, yaw_rad = (float(v) for v in self.world_in_map)
        return PlanarPose(x_m, y_m, yaw_rad)

    @property
    def map_qos(self) -> TopicQos:
        return _keep_last(self.map_reliability, self.map_durability, self.map_depth)

    @property
    def height_qos(self) -> TopicQos:
        return _keep_last(self.height_reliability, self.height_durability, self.height_depth)

    @property
    def objects_qos(self) -> TopicQos:
        """Of the MarkerArray and the Detection3DArray alike."""
        return _keep_last(self.objects_reliability, self.objects_durability, self.objects_depth)

    @property
    def tf_static_qos(self) -> TopicQos:
        """tf2_ros's StaticBroadcasterQoS: reliable, transient_local, depth 1."""
        return TopicQos(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1)

    @property
    def updates_qos(self) -> TopicQos:
        return TopicQos(
            Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, self.updates_depth
        )


def _keep_last(reliability: ReliabilityName, durability: DurabilityName, depth: int) -> TopicQos:
    return TopicQos(
        Reliability[reliability.upper()], Durability[durability.upper()], History.KEEP_LAST, depth
    )


DOMAIN_ID_MAX = 232
"""ROS 2's highest domain id (DDS port arithmetic; rmw_zenoh takes the same range)."""


def ros_domain_id() -> int:
    """``ROS_DOMAIN_ID`` as every rmw reads it, 0 when unset; one a ROS 2 does not take stops the
    start with one line (it was a traceback, or a silent start on a domain no robot uses)."""
    text = os.environ.get("ROS_DOMAIN_ID") or "0"
    try:
        domain_id = int(text)
    except ValueError:
        domain_id = -1
    if not 0 <= domain_id <= DOMAIN_ID_MAX:
        startup_error(f"ROS_DOMAIN_ID {text!r}: a ROS domain id is a whole number 0 … 232")
    return domain_id


class RmwZenohSettings(Ros2Settings):
    """The native output also needs what a ROS 2 context would know: domain and distro."""

    domain_id: int | None = Field(
        None, ge=0, le=DOMAIN_ID_MAX, description="ROS domain id (default: $ROS_DOMAIN_ID, else 0)"
    )
    distro: Distro = Field(
        "jazzy", description="ROS 2 distro of the robots (type hashes differ; humble has none)"
    )
