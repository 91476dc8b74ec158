"""The robot client against map services that lag or misbehave: a MapFollower whose
``map/latest`` lags its ``map/updates`` (fusion builds snapshots at a pace; updates go out at once)
must reach the newest version even when the stream goes quiet right after an update it cannot
replay; a forged update must not freeze it; answers that do not decode are MapUnavailable."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
import zenoh

from common import client
from common.client import MapFollower, MapUnavailable, latest
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.messages import MAP_UPDATE_KIND, MapUpdateHeader
from common.occupancy_map import OccupancyMap
from tests.conftest import Bus, wait_for

RESOLUTION_M = 0.05
EPOCH = 1_000


def _map(window: Window, value: int, version: int, stamp_ns: int = 0) -> OccupancyMap:
    cells = np.full((window.rows, window.cols), value, np.int8)
    return OccupancyMap(cells, RESOLUTION_M, window.i0, window.j0, version, stamp_ns, epoch=EPOCH)


def _update(
    grown: OccupancyMap,
    previous_version: int,
    arrays: dict[str, np.ndarray] | None = None,
    window: Window | None = None,
    final_version: int | None = None,
) -> bytes:
    """``grown`` whole as an update of ``previous_version``; or ``arrays`` over ``window``."""
    w, m = window or grown.window, grown.window
    header = MapUpdateHeader(
        version=grown.version,
        previous_version=previous_version,
        final_version=final_version,
        epoch=EPOCH,
        stamp_ns=0,
        resolution_m=RESOLUTION_M,
        i0=w.i0,
        j0=w.j0,
        cols=w.cols,
        rows=w.rows,
        map_i0=m.i0,
        map_j0=m.j0,
        map_cols=m.cols,
        map_rows=m.rows,
    )
    return encode(
        MAP_UPDATE_KIND, header, {"occupancy": grown.occupancy} if arrays is None else arrays
    )


def _peer(bus: Bus) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([bus.endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("namespace", json.dumps(bus.namespace))
    return zenoh.open(config)


@pytest.mark.process
def test_a_follower_behind_a_grown_map_fetches_until_it_has_the_newest(bus: Bus) -> None:
    empty = _map(Window(0, 0, 0, 0), -1, version=0)
    grown = _map(Window(10, 20, 30, 40), 100, version=1, stamp_ns=time.time_ns() - 2 * 10**9)
    served = [empty]
    stale_answers_left = [3]

    def answer(query: zenoh.Query) -> None:
        # The first answers after the update still give the old snapshot, as a paced fusion does.
        current = served[-1]
        if len(served) > 1 and stale_answers_left[0] > 0:
            stale_answers_left[0] -= 1
            current = served[0]
        query.reply("map/latest", current.to_msgpack(), encoding=WIRE_ENCODING)

    queryable = bus.session.declare_queryable("map/latest", answer)
    updates = bus.session.declare_publisher("map/updates", encoding=WIRE_ENCODING)
    with _peer(bus) as session:
        follower = MapFollower(session, timeout_s=5)
        assert follower.map.revision == (EPOCH, 0)
        assert follower.age_s == math.inf  # no capture yet
        served.append(grown)
        # One update that grows the map, then silence: no later update will trigger a fetch. (The
        # follower's subscription reached the router before its fetch did, on the same link.)
        updates.put(_update(grown, 0))
        wait_for(lambda: follower.map.revision == (EPOCH, 1), 10, "the follower to catch up")
        assert stale_answers_left == [0]  # it did meet the stale snapshots on its way
        np.testing.assert_array_equal(follower.map.occupancy, grown.occupancy)
        assert follower.map.window == grown.window
        assert 2.0 <= follower.age_s < 30.0  # the capture's age, by this box's clock
        follower.close()
    queryable.undeclare()  # type: ignore[no-untyped-call]


@pytest.mark.process
def test_a_follower_started_as_the_map_changed_settles_on_it(bus: Bus) -> None:
    """The last update before the map stood still went out while the follower's subscription was
    on its way (it never arrives), and the first snapshot it fetched was older (fusion builds
    them at a pace): with no later update to show the gap, one more fetch after it settles
    finds the newer map."""
    before = _map(Window(0, 0, 4, 4), 0, version=1)
    after = _map(Window(0, 0, 4, 4), 100, version=2)
    answers = [before]

    def answer(query: zenoh.Query) -> None:
        current = answers.pop(0) if len(answers) > 1 else answers[0]
        query.reply("map/latest", current.to_msgpack(), encoding=WIRE_ENCODING)

    queryable = bus.session.declare_queryable("map/latest", answer)
    answers.append(after)  # the first answer is the old snapshot, every later one the new
    with _peer(bus) as session:
        follower = MapFollower(session, timeout_s=5)
        assert follower.map.revision == (EPOCH, 1)
        wait_for(lambda: follower.map.revision == (EPOCH, 2), 2 * client.SETTLE_S + 3, "settled")
        assert follower.refetches == 1
        follower.close()
    queryable.undeclare()  # type: ignore[no-untyped-call]


def test_a_closed_session_is_the_clients_own_error() -> None:
    """After ``session.close()`` the calls raised zenoh.ZError, not MapUnavailable."""
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    session.close()  # type: ignore[no-untyped-call]
    with pytest.raises(MapUnavailable, match="map/latest"):
        latest(session, timeout_s=0.5)
    with pytest.raises(MapUnavailable, match="map/updates"):
        MapFollower(session, timeout_s=0.5)


FORGED: dict[str, tuple[dict[str, np.ndarray], Window | None]] = {
    "occupancy_shape": ({"occupancy": np.zeros((3, 3), np.int8)}, None),
    "no_occupancy": ({"other": np.zeros((2, 2), np.int8)}, None),
    "occupancy_dtype": ({"occupancy": np.zeros((2, 2), np.float32)}, None),
    "outside_map": ({"occupancy": np.zeros((2, 2), np.int8)}, Window(1, 1, 2, 2)),
}


@pytest.mark.process
@pytest.mark.parametrize("reason", FORGED)
def test_a_forged_update_is_refused_and_the_copy_goes_on(bus: Bus, reason: str) -> None:
    """One update that continues the copy (same epoch, map window, previous version) but whose
    cells do not fit its header froze every follower for 64 updates (13 s): kept for replay, it
    failed every replay before the genuine update of the same version could apply (without an
    occupancy array, each also logged an "on_change raised" traceback)."""
    first = _map(Window(0, 0, 2, 2), 0, version=0)
    queryable = bus.session.declare_queryable(
        "map/latest", lambda query: query.reply("map/latest", first.to_msgpack())
    )
    updates = bus.session.declare_publisher("map/updates", encoding=WIRE_ENCODING)
    changes: list[int] = []
    with _peer(bus) as session:
        follower = MapFollower(
            session, timeout_s=5, on_change=lambda m, _s: changes.append(m.version)
        )
        arrays, window = FORGED[reason]
        genuine = _map(first.window, 100, version=1)
        updates.put(_update(genuine, 0, arrays, window))
        wait_for(lambda: follower.rejected == {reason: 1}, 5, f"the update refused: {reason}")
        updates.put(_update(genuine, 0))
        wait_for(lambda: follower.map.revision == (EPOCH, 1), 5, "the genuine update applied")
        np.testing.assert_array_equal(follower.map.occupancy, genuine.occupancy)
        assert follower.callback_errors == 0 and changes == [1] and follower.alive
        follower.close()
    queryable.undeclare()  # type: ignore[no-untyped-call]


@pytest.mark.process
def test_an_update_that_does_not_step_the_version_forward_is_refused(bus: Bus) -> None:
    """An update from the copy's version to itself, well formed, matched itself on every pass of
    the replay, under the copy's lock: every reader of ``follower.map`` hung for good."""
    first = _map(Window(0, 0, 2, 2), 0, version=0)
    queryable = bus.session.declare_queryable(
        "map/latest", lambda query: query.reply("map/latest", first.to_msgpack())
    )
    updates = bus.session.declare_publisher("map/updates", encoding=WIRE_ENCODING)
    with _peer(bus) as session:
        follower = MapFollower(session, timeout_s=5)
        updates.put(_update(first, 0))  # version 0 after version 0
        wait_for(lambda: follower.rejected == {"version_order": 1}, 5, "the update refused")
        genuine = _map(first.window, 100, version=1)
        updates.put(_update(genuine, 0, final_version=0))  # a chain that ends before it
        wait_for(lambda: follower.rejected == {"version_order": 2}, 5, "that refused too")
        assert follower.map.version == 0 and follower.reached == (EPOCH, 0)
        updates.put(_update(genuine, 0))
        wait_for(lambda: follower.map.revision == (EPOCH, 1), 5, "the genuine update applied")
        follower.close()
    queryable.undeclare()  # type: ignore[no-untyped-call]


