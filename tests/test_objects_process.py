"""A real fusion process fed one pair's detections over Zenoh serves them as tracked objects on
``map/objects``: queryable (msgpack and JSON) and a put per change."""

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common import keys
from common.client import MapFollower, MapUnavailable, health, latest, objects, query_first
from common.codec import WIRE_ENCODING, decode, encode
from common.lattice import Window
from common.mapfiles import FREE_MAX
from common.messages import (
    DETECTIONS_KIND,
    OBJECTS_KIND,
    DetectionRecord,
    DetectionsHeader,
    ObjectsHeader,
    TrackedObject,
)
from common.occupancy_map import OccupancyMap
from tests.conftest import REPO, Bus, wait_for
from tests.tiles import tile_arrays, tile_payload

pytestmark = pytest.mark.process


def _detections(seq: int, stamp_ns: int) -> bytes:
    box = DetectionRecord(
        center_m=(3.0, 2.0), size_m=(0.8, 0.5), yaw_rad=0.3, top_m=1.1, points=900, partial=False
    )
    return encode(
        DETECTIONS_KIND, DetectionsHeader(pair="p0", seq=seq, stamp_ns=stamp_ns, detections=[box])
    )


def _mover(seq: int, stamp_ns: int, x_m: float) -> bytes:
    """p0's detections of a frame: a 1.2 × 0.8 m box centred at (x_m, 2.0), 1.1 m tall."""
    box = DetectionRecord(
        center_m=(x_m, 2.0), size_m=(1.2, 0.8), yaw_rad=0.0, top_m=1.1, points=900, partial=False
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


def test_a_static_objects_footprint_is_served_occupied(bus: Bus, tmp_path: Path) -> None:
    """Frames that read a box's rim free (its tile: occupied 3 cm inside its outline, free
    elsewhere and in one cell at its centre, a plain top read as floor) do not make its rim free
    in the map once its track is static: the cells whose centres its measured footprint holds
    are served occupied, in the predicted layer, but for its edge's (centres within half a cell
    inside it) that the frames call free, served unknown; so are those within a centimetre
    outside it (its rim, within the footprint's error). An object the frames call free (a floor
    marking tracked for a while) is not outlined: its footprint is served unknown, neither an
    obstacle nor free floor; the floor around both stays free. Once the pair stops, both go
    with the cells' evidence."""
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), "--publish-interval-s", "0.05")
    tiles = bus.session.declare_publisher(keys.tile("p0"), encoding=WIRE_ENCODING)
    detections = bus.session.declare_publisher(keys.objects("p0"), encoding=WIRE_ENCODING)
    wait_for(lambda: bool(query_first(bus.session, keys.MAP_OBJECTS, 30)), 30, "map/objects")
    floor = Window(0, 0, 100, 80)  # 5 × 4 m
    x, y = floor.cell_centers(0.05)
    c, s = math.cos(0.3), math.sin(0.3)
    along, across = c * (x - 3.0) + s * (y - 2.0), -s * (x - 3.0) + c * (y - 2.0)
    inside = (np.abs(along) <= 0.4) & (np.abs(across) <= 0.25)
    rim = (np.abs(along) <= 0.41) & (np.abs(across) <= 0.26) & ~inside
    core = (np.abs(along) <= 0.37) & (np.abs(across) <= 0.22)
    arrays = tile_arrays(floor, -1.0)
    arrays["logodds"][core] = 1.0
    plain = (np.abs(x - 3.025) < 0.01) & (np.abs(y - 2.025) < 0.01)
    arrays["logodds"][plain] = -1.0
    marking = DetectionRecord(
        center_m=(1.0, 0.5), size_m=(1.0, 0.2), yaw_rad=0.0, top_m=0.15, points=300, partial=False
    )
    started = time.time()
    seq = 0
    while time.time() - started < 4.5:  # a track is static after 3 s in place
        stamp_ns = time.time_ns()
        tiles.put(tile_payload("p0", floor, 0.0, seq=seq, stamp_ns=stamp_ns, arrays=arrays))
        header = DetectionsHeader.model_validate(
            decode(_detections(seq, stamp_ns), DETECTIONS_KIND, DetectionsHeader).header
        )
        both = header.model_copy(update={"detections": [*header.detections, marking]})
        detections.put(encode(DETECTIONS_KIND, both))
        seq += 1
        time.sleep(0.3)

    def served() -> OccupancyMap:
        return latest(bus.session, layers=("predicted",), timeout_s=5)

    def outlined() -> bool:
        layer = served().predicted
        return layer is not None and bool(layer.any())

    wait_for(outlined, 10, "the footprint in the predicted layer")
    grid = served()
    # The list is of the map's epoch (ids restart with a new one) and the box has settled.
    listed = objects(bus.session, timeout_s=5)
    assert listed.epoch == grid.epoch > 0
    assert all(o.settled and o.object_class == "static" for o in listed.objects)
    assert grid.predicted is not None
    where = floor.slices_in(grid.window)
    occupancy, predicted = grid.occupancy[where], grid.predicted[where]
    inside_m = np.minimum(0.4 - np.abs(along), 0.25 - np.abs(across))
    edge_free = inside & ~core & (inside_m < 0.025)  # the edge cells the frames call free
    held = inside & ~edge_free
    assert edge_free.sum() > 20 and plain.sum() == 1 and held[plain].all()
    assert predicted[held].all() and (occupancy[held] == 100).all()
    assert not predicted[edge_free].any() and (occupancy[edge_free] == -1).all()
    marked = (np.abs(x - 1.0) <= 0.5) & (np.abs(y - 0.5) <= 0.1)
    marked_core = (np.abs(x - 1.0) <= 0.45) & (np.abs(y - 0.5) <= 0.05)
    assert not predicted[~inside].any()
    assert (occupancy[marked_core] == -1).all()  # contested: unknown
    assert rim.any() and (occupancy[rim] == -1).all()  # contested: unknown
    elsewhere = ~inside & ~rim & ~marked
    free = (occupancy[elsewhere] >= 0) & (occupancy[elsewhere] <= 25)  # map.yaml's free_thresh
    assert free.all()
    # The pair stops: as its cells decay unknown (5 s unseen), the outline and the track go too
    # (they stayed, obstacles on an unknown map and a list of objects 50 s old).
    assert _tracked(bus)
    wait_for(lambda: not outlined() and not _tracked(bus), 20, "outline and track forgotten")
    assert not (served().occupancy == 100).any()


