"""10,000 fuzzed tiles at a real fusion process: none crashes it, each is counted by reason in
map/health, and good tiles sent among them still land. 10,000 fuzzed stereo frames at a real depth
process: it lives, and every frame is accounted for in depth/{pair}/health by outcome."""

import json
import random
import time
from collections import Counter
from functools import partial
from pathlib import Path
from typing import Any, cast

import cv2
import msgpack
import numpy as np
import pytest
import yaml
import zenoh

from common import keys
from common.client import health, latest
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.messages import STEREO_KIND, StereoFrameHeader
from services.camera_sim.rig import RigSpec, layout_pairs
from tests.conftest import Bus, fusion_answers, wait_for
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
    wait_for(lambda: fusion_answers(bus), 30, "fusion up")
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


FRAMES = 10_000
FRAME_SIZE = (160, 120)  # width, height: small frames keep 10,000 of them quick on loopback
BURST_FRAMES = 500
"""Frames sent before waiting for the process to have received them all."""
FRAME_LIMIT_MB = 0.4  # above every fuzzed frame of the right size (float64 ones: 0.3 MB)


def _frame(rng: np.random.Generator, kind: int, seq: int) -> tuple[str, bytes]:
    """One fuzzed stereo frame for pair p0 and the outcome the depth process must give it."""
    width, height = FRAME_SIZE
    texture = rng.integers(0, 256, (height, width), dtype=np.uint8)

    def raw(left: np.ndarray, right: np.ndarray | None = None, pair: str = "p0") -> bytes:
        header = StereoFrameHeader(pair=pair, seq=seq, stamp_ns=time.time_ns())
        return encode(
            STEREO_KIND, header, {"left": left, "right": left if right is None else right}
        )

    def blobs(encoding: str, blob: bytes) -> bytes:
        header = StereoFrameHeader(pair="p0", seq=seq, stamp_ns=time.time_ns(), encoding=encoding)
        return encode(STEREO_KIND, header, blobs={"left": blob, "right": blob})

    if kind == 0:
        return "ok", raw(texture)
    if kind == 1:
        return "ok", raw(texture.astype(np.uint16) << int(rng.integers(0, 9)))
    if kind == 2:
        return "malformed", rng.bytes(int(rng.integers(0, 2000)))
    if kind == 3:
        good = raw(texture)
        return "malformed", good[: int(rng.integers(0, len(good) - 1))]  # truncated
    if kind == 4:  # valid header, bad body: an array's bytes disagree with its shape, or are gone
        envelope = msgpack.unpackb(raw(texture), raw=False)
        if rng.random() < 0.5:
            envelope["arrays"]["left"]["shape"] = [height, width + 1]
        else:
            del envelope["arrays"]["right"]
        return "malformed", msgpack.packb(envelope)
    if kind == 5:  # a header field of the wrong type
        envelope = msgpack.unpackb(raw(texture), raw=False)
        envelope["header"]["seq"] = "seven"
        return "malformed", msgpack.packb(envelope)
    if kind == 6:
        dtype = rng.choice(["f4", "f8", "i1", "i2", "u4", "b1"])
        return "bad_pixels", raw(np.zeros((height, width), dtype))
    if kind == 7:
        channels = int(rng.choice([2, 5, 7]))
        return "bad_pixels", raw(np.zeros((height, width, channels), np.uint8))
    if kind == 8:
        shape = (int(rng.integers(1, 200)), int(rng.integers(1, 200)))
        if shape == (height, width):
            shape = (height + 1, width)
        return "wrong_size", raw(np.zeros(shape, np.uint8))
    if kind == 9:
        return "wrong_pair", raw(texture, pair="p1")
    if kind == 10:
        return "undecodable", blobs("jpeg", b"\xff\xd8" + rng.bytes(int(rng.integers(0, 500))))
    if kind == 11:  # a PNG header declaring a huge image over a few bytes
        bomb = bytearray(cv2.imencode(".png", texture)[1].tobytes())
        bomb[16:24] = int(rng.integers(10_000, 2**31)).to_bytes(4, "big") * 2
        return "wrong_size", blobs("png", bytes(bomb))
    return "oversize", rng.bytes(int(FRAME_LIMIT_MB * 1024 * 1024) + int(rng.integers(1, 5000)))


def test_fuzzed_stereo_frames_are_each_counted_and_the_depth_process_lives(
    bus: Bus, tmp_path: Path
) -> None:
    calib = layout_pairs(
        RigSpec(pair_count=1, width_px=FRAME_SIZE[0], height_px=FRAME_SIZE[1]), (12.0, 10.0)
    )[0]
    calib_file = tmp_path / "calib.yaml"
    calib_file.write_text(yaml.safe_dump(calib.model_dump(mode="json")))
    depth = bus.start(
        "depth",
        "--pair",
        "p0",
        "--calib",
        str(calib_file),
        "--max-message-mb",
        str(FRAME_LIMIT_MB),
        log_path=tmp_path / "depth.log",
    )

    def depth_health() -> dict[str, Any]:
        for reply in bus.session.get(keys.depth_health("p0"), timeout=5.0):
            if reply.ok is not None:
                return cast(dict[str, Any], json.loads(reply.ok.payload.to_string()))
        return {}

    def received_at_least(frames: int) -> bool:
        return cast(int, depth_health().get("received", 0)) >= frames

    wait_for(lambda: depth_health().get("state") == "running", 60, "the depth process up")
    publisher = bus.session.declare_publisher(
        keys.stereo("p0"),
        encoding=WIRE_ENCODING,
        congestion_control=zenoh.CongestionControl.BLOCK,  # every frame reaches the process
    )
    # "running" comes before the process's subscription reaches the router: frames put before
    # that go nowhere (3 of the first 500 once did).
    # (zenoh's stub types matching_status as a bool; it is a MatchingStatus snapshot.)
    matched = cast(Any, publisher)
    wait_for(lambda: bool(matched.matching_status.matching), 30, "the process's subscription")
    rng = np.random.default_rng(11)
    expected: Counter[str] = Counter()
    kinds = 13
    for seq in range(FRAMES):
        # Good frames one in six, so some are processed and some replaced while others wait.
        kind = 0 if seq % 6 == 0 else int(rng.integers(1, kinds))
        outcome, payload = _frame(rng, kind, seq)
        expected[outcome] += 1
        publisher.put(payload)
        if (seq + 1) % BURST_FRAMES == 0:
            # Bursts the process takes in: a put that Zenoh must hold back longer than its
            # wait_before_close (a loaded machine) closes the link and loses frames in transit,
            # before the process could count them.
            wait_for(partial(received_at_least, seq + 1), 60, f"{seq + 1} frames in")

    def accounted(health: dict[str, Any]) -> int:
        return cast(int, health["processed"] + health["skipped"] + sum(health["rejected"].values()))

    try:
        wait_for(lambda: accounted(depth_health()) >= FRAMES, 60, "every frame accounted for")
    except AssertionError as error:
        raise AssertionError(f"{error}; depth health: {depth_health()}") from None
    health = depth_health()
    print("depth health:", {k: health[k] for k in ("received", "processed", "skipped", "rejected")})
    print("expected:", dict(expected))
    assert depth.poll() is None
    assert health["received"] == FRAMES == accounted(health)
    assert health["rejected"] == {k: n for k, n in expected.items() if k != "ok"}
    assert health["processed"] + health["skipped"] == expected["ok"]
    assert health["processed"] >= 10 and health["tiles"] == health["processed"]