@pytest.mark.process
def test_the_copy_moves_only_to_the_end_of_a_chain(bus: Bus) -> None:
    """Fusion sends one change as a chain of updates (a group of chunks each): a copy that took
    each as it came was part new capture, part old (a mover drawn half where it was) for as
    long as the rest took, stamped with the new capture, and ``overgrid eval`` scored such
    copies. A chain whose end is lost is fetched past."""
    window = Window(0, 0, 4, 2)
    served = [_map(window, 0, version=0)]
    queryable = bus.session.declare_queryable(
        "map/latest", lambda query: query.reply("map/latest", served[-1].to_msgpack())
    )
    updates = bus.session.declare_publisher("map/updates", encoding=WIRE_ENCODING)
    left, right = Window(0, 0, 2, 2), Window(2, 0, 2, 2)
    changes: list[OccupancyMap] = []
    with _peer(bus) as session:
        follower = MapFollower(session, timeout_s=5, on_change=lambda m, _s: changes.append(m))

        def half(version: int, part: Window, value: int, final: int) -> bytes:
            cells = {"occupancy": np.full((2, 2), value, np.int8)}
            return _update(_map(window, 0, version), version - 1, cells, part, final)

        updates.put(half(1, left, 100, final=2))
        wait_for(lambda: follower.reached == (EPOCH, 1), 5, "the first half")
        time.sleep(0.3)
        assert follower.map.version == 0 and changes == [] and follower.refetches == 0
        updates.put(half(2, right, 100, final=2))
        wait_for(lambda: follower.map.version == 2, 5, "the chain's end")
        assert [m.version for m in changes] == [2]
        assert (changes[0].occupancy == 100).all()

        # Version 4, the end of the next chain, never arrives: the one after is fetched past.
        served.append(_map(window, 0, version=5))
        updates.put(half(3, left, 0, final=4))
        updates.put(half(5, right, 0, final=5))
        wait_for(lambda: follower.map.version == 5, 10, "the copy fetched past the lost end")
        assert [m.version for m in changes] == [2, 5] and (follower.map.occupancy == 0).all()

        # Version 7, the chain's end, is lost, and nothing comes after it (the map stands still):
        # the copy does not wait on the chain for ever, it fetches.
        served.append(_map(window, 100, version=7))
        updates.put(half(6, left, 100, final=7))
        wait_for(lambda: follower.map.version == 7, 10, "the copy fetched past a quiet lost end")
        assert [m.version for m in changes] == [2, 5, 7] and (follower.map.occupancy == 100).all()
        follower.close()
    queryable.undeclare()  # type: ignore[no-untyped-call]


