"""``map/objects`` as oriented boxes in the robots' map frame, independent of any ROS library: the
fields of both object messages.

- visualization_msgs/MarkerArray: one CUBE per tracked object (its oriented footprint, from the
  floor to its top; a CYLINDER for a round one), after a DELETEALL, so a track that ended
  disappears from RViz without bookkeeping of ids. Every ROS 2 robot can show and read it (id,
  pose, size) with no extra package.
- vision_msgs/Detection3DArray: the typed form a perception or planning node consumes, one
  Detection3D per track (its box, its id, its class as the one hypothesis). vision_msgs has no
  wheel: the native output registers its definitions with rosbags (services/ros2/cdr.py), the rclpy
  node publishes it where vision_msgs is importable.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.messages import ObjectsHeader
from services.ros2.grid_message import INT32_MAX, PlanarPose

NAMESPACE = "overgrid_objects"
"""Marker ``ns``: the ids are the tracks' ids within it."""
MIN_HEIGHT_M = 0.01
"""A box needs some height to be drawn; a flat object's top can read 0."""
COLOR_RGBA = {"static": (0.55, 0.55, 0.6, 0.8), "moving": (1.0, 0.45, 0.0, 0.9)}
TRACK_SCORE = 1.0
"""ObjectHypothesis ``score`` of a track's class: a confirmed track, not a classifier's guess."""


@dataclass(frozen=True)
class BoxMarker:
    """One tracked object's box: centre and size in metres, orientation as a quaternion (x, y, z,
    w); its class ("static", "moving") and the colour the marker shows it in."""

    id: int
    center_xyz_m: tuple[float, float, float]
    orientation_xyzw: tuple[float, float, float, float]
    size_xyz_m: tuple[float, float, float]
    color_rgba: tuple[float, float, float, float]
    object_class: str
    round: bool = False
    """A round top: a CYLINDER whose diameters are the size's x and y."""

    @property
    def marker_id(self) -> int:
        """The track's id as a Marker's int32 ``id``: the same for every message of the track,
        so RViz moves its box in place. Fusion counts ids from 1 in each epoch, so only a broken
        or forged list reaches 2³¹ (it ended the native output); folded, its boxes still show,
        and the Detection3D's string id carries the id whole."""
        return self.id % (INT32_MAX + 1)


@dataclass(frozen=True)
class ObjectMarkers:
    stamp_ns: int
    frame_id: str
    boxes: tuple[BoxMarker, ...]


def object_markers(header: ObjectsHeader, frame_id: str, world_in_map: PlanarPose) -> ObjectMarkers:
    boxes = []
    for tracked in header.objects:
        x_m, y_m = world_in_map.apply(tracked.center_m)
        height_m = max(tracked.top_m, MIN_HEIGHT_M)
        yaw = PlanarPose(yaw_rad=tracked.yaw_rad + world_in_map.yaw_rad)
        boxes.append(
            BoxMarker(
                id=tracked.id,
                center_xyz_m=(x_m, y_m, height_m / 2),
                orientation_xyzw=yaw.quaternion_xyzw,
                size_xyz_m=(tracked.size_m[0], tracked.size_m[1], height_m),
                color_rgba=COLOR_RGBA[tracked.object_class],
                object_class=tracked.object_class,
                round=tracked.round,
            )
        )
    return ObjectMarkers(header.stamp_ns, frame_id, tuple(boxes))
