"""rmw_zenoh's conventions (services/ros2/rmw_zenoh.py) against its source's rules and examples:
docs/design.md's literal keys and tokens, liveliness_utils.cpp (keys, tokens, QoS),
attachment_helpers.cpp, the zenoh serialization format; the native sink's keys for a domain and a
distro."""

from __future__ import annotations

import json
import os
import struct
import sys
from pathlib import Path

import pytest
import xxhash

from common.zenoh_session import open_session
from services.ros2 import cdr
from services.ros2.environment import ros_environment
from services.ros2.native import NativeSink
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
from services.ros2.settings import RmwZenohSettings, Ros2Settings
from tests.conftest import assert_one_line_exit_2, run_overgrid

MAP_QOS = TopicQos(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1)
ZID = "4bf9c8b6f3cbb1d2a6cd0c2d1fa5e4e1"

# Verbatim from ros2/rmw_zenoh, docs/design.md (commit 99a6a2bd10b949052f4f12c5854825dc005e95a5):
# "Topic and Service name mapping to Zenoh key expressions" and "Graph Cache", the examples with
# demo_nodes_cpp's talker and listener and example_interfaces' add_two_ints.
DESIGN_STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DESIGN_ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
DESIGN_CHATTER_KEY = (
    "0/chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
)
DESIGN_ROBOT1_CHATTER_KEY = (
    "0/robot1/chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
)
DESIGN_ADD_TWO_INTS_KEY = (
    "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/"
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
)
DESIGN_LISTENER_NODE_TOKEN = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DESIGN_TALKER_PUBLISHER_TOKEN = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
)


