import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.codec import CodecError, decode, encode
from common.messages import (
    STEREO_KIND,
    TILE_KIND,
    MapHeader,
    ObjectsHeader,
    StereoFrameHeader,
    TileHeader,
)


def _frame() -> bytes:
    header = StereoFrameHeader(pair="p0", seq=7, stamp_ns=123, encoding="raw")
    left = np.arange(12, dtype=np.uint8).reshape(3, 4)
    return encode(STEREO_KIND, header, {"left": left, "right": left[::-1]})


def test_round_trip_keeps_header_and_arrays() -> None:
    message = decode(_frame(), STEREO_KIND, StereoFrameHeader)
    assert message.header.seq == 7 and message.header.pair == "p0"
    np.testing.assert_array_equal(
        message.arrays["left"], np.arange(12, dtype=np.uint8).reshape(3, 4)
    )
    np.testing.assert_array_equal(
        message.arrays["right"], np.arange(12, dtype=np.uint8).reshape(3, 4)[::-1]
    )


def test_float_arrays_with_nan_round_trip() -> None:
    header = TileHeader(
        pair="p1", seq=0, stamp_ns=1, resolution_m=0.05, i0=-3, j0=4, cols=2, rows=1
    )
    heights = np.array([[np.nan, 1.5]], dtype=np.float32)
    message = decode(encode(TILE_KIND, header, {"height_m": heights}), TILE_KIND, TileHeader)
    assert message.header.i0 == -3
    np.testing.assert_array_equal(message.arrays["height_m"], heights)


def test_truncated_message_is_rejected() -> None:
    payload = _frame()
    with pytest.raises(CodecError, match="msgpack"):
        decode(payload[: len(payload) // 2], STEREO_KIND, StereoFrameHeader)


def test_oversized_message_is_rejected_before_decoding() -> None:
    with pytest.raises(CodecError, match="exceeds the limit"):
        decode(_frame(), STEREO_KIND, StereoFrameHeader, max_bytes=64)


def test_wrong_kind_and_wrong_header_types_are_rejected() -> None:
    with pytest.raises(CodecError, match="kind"):
        decode(_frame(), TILE_KIND, TileHeader)
    bad = msgpack.packb(
        {
            "v": 1,
            "kind": STEREO_KIND,
            "header": {"pair": "p0", "seq": "x", "stamp_ns": 1},
            "arrays": {},
            "blobs": {},
        }
    )
    with pytest.raises(CodecError, match="seq"):
        decode(bad, STEREO_KIND, StereoFrameHeader)


def test_array_whose_bytes_disagree_with_shape_is_rejected() -> None:
    bad = msgpack.packb(
        {
            "v": 1,
            "kind": STEREO_KIND,
            "header": {"pair": "p0", "seq": 1, "stamp_ns": 1},
            "arrays": {"left": {"dtype": "|u1", "shape": [1000, 1000], "data": b"abc"}},
            "blobs": {},
        }
    )
    with pytest.raises(CodecError, match="needs 1000000 bytes"):
        decode(bad, STEREO_KIND, StereoFrameHeader)


def test_disallowed_dtype_is_rejected() -> None:
    bad = msgpack.packb(
        {
            "v": 1,
            "kind": STEREO_KIND,
            "header": {"pair": "p0", "seq": 1, "stamp_ns": 1},
            "arrays": {"left": {"dtype": "|O", "shape": [1], "data": b"a"}},
            "blobs": {},
        }
    )
    with pytest.raises(CodecError, match="dtype"):
        decode(bad, STEREO_KIND, StereoFrameHeader)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes_only_ever_raise_codec_error(payload: bytes) -> None:
    with pytest.raises(CodecError):
        decode(payload, STEREO_KIND, StereoFrameHeader)


def test_compressed_arrays_round_trip_and_bombs_are_refused() -> None:
    header = StereoFrameHeader(pair="p0", seq=1, stamp_ns=1)
    image = np.zeros((480, 640), np.uint8)
    payload = encode(STEREO_KIND, header, {"left": image}, compress=True)
    assert len(payload) < 5000
    np.testing.assert_array_equal(
        decode(payload, STEREO_KIND, StereoFrameHeader).arrays["left"], image
    )
    import zlib

    bomb = msgpack.packb(
        {
            "v": 1,
            "kind": STEREO_KIND,
            "header": {"pair": "p0", "seq": 1, "stamp_ns": 1},
            "arrays": {
                "left": {
                    "dtype": "|u1",
                    "shape": [10],
                    "data": zlib.compress(bytes(10**8)),
                    "compression": "zlib",
                }
            },
            "blobs": {},
        }
    )
    with pytest.raises(CodecError, match="does not inflate to 10 bytes"):
        decode(bomb, STEREO_KIND, StereoFrameHeader)
    bad = msgpack.packb(
        {
            "v": 1,
            "kind": STEREO_KIND,
            "header": {"pair": "p0", "seq": 1, "stamp_ns": 1},
            "arrays": {
                "left": {"dtype": "|u1", "shape": [10], "data": b"xx", "compression": "lz4"}
            },
            "blobs": {},
        }
    )
    with pytest.raises(CodecError, match="compression"):
        decode(bad, STEREO_KIND, StereoFrameHeader)


def test_what_fusion_serves_reads_past_fields_it_does_not_know_and_intake_does_not() -> None:
    """A robot's client older than the map box reads its messages; a service's input stays
    strict."""
    served: dict[str, object] = {"resolution_m": 0.05, "i0": 0, "j0": 0, "cols": 1, "rows": 1}
    served |= {"version": 3, "stamp_ns": 1, "added_in_a_later_version": [1, 2]}
    assert MapHeader.model_validate(served).version == 3
    track: dict[str, object] = {"id": 1, "class": "static", "top_m": 1.0, "velocity_mps": (0, 0)}
    track |= {"velocity_cov_m2ps2": ((0, 0), (0, 0)), "first_seen_ns": 0, "last_seen_ns": 0}
    track |= {"pairs": ["p0"], "partial": False, "detections": 1, "later": True}
    track |= {"center_m": (1.0, 2.0), "size_m": (1.0, 0.5), "yaw_rad": 0.0}
    listed = ObjectsHeader.model_validate({"version": 1, "stamp_ns": 1, "objects": [track]})
    assert listed.objects[0].object_class == "static"
    tile = {"pair": "p0", "seq": 0, "stamp_ns": 1, "resolution_m": 0.05, "i0": 0, "j0": 0}
    with pytest.raises(ValueError, match="extra"):
        TileHeader.model_validate(tile | {"cols": 1, "rows": 1, "added_in_a_later_version": 1})
