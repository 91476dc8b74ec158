"""``overgrid ros2`` as a real rclpy node beside a real fusion process: a real rclpy subscriber
started after the map exists gets /map (transient_local) equal to map/latest cell for cell, then a
newer /map after tiles change it, the height layer, and the objects as markers.

DDS isolation: rmw_fastrtps_cpp on a random domain id, discovery kept to this host, and topic names
of this run only, so concurrent runs never cross."""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common import keys
from common.client import latest
from common.codec import encode
from common.lattice import Window
from common.messages import OBJECTS_KIND
from tests.conftest import REPO, Bus, wait_for
from tests.test_ros2_messages import tracked_objects
from tests.test_ros2_native import start_fusion_with_a_tile
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

FIRST, SECOND = Window(-4, 2, 30, 20), Window(0, 5, 6, 4)
SUBSCRIBER_LIFETIME_S = 60
SUBSCRIBER = """
import json, sys, time
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import Image
from visualization_msgs.msg import Marker, MarkerArray

deadline, prefix = time.monotonic() + float(sys.argv[1]), sys.argv[2]
rclpy.init()
node = rclpy.create_node("overgrid_test_subscriber")
maps, heights, cubes = [], [], []
qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.TRANSIENT_LOCAL)

def on_map(msg):
    o = msg.info.origin
    maps.append({"frame_id": msg.header.frame_id, "width": msg.info.width,
                 "height": msg.info.height, "resolution": msg.info.resolution,
                 "origin": [o.position.x, o.position.y, o.orientation.z, o.orientation.w],
                 "data": list(msg.data)})
    print(json.dumps({"map": maps[-1]}), flush=True)

def on_height(msg):
    heights.append(msg)
    print(json.dumps({"height": {"encoding": msg.encoding, "width": msg.width,
                                 "height": msg.height, "step": msg.step}}), flush=True)

def on_objects(msg):
    cubes.extend(m.id for m in msg.markers if m.type == Marker.CUBE)
    print(json.dumps({"cubes": cubes}), flush=True)

node.create_subscription(OccupancyGrid, prefix + "/map", on_map, qos)
node.create_subscription(MarkerArray, prefix + "/map_objects", on_objects, 1)
node.create_subscription(Image, prefix + "/map_height", on_height, 1)
def done():  # a /map that differs from the first one, a height image, a cube
    return bool(heights and cubes) and any(m["data"] != maps[0]["data"] for m in maps[1:])

while time.monotonic() < deadline and not done():
    rclpy.spin_once(node, timeout_sec=0.1)
node.destroy_node()
rclpy.shutdown()
sys.exit(0 if done() else 1)
"""


@pytest.fixture
def ros_env(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    env = {
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_DOMAIN_ID": str(random.randint(1, 232)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    }
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    return env


def test_rclpy_subscriber_gets_map_then_newer_map(
    bus: Bus, tmp_path: Path, ros_env: dict[str, str]
) -> None:
    tiles = start_fusion_with_a_tile(bus, tmp_path, FIRST)
    node_log = tmp_path / "ros2.log"
    prefix = "/" + bus.namespace.replace("-", "_")  # topics of this run only, whatever the domain
    node_process = bus.start(
        "ros2",
        "--map-topic",
        prefix + "/map",
        "--height-topic",
        prefix + "/map_height",
        "--objects-topic",
        prefix + "/map_objects",
        "--map-interval-s",
        "0.2",
        "--height-interval-s",
        "0.2",
        # Settings as node parameters, the ROS way; overgrid's (Zenoh) flags follow the "--".
        *("--ros-args", "-p", "frame_id:=site", "-p", "world_in_map:=1,2,0", "--"),
        log_path=node_log,
    )
    wait_for(lambda: b"first map published" in node_log.read_bytes(), 60, "the node's first /map")
    # No wheel ships map_msgs or tf2_msgs: the node says at start what it does not publish.
    said = node_log.read_text()
    assert "map_msgs is not importable" in said and "/map_updates is not published" in said
    assert "tf2_msgs is not importable" in said and "/tf_static is not published" in said
    subscriber = subprocess.Popen(
        [
            *("timeout", "-s", "INT", "-k", "5", str(SUBSCRIBER_LIFETIME_S)),
            *(sys.executable, "-c", SUBSCRIBER, str(SUBSCRIBER_LIFETIME_S - 10), prefix),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = json.loads(subscriber.stdout.readline())["map"]  # type: ignore[union-attr]
        fused = latest(bus.session, timeout_s=10)
        rows, cols = fused.occupancy.shape
        assert (first["width"], first["height"]) == (cols, rows)
        assert first["frame_id"] == "site"
        assert first["resolution"] == pytest.approx(0.05)
        x0, y0 = fused.origin_m
        assert first["origin"] == pytest.approx([x0 + 1, y0 + 2, 0.0, 1.0])
        assert np.array_equal(np.array(first["data"], np.int8).reshape(rows, cols), fused.occupancy)

        # A tile changes the map: a newer /map follows, equal to the newer map/latest. A
        # map/objects put: a MarkerArray with its box.
        tiles.put(tile_payload("p0", SECOND, -2.0, seq=10**12))
        bus.session.put(keys.MAP_OBJECTS, encode(OBJECTS_KIND, tracked_objects(version=10**6)))
        output, errors = subscriber.communicate(timeout=SUBSCRIBER_LIFETIME_S)
    finally:
        if subscriber.poll() is None:
            subscriber.kill()
    assert subscriber.returncode == 0, errors[-2000:]
    lines = [json.loads(line) for line in output.splitlines() if line.strip()]
    newer = [line["map"] for line in lines if "map" in line][-1]
    now = latest(bus.session, timeout_s=10)
    assert np.array_equal(
        np.array(newer["data"], np.int8).reshape(now.occupancy.shape), now.occupancy
    )
    height = next(line["height"] for line in lines if "height" in line)
    assert height == {"encoding": "32FC1", "width": cols, "height": rows, "step": cols * 4}
    assert next(line["cubes"] for line in lines if line.get("cubes")) == [5]
    # It stops cleanly: no spinning thread left to abort the process at exit.
    node_process.send_signal(signal.SIGINT)
    assert node_process.wait(20) == 0, node_log.read_text()[-2000:]
