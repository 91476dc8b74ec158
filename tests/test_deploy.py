"""The shipped deploy files stay in step with the code: unit commands parse, configs load, and
the router's access control lets the native ROS 2 output publish the map and nothing more."""

from __future__ import annotations

import json
import queue
import shlex
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import zenoh
import zenoh.ext

from common.client import latest
from common.lattice import Window
from common.settings import ZenohSettings, parse_settings
from services.camera_sim.settings import CameraSimSettings
from services.depth.settings import DepthSettings
from services.fusion.settings import FusionSettings
from services.ros2 import cdr
from services.ros2.settings import RmwZenohSettings
from services.router import RouterSettings
from services.viewer.address import LOOPBACK_HOSTS
from services.viewer.server import ViewSettings
from tests.conftest import (
    PROCESS_LIFETIME_S,
    REPO,
    assert_one_line_exit_2,
    free_port,
    run_overgrid,
    wait_for,
)
from tests.reliability.test_security import PASSWORDS, _client_config, certs  # noqa: F401
from tests.test_ros2_native import late_joiner
from tests.tiles import put_until_fused, tile_payload

SETTINGS: dict[str, type[ZenohSettings]] = {
    "router": RouterSettings,
    "fusion": FusionSettings,
    "depth": DepthSettings,
    "camera-sim": CameraSimSettings,
    "rmw-zenoh": RmwZenohSettings,
    "view": ViewSettings,
}


def _unit_settings(unit: Path, tmp_path: Path) -> ZenohSettings:
    exec_start = next(
        line.split("=", 1)[1]
        for line in unit.read_text().splitlines()
        if line.startswith("ExecStart=")
    )
    words = shlex.split(exec_start.replace("%i", "p0").replace("${STATE_DIRECTORY}", str(tmp_path)))
    assert words[0].endswith("/overgrid")
    command, args = words[1], words[2:]
    return parse_settings(SETTINGS[command], args, command, "")


@pytest.mark.parametrize("unit", sorted((REPO / "deploy" / "systemd").glob("*.service")))
def test_systemd_units_run_commands_that_parse(unit: Path, tmp_path: Path) -> None:
    settings = _unit_settings(unit, tmp_path)
    assert settings.config is not None and settings.config.name.endswith(".json5")


def test_the_viewer_unit_reads_as_the_robot_user_and_serves_loopback(tmp_path: Path) -> None:
    settings = _unit_settings(REPO / "deploy" / "systemd" / "overgrid-view.service", tmp_path)
    assert isinstance(settings, ViewSettings)
    assert settings.config is not None and settings.config.name == "robot.json5"
    assert settings.http_host in LOOPBACK_HOSTS and settings.token is None  # overgrid.env opens it
    example = (REPO / "deploy" / "zenoh" / "credentials.txt.example").read_text()
    assert any(line.startswith("robot:") for line in example.splitlines())


@pytest.mark.parametrize("name", ["router.json5", "client.json5"])
def test_zenoh_configs_load(name: str) -> None:
    zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / name))


@pytest.mark.parametrize("name", ["router.json5", "client.json5"])
def test_a_file_a_shipped_config_names_and_the_box_lacks_is_one_line(name: str) -> None:
    """The shipped configs name /etc/overgrid/… files this machine has not: Zenoh's own error
    named no file (or, for a client's certificate, blamed the network)."""
    command = "router" if name == "router.json5" else "health"
    done = run_overgrid(command, "--config", str(REPO / "deploy" / "zenoh" / name))
    assert_one_line_exit_2(done, "--config", "/etc/overgrid/", "no such file")


DOMAIN = 7
USERS = {**PASSWORDS, "ros2": "pw-ros2"}


def _data_key(topic: str, ros_type: str) -> str:
    package, _, name = ros_type.split("/")
    return f"{DOMAIN}/{topic}/{package}::msg::dds_::{name}_/{cdr.type_hash('jazzy', ros_type)}"


