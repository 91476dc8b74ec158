"""Client of the map service, for any robot: the base install (no OpenCV, no renderer) suffices."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
import zenoh

from common import keys
from common.camera import StereoCalibration
from common.codec import CodecError, Message, decode
from common.logs import CountedRefusals
from common.messages import (
    CALIB_KIND,
    MAP_UPDATE_KIND,
    OBJECTS_KIND,
    MapUpdateHeader,
    ObjectsHeader,
)
from common.occupancy_map import OccupancyMap

Region = tuple[float, float, float, float]
T = TypeVar("T")
log = logging.getLogger("overgrid.client")


class MapUnavailable(RuntimeError):
    """No fusion service answered, or it answered with an error or with what does not decode."""


RETRY_PERIOD_S = 0.2
MAX_TIMEOUT_S = 86_400.0
"""The longest wait a client call takes in one query (a day); settings bound their timeouts by
it. Zenoh refuses a query timeout past about 1.8e19 s ("negative timeout": ``inf`` was a
ValueError traceback); a longer ``timeout_s`` given to a call asks again until it has passed."""


def query_all(session: zenoh.Session, selector: str, timeout_s: float) -> list[bytes]:
    """Every good reply. A session just opened may not have found the services by scouting yet,
    so an empty answer is retried until ``timeout_s``; error replies with no good one are final."""
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        answers, errors = [], []
        try:
            for reply in session.get(selector, timeout=min(max(remaining, 0.1), MAX_TIMEOUT_S)):
                if reply.ok is not None:
                    answers.append(bytes(reply.ok.payload.to_bytes()))
                else:
                    errors.append(reply.err.payload.to_string() if reply.err is not None else "?")
        except zenoh.ZError as error:  # the session closed: the client's own error type
            raise MapUnavailable(f"{selector}: {error}") from None
        if answers:
            return answers
        if errors:
            raise MapUnavailable("; ".join(errors))
        if time.monotonic() + RETRY_PERIOD_S > deadline:
            raise MapUnavailable(f"no answer on {selector} within {timeout_s} s")
        time.sleep(RETRY_PERIOD_S)


def query_first(session: zenoh.Session, selector: str, timeout_s: float) -> bytes:
    return query_all(session, selector, timeout_s)[0]


def _parsed(key: str, parse: Callable[[bytes], T], payload: bytes) -> T:
    """``parse(payload)``; an answer that does not decode (another wire version, a forged or
    broken service; JSON nested past the interpreter's recursion limit) is MapUnavailable naming
    the key and why, as a silent service is: the one error a robot's code catches."""
    try:
        return parse(payload)
    except (ValueError, RecursionError) as error:  # CodecError and JSONDecodeError among them
        raise MapUnavailable(f"{key}: {error}") from None


def latest(
    session: zenoh.Session,
    region: Region | None = None,
    layers: tuple[str, ...] = (),
    timeout_s: float = 5.0,
) -> OccupancyMap:
    """The current map (or a region of it, in metres), with optional ``logodds``/``height`` layers."""
    parameters = [] if region is None else [_region_parameter(region)]
    if layers:
        parameters.append("layers=" + ",".join(layers))
    selector = keys.MAP_LATEST + ("?" + ";".join(parameters) if parameters else "")
    return _parsed(
        keys.MAP_LATEST, OccupancyMap.from_msgpack, query_first(session, selector, timeout_s)
    )


def latest_encoded(
    session: zenoh.Session, fmt: str, region: Region | None = None, timeout_s: float = 5.0
) -> bytes:
    """The map as the service encodes it: ``png``, ``pgm`` or ``yaml``."""
    parameters = [f"format={fmt}"] + ([_region_parameter(region)] if region else [])
    return query_first(session, keys.MAP_LATEST + "?" + ";".join(parameters), timeout_s)


def _region_parameter(region: Region) -> str:
    """``region=x0,y0,x1,y1`` at full precision (``:g``'s six digits moved a bound by a cell, and
    made a region 1e-7 m wide an error)."""
    return "region=" + ",".join(repr(float(v)) for v in region)


def health(session: zenoh.Session, timeout_s: float = 5.0) -> dict[str, Any]:
    """Fusion's ``map/health``: a JSON object (its fields: services/fusion)."""
    answer = _parsed(keys.MAP_HEALTH, json.loads, query_first(session, keys.MAP_HEALTH, timeout_s))
    if not isinstance(answer, dict):
        kind = type(answer).__name__
        raise MapUnavailable(f"{keys.MAP_HEALTH}: a JSON {kind}, not the object fusion answers")
    return answer


def objects(session: zenoh.Session, timeout_s: float = 5.0) -> ObjectsHeader:
    """The tracked obstacles of ``map/objects``: each with id, class, oriented footprint, top
    height, velocity and its covariance."""
    return _parsed(
        keys.MAP_OBJECTS,
        lambda payload: decode(payload, OBJECTS_KIND, ObjectsHeader).header,
        query_first(session, keys.MAP_OBJECTS, timeout_s),
    )


def calibrations(session: zenoh.Session, timeout_s: float = 5.0) -> list[StereoCalibration]:
    """Every pair's published calibration (``cam/*/calib``), sorted by pair; an answer that does
    not decode is skipped; MapUnavailable when no camera source answers."""
    found: dict[str, StereoCalibration] = {}
    for payload in query_all(session, keys.CALIB_ALL, timeout_s):
        try:
            calib = decode(payload, CALIB_KIND, StereoCalibration).header
        except CodecError:
            continue
        found[calib.pair] = calib
    return [found[pair] for pair in sorted(found)]


CATCH_UP_LIMIT_S = 5.0
"""How long a follower behind the newest update keeps fetching ``map/latest`` to reach it."""
CHAIN_END_WAIT_S = 0.5
"""How long a copy waits for the rest of a chain of updates (fusion sends one within
milliseconds) before it fetches ``map/latest``: the end was lost (updates are sent best effort)
and nothing may come after it while the map stands still."""
SETTLE_S = 1.0
"""A follower fetches ``map/latest`` once more this long after it began, unless an update came
first: an update sent while its subscription was on its way to fusion never reaches it, the
snapshot it fetched may be older than that update (fusion builds snapshots at a pace), and on a
map that then stands still no later update shows the gap (a viewer started as a box landed
drew the floor without it for good)."""
CHAIN_POLL_S = 0.02
UPDATES_BACKLOG = 64
"""Updates a follower keeps: waiting to be applied, and the recent ones it may replay onto a map it
fetched (map/latest may be a little older than the newest update)."""


def update_problem(message: Message[MapUpdateHeader]) -> str | None:
    """Why a decoded ``map/updates`` message fits no copy, or None: it must step the version
    forward, and its ``occupancy`` be int8 cells of its own window, inside the map window it
    names. (An update from a version to itself, or two forming a cycle, replayed for ever under
    the copy's lock: every reader of ``follower.map`` hung.)"""
    h = message.header
    if h.version <= h.previous_version or (
        h.final_version is not None and h.final_version < h.version
    ):
        return "version_order"
    occupancy = message.arrays.get("occupancy")
    if occupancy is None:
        return "no_occupancy"
    if occupancy.dtype != np.int8:
        return "occupancy_dtype"
    if occupancy.shape != (h.rows, h.cols):
        return "occupancy_shape"
    if not h.map_window.contains(h.window):
        return "outside_map"
    return None


class MapFollower:
    """A local copy kept current by ``map/updates``. The map's version is (epoch, version): an
    update of a new epoch (a fusion restarted, perhaps after a crash with a lower counter), a
    missed update (version gap) or a grown map triggers a fetch of ``map/latest``.

    It subscribes before it fetches and keeps the recent updates, so a fetched map older than the
    newest update is brought up to date by replaying them (fusion builds ``map/latest`` snapshots
    at a pace bounded by their cost, while updates go out at once); and it fetches once more when
    its subscription has surely reached fusion (``SETTLE_S``), for an update sent on the way.
    Updates are applied on the follower's own thread (a ring channel hands them over): a fetch
    never blocks a Zenoh callback.

    One change of the map goes out as a chain of updates (one per group of changed chunks); the
    copy moves to the chain's end only (``final_version``), so it is never part one capture, part
    the one before: a mover drawn half where it was."""

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
        self._reached: tuple[int, int] = (-1, -1)
        """The (epoch, version) the kept updates reach from the copy, whole or not."""
        self._recent: deque[Message[MapUpdateHeader]] = deque(maxlen=UPDATES_BACKLOG)
        self.callback_errors = 0
        """``on_change`` calls that raised (logged; the follower goes on)."""
        self._refused = CountedRefusals(log, "map follower: update refused")
        self.rejected = self._refused.counts
        """Updates refused where they enter, by reason (``update_problem``, ``undecodable``;
        logged, rate-limited): the copy stays as it was, and is fetched if the update was newer."""
        self._closed = False
        try:
            self._subscriber = session.declare_subscriber(
                keys.MAP_UPDATES, zenoh.handlers.RingChannel(UPDATES_BACKLOG)
            )
        except zenoh.ZError as error:
            raise MapUnavailable(f"{keys.MAP_UPDATES}: {error}") from None
        try:
            self._map = latest(session, timeout_s=timeout_s)
            self._reached = self._map.revision
        except MapUnavailable:
            self._subscriber.undeclare()  # type: ignore[no-untyped-call]
            raise
        self._thread = threading.Thread(target=self._run, name="map-follower", daemon=True)
        self._thread.start()

    @property
    def map(self) -> OccupancyMap:
        with self._lock:
            return self._map

    @property
    def reached(self) -> tuple[int, int]:
        """The (epoch, version) the updates received reach: past the copy's while the rest of a
        chain is on its way."""
        with self._lock:
            return self._reached

    @property
    def alive(self) -> bool:
        """Still following: False once closed or once its session closed (its copy then ages;
        :attr:`age_s` says how much)."""
        return self._thread.is_alive()

    @property
    def age_s(self) -> float:
        """Seconds since the newest capture in the copy, by this box's clock (inf before any; 0
        for a capture stamped ahead of it, a camera clock a little fast): following goes on
        while fusion is gone, and the copy ages; a robot should not plan on a map older than it
        can afford."""
        stamp_ns = self.map.stamp_ns
        return max(0.0, time.time() - stamp_ns / 1e9) if stamp_ns else math.inf

    def _run(self) -> None:
        samples = iter(self._subscriber)  # ends when the subscriber is undeclared
        chain_since_s: float | None = None  # waiting for the rest of a chain since
        settle_at_s: float | None = time.monotonic() + SETTLE_S  # the fetch after subscribing
        while True:
            if chain_since_s is None and settle_at_s is None:
                sample = next(samples, None)
                if sample is None:
                    return
            else:
                try:
                    sample = self._subscriber.handler.try_recv()
                except zenoh.ZError:  # undeclared: closed
                    return
                wait_until_s = (
                    settle_at_s if chain_since_s is None else chain_since_s + CHAIN_END_WAIT_S
                )
                if sample is None and wait_until_s is not None and time.monotonic() < wait_until_s:
                    time.sleep(CHAIN_POLL_S)
                    continue
            settle_at_s = None  # an update came (a gap before it shows), or the settle fetch
            arrival_s = time.time()
            try:
                if sample is None:  # the chain's end was lost, or settling: fetch past it
                    changed = self._catch_up()
                else:
                    changed = self._on_update(sample.payload.to_bytes())
            except (MapUnavailable, zenoh.ZError):
                changed = None  # fusion gone mid-fetch: the next update or epoch tries again
            with self._lock:
                mid_chain = self._reached > self._map.revision
            if not mid_chain:
                chain_since_s = None
            elif chain_since_s is None or sample is None:
                chain_since_s = time.monotonic()
            self._notify(changed, arrival_s)

    def _notify(self, changed: OccupancyMap | None, arrival_s: float) -> None:
        if changed is None or self._on_change is None:
            return
        try:
            self._on_change(changed, arrival_s)
        except Exception:  # the robot's own: one failure must not stop the copy
            self.callback_errors += 1
            log.exception("map follower: on_change raised; following goes on")

    def _on_update(self, payload: bytes) -> OccupancyMap | None:
        """The new copy this update makes, if any. A refused update is never kept for replay
        (kept, it failed every replay and froze the copy until 64 updates had pushed it out); a
        newer one still says the copy may be behind, so it is fetched."""
        try:
            message = decode(payload, MAP_UPDATE_KIND, MapUpdateHeader)
        except CodecError as error:
            self._refused.refuse("undecodable", error=str(error)[:200])
            return None
        h = message.header
        reason = update_problem(message)
        if reason is not None:
            arrays = {name: f"{a.dtype} {a.shape}" for name, a in message.arrays.items()}
            self._refused.refuse(
                reason, version=h.version, window=str(h.window), arrays=str(arrays)
            )
        with self._lock:
            if reason is None:
                self._recent.append(message)
            changed = self._replay()
            behind = h.revision > self._reached
        if behind:  # a gap, a grown map, a new epoch or a refused update: fetch, then replay
            changed = self._catch_up() or changed
        return changed

    def _catch_up(self) -> OccupancyMap | None:
        """Fetch ``map/latest`` until the copy reaches the newest update seen. A snapshot may be
        older than an update that grew the map (no replay crosses a new window), and when the stream
        then goes quiet no later update would trigger another fetch: fetched once, the copy would
        stay behind for good. Gives up after CATCH_UP_LIMIT_S; the next update tries again."""
        changed = None
        deadline = time.monotonic() + CATCH_UP_LIMIT_S
        while True:
            fresh = latest(self._session, timeout_s=self._timeout_s)
            with self._lock:
                self.refetches += 1
                if fresh.revision > self._map.revision:
                    self._map = changed = fresh
                changed = self._replay() or changed
                newest = max((m.header.revision for m in self._recent), default=(-1, -1))
                caught_up = self._map.revision >= newest
            if caught_up or time.monotonic() + RETRY_PERIOD_S > deadline:
                return changed
            time.sleep(RETRY_PERIOD_S)

    def _replay(self) -> OccupancyMap | None:
        """Apply every kept update that continues the copy (same epoch and map window, previous
        version the copy's), into one new copy, kept if it ends a chain; it, if so. Notes the
        version reached in ``_reached``. Call with the lock held."""
        current = self._map
        occupancy = None
        version, stamp_ns, applied = current.version, current.stamp_ns, 0
        whole: tuple[npt.NDArray[np.int8], int, int, int] | None = None
        """The cells, version, stamp and updates applied at the last chain's end walked."""
        while True:
            following = next(
                (
                    m
                    for m in self._recent
                    if m.header.epoch == current.epoch
                    and m.header.previous_version == version
                    and m.header.map_window == current.window
                ),
                None,
            )
            if following is None:
                break
            h = following.header
            if occupancy is None:
                occupancy = current.occupancy.copy()
            elif whole is not None and whole[0] is occupancy:  # walking on past a chain's end
                whole = (occupancy.copy(), *whole[1:])
            occupancy[h.window.slices_in(current.window)] = following.arrays["occupancy"]
            version, stamp_ns = h.version, h.stamp_ns
            applied += 1
            if h.final_version is None or h.version >= h.final_version:
                whole = (occupancy, version, stamp_ns, applied)
        self._reached = (current.epoch, version)
        if whole is None:  # nothing applied, or the rest of the chain is on its way
            return None
        occupancy, version, stamp_ns, applied = whole
        self.applied += applied
        self._map = replace(
            current,
            occupancy=occupancy,
            version=version,
            stamp_ns=stamp_ns,
            logodds=None,
            height_m=None,
            predicted=None,
            last_seen_s=None,
        )
        return self._map

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(zenoh.ZError):  # its session closed first: nothing to undeclare
            self._subscriber.undeclare()  # type: ignore[no-untyped-call]
        if threading.current_thread() is not self._thread:
            self._thread.join(self._timeout_s + 1.0)


def occupied_fraction(occupancy_map: OccupancyMap, threshold: int = 65) -> float:
    known = occupancy_map.occupancy >= 0
    return float(np.mean(occupancy_map.occupancy[known] >= threshold)) if known.any() else 0.0
