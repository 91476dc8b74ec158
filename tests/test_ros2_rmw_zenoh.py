"""rmw_zenoh's conventions (services/ros2/rmw_zenoh.py) against its source's rules and examples:
liveliness_utils.cpp (keys, tokens, QoS), attachment_helpers.cpp, the zenoh serialization format."""

from __future__ import annotations

import json
import os
import struct
import sys
from pathlib import Path

import pytest
import xxhash

from services.ros2 import cdr
from services.ros2.environment import ros_environment
from services.ros2.node import split_ros_args
from services.ros2.rmw_zenoh import (
    DEFAULT_QOS,
    NO_TYPE_HASH,
    Durability,
    History,
    NodeIdentity,
    Reliability,
    TopicQos,
    attachment,
    dds_type_name,
    gid_of,
    parse_attachment,
    qos_keyexpr,
    topic_keyexpr,
)
from services.ros2.settings import Ros2Settings

MAP_QOS = TopicQos(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1)
ZID = "4bf9c8b6f3cbb1d2a6cd0c2d1fa5e4e1"


def parse_qos(keyexpr: str) -> TopicQos:
    """rmw_zenoh's keyexpr_to_qos: six ':' parts, history/deadline/lifespan of two ',' fields,
    liveliness of three; an empty field is the default."""
    parts = keyexpr.split(":")
    assert len(parts) == 6
    history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:])
    assert (len(history), len(deadline), len(lifespan), len(liveliness)) == (2, 2, 2, 3)
    assert deadline == lifespan == ["", ""] and liveliness == ["", "", ""]
    return TopicQos(
        Reliability(int(parts[0])) if parts[0] else DEFAULT_QOS.reliability,
        Durability(int(parts[1])) if parts[1] else DEFAULT_QOS.durability,
        History(int(history[0])) if history[0] else DEFAULT_QOS.history,
        int(history[1]) if history[1] else DEFAULT_QOS.depth,
    )


@pytest.mark.parametrize(
    ("qos", "keyexpr"),
    [
        (DEFAULT_QOS, "::,:,:,:,,"),
        (MAP_QOS, ":1:,1:,:,:,,"),
        (
            TopicQos(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_ALL, 5),
            "2::2,5:,:,:,,",
        ),
    ],
)
def test_qos_keyexpr_leaves_defaults_empty_and_parses_back(qos: TopicQos, keyexpr: str) -> None:
    assert qos_keyexpr(qos) == keyexpr
    assert parse_qos(qos_keyexpr(qos)) == qos


def test_data_key_and_tokens_have_rmw_zenohs_parts() -> None:
    hash_ = cdr.type_hash("jazzy", cdr.OCCUPANCY_GRID)
    assert dds_type_name(cdr.OCCUPANCY_GRID) == "nav_msgs::msg::dds_::OccupancyGrid_"
    assert topic_keyexpr(0, "/map", cdr.OCCUPANCY_GRID, hash_) == (
        f"0/map/nav_msgs::msg::dds_::OccupancyGrid_/{hash_}"
    )
    assert topic_keyexpr(3, "/robot1/map/", cdr.OCCUPANCY_GRID, hash_).startswith("3/robot1/map/")
    node = NodeIdentity(0, ZID, 0, "overgrid_map")
    assert node.node_token() == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/overgrid_map"
    token = node.publisher_token(1, "/robot1/map", cdr.OCCUPANCY_GRID, hash_, MAP_QOS)
    parts = token.split("/")
    # AdminSpace … NodeName is 9 parts, then TopicName, TopicType, TopicTypeHash, TopicQoS.
    assert len(parts) == 13 and all(parts)
    assert parts[:9] == ["@ros2_lv", "0", ZID, "0", "1", "MP", "%", "%", "overgrid_map"]
    assert parts[9:12] == ["%robot1%map", "nav_msgs::msg::dds_::OccupancyGrid_", hash_]
    assert parse_qos(parts[12]) == MAP_QOS
    namespaced = NodeIdentity(0, ZID, 4, "n", namespace="/site/a")
    assert namespaced.node_token().endswith("/4/4/NN/%/%site%a/n")


def test_type_hashes_are_the_shipped_ones_and_humble_has_none() -> None:
    for package, name, ros_type in [
        ("nav_msgs", "OccupancyGrid", cdr.OCCUPANCY_GRID),
        ("sensor_msgs", "Image", cdr.IMAGE),
    ]:
        path = Path(sys.prefix) / "share" / package / "msg" / f"{name}.json"
        shipped = json.loads(path.read_text())["type_hashes"][0]["hash_string"]
        assert cdr.type_hash("kilted", ros_type) == shipped
    assert cdr.type_hash("humble", cdr.OCCUPANCY_GRID) == NO_TYPE_HASH
    assert topic_keyexpr(0, "/map", cdr.OCCUPANCY_GRID, NO_TYPE_HASH).endswith(
        "/TypeHashNotSupported"
    )


def test_gid_is_xxh3_128_of_the_token_low_half_first() -> None:
    token = NodeIdentity(0, ZID, 0, "overgrid_map").node_token()
    digest = xxhash.xxh3_128(token.encode())
    low, high = digest.intdigest() & (2**64 - 1), digest.intdigest() >> 64
    assert gid_of(token) == struct.pack("<QQ", low, high)


def test_attachment_is_zenoh_serialized_seq_stamp_gid() -> None:
    gid = bytes(range(16))
    raw = attachment(7, 1_700_000_000_000_000_001, gid)
    # Zenoh serialization format: fixed-size little-endian numbers, a sequence as LEB128
    # length then items (an array of 16 bytes too).
    assert raw == struct.pack("<qq", 7, 1_700_000_000_000_000_001) + b"\x10" + gid
    assert parse_attachment(raw) == (7, 1_700_000_000_000_000_001, gid)
    with pytest.raises(ValueError, match="16 bytes"):
        attachment(1, 1, b"short")


def test_settings_give_the_map_qos_and_pose() -> None:
    settings = Ros2Settings(world_in_map=["1", "-2", "0.5"])
    assert settings.map_qos == MAP_QOS
    assert (settings.pose.x_m, settings.pose.y_m, settings.pose.yaw_rad) == (1, -2, 0.5)
    with pytest.raises(ValueError, match="x,y,yaw"):
        Ros2Settings(world_in_map=["1", "2"])


def test_ros_environment_names_the_wheels_prefix(tmp_path: Path) -> None:
    (tmp_path / "share" / "ament_index").mkdir(parents=True)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    libs = tmp_path / "lib" / version / "site-packages" / "ros_rcl.libs"
    libs.mkdir(parents=True)
    changes = ros_environment({"LD_LIBRARY_PATH": "/opt/x"}, tmp_path)
    assert changes["AMENT_PREFIX_PATH"] == str(tmp_path)
    assert changes["LD_LIBRARY_PATH"].split(os.pathsep) == [
        str(tmp_path / "lib"),
        str(libs),
        "/opt/x",
    ]
    assert ros_environment({**changes}, tmp_path) == {}


def test_ros_arguments_run_from_ros_args_to_a_lone_double_dash() -> None:
    own, ros = split_ros_args(
        ["--frame-id", "a", "--ros-args", "-p", "x:=1", "--", "--mode", "peer"]
    )
    assert (own, ros) == (["--frame-id", "a", "--mode", "peer"], ["-p", "x:=1"])
    assert split_ros_args(["--ros-args", "-r", "/map:=/m"]) == ([], ["-r", "/map:=/m"])
    assert split_ros_args(["--frame-id", "a"]) == (["--frame-id", "a"], [])