def test_a_movers_top_is_served_occupied_until_captures_stop(bus: Bus, tmp_path: Path) -> None:
    """A box 1.2 × 0.8 m crossing a corridor the tiles never measure (its plain top gives the
    matcher nothing) at 2 m/s: once its track moves, its top, 10 cm inside its newest view, is in
    the predicted layer and served occupied; the cells it left are not. When the pair stops
    sending, the top goes within ``sweep_max_s`` (1.5 s): no ghost of a mover stays in the map."""
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), "--publish-interval-s", "0.05")
    tiles = bus.session.declare_publisher(keys.tile("p0"), encoding=WIRE_ENCODING)
    detections = bus.session.declare_publisher(keys.objects("p0"), encoding=WIRE_ENCODING)
    wait_for(lambda: bool(query_first(bus.session, keys.MAP_OBJECTS, 30)), 30, "map/objects")
    floor = Window(0, 0, 120, 80)  # 6 × 4 m
    arrays = tile_arrays(floor, -1.0)
    corridor = np.zeros(floor.shape, np.bool_)
    corridor[32:48] = True  # y 1.6–2.4: never measured
    arrays["count"][corridor] = 0
    arrays["logodds"][corridor] = 0.0
    x_m = 1.0
    for seq in range(8):
        stamp_ns = time.time_ns()
        x_m = 1.0 + 0.6 * seq
        tiles.put(tile_payload("p0", floor, 0.0, seq=seq, stamp_ns=stamp_ns, arrays=arrays))
        detections.put(_mover(seq, stamp_ns, x_m))
        time.sleep(0.3)
    top = (int(2.0 / 0.05), int(x_m / 0.05))  # (row, col) of the box's centre now
    left = (int(2.0 / 0.05), int((x_m - 1.2) / 0.05))  # its centre two captures before

    def at(cell: tuple[int, int]) -> tuple[bool, int]:
        grid = latest(bus.session, layers=("predicted",), timeout_s=5)
        assert grid.predicted is not None
        row, col = cell[0] - grid.window.j0, cell[1] - grid.window.i0
        return bool(grid.predicted[row, col]), int(grid.occupancy[row, col])

    wait_for(lambda: at(top) == (True, 100), 1.0, "the top of the newest view occupied")
    assert at(left) == (False, -1)
    assert [(t.object_class, t.settled) for t in _tracked(bus)] == [("moving", False)]
    wait_for(lambda: at(top) == (False, -1), 10, "the top gone once captures stopped")


