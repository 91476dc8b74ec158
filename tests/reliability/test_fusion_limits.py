"""Trust and limits at a real fusion process: the pair comes from the key, a future stamp locks
nobody out, a tile beyond the site's extent is refused at the edge (and a far first tile locks the
real site out of nothing, nor costs the saved map), growth past the cell limit is refused and never
saved, a flood is dropped and counted, and a second depth process claiming a pair is reported."""

import time
from pathlib import Path
from typing import Any, cast

import pytest
import zenoh

from common.client import health, latest
from common.codec import WIRE_ENCODING
from common.lattice import Window
from tests.conftest import Bus, fusion_answers, wait_for
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

W = Window(0, 0, 20, 20)


def _health(bus: Bus) -> dict[str, Any]:
    return health(bus.session, timeout_s=10)


def _start(bus: Bus, state_dir: Path, *extra: str, log_path: Path | None = None) -> None:
    bus.start("fusion", "--state-dir", str(state_dir), *extra, log_path=log_path)
    wait_for(lambda: fusion_answers(bus), 60, "fusion up")


def test_the_pair_is_the_keys_and_a_future_stamp_locks_nobody_out(bus: Bus, tmp_path: Path) -> None:
    _start(bus, tmp_path / "state")
    p0 = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    p1 = bus.session.declare_publisher("depth/p1/tile", encoding=WIRE_ENCODING)
    p1.put(tile_payload("p0", W, 1.0, seq=0))  # p1's credential speaking for p0
    p0.put(tile_payload("p0", W, 1.0, seq=1, stamp_ns=time.time_ns() + 1_500_000_000))
    wait_for(lambda: sum(_health(bus)["tiles_rejected"].values()) == 2, 10, "both refused")
    assert _health(bus)["tiles_rejected"] == {"pair": 1, "future": 1}
    p0.put(tile_payload("p0", W, 1.0, seq=2))  # p0's real next tile, stamped now
    wait_for(lambda: _health(bus)["tiles_accepted"] == 1, 10, "p0's real tile to land")
    answer = _health(bus)
    assert answer["pairs"]["p0"]["tiles"] == 1 and answer["pairs"]["p0"]["rejected"] == 1
    # The refusal is the key's pair's: p1 sent it, and contributed nothing.
    assert answer["pairs"]["p1"]["tiles"] == 0 and answer["pairs"]["p1"]["rejected"] == 1


def test_far_first_tiles_are_refused_and_the_real_map_survives_a_restart(
    bus: Bus, tmp_path: Path
) -> None:
    """A 1×1 tile at cell 2**62 was taken into an empty map as a 0×0 window, saved, and at the
    next start the saved map exceeded --max-cells: the whole state was set aside as corrupt. A
    first tile at cell 1e7 (500 km) made every real tile fail as growth, restart after restart."""
    args = ("--save-interval-s", "0.2")  # the default cell limit and extent
    _start(bus, tmp_path / "state", *args)
    p0 = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    p0.put(tile_payload("p0", Window(2**62, 2**62, 1, 1), 1.0, seq=0))
    p0.put(tile_payload("p0", Window(10**7, 10**7, 1, 1), 1.0, seq=1))
    wait_for(lambda: _health(bus)["tiles_rejected"].get("outside_extent") == 2, 10, "both refused")
    p0.put(tile_payload("p0", W, 3.0, seq=2))  # the real site
    wait_for(lambda: _health(bus)["tiles_accepted"] == 1, 10, "the real tile")
    wait_for(lambda: _health(bus)["state"]["saved_version"] >= 1, 10, "a save")
    bus.stop_all()
    _start(bus, tmp_path / "state", *args)
    restored = latest(bus.session)
    assert restored.window == Window(0, 0, 64, 64)
    assert restored.occupancy[W.slices_in(restored.window)].min() > 50  # the real tile's cells
    assert not list((tmp_path / "state").glob("*.corrupt-*"))


