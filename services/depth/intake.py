"""What reaches a depth process over Zenoh, checked once where it enters: one decode function per
message kind turns bytes into a typed value or a named :class:`Rejection`, which the service counts
in ``depth/{pair}/health``. Nothing past these functions sees a frame it cannot process.

Pixels accepted: 8- and 16-bit gray, H×W×1, RGB and RGBA (each image converted to gray on its
own, so a mono camera pairs with a colour one); 16-bit pixels (machine-vision drivers deliver
10/12/16-bit pixels in 16-bit words) are reduced to 8 bits by the shift that keeps the frame's
brightest pixel, one shift for both images so that left and right keep one scale (a
frame-to-frame change of it is a gain step, which the floor model normalises).
Float, signed and bool pixels are rejected: they carry no agreed brightness scale.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Generic, TypeVar

import cv2
import numpy as np

from common.arrays import U8
from common.camera import StereoCalibration
from common.codec import CodecError, decode
from common.messages import CALIB_KIND, STEREO_KIND, StereoFrameHeader
from services.depth.pipeline import DepthPipeline, PipelineConfig

T = TypeVar("T")
MAX_VIEW_EXTENT_M = 200.0
"""The most floor one pair's view may span: a ceiling camera sees tens of metres. A calibration
in millimetres (a camera 5000 "m" up) passed every other check and had the first frame's tile
ask for gigabytes (the box ran out of memory)."""
SIDES = ("left", "right")

FRAME_REJECTIONS = (
    "oversize",  # larger than --max-message-mb, never unpacked
    "malformed",  # not an overgrid stereo message: bytes, envelope, header, arrays
    "wrong_pair",  # the header names another pair than the key it came on
    "undecodable",  # png/jpeg images that do not decode
    "bad_pixels",  # a pixel format of no camera: float, signed, bool, 2 or 5+ channels
    "wrong_size",  # not the calibration's image size
    "processing_failed",  # passed every check and still failed in the pipeline (a defect)
)


@dataclass(frozen=True)
class Rejection:
    """Why one message was refused: ``reason`` is one of the named reasons, ``detail`` for logs."""

    reason: str
    detail: str


@dataclass(frozen=True)
class StereoFrame:
    header: StereoFrameHeader
    left: U8
    right: U8
    received_ns: int


class _Refused(Exception):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def decode_stereo_frame(
    payload: bytes, pair: str, image_size: tuple[int, int], max_bytes: int
) -> StereoFrame | Rejection:
    """``cam/{pair}/stereo`` bytes → two gray 8-bit images of ``image_size`` (width, height)."""
    received_ns = time.time_ns()
    try:
        if len(payload) > max_bytes:
            raise _Refused("oversize", f"{len(payload)} bytes exceed the limit of {max_bytes}")
        try:
            message = decode(payload, STEREO_KIND, StereoFrameHeader, max_bytes)
        except CodecError as error:
            raise _Refused("malformed", str(error)) from None
        header = message.header
        if header.pair != pair:
            raise _Refused("wrong_pair", f"header names pair {header.pair!r}, key says {pair!r}")
        if header.encoding == "raw":
            left, right = (_raw_image(message.arrays, side) for side in SIDES)
        else:
            left, right = (
                _encoded_image(message.blobs, side, header.encoding, image_size) for side in SIDES
            )
        left_8, right_8 = _checked(left, right, image_size)
        return StereoFrame(header, left_8, right_8, received_ns)
    except _Refused as refused:
        return Rejection(refused.reason, str(refused))


def _raw_image(arrays: dict[str, np.ndarray], side: str) -> np.ndarray:
    if side not in arrays:
        raise _Refused("malformed", f"raw frame has no {side!r} array")
    return arrays[side]


def _encoded_image(
    blobs: dict[str, bytes], side: str, encoding: str, image_size: tuple[int, int]
) -> np.ndarray:
    """Decoded only once its header says the calibration's size: a small PNG can declare a
    gigapixel image."""
    blob = blobs.get(side)
    if blob is None:
        raise _Refused("malformed", f"{encoding} frame has no {side!r} blob")
    size = encoded_size(blob, encoding)
    if size is None:
        raise _Refused("undecodable", f"{side} blob is not a {encoding} image")
    _check_size(side, size, image_size)
    if encoding == "jpeg" and not jpeg_complete(blob):
        raise _Refused("undecodable", f"{side} jpeg image is cut short (no end-of-image marker)")
    image = decoded_image(blob)
    if image is None:
        raise _Refused("undecodable", f"{side} {encoding} image does not decode")
    return image


def _check_size(side: str, size: tuple[int, int], image_size: tuple[int, int]) -> None:
    if size != image_size:
        raise _Refused(
            "wrong_size",
            f"{side} image is {size[0]}×{size[1]}, calibration says {image_size[0]}×{image_size[1]}",
        )


def decoded_image(blob: bytes) -> np.ndarray | None:
    """An image file's pixels, unchanged (no colour conversion, 16 bits kept); None if it does
    not decode. A JPEG cut short is the caller's to refuse first (:func:`jpeg_complete`)."""
    image = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    return None if image is None else np.asarray(image)


