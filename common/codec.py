"""msgpack codec for overgrid messages: a pydantic header plus named numpy arrays and byte blobs.

Wire form: ``{"v": 1, "kind": str, "header": {...}, "arrays": {name: {dtype, shape, data}},
"blobs": {name: bytes}}``. Every failure to decode — truncated, wrong types, oversized, an array whose
bytes disagree with its shape — raises :class:`CodecError`, the one error type receivers catch.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import Annotated, Any, Generic, TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, Field, ValidationError

WIRE_VERSION = 1
WIRE_ENCODING = f"application/msgpack;overgrid/{WIRE_VERSION}"
"""Zenoh encoding string of every overgrid msgpack payload; the suffix is the wire version."""

DEFAULT_MAX_MESSAGE_BYTES = 32 * 1024 * 1024
MessageLimitMb = Annotated[float, Field(ge=0.01, le=1024.0)]
"""A service's largest message taken, in MiB (the setting ``--max-message-mb`` of each): from
10 KiB (1e-300 took no message at all) to a GiB (a tile of the most cells a header may claim is
180 MiB; 1e300 was taken as no limit)."""
ZLIB_LEVEL = 1  # fastest: maps are re-encoded every version
MAX_ARRAY_DIMS = 4
ALLOWED_DTYPES = frozenset({"|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<f4", "<f8", "|b1"})

H = TypeVar("H", bound=BaseModel)


class CodecError(ValueError):
    """A payload that is not a valid overgrid message of the expected kind."""


@dataclass(frozen=True)
class Message(Generic[H]):
    header: H
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    blobs: dict[str, bytes] = field(default_factory=dict)


PackedArray = dict[str, Any]
"""An array already in wire form, from :func:`pack_arrays`."""


def pack_arrays(arrays: dict[str, np.ndarray], compress: bool = False) -> dict[str, PackedArray]:
    """The costly part of encoding, separable so a sender can time it and report the time inside
    the same message's header. ``compress`` zlib-compresses the data (worth it for maps: mostly
    uniform cells; not for tiles, whose encode time is on the latency path)."""
    return {name: _pack_array(array, compress) for name, array in arrays.items()}


def _pack_array(array: np.ndarray, compress: bool = False) -> PackedArray:
    contiguous = np.ascontiguousarray(array)
    dtype = (
        contiguous.dtype.newbyteorder("<")
        if contiguous.dtype.byteorder == ">"
        else contiguous.dtype
    )
    contiguous = contiguous.astype(dtype, copy=False)
    if dtype.str not in ALLOWED_DTYPES:
        raise CodecError(f"array dtype {dtype.str} is not one of {sorted(ALLOWED_DTYPES)}")
    packed: PackedArray = {
        "dtype": dtype.str,
        "shape": list(contiguous.shape),
        "data": contiguous.tobytes(),
    }
    if compress:
        packed["data"] = zlib.compress(packed["data"], ZLIB_LEVEL)
        packed["compression"] = "zlib"
    return packed


def _unpack_array(name: str, obj: Any) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) - {"compression"} != {"dtype", "shape", "data"}:
        raise CodecError(f"array {name!r} is not a {{dtype, shape, data[, compression]}} map")
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    compression = obj.get("compression")
    if compression not in (None, "zlib"):
        raise CodecError(f"array {name!r} has compression {compression!r}, accepted: zlib")
    if dtype not in ALLOWED_DTYPES:
        raise CodecError(f"array {name!r} has dtype {dtype!r}, accepted: {sorted(ALLOWED_DTYPES)}")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_ARRAY_DIMS
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
    ):
        raise CodecError(f"array {name!r} has an invalid shape {shape!r}")
    if not isinstance(data, bytes):
        raise CodecError(f"array {name!r} data is {type(data).__name__}, expected bytes")
    expected = math.prod(shape) * np.dtype(dtype).itemsize  # not np.prod: 50× slower on a list
    if compression == "zlib":
        data = _inflate(name, data, expected)
    if expected != len(data):
        raise CodecError(f"array {name!r}: shape {shape} needs {expected} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _inflate(name: str, data: bytes, expected: int) -> bytes:
    """Decompress at most ``expected`` + 1 bytes: a small message cannot expand without bound."""
    inflater = zlib.decompressobj()
    try:
        out = inflater.decompress(data, expected + 1)
    except zlib.error as error:
        raise CodecError(f"array {name!r}: bad zlib data: {error}") from None
    if len(out) != expected or not inflater.eof:
        raise CodecError(f"array {name!r}: compressed data does not inflate to {expected} bytes")
    return out


def encode(
    kind: str,
    header: BaseModel,
    arrays: dict[str, np.ndarray] | None = None,
    blobs: dict[str, bytes] | None = None,
    packed_arrays: dict[str, PackedArray] | None = None,
    compress: bool = False,
) -> bytes:
    envelope = {
        "v": WIRE_VERSION,
        "kind": kind,
        "header": header.model_dump(mode="json"),
        "arrays": {**pack_arrays(arrays or {}, compress), **(packed_arrays or {})},
        "blobs": dict(blobs or {}),
    }
    packed: bytes = msgpack.packb(envelope, use_bin_type=True)
    return packed


def decode(
    payload: bytes | bytearray | memoryview,
    kind: str,
    header_model: type[H],
    max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
) -> Message[H]:
    """Decode and validate; raise :class:`CodecError` naming what is wrong."""
    size = len(payload)
    if size > max_bytes:
        raise CodecError(f"message of {size} bytes exceeds the limit of {max_bytes} bytes")
    try:
        envelope = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True)
    except Exception as error:  # msgpack raises several types for bad bytes
        raise CodecError(f"not a msgpack message: {type(error).__name__}: {error}") from None
    if not isinstance(envelope, dict):
        raise CodecError(f"message is a {type(envelope).__name__}, expected a map")
    if envelope.get("v") != WIRE_VERSION:
        raise CodecError(f"wire version {envelope.get('v')!r}, expected {WIRE_VERSION}")
    if envelope.get("kind") != kind:
        raise CodecError(f"message kind {envelope.get('kind')!r}, expected {kind!r}")
    arrays_obj, blobs_obj = envelope.get("arrays", {}), envelope.get("blobs", {})
    if not isinstance(arrays_obj, dict) or not isinstance(blobs_obj, dict):
        raise CodecError("arrays and blobs must be maps")
    if not all(isinstance(v, bytes) for v in blobs_obj.values()):
        raise CodecError("every blob must be bytes")
    try:
        header = header_model.model_validate(envelope.get("header"))
    except ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise CodecError(f"invalid {kind} header: {where}: {first['msg']}") from None
    arrays = {str(name): _unpack_array(str(name), obj) for name, obj in arrays_obj.items()}
    return Message(header=header, arrays=arrays, blobs={str(k): v for k, v in blobs_obj.items()})
