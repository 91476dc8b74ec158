"""Processes die mid-stream: the map keeps being served, the dead pair is seen as dead and forgotten,
and what restarts rejoins by itself; a killed fusion comes back with its map."""

import time
from pathlib import Path

import pytest

from common.client import health, latest
from common.codec import WIRE_ENCODING
from common.lattice import Window
from tests.conftest import Bus, fusion_answers, wait_for
from tests.tiles import tile_payload

pytestmark = pytest.mark.process


def _alive(bus: Bus, pair: str) -> bool:
    return bool(health(bus.session, timeout_s=5)["pairs"].get(pair, {}).get("alive"))


def test_sigkilled_depth_is_dead_within_2_s_decays_and_rejoins(bus: Bus, tmp_path: Path) -> None:
    bus.start(
        "fusion",
        "--state-dir",
        str(tmp_path / "state"),
        "--decay-after-s",
        "1",
        "--decay-time-constant-s",
        "0.5",
    )
    bus.start("camera-sim", "--pair-count", "2", "--pairs", "p0", "--rate-hz", "2")
    depth = bus.start("depth", "--pair", "p0")
    # Three processes start on two cores: fusion's first answer took over 5 s in a full run.
    wait_for(lambda: fusion_answers(bus), 60, "fusion to answer")
    wait_for(lambda: _alive(bus, "p0"), 60, "p0 alive")
    wait_for(lambda: (latest(bus.session).occupancy >= 0).sum() > 5000, 60, "p0's cells known")

    bus.kill(depth)
    killed_at = time.monotonic()
    wait_for(lambda: not _alive(bus, "p0"), 10, "p0 reported dead")
    assert time.monotonic() - killed_at <= 2.0  # liveliness, not a timeout, tells fusion
    served = latest(bus.session)  # the map is still served
    assert served.version > 0
    wait_for(
        lambda: (latest(bus.session).occupancy >= 0).sum() == 0, 30, "p0's cells decay to unknown"
    )

    bus.start("depth", "--pair", "p0")  # same pair, new process: rejoins with no one's help
    wait_for(lambda: _alive(bus, "p0"), 60, "p0 alive again")
    wait_for(lambda: (latest(bus.session).occupancy >= 0).sum() > 5000, 60, "p0's cells again")

    # A new pair while running: one more camera and one more depth process, nothing restarted.
    before = latest(bus.session)
    bus.start("camera-sim", "--pair-count", "2", "--pairs", "p1", "--rate-hz", "2")
    bus.start("depth", "--pair", "p1")
    wait_for(lambda: _alive(bus, "p1"), 60, "p1 alive")
    # p1's tiles are used as they arrive: the map names it and grows over its view (p0's own
    # tiles may grow the map too, so the growth alone says nothing of p1).
    wait_for(lambda: "p1" in latest(bus.session).pairs, 60, "p1's tiles in the map")
    wait_for(
        lambda: latest(bus.session).window.union(before.window) != before.window,
        60,
        "the map to grow over p1's view",
    )


def test_sigkilled_fusion_restarts_with_its_map(bus: Bus, tmp_path: Path) -> None:
    state = tmp_path / "state"
    args = ("fusion", "--state-dir", str(state), "--save-interval-s", "1")
    fusion = bus.start(*args)
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    wait_for(lambda: fusion_answers(bus), 30, "fusion up")
    for seq in range(20):
        window = Window(seq * 10, 0, 10, 10)
        publisher.put(tile_payload("p0", window, 1.0, seq=seq))
        time.sleep(0.05)
    wait_for(lambda: latest(bus.session).version >= 20, 10, "all tiles fused")
    before = latest(bus.session)
    time.sleep(1.5)  # one save interval: the state on disk now holds every tile
    bus.kill(fusion)

    bus.start(*args)
    wait_for(lambda: fusion_answers(bus), 30, "fusion back")
    after = latest(bus.session)
    assert after.version >= before.version  # never goes backwards
    assert (after.occupancy == before.occupancy).all()  # nothing lost beyond one save interval
    publisher.put(tile_payload("p0", Window(0, 20, 10, 10), 1.0, seq=21))
    wait_for(lambda: latest(bus.session).version > after.version, 10, "new tiles after restart")