def jpeg_complete(blob: bytes) -> bool:
    """Whether a JPEG's end-of-image marker follows its last scan: libjpeg decodes a file cut
    short as grey below the cut, with a warning on stderr and no error. (Scan data cannot hold
    the marker's bytes; bytes after it, as parts cut from an MJPEG stream carry, are no harm.)"""
    last_scan = blob.rfind(b"\xff\xda")
    return last_scan >= 0 and blob.find(b"\xff\xd9", last_scan + 2) >= 0


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
"""Start-of-frame markers (baseline, progressive, …); C4/C8/CC are tables and a reserved code."""


def encoded_size(blob: bytes, encoding: str) -> tuple[int, int] | None:
    """(width, height) a PNG's IHDR or a JPEG's start-of-frame declares; None if it has none."""
    if encoding == "png":
        if blob[:8] != PNG_SIGNATURE or blob[12:16] != b"IHDR" or len(blob) < 24:
            return None
        return int.from_bytes(blob[16:20], "big"), int.from_bytes(blob[20:24], "big")
    if encoding != "jpeg" or blob[:2] != b"\xff\xd8":
        return None
    offset = 2
    while offset + 9 <= len(blob):
        if blob[offset] != 0xFF:
            return None
        marker = blob[offset + 1]
        if marker == 0xFF:  # fill byte
            offset += 1
            continue
        if marker in JPEG_SOF_MARKERS:
            height = int.from_bytes(blob[offset + 5 : offset + 7], "big")
            return int.from_bytes(blob[offset + 7 : offset + 9], "big"), height
        if marker == 0xDA:  # image data before any frame header
            return None
        offset += 2 + int.from_bytes(blob[offset + 2 : offset + 4], "big")
    return None


def check_images(
    left: np.ndarray, right: np.ndarray, image_size: tuple[int, int]
) -> tuple[U8, U8] | Rejection:
    """Images from any source (a frame's arrays, decoded blobs, a recording) → gray uint8 of the
    calibration's size, or why not."""
    try:
        return _checked(left, right, image_size)
    except _Refused as refused:
        return Rejection(refused.reason, str(refused))


def _checked(left: np.ndarray, right: np.ndarray, image_size: tuple[int, int]) -> tuple[U8, U8]:
    for side, image in zip(SIDES, (left, right), strict=True):
        if image.ndim not in (2, 3):
            raise _Refused("bad_pixels", f"{side} image has {image.ndim} dimensions")
        _check_size(side, (image.shape[1], image.shape[0]), image_size)
    return _to_mono8(left, right)


def _to_mono8(left: np.ndarray, right: np.ndarray) -> tuple[U8, U8]:
    """Both images as gray uint8 (see the module docstring for the formats accepted)."""
    left, right = _gray("left", left), _gray("right", right)
    if left.dtype != right.dtype:
        raise _Refused("bad_pixels", f"left pixels are {left.dtype}, right {right.dtype}")
    if left.dtype == np.uint16:
        bits = max(int(left.max()), int(right.max())).bit_length()
        shift = max(bits - 8, 0)
        return (left >> shift).astype(np.uint8), (right >> shift).astype(np.uint8)
    return left, right


