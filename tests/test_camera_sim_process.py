"""A real camera_sim process publishes over Zenoh on loopback; this test process receives."""

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from common import keys
from common.camera import StereoCalibration
from common.codec import decode
from common.messages import CALIB_KIND, STEREO_KIND, TRUTH_KIND, StereoFrameHeader, TruthHeader
from tests.conftest import Bus, wait_for

pytestmark = pytest.mark.process


def _get_one(session: zenoh.Session, selector: str, timeout_s: float = 5.0) -> zenoh.Reply | None:
    for reply in session.get(selector, timeout=timeout_s):
        return reply
    return None


def test_sim_publishes_frames_and_answers_calib_and_truth(bus: Bus) -> None:
    frames: list[bytes] = []
    got = threading.Event()

    def on_frame(sample: zenoh.Sample) -> None:
        frames.append(sample.payload.to_bytes())
        got.set()

    subscriber = bus.session.declare_subscriber(keys.stereo("p1"), on_frame)
    process = bus.start(
        "camera-sim",
        "--pair-count",
        "2",
        "--pairs",
        "p1",
        "--rate-hz",
        "2",
        "--frames",
        "40",
        "--light-step-period-s",
        "4",
    )
    assert got.wait(60), "no stereo frame from camera_sim"
    frame = decode(frames[0], STEREO_KIND, StereoFrameHeader)
    assert frame.header.pair == "p1" and frame.header.encoding == "raw"
    assert frame.arrays["left"].shape == (480, 640) and frame.arrays["right"].shape == (480, 640)
    assert frame.arrays["left"].std() > 10  # textured, not blank

    reply = _get_one(bus.session, keys.calib("p1"))
    assert reply is not None and reply.ok is not None
    calib = decode(reply.ok.payload.to_bytes(), CALIB_KIND, StereoCalibration).header
    assert calib.pair == "p1" and calib.baseline_m == pytest.approx(0.5, abs=5e-3)
    assert calib.left.position_world[2] == pytest.approx(6.0, abs=5e-3)  # published: off by mm

    assert _get_one(bus.session, keys.calib("p0"), timeout_s=1.0) is None  # not rendered here

    stamp_ns = frame.header.stamp_ns
    reply = _get_one(bus.session, f"{keys.SIM_TRUTH}?stamp_ns={stamp_ns};resolution=0.1")
    assert reply is not None and reply.ok is not None
    truth = decode(reply.ok.payload.to_bytes(), TRUTH_KIND, TruthHeader)
    occupied = truth.arrays["occupied"]
    assert occupied.shape == (truth.header.rows, truth.header.cols)
    assert truth.header.stamp_ns == stamp_ns and truth.header.resolution_m == 0.1
    assert 0.02 < occupied.mean() < 0.5
    assert any(o.moving for o in truth.header.objects)
    steps = truth.header.light_steps_ns  # lights switch every 2 s: the truth says when
    assert len(steps) >= 50 and all(stamp_ns - 121e9 < t <= stamp_ns + 1e9 for t in steps)
    assert truth.header.light_level in (0.5, 1.0)

    bad = _get_one(bus.session, f"{keys.SIM_TRUTH}?resolution=-1")
    assert bad is not None and bad.err is not None
    assert "resolution" in bad.err.payload.to_string()

    subscriber.undeclare()  # type: ignore[no-untyped-call]
    process.send_signal(2)
    assert process.wait(10) == 0
    wait_for(lambda: process.poll() is not None, 5, "camera_sim to stop")
    assert np.isfinite(calib.left.focal_px)


def test_save_frame_saves_a_jpeg_stream_as_the_depth_process_reads_it(
    bus: Bus, tmp_path: Path
) -> None:
    sim = bus.start(
        "camera-sim",
        "--pair-count",
        "1",
        "--rate-hz",
        "2",
        "--frames",
        "60",
        "--jpeg-quality",
        "80",
    )
    out = tmp_path / "stereo.png"
    saver = bus.start("save-frame", "--pair", "p0", "--out", str(out), "--timeout-s", "60")
    assert saver.wait(90) == 0  # it ignored JPEG frames and timed out
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape == (480, 1280) and image.std() > 10
    sim.send_signal(2)
    assert sim.wait(10) == 0
