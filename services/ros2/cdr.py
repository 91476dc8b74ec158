"""CDR bytes and RIHS01 type hashes of the map messages, from rosbags (pure Python, no ROS):
the same bytes rclpy's ``serialize_message`` gives, with the 4-byte encapsulation header.

map_msgs has no wheel and is not in rosbags' stores: its OccupancyGridUpdate is registered from
its message definition (ros-planning/navigation_msgs, map_msgs/msg/OccupancyGridUpdate.msg), so
rosbags derives its CDR layout and type hash the way it does for the shipped types.
"""

from __future__ import annotations

from functools import cache
from typing import Any, Literal

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from services.ros2.grid_message import (
    GridInfo,
    GridMessage,
    GridUpdate,
    HeightImage,
    StaticTransform,
    stamp_parts,
)
from services.ros2.object_markers import NAMESPACE, ObjectMarkers
from services.ros2.rmw_zenoh import NO_TYPE_HASH

Distro = Literal["humble", "jazzy", "kilted"]
STORES: dict[str, Stores] = {
    "humble": Stores.ROS2_HUMBLE,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
}
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
OCCUPANCY_GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
IMAGE = "sensor_msgs/msg/Image"
MARKER = "visualization_msgs/msg/Marker"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
MARKER_CUBE, MARKER_ADD, MARKER_DELETEALL = 1, 0, 3
"""visualization_msgs/Marker's constants."""
NUMPY_TYPES = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8}
OCCUPANCY_GRID_UPDATE_MSG = """\
std_msgs/Header header
int32 x
int32 y
uint32 width
uint32 height
int8[] data
"""


@cache
def typestore(distro: Distro) -> Typestore:
    store = get_typestore(STORES[distro])
    store.register(get_types_from_msg(OCCUPANCY_GRID_UPDATE_MSG, OCCUPANCY_GRID_UPDATE))
    return store


def type_hash(distro: Distro, ros_type: str) -> str:
    """The RIHS01 hash rmw_zenoh puts in keys; Humble has none."""
    if distro == "humble":
        return NO_TYPE_HASH
    return str(typestore(distro).hash_rihs01(ros_type))


def _header(store: Typestore, stamp_ns: int, frame_id: str) -> Any:
    types = store.types
    sec, nanosec = stamp_parts(stamp_ns)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def _info(store: Typestore, info: GridInfo) -> Any:
    types = store.types
    x, y, z = info.origin_xyz_m
    qx, qy, qz, qw = info.origin_xyzw
    sec, nanosec = stamp_parts(info.stamp_ns)
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    return types["nav_msgs/msg/MapMetaData"](
        map_load_time=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
        resolution=info.resolution_m,
        width=info.width,
        height=info.height,
        origin=pose,
    )


def occupancy_grid_cdr(distro: Distro, message: GridMessage) -> bytes:
    store = typestore(distro)
    grid = store.types[OCCUPANCY_GRID](
        header=_header(store, message.info.stamp_ns, message.info.frame_id),
        info=_info(store, message.info),
        data=np.asarray(message.data, dtype=np.int8),
    )
    return bytes(store.serialize_cdr(grid, OCCUPANCY_GRID))


def occupancy_grid_update_cdr(distro: Distro, update: GridUpdate) -> bytes:
    store = typestore(distro)
    message = store.types[OCCUPANCY_GRID_UPDATE](
        header=_header(store, update.stamp_ns, update.frame_id),
        x=update.x,
        y=update.y,
        width=update.width,
        height=update.height,
        data=np.asarray(update.data, dtype=np.int8),
    )
    return bytes(store.serialize_cdr(message, OCCUPANCY_GRID_UPDATE))


def height_image_cdr(distro: Distro, image: HeightImage) -> bytes:
    store = typestore(distro)
    message = store.types[IMAGE](
        header=_header(store, image.stamp_ns, image.frame_id),
        height=image.height,
        width=image.width,
        encoding=image.ENCODING,
        is_bigendian=0,
        step=image.step_bytes,
        data=np.frombuffer(image.data.astype("<f4").tobytes(), np.uint8),
    )
    return bytes(store.serialize_cdr(message, IMAGE))


def tf_message_cdr(distro: Distro, transform: StaticTransform) -> bytes:
    store = typestore(distro)
    types = store.types
    (x, y, z), (qx, qy, qz, qw) = transform.translation_xyz_m, transform.rotation_xyzw
    stamped = types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, transform.stamp_ns, transform.frame_id),
        child_frame_id=transform.child_frame_id,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return bytes(store.serialize_cdr(types[TF_MESSAGE](transforms=[stamped]), TF_MESSAGE))


def default_message(store: Typestore, ros_type: str, **values: Any) -> Any:
    """A message with ``values`` and every other field at ROS's default (0, "", false, empty):
    rosbags' message classes have no defaults, and a Marker has a dozen fields a box never uses."""
    fields = store.fielddefs[ros_type][1]
    return store.types[ros_type](
        **{
            name: values[name] if name in values else _default(store, node, detail)
            for name, (node, detail) in fields
        }
    )


def _default(store: Typestore, node: Nodetype, detail: Any) -> Any:
    if node == Nodetype.BASE:
        base = detail[0]
        return "" if base == "string" else False if base == "bool" else 0
    if node == Nodetype.NAME:
        return default_message(store, detail)
    (item_node, item_detail), count = detail
    if item_node == Nodetype.BASE and item_detail[0] != "string":
        dtype = NUMPY_TYPES.get(item_detail[0], item_detail[0])
        return np.zeros(count if node == Nodetype.ARRAY else 0, dtype)
    return [_default(store, item_node, item_detail) for _ in range(count)]


def marker_array_cdr(distro: Distro, markers: ObjectMarkers) -> bytes:
    store = typestore(distro)
    types = store.types
    header = _header(store, markers.stamp_ns, markers.frame_id)
    clear = default_message(store, MARKER, header=header, ns=NAMESPACE, action=MARKER_DELETEALL)
    boxes = []
    for box in markers.boxes:
        (x, y, z), (qx, qy, qz, qw) = box.center_xyz_m, box.orientation_xyzw
        (sx, sy, sz), (r, g, b, a) = box.size_xyz_m, box.color_rgba
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )
        boxes.append(
            default_message(
                store,
                MARKER,
                header=header,
                ns=NAMESPACE,
                id=box.id,
                type=MARKER_CUBE,
                action=MARKER_ADD,
                pose=pose,
                scale=types["geometry_msgs/msg/Vector3"](x=sx, y=sy, z=sz),
                color=types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a),
            )
        )
    message = types[MARKER_ARRAY](markers=[clear, *boxes])
    return bytes(store.serialize_cdr(message, MARKER_ARRAY))


def decode(distro: Distro, raw: bytes, ros_type: str) -> Any:
    """A message object of ``raw`` CDR bytes (for readers and tests)."""
    return typestore(distro).deserialize_cdr(raw, ros_type)
