"""The depth frame loop over a real Zenoh session: whatever one frame raises in processing (memory,
numpy, OpenCV) is counted as processing_failed and the loop takes the next frame."""

import threading
import time
import uuid
from collections.abc import Callable
from types import SimpleNamespace
from typing import cast

import numpy as np
import zenoh

from common import keys
from common.codec import WIRE_ENCODING, encode
from common.messages import STEREO_KIND, StereoFrameHeader
from services.depth.service import Counts, FrameIntake, Worker, _serve_frames
from tests.conftest import wait_for

SIZE = (64, 48)


class FlakyPublisher:
    """Fails its first frames the ways a real pipeline can, then publishes."""

    failures = (MemoryError("cannot allocate"), np.linalg.LinAlgError("singular"), IndexError("0"))

    def __init__(self) -> None:
        self.calls = 0
        self.published = 0

    def publish(self, *args: object) -> None:
        self.calls += 1
        if self.calls <= len(self.failures):
            raise self.failures[self.calls - 1]
        self.published += 1


def test_the_frame_loop_counts_any_exception_of_one_frame_and_goes_on() -> None:
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("namespace", f'"test-{uuid.uuid4().hex[:10]}"')
    with zenoh.open(config) as session:
        counts = Counts()
        pipeline = SimpleNamespace(calib=SimpleNamespace(image_size=SIZE))
        publisher = FlakyPublisher()
        worker = Worker(pipeline, publisher, FrameIntake(pipeline, "p0", 1 << 20, counts))  # type: ignore[arg-type]
        stop = threading.Event()
        loop = threading.Thread(target=_serve_frames, args=(session, "p0", worker, counts, stop))
        loop.start()
        time.sleep(0.2)  # the loop's subscriber declared
        image = np.zeros((SIZE[1], SIZE[0]), np.uint8)
        for seq in range(5):
            header = StereoFrameHeader(pair="p0", seq=seq, stamp_ns=time.time_ns())
            payload = encode(STEREO_KIND, header, {"left": image, "right": image})
            session.put(keys.stereo("p0"), payload, encoding=WIRE_ENCODING)
            wait_for(
                cast(Callable[[], bool], lambda seq=seq: publisher.calls == seq + 1),
                5,
                f"frame {seq} taken",
            )
        stop.set()
        loop.join(5)
        assert not loop.is_alive()
        snapshot = counts.snapshot()
        assert snapshot["rejected"] == {"processing_failed": 3}
        assert snapshot["processed"] == publisher.published == 2 and snapshot["received"] == 5
