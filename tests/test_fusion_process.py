"""A real fusion process on loopback, fed hand-made tiles, queried by clients in other processes."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common import keys
from common.client import MapFollower, MapUnavailable, health, latest, latest_encoded
from common.codec import WIRE_ENCODING
from common.lattice import Window
from common.mapfiles import read_map_server
from common.occupancy_map import OccupancyMap
from common.png import decode_png
from tests.conftest import (
    REPO,
    Bus,
    assert_one_line_exit_2,
    fusion_answers,
    run_overgrid,
    wait_for,
)
from tests.tiles import put_until_fused, tile_arrays, tile_payload

pytestmark = pytest.mark.process

A, B = Window(0, 0, 40, 30), Window(30, 20, 40, 30)


def _start_fusion(bus: Bus, state_dir: Path) -> subprocess.Popen[bytes]:
    return bus.start(
        "fusion",
        "--state-dir",
        str(state_dir),
        "--save-interval-s",
        "1",
        "--publish-interval-s",
        "0.05",
    )


def _health(bus: Bus) -> dict[str, Any]:
    return health(bus.session, timeout_s=10)


def test_fusion_serves_map_and_health_and_survives_bad_tiles(bus: Bus, tmp_path: Path) -> None:
    fusion = _start_fusion(bus, tmp_path / "state")
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    other = bus.session.declare_publisher("depth/p1/tile", encoding=WIRE_ENCODING)
    wait_for(lambda: fusion_answers(bus), 30, "fusion to answer map/health")
    for seq in range(3):
        publisher.put(tile_payload("p0", A, 1.0, seq=seq, height_m=0.7))
        other.put(tile_payload("p1", B, -0.5, seq=seq))
        time.sleep(0.05)
    wait_for(lambda: _health(bus)["tiles_accepted"] == 6, 10, "six tiles accepted")

    # Bad tiles of every kind: each counted by reason, none crashes fusion.
    nan = tile_arrays(A, 0.1)
    nan["logodds"][0, 0] = np.inf
    bad = [
        b"\x00\x01garbage",
        tile_payload("p0", A, 0.1, resolution_m=0.1),
        tile_payload("p0", A, 0.1, arrays=tile_arrays(Window(0, 0, 3, 3), 0.1)),
        tile_payload("p0", A, 0.1, arrays=nan),
        tile_payload("p0", A, 0.1, stamp_ns=time.time_ns() - 60 * 10**9),
        tile_payload("p0", A, 0.1, stamp_ns=1_000),
    ]
    for payload in bad:
        publisher.put(payload)
    wait_for(
        lambda: sum(_health(bus)["tiles_rejected"].values()) == len(bad),
        10,
        "every bad tile counted",
    )
    rejected = _health(bus)["tiles_rejected"]
    assert rejected == {"malformed": 1, "resolution": 1, "dimensions": 1, "nan": 1, "stale": 2}
    pairs = _health(bus)["pairs"]  # and by the pair they came from
    assert (pairs["p0"]["rejected"], pairs["p1"]["rejected"]) == (6, 0)
    # A pair's refused detections are no refused tiles (a stall's stale ones read as such).
    bus.session.put(keys.objects("p0"), b"\x00\x01garbage")
    wait_for(lambda: _health(bus)["pairs"]["p0"]["detections_rejected"] == 1, 10, "the detections")
    assert _health(bus)["pairs"]["p0"]["rejected"] == 6
    publisher.put(tile_payload("p0", A, 1.0, seq=10, height_m=0.7))
    wait_for(
        lambda: _health(bus)["tiles_accepted"] == 7, 10, "a good tile to land after the bad ones"
    )
    # map/latest serves snapshots refreshed at most every publish interval: wait for the one with all 7 tiles.
    wait_for(
        lambda: latest(bus.session, timeout_s=10).version == 7, 10, "the snapshot of version 7"
    )

    occupancy_map = latest(bus.session, layers=("height", "logodds"), timeout_s=10)
    assert occupancy_map.resolution_m == 0.05 and occupancy_map.pairs == ["p0", "p1"]
    assert occupancy_map.value_at(0.3, 0.3) == 92  # 4 × +1.0 clamps at 2.5: p 0.924
    assert 0 <= occupancy_map.value_at(3.4, 2.4) <= 20  # only p1's free evidence
    overlap = occupancy_map.crop((1.55, 1.05, 1.95, 1.45))
    assert overlap.logodds is not None
    np.testing.assert_allclose(
        overlap.logodds, 2.5, atol=1e-6
    )  # exact stitching: 4·(+1) + 3·(-0.5)
    assert occupancy_map.value_at(-5.0, -5.0) == -1

    region = latest(bus.session, region=(0.0, 0.0, 1.0, 0.5), timeout_s=10)
    assert region.occupancy.shape == (10, 20) and (region.i0, region.j0) == (0, 0)
    png = decode_png(latest_encoded(bus.session, "png", timeout_s=10))
    assert png.ndim == 3 and png.shape[1] >= 800
    assert latest_encoded(bus.session, "pgm", timeout_s=10).startswith(b"P5\n")
    with pytest.raises(MapUnavailable, match="format 'jpg' not one of"):
        latest_encoded(bus.session, "jpg", timeout_s=10)

    # Another process (the CLI a person runs) gets the map too, as nav2 files.
    out = tmp_path / "out" / "map.yaml"
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "map", "get", "-o", str(out), *bus.flags()],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    meta, image = read_map_server(out)
    assert meta["resolution"] == 0.05 and image.shape == occupancy_map.occupancy.shape
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "health", *bus.flags()],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0 and "no save errors" in result.stdout
    rows = [line.split()[:4] for line in result.stdout.splitlines()]
    assert ["p0", "NO", "4", "6"] in rows and ["p1", "NO", "3", "0"] in rows  # tiles, rejected
    assert fusion.poll() is None


def test_restart_restores_the_map_and_version_never_goes_back(bus: Bus, tmp_path: Path) -> None:
    fusion = _start_fusion(bus, tmp_path / "state")
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    wait_for(lambda: fusion_answers(bus), 30, "fusion to start")
    for seq in range(5):
        publisher.put(tile_payload("p0", A, 0.9, seq=seq))
        time.sleep(0.05)
    wait_for(lambda: _health(bus)["tiles_accepted"] == 5, 10, "tiles accepted")
    before = latest(bus.session, layers=("logodds",), timeout_s=10)
    # A second service on the directory: its saves went into the same log, interleaved.
    second = run_overgrid("fusion", "--state-dir", str(tmp_path / "state"))
    assert_one_line_exit_2(second, "--state-dir", "in use by another fusion service (pid ")
    fusion.send_signal(signal.SIGTERM)
    assert fusion.wait(10) == 0
    # Another resolution: the log was set aside as corrupt, gone for the next start at 0.05 m.
    other = run_overgrid(
        "fusion", "--state-dir", str(tmp_path / "state"), "--grid.resolution-m", "0.1"
    )
    assert_one_line_exit_2(other, "--state-dir", "0.05 m cells", "0.1 m")

    _start_fusion(bus, tmp_path / "state")
    wait_for(lambda: fusion_answers(bus), 30, "fusion to restart")
    after = latest(bus.session, layers=("logodds",), timeout_s=10)
    assert after.version >= before.version
    np.testing.assert_array_equal(after.occupancy, before.occupancy)
    np.testing.assert_array_equal(after.logodds, before.logodds)
    publisher.put(tile_payload("p0", A, 0.9, seq=6))
    wait_for(
        lambda: latest(bus.session, timeout_s=10).version > after.version,
        10,
        "the version to move on",
    )


def test_follower_keeps_a_copy_current_from_updates(bus: Bus, tmp_path: Path) -> None:
    _start_fusion(bus, tmp_path / "state")
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    wait_for(lambda: fusion_answers(bus), 30, "fusion to start")
    publisher.put(tile_payload("p0", Window(0, 0, 64, 64), -0.4, seq=0))
    wait_for(lambda: latest(bus.session, timeout_s=10).version >= 1, 10, "a first map")
    changes: list[int] = []

    def robot_bug(changed: OccupancyMap, arrival_s: float) -> None:
        changes.append(changed.version)
        if len(changes) == 1:
            raise RuntimeError("a robot's own bug")  # it ended the follower's thread, silently

    follower = MapFollower(bus.session, timeout_s=10, on_change=robot_bug)
    for seq in range(1, 6):
        publisher.put(tile_payload("p0", Window(5 * seq, 5, 4, 4), 3.0, seq=seq))
        time.sleep(0.15)
    wait_for(
        lambda: latest(bus.session, timeout_s=10).version == follower.map.version,
        10,
        "the follower to catch up",
    )
    np.testing.assert_array_equal(
        follower.map.occupancy, latest(bus.session, timeout_s=10).occupancy
    )
    assert follower.applied >= 1 and follower.alive
    assert follower.callback_errors == 1 and len(changes) >= 2
    # A region as the robot gives it, to the last digit (":g" moved 0.2499999 to 0.25: a cell).
    region = (0.2499999, 0.1, 0.6, 0.4)
    assert latest(bus.session, region=region, timeout_s=10).window == (
        follower.map.crop(region).window
    )
    follower.close()
    follower.close()  # twice: no error
    assert not follower.alive


def test_updates_carry_the_changed_cells_not_their_bounding_box(bus: Bus, tmp_path: Path) -> None:
    """Small tiles at opposite corners of a 4928×4928 map, fused in one publish: a few small
    updates (one per group of changed chunks, chained by version), not the 24 MB rectangle
    between them; a follower replays them and stays equal to map/latest."""
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), "--publish-interval-s", "1")
    publisher = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    wait_for(lambda: fusion_answers(bus), 30, "fusion to start")
    publisher.put(tile_payload("p0", Window(0, 0, 20, 20), -1.0, seq=0))
    publisher.put(tile_payload("p0", Window(4900, 4900, 20, 20), -1.0, seq=1))
    corners = Window(0, 0, 4928, 4928)
    wait_for(lambda: latest(bus.session, timeout_s=10).window == corners, 10, "the grown map")
    follower = MapFollower(bus.session, timeout_s=10)
    wait_for(lambda: follower.map.window == corners, 10, "the follower's first map")
    refetches = follower.refetches
    sizes: list[int] = []
    updates = bus.session.declare_subscriber(
        "map/updates", lambda sample: sizes.append(len(sample.payload.to_bytes()))
    )
    time.sleep(0.3)  # the subscriber reaches fusion
    # The first tile after a quiet spell is published at once; the corners then wait for the next
    # publish, together.
    publisher.put(tile_payload("p0", Window(2400, 2400, 4, 4), 3.0, seq=2))
    publisher.put(tile_payload("p0", Window(2, 2, 4, 4), 3.0, seq=3))
    publisher.put(tile_payload("p0", Window(4910, 4910, 4, 4), 3.0, seq=4))
    wait_for(lambda: _health(bus)["tiles_accepted"] == 5, 10, "the tiles")

    def followed() -> bool:
        now = latest(bus.session, timeout_s=10)
        return bool(
            follower.map.revision == now.revision
            and follower.map.value_at(4910.1 * 0.05, 4910.1 * 0.05) > 50
        )

    wait_for(followed, 10, "the follower to reach map/latest")
    print("update sizes", sizes)
    assert 2 <= len(sizes) <= 3 and sum(sizes) < 20_000  # bytes; the bounding box: 24 MB
    np.testing.assert_array_equal(follower.map.occupancy, latest(bus.session).occupancy)
    assert follower.map.value_at(0.15, 0.15) > 50 and follower.map.value_at(120.1, 120.1) > 50
    assert follower.refetches == refetches  # the chain replayed as it came: nothing to fetch
    updates.undeclare()  # type: ignore[no-untyped-call]
    follower.close()


def test_a_stopped_fusion_does_not_forget_its_map_when_it_runs_again(
    bus: Bus, tmp_path: Path
) -> None:
    """A 20 s SIGSTOP (a paused VM, swap) made the whole map unknown at the first pass after
    it: its cells were old by the stop, with no camera at fault."""
    fusion = bus.start(
        "fusion", "--state-dir", str(tmp_path / "state"), "--publish-interval-s", "0.05"
    )
    wait_for(lambda: fusion_answers(bus), 30, "fusion to answer")
    put_until_fused(bus.session, bus.session)
    assert (latest(bus.session).occupancy >= 0).sum() > 0
    (pid,) = subprocess.run(
        ["pgrep", "-P", str(fusion.pid)], capture_output=True, text=True
    ).stdout.split()  # the service itself, not the `timeout` wrapping it
    os.kill(int(pid), signal.SIGSTOP)
    time.sleep(12.0)  # past decay_after_s (5 s), by as much again: decay would clear it
    os.kill(int(pid), signal.SIGCONT)
    time.sleep(1.5)  # a few of the loop's passes and snapshots
    assert (latest(bus.session, timeout_s=10).occupancy >= 0).sum() > 0
