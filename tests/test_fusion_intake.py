import math
import time

import msgpack
import numpy as np
import pytest

from common.codec import encode
from common.lattice import Window
from common.messages import DETECTIONS_KIND, MAX_DETECTIONS, DetectionRecord, DetectionsHeader
from services.fusion.grid import GridParams
from services.fusion.intake import (
    FUTURE_TOLERANCE_S,
    HEIGHT_RANGE_M,
    Rejected,
    TileGate,
    decode_detections,
)
from tests.tiles import tile_arrays, tile_payload

W = Window(0, 0, 8, 6)


def _gate() -> TileGate:
    return TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=1_000_000)


def _reason(payload: bytes, gate: TileGate | None = None, key: str = "depth/p0/tile") -> str:
    with pytest.raises(Rejected) as rejected:
        (gate or _gate()).admit(payload, time.time_ns(), key)
    return rejected.value.reason


def _admit(gate: TileGate, payload: bytes, now_ns: int, key: str = "depth/p0/tile") -> None:
    gate.accepted(gate.admit(payload, now_ns, key))


def test_good_tile_is_admitted() -> None:
    tile = _gate().admit(tile_payload("p0", W, 0.5), time.time_ns(), "depth/p0/tile")
    assert tile.window == W and tile.logodds.shape == (6, 8)


def test_each_bad_kind_is_rejected_with_its_reason() -> None:
    assert _reason(b"\x93garbage") == "malformed"
    assert _reason(tile_payload("p0", W, 0.5)[:40]) == "malformed"
    assert _reason(msgpack.packb({"v": 1, "kind": "tile", "header": {"pair": 3}})) == "malformed"
    assert _reason(tile_payload("p0", W, 0.5, resolution_m=0.1)) == "resolution"
    wrong_shape = tile_arrays(Window(0, 0, 5, 5), 0.5)
    assert _reason(tile_payload("p0", W, 0.5, arrays=wrong_shape)) == "dimensions"
    nan = tile_arrays(W, 0.5)
    nan["logodds"][2, 3] = np.nan
    assert _reason(tile_payload("p0", W, 0.5, arrays=nan)) == "nan"
    assert _reason(tile_payload("p0", W, 0.5, stamp_ns=time.time_ns() - 10**10)) == "stale"
    huge = {
        "v": 1,
        "kind": "tile",
        "header": {
            "pair": "p0",
            "seq": 0,
            "stamp_ns": 1,
            "resolution_m": 0.05,
            "i0": 0,
            "j0": 0,
            "cols": 10**6,
            "rows": 10**6,
        },
        "arrays": {},
        "blobs": {},
    }
    assert _reason(msgpack.packb(huge)) == "malformed"


def test_the_hidden_layer_is_optional_and_checked_where_given() -> None:
    """A tile without the layer (an older depth service, another producer) hides nothing; one
    with it must hold 0/1 bytes of the tile's shape."""
    tile = _gate().admit(tile_payload("p0", W, 0.5), time.time_ns(), "depth/p0/tile")
    assert tile.hidden is None  # the grid integrates it with no cell hidden
    arrays = tile_arrays(W, 0.0, count=0)
    arrays["hidden"] = np.zeros(W.shape, np.uint8)
    arrays["hidden"][1, 2] = 1
    tile = _gate().admit(tile_payload("p0", W, 0.0, arrays=arrays), time.time_ns(), "depth/p0/tile")
    assert tile.hidden is not None
    assert tile.hidden.dtype == np.bool_ and tile.hidden.sum() == 1 and tile.hidden[1, 2]
    for bad, reason in (
        (np.zeros((2, 2), np.uint8), "dimensions"),
        (np.zeros(W.shape, np.float32), "dimensions"),
        (np.full(W.shape, 7, np.uint8), "hidden"),
    ):
        arrays["hidden"] = bad
        assert _reason(tile_payload("p0", W, 0.0, arrays=arrays)) == reason


def test_oversized_message_is_rejected_before_decoding() -> None:
    gate = TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=100)
    assert _reason(tile_payload("p0", W, 0.5), gate) == "malformed"


def test_out_of_order_per_pair() -> None:
    gate = _gate()
    now = time.time_ns()
    _admit(gate, tile_payload("p0", W, 0.5, stamp_ns=now), now)
    assert _reason(tile_payload("p0", W, 0.5, stamp_ns=now - 1000), gate) == "out_of_order"
    _admit(gate, tile_payload("p1", W, 0.5, stamp_ns=now - 1000), now, "depth/p1/tile")