def test_a_capture_is_published_with_its_objects(bus: Bus, tmp_path: Path) -> None:
    """Depth sends a frame's tile first and its detections once measured (15–50 ms later live;
    0.3 s here). A box crossing measured floor whose plain top gives no reading: published as
    soon as the tile came, the map served the floor the box had just driven onto free (the
    tracks, and the cells they contest, were still the capture's before), 1.3 % of the
    obstacles' cells live on a plain floor. Every version of a capture's stamp comes with its
    objects: the box's new centre is never free in it."""
    bus.start("fusion", "--state-dir", str(tmp_path / "state"), "--publish-interval-s", "0.02")
    tiles = bus.session.declare_publisher(keys.tile("p0"), encoding=WIRE_ENCODING)
    detections = bus.session.declare_publisher(keys.objects("p0"), encoding=WIRE_ENCODING)
    alive = bus.session.liveliness().declare_token("depth/p0/alive/test")  # as a depth process
    wait_for(lambda: bool(query_first(bus.session, keys.MAP_OBJECTS, 30)), 30, "map/objects")
    wait_for(lambda: "p0" in health(bus.session, timeout_s=2)["pairs"], 10, "p0's token seen")
    floor = Window(0, 0, 120, 80)  # 6 × 4 m, measured free but where the box stands
    tiles.put(tile_payload("p0", floor, -3.0, seq=0, stamp_ns=time.time_ns() - 10**9))

    def free_at(x_m: float) -> bool:
        return 0 <= latest(bus.session, timeout_s=5).value_at(x_m, 2.0) <= FREE_MAX

    wait_for(lambda: free_at(3.0), 10, "free floor")
    maps: list[OccupancyMap] = []
    follower = MapFollower(bus.session, timeout_s=10, on_change=lambda m, _s: maps.append(m))
    centres: dict[int, float] = {}
    for seq in range(1, 7):
        stamp_ns, x_m = time.time_ns(), 0.8 + 0.6 * seq
        arrays = tile_arrays(floor, -1.0)
        box = (slice(32, 48), slice(int((x_m - 0.6) / 0.05), int((x_m + 0.6) / 0.05)))
        arrays["count"][box], arrays["logodds"][box] = 0, 0.0  # its plain top: no reading
        tiles.put(tile_payload("p0", floor, 0.0, seq=seq, stamp_ns=stamp_ns, arrays=arrays))
        time.sleep(0.3)
        detections.put(_mover(seq, stamp_ns, x_m))
        centres[stamp_ns] = x_m
        time.sleep(0.2)
    follower.close()
    alive.undeclare()  # type: ignore[no-untyped-call]
    shown = [(centres[m.stamp_ns], m.value_at(centres[m.stamp_ns], 2.0)) for m in maps[1:]]
    assert len({x for x, _ in shown}) >= 5  # the captures were followed
    assert not any(0 <= value <= FREE_MAX for _, value in shown), shown