def test_growth_past_the_cell_limit_is_refused_counted_and_never_saved(
    bus: Bus, tmp_path: Path
) -> None:
    args = ("--save-interval-s", "0.2")  # the default --max-cells (25 M)
    _start(bus, tmp_path / "state", *args)
    p0 = bus.session.declare_publisher("depth/p0/tile", encoding=WIRE_ENCODING)
    p0.put(tile_payload("p0", W, 1.0, seq=0))
    wait_for(lambda: _health(bus)["tiles_accepted"] == 1, 10, "a first tile")
    # 750 m away: within the site's extent (1 km), but the map would need 226 M cells
    p0.put(tile_payload("p0", Window(15000, 15000, 1, 1), 1.0, seq=1))
    wait_for(lambda: _health(bus)["tiles_rejected"].get("growth") == 1, 10, "growth refused")
    p0.put(tile_payload("p0", Window(20, 0, 20, 20), 1.0, seq=2))  # the pair goes on
    wait_for(lambda: _health(bus)["tiles_accepted"] == 2, 10, "the next tile")
    assert latest(bus.session).window == Window(0, 0, 64, 64)
    time.sleep(0.5)  # a save or two
    bus.stop_all()
    _start(bus, tmp_path / "state", *args)
    assert latest(bus.session).window == Window(0, 0, 64, 64)  # the refused growth was not saved


def test_a_flood_is_dropped_and_counted_as_overload_and_queries_still_answer(
    bus: Bus, tmp_path: Path
) -> None:
    # One-megabyte messages: the inbox holds four of them while the map takes one.
    _start(bus, tmp_path / "state", "--max-message-mb", "1", "--max-tile-age-s", "60")
    p0 = bus.session.declare_publisher(
        "depth/p0/tile", encoding=WIRE_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
    )
    sent = 200
    big = Window(0, 0, 250, 250)  # 0.6 MB
    now_ns = time.time_ns()
    payloads = [tile_payload("p0", big, 0.1, seq=n, stamp_ns=now_ns + n) for n in range(sent)]
    for payload in payloads:  # encoded beforehand: they arrive faster than the map takes them
        p0.put(payload)

    def counted() -> int:
        answer = _health(bus)
        return cast(int, answer["tiles_accepted"] + sum(answer["tiles_rejected"].values()))

    wait_for(lambda: counted() == sent, 60, "every tile fused or counted")
    answer = _health(bus)
    print("accepted", answer["tiles_accepted"], "rejected", answer["tiles_rejected"])
    assert set(answer["tiles_rejected"]) == {"overload"}
    assert answer["tiles_accepted"] >= 1 and answer["tiles_rejected"]["overload"] >= 1
    assert latest(bus.session).value_at(1.0, 1.0) > 50


def test_two_processes_claiming_one_pair_are_reported(bus: Bus, tmp_path: Path) -> None:
    log_path = tmp_path / "fusion.log"
    _start(bus, tmp_path / "state", log_path=log_path)
    liveliness = bus.session.liveliness()
    first = liveliness.declare_token("depth/p0/alive/a1")
    wait_for(lambda: _health(bus)["pairs"].get("p0", {}).get("alive"), 10, "p0 alive")
    second = liveliness.declare_token("depth/p0/alive/b2")
    wait_for(lambda: _health(bus)["pairs"]["p0"]["conflict"], 10, "the conflict reported")
    assert _health(bus)["pairs"]["p0"]["processes"] == ["a1", "b2"]
    assert "a second depth process claims the pair" in log_path.read_text()
    first.undeclare()  # type: ignore[no-untyped-call]
    wait_for(lambda: not _health(bus)["pairs"]["p0"]["conflict"], 10, "one process left")
    assert _health(bus)["pairs"]["p0"]["alive"]  # alive while any of its processes is
    second.undeclare()  # type: ignore[no-untyped-call]
    wait_for(lambda: not _health(bus)["pairs"]["p0"]["alive"], 10, "p0 gone")