def _gray(side: str, image: np.ndarray) -> np.ndarray:
    """One image as 2-D gray of its own depth (uint8 or uint16): each camera on its own, so a
    mono camera beside a colour one pairs."""
    channels = image.shape[2] if image.ndim == 3 else 1
    if channels not in (1, 3, 4):
        raise _Refused("bad_pixels", f"{side} image has {channels} channels, accepted 1, 3 or 4")
    if image.dtype not in (np.uint8, np.uint16):
        raise _Refused(
            "bad_pixels",
            f"{side} pixels are {image.dtype} with {channels} channel(s): "
            "accepted uint8 or uint16, gray, RGB or RGBA",
        )
    if image.ndim == 3 and channels == 1:
        return image[:, :, 0]
    if image.ndim == 3:
        code = cv2.COLOR_RGB2GRAY if channels == 3 else cv2.COLOR_RGBA2GRAY
        return np.asarray(cv2.cvtColor(image, code))
    return image


def decode_calibration(payload: bytes) -> StereoCalibration | Rejection:
    """A ``cam/{pair}/calib`` reply → its calibration, field-validated (common.camera), or
    ``malformed``; the service refuses a valid one :func:`build_pipeline` cannot use as
    ``unusable``."""
    try:
        return decode(payload, CALIB_KIND, StereoCalibration).header
    except CodecError as error:
        return Rejection("malformed", str(error))


def build_pipeline(calib: StereoCalibration, config: PipelineConfig) -> DepthPipeline:
    """The pipeline of a calibration, or ValueError when its geometry describes no stereo pair
    this service can match (a 1000 m baseline, k3 = 100): the floor-to-obstacle disparity band
    must fit the image, which also bounds what SGBM allocates at the first frame."""
    try:
        pipeline = DepthPipeline(calib, config)
    except (cv2.error, MemoryError, ArithmeticError, np.linalg.LinAlgError) as error:
        raise ValueError(f"{type(error).__name__}: {' '.join(str(error).split())}") from None
    floor_xy_m = pipeline.floor_xy_m.reshape(2, -1)[:, pipeline.meets_floor]
    extent_m = np.ptp(floor_xy_m, axis=1) if floor_xy_m.size else np.zeros(2)
    if float(extent_m.max()) > MAX_VIEW_EXTENT_M:
        raise ValueError(
            f"the view spans {extent_m[0]:.4g} × {extent_m[1]:.4g} m of floor from a camera "
            f"{pipeline.rectifier.C_world[2]:.4g} m up (at most {MAX_VIEW_EXTENT_M:g} m): are the "
            "poses in metres?"
        )
    width = pipeline.rectifier.size[0]
    low, count = pipeline.min_disparity, pipeline.num_disparities
    if low + count > width // 2:
        raise ValueError(
            f"the floor-to-obstacle disparities {low}…{low + count} px (at the processing "
            f"resolution) do not fit its image, {width} px wide: check the baseline "
            f"({calib.baseline_m:.4g} m: in metres?), focal length, distortion and poses"
        )
    return pipeline


class LatestSlot(Generic[T]):
    """One-deep mailbox: a new item replaces an unread one (counted), so a slow consumer works on
    the newest frame and memory stays bounded.

    Not zenoh's ``RingChannel(1)``, which does the same but cannot say how many it dropped (the
    health's ``skipped``), and whose blocking ``recv`` neither a signal nor ``undeclare`` from
    another thread interrupts (measured with zenoh-python 1.10): the worker would have to poll."""

    def __init__(self) -> None:
        self._item: T | None = None
        self._cond = threading.Condition()
        self.replaced = 0

    def put(self, item: T) -> None:
        with self._cond:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout_s: float) -> T | None:
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout_s)
            item, self._item = self._item, None
            return item
