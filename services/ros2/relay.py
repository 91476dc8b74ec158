"""Follows the fusion service (``common.client.MapFollower``) and hands a sink what a ROS 2 robot
needs, at the pace it needs it: a whole /map now and then, every change as an update, the height
layer at its own period. Both outputs (the rclpy node, the native rmw_zenoh publisher) are sinks.

Why a whole /map at most every ``map_interval_s`` and not at every version: /map is the latched
(transient_local) sample a late joiner starts from, so it must not lag far behind, but it costs
the whole grid each time; the updates carry only the changed rectangle (nav2's costmap does the
same with /costmap and /costmap_updates).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

import zenoh

from common import keys
from common.client import MapFollower, MapUnavailable, health, latest, objects
from common.codec import CodecError, decode
from common.lattice import Window
from common.logs import CountedRefusals, RateLimitedLog, Transitions
from common.messages import OBJECTS_KIND, ObjectsHeader
from common.occupancy_map import OccupancyMap
from services.ros2.grid_message import (
    GridMessage,
    GridUpdate,
    HeightImage,
    StaticTransform,
    changed_window,
    grid_message,
    grid_update,
    height_image,
    world_transform,
)
from services.ros2.object_markers import ObjectMarkers, object_markers
from services.ros2.settings import Ros2Settings

FOLLOW_RETRY_S = 1.0
FUSION_CHECK_S = 5.0
"""With no new map for this long, whether fusion still answers is asked (and said when not)."""


class MapSink(Protocol):
    def publish_map(self, message: GridMessage) -> None: ...

    def publish_update(self, update: GridUpdate) -> None: ...

    def publish_height(self, image: HeightImage) -> None: ...

    def publish_objects(self, markers: ObjectMarkers) -> None: ...

    def publish_static_transform(self, transform: StaticTransform) -> None: ...


class MapRelay:
    def __init__(
        self, session: zenoh.Session, settings: Ros2Settings, sink: MapSink, log: logging.Logger
    ) -> None:
        self._session = session
        self._settings = settings
        self._sink = sink
        self._log = log
        self.wake = threading.Event()
        """Set by each new map version, and by a stop."""
        self.counts = {"map": 0, "update": 0, "height": 0, "objects": 0, "tf_static": 0}
        self._refused = CountedRefusals(log, "message not published")
        self.rejected = self._refused.counts
        """Messages not published, by reason (``objects_undecodable``, ``{kind}_unpublishable``:
        a value a ROS message cannot carry); each reason logged, rate-limited."""
        self._warn = RateLimitedLog(log)
        self._said_empty = False
        self._fusion = Transitions(
            log,
            "fusion does not answer: the topics keep the last map and objects",
            "fusion answers again",
        )
        self._objects: ObjectsHeader | None = None
        """The newest map/objects put, handed over by the Zenoh callback."""
        self._objects_lock = threading.Lock()

    def run(self, stop: threading.Event) -> None:
        s = self._settings
        # The world → map pose needs no map: robots' tf2 has it before the first /map.
        transform = world_transform(s.pose, s.frame_id, s.world_frame_id, time.time_ns())
        self._sink.publish_static_transform(transform)
        self.counts["tf_static"] += 1
        follower = self._follow(stop)
        if follower is None:
            return
        objects_subscriber = self._session.declare_subscriber(keys.MAP_OBJECTS, self._on_objects)
        try:
            sent = follower.map
            self._publish_map(sent)
            self._publish_height()
            objects_version = self._publish_first_objects()
            map_due = False
            last_map_s = last_height_s = last_change_s = checked_s = time.monotonic()
            height_revision = sent.revision
            while not stop.is_set():
                now = time.monotonic()
                # Wake when the next whole /map falls due, not a period after it.
                due_in_s = last_map_s + s.map_interval_s - now if map_due else s.map_interval_s
                self.wake.wait(max(0.0, min(due_in_s, s.height_interval_s, FUSION_CHECK_S)))
                self.wake.clear()
                current = follower.map
                if current.revision > sent.revision:
                    if current.epoch != sent.epoch:
                        self._log.info("fusion started a new map", extra={"epoch": current.epoch})
                    changed = changed_window(sent, current)
                    # Moved or grew, or none sent yet (no cell till now): a whole map says it.
                    if changed is None or self.counts["map"] == 0:
                        if self._publish_map(current):
                            last_map_s, map_due = time.monotonic(), False
                    else:
                        if not changed.empty:
                            self._publish_update(current, changed)
                        map_due = True
                    sent, last_change_s = current, time.monotonic()
                    # A new map is fusion answering: said when it had not (else the next silence,
                    # still "not answering", went unsaid, and its end said "answers again").
                    self._fusion.update(True)
                now = time.monotonic()
                if map_due and now - last_map_s >= s.map_interval_s:
                    self._publish_map(sent)
                    last_map_s, map_due = now, False
                if now - last_height_s >= s.height_interval_s and height_revision != sent.revision:
                    self._publish_height()
                    last_height_s, height_revision = now, sent.revision
                with self._objects_lock:
                    tracked, self._objects = self._objects, None
                if tracked is not None and tracked.version != objects_version:
                    self._publish_objects(tracked)
                    objects_version = tracked.version
                if now - max(last_change_s, checked_s) >= FUSION_CHECK_S:
                    self._check_fusion(now - last_change_s)
                    checked_s = now
        finally:
            objects_subscriber.undeclare()  # type: ignore[no-untyped-call]
            follower.close()

    def _check_fusion(self, quiet_s: float) -> None:
        """Say when fusion stops answering (what was published stays latched, older by the
        minute) and when it answers again."""
        try:
            health(self._session, timeout_s=1.0)
        except MapUnavailable:
            self._fusion.update(False, quiet_s=round(quiet_s, 1))
        else:
            self._fusion.update(True)

    def _follow(self, stop: threading.Event) -> MapFollower | None:
        """A follower of the fusion service, waiting for it as long as it takes (this process may
        start first); ``None`` when stopped meanwhile."""
        while not stop.is_set():
            try:
                return MapFollower(
                    self._session,
                    timeout_s=self._settings.timeout_s,
                    on_change=lambda _map, _arrival_s: self.wake.set(),
                )
            except MapUnavailable as error:
                self._warn.warning(
                    "fusion", "waiting for the fusion service", error=str(error)[:200]
                )
                stop.wait(FOLLOW_RETRY_S)
        return None

    def _on_objects(self, sample: zenoh.Sample) -> None:
        try:
            tracked = decode(sample.payload.to_bytes(), OBJECTS_KIND, ObjectsHeader).header
        except CodecError as error:
            self._reject("objects_undecodable", error)
            return
        with self._objects_lock:
            self._objects = tracked
        self.wake.set()

    def _publish_first_objects(self) -> int | None:
        """The current objects once at start (later ones arrive as puts); ``None`` when the
        fusion service serves none (an older one, or not yet)."""
        try:
            tracked = objects(self._session, timeout_s=self._settings.timeout_s)
        except MapUnavailable:
            return None
        self._publish_objects(tracked)
        return tracked.version

    def _publish_objects(self, tracked: ObjectsHeader) -> None:
        s = self._settings
        self._publish(
            "objects",
            lambda: self._sink.publish_objects(object_markers(tracked, s.frame_id, s.pose)),
        )

    def _publish(self, kind: str, publish: Callable[[], None]) -> bool:
        """Build and publish one message of ``kind`` (a ``counts`` key); one that fails is skipped
        and counted, and the robots keep the last good one. Any exception: what fails is rosbags'
        or rclpy's code fed values from the network (a stamp past ROS time was a struct.error that
        ended the process), and one message must not end the relay."""
        try:
            publish()
        except Exception as error:
            self._reject(f"{kind}_unpublishable", error)
            return False
        self.counts[kind] += 1
        return True

    def _reject(self, reason: str, error: Exception) -> None:
        self._refused.refuse(reason, error=f"{type(error).__name__}: {error}"[:200])

    def _publish_map(self, occupancy_map: OccupancyMap) -> bool:
        """A whole /map, unless the map has no cell yet (a 0 × 0 grid latched for late joiners
        would be all they get until the next whole map)."""
        if occupancy_map.occupancy.size == 0:
            if not self._said_empty:
                self._log.info("the map has no cell yet: no /map until it has")
                self._said_empty = True
            return False
        s = self._settings
        message = grid_message(occupancy_map, s.frame_id, s.pose, s.map_mode)
        if not self._publish("map", lambda: self._sink.publish_map(message)):
            return False
        first = self.counts["map"] == 1
        self._log.log(
            logging.INFO if first else logging.DEBUG,
            "first map published" if first else "map published",
            extra={"version": occupancy_map.version},
        )
        return True

    def _publish_update(self, current: OccupancyMap, changed: Window) -> None:
        s = self._settings
        update = grid_update(current, changed, s.frame_id, s.map_mode)
        self._publish("update", lambda: self._sink.publish_update(update))

    def _publish_height(self) -> None:
        """The follower's copy has no height layer (map/updates carries occupancy only), so the
        layer is asked of map/latest at its own, slower, period."""
        try:
            layered = latest(self._session, layers=("height",), timeout_s=self._settings.timeout_s)
        except MapUnavailable as error:
            self._warn.warning("height", "height layer unavailable", error=str(error)[:200])
            return
        frame_id = self._settings.frame_id
        self._publish("height", lambda: self._sink.publish_height(height_image(layered, frame_id)))