def test_heights_may_be_nan_only_where_unobserved() -> None:
    arrays = tile_arrays(W, 0.0)
    arrays["count"][0, 0] = 0
    arrays["height_m"][0, 0] = np.nan
    _gate().admit(tile_payload("p0", W, 0.0, arrays=arrays), time.time_ns(), "depth/p0/tile")
    arrays["height_m"][1, 1] = np.nan
    assert _reason(tile_payload("p0", W, 0.0, arrays=arrays)) == "nan"


@pytest.mark.parametrize("height_m", [3e38, -3e38, HEIGHT_RANGE_M[1] + 1, HEIGHT_RANGE_M[0] - 1])
def test_an_observed_height_beyond_the_sites_range_is_refused(height_m: float) -> None:
    """±3e38 m tops were taken and served on the height layer; an unobserved cell's height is
    not looked at."""
    arrays = tile_arrays(W, 0.0)
    arrays["count"][0, 0] = 0
    arrays["height_m"][0, 0] = height_m
    _gate().admit(tile_payload("p0", W, 0.0, arrays=arrays), time.time_ns(), "depth/p0/tile")
    arrays["height_m"][1, 1] = height_m
    assert _reason(tile_payload("p0", W, 0.0, arrays=arrays)) == "height"


def test_the_pair_comes_from_the_key() -> None:
    """A p1 credential cannot speak for p0: the header must name the key's pair."""
    assert _reason(tile_payload("p0", W, 0.5), key="depth/p1/tile") == "pair"
    assert _reason(tile_payload("p0", W, 0.5), key="elsewhere") == "pair"


def test_a_tile_from_the_future_is_refused_and_does_not_lock_the_pair_out() -> None:
    gate = _gate()
    now = time.time_ns()
    ahead = tile_payload("p0", W, 0.5, stamp_ns=now + int((FUTURE_TOLERANCE_S + 1.5) * 1e9))
    assert _reason(ahead, gate) == "future"
    _admit(gate, tile_payload("p0", W, 0.5, stamp_ns=now), now)  # the pair's next real tile lands
    # Within the tolerance (clock skew between boxes) a tile is taken.
    _admit(gate, tile_payload("p0", W, 0.5, stamp_ns=now + int(FUTURE_TOLERANCE_S * 0.5e9)), now)


def test_a_stamp_is_kept_only_once_the_map_took_the_tile() -> None:
    gate = _gate()
    now = time.time_ns()
    gate.admit(tile_payload("p0", W, 0.5, stamp_ns=now), now, "depth/p0/tile")  # refused later
    _admit(gate, tile_payload("p0", W, 0.5, stamp_ns=now - 1000), now)


def test_a_tile_beyond_the_site_is_rejected_at_the_edge() -> None:
    site = GridParams().site_window()  # ±1 km around the origin
    gate = TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=1_000_000, site=site)
    for corner in (2**62, 10**7, -(10**7)):
        assert _reason(tile_payload("p0", Window(corner, corner, 1, 1), 1.0), gate) == (
            "outside_extent"
        )
    gate.admit(tile_payload("p0", Window(19_990, 0, 20, 5), 1.0), time.time_ns(), "depth/p0/tile")
    bounds = Window(0, 0, 100, 100)
    bounded = TileGate(0.05, 2.0, 1_000_000, site=bounds, bounded=True)
    assert _reason(tile_payload("p0", Window(500, 0, 5, 5), 1.0), bounded) == "outside_map"


def _detections() -> DetectionsHeader:
    return DetectionsHeader(
        pair="p0",
        seq=1,
        stamp_ns=time.time_ns(),
        detections=[
            DetectionRecord(
                center_m=(1.0, 2.0),
                size_m=(0.5, 0.4),
                yaw_rad=0.0,
                top_m=1.0,
                points=100,
                partial=False,
                outline_m=((0.8, 1.8), (1.2, 1.8), (1.2, 2.2)),
            )
        ],
    )


