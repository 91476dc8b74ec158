import time

import msgpack
import numpy as np
import pytest

from common.lattice import Window
from services.fusion.intake import TileGate, TileRejected
from tests.tiles import tile_arrays, tile_payload

W = Window(0, 0, 8, 6)


def _gate() -> TileGate:
    return TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=1_000_000)


def _reason(payload: bytes, gate: TileGate | None = None) -> str:
    with pytest.raises(TileRejected) as rejected:
        (gate or _gate()).admit(payload, time.time_ns())
    return rejected.value.reason


def test_good_tile_is_admitted() -> None:
    tile = _gate().admit(tile_payload("p0", W, 0.5), time.time_ns())
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


def test_oversized_message_is_rejected_before_decoding() -> None:
    gate = TileGate(resolution_m=0.05, max_age_s=2.0, max_bytes=100)
    assert _reason(tile_payload("p0", W, 0.5), gate) == "malformed"


def test_out_of_order_per_pair() -> None:
    gate = _gate()
    now = time.time_ns()
    gate.admit(tile_payload("p0", W, 0.5, stamp_ns=now), now)
    assert _reason(tile_payload("p0", W, 0.5, stamp_ns=now - 1000), gate) == "out_of_order"
    gate.admit(
        tile_payload("p1", W, 0.5, stamp_ns=now - 1000), now
    )  # another pair has its own order


def test_heights_may_be_nan_only_where_unobserved() -> None:
    arrays = tile_arrays(W, 0.0)
    arrays["count"][0, 0] = 0
    arrays["height_m"][0, 0] = np.nan
    _gate().admit(tile_payload("p0", W, 0.0, arrays=arrays), time.time_ns())
    arrays["height_m"][1, 1] = np.nan
    assert _reason(tile_payload("p0", W, 0.0, arrays=arrays)) == "nan"
