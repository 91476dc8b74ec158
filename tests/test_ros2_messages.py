"""The map and its objects as ROS 2 message fields (services/ros2/grid_message.py,
object_markers.py), their CDR (rosbags) against rclpy's, and the type hashes of the messages
registered from their definitions (map_msgs, vision_msgs)."""

from __future__ import annotations

import importlib
import math
from typing import Any

import numpy as np
import pytest
from rosbags.interfaces import Nodetype
from rosbags.typesys.store import Typestore

from common.lattice import Window
from common.messages import ObjectsHeader, TrackedObject
from common.occupancy_map import UNKNOWN, OccupancyMap
from services.ros2 import cdr, node
from services.ros2.grid_message import (
    INT32_MAX,
    NS_PER_S,
    PlanarPose,
    changed_window,
    grid_message,
    grid_update,
    height_image,
    map_values,
    stamp_parts,
    world_transform,
)
from services.ros2.object_markers import COLOR_RGBA, NAMESPACE, object_markers

STAMP_NS = 1_700_000_000_123_456_789


def a_map(i0: int = -3, j0: int = 4, cols: int = 5, rows: int = 3) -> OccupancyMap:
    occupancy = np.full((rows, cols), UNKNOWN, np.int8)
    occupancy[0, 1] = 100  # cell (i0 + 1, j0): lowest row, second column
    occupancy[2, 4] = 0
    height = np.full((rows, cols), np.nan, np.float32)
    height[0, 1] = 0.7
    return OccupancyMap(occupancy, 0.05, i0, j0, 3, STAMP_NS, ["p0"], height_m=height)


def test_grid_is_the_lattice_row_major_from_the_origin_cell() -> None:
    message = grid_message(a_map(), "map", PlanarPose(), "raw")
    info = message.info
    assert (info.width, info.height, info.resolution_m) == (5, 3, 0.05)
    assert info.origin_xyz_m == pytest.approx((-0.15, 0.2, 0.0))
    assert info.origin_xyzw == (0.0, 0.0, 0.0, 1.0)
    assert message.data[1] == 100 and message.data[2 * 5 + 4] == 0
    assert (message.data == UNKNOWN).sum() == 13


def test_map_values_are_map_servers_by_the_map_files_thresholds() -> None:
    """The belief's free floor reads 18 (its clamp), never 0: AMCL took no cell for free and the
    static layer (trinary) a 65..99 cell for free, where the map files call it occupied."""
    belief = np.array([[-1, 18, 25, 26, 45, 64, 65, 99, 100]], np.int8)
    assert map_values(belief, "trinary").tolist() == [[-1, 0, 0, -1, -1, -1, 100, 100, 100]]
    assert map_values(belief, "scale").tolist() == [[-1, 0, 0, 2, 50, 98, 100, 100, 100]]
    assert map_values(belief, "raw") is belief
    occupancy_map = a_map()
    occupancy_map.occupancy[1, 1] = 18
    trinary = grid_message(occupancy_map, "map", PlanarPose(), "trinary").data
    assert trinary[5 + 1] == 0 and set(np.unique(trinary).tolist()) == {-1, 0, 100}
    changed = Window(occupancy_map.i0 + 1, occupancy_map.j0 + 1, 1, 1)
    assert grid_update(occupancy_map, changed, "map", "trinary").data.tolist() == [0]


def test_world_in_map_pose_moves_and_turns_the_origin() -> None:
    pose = PlanarPose(10.0, -1.0, math.pi / 2)
    info = grid_message(a_map(), "site", pose, "raw").info
    # origin (-0.15, 0.2) turned by 90°: (-0.2, -0.15), then shifted.
    assert info.origin_xyz_m == pytest.approx((9.8, -1.15, 0.0))
    assert info.origin_xyzw == pytest.approx((0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)))
    assert info.frame_id == "site"


def test_changed_window_is_the_bounding_box_of_changed_cells() -> None:
    before = a_map()
    assert changed_window(before, before) == Window(-3, 4, 0, 0)
    occupancy = before.occupancy.copy()
    occupancy[1, 0] = 50
    occupancy[2, 2] = 20
    after = OccupancyMap(occupancy, 0.05, -3, 4, 4, STAMP_NS)
    changed = changed_window(before, after)
    assert changed == Window(-3, 5, 3, 2)
    assert changed is not None
    update = grid_update(after, changed, "map", "raw")
    assert (update.x, update.y, update.width, update.height) == (0, 1, 3, 2)
    assert update.data.reshape(2, 3).tolist() == [[50, -1, -1], [-1, -1, 20]]
    grown = a_map(cols=6)
    assert changed_window(before, grown) is None