SITE = GridParams().site_window()  # ±1 km around the origin


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("outline_m", [(1.0, 2.0), (math.nan, 2.0), (1.5, 2.5)], "malformed"),  # not finite
        ("outline_m", [(0.01 * k, 0.0) for k in range(65)], "malformed"),  # too many vertices
        ("round", "banana", "malformed"),  # not a flag
        ("round", [True], "malformed"),
        ("low", "banana", "malformed"),
        ("top_m", math.nan, "malformed"),  # NaN in map/objects is not even JSON
        ("top_m", math.inf, "malformed"),
        ("size_m", [-3.0, -2.0], "malformed"),
        ("size_m", [0.5, 0.0], "malformed"),
        ("center_m", [1e300, -1e300], "outside_extent"),
        ("center_m", [1500.0, 2.0], "outside_extent"),
        ("size_m", [1e5, 1e5], "dimensions"),
        ("outline_m", [(1e6, 1e6), (1e6 + 0.5, 1e6), (1e6, 1e6 + 0.5)], "dimensions"),
        ("outline_m", [(1.0, 2.0), (5e4, 2.0), (1.0, 5e4)], "dimensions"),
        ("outline_m", [(1.0, 2.0)] * 3, "footprint"),  # one point: joined into a 0 × 0 object
        ("outline_m", [(0.8, 1.8), (1.0, 2.0), (1.2, 2.2)], "footprint"),  # on one line
        ("outline_m", [(0.8, 1.8), (1.2, 2.2)], "footprint"),
        ("yaw_rad", 1e308, "footprint"),  # averaged on the doubled circle: inf, then NaN
        ("yaw_rad", -0.1, "footprint"),
        ("yaw_rad", math.pi, "footprint"),
        ("top_m", 3e38, "height"),
        ("top_m", -3e38, "height"),
    ],
)
def test_detections_with_a_bad_value_are_rejected(field: str, value: object, reason: str) -> None:
    gate = TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=1_000_000, site=SITE)
    now_ns = time.time_ns()
    good = encode(DETECTIONS_KIND, _detections())
    assert decode_detections(good, "depth/p0/objects", now_ns, gate)
    envelope = msgpack.unpackb(good)
    envelope["header"]["detections"][0][field] = value  # all else as sent
    payload = msgpack.packb(envelope)
    with pytest.raises(Rejected) as rejected:
        decode_detections(payload, "depth/p0/objects", now_ns, gate)
    assert rejected.value.reason == reason


@pytest.mark.parametrize(
    ("camera", "reason"),
    [
        ([2.0, 3.0, 6.0], None),
        ([1500.0, 3.0, 6.0], None),  # a wall-mounted camera beside the site
        ([1e30, 3.0, 6.0], "camera"),  # a mover lifted toward it would be carried there
        ([2.0, 3.0, 0.0], "camera"),
        ([2.0, 3.0, 1e6], "camera"),
        ([2.0, math.inf, 6.0], "malformed"),
        ([2.0, 3.0], "malformed"),
    ],
)
def test_detections_say_where_their_camera_stands_over_the_site(
    camera: list[float], reason: str | None
) -> None:
    envelope = msgpack.unpackb(encode(DETECTIONS_KIND, _detections()))
    envelope["header"]["camera_m"] = camera
    payload = msgpack.packb(envelope)
    gate = TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=1_000_000, site=SITE)
    if reason is None:
        header = decode_detections(payload, "depth/p0/objects", time.time_ns(), gate)
        assert header.camera_m == tuple(camera)
        return
    with pytest.raises(Rejected) as rejected:
        decode_detections(payload, "depth/p0/objects", time.time_ns(), gate)
    assert rejected.value.reason == reason


def test_more_detections_than_a_frame_holds_are_rejected() -> None:
    """Thousands in one message (a broken or forged pair) stalled the tracker for minutes."""
    now_ns = time.time_ns()
    envelope = msgpack.unpackb(encode(DETECTIONS_KIND, _detections()))
    detections = envelope["header"]["detections"]
    envelope["header"]["detections"] = detections * MAX_DETECTIONS
    payload = msgpack.packb(envelope)
    assert decode_detections(payload, "depth/p0/objects", now_ns, _gate())
    envelope["header"]["detections"] = detections * (MAX_DETECTIONS + 1)
    with pytest.raises(Rejected) as rejected:
        decode_detections(msgpack.packb(envelope), "depth/p0/objects", now_ns, _gate())
    assert rejected.value.reason == "malformed"


def test_real_detections_past_the_trackers_size_or_the_bounds_edge_are_taken() -> None:
    """A box against the site's bounded edge (its outline 15 cm past it) and a trailer 13.6 m long
    (past the tracker's largest object, which it only never rasterises) were refused with every
    other detection of their frame: the checks against forged ones must keep real ones."""
    site = Window(0, 0, 400, 300)  # --bounds 0,0,20,15
    gate = TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=1_000_000, site=site, bounded=True)
    header = _detections()
    against_edge = header.detections[0].model_copy(
        update={
            "center_m": (19.7, 5.0),
            "size_m": (0.9, 0.5),
            "outline_m": ((19.25, 4.75), (20.15, 4.75), (20.15, 5.25), (19.25, 5.25)),
        }
    )
    trailer = header.detections[0].model_copy(
        update={"center_m": (10.0, 10.0), "size_m": (13.6, 2.5), "outline_m": ()}
    )
    header = header.model_copy(update={"detections": [*header.detections, against_edge, trailer]})
    payload = encode(DETECTIONS_KIND, header)
    assert len(decode_detections(payload, "depth/p0/objects", time.time_ns(), gate).detections) == 3