@pytest.mark.process
def test_the_router_lets_the_ros2_user_publish_the_map_and_no_more(
    certs: Path,  # noqa: F811 (the fixture imported above)
    tmp_path: Path,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
    config = zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / "router.json5"))
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials)))
    router = zenoh.open(config)

    def session(user: str) -> zenoh.Session:
        path = _client_config(tmp_path / f"{user}.json5", endpoint, certs, user, USERS[user])
        return zenoh.open(zenoh.Config.from_file(str(path)))

    def start(user: str, *args: str) -> subprocess.Popen[bytes]:
        path = _client_config(tmp_path / f"{user}.json5", endpoint, certs, user, USERS[user])
        command = ["timeout", "-s", "INT", "-k", "5", str(PROCESS_LIFETIME_S), sys.executable]
        return subprocess.Popen(
            [*command, "-m", "services.cli", *args, "--config", str(path)],
            cwd=REPO,
            stdout=open(tmp_path / f"{args[0]}.log", "wb"),
            stderr=subprocess.STDOUT,
        )

    processes = [start("fusion", "fusion", "--state-dir", str(tmp_path / "state"))]
    robot, rogue_robot, depth = session("robot"), session("robot"), session("depth-p0")
    try:
        put_until_fused(depth, robot)  # through the router
        processes.append(
            start("ros2", "rmw-zenoh", "--domain-id", str(DOMAIN), "--map-interval-s", "600")
        )
        log = tmp_path / "rmw-zenoh.log"
        wait_for(lambda: b"first map published" in log.read_bytes(), 30, "the first /map")

        # A robot sees the node in the ROS graph and, joining late, gets /map and /tf_static
        # from the publishers' caches.
        def graph() -> list[str]:
            replies = robot.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2)
            return [str(r.ok.key_expr) for r in replies if r.ok is not None]

        wait_for(lambda: len(graph()) == 7, 10, "the node and its six publishers in the graph")
        assert sum("/NN/%/%/overgrid_map" in token for token in graph()) == 1
        maps = late_joiner(robot, _data_key("map", cdr.OCCUPANCY_GRID))
        transforms = late_joiner(robot, _data_key("tf_static", cdr.TF_MESSAGE))
        detections = late_joiner(robot, _data_key("map_detections", cdr.DETECTION_3D_ARRAY))
        grid = cdr.decode(
            "jazzy", bytes(maps[1].get(timeout=10).payload.to_bytes()), cdr.OCCUPANCY_GRID
        )
        assert grid.info.width * grid.info.height == latest(robot).occupancy.size > 0
        raw_tf = bytes(transforms[1].get(timeout=10).payload.to_bytes())
        assert cdr.decode("jazzy", raw_tf, cdr.TF_MESSAGE).transforms[0].child_frame_id == (
            "overgrid_world"
        )
        # The objects as fusion serves them at start (none tracked): the typed topic passes too.
        raw_detections = bytes(detections[1].get(timeout=10).payload.to_bytes())
        assert cdr.decode("jazzy", raw_detections, cdr.DETECTION_3D_ARRAY).detections == []

        # The viewer behind the router connects as a robot and shows the map.
        port = free_port()
        processes.append(start("robot", "view", "--http-port", str(port)))

        def viewer_has_the_map() -> bool:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/download/map.png") as got:
                    return bool(got.status == 200 and got.read(8) == b"\x89PNG\r\n\x1a\n")
            except OSError:  # not serving yet, or 503 until its feed has the map
                return False

        wait_for(viewer_has_the_map, 30, "the viewer, as the robot user, to have the map")

        # Nothing more: the ros2 user cannot command robots, pose as another node or answer
        # map/latest; a robot cannot put a /map of its own or pose as overgrid's node.
        seen: queue.Queue[str] = queue.Queue()
        watcher = robot.declare_subscriber(f"{DOMAIN}/**", lambda s: seen.put(str(s.key_expr)))
        rogue_ros2 = session("ros2")
        cmd_vel = _data_key("cmd_vel", "geometry_msgs/msg/Twist")
        forged_map = _data_key("map", cdr.OCCUPANCY_GRID)
        rogue_ros2.put(cmd_vel, b"\x00\x01\x00\x00")
        rogue_robot.put(forged_map, b"forged")
        intruders = [
            rogue_ros2.liveliness().declare_token(f"@ros2_lv/{DOMAIN}/ff/0/0/NN/%/%/intruder"),
            rogue_robot.liveliness().declare_token(f"@ros2_lv/{DOMAIN}/ff/0/0/NN/%/%/overgrid_map"),
        ]
        forger = rogue_ros2.declare_queryable(
            "map/latest", lambda q: q.reply("map/latest", b"forged")
        )
        # The watcher does see what is allowed: a tile changes the map, /map_updates follows.
        updates_key = _data_key("map_updates", cdr.OCCUPANCY_GRID_UPDATE)
        received: list[str] = []

        def update_seen() -> bool:
            depth.put("depth/p0/tile", tile_payload("p0", Window(2, 2, 4, 4), -2.0))
            time.sleep(0.2)
            while not seen.empty():
                received.append(seen.get())
            return updates_key in received

        wait_for(update_seen, 10, "a /map_updates sample at the robot")
        assert cmd_vel not in received and forged_map not in received
        assert len(graph()) == 7 and not any("/ff/" in token for token in graph())
        replies = [r.ok.payload.to_bytes() for r in robot.get("map/latest", timeout=2) if r.ok]
        assert replies and b"forged" not in replies
        for token in intruders:
            token.undeclare()  # type: ignore[no-untyped-call]
        forger.undeclare()  # type: ignore[no-untyped-call]
        watcher.undeclare()  # type: ignore[no-untyped-call]
        for subscriber, _ in (maps, transforms, detections):
            subscriber.undeclare()  # type: ignore[no-untyped-call]
        rogue_ros2.close()  # type: ignore[no-untyped-call]
    finally:
        for process in processes:
            process.terminate()
            process.wait(10)
        for each in (robot, rogue_robot, depth):
            each.close()  # type: ignore[no-untyped-call]
        router.close()  # type: ignore[no-untyped-call]


def test_make_certs_takes_an_ipv6_router_address_and_names_a_bad_name(tmp_path: Path) -> None:
    script = str(REPO / "deploy" / "make-certs.sh")
    made = subprocess.run(["bash", script, str(tmp_path / "v6"), "::1", "box"], capture_output=True)
    assert made.returncode == 0, made.stderr
    names = subprocess.run(
        [
            "openssl",
            "x509",
            "-in",
            str(tmp_path / "v6" / "::1.pem"),
            "-noout",
            "-ext",
            "subjectAltName",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "IP Address:0:0:0:0:0:0:0:1" in names.stdout  # it was DNS:::1, refused by every client
    bad = subprocess.run(
        ["bash", script, str(tmp_path / "bad"), "localhost", "bad,name"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "'bad,name'" in bad.stderr
    assert not (tmp_path / "bad").exists()  # nothing half made
