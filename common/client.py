"""Client of the map service, for any robot: the base install (no OpenCV, no renderer) suffices."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import zenoh

from common import keys
from common.camera import StereoCalibration
from common.codec import CodecError, decode
from common.messages import (
    CALIB_KIND,
    MAP_UPDATE_KIND,
    OBJECTS_KIND,
    MapUpdateHeader,
    ObjectsHeader,
)
from common.occupancy_map import OccupancyMap

Region = tuple[float, float, float, float]


class MapUnavailable(RuntimeError):
    """No fusion service answered, or it answered with an error."""


RETRY_PERIOD_S = 0.2


def query_all(session: zenoh.Session, selector: str, timeout_s: float) -> list[bytes]:
    """Every good reply. A session just opened may not have found the services by scouting yet,
    so an empty answer is retried until ``timeout_s``; error replies with no good one are final."""
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        answers, errors = [], []
        for reply in session.get(selector, timeout=max(remaining, 0.1)):
            if reply.ok is not None:
                answers.append(bytes(reply.ok.payload.to_bytes()))
            else:
                errors.append(reply.err.payload.to_string() if reply.err is not None else "?")
        if answers:
            return answers
        if errors:
            raise MapUnavailable("; ".join(errors))
        if time.monotonic() + RETRY_PERIOD_S > deadline:
            raise MapUnavailable(f"no answer on {selector} within {timeout_s} s")
        time.sleep(RETRY_PERIOD_S)


def query_first(session: zenoh.Session, selector: str, timeout_s: float) -> bytes:
    return query_all(session, selector, timeout_s)[0]


def latest(
    session: zenoh.Session,
    region: Region | None = None,
    layers: tuple[str, ...] = (),
    timeout_s: float = 5.0,
) -> OccupancyMap:
    """The current map (or a region of it, in metres), with optional ``logodds``/``height`` layers."""
    parameters = []
    if region is not None:
        parameters.append("region=" + ",".join(f"{v:g}" for v in region))
    if layers:
        parameters.append("layers=" + ",".join(layers))
    selector = keys.MAP_LATEST + ("?" + ";".join(parameters) if parameters else "")
    return OccupancyMap.from_msgpack(query_first(session, selector, timeout_s))


def latest_encoded(
    session: zenoh.Session, fmt: str, region: Region | None = None, timeout_s: float = 5.0
) -> bytes:
    """The map as the service encodes it: ``png``, ``pgm`` or ``yaml``."""
    parameters = [f"format={fmt}"] + (
        ["region=" + ",".join(f"{v:g}" for v in region)] if region else []
    )
    return query_first(session, keys.MAP_LATEST + "?" + ";".join(parameters), timeout_s)


def health(session: zenoh.Session, timeout_s: float = 5.0) -> dict[str, Any]:
    answer: dict[str, Any] = json.loads(query_first(session, keys.MAP_HEALTH, timeout_s))
    return answer


def objects(session: zenoh.Session, timeout_s: float = 5.0) -> ObjectsHeader:
    """The tracked obstacles of ``map/objects``: each with id, class, oriented footprint, top
    height, velocity and its covariance."""
    try:
        return decode(
            query_first(session, keys.MAP_OBJECTS, timeout_s), OBJECTS_KIND, ObjectsHeader
        ).header
    except CodecError as error:
        raise MapUnavailable(f"map/objects: {error}") from None


def calibrations(session: zenoh.Session, timeout_s: float = 5.0) -> list[StereoCalibration]:
    """Every pair's published calibration (``cam/*/calib``), sorted by pair; an answer that does
    not decode is skipped; empty when no camera source answers."""
    found: dict[str, StereoCalibration] = {}
    for payload in query_all(session, keys.CALIB_ALL, timeout_s):
        try:
            calib = decode(payload, CALIB_KIND, StereoCalibration).header
        except CodecError:
            continue
        found[calib.pair] = calib
    return [found[pair] for pair in sorted(found)]


UPDATES_BACKLOG = 64
"""Updates a follower holds while it applies one; older ones are dropped (the version gap then
makes it fetch the map)."""


class MapFollower:
    """A local copy kept current by ``map/updates``. The map's version is (epoch, version): an
    update of a new epoch (a fusion restarted, perhaps after a crash with a lower counter), a
    missed update (version gap) or a grown map triggers one fetch of ``map/latest``.

    Updates are applied on the follower's own thread (a ring channel hands them over), so the
    fetch never blocks a Zenoh callback."""

    def __init__(
        self,
        session: zenoh.Session,
        timeout_s: float = 5.0,
        on_change: Callable[[OccupancyMap, float], None] | None = None,
    ) -> None:
        """``on_change(map, arrival_s)`` is called with each new version (arrival: epoch seconds),
        from the follower's thread."""
        self._session = session
        self._timeout_s = timeout_s
        self._on_change = on_change
        self._lock = threading.Lock()
        self.refetches = 0
        self.applied = 0
        self._map = latest(session, timeout_s=timeout_s)
        self._subscriber = session.declare_subscriber(
            keys.MAP_UPDATES, zenoh.handlers.RingChannel(UPDATES_BACKLOG)
        )
        self._thread = threading.Thread(target=self._run, name="map-follower", daemon=True)
        self._thread.start()

    @property
    def map(self) -> OccupancyMap:
        with self._lock:
            return self._map

    def _run(self) -> None:
        for sample in self._subscriber:  # ends when the subscriber is undeclared
            try:
                self._on_update(sample.payload.to_bytes(), time.time())
            except (MapUnavailable, CodecError, ValueError, zenoh.ZError):
                continue  # fusion gone mid-fetch: the next update or epoch tries again

    def _on_update(self, payload: bytes, arrival_s: float) -> None:
        message = decode(payload, MAP_UPDATE_KIND, MapUpdateHeader)
        h = message.header
        changed: OccupancyMap | None = None
        with self._lock:
            current = self._map
            if (h.epoch, h.version) <= current.revision:
                return  # old news, or from a fusion run that has since been replaced
            if (
                h.epoch == current.epoch
                and h.previous_version == current.version
                and h.map_window == current.window
            ):
                occupancy = current.occupancy.copy()
                occupancy[h.window.slices_in(current.window)] = message.arrays["occupancy"]
                self._map = replace(
                    current,
                    occupancy=occupancy,
                    version=h.version,
                    stamp_ns=h.stamp_ns,
                    logodds=None,
                    height_m=None,
                )
                self.applied += 1
                changed = self._map
        if changed is None:
            fresh = latest(self._session, timeout_s=self._timeout_s)
            with self._lock:
                self.refetches += 1
                if fresh.revision > self._map.revision:
                    self._map = changed = fresh
        if changed is not None and self._on_change is not None:
            self._on_change(changed, arrival_s)

    def close(self) -> None:
        self._subscriber.undeclare()  # type: ignore[no-untyped-call]
        if threading.current_thread() is not self._thread:
            self._thread.join(self._timeout_s + 1.0)


def occupied_fraction(occupancy_map: OccupancyMap, threshold: int = 65) -> float:
    known = occupancy_map.occupancy >= 0
    return float(np.mean(occupancy_map.occupancy[known] >= threshold)) if known.any() else 0.0