def test_height_image_keeps_metres_and_unseen_nan() -> None:
    image = height_image(a_map(), "map")
    assert (image.width, image.height, image.step_bytes) == (5, 3, 20)
    assert image.data[1] == pytest.approx(0.7)
    assert np.isnan(image.data).sum() == 14
    without = OccupancyMap(a_map().occupancy, 0.05, 0, 0, 1, STAMP_NS)
    with pytest.raises(ValueError, match="layers=height"):
        height_image(without, "map")


def test_stamp_parts() -> None:
    assert stamp_parts(STAMP_NS) == (1_700_000_000, 123_456_789)
    last_ns = (INT32_MAX + 1) * NS_PER_S - 1
    assert stamp_parts(last_ns) == (INT32_MAX, NS_PER_S - 1)
    with pytest.raises(ValueError, match="outside ROS time"):
        stamp_parts(last_ns + 1)


@pytest.mark.parametrize("distro", ["humble", "jazzy", "kilted"])
def test_cdr_round_trips_through_rosbags(distro: cdr.Distro) -> None:
    occupancy_map = a_map()
    raw = cdr.occupancy_grid_cdr(
        distro, grid_message(occupancy_map, "map", PlanarPose(1, 2, 0), "raw")
    )
    assert raw[:4] == b"\x00\x01\x00\x00"  # little-endian CDR encapsulation header
    grid = cdr.decode(distro, raw, cdr.OCCUPANCY_GRID)
    assert (grid.info.width, grid.info.height) == (5, 3)
    assert (grid.header.stamp.sec, grid.header.stamp.nanosec) == stamp_parts(STAMP_NS)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == pytest.approx((0.85, 2.2))
    assert np.array_equal(np.asarray(grid.data).reshape(3, 5), occupancy_map.occupancy)

    changed = Window(-2, 4, 2, 1)
    update = cdr.decode(
        distro,
        cdr.occupancy_grid_update_cdr(distro, grid_update(occupancy_map, changed, "map", "raw")),
        cdr.OCCUPANCY_GRID_UPDATE,
    )
    assert (update.x, update.y, update.width, update.height) == (1, 0, 2, 1)
    assert list(update.data) == [100, -1]

    image = cdr.decode(
        distro, cdr.height_image_cdr(distro, height_image(occupancy_map, "map")), cdr.IMAGE
    )
    assert (image.encoding, image.step, image.is_bigendian) == ("32FC1", 20, 0)
    metres = np.frombuffer(bytes(image.data), "<f4").reshape(3, 5)
    assert metres[0, 1] == pytest.approx(0.7) and np.isnan(metres[0, 0])


def tracked_objects(version: int = 1, drum: bool = False) -> ObjectsHeader:
    """A map/objects message with one moving box, 0.8 × 0.4 m, 1.2 m tall, at (1, 2); ``drum``:
    and a static round one, 0.5 m across, 0.9 m tall, at (3, 1)."""
    box = TrackedObject(
        center_m=(1.0, 2.0),
        size_m=(0.8, 0.4),
        yaw_rad=0.3,
        id=5,
        object_class="moving",
        top_m=1.2,
        velocity_mps=(0.5, 0.0),
        velocity_cov_m2ps2=((0.01, 0.0), (0.0, 0.01)),
        first_seen_ns=STAMP_NS - 10**9,
        last_seen_ns=STAMP_NS,
        pairs=["p0"],
        partial=False,
        detections=3,
    )
    round_ = box.model_copy(
        update={
            "center_m": (3.0, 1.0),
            "size_m": (0.5, 0.5),
            "yaw_rad": 0.0,
            "id": 6,
            "object_class": "static",
            "top_m": 0.9,
            "velocity_mps": (0.0, 0.0),
            "round": True,
        }
    )
    return ObjectsHeader(
        version=version, stamp_ns=STAMP_NS, objects=[box, round_] if drum else [box]
    )