def test_keys_and_tokens_are_rmw_zenohs_design_examples_exactly() -> None:
    string_type, add_two_ints = "std_msgs/msg/String", "example_interfaces/srv/AddTwoInts"
    # rosbags computes the same type hash the example carries.
    assert cdr.type_hash("jazzy", string_type) == DESIGN_STRING_HASH
    assert topic_keyexpr(0, "/chatter", string_type, DESIGN_STRING_HASH) == DESIGN_CHATTER_KEY
    robot1 = topic_keyexpr(0, "/robot1/chatter", string_type, DESIGN_STRING_HASH)
    assert robot1 == DESIGN_ROBOT1_CHATTER_KEY
    service = topic_keyexpr(2, "/add_two_ints", add_two_ints, DESIGN_ADD_TWO_INTS_HASH)
    assert service == DESIGN_ADD_TWO_INTS_KEY
    listener = NodeIdentity(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener")
    assert listener.node_token() == DESIGN_LISTENER_NODE_TOKEN
    talker = NodeIdentity(2, "8b20917502ee955ac4476e0266340d5c", 0, "talker")
    # demo_nodes_cpp's talker: reliable, volatile, keep_last 7 (rmw_zenoh's defaults but depth).
    token = talker.publisher_token(
        10, "/chatter", string_type, DESIGN_STRING_HASH, TopicQos(depth=7)
    )
    assert token == DESIGN_TALKER_PUBLISHER_TOKEN


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


def _sink_keys(settings: RmwZenohSettings) -> tuple[str, list[str], list[str]]:
    """(node token, data keys, publisher tokens) of a native sink on a session of its own."""
    with open_session(settings) as session:
        sink = NativeSink(session, settings)
        try:
            publishers = [sink.map, sink.updates, sink.height, sink.objects, sink.tf_static]
            publishers.append(sink.detections)
            return (
                sink.node.node_token(),
                [p.key for p in publishers],
                [p.token_key for p in publishers],
            )
        finally:
            sink.close()


def test_native_keys_take_ros_domain_id_unless_given(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    node_token, keys, tokens = _sink_keys(RmwZenohSettings(no_multicast_scouting=True))
    assert node_token.startswith("@ros2_lv/42/") and node_token.endswith("/0/0/NN/%/%/overgrid_map")
    map_hash = cdr.type_hash("jazzy", cdr.OCCUPANCY_GRID)
    assert keys[0] == f"42/map/nav_msgs::msg::dds_::OccupancyGrid_/{map_hash}"
    assert all(key.startswith("42/") for key in keys)
    assert all(token.startswith("@ros2_lv/42/") for token in tokens)
    given = RmwZenohSettings(no_multicast_scouting=True, domain_id=3)
    assert all(key.startswith("3/") for key in _sink_keys(given)[1])
    monkeypatch.delenv("ROS_DOMAIN_ID")
    unset = RmwZenohSettings(no_multicast_scouting=True)
    assert all(key.startswith("0/") for key in _sink_keys(unset)[1])


def test_native_keys_for_humble_carry_no_type_hash() -> None:
    settings = RmwZenohSettings(no_multicast_scouting=True, distro="humble", domain_id=0)
    _, keys, tokens = _sink_keys(settings)
    assert keys[0] == "0/map/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported"
    assert all(key.endswith(f"/{NO_TYPE_HASH}") for key in keys)
    # The token's type hash part, then the QoS: ``.../<type>/TypeHashNotSupported/<qos>``.
    assert all(token.split("/")[11] == NO_TYPE_HASH for token in tokens)
    assert tokens[0].endswith(
        "/MP/%/%/overgrid_map/%map/nav_msgs::msg::dds_::OccupancyGrid_/"
        "TypeHashNotSupported/:1:,1:,:,:,,"
    )


def test_a_relative_topic_is_published_under_its_fully_qualified_name() -> None:
    # rcl resolves every name before rmw_zenoh sees it: a token of ``map`` (not ``%map``) would
    # list a second topic in the robots' graph, with no publisher on /map.
    relative = RmwZenohSettings(no_multicast_scouting=True, domain_id=0, map_topic="map")
    _, keys, tokens = _sink_keys(relative)
    _, absolute_keys, absolute_tokens = _sink_keys(
        RmwZenohSettings(no_multicast_scouting=True, domain_id=0)
    )
    assert keys[0] == absolute_keys[0]
    assert tokens[0].split("/")[9:] == absolute_tokens[0].split("/")[9:]
    assert tokens[0].split("/")[9] == "%map"
    site = NodeIdentity(0, "zid", 0, "overgrid_map", namespace="/site")
    assert site.resolve("map") == "/site/map" and site.resolve("/map") == "/map"


def test_settings_give_the_map_qos_and_pose() -> None:
    settings = Ros2Settings(world_in_map=["1", "-2", "0.5"])
    assert settings.map_qos == MAP_QOS
    # Late joiners get the last height layer and objects too, as /map; each is a setting.
    assert settings.height_qos == settings.objects_qos == MAP_QOS
    volatile = Ros2Settings(objects_durability="volatile", objects_depth=3, height_depth=2)
    assert volatile.objects_qos == TopicQos(depth=3)
    assert volatile.height_qos == TopicQos(durability=Durability.TRANSIENT_LOCAL, depth=2)
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


@pytest.mark.parametrize("command", ["ros2", "rmw-zenoh"])
@pytest.mark.parametrize(
    ("flag", "value"),
    [
        ("--map-topic", "bad topic"),
        ("--map-topic", ""),
        ("--node-name", "bad-name"),
        ("--frame-id", ""),
        ("--frame-id", "/map"),
        ("--world-in-map", "1,2,nan"),
        ("--world-in-map", "1,2,inf"),
        ("--map-depth", "100000000000"),
        ("--updates-depth", "2147483648"),
        ("--timeout-s", "inf"),
        ("--timeout-s", "1e300"),
    ],
)
def test_a_name_ros_refuses_is_one_line_at_start_up(command: str, flag: str, value: str) -> None:
    """rclpy raised on such names only once the node started (a traceback), rmw_zenoh's keys took
    a space, and a NaN pose went out on /tf_static; rclpy refused a depth past int32 with a
    TypeError traceback, Zenoh a timeout past 1.8e19 s with a ValueError one."""
    assert_one_line_exit_2(run_overgrid(command, flag, value, "--no-multicast-scouting"), flag)


@pytest.mark.parametrize("domain", ["300", "abc"])
def test_a_ros_domain_no_ros_takes_is_one_line(
    monkeypatch: pytest.MonkeyPatch, domain: str
) -> None:
    """A traceback for ``abc``; for 300 a silent start on a domain no robot can use."""
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    assert_one_line_exit_2(run_overgrid("rmw-zenoh", "--no-multicast-scouting"), "ROS_DOMAIN_ID")
