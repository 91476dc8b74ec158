"""``overgrid rmw-zenoh`` beside a real fusion process, checked against rmw_zenoh's conventions
(no rmw_zenoh_cpp exists here): keys, liveliness graph tokens, attachment, CDR that rosbags and
rclpy read back, the cached /map and /tf_static for a late joiner, /map_updates keeping its copy
equal, the objects as markers and as a vision_msgs/Detection3DArray, cached with the height layer
for late joiners too."""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zenoh
import zenoh.ext

from common import keys
from common.client import MapUnavailable, latest
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.messages import OBJECTS_KIND
from services.ros2 import cdr
from services.ros2.rmw_zenoh import gid_of, parse_attachment
from tests.conftest import REPO, Bus, wait_for
from tests.test_ros2_messages import TF_MESSAGE_HASH, a_map, tracked_objects
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

DOMAIN = 7
FIRST, SECOND = Window(0, 0, 40, 30), Window(10, 5, 6, 4)
MAP_KEY = f"{DOMAIN}/map/nav_msgs::msg::dds_::OccupancyGrid_/"
UPDATES_KEY = f"{DOMAIN}/map_updates/map_msgs::msg::dds_::OccupancyGridUpdate_/"


def shipped_type_hash(package: str, name: str) -> str:
    """The RIHS01 hash in the message package's own type description (ros-nav-msgs wheel)."""
    path = Path(sys.prefix) / "share" / package / "msg" / f"{name}.json"
    description = json.loads(path.read_text())
    return str(description["type_hashes"][0]["hash_string"])


def late_joiner(
    session: zenoh.Session, key: str
) -> tuple[zenoh.ext.AdvancedSubscriber[None], queue.Queue[zenoh.Sample]]:
    """Subscribed as rmw_zenoh subscribes a reliable transient_local reader
    (rmw_subscription_data.cpp, SubscriptionData::init): an advanced subscriber on the exact key
    that detects late publishers, queries their cache and recovers by heartbeat."""
    samples: queue.Queue[zenoh.Sample] = queue.Queue()
    subscriber = zenoh.ext.declare_advanced_subscriber(
        session,
        key,
        samples.put,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
        subscriber_detection=True,
    )
    return subscriber, samples


def graph_tokens(session: zenoh.Session) -> list[str]:
    return [
        str(reply.ok.key_expr)
        for reply in session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2)
        if reply.ok is not None
    ]