def test_objects_are_boxes_from_the_floor_to_their_top_in_the_map_frame() -> None:
    markers = object_markers(tracked_objects(), "site", PlanarPose(10.0, 0.0, math.pi / 2))
    (box,) = markers.boxes
    assert (markers.frame_id, markers.stamp_ns, box.id) == ("site", STAMP_NS, 5)
    assert box.center_xyz_m == pytest.approx((8.0, 1.0, 0.6))
    assert box.size_xyz_m == pytest.approx((0.8, 0.4, 1.2))
    yaw = 0.3 + math.pi / 2
    assert box.orientation_xyzw == pytest.approx((0, 0, math.sin(yaw / 2), math.cos(yaw / 2)))
    assert box.color_rgba == COLOR_RGBA["moving"]


@pytest.mark.parametrize("distro", ["humble", "kilted"])
def test_marker_array_clears_then_adds_one_cube_per_object(distro: cdr.Distro) -> None:
    markers = object_markers(tracked_objects(), "map", PlanarPose())
    array = cdr.decode(distro, cdr.marker_array_cdr(distro, markers), cdr.MARKER_ARRAY)
    clear, cube = array.markers
    assert (clear.ns, clear.action) == (NAMESPACE, cdr.MARKER_DELETEALL)
    assert clear.pose.orientation.w == 1.0  # the .msg default, as rclpy gives it
    assert (cube.ns, cube.id, cube.type, cube.action) == (NAMESPACE, 5, cdr.MARKER_CUBE, 0)
    assert (cube.pose.position.x, cube.pose.position.y, cube.pose.position.z) == pytest.approx(
        (1.0, 2.0, 0.6)
    )
    assert (cube.scale.x, cube.scale.y, cube.scale.z) == pytest.approx((0.8, 0.4, 1.2))
    assert cube.header.frame_id == "map" and len(cube.points) == 0
    with_drum = object_markers(tracked_objects(drum=True), "map", PlanarPose())
    array = cdr.decode(distro, cdr.marker_array_cdr(distro, with_drum), cdr.MARKER_ARRAY)
    _, _, drum = array.markers
    assert (drum.id, drum.type) == (6, cdr.MARKER_CYLINDER)
    assert (drum.scale.x, drum.scale.y, drum.scale.z) == pytest.approx((0.5, 0.5, 0.9))


def test_values_ros_messages_cannot_carry_are_folded_or_refused() -> None:
    """A track id past int32 (only a broken or forged list has one) and a stamp past 2038 ended
    `overgrid rmw-zenoh` with a struct.error; rclpy took both and wrapped them to other values
    without a word. The id is folded into the Marker's int32, the same for each message of the
    track, and carried whole by the Detection3D; the stamp is refused (a ValueError the relay
    counts), by both outputs alike."""
    header = tracked_objects()
    far = header.objects[0].model_copy(update={"id": 2**40})
    markers = object_markers(header.model_copy(update={"objects": [far]}), "map", PlanarPose())
    visualization = node.ros_messages("visualization_msgs")
    folded = 2**40 % 2**31
    _, cube = cdr.decode("jazzy", cdr.marker_array_cdr("jazzy", markers), cdr.MARKER_ARRAY).markers
    (detection,) = cdr.decode(
        "jazzy", cdr.detection_array_cdr("jazzy", markers), cdr.DETECTION_3D_ARRAY
    ).detections
    assert (cube.id, detection.id) == (folded, str(2**40))
    rclpy_array = node.marker_array_msg(visualization.Marker, visualization.MarkerArray, markers)
    assert rclpy_array.markers[1].id == folded
    late = object_markers(header.model_copy(update={"stamp_ns": 2**64 - 1}), "map", PlanarPose())
    with pytest.raises(ValueError, match="outside ROS time"):
        cdr.marker_array_cdr("jazzy", late)
    with pytest.raises(ValueError, match="outside ROS time"):
        node.marker_array_msg(visualization.Marker, visualization.MarkerArray, late)


TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
"""tf2_msgs/msg/TFMessage's type hash as ZettaScale's rmw_zenoh examples spell it in their /tf and
/tf_static graph tokens (no tf2_msgs wheel ships its .json here to read it from)."""


