"""``overgrid ros2``: a real ROS 2 node (rclpy) that follows the fusion service over Zenoh and
publishes /map (nav_msgs/OccupancyGrid, reliable + transient_local, depth 1 by default: a robot
that starts later still gets it, as from nav2's map_server), /map_updates
(map_msgs/OccupancyGridUpdate), /tf_static (tf2_msgs/TFMessage: overgrid's world frame in the
robots' map frame, transient_local) — these two when map_msgs and tf2_msgs are importable: no wheel
ships them, every system ROS 2 has them, and the node says at start which it lacks — the height
layer, and the tracked objects of ``map/objects`` as a visualization_msgs/MarkerArray and, where
vision_msgs is importable, a vision_msgs/Detection3DArray (services/ros2/object_markers.py). The
height layer and both objects topics are transient_local with depth 1 by default, like /map: a
robot that starts later gets the last ones.

The height layer is a sensor_msgs/Image 32FC1 on /map's cells, not a second OccupancyGrid: it
carries metres as float32 with NaN for "never seen", which an int8 0..100 grid could only carry
quantised and with an invented scale; width, height, row order and frame are /map's, so a cell
(row, col) of one is the same lattice cell in the other.

Settings are overgrid's flags and ``OVERGRID_*`` variables, and also this node's ROS parameters
(``--ros-args -p frame_id:=odom``); remapping (``-r /map:=/site/map``) and ``ROS_DOMAIN_ID`` work as
for any node.
"""

from __future__ import annotations

import array
import importlib
import logging
import os
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from pydantic import ValidationError

from common.lifecycle import stop_on_signals
from common.logs import setup_logging
from common.settings import parse_settings, startup_error
from common.zenoh_session import open_session
from services.ros2.environment import ensure_ros_environment
from services.ros2.grid_message import (
    GridMessage,
    GridUpdate,
    HeightImage,
    StaticTransform,
    stamp_parts,
)
from services.ros2.object_markers import NAMESPACE, TRACK_SCORE, ObjectMarkers
from services.ros2.relay import MapRelay
from services.ros2.rmw_zenoh import TopicQos
from services.ros2.settings import TOPIC_FIELDS, Ros2Settings, ros_domain_id

log = logging.getLogger("ros2")
ROS_ARGS = "--ros-args"
ROS_PARAMETERS = (
    "frame_id",
    *TOPIC_FIELDS,
    "world_frame_id",
    "map_depth",
    "updates_depth",
    "map_durability",
    "map_reliability",
    "height_depth",
    "height_durability",
    "height_reliability",
    "objects_depth",
    "objects_durability",
    "objects_reliability",
    "world_in_map",
    "map_mode",
    "map_interval_s",
    "height_interval_s",
)
"""Settings a ROS user may also give as node parameters; the flag or env value is the default."""


def _set_header(header: Any, stamp_ns: int, frame_id: str) -> None:
    header.stamp.sec, header.stamp.nanosec = stamp_parts(stamp_ns)
    header.frame_id = frame_id


def _set_pose(
    pose: Any, xyz_m: tuple[float, float, float], xyzw: tuple[float, float, float, float]
) -> None:
    pose.position.x, pose.position.y, pose.position.z = xyz_m
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = xyzw


def occupancy_grid_msg(grid_type: Any, message: GridMessage) -> Any:
    """A nav_msgs/OccupancyGrid (``grid_type``) of ``message``."""
    grid = grid_type()
    info = message.info
    _set_header(grid.header, info.stamp_ns, info.frame_id)
    grid.info.map_load_time.sec, grid.info.map_load_time.nanosec = stamp_parts(info.stamp_ns)
    grid.info.resolution = info.resolution_m
    grid.info.width, grid.info.height = info.width, info.height
    _set_pose(grid.info.origin, info.origin_xyz_m, info.origin_xyzw)
    grid.data = array.array("b", message.data.tobytes())
    return grid


