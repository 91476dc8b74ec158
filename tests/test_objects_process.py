"""A real fusion process fed one pair's detections over Zenoh serves them as tracked objects on
``map/objects``: queryable (msgpack and JSON) and a put per change."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common import keys
from common.client import MapUnavailable, objects, query_first
from common.codec import WIRE_ENCODING, decode, encode
from common.messages import (
    DETECTIONS_KIND,
    OBJECTS_KIND,
    DetectionRecord,
    DetectionsHeader,
    ObjectsHeader,
    TrackedObject,
)
from tests.conftest import REPO, Bus, wait_for

pytestmark = pytest.mark.process


def _detections(seq: int, stamp_ns: int) -> bytes:
    box = DetectionRecord(
        center_m=(3.0, 2.0), size_m=(0.8, 0.5), yaw_rad=0.3, top_m=1.1, points=900, partial=False
    )
    return encode(
        DETECTIONS_KIND, DetectionsHeader(pair="p0", seq=seq, stamp_ns=stamp_ns, detections=[box])
    )


def _tracked(bus: Bus) -> list[TrackedObject]:
    try:
        return list(objects(bus.session, timeout_s=2).objects)
    except MapUnavailable:
        return []


def test_fusion_serves_tracked_objects(bus: Bus, tmp_path: Path) -> None:
    bus.start("fusion", "--state-dir", str(tmp_path / "state"))
    puts: list[ObjectsHeader] = []
    subscriber = bus.session.declare_subscriber(
        keys.MAP_OBJECTS,
        lambda s: puts.append(decode(s.payload.to_bytes(), OBJECTS_KIND, ObjectsHeader).header),
    )
    publisher = bus.session.declare_publisher(keys.objects("p0"), encoding=WIRE_ENCODING)
    wait_for(lambda: bool(query_first(bus.session, keys.MAP_OBJECTS, 30)), 30, "map/objects")
    for seq in range(4):
        publisher.put(_detections(seq, time.time_ns()))
        time.sleep(0.3)
    wait_for(lambda: len(_tracked(bus)) == 1, 10, "one tracked object")
    (obj,) = _tracked(bus)
    assert obj.object_class == "static" and obj.size_m == (0.8, 0.5) and obj.pairs == ["p0"]
    assert obj.velocity_mps == (0.0, 0.0) and obj.detections >= 2

    people = json.loads(query_first(bus.session, keys.MAP_OBJECTS + "?format=json", 5))
    assert people["objects"][0]["class"] == "static"
    assert people["objects"][0]["id"] == obj.id
    wait_for(lambda: any(p.objects for p in puts), 5, "a put on map/objects")
    subscriber.undeclare()  # type: ignore[no-untyped-call]

    table = subprocess.run(
        [sys.executable, "-m", "services.cli", "objects", *bus.flags()],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert table.returncode == 0, table.stderr
    row = next(line for line in table.stdout.splitlines() if line.split()[:1] == [str(obj.id)])
    assert "static" in row and "0.800" in row and "p0" in row
