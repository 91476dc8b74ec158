"""10,000 fuzzed tiles at a real fusion process: none crashes it, each is counted by reason in
map/health, and good tiles sent among them still land."""

import random
import time
from collections import Counter
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from common.client import health, latest
from common.codec import WIRE_ENCODING
from common.lattice import Window
from tests.conftest import Bus, wait_for
from tests.tiles import tile_arrays, tile_payload

pytestmark = pytest.mark.process

FUZZED = 10_000
W = Window(0, 0, 20, 20)


def _fuzzed(rng: random.Random, seq: int) -> tuple[str, bytes]:
    """One bad tile and the reason fusion must give for it."""
    kind = rng.randrange(7)
    good = tile_payload("p0", W, 0.5, seq=seq)
    if kind == 0:
        return "malformed", rng.randbytes(rng.randrange(1, 300))
    if kind == 1:
        return "malformed", good[: rng.randrange(1, len(good) - 1)]  # truncated
    if kind == 2:  # a field of the wrong type
        envelope = msgpack.unpackb(good, raw=False)
        envelope["header"]["cols"] = "twenty"
        return "malformed", msgpack.packb(envelope)
    if kind == 3:
        arrays = tile_arrays(W, 0.5)
        arrays["logodds"][rng.randrange(20), rng.randrange(20)] = np.nan
        return "nan", tile_payload("p0", W, 0.5, seq=seq, arrays=arrays)
    if kind == 4:  # the header claims far more cells than the arrays hold
        return "dimensions", tile_payload(
            "p0", Window(0, 0, 3000, 3000), 0.5, seq=seq, arrays=tile_arrays(W, 0.5)
        )
    if kind == 5:
        return "resolution", tile_payload("p0", W, 0.5, seq=seq, resolution_m=0.1)
    return "stale", tile_payload("p0", W, 0.5, seq=seq, stamp_ns=time.time_ns() - 3600 * 10**9)


def test_fuzzed_tiles_are_counted_by_reason_and_good_ones_land(bus: Bus, tmp_path: Path) -> None:
    # Ten thousand messages queue up: a generous age bound keeps the good tiles among them fresh.
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), "--max-tile-age-s", "120")
    wait_for(lambda: "map" in health(bus.session, timeout_s=5), 30, "fusion up")
    # BLOCK: on a burst, Zenoh's default drops; here every message must reach fusion to be counted.
    publisher, good_pub = (
        bus.session.declare_publisher(
            key, encoding=WIRE_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
        )
        for key in ("depth/p0/tile", "depth/p1/tile")
    )
    rng = random.Random(7)
    expected: Counter[str] = Counter()
    good_sent = 0
    for n in range(FUZZED):
        reason, payload = _fuzzed(rng, n)
        expected[reason] += 1
        publisher.put(payload)
        if n % 500 == 0:  # good tiles, from another pair, in the middle of the storm
            good_pub.put(tile_payload("p1", Window(100, 100, 10, 10), 1.0, seq=good_sent))
            good_sent += 1

    def counted() -> int:
        return sum(health(bus.session, timeout_s=5)["tiles_rejected"].values())

    wait_for(lambda: counted() >= FUZZED, 120, "every fuzzed tile counted")
    answer = health(bus.session, timeout_s=5)
    rejected = answer["tiles_rejected"]
    print("rejected by reason:", dict(rejected), "expected:", dict(expected))
    assert sum(rejected.values()) == FUZZED
    assert rejected["nan"] == expected["nan"] and rejected["resolution"] == expected["resolution"]
    assert rejected["stale"] == expected["stale"]
    assert rejected["malformed"] + rejected.get("dimensions", 0) == (
        expected["malformed"] + expected["dimensions"]
    )  # a header that contradicts its arrays fails decoding or the dimension check
    assert answer["tiles_accepted"] == good_sent
    assert latest(bus.session).value_at(5.2, 5.2) >= 65  # the good tiles made it occupied