@pytest.mark.parametrize("distro", ["humble", "jazzy", "kilted"])
def test_tf_static_carries_the_world_in_the_map_frame(distro: cdr.Distro) -> None:
    pose = PlanarPose(10.0, -1.0, math.pi / 2)
    transform = world_transform(pose, "map", "overgrid_world", STAMP_NS)
    raw = cdr.tf_message_cdr(distro, transform)
    assert raw[:4] == b"\x00\x01\x00\x00"
    (stamped,) = cdr.decode(distro, raw, cdr.TF_MESSAGE).transforms
    assert (stamped.header.frame_id, stamped.child_frame_id) == ("map", "overgrid_world")
    assert (stamped.header.stamp.sec, stamped.header.stamp.nanosec) == stamp_parts(STAMP_NS)
    moved = stamped.transform.translation
    assert (moved.x, moved.y, moved.z) == (10.0, -1.0, 0.0)
    turned = stamped.transform.rotation
    assert (turned.x, turned.y, turned.z, turned.w) == pytest.approx(pose.quaternion_xyzw)
    # The same pose moves /map's origin: the world's origin cell lands where tf2 puts it.
    origin = grid_message(a_map(i0=0, j0=0), "map", pose, "raw").info.origin_xyz_m
    assert origin == pytest.approx((10.0, -1.0, 0.0))
    if distro != "humble":
        assert cdr.type_hash(distro, cdr.TF_MESSAGE) == TF_MESSAGE_HASH


VISION_MSGS_HASHES = {
    cdr.DETECTION_3D_ARRAY: "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018",
    cdr.DETECTION_3D: "RIHS01_ddd703be132ab0b69d33121f1bb034132bfbb3b0ac5f9fb1516005ba1c8a265b",
    cdr.BOUNDING_BOX_3D: "RIHS01_bbb73a65c163d7f9bb29009c7bde9f7faa576bd2d23299c4511d19230dab4698",
    cdr.OBJECT_HYPOTHESIS_WITH_POSE: (
        "RIHS01_41c12344c0396c48b81df12467c192d99b2a0eb1463c5c37194e4223251c80bc"
    ),
    cdr.OBJECT_HYPOTHESIS: "RIHS01_51da43cec11c01957a64d1e05a24acd18aae7745ec30b74348ad5f6d634f7f90",
}
"""vision_msgs 4.x's hashes as rosidl generated them (rosidl_generator_c's
detection3_d_array__description.c of a vision_msgs build: its own hash and its referenced types'
EXPECTED_HASH); no vision_msgs wheel ships its .json to read them from."""


@pytest.mark.parametrize("distro", ["jazzy", "kilted"])
def test_registered_vision_msgs_have_rosidls_type_hashes(distro: cdr.Distro) -> None:
    for ros_type, expected in VISION_MSGS_HASHES.items():
        assert cdr.type_hash(distro, ros_type) == expected, ros_type


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_detection_array_carries_each_track_typed(distro: cdr.Distro) -> None:
    markers = object_markers(tracked_objects(), "site", PlanarPose(10.0, 0.0, math.pi / 2))
    raw = cdr.detection_array_cdr(distro, markers)
    assert raw[:4] == b"\x00\x01\x00\x00"
    array = cdr.decode(distro, raw, cdr.DETECTION_3D_ARRAY)
    (detection,) = array.detections
    assert (array.header.frame_id, detection.header.frame_id, detection.id) == ("site", "site", "5")
    assert (array.header.stamp.sec, array.header.stamp.nanosec) == stamp_parts(STAMP_NS)
    center, size = detection.bbox.center, detection.bbox.size
    assert (center.position.x, center.position.y, center.position.z) == pytest.approx(
        (8.0, 1.0, 0.6)
    )
    yaw = 0.3 + math.pi / 2
    assert (center.orientation.z, center.orientation.w) == pytest.approx(
        (math.sin(yaw / 2), math.cos(yaw / 2))
    )
    assert (size.x, size.y, size.z) == pytest.approx((0.8, 0.4, 1.2))
    (result,) = detection.results
    assert (result.hypothesis.class_id, result.hypothesis.score) == ("moving", 1.0)
    assert result.pose.pose.position.x == center.position.x
    assert not np.asarray(result.pose.covariance).any()  # unknown, not "exact"
    none = object_markers(
        ObjectsHeader(version=1, stamp_ns=STAMP_NS, objects=[]), "map", PlanarPose()
    )
    raw_none = cdr.detection_array_cdr(distro, none)
    assert cdr.decode(distro, raw_none, cdr.DETECTION_3D_ARRAY).detections == []


CDR_ALIGNMENT_BYTES = {
    "bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
    "int32": 4, "uint32": 4, "float32": 4, "int64": 8, "uint64": 8, "float64": 8,
}  # fmt: skip
"""Size, and so alignment, of each primitive in ROS 2's CDR (XCDR1: 8-byte types align to 8)."""
ENCAPSULATION_BYTES = 4


