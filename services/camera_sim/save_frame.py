"""Receive one stereo frame of a pair over Zenoh and save it as a side-by-side PNG."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import zenoh
from pydantic import Field

from common import keys
from common.codec import CodecError, decode
from common.messages import STEREO_KIND, StereoFrameHeader
from common.png import encode_png
from common.settings import ZenohSettings, parse_settings
from common.zenoh_session import open_session


class SaveFrameSettings(ZenohSettings):
    pair: str = Field("p0", description="pair whose frame to save")
    out: Path = Field(Path("stereo.png"), description="PNG file to write (left | right)")
    timeout_s: float = Field(30.0, gt=0, description="give up after this long without a frame")


def main(settings: SaveFrameSettings) -> None:
    received = threading.Event()
    frame: dict[str, np.ndarray] = {}

    def on_sample(sample: zenoh.Sample) -> None:
        if received.is_set():
            return
        try:
            message = decode(sample.payload.to_bytes(), STEREO_KIND, StereoFrameHeader)
        except CodecError:
            return
        if message.header.encoding == "raw":
            frame.update(message.arrays)
            received.set()

    with open_session(settings) as session:
        session.declare_subscriber(keys.stereo(settings.pair), on_sample)
        if not received.wait(settings.timeout_s):
            raise SystemExit(
                f"no frame on {keys.stereo(settings.pair)} within {settings.timeout_s} s"
            )
    settings.out.parent.mkdir(parents=True, exist_ok=True)
    settings.out.write_bytes(encode_png(np.hstack([frame["left"], frame["right"]])))
    print(f"saved {settings.out}")


def cli(argv: Sequence[str] | None = None) -> None:
    main(parse_settings(SaveFrameSettings, argv, "overgrid save-frame", __doc__ or ""))