def occupancy_grid_update_msg(update_type: Any, update: GridUpdate) -> Any:
    message = update_type()
    _set_header(message.header, update.stamp_ns, update.frame_id)
    message.x, message.y = update.x, update.y
    message.width, message.height = update.width, update.height
    message.data = array.array("b", update.data.tobytes())
    return message


def height_image_msg(image_type: Any, image: HeightImage) -> Any:
    message = image_type()
    _set_header(message.header, image.stamp_ns, image.frame_id)
    message.height, message.width = image.height, image.width
    message.encoding, message.is_bigendian = image.ENCODING, sys.byteorder == "big"
    message.step = image.step_bytes
    message.data = array.array("B", image.data.tobytes())
    return message


def marker_array_msg(marker_type: Any, array_type: Any, markers: ObjectMarkers) -> Any:
    """A DELETEALL, then a CUBE per box, a CYLINDER per round one
    (services/ros2/object_markers.py)."""
    clear = marker_type(ns=NAMESPACE, action=marker_type.DELETEALL)
    _set_header(clear.header, markers.stamp_ns, markers.frame_id)
    message = array_type(markers=[clear])
    for box in markers.boxes:
        shape = marker_type.CYLINDER if box.round else marker_type.CUBE
        marker = marker_type(ns=NAMESPACE, id=box.marker_id, type=shape)
        marker.action = marker_type.ADD
        _set_header(marker.header, markers.stamp_ns, markers.frame_id)
        _set_pose(marker.pose, box.center_xyz_m, box.orientation_xyzw)
        marker.scale.x, marker.scale.y, marker.scale.z = box.size_xyz_m
        marker.color.r, marker.color.g, marker.color.b, marker.color.a = box.color_rgba
        message.markers.append(marker)
    return message


def detection_array_msg(vision: Any, markers: ObjectMarkers) -> Any:
    """A vision_msgs/Detection3DArray (``vision``: the ``vision_msgs.msg`` module), as
    ``cdr.detection_array_cdr`` builds it for the native output."""
    message = vision.Detection3DArray()
    _set_header(message.header, markers.stamp_ns, markers.frame_id)
    for box in markers.boxes:
        detection = vision.Detection3D(id=str(box.id))
        _set_header(detection.header, markers.stamp_ns, markers.frame_id)
        _set_pose(detection.bbox.center, box.center_xyz_m, box.orientation_xyzw)
        detection.bbox.size.x, detection.bbox.size.y, detection.bbox.size.z = box.size_xyz_m
        result = vision.ObjectHypothesisWithPose()
        result.hypothesis.class_id, result.hypothesis.score = box.object_class, TRACK_SCORE
        _set_pose(result.pose.pose, box.center_xyz_m, box.orientation_xyzw)
        detection.results.append(result)
        message.detections.append(detection)
    return message


def tf_msg(stamped_type: Any, message_type: Any, transform: StaticTransform) -> Any:
    stamped = stamped_type(child_frame_id=transform.child_frame_id)
    _set_header(stamped.header, transform.stamp_ns, transform.frame_id)
    translation, rotation = stamped.transform.translation, stamped.transform.rotation
    translation.x, translation.y, translation.z = transform.translation_xyz_m
    rotation.x, rotation.y, rotation.z, rotation.w = transform.rotation_xyzw
    return message_type(transforms=[stamped])