def padding_offsets(store: Typestore, ros_type: str, message: Any) -> tuple[set[int], int]:
    """Offsets of CDR's alignment padding in a message's bytes (encapsulation header included),
    from walking its layout: each primitive starts at a multiple of its size counted from the end
    of the header; a string is a uint32 length, then its bytes and a NUL; a sequence a uint32
    length, then its items. Also the total size, to check the walk against the bytes."""
    padding: set[int] = set()
    position = 0

    def align(size: int) -> None:
        nonlocal position
        skip = -position % size
        padding.update(range(ENCAPSULATION_BYTES + position, ENCAPSULATION_BYTES + position + skip))
        position += skip

    def walk(kind: Nodetype, detail: Any, value: Any) -> None:
        nonlocal position
        if kind == Nodetype.NAME:
            for name, (field_kind, field_detail) in store.fielddefs[detail][1]:
                walk(field_kind, field_detail, getattr(value, name))
        elif kind == Nodetype.BASE and detail[0] == "string":
            align(4)
            position += 4 + len(value.encode()) + 1
        elif kind == Nodetype.BASE:
            align(CDR_ALIGNMENT_BYTES[detail[0]])
            position += CDR_ALIGNMENT_BYTES[detail[0]]
        else:
            (item_kind, item_detail), _count = detail
            if kind == Nodetype.SEQUENCE:
                align(4)
                position += 4
            for item in value:
                walk(item_kind, item_detail, item)

    walk(Nodetype.NAME, ros_type, message)
    return padding, ENCAPSULATION_BYTES + position


def test_cdr_equals_rclpys_serialize_message_outside_alignment_padding() -> None:
    """The same messages, built by the rclpy node's own builders (services/ros2/node.py) and
    serialised by rclpy's ``serialize_message``, and by rosbags for the native output: equal byte
    for byte but for CDR's alignment padding, and rosbags reads rclpy's bytes back into exactly
    its own.

    Why not strict equality: rmw_fastrtps serialises with Fast CDR into a freshly allocated buffer
    and skips alignment padding without writing it, so those bytes are whatever the allocation
    held (an OccupancyGrid's offsets 40-43, before the origin pose's first float64, came out 0x51
    in one run and otherwise in others); rosbags writes zeros there. Subscribers never read
    padding, so only these bytes may differ."""
    serialization = importlib.import_module("rclpy.serialization")
    nav, sensor = node.ros_messages("nav_msgs"), node.ros_messages("sensor_msgs")
    visualization = node.ros_messages("visualization_msgs")
    occupancy_map = a_map()
    grid = grid_message(occupancy_map, "map", PlanarPose(1.0, 2.0, 0.3), "raw")
    image = height_image(occupancy_map, "map")
    markers = object_markers(tracked_objects(drum=True), "map", PlanarPose(1.0, 2.0, 0.3))
    cases = [
        (
            cdr.OCCUPANCY_GRID,
            cdr.occupancy_grid_cdr("kilted", grid),
            node.occupancy_grid_msg(nav.OccupancyGrid, grid),
        ),
        (
            cdr.IMAGE,
            cdr.height_image_cdr("kilted", image),
            node.height_image_msg(sensor.Image, image),
        ),
        (
            cdr.MARKER_ARRAY,
            cdr.marker_array_cdr("kilted", markers),
            node.marker_array_msg(visualization.Marker, visualization.MarkerArray, markers),
        ),
    ]
    store = cdr.typestore("kilted")
    for ros_type, ours, message in cases:
        theirs = bytes(serialization.serialize_message(message))
        padding, size = padding_offsets(store, ros_type, store.deserialize_cdr(ours, ros_type))
        assert len(theirs) == len(ours) == size, ros_type
        assert all(ours[at] == 0 for at in padding)
        differing = {at for at in range(size) if ours[at] != theirs[at]}
        assert differing <= padding, (ros_type, sorted(differing - padding))
        again = store.serialize_cdr(store.deserialize_cdr(theirs, ros_type), ros_type)
        assert bytes(again) == ours, ros_type
    # The grid's padding is where the audit saw rclpy's bytes differ: before the origin pose.
    grid_padding, _ = padding_offsets(
        store, cdr.OCCUPANCY_GRID, store.deserialize_cdr(cases[0][1], cdr.OCCUPANCY_GRID)
    )
    assert grid_padding == {40, 41, 42, 43}