def test_native_output_follows_rmw_zenoh(bus: Bus, tmp_path: Path) -> None:
    map_hash = shipped_type_hash("nav_msgs", "OccupancyGrid")
    assert cdr.type_hash("jazzy", cdr.OCCUPANCY_GRID) == map_hash
    tiles = start_fusion_with_a_tile(bus, tmp_path, FIRST)
    log = tmp_path / "rmw-zenoh.log"
    native = bus.start(
        "rmw-zenoh",
        "--domain-id",
        str(DOMAIN),
        "--world-in-map",
        "1.5,-2,0",
        "--map-interval-s",
        "600",  # one /map only, at start: the late joiner below can get it from the cache alone
        "--height-interval-s",
        "0.2",
        # Best effort and transient_local: a cache without miss detection, which needs the
        # session's timestamping (the process stopped at start without it).
        "--height-reliability",
        "best_effort",
        # The belief as is (the default is map_server's trinary values, tested with the node).
        "--map-mode",
        "raw",
        log_path=log,
    )
    wait_for(lambda: b"first map published" in log.read_bytes(), 30, "the first /map")
    tokens = graph_tokens(bus.session)
    zid_chunks = {token.split("/")[2] for token in tokens}
    assert len(zid_chunks) == 1
    zid = zid_chunks.pop()
    assert f"@ros2_lv/{DOMAIN}/{zid}/0/0/NN/%/%/overgrid_map" in tokens
    map_token = (
        f"@ros2_lv/{DOMAIN}/{zid}/0/1/MP/%/%/overgrid_map/%map/"
        f"nav_msgs::msg::dds_::OccupancyGrid_/{map_hash}/:1:,1:,:,:,,"
    )
    assert map_token in tokens
    updates_hash = cdr.type_hash("jazzy", cdr.OCCUPANCY_GRID_UPDATE)
    assert (
        f"@ros2_lv/{DOMAIN}/{zid}/0/2/MP/%/%/overgrid_map/%map_updates/"
        f"map_msgs::msg::dds_::OccupancyGridUpdate_/{updates_hash}/::,10:,:,:,,"
    ) in tokens

    tf_hash = cdr.type_hash("jazzy", cdr.TF_MESSAGE)
    assert tf_hash == TF_MESSAGE_HASH
    tf_token = (
        f"@ros2_lv/{DOMAIN}/{zid}/0/5/MP/%/%/overgrid_map/%tf_static/"
        f"tf2_msgs::msg::dds_::TFMessage_/{tf_hash}/:1:,1:,:,:,,"
    )
    assert tf_token in tokens  # as tf2_ros's static broadcaster: transient_local, depth 1
    image_hash = cdr.type_hash("jazzy", cdr.IMAGE)
    marker_hash = cdr.type_hash("jazzy", cdr.MARKER_ARRAY)
    detections_hash = cdr.type_hash("jazzy", cdr.DETECTION_3D_ARRAY)
    height = f"3/MP/%/%/overgrid_map/%map_height/sensor_msgs::msg::dds_::Image_/{image_hash}"
    assert f"@ros2_lv/{DOMAIN}/{zid}/0/{height}/2:1:,1:,:,:,," in tokens  # best effort
    latched = [  # transient_local, depth 1, like /map: a late joiner gets the last one
        f"4/MP/%/%/overgrid_map/%map_objects/visualization_msgs::msg::dds_::MarkerArray_/"
        f"{marker_hash}",
        f"6/MP/%/%/overgrid_map/%map_detections/vision_msgs::msg::dds_::Detection3DArray_/"
        f"{detections_hash}",
    ]
    for endpoint in latched:
        assert f"@ros2_lv/{DOMAIN}/{zid}/0/{endpoint}/:1:,1:,:,:,," in tokens

    # A late joiner, subscribed as rmw_zenoh subscribes a reliable transient_local reader
    # (rmw_subscription_data.cpp, SubscriptionData::init): an advanced subscriber on the exact key
    # that detects late publishers, queries their cache and recovers by heartbeat.
    maps: queue.Queue[zenoh.Sample] = queue.Queue()
    late = zenoh.ext.declare_advanced_subscriber(
        bus.session,
        MAP_KEY + map_hash,
        maps.put,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
        subscriber_detection=True,
    )
    updates: queue.Queue[zenoh.Sample] = queue.Queue()
    updates_subscriber = bus.session.declare_subscriber(UPDATES_KEY + updates_hash, updates.put)
    heights: queue.Queue[zenoh.Sample] = queue.Queue()
    heights_subscriber = bus.session.declare_subscriber(
        f"{DOMAIN}/map_height/sensor_msgs::msg::dds_::Image_/{image_hash}", heights.put
    )
    transforms: queue.Queue[zenoh.Sample] = queue.Queue()
    late_tf = zenoh.ext.declare_advanced_subscriber(
        bus.session,
        f"{DOMAIN}/tf_static/tf2_msgs::msg::dds_::TFMessage_/{tf_hash}",
        transforms.put,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
        subscriber_detection=True,
    )
    tf_sample = transforms.get(timeout=10)
    assert tf_sample.attachment is not None
    assert parse_attachment(bytes(tf_sample.attachment.to_bytes()))[2] == gid_of(tf_token)
    (stamped,) = cdr.decode("jazzy", bytes(tf_sample.payload.to_bytes()), cdr.TF_MESSAGE).transforms
    assert (stamped.header.frame_id, stamped.child_frame_id) == ("map", "overgrid_world")
    moved = stamped.transform.translation
    assert (moved.x, moved.y, moved.z) == (1.5, -2.0, 0.0)
    late_tf.undeclare()  # type: ignore[no-untyped-call]

    sample = maps.get(timeout=10)
    assert str(sample.key_expr) == MAP_KEY + map_hash
    assert sample.attachment is not None
    sequence_number, stamp_ns, gid = parse_attachment(bytes(sample.attachment.to_bytes()))
    assert sequence_number >= 1
    assert abs(stamp_ns - time.time_ns()) < 30 * 10**9
    assert gid == gid_of(map_token)
    raw = bytes(sample.payload.to_bytes())
    assert raw[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    grid = cdr.decode("jazzy", raw, cdr.OCCUPANCY_GRID)
    fused = latest(bus.session, timeout_s=10)
    assert grid.header.frame_id == "map"
    assert (grid.info.width, grid.info.height) == (
        fused.occupancy.shape[1],
        fused.occupancy.shape[0],
    )
    assert grid.info.resolution == pytest.approx(0.05)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == pytest.approx((1.5, -2.0))
    assert _rclpy_reads_and_writes(tmp_path, raw, cdr.OCCUPANCY_GRID)

    # Copy = the late joiner's /map; every native update applied to it keeps it equal.
    copy = np.asarray(grid.data, np.int8).reshape(grid.info.height, grid.info.width).copy()
    for seq in range(3):
        tiles.put(tile_payload("p0", SECOND, 2.0 * (-1) ** seq, seq=100 + seq))
        time.sleep(0.3)
    target = latest(bus.session, timeout_s=10).occupancy

    def copy_is_current() -> bool:
        while not updates.empty():
            update = cdr.decode(
                "jazzy", bytes(updates.get().payload.to_bytes()), cdr.OCCUPANCY_GRID_UPDATE
            )
            window = np.asarray(update.data, np.int8).reshape(update.height, update.width)
            copy[update.y : update.y + update.height, update.x : update.x + update.width] = window
        return bool(np.array_equal(copy, target))

    wait_for(copy_is_current, 10, "the copy kept by /map_updates to equal map/latest")
    late.undeclare()  # type: ignore[no-untyped-call]
    updates_subscriber.undeclare()  # type: ignore[no-untyped-call]

    # The height layer follows as a 32FC1 image on /map's cells, which rclpy reads as well.
    raw_image = bytes(heights.get(timeout=10).payload.to_bytes())
    image = cdr.decode("jazzy", raw_image, cdr.IMAGE)
    assert (image.encoding, image.width, image.height) == (
        "32FC1",
        grid.info.width,
        grid.info.height,
    )
    metres = np.frombuffer(bytes(image.data), "<f4").reshape(image.height, image.width)
    assert metres[0, 0] == pytest.approx(0.7)  # the first tile's top, at the origin cell
    assert _rclpy_reads_and_writes(tmp_path, raw_image, cdr.IMAGE)
    heights_subscriber.undeclare()  # type: ignore[no-untyped-call]

    # A map/objects put becomes a MarkerArray: a DELETEALL, then a CUBE per tracked object.
    assert marker_hash == shipped_type_hash("visualization_msgs", "MarkerArray")
    arrays: queue.Queue[zenoh.Sample] = queue.Queue()
    markers_subscriber = bus.session.declare_subscriber(
        f"{DOMAIN}/map_objects/visualization_msgs::msg::dds_::MarkerArray_/{marker_hash}",
        arrays.put,
    )
    bus.session.put(keys.MAP_OBJECTS, encode(OBJECTS_KIND, tracked_objects(version=10**6)))

    def cubes() -> list[int]:
        raw_array = bytes(arrays.get(timeout=10).payload.to_bytes())
        received = cdr.decode("jazzy", raw_array, cdr.MARKER_ARRAY).markers
        if any(marker.id == 5 for marker in received):
            assert _rclpy_reads_and_writes(tmp_path, raw_array, cdr.MARKER_ARRAY)
        return [marker.id for marker in received if marker.type == cdr.MARKER_CUBE]

    wait_for(lambda: cubes() == [5], 10, "the tracked object as a cube")
    markers_subscriber.undeclare()  # type: ignore[no-untyped-call]

    # Late joiners get the last objects, markers and typed, and the last height layer from the
    # publishers' caches: nothing is published while they subscribe (the objects and the map do
    # not change any more).
    objects_key = f"{DOMAIN}/map_objects/visualization_msgs::msg::dds_::MarkerArray_/{marker_hash}"
    detections_key = (
        f"{DOMAIN}/map_detections/vision_msgs::msg::dds_::Detection3DArray_/{detections_hash}"
    )
    height_key = f"{DOMAIN}/map_height/sensor_msgs::msg::dds_::Image_/{image_hash}"
    joiners = {
        key: late_joiner(bus.session, key) for key in (objects_key, detections_key, height_key)
    }
    raw_markers = bytes(joiners[objects_key][1].get(timeout=10).payload.to_bytes())
    late_markers = cdr.decode("jazzy", raw_markers, cdr.MARKER_ARRAY).markers
    assert [m.id for m in late_markers if m.type == cdr.MARKER_CUBE] == [5]
    raw_detections = bytes(joiners[detections_key][1].get(timeout=10).payload.to_bytes())
    (detection,) = cdr.decode("jazzy", raw_detections, cdr.DETECTION_3D_ARRAY).detections
    assert detection.id == "5" and detection.results[0].hypothesis.class_id == "moving"
    assert (detection.bbox.size.x, detection.bbox.size.y) == pytest.approx((0.8, 0.4))
    assert (detection.bbox.center.position.x, detection.bbox.center.position.y) == pytest.approx(
        (1.0 + 1.5, 2.0 - 2.0)  # the object's centre, moved by --world-in-map
    )
    raw_late_image = bytes(joiners[height_key][1].get(timeout=10).payload.to_bytes())
    assert cdr.decode("jazzy", raw_late_image, cdr.IMAGE).width == grid.info.width
    for subscriber, _ in joiners.values():
        subscriber.undeclare()  # type: ignore[no-untyped-call]

    # Stopped, it leaves the robots' graph: its tokens go with it.
    native.send_signal(signal.SIGINT)
    assert native.wait(10) == 0
    wait_for(lambda: not graph_tokens(bus.session), 10, "the graph tokens to be gone")


def start_fusion_with_a_tile(bus: Bus, tmp_path: Path, window: Window) -> zenoh.Publisher:
    """A real fusion process whose map holds one tile over ``window`` (occupied, 0.7 m tall);
    nothing but the tiles a test puts changes it afterwards (no decay). The tile publisher."""
    bus.start(
        "fusion",
        "--state-dir",
        str(tmp_path / "state"),
        "--publish-interval-s",
        "0.05",
        "--decay-after-s",
        "600",
    )
    tiles = bus.session.declare_publisher(keys.tile("p0"), encoding=WIRE_ENCODING)

    def fused() -> bool:  # fusion may not be subscribed yet: put until a tile lands
        tiles.put(tile_payload("p0", window, 1.0, seq=time.monotonic_ns() // 1000, height_m=0.7))
        try:
            return latest(bus.session, timeout_s=1).version >= 1
        except MapUnavailable:
            return False

    wait_for(fused, 30, "fusion to fuse a first tile")
    return tiles


def _rclpy_reads_and_writes(tmp_path: Path, raw: bytes, ros_type: str) -> bool:
    """rclpy (its own C typesupport) reads the bytes and writes them back; rosbags reads that and
    writes exactly ``raw`` again. (Not rclpy's bytes themselves: Fast CDR leaves alignment padding
    as it finds it in memory, so only the values and the layout can be equal.)"""
    package, _, name = ros_type.split("/")
    path = tmp_path / f"{name}.cdr"
    path.write_bytes(raw)
    code = (
        "import sys; from pathlib import Path;"
        "from rclpy.serialization import deserialize_message, serialize_message;"
        f"from {package}.msg import {name} as Message;"
        "path = Path(sys.argv[1]);"
        "path.write_bytes(serialize_message(deserialize_message(path.read_bytes(), Message)))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, str(path)], cwd=REPO, capture_output=True, timeout=60
    )
    if result.returncode != 0:
        return False
    store = cdr.typestore("jazzy")
    again = store.serialize_cdr(store.deserialize_cdr(path.read_bytes(), ros_type), ros_type)
    return bytes(again) == raw


def test_no_empty_map_is_latched_and_a_silent_fusion_is_said(bus: Bus, tmp_path: Path) -> None:
    """A fusion with no tile yet serves a 0 × 0 map: latched as /map, stamped 1970, it was all a
    late joiner got. And a fusion gone left the topics latched with nothing said."""
    fusion = bus.start("fusion", "--state-dir", str(tmp_path / "state"))
    log = tmp_path / "rmw-zenoh.log"
    bus.start("rmw-zenoh", "--domain-id", str(DOMAIN), log_path=log)
    wait_for(lambda: b"msg=started" in log.read_bytes(), 30, "rmw-zenoh to start")
    wait_for(lambda: b"the map has no cell yet" in log.read_bytes(), 30, "the empty map, followed")
    assert b"first map published" not in log.read_bytes()
    tiles = bus.session.declare_publisher(keys.tile("p0"), encoding=WIRE_ENCODING)

    def tile_until(said: bytes) -> Callable[[], bool]:
        """A tile put at each poll, until the relay's log says ``said``."""

        def poll() -> bool:
            tiles.put(tile_payload("p0", FIRST, 1.0, seq=time.monotonic_ns() // 1000))
            return said in log.read_bytes()

        return poll

    wait_for(tile_until(b"first map published"), 30, "the first /map, once the map has cells")
    fusion.send_signal(signal.SIGTERM)
    fusion.wait(10)
    wait_for(lambda: b"fusion does not answer" in log.read_bytes(), 20, "the silence, said")
    assert b"svc=ros2" not in log.read_bytes()  # its own service's name on every line
    # Back, and gone again: each said (after the first outage, the relay said nothing of the
    # next ones, and "answers again" at random).
    fusion = bus.start("fusion", "--state-dir", str(tmp_path / "state"))
    wait_for(tile_until(b"fusion answers again"), 30, "fusion back, said")
    fusion.send_signal(signal.SIGTERM)
    fusion.wait(10)
    wait_for(
        lambda: log.read_bytes().count(b"fusion does not answer") == 2, 20, "the second silence"
    )


def _cube_ids(arrays: queue.Queue[zenoh.Sample]) -> list[int]:
    """The CUBE ids of every MarkerArray received so far."""
    ids = []
    while not arrays.empty():
        raw = bytes(arrays.get().payload.to_bytes())
        received = cdr.decode("jazzy", raw, cdr.MARKER_ARRAY).markers
        ids += [marker.id for marker in received if marker.type == cdr.MARKER_CUBE]
    return ids


def test_objects_ros_cannot_carry_end_nothing(bus: Bus, tmp_path: Path) -> None:
    """map/objects puts valid by their model but past ROS's types: a stamp past 2038 and a track
    id past int32 each ended the process (a struct.error in the CDR), and the robots lost /map.
    The first is skipped, counted and said; the second's box goes out under its id folded into
    the Marker's int32; the map goes on."""
    tiles = start_fusion_with_a_tile(bus, tmp_path, FIRST)
    log = tmp_path / "rmw-zenoh.log"
    native = bus.start("rmw-zenoh", "--domain-id", str(DOMAIN), log_path=log)
    wait_for(lambda: b"first map published" in log.read_bytes(), 30, "the first /map")
    arrays: queue.Queue[zenoh.Sample] = queue.Queue()
    markers = bus.session.declare_subscriber(f"{DOMAIN}/map_objects/**", arrays.put)
    updates: queue.Queue[zenoh.Sample] = queue.Queue()
    updates_subscriber = bus.session.declare_subscriber(f"{DOMAIN}/map_updates/**", updates.put)
    tracked = tracked_objects(version=10**6)
    late = tracked.model_copy(update={"stamp_ns": 2**64 - 1})
    bus.session.put(keys.MAP_OBJECTS, encode(OBJECTS_KIND, late))
    wait_for(lambda: b"objects_unpublishable" in log.read_bytes(), 10, "the stamp refused, said")
    far = tracked.objects[0].model_copy(update={"id": 2**40})
    far_list = tracked.model_copy(update={"version": 10**6 + 1, "objects": [far]})
    seen: list[int] = []

    def folded_box() -> bool:
        bus.session.put(keys.MAP_OBJECTS, encode(OBJECTS_KIND, far_list))
        seen.extend(_cube_ids(arrays))
        return 2**40 % 2**31 in seen

    wait_for(folded_box, 10, "the far id's box under its folded id")
    tiles.put(tile_payload("p0", SECOND, -2.0, seq=time.monotonic_ns() // 1000))
    assert updates.get(timeout=10) is not None  # still relaying the map
    assert native.poll() is None
    text = log.read_text()
    assert "Traceback" not in text and text.count("outside ROS time") == 1, text
    markers.undeclare()  # type: ignore[no-untyped-call]
    updates_subscriber.undeclare()  # type: ignore[no-untyped-call]


def test_a_map_latest_that_does_not_decode_is_waited_out(bus: Bus, tmp_path: Path) -> None:
    """A map/latest of another wire version (a forged or newer fusion) ended the process at
    start with a CodecError traceback; it is a fusion not there yet: said, waited out, and
    the map followed once one decodes."""
    served = [b"\x81\xa1v\x02"]
    queryable = bus.session.declare_queryable(
        keys.MAP_LATEST, lambda query: query.reply(keys.MAP_LATEST, served[-1])
    )
    log = tmp_path / "rmw-zenoh.log"
    native = bus.start("rmw-zenoh", "--domain-id", str(DOMAIN), log_path=log)
    wait_for(lambda: b"wire version 2" in log.read_bytes(), 30, "the answer refused, said")
    assert native.poll() is None
    served.append(a_map().to_msgpack())
    wait_for(lambda: b"first map published" in log.read_bytes(), 30, "the map, once it decodes")
    assert b"Traceback" not in log.read_bytes()
    queryable.undeclare()  # type: ignore[no-untyped-call]