class RclpySink:
    """The relay's messages as rclpy messages on the publishers of ``node``: /map, the height layer
    and the objects' markers always; /map_updates, /tf_static and the objects' Detection3DArray
    when map_msgs, tf2_msgs and vision_msgs are importable (six at most)."""

    def __init__(self, node: Any, settings: Ros2Settings) -> None:
        OccupancyGrid = ros_messages("nav_msgs").OccupancyGrid
        Image = ros_messages("sensor_msgs").Image
        self._grid_type, self._image_type = OccupancyGrid, Image
        self._map = node.create_publisher(
            OccupancyGrid, settings.map_topic, rclpy_qos(settings.map_qos)
        )
        self._height = node.create_publisher(
            Image, settings.height_topic, rclpy_qos(settings.height_qos)
        )
        objects_qos = rclpy_qos(settings.objects_qos)
        try:
            visualization = ros_messages("visualization_msgs")
            Marker, MarkerArray = visualization.Marker, visualization.MarkerArray
        except ImportError:
            self._objects: Any = None
            log.warning(f"visualization_msgs is not importable: {settings.objects_topic} is off")
        else:
            self._marker_types: Any = (Marker, MarkerArray)
            self._objects = node.create_publisher(MarkerArray, settings.objects_topic, objects_qos)
        try:
            self._vision: Any = ros_messages("vision_msgs")
        except ImportError:
            self._detections: Any = None
            _say_not_published("vision_msgs", settings.detections_topic, VISION_MSGS_HINT)
        else:
            self._detections = node.create_publisher(
                self._vision.Detection3DArray, settings.detections_topic, objects_qos
            )
        try:
            OccupancyGridUpdate = ros_messages("map_msgs").OccupancyGridUpdate
        except ImportError:
            self._update_type: Any = None
            self._updates = None
            _say_not_published("map_msgs", settings.updates_topic)
        else:
            self._update_type = OccupancyGridUpdate
            self._updates = node.create_publisher(
                OccupancyGridUpdate, settings.updates_topic, settings.updates_depth
            )
        try:
            TransformStamped = ros_messages("geometry_msgs").TransformStamped
            TFMessage = ros_messages("tf2_msgs").TFMessage
        except ImportError:
            self._tf_static = None
            _say_not_published("tf2_msgs", settings.tf_static_topic)
        else:
            self._tf_types: Any = (TransformStamped, TFMessage)
            self._tf_static = node.create_publisher(
                TFMessage, settings.tf_static_topic, rclpy_qos(settings.tf_static_qos)
            )

    @property
    def map_topic(self) -> str:
        """/map's name as remapped."""
        return str(self._map.topic_name)

    def publish_map(self, message: GridMessage) -> None:
        self._map.publish(occupancy_grid_msg(self._grid_type, message))

    def publish_update(self, update: GridUpdate) -> None:
        if self._updates is not None:
            self._updates.publish(occupancy_grid_update_msg(self._update_type, update))

    def publish_height(self, image: HeightImage) -> None:
        self._height.publish(height_image_msg(self._image_type, image))

    def publish_objects(self, markers: ObjectMarkers) -> None:
        if self._objects is not None:
            marker_type, array_type = self._marker_types
            self._objects.publish(marker_array_msg(marker_type, array_type, markers))
        if self._detections is not None:
            self._detections.publish(detection_array_msg(self._vision, markers))

    def publish_static_transform(self, transform: StaticTransform) -> None:
        if self._tf_static is not None:
            stamped_type, message_type = self._tf_types
            self._tf_static.publish(tf_msg(stamped_type, message_type, transform))


def ros_messages(package: str) -> Any:
    """``package.msg``, untyped: ROS message modules ship no type information."""
    return importlib.import_module(f"{package}.msg")


SYSTEM_ROS_HINT = "no wheel ships it; a system ROS 2 has it"
VISION_MSGS_HINT = "no wheel ships it; apt install ros-$ROS_DISTRO-vision-msgs"


def _say_not_published(package: str, topic: str, hint: str = SYSTEM_ROS_HINT) -> None:
    log.warning(
        f"{package} is not importable ({hint}): "
        f"{topic} is not published by this node; `overgrid rmw-zenoh` always carries it"
    )


