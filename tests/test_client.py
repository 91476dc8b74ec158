"""The robot client's MapFollower against a map service whose ``map/latest`` lags its
``map/updates`` (fusion builds snapshots at a pace; updates go out at once): the follower must
reach the newest version even when the stream goes quiet right after an update it cannot replay."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zenoh

from common.client import MapFollower, MapUnavailable, latest
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.messages import MAP_UPDATE_KIND, MapUpdateHeader
from common.occupancy_map import OccupancyMap
from tests.conftest import Bus, wait_for

RESOLUTION_M = 0.05
EPOCH = 1_000


def _map(window: Window, value: int, version: int) -> OccupancyMap:
    cells = np.full((window.rows, window.cols), value, np.int8)
    return OccupancyMap(cells, RESOLUTION_M, window.i0, window.j0, version, 0, epoch=EPOCH)


def _update(grown: OccupancyMap, previous_version: int) -> bytes:
    w = grown.window
    header = MapUpdateHeader(
        version=grown.version,
        previous_version=previous_version,
        epoch=EPOCH,
        stamp_ns=0,
        resolution_m=RESOLUTION_M,
        i0=w.i0,
        j0=w.j0,
        cols=w.cols,
        rows=w.rows,
        map_i0=w.i0,
        map_j0=w.j0,
        map_cols=w.cols,
        map_rows=w.rows,
    )
    return encode(MAP_UPDATE_KIND, header, {"occupancy": grown.occupancy})


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
    grown = _map(Window(10, 20, 30, 40), 100, version=1)
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
        served.append(grown)
        # One update that grows the map, then silence: no later update will trigger a fetch. (The
        # follower's subscription reached the router before its fetch did, on the same link.)
        updates.put(_update(grown, 0))
        wait_for(lambda: follower.map.revision == (EPOCH, 1), 10, "the follower to catch up")
        assert stale_answers_left == [0]  # it did meet the stale snapshots on its way
        np.testing.assert_array_equal(follower.map.occupancy, grown.occupancy)
        assert follower.map.window == grown.window
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
