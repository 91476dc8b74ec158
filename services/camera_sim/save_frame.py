"""Receive one stereo frame of a pair over Zenoh and save it as a side-by-side PNG.

Frames are read as the depth process reads them (services.depth.intake: raw, PNG or JPEG, any
camera pixel format → gray 8-bit), against the size the pair's calibration gives."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import zenoh
from pydantic import Field

from common import keys
from common.client import MAX_TIMEOUT_S
from common.png import encode_png
from common.settings import ZenohSettings, parse_settings, startup_error
from common.zenoh_session import open_session
from services.depth.intake import Rejection, StereoFrame, decode_calibration, decode_stereo_frame


class SaveFrameSettings(ZenohSettings):
    pair: str = Field("p0", description="pair whose frame to save")
    out: Path = Field(Path("stereo.png"), description="PNG file to write (left | right)")
    timeout_s: float = Field(
        30.0, gt=0, le=MAX_TIMEOUT_S, description="give up after this long without a frame"
    )


def image_size(session: zenoh.Session, pair: str, timeout_s: float) -> tuple[int, int]:
    """(width, height) from cam/{pair}/calib, asked until the timeout (the camera box may start
    after this tool): a frame is checked against it before it is decoded, as in the depth
    process."""
    deadline = time.monotonic() + timeout_s
    refused: list[str] = []
    while time.monotonic() < deadline:
        for reply in session.get(keys.calib(pair), timeout=min(2.0, timeout_s)):
            if reply.ok is None:
                continue
            calib = decode_calibration(reply.ok.payload.to_bytes())
            if isinstance(calib, Rejection):
                refused.append(calib.detail)
                continue
            return calib.image_size
        time.sleep(0.2)
    startup_error(
        f"no usable calibration on {keys.calib(pair)} within {timeout_s} s"
        + (f": {refused[-1][:200]}" if refused else "")
    )


def largest_frame_bytes(size: tuple[int, int]) -> int:
    """The largest stereo message a camera of this size sends: two raw images of the widest pixel
    format accepted (RGBA, 4 bytes a pixel), and 64 KiB for the envelope and header."""
    return 2 * 4 * size[0] * size[1] + 65536


def main(settings: SaveFrameSettings) -> None:
    received = threading.Event()
    frames: list[StereoFrame] = []
    rejections: list[Rejection] = []

    with open_session(settings) as session:
        size = image_size(session, settings.pair, settings.timeout_s)
        max_bytes = largest_frame_bytes(size)

        def on_sample(sample: zenoh.Sample) -> None:
            if received.is_set():
                return
            frame = decode_stereo_frame(sample.payload.to_bytes(), settings.pair, size, max_bytes)
            if isinstance(frame, Rejection):
                rejections.append(frame)
                return
            frames.append(frame)
            received.set()

        subscriber = session.declare_subscriber(keys.stereo(settings.pair), on_sample)
        got = received.wait(settings.timeout_s)
        subscriber.undeclare()  # type: ignore[no-untyped-call]
    if not got:
        refused = f"; refused {len(rejections)}, e.g. {rejections[0].detail}" if rejections else ""
        raise SystemExit(
            f"no frame on {keys.stereo(settings.pair)} within {settings.timeout_s} s{refused}"
        )
    settings.out.parent.mkdir(parents=True, exist_ok=True)
    settings.out.write_bytes(encode_png(np.hstack([frames[0].left, frames[0].right])))
    print(f"saved {settings.out}")


def cli(argv: Sequence[str] | None = None) -> None:
    main(parse_settings(SaveFrameSettings, argv, "overgrid save-frame", __doc__ or ""))
