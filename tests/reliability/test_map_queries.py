"""``map/latest`` asked what it cannot serve, of a real fusion process: every query gets one reply,
and a query the map cannot answer gets an error naming why, never silence or a silent 0×0 map."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from common import keys
from common.client import MapUnavailable, health, latest
from common.lattice import Window
from common.occupancy_map import OccupancyMap
from tests.conftest import Bus, wait_for
from tests.test_ros2_native import start_fusion_with_a_tile
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

TILE = Window(0, 0, 20, 20)
"""x, y ∈ [0, 1) m; the map grows in 64-cell chunks, so it covers [0, 3.2) m."""
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def ask(bus: Bus, parameters: str) -> tuple[bytes | None, str | None]:
    """The one reply to ``map/latest?parameters``: (payload, None) or (None, error text)."""
    replies = list(bus.session.get(f"{keys.MAP_LATEST}?{parameters}", timeout=5))
    assert len(replies) == 1, f"{len(replies)} replies to map/latest?{parameters}"
    reply = replies[0]
    if reply.ok is not None:
        return bytes(reply.ok.payload.to_bytes()), None
    assert reply.err is not None
    return None, reply.err.payload.to_string()


def test_an_empty_map_refuses_images_and_regions_and_serves_its_metadata(
    bus: Bus, tmp_path: Path
) -> None:
    bus.start("fusion", "--state-dir", str(tmp_path / "state"))
    wait_for(lambda: _answers(bus), 30, "fusion to answer map/health")
    for parameters in ("format=png", "format=pgm", "format=yaml", "region=0,0,1,1"):
        payload, error = ask(bus, parameters)
        assert payload is None and error is not None, parameters
        assert "no cells yet" in error, error
    payload, error = ask(bus, "format=msgpack")  # a follower starting first learns the version
    assert error is None and payload is not None
    assert OccupancyMap.from_msgpack(payload).occupancy.shape == (0, 0)


@pytest.mark.parametrize(
    ("parameters", "reason"),
    [
        ("format=png;region=100,100,101,101", "does not overlap the map"),
        ("region=100,100,101,101", "does not overlap the map"),
        ("format=pgm;region=-5,-5,-4,-4", "does not overlap the map"),
        ("format=png;region=-inf,0,1,1", "finite"),
        ("region=0,0,inf,1", "finite"),
        ("region=nan,0,1,1", "finite"),
        ("format=png;region=1,0,0,1", "x1 > x0"),
        ("region=a,b,c,d", "four numbers"),
        ("region=1,2,3", "four numbers"),
        ("layers=nonsense", "layers must be among"),
    ],
)
def test_what_the_map_cannot_answer_gets_an_error_naming_why(
    bus: Bus, tmp_path: Path, parameters: str, reason: str
) -> None:
    start_fusion_with_a_tile(bus, tmp_path, TILE)
    payload, error = ask(bus, parameters)
    assert payload is None and error is not None
    assert reason in error, error


def test_a_region_overlapping_the_map_is_served_cropped(bus: Bus, tmp_path: Path) -> None:
    start_fusion_with_a_tile(bus, tmp_path, TILE)
    png, error = ask(bus, "format=png;region=-10,-10,0.5,0.5")
    assert error is None and png is not None and png.startswith(PNG_MAGIC)
    part = latest(bus.session, region=(-10.0, -10.0, 0.5, 0.5), timeout_s=5)
    assert part.occupancy.shape == (10, 10) and (part.i0, part.j0) == (0, 0)


def test_the_last_seen_layer_holds_each_cells_capture_time(bus: Bus, tmp_path: Path) -> None:
    tiles = start_fusion_with_a_tile(bus, tmp_path, TILE)
    stamp_ns = time.time_ns()
    corner = Window(0, 0, 4, 4)
    tiles.put(tile_payload("p0", corner, 1.0, seq=10**12, stamp_ns=stamp_ns))

    def stamped() -> bool:
        layered = latest(bus.session, layers=("last_seen",), timeout_s=5)
        assert layered.last_seen_s is not None and layered.last_seen_s.dtype == np.float64
        return bool(layered.last_seen_s[0, 0] == pytest.approx(stamp_ns / 1e9, abs=1e-3))

    wait_for(stamped, 10, "the newer tile's capture time in the last_seen layer")
    layered = latest(bus.session, layers=("last_seen",), region=(0.0, 0.0, 1.5, 1.5), timeout_s=5)
    assert layered.last_seen_s is not None
    seen = layered.last_seen_s
    assert seen.shape == layered.occupancy.shape == (30, 30)
    assert np.all(seen[:4, :4] == pytest.approx(stamp_ns / 1e9, abs=1e-3))
    assert np.all(seen[:20, :20] > 0) and np.all(seen[20:, :] == 0) and np.all(seen[:, 20:] == 0)
    assert latest(bus.session, timeout_s=5).last_seen_s is None  # only when asked


def _answers(bus: Bus) -> bool:
    try:
        health(bus.session, timeout_s=1)
        return True
    except MapUnavailable:
        return False
