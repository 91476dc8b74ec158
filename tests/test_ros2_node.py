"""``overgrid ros2`` as a real rclpy node beside a real fusion process: a real rclpy subscriber
started after the map exists gets /map (transient_local, remapped the ROS way) equal to map/latest
cell for cell, then a newer /map equal to the newer map/latest after each of several tile changes,
the height layer, and the objects as markers.

DDS isolation: rmw_fastrtps_cpp on a random domain id, discovery kept to this host, and topic names
of this run only, so concurrent runs never cross."""

from __future__ import annotations

import json
import queue
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt
import pytest

from common import keys
from common.client import latest
from common.codec import encode
from common.lattice import Window
from common.messages import OBJECTS_KIND
from common.occupancy_map import OccupancyMap
from services.ros2.grid_message import map_values
from tests.conftest import REPO, Bus, assert_one_line_exit_2, run_overgrid, wait_for
from tests.test_ros2_messages import tracked_objects
from tests.test_ros2_native import start_fusion_with_a_tile
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

FIRST, SECOND = Window(-4, 2, 30, 20), Window(0, 5, 6, 4)
TILE_CHANGES = 3
SUBSCRIBER_LIFETIME_S = 90
LINE_TIMEOUT_S = 20
SUBSCRIBER = """
import json, sys, threading, time
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import Image
from visualization_msgs.msg import Marker, MarkerArray

deadline, prefix = time.monotonic() + float(sys.argv[1]), sys.argv[2]
stop = threading.Event()  # the test closes our stdin when it has seen enough
threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
rclpy.init()
node = rclpy.create_node("overgrid_test_subscriber")
latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

def on_map(msg):
    o = msg.info.origin
    print(json.dumps({"map": {"frame_id": msg.header.frame_id, "width": msg.info.width,
                              "height": msg.info.height, "resolution": msg.info.resolution,
                              "origin": [o.position.x, o.position.y, o.orientation.z,
                                         o.orientation.w],
                              "data": list(msg.data)}}), flush=True)

def on_height(msg):
    print(json.dumps({"height": {"encoding": msg.encoding, "width": msg.width,
                                 "height": msg.height, "step": msg.step}}), flush=True)

def on_objects(msg):
    print(json.dumps({"cubes": [m.id for m in msg.markers if m.type == Marker.CUBE]}), flush=True)

node.create_subscription(OccupancyGrid, prefix + "/site/map", on_map, latched)
node.create_subscription(MarkerArray, prefix + "/map_objects", on_objects, latched)
node.create_subscription(Image, prefix + "/map_height", on_height, latched)
while time.monotonic() < deadline and not stop.is_set():
    rclpy.spin_once(node, timeout_sec=0.1)
node.destroy_node()
rclpy.shutdown()
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


class Lines:
    """The subscriber's JSON lines as they come (a reader thread), one queue per kind of line, so
    the test can wait for the next of one kind without losing the others."""

    def __init__(self, stream: IO[str], kinds: tuple[str, ...]) -> None:
        self._queues: dict[str, queue.Queue[Any]] = {kind: queue.Queue() for kind in kinds}
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            if line.strip():
                ((kind, value),) = json.loads(line).items()
                self._queues[kind].put(value)

    def next(self, kind: str, matches: Callable[[Any], bool], what: str) -> Any:
        """The next ``kind`` line that ``matches`` (earlier ones of that kind are dropped), or an
        assertion error after the timeout."""
        deadline = time.monotonic() + LINE_TIMEOUT_S
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                value = self._queues[kind].get(timeout=remaining)
            except queue.Empty:
                break
            if matches(value):
                return value
        raise AssertionError(f"the subscriber got no {what} in {LINE_TIMEOUT_S} s")


def cells(grid: dict[str, Any]) -> npt.NDArray[np.int8]:
    return np.array(grid["data"], np.int8).reshape(grid["height"], grid["width"])


def newer_map(bus: Bus, version: int, what: str) -> OccupancyMap:
    """map/latest once it is newer than ``version``."""
    deadline = time.monotonic() + LINE_TIMEOUT_S
    while time.monotonic() < deadline:
        current = latest(bus.session, timeout_s=5)
        if current.version > version:
            return current
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_rclpy_subscriber_gets_map_then_each_newer_map(
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
        # Settings as node parameters and a remapping, the ROS way; overgrid's (Zenoh) flags follow
        # the "--".
        *("--ros-args", "-p", "frame_id:=site", "-p", "world_in_map:=1,2,0"),
        *("-r", f"{prefix}/map:={prefix}/site/map", "--"),
        log_path=node_log,
    )
    wait_for(lambda: b"first map published" in node_log.read_bytes(), 60, "the node's first /map")
    # The names as remapped, as the robots' graph shows them.
    assert f"map_topic={prefix}/site/map" in node_log.read_text()
    # No wheel ships map_msgs, tf2_msgs or vision_msgs: the node says at start what it does not
    # publish.
    said = node_log.read_text()
    assert "map_msgs is not importable" in said and "/map_updates is not published" in said
    assert "tf2_msgs is not importable" in said and "/tf_static is not published" in said
    assert "vision_msgs is not importable" in said and "/map_detections is not published" in said
    subscriber = subprocess.Popen(
        [
            *("timeout", "-s", "INT", "-k", "5", str(SUBSCRIBER_LIFETIME_S)),
            *(sys.executable, "-c", SUBSCRIBER, str(SUBSCRIBER_LIFETIME_S - 10), prefix),
        ],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert subscriber.stdout is not None and subscriber.stdin is not None
    lines = Lines(subscriber.stdout, ("map", "height", "cubes"))
    try:
        # Started after the map exists, on the remapped name: the latched /map.
        first = lines.next("map", lambda _: True, "first /map")
        fused = latest(bus.session, timeout_s=10)
        rows, cols = fused.occupancy.shape
        assert (first["width"], first["height"]) == (cols, rows)
        assert first["frame_id"] == "site"
        assert first["resolution"] == pytest.approx(0.05)
        x0, y0 = fused.origin_m
        assert first["origin"] == pytest.approx([x0 + 1, y0 + 2, 0.0, 1.0])
        # map_server's values (the default mode), not the belief's 18..100.
        assert np.array_equal(cells(first), map_values(fused.occupancy, "trinary"))
        assert set(np.unique(cells(first)).tolist()) <= {-1, 0, 100}
        height = lines.next("height", lambda _: True, "height image")
        assert height == {"encoding": "32FC1", "width": cols, "height": rows, "step": cols * 4}

        # Tiles keep changing the map: after each change a newer /map equal to the newer
        # map/latest arrives.
        before = fused
        for change in range(1, TILE_CHANGES + 1):
            seq = time.monotonic_ns() // 1000
            tiles.put(tile_payload("p0", SECOND, 2.0 * (-1) ** change, seq=seq))
            now = newer_map(bus, before.version, f"tile change {change} fused")
            assert not np.array_equal(now.occupancy, before.occupancy)

            target = map_values(now.occupancy, "trinary")

            def is_now(grid: dict[str, Any], target: npt.NDArray[np.int8] = target) -> bool:
                return bool(np.array_equal(cells(grid), target))

            lines.next("map", is_now, f"/map equal to map/latest after tile change {change}")
            before = now

        # A map/objects put: a MarkerArray with its box.
        bus.session.put(keys.MAP_OBJECTS, encode(OBJECTS_KIND, tracked_objects(version=10**6)))
        assert lines.next("cubes", lambda ids: ids == [5], "cube of the tracked object") == [5]
        subscriber.stdin.close()
        subscriber.wait(20)
    finally:
        if subscriber.poll() is None:
            subscriber.kill()
    assert subscriber.returncode == 0, subscriber.stderr.read()[-2000:]  # type: ignore[union-attr]
    # It stops cleanly: no spinning thread left to abort the process at exit.
    node_process.send_signal(signal.SIGINT)
    assert node_process.wait(20) == 0, node_log.read_text()[-2000:]


@pytest.mark.parametrize(
    ("parameter", "named"),
    [("world_in_map:=1,2", "world_in_map"), ("frame_id:=123", "frame_id")],
)
def test_a_bad_node_parameter_is_one_line_naming_it(
    ros_env: dict[str, str], parameter: str, named: str
) -> None:
    """Settings given as node parameters are checked as the flags are: they ended in a
    pydantic or rclpy traceback."""
    done = run_overgrid("ros2", "--no-multicast-scouting", "--ros-args", "-p", parameter)
    assert_one_line_exit_2(done, f"ROS parameter {named}")


@pytest.mark.parametrize(
    ("environment", "args", "named"),
    [
        ({}, ("--ros-args", "--bogus"), "--ros-args --bogus"),
        ({}, ("--ros-args", "-r", "/map:=bad topic"), "--ros-args"),
        ({"ROS_DOMAIN_ID": "abc"}, (), "ROS_DOMAIN_ID"),
        ({"ROS_DOMAIN_ID": "300"}, (), "ROS_DOMAIN_ID"),
    ],
)
def test_a_bad_ros_argument_or_domain_is_one_line(
    ros_env: dict[str, str],
    monkeypatch: pytest.MonkeyPatch,
    environment: dict[str, str],
    args: tuple[str, ...],
    named: str,
) -> None:
    """rclpy's and rcl's refusals were tracebacks (exit 1); Fast DDS refused domain 300 only
    when it computed its ports."""
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    done = run_overgrid("ros2", "--no-multicast-scouting", *args)
    assert_one_line_exit_2(done, named)
