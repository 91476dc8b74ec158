"""SIGKILL of fusion while tiles stream: at most one second of tiles lost, the map's version
(epoch, counter) never goes backwards, and a follower that ran through it shows the new map."""

import time
from pathlib import Path

import numpy as np
import pytest

from common.client import MapFollower, health, latest
from common.codec import WIRE_ENCODING
from common.lattice import Window
from common.occupancy_map import OccupancyMap
from tests.conftest import Bus, fusion_answers, wait_for
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

SAVE_INTERVAL_S = 0.5
RATE_HZ = 20
CELL_M = 0.05


def _window(k: int) -> Window:
    """Tile k marks its own 4×4 cells: which tiles survived is read off the map."""
    return Window(4 * (k % 50), 4 * (k // 50), 4, 4)


def _landed(occupancy_map: OccupancyMap, k: int) -> bool:
    """Tile k's cells are in the map: observed (decay may have faded their occupancy since)."""
    w = _window(k)
    if occupancy_map.last_seen_s is None:
        return occupancy_map.value_at((w.i0 + 1.5) * CELL_M, (w.j0 + 1.5) * CELL_M) >= 65
    seen = occupancy_map.last_seen_s[w.slices_in(occupancy_map.window)]
    return bool((seen > 0).all())


def _layered(bus: Bus) -> OccupancyMap:
    return latest(bus.session, layers=("last_seen",), timeout_s=10)


def test_sigkill_loses_at_most_a_second_and_followers_see_the_new_map(
    bus: Bus, tmp_path: Path
) -> None:
    args = (
        "fusion",
        "--state-dir",
        str(tmp_path / "state"),
        "--save-interval-s",
        str(SAVE_INTERVAL_S),
        "--publish-interval-s",
        "0.05",
    )
    fusion = bus.start(*args)
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    wait_for(lambda: fusion_answers(bus), 60, "fusion up")
    publisher.put(tile_payload("p0", Window(0, 0, 200, 40), -1.0, seq=0))  # free floor
    wait_for(lambda: latest(bus.session).version >= 1, 10, "a first map")
    follower = MapFollower(bus.session, timeout_s=10)
    before_epoch = health(bus.session)["map"]["epoch"]

    sent_s: dict[int, float] = {}
    k = 0

    def stream(duration_s: float) -> None:
        nonlocal k
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            k += 1
            publisher.put(tile_payload("p0", _window(k), 3.0, seq=k))
            sent_s[k] = time.monotonic()
            time.sleep(1 / RATE_HZ)

    stream(3.0)
    served_before = latest(bus.session)
    bus.kill(fusion)
    killed_s = time.monotonic()
    last_before_kill = max(n for n, t in sent_s.items() if t < killed_s)
    stream(0.5)  # into the void: nobody fuses these

    bus.start(*args)
    wait_for(lambda: fusion_answers(bus), 60, "fusion back")
    restored = _layered(bus)
    answer = health(bus.session)
    assert answer["map"]["epoch"] > before_epoch
    assert restored.revision > served_before.revision  # never backwards, though its counter may be
    lost = [n for n in range(1, last_before_kill + 1) if not _landed(restored, n)]
    print(f"tiles lost by the kill: {lost} (sent {last_before_kill})")
    assert all(killed_s - sent_s[n] <= 1.0 for n in lost), "more than 1 s of tiles lost"

    first_after = k + 1
    stream(1.0)
    wait_for(
        lambda: _landed(_layered(bus), k),
        10,
        "tiles after the restart to land",
    )
    wait_for(
        lambda: follower.map.revision == latest(bus.session).revision,
        10,
        "the follower to follow the restarted fusion",
    )
    now = latest(bus.session)
    assert follower.map.epoch == now.epoch == answer["map"]["epoch"]
    np.testing.assert_array_equal(follower.map.occupancy, now.occupancy)  # no stale cells
    assert _landed(follower.map, first_after)
    follower.close()
