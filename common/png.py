"""PNG encoding of uint8 gray/RGB images with the standard library: the base install (a robot's
client) writes map pictures without OpenCV."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import numpy.typing as npt

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(image: npt.NDArray[np.uint8], compression: int = 6) -> bytes:
    """(H, W) gray or (H, W, 3) RGB uint8 → PNG bytes."""
    if (
        image.dtype != np.uint8
        or image.ndim not in (2, 3)
        or (image.ndim == 3 and image.shape[2] != 3)
    ):
        raise ValueError(
            f"encode_png takes uint8 (H, W) or (H, W, 3), got {image.dtype} {image.shape}"
        )
    height, width = image.shape[:2]
    color_type = 0 if image.ndim == 2 else 2
    rows = np.ascontiguousarray(image).reshape(height, -1)
    raw = np.hstack([np.zeros((height, 1), dtype=np.uint8), rows]).tobytes()  # filter 0 per row
    header = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return (
        _SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw, compression))
        + _chunk(b"IEND", b"")
    )


def decode_png(data: bytes) -> npt.NDArray[np.uint8]:
    """Inverse of :func:`encode_png` (8-bit gray/RGB, filter 0 rows only): for tests and tools."""
    if not data.startswith(_SIGNATURE):
        raise ValueError("not a PNG")
    pos, idat, width = len(_SIGNATURE), b"", 0
    height = color_type = 0
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            width, height, _, color_type = struct.unpack(">IIBB", body[:10])
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    channels = 1 if color_type == 0 else 3
    rows = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(
        height, 1 + width * channels
    )
    if np.any(rows[:, 0] != 0):
        raise ValueError("only unfiltered PNG rows are supported")
    image = rows[:, 1:].reshape((height, width) if channels == 1 else (height, width, 3))
    return image.copy()
