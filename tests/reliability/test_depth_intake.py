"""The depth process's edge: each stereo frame and calibration a camera could send is decoded
into gray 8-bit images of the calibration's size or refused with a named reason, never raised."""

import time
from collections.abc import Callable
from typing import Any

import cv2
import msgpack
import numpy as np
import pytest

from common.camera import StereoCalibration
from common.codec import encode
from common.messages import CALIB_KIND, STEREO_KIND, StereoFrameHeader
from services.camera_sim.rig import RigSpec, layout_pairs
from services.depth.intake import (
    FRAME_REJECTIONS,
    Rejection,
    StereoFrame,
    build_pipeline,
    decode_calibration,
    decode_stereo_frame,
    encoded_size,
)
from services.depth.settings import DepthSettings

SIZE = (64, 48)  # width, height
MAX_BYTES = 1 << 20
RNG = np.random.default_rng(3)
GRAY = RNG.integers(0, 256, (SIZE[1], SIZE[0]), dtype=np.uint8)


def _header(pair: str = "p0", encoding: str = "raw") -> StereoFrameHeader:
    return StereoFrameHeader(pair=pair, seq=1, stamp_ns=time.time_ns(), encoding=encoding)


def _raw(left: np.ndarray, right: np.ndarray | None = None, pair: str = "p0") -> bytes:
    return encode(
        STEREO_KIND, _header(pair), {"left": left, "right": left if right is None else right}
    )


def _decode(payload: bytes) -> StereoFrame | Rejection:
    return decode_stereo_frame(payload, "p0", SIZE, MAX_BYTES)


def _reason(payload: bytes) -> str:
    result = _decode(payload)
    assert isinstance(result, Rejection), result
    assert result.reason in FRAME_REJECTIONS
    return result.reason


@pytest.mark.parametrize(
    "image",
    [
        GRAY,
        GRAY[:, :, None],
        np.repeat(GRAY[:, :, None], 3, axis=2),  # RGB
        np.dstack([np.repeat(GRAY[:, :, None], 3, axis=2), np.full_like(GRAY, 255)]),  # RGBA
        GRAY.astype(np.uint16) << 4,  # a 12-bit camera in 16-bit words
        (GRAY.astype(np.uint16) << 8)[:, :, None],  # 16-bit, one channel
        np.repeat((GRAY.astype(np.uint16) << 8)[:, :, None], 3, axis=2),  # 16-bit RGB
    ],
    ids=["gray", "gray1", "rgb", "rgba", "mono12in16", "mono16x1", "rgb16"],
)
def test_camera_pixel_formats_become_the_same_gray_image(image: np.ndarray) -> None:
    frame = _decode(_raw(image))
    assert isinstance(frame, StereoFrame)
    assert frame.left.dtype == np.uint8 and frame.left.shape == (SIZE[1], SIZE[0])
    assert np.abs(frame.left.astype(int) - GRAY).max() <= 1  # colour weights round


