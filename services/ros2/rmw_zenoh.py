"""rmw_zenoh's wire conventions, as strings and bytes: data key expressions, liveliness graph
tokens with the QoS encoded, the per-sample attachment and the entity GID.

Followed from rmw_zenoh (ros2/rmw_zenoh, rolling, which Kilted, Jazzy ≥ 0.2.4 and Humble ≥ 0.1.2
share; older releases wrote a labelled attachment their readers throw on, and robots on them
cannot read these samples):
- docs/design.md: one liveliness token per entity under ``@ros2_lv``; "NN" node, "MP" publisher;
  transient_local publishers keep a cache that late-joining subscriptions query;
- rmw_zenoh_cpp/src/detail/liveliness_utils.cpp: ``TopicInfo`` (data key
  ``<domain>/<topic without leading and trailing '/'>/<type>/<type hash>``), ``Entity::Entity``
  (token ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/<namespace>/<node>`` then, for
  endpoints, ``/<topic>/<type>/<type hash>/<qos>``, every part with '/' mangled to '%'),
  ``qos_to_keyexpr`` (``rel:dur:hist,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns``,
  a field equal to rmw_zenoh's default left empty) and the GID (XXH3-128 of the token, low 64
  bits first);
- rmw_zenoh_cpp/src/detail/qos.cpp: the defaults (reliable, volatile, keep_last 42, infinite
  durations, automatic liveliness);
- rmw_zenoh_cpp/src/detail/attachment_helpers.cpp: the attachment is zenoh-ext serialization of
  (int64 sequence number, int64 source timestamp ns, the 16-byte GID), which zenoh's
  serialization format writes as a sequence (LEB128 length, then the bytes);
- rmw_zenoh_cpp/src/detail/rmw_publisher_data.cpp: an advanced publisher, with
  publisher_detection and a cache of ``depth`` samples when transient_local, plus sporadic
  heartbeats (500 ms) for sample miss detection when also reliable; sequence numbers from 1;
- Humble's rmw_zenoh has no type hashes: its keys and tokens carry ``TypeHashNotSupported``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import xxhash
from zenoh import ZBytes
from zenoh.ext import Int64, z_deserialize, z_serialize

ADMIN_SPACE = "@ros2_lv"
NODE_KIND = "NN"
PUBLISHER_KIND = "MP"
SLASH_REPLACEMENT = "%"
QOS_DELIMITER = ":"
QOS_COMPONENT_DELIMITER = ","
NO_TYPE_HASH = "TypeHashNotSupported"
"""What Humble's rmw_zenoh puts where later distros put the RIHS01 hash."""
GID_SIZE_BYTES = 16
"""RMW_GID_STORAGE_SIZE since Jazzy."""
FIRST_SEQUENCE_NUMBER = 1
MISS_DETECTION_HEARTBEAT_S = 0.5
"""SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD of rmw_publisher_data.cpp."""
ROOT_NAMESPACE = "/"
DEFAULT_ENCLAVE = "/"


class Reliability(IntEnum):
    """rmw_qos_reliability_policy_e (rmw/types.h)."""

    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(IntEnum):
    """rmw_qos_durability_policy_e."""

    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class History(IntEnum):
    """rmw_qos_history_policy_e."""

    KEEP_LAST = 1
    KEEP_ALL = 2


@dataclass(frozen=True)
class TopicQos:
    """The QoS a liveliness token carries; deadline, lifespan and liveliness stay at rmw_zenoh's
    defaults (infinite, automatic), which the token writes as empty fields."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10


DEFAULT_QOS = TopicQos(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 42)
"""rmw_zenoh's QoS::default_qos() (qos.cpp)."""


def qos_keyexpr(qos: TopicQos) -> str:
    """``qos_to_keyexpr`` of liveliness_utils.cpp: a field equal to the default is left empty."""

    def field(value: int, default: int) -> str:
        return "" if value == default else str(int(value))

    reliability = field(qos.reliability, DEFAULT_QOS.reliability)
    durability = field(qos.durability, DEFAULT_QOS.durability)
    history = field(qos.history, DEFAULT_QOS.history) + QOS_COMPONENT_DELIMITER
    history += field(qos.depth, DEFAULT_QOS.depth)
    unset_duration = QOS_COMPONENT_DELIMITER  # deadline, lifespan: sec,nsec both default
    liveliness = QOS_COMPONENT_DELIMITER * 2  # kind,lease sec,lease nsec all default
    return QOS_DELIMITER.join(
        [reliability, durability, history, unset_duration, unset_duration, liveliness]
    )


def mangle(name: str) -> str:
    """A ROS name as one key chunk: '/' becomes '%' (``mangle_name``)."""
    return name.replace("/", SLASH_REPLACEMENT)


def dds_type_name(ros_type: str) -> str:
    """``nav_msgs/msg/OccupancyGrid`` → ``nav_msgs::msg::dds_::OccupancyGrid_``, the name the
    rosidl typesupport gives and rmw_zenoh puts in keys and tokens."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_keyexpr(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key samples of ``topic`` are put on (``TopicInfo::TopicInfo``)."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class NodeIdentity:
    """What every token of one node repeats: domain, Zenoh session id, node id, names."""

    domain_id: int
    zid: str
    node_id: int
    name: str
    namespace: str = ROOT_NAMESPACE
    enclave: str = DEFAULT_ENCLAVE

    def _prefix(self, entity_id: int, kind: str) -> str:
        parts = [ADMIN_SPACE, str(self.domain_id), self.zid, str(self.node_id), str(entity_id)]
        parts += [kind, mangle(self.enclave), mangle(self.namespace), mangle(self.name)]
        return "/".join(parts)

    def resolve(self, topic: str) -> str:
        """A topic's fully qualified name, as rcl hands rmw_zenoh every name: a relative one in
        the node's namespace (the graph lists ``map`` and ``/map`` as two topics)."""
        return topic if topic.startswith("/") else f"{self.namespace.rstrip('/')}/{topic}"

    def node_token(self) -> str:
        """The node's ``NN`` token: rmw_node_data.cpp gives a node its own id as both ids."""
        return self._prefix(self.node_id, NODE_KIND)

    def publisher_token(
        self, publisher_id: int, topic: str, ros_type: str, type_hash: str, qos: TopicQos
    ) -> str:
        endpoint = [mangle(topic), mangle(dds_type_name(ros_type)), mangle(type_hash)]
        return "/".join([self._prefix(publisher_id, PUBLISHER_KIND), *endpoint, qos_keyexpr(qos)])


def gid_of(token: str) -> bytes:
    """The entity's GID: XXH3-128 of its liveliness token, ``low64`` then ``high64`` copied in
    the host's (little-endian) byte order, as ``Entity::Entity`` does."""
    value = xxhash.xxh3_128_intdigest(token.encode())
    return value.to_bytes(GID_SIZE_BYTES, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """``AttachmentData::serialize_to_zbytes``: zenoh-ext serialization of the three fields."""
    if len(gid) != GID_SIZE_BYTES:
        raise ValueError(f"a GID has {GID_SIZE_BYTES} bytes, got {len(gid)}")
    payload = z_serialize((Int64(sequence_number), Int64(source_timestamp_ns), gid))
    return bytes(payload.to_bytes())


def parse_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an attachment, as rmw_zenoh reads it."""
    sequence_number, stamp_ns, gid = z_deserialize(tuple[Int64, Int64, bytes], ZBytes(raw))
    return int(sequence_number), int(stamp_ns), bytes(gid)
