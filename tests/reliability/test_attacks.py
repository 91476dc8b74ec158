"""Attacks of issue 14 that no other reliability test covers, each against a real process."""

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from common.client import health, latest, objects
from common.codec import WIRE_ENCODING, encode
from common.lattice import Window
from common.messages import DETECTIONS_KIND, DetectionRecord, DetectionsHeader
from tests.conftest import Bus, assert_one_line_exit_2, fusion_answers, run_overgrid, wait_for
from tests.tiles import tile_payload

pytestmark = pytest.mark.process


@pytest.mark.parametrize("bounds", ["0,0,1e300,1e300", "1e19,0,1.00001e19,1", "-1e300,-1e300,0,0"])
def test_bounds_past_the_lattice_are_a_start_up_error(bounds: str) -> None:
    """1e300 m wrapped the int64 cell indices into a 0×0 window that passed the cell limit: fusion
    started with a map no tile could land in."""
    result = run_overgrid(
        "fusion",
        f"--bounds={bounds}",
        "--no-multicast-scouting",
        *("--namespace", "attacks-bounds", "--connect", "tcp/127.0.0.1:9"),
    )
    assert_one_line_exit_2(result, "--bounds")


@pytest.mark.parametrize(
    "args",
    [
        ("fusion", "--publish-interval-s", "1e300"),
        ("fusion", "--max-tile-age-s", "1e300"),
        ("fusion", "--save-interval-s", "1e300"),
        ("fusion", "--max-message-mb", "1e300"),
        ("fusion", "--max-message-mb", "1e-300"),
        ("fusion", "--grid.decay-after-s", "inf"),
        ("depth", "--pair", "p0", "--max-message-mb", "1e300"),
    ],
    ids=lambda args: " ".join(args[-2:]),
)
def test_a_period_or_limit_past_any_use_is_a_start_up_error(args: tuple[str, ...]) -> None:
    """A publish interval of 1e300 s started a fusion that never served its map; a tile age of
    1e300 s ended in an OverflowError traceback; a message limit of 1e300 MB was no limit."""
    result = run_overgrid(*args, "--no-multicast-scouting", "--connect", "tcp/127.0.0.1:9")
    assert_one_line_exit_2(result, args[-2].removeprefix("--grid."))


def _start_fusion(bus: Bus, tmp_path: Path) -> None:
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), log_path=tmp_path / "fusion.log")
    wait_for(lambda: fusion_answers(bus), 60, "fusion up")


def _health(bus: Bus) -> dict[str, Any]:
    return health(bus.session, timeout_s=10)


def _detection(**values: Any) -> DetectionRecord:
    box = {"center_m": (3.0, 2.0), "size_m": (0.8, 0.5), "yaw_rad": 0.0, "top_m": 1.0}
    return DetectionRecord(**{**box, "points": 100, "partial": False, **values})


def test_detections_that_broke_the_tracker_are_refused_by_reason_and_fusion_goes_on(
    bus: Bus, tmp_path: Path
) -> None:
    """Each valid by the message's schema: a yaw of 1e308 (averaged: NaN) killed fusion at the
    track's second view; two pairs' outlines of one point, joined, an object of size 0; outlines
    reaching 50 km, joined and rasterised, asked for terabytes; outlines at 10⁶ m put objects there
    in map/objects. Each is refused and counted; the pairs' real objects are tracked."""
    _start_fusion(bus, tmp_path)
    tokens = [bus.session.liveliness().declare_token(f"depth/{p}/alive/a{p}") for p in ("p0", "p1")]
    publishers = {
        p: bus.session.declare_publisher(f"depth/{p}/objects", encoding=WIRE_ENCODING)
        for p in ("p0", "p1")
    }
    forged = {
        "footprint": [
            _detection(yaw_rad=1e308),
            _detection(partial=True, outline_m=((5.0, 5.0),) * 3),
        ],
        "dimensions": [
            _detection(partial=True, outline_m=((5.0, 5.0), (5e4, 5.0), (5.0, 5e4))),
            _detection(partial=True, outline_m=((1e6, 1e6), (1e6 + 0.5, 1e6), (1e6, 1e6 + 0.5))),
            _detection(partial=True, size_m=(2500.0, 2500.0)),  # longer than the site
        ],
    }
    seq = 0

    def capture(*detections: DetectionRecord) -> None:
        nonlocal seq
        now_ns = time.time_ns()
        for pair, publisher in publishers.items():
            header = DetectionsHeader(
                pair=pair, seq=seq, stamp_ns=now_ns, detections=list(detections)
            )
            publisher.put(encode(DETECTIONS_KIND, header))
        seq += 1
        time.sleep(0.3)

    for _ in range(2):
        for bad in forged.values():
            for detection in bad:
                capture(detection)
    expected = {reason: 2 * 2 * len(bad) for reason, bad in forged.items()}  # twice, both pairs
    wait_for(lambda: _health(bus)["detections_rejected"] == expected, 10, "every one refused")
    for _ in range(4):
        capture(_detection())
    wait_for(lambda: len(objects(bus.session).objects) == 1, 10, "the real box tracked")
    (box,) = objects(bus.session).objects
    assert abs(box.center_m[0] - 3.0) < 0.01 and abs(box.center_m[1] - 2.0) < 0.01
    assert sorted(box.pairs) == ["p0", "p1"]
    assert _health(bus)["detections_rejected"] == expected  # nothing raised in the owner's loop
    for token in tokens:
        token.undeclare()  # type: ignore[no-untyped-call]


def test_a_tile_claiming_tops_no_camera_sees_is_refused(bus: Bus, tmp_path: Path) -> None:
    """Tops of ±3e38 m were taken and served on the height layer."""
    _start_fusion(bus, tmp_path)
    p0 = bus.session.declare_publisher(
        "depth/p0/tile", encoding=WIRE_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
    )
    now_ns = time.time_ns()
    for n, height_m in enumerate((3e38, -3e38, 1.2)):
        p0.put(tile_payload("p0", Window(20 * n, 0, 20, 20), 1.0, n, now_ns + n, height_m=height_m))

    def counted() -> int:
        answer = _health(bus)
        return int(answer["tiles_accepted"] + sum(answer["tiles_rejected"].values()))

    wait_for(lambda: counted() == 3, 10, "every tile fused or refused")
    assert _health(bus)["tiles_accepted"] == 1
    assert _health(bus)["tiles_rejected"] == {"height": 2}
    heights = latest(bus.session, layers=("height",)).height_m
    assert heights is not None
    np.testing.assert_allclose(heights[np.isfinite(heights)], 1.2)


def test_a_wildcard_query_gets_each_answer_on_its_own_key(bus: Bus, tmp_path: Path) -> None:
    """Fusion answered on the query's key: a get of map/* took one reply, keyed map/*, of three."""
    _start_fusion(bus, tmp_path)
    for selector in ("map/*", "**"):
        replies = list(bus.session.get(selector, timeout=5.0))
        answered = sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)
        assert answered == ["map/health", "map/latest", "map/objects"], selector
