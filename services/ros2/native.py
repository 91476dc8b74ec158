"""``overgrid rmw-zenoh``: /map, /map_updates, the height layer, the objects (as markers and as
vision_msgs/Detection3DArray) and /tf_static straight onto rmw_zenoh's Zenoh keys, so a robot with
``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` on the same Zenoh network gets the map from
``ros2 topic echo /map`` with no ROS node or bridge here (base install + rosbags).

The process shows up in the robot's ROS graph as node ``overgrid_map`` with six publishers,
because it declares the same liveliness tokens an rmw_zenoh node would (services/ros2/rmw_zenoh.py
says which source each convention comes from).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import zenoh
import zenoh.ext

from common.lifecycle import stop_on_signals
from common.logs import setup_logging
from common.settings import parse_settings
from common.zenoh_session import open_session
from services.ros2 import cdr
from services.ros2.grid_message import GridMessage, GridUpdate, HeightImage, StaticTransform
from services.ros2.object_markers import ObjectMarkers
from services.ros2.relay import MapRelay
from services.ros2.rmw_zenoh import (
    FIRST_SEQUENCE_NUMBER,
    MISS_DETECTION_HEARTBEAT_S,
    Durability,
    History,
    NodeIdentity,
    Reliability,
    TopicQos,
    attachment,
    gid_of,
    topic_keyexpr,
)
from services.ros2.settings import RmwZenohSettings, ros_domain_id

log = logging.getLogger("rmw-zenoh")
NODE_ID = 0
"""Entity ids as one rmw_zenoh context hands them out: the node first, then its publishers."""


class NativePublisher:
    """One ROS 2 publisher as rmw_zenoh makes it: an advanced publisher on the topic's key (with a
    cache for transient_local), a liveliness token, a GID and a sequence number per sample."""

    def __init__(
        self,
        session: zenoh.Session,
        node: NodeIdentity,
        publisher_id: int,
        topic: str,
        ros_type: str,
        distro: cdr.Distro,
        qos: TopicQos,
    ) -> None:
        type_hash = cdr.type_hash(distro, ros_type)
        topic = node.resolve(topic)
        self.key = topic_keyexpr(node.domain_id, topic, ros_type, type_hash)
        self.token_key = node.publisher_token(publisher_id, topic, ros_type, type_hash, qos)
        self.gid = gid_of(self.token_key)
        transient = qos.durability == Durability.TRANSIENT_LOCAL
        reliable = qos.reliability == Reliability.RELIABLE
        self._publisher = zenoh.ext.declare_advanced_publisher(
            session,
            self.key,
            congestion_control=zenoh.CongestionControl.BLOCK
            if reliable and qos.history == History.KEEP_ALL
            else zenoh.CongestionControl.DROP,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
            cache=zenoh.ext.CacheConfig(qos.depth) if transient else None,
            publisher_detection=transient,
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=MISS_DETECTION_HEARTBEAT_S
            )
            if transient and reliable
            else None,
        )
        self._token = session.liveliness().declare_token(self.token_key)
        self._sequence_number = FIRST_SEQUENCE_NUMBER

    def put(self, payload_cdr: bytes) -> None:
        extra = attachment(self._sequence_number, time.time_ns(), self.gid)
        self._sequence_number += 1
        self._publisher.put(payload_cdr, attachment=extra)

    def close(self) -> None:
        self._token.undeclare()  # type: ignore[no-untyped-call]
        self._publisher.undeclare()  # type: ignore[no-untyped-call]


class NativeSink:
    def __init__(self, session: zenoh.Session, settings: RmwZenohSettings) -> None:
        s = settings
        self._distro = s.distro
        domain_id = s.domain_id if s.domain_id is not None else ros_domain_id()
        self.node = NodeIdentity(domain_id, str(session.info.zid()), NODE_ID, s.node_name)
        self._node_token = session.liveliness().declare_token(self.node.node_token())
        self.map = NativePublisher(
            session, self.node, 1, s.map_topic, cdr.OCCUPANCY_GRID, s.distro, s.map_qos
        )
        self.updates = NativePublisher(
            session,
            self.node,
            2,
            s.updates_topic,
            cdr.OCCUPANCY_GRID_UPDATE,
            s.distro,
            s.updates_qos,
        )
        self.height = NativePublisher(
            session, self.node, 3, s.height_topic, cdr.IMAGE, s.distro, s.height_qos
        )
        self.objects = NativePublisher(
            session, self.node, 4, s.objects_topic, cdr.MARKER_ARRAY, s.distro, s.objects_qos
        )
        self.tf_static = NativePublisher(
            session, self.node, 5, s.tf_static_topic, cdr.TF_MESSAGE, s.distro, s.tf_static_qos
        )
        self.detections = NativePublisher(
            session,
            self.node,
            6,
            s.detections_topic,
            cdr.DETECTION_3D_ARRAY,
            s.distro,
            s.objects_qos,
        )

    def publish_map(self, message: GridMessage) -> None:
        self.map.put(cdr.occupancy_grid_cdr(self._distro, message))

    def publish_update(self, update: GridUpdate) -> None:
        self.updates.put(cdr.occupancy_grid_update_cdr(self._distro, update))

    def publish_height(self, image: HeightImage) -> None:
        self.height.put(cdr.height_image_cdr(self._distro, image))

    def publish_objects(self, markers: ObjectMarkers) -> None:
        self.objects.put(cdr.marker_array_cdr(self._distro, markers))
        self.detections.put(cdr.detection_array_cdr(self._distro, markers))

    def publish_static_transform(self, transform: StaticTransform) -> None:
        self.tf_static.put(cdr.tf_message_cdr(self._distro, transform))

    def close(self) -> None:
        publishers = (self.detections, self.tf_static, self.objects, self.height, self.updates)
        for publisher in (*publishers, self.map):
            publisher.close()
        self._node_token.undeclare()  # type: ignore[no-untyped-call]


def main(settings: RmwZenohSettings) -> None:
    setup_logging("rmw-zenoh", settings.log_level)
    if settings.domain_id is None:
        ros_domain_id()  # checked before waiting for a router, not after
    with open_session(settings, timestamping=True, wait_for_router=True) as session:
        sink = NativeSink(session, settings)
        relay = MapRelay(session, settings, sink, log)
        stop = stop_on_signals(relay.wake)
        log.info(
            "started",
            extra={"map_key": sink.map.key, "distro": settings.distro, "node": settings.node_name},
        )
        try:
            relay.run(stop)
        finally:
            sink.close()
    log.info("stopped", extra={**relay.counts, **relay.rejected})


def cli(argv: Sequence[str] | None = None) -> None:
    main(
        parse_settings(
            RmwZenohSettings,
            argv,
            "overgrid rmw-zenoh",
            "Publishes the map on rmw_zenoh's keys for ROS 2 robots (no ROS installation needed).",
        )
    )