@pytest.mark.process
def test_answers_that_do_not_decode_are_map_unavailable(bus: Bus) -> None:
    """The README's contract: every client call raises MapUnavailable. A map/health that is no
    JSON object raised JSONDecodeError (or RecursionError, nested deep), a map/latest of
    another wire version CodecError, from latest() and MapFollower() alike."""
    health_answers = ["not json", "[1, 2]", "NaN", "[" * 100_000 + "]" * 100_000]
    health_answer = [health_answers[0]]
    queryables = [
        bus.session.declare_queryable(
            "map/health", lambda query: query.reply("map/health", health_answer[0])
        ),
        bus.session.declare_queryable(
            "map/latest", lambda query: query.reply("map/latest", b"\x81\xa1v\x02")
        ),
        bus.session.declare_queryable(
            "map/objects", lambda query: query.reply("map/objects", b"[1, 2, 3]")
        ),
    ]
    with _peer(bus) as session:
        for answer in health_answers:
            health_answer[0] = answer
            with pytest.raises(MapUnavailable, match="map/health"):
                client.health(session, timeout_s=2)
        with pytest.raises(MapUnavailable, match="map/latest: wire version 2"):
            client.latest(session, timeout_s=2)
        with pytest.raises(MapUnavailable, match="map/latest: wire version 2"):
            MapFollower(session, timeout_s=2)
        with pytest.raises(MapUnavailable, match="map/objects"):
            client.objects(session, timeout_s=2)
    for queryable in queryables:
        queryable.undeclare()  # type: ignore[no-untyped-call]


def test_a_timeout_past_what_zenoh_takes_waits_instead() -> None:
    """``timeout_s=inf`` was Zenoh's "negative timeout" ValueError; each query now waits at most
    MAX_TIMEOUT_S (and asks again until ``timeout_s`` has passed)."""
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        session.declare_queryable("map/health", lambda query: query.reply("map/health", "{}"))
        assert client.health(session, timeout_s=float("inf")) == {}