def rclpy_qos(qos: TopicQos) -> Any:
    """rclpy's QoSProfile of the QoS both outputs declare (rmw's enum names are rclpy's)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy[qos.history.name],
        depth=qos.depth,
        reliability=ReliabilityPolicy[qos.reliability.name],
        durability=DurabilityPolicy[qos.durability.name],
    )


def with_ros_parameters(node: Any, settings: Ros2Settings) -> Ros2Settings:
    """Declare ``ROS_PARAMETERS`` with the settings as defaults; a value given as a parameter
    (``-p name:=value``, a parameter file) wins, and is validated like a flag."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    # Read once, at start: a later set would be taken and not applied, so it is refused. One
    # descriptor each: rclpy writes the parameter's name and type into the one it is given.
    values: dict[str, Any] = {}
    for name in ROS_PARAMETERS:
        default = getattr(settings, name)
        if isinstance(default, list):
            default = ",".join(default)
        try:
            fixed = ParameterDescriptor(read_only=True)
            values[name] = node.declare_parameter(name, default, fixed).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as error:
            startup_error(f"ROS parameter {name}: {error}")
    try:
        return Ros2Settings.model_validate({**settings.model_dump(), **values})
    except ValidationError as error:
        first = error.errors()[0]
        name = ".".join(str(part) for part in first["loc"])
        startup_error(f"ROS parameter {name}: {first['msg']}")


def main(settings: Ros2Settings, ros_args: Sequence[str] = ()) -> None:
    setup_logging("ros2", settings.log_level)
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.signals import SignalHandlerOptions

    # What rcl raises for arguments it refuses (rclpy re-exports neither).
    refusals = (rclpy_implementation.UnknownROSArgsError, rclpy_implementation.RCLError)

    ros_domain_id()  # checked here: rcl's own refusal is a traceback
    refused: Exception | None = None
    with _stderr_held() as drop_held:
        try:
            rclpy.init(
                args=["overgrid-ros2", ROS_ARGS, *ros_args] if ros_args else None,
                signal_handler_options=SignalHandlerOptions.NO,
            )
        except refusals as error:
            if not ros_args:
                raise  # not the arguments' fault: rcl's own words, and its traceback
            drop_held()  # rcl's own log line of it: the one line below says it
            refused = error
    if refused is not None:
        reason = (str(refused).splitlines() or [type(refused).__name__])[0].split(", at /")[0]
        startup_error(f"--ros-args {' '.join(ros_args)}: {reason}")
    node = rclpy.create_node(settings.node_name)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner: threading.Thread | None = None
    try:
        settings = with_ros_parameters(node, settings)
        sink = RclpySink(node, settings)
        # Spinning serves the node's parameter and graph services; publishing needs no spin.
        spinner = threading.Thread(target=executor.spin, name="rclpy-spin")
        spinner.start()
        with open_session(settings, wait_for_router=True) as session:
            relay = MapRelay(session, settings, sink, log)
            stop = stop_on_signals(relay.wake)
            log.info(  # as remapped: the names the robots' graph shows
                "started",
                extra={"node": node.get_fully_qualified_name(), "map_topic": sink.map_topic},
            )
            relay.run(stop)
        log.info("stopped", extra={**relay.counts, **relay.rejected})
    finally:
        executor.shutdown(timeout_sec=1.0)
        if spinner is not None:  # a spinning thread left to die at exit aborts the process
            spinner.join()
        node.destroy_node()
        rclpy.try_shutdown()


@contextmanager
def _stderr_held() -> Iterator[Callable[[], None]]:
    """What C code writes to stderr meanwhile, held and written after, unless the function it
    yields is called: rcl logs a refused argument itself before rclpy raises (a second line)."""
    dropped = False

    def drop() -> None:
        nonlocal dropped
        dropped = True

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield drop
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            if not dropped:
                sys.stderr.buffer.write(held.read())
                sys.stderr.flush()


def split_ros_args(args: Sequence[str]) -> tuple[list[str], list[str]]:
    """overgrid's own arguments, and the ROS ones: from ``--ros-args`` to a lone ``--`` or the
    end, as rcl delimits them (so overgrid's flags may follow a ``--``)."""
    if ROS_ARGS not in args:
        return list(args), []
    at = list(args).index(ROS_ARGS)
    rest = list(args[at + 1 :])
    end = rest.index("--") if "--" in rest else len(rest)
    return [*args[:at], *rest[end + 1 :]], rest[:end]


def cli(argv: Sequence[str] | None = None) -> None:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    settings = parse_settings(
        Ros2Settings, own, "overgrid ros2", "A ROS 2 node publishing the map (rclpy)."
    )
    ensure_ros_environment()
    main(settings, ros_args)
