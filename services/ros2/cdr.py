"""CDR bytes and RIHS01 type hashes of the map messages, from rosbags (pure Python, no ROS):
the same bytes rclpy's ``serialize_message`` gives, with the 4-byte encapsulation header.

map_msgs and vision_msgs have no wheel and are not in rosbags' stores: their messages are
registered from their definitions, so rosbags derives their CDR layout and type hash the way it
does for the shipped types.
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
from services.ros2.object_markers import NAMESPACE, TRACK_SCORE, ObjectMarkers
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
MARKER_CUBE, MARKER_CYLINDER, MARKER_ADD, MARKER_DELETEALL = 1, 3, 0, 3
"""visualization_msgs/Marker's constants."""
DETECTION_3D_ARRAY = "vision_msgs/msg/Detection3DArray"
DETECTION_3D = "vision_msgs/msg/Detection3D"
BOUNDING_BOX_3D = "vision_msgs/msg/BoundingBox3D"
OBJECT_HYPOTHESIS_WITH_POSE = "vision_msgs/msg/ObjectHypothesisWithPose"
OBJECT_HYPOTHESIS = "vision_msgs/msg/ObjectHypothesis"
NUMPY_TYPES = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8}
COVARIANCE_SIZE = 36
"""geometry_msgs/PoseWithCovariance's 6×6 row-major covariance."""
REGISTERED_MSGS = {
    # ros-planning/navigation_msgs, map_msgs/msg/OccupancyGridUpdate.msg.
    OCCUPANCY_GRID_UPDATE: """\
std_msgs/Header header
int32 x
int32 y
uint32 width
uint32 height
int8[] data
""",
    # ros-perception/vision_msgs 4.x (Humble, Jazzy, Kilted), vision_msgs/msg/*.msg, their field
    # lines (comments do not enter the layout or the RIHS01 hash). Taken from the raw sources that
    # rosidl embeds in the generated type descriptions; the hashes rosbags derives from them equal
    # the ones rosidl generated (tests/test_ros2_messages.py).
    OBJECT_HYPOTHESIS: """\
string class_id
float64 score
""",
    OBJECT_HYPOTHESIS_WITH_POSE: """\
ObjectHypothesis hypothesis
geometry_msgs/PoseWithCovariance pose
""",
    BOUNDING_BOX_3D: """\
geometry_msgs/Pose center
geometry_msgs/Vector3 size
""",
    DETECTION_3D: """\
std_msgs/Header header
ObjectHypothesisWithPose[] results
BoundingBox3D bbox
string id
""",
    DETECTION_3D_ARRAY: """\
std_msgs/Header header
Detection3D[] detections
""",
}


@cache
def typestore(distro: Distro) -> Typestore:
    store = get_typestore(STORES[distro])
    for ros_type, definition in REGISTERED_MSGS.items():
        store.register(get_types_from_msg(definition, ros_type))
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


def _pose(
    store: Typestore,
    xyz_m: tuple[float, float, float],
    xyzw: tuple[float, float, float, float],
) -> Any:
    types = store.types
    (x, y, z), (qx, qy, qz, qw) = xyz_m, xyzw
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )


def _vector3(store: Typestore, xyz: tuple[float, float, float]) -> Any:
    x, y, z = xyz
    return store.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _info(store: Typestore, info: GridInfo) -> Any:
    types = store.types
    sec, nanosec = stamp_parts(info.stamp_ns)
    return types["nav_msgs/msg/MapMetaData"](
        map_load_time=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
        resolution=info.resolution_m,
        width=info.width,
        height=info.height,
        origin=_pose(store, info.origin_xyz_m, info.origin_xyzw),
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
    qx, qy, qz, qw = transform.rotation_xyzw
    stamped = types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, transform.stamp_ns, transform.frame_id),
        child_frame_id=transform.child_frame_id,
        transform=types["geometry_msgs/msg/Transform"](
            translation=_vector3(store, transform.translation_xyz_m),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return bytes(store.serialize_cdr(types[TF_MESSAGE](transforms=[stamped]), TF_MESSAGE))


MSG_DEFAULTS: dict[str, dict[str, Any]] = {"geometry_msgs/msg/Quaternion": {"w": 1.0}}
"""The non-zero defaults of .msg definitions that rosbags' type store does not keep: the identity
quaternion (``float64 w 1``), as rclpy gives an unset pose."""


def default_message(store: Typestore, ros_type: str, **values: Any) -> Any:
    """A message with ``values`` and every other field at ROS's default (``MSG_DEFAULTS``, else 0,
    "", false, empty): rosbags' message classes have no defaults, and a Marker has a dozen fields
    a box never uses."""
    fields = store.fielddefs[ros_type][1]
    values = {**MSG_DEFAULTS.get(ros_type, {}), **values}
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
        r, g, b, a = box.color_rgba
        boxes.append(
            default_message(
                store,
                MARKER,
                header=header,
                ns=NAMESPACE,
                id=box.marker_id,
                type=MARKER_CYLINDER if box.round else MARKER_CUBE,
                action=MARKER_ADD,
                pose=_pose(store, box.center_xyz_m, box.orientation_xyzw),
                scale=_vector3(store, box.size_xyz_m),
                color=types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a),
            )
        )
    message = types[MARKER_ARRAY](markers=[clear, *boxes])
    return bytes(store.serialize_cdr(message, MARKER_ARRAY))


def detection_array_cdr(distro: Distro, markers: ObjectMarkers) -> bytes:
    """vision_msgs/Detection3DArray: per track its box, its id, its class as the one hypothesis
    (score ``TRACK_SCORE``) posed at the box centre; the pose covariance stays zero (unknown):
    the tracker estimates the velocity's uncertainty, not the position's."""
    store = typestore(distro)
    types = store.types
    header = _header(store, markers.stamp_ns, markers.frame_id)
    detections = []
    for box in markers.boxes:
        center = _pose(store, box.center_xyz_m, box.orientation_xyzw)
        hypothesis = types[OBJECT_HYPOTHESIS_WITH_POSE](
            hypothesis=types[OBJECT_HYPOTHESIS](class_id=box.object_class, score=TRACK_SCORE),
            pose=types["geometry_msgs/msg/PoseWithCovariance"](
                pose=center, covariance=np.zeros(COVARIANCE_SIZE)
            ),
        )
        detections.append(
            types[DETECTION_3D](
                header=header,
                results=[hypothesis],
                bbox=types[BOUNDING_BOX_3D](center=center, size=_vector3(store, box.size_xyz_m)),
                id=str(box.id),
            )
        )
    message = types[DETECTION_3D_ARRAY](header=header, detections=detections)
    return bytes(store.serialize_cdr(message, DETECTION_3D_ARRAY))


def decode(distro: Distro, raw: bytes, ros_type: str) -> Any:
    """A message object of ``raw`` CDR bytes (for readers and tests)."""
    return typestore(distro).deserialize_cdr(raw, ros_type)