def test_a_16_bit_pair_keeps_one_scale_for_both_images() -> None:
    dark = (GRAY // 4).astype(np.uint16) << 4  # left uses 10 bits, right 12
    bright = GRAY.astype(np.uint16) << 4
    frame = _decode(_raw(dark, bright))
    assert isinstance(frame, StereoFrame)
    assert np.array_equal(frame.right, GRAY) and np.array_equal(frame.left, GRAY // 4)


@pytest.mark.parametrize(
    ("image", "reason"),
    [
        (GRAY.astype(np.float32), "bad_pixels"),
        (GRAY.astype(np.int8), "bad_pixels"),
        (GRAY.astype(np.bool_), "bad_pixels"),
        (GRAY.astype(np.uint32), "bad_pixels"),
        (np.zeros((SIZE[1], SIZE[0], 2), np.uint8), "bad_pixels"),
        (np.zeros((SIZE[1], SIZE[0], 5), np.uint8), "bad_pixels"),
        (np.zeros((SIZE[1], SIZE[0], 1, 1), np.uint8), "bad_pixels"),
        (np.zeros(SIZE[0], np.uint8), "bad_pixels"),
        (np.zeros((SIZE[0], SIZE[1]), np.uint8), "wrong_size"),  # transposed
        (np.zeros((480, 640), np.uint8), "wrong_size"),
    ],
)
def test_pixels_no_camera_sends_are_refused_by_reason(image: np.ndarray, reason: str) -> None:
    assert _reason(_raw(image)) == reason


def test_messages_that_are_no_frame_are_refused_by_reason() -> None:
    good = _raw(GRAY)
    assert isinstance(_decode(good), StereoFrame)
    assert _reason(good[: len(good) // 2]) == "malformed"  # truncated
    assert _reason(b"\x00\xff" * 100) == "malformed"
    assert _reason(b"") == "malformed"
    envelope = msgpack.unpackb(good, raw=False)
    del envelope["arrays"]["right"]
    assert _reason(msgpack.packb(envelope)) == "malformed"
    envelope = msgpack.unpackb(good, raw=False)
    envelope["arrays"]["left"]["shape"] = [SIZE[1] * 2, SIZE[0]]  # shape disagrees with its bytes
    assert _reason(msgpack.packb(envelope)) == "malformed"
    assert _reason(_raw(GRAY, pair="p1")) == "wrong_pair"
    assert _reason(_raw(GRAY, GRAY.astype(np.uint16))) == "bad_pixels"  # 8 and 16 bits
    assert isinstance(_decode(_raw(GRAY, GRAY[:, :, None])), StereoFrame)  # each its own layout
    assert decode_stereo_frame(good, "p0", SIZE, len(good) - 1) == Rejection(
        "oversize", f"{len(good)} bytes exceed the limit of {len(good) - 1}"
    )


def _encoded(encoding: str, left: bytes, right: bytes | None = None) -> bytes:
    blobs = {"left": left, "right": left if right is None else right}
    return encode(STEREO_KIND, _header(encoding=encoding), blobs=blobs)


def test_png_and_jpeg_frames_are_checked_before_they_are_decoded() -> None:
    png = cv2.imencode(".png", GRAY)[1].tobytes()
    png16 = cv2.imencode(".png", GRAY.astype(np.uint16) << 8)[1].tobytes()
    jpeg = cv2.imencode(".jpg", GRAY)[1].tobytes()
    progressive = cv2.imencode(".jpg", GRAY, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    for encoding, blob in (("png", png), ("png", png16), ("jpeg", jpeg), ("jpeg", progressive)):
        assert encoded_size(blob, encoding) == SIZE
        frame = _decode(_encoded(encoding, blob))
        assert isinstance(frame, StereoFrame), (encoding, frame)
        assert np.abs(frame.left.astype(int) - GRAY).mean() < 3  # jpeg is lossy
    # A 4 kB PNG that declares 100000×100000 pixels (10 GB decoded) is never decoded.
    bomb = bytearray(png)
    bomb[16:24] = (100_000).to_bytes(4, "big") * 2
    assert _reason(_encoded("png", bytes(bomb))) == "wrong_size"
    assert _reason(_encoded("png", jpeg)) == "undecodable"  # not what the header says
    assert _reason(_encoded("jpeg", b"\xff\xd8" + bytes(200))) == "undecodable"
    assert _reason(_encoded("png", png[:40])) == "undecodable"  # header fine, body cut
    small = cv2.imencode(".png", GRAY[:24, :32])[1].tobytes()
    assert _reason(_encoded("png", small)) == "wrong_size"


def _calibration() -> dict[str, Any]:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0].model_dump()
    calib["right"]["dist"] = calib["left"]["dist"] = [0.0] * 5
    return calib


def test_a_calibration_over_zenoh_is_decoded_or_refused() -> None:
    calib = StereoCalibration.model_validate(_calibration())
    decoded = decode_calibration(encode(CALIB_KIND, calib))
    assert isinstance(decoded, StereoCalibration) and decoded.model_dump() == calib.model_dump()
    rejection = decode_calibration(encode(CALIB_KIND, calib)[:-10])
    assert isinstance(rejection, Rejection) and rejection.reason == "malformed"
    folded = calib.model_copy(
        update={"left": calib.left.model_copy(update={"dist": [-100.0, 0, 0, 0, 0]})}
    )  # model_copy skips validation: what a camera box with a broken calibration would send
    rejection = decode_calibration(encode(CALIB_KIND, folded))
    assert isinstance(rejection, Rejection) and rejection.reason == "malformed"
    assert "not invertible" in rejection.detail


@pytest.mark.parametrize(
    "dist",
    [
        [0.0] * 5,
        [],
        [-0.28, 0.07, 0.0005, -0.0003, 0.0],  # a wide-angle lens: barrel, held by k2
        [-0.1, 0.01, 0.0, 0.0, 0.0],
        [0.1, -0.05, 0.0, 0.0, 0.01],  # pincushion
        [2.0, 1.0, 0.0, 0.0, 0.1, 2.1, 1.1, 0.1],  # rational model as OpenCV fits it
    ],
)
def test_lens_distortion_of_real_calibrations_is_accepted(dist: list[float]) -> None:
    calib = _calibration()
    calib["left"]["dist"] = calib["right"]["dist"] = dist
    StereoCalibration.model_validate(calib)


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda d: d["left"]["K"][0].__setitem__(0, 1e-9), "field of view"),
        (lambda d: d["left"]["K"][0].__setitem__(2, 1e9), "principal point"),
        (
            lambda d: [
                d[s].update(
                    width=16384, height=16384, K=[[554, 0, 8191.5], [0, 554, 8191.5], [0, 0, 1]]
                )
                for s in ("left", "right")
            ],
            "pixels",
        ),
        (lambda d: d["left"].__setitem__("dist", [-100.0, 0, 0, 0, 0]), "not invertible"),
        (lambda d: d["right"].__setitem__("dist", [-0.3, 0, 0, 0, 0]), "not invertible"),
        (lambda d: d["left"].__setitem__("dist", [0, 0, 0, 0, 0, 5.0, 0, 0]), "not invertible"),
    ],
    ids=["focal", "principal_point", "pixels", "k1_minus_100", "k1_folds_at_corner", "k4"],
)
def test_absurd_intrinsics_fail_field_validation(
    change: Callable[[dict[str, Any]], object], says: str
) -> None:
    calib = _calibration()
    change(calib)
    with pytest.raises(ValueError, match=says):
        StereoCalibration.model_validate(calib)


@pytest.mark.parametrize(
    "change",
    [
        lambda d: d["right"]["T_world_cam"][0].__setitem__(3, 1000.0),  # 1000 m baseline
        lambda d: d["left"].__setitem__("dist", [0, 0, 0, 0, 100.0]),  # k3 = 100
        lambda d: [d[s]["K"][i].__setitem__(i, 1e9) for s in ("left", "right") for i in (0, 1)],
    ],
    ids=["baseline", "k3", "focal"],
)
def test_absurd_geometry_builds_no_pipeline(change: Callable[[dict[str, Any]], object]) -> None:
    calib = _calibration()
    change(calib)
    with pytest.raises(ValueError, match="disparities"):
        build_pipeline(
            StereoCalibration.model_validate(calib), DepthSettings(pair="p0").pipeline_config()
        )
