"""Real camera_sim and depth processes over Zenoh on loopback."""

import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import msgpack
import numpy as np
import pytest
import yaml
import zenoh

from common import keys
from common.camera import StereoCalibration
from common.codec import WIRE_ENCODING, decode, encode
from common.messages import (
    CALIB_KIND,
    DETECTIONS_KIND,
    STEREO_KIND,
    TILE_KIND,
    DetectionsHeader,
    StereoFrameHeader,
    TileHeader,
)
from common.png import encode_png
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import SceneSpec, generate_scene
from services.depth.pipeline import undersampled
from services.depth.service import CALIB_RECHECK_S, SWAP_TRIES, FusionIntake, Worker, _summaries
from tests.conftest import Bus, assert_one_line_exit_2, run_overgrid, wait_for

pytestmark = pytest.mark.process


class TileSink:
    def __init__(self, session: zenoh.Session, pair: str = "*") -> None:
        self.tiles: list[TileHeader] = []
        self.lock = threading.Lock()
        self.subscriber = session.declare_subscriber(f"depth/{pair}/tile", self._on_tile)

    def _on_tile(self, sample: zenoh.Sample) -> None:
        message = decode(sample.payload.to_bytes(), TILE_KIND, TileHeader)
        with self.lock:
            self.tiles.append(message.header)

    def count(self) -> int:
        with self.lock:
            return len(self.tiles)


def _health(session: zenoh.Session, pair: str) -> dict[str, Any]:
    for reply in session.get(keys.depth_health(pair), timeout=3.0):
        if reply.ok is not None:
            return cast(dict[str, Any], json.loads(reply.ok.payload.to_string()))
    return {}


def _alive(session: zenoh.Session) -> set[str]:
    return {
        keys.pair_of(str(r.ok.key_expr))
        for r in session.liveliness().get(keys.DEPTH_ALIVE_ALL, timeout=2.0)
        if r.ok
    }


def test_depth_turns_frames_into_tiles_and_survives_bad_frames(bus: Bus) -> None:
    sink = TileSink(bus.session)
    objects: list[DetectionsHeader] = []
    objects_sub = bus.session.declare_subscriber(
        "depth/p0/objects",
        lambda s: objects.append(
            decode(s.payload.to_bytes(), DETECTIONS_KIND, DetectionsHeader).header
        ),
    )
    bus.start("camera-sim", "--pair-count", "1", "--rate-hz", "4", "--frames", "400")
    depth = bus.start("depth", "--pair", "p0")
    wait_for(lambda: sink.count() >= 3, 60, "three tiles from the depth process")
    first = sink.tiles[0]
    assert first.pair == "p0" and first.resolution_m == 0.05
    assert {"rectify", "disparity", "projection", "model", "encode"} <= set(first.stage_ms)
    assert "p0" in _alive(bus.session)
    # Each frame's objects say where the pair's camera stands (fusion lifts a mover's view
    # measured too low along its rays): over the floor the sim's one pair watches, 6 m up.
    wait_for(lambda: bool(objects), 30, "the objects of a frame")
    (calib,) = layout_pairs(RigSpec(pair_count=1), generate_scene(0).floor_size_m)
    # (The sim publishes its calibration with a realistic error of a few millimetres.)
    assert objects[0].camera_m == pytest.approx(tuple(calib.left.position_world), abs=0.05)
    objects_sub.undeclare()  # type: ignore[no-untyped-call]

    # Malformed input on the pair's key: random bytes, a wrong-typed header, a frame of the wrong size.
    # Blocking, as the camera sim publishes: zenoh's default drops a put when its queue is
    # congested, and the count below needs every one of these 1–2 MB puts to arrive.
    publisher = bus.session.declare_publisher(
        keys.stereo("p0"),
        encoding=WIRE_ENCODING,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    publisher.put(b"\x00garbage\xff" * 10)
    publisher.put(msgpack.packb({"v": 1, "kind": "stereo", "header": {"pair": "p0", "seq": "x"}}))
    small = np.zeros((240, 320), np.uint8)
    huge_seq = 10**12  # ahead of the sim's sequence, so it is judged on its images, not its order
    publisher.put(
        encode(
            STEREO_KIND,
            StereoFrameHeader(pair="p0", seq=huge_seq, stamp_ns=time.time_ns()),
            {"left": small, "right": small},
        )
    )
    # The right size but what other camera drivers send: float, signed, bool pixels are refused
    # and counted at intake; 16-bit mono, one channel and RGBA are converted. None reaches (or
    # kills) the worker unchecked.
    refused = (np.float32, np.int8, np.bool_)
    accepted = ((480, 640), np.uint16), ((480, 640, 1), np.uint8), ((480, 640, 4), np.uint8)
    for shape, dtype in [((480, 640), t) for t in refused] + list(accepted):
        huge_seq += 1
        image = np.zeros(shape, dtype)
        publisher.put(
            encode(
                STEREO_KIND,
                StereoFrameHeader(pair="p0", seq=huge_seq, stamp_ns=time.time_ns()),
                {"left": image, "right": image},
            )
        )
    wait_for(
        lambda: sum(_health(bus.session, "p0").get("rejected", {}).values()) >= 6,
        20,
        "6 rejections counted",
    )
    time.sleep(1.0)  # nothing more is refused
    health = _health(bus.session, "p0")
    assert health["rejected"] == {"malformed": 2, "wrong_size": 1, "bad_pixels": 3}
    assert health["received"] >= 9 and health["state"] == "running"
    before = sink.count()
    wait_for(lambda: sink.count() >= before + 2, 30, "tiles to keep coming after bad frames")
    assert depth.poll() is None

    depth.send_signal(signal.SIGINT)
    assert depth.wait(10) == 0
    wait_for(lambda: "p0" not in _alive(bus.session), 5, "the liveliness token of p0 to vanish")


def test_sigkill_of_the_depth_process_itself_drops_its_token(bus: Bus) -> None:
    bus.start("camera-sim", "--pair-count", "1", "--rate-hz", "2", "--frames", "400")
    depth = bus.start("depth", "--pair", "p0")
    wait_for(lambda: "p0" in _alive(bus.session), 60, "p0 to become alive")
    children = subprocess.run(
        ["pgrep", "-P", str(depth.pid)], capture_output=True, text=True
    ).stdout.split()
    assert children, "the depth process runs under timeout"
    killed_at = time.monotonic()
    subprocess.run(["kill", "-KILL", children[0]], check=True)  # the real process, not `timeout`
    wait_for(lambda: "p0" not in _alive(bus.session), 15, "the token to vanish")
    assert time.monotonic() - killed_at < 15


def test_recorded_images_and_calibration_file_go_through_the_same_pipeline(
    bus: Bus, tmp_path: Path
) -> None:
    scene = generate_scene(1)
    calib = layout_pairs(RigSpec(pair_count=1), scene.floor_size_m)[0]
    renderer = SceneRenderer(scene, [calib])
    (tmp_path / "left").mkdir()
    (tmp_path / "right").mkdir()
    for k, t in enumerate((0.0, 1.0, 2.0)):
        renderer.set_time(t)
        (tmp_path / "left" / f"{k:04d}.png").write_bytes(
            encode_png(renderer.render_gray("p0_left", 640, 480))
        )
        (tmp_path / "right" / f"{k:04d}.png").write_bytes(
            encode_png(renderer.render_gray("p0_right", 640, 480))
        )
    renderer.close()
    # An unreadable pair and one of the wrong size are counted; the recording goes on after them.
    (tmp_path / "left" / "0003.png").write_bytes(b"not a png")
    (tmp_path / "right" / "0003.png").write_bytes(b"not a png")
    for side in ("left", "right"):
        small = encode_png(np.zeros((240, 320), np.uint8))
        (tmp_path / side / "0004.png").write_bytes(small)
        (tmp_path / side / "0005.png").write_bytes((tmp_path / side / "0000.png").read_bytes())
    calib_file = tmp_path / "calib.yaml"
    calib_file.write_text(yaml.safe_dump(calib.model_dump(mode="json")))
    sink = TileSink(bus.session, "cam7")
    time.sleep(0.5)
    bus.start(
        "depth",
        "--pair",
        "cam7",
        "--calib",
        str(calib_file),
        "--images",
        str(tmp_path),
        "--rate-hz",
        "2",
    )
    wait_for(lambda: sink.count() >= 4, 60, "four tiles from recorded images")
    assert [t.seq for t in sink.tiles] == [0, 1, 2, 5]
    assert all(t.cols * t.rows > 10_000 for t in sink.tiles)


def _rendered_recording(
    folder: Path, scene: SceneSpec, calib: StereoCalibration, cameras: dict[str, str], frames: int
) -> Path:
    """A recording of ``scene`` at one instant in ``folder`` (``cameras``: the camera each side's
    folder holds) and its calibration file, returned."""
    renderer = SceneRenderer(scene, [calib])
    renderer.set_time(0.0)  # without, the renders are black
    width, height = calib.image_size
    for side, camera in cameras.items():
        (folder / side).mkdir()
        image = encode_png(renderer.render_gray(camera, width, height))
        for index in range(frames):
            (folder / side / f"{index:04d}.png").write_bytes(image)
    renderer.close()
    calib_file = folder / "calib.yaml"
    calib_file.write_text(yaml.safe_dump(calib.model_dump(mode="json")))
    return calib_file


def _replayed(
    folder: Path, calib_file: Path, name: str, *flags: str
) -> subprocess.CompletedProcess[str]:
    """``overgrid depth`` over the recording in ``folder``, in a namespace of its own."""
    return run_overgrid(
        "depth",
        "--pair",
        "p0",
        "--calib",
        str(calib_file),
        "--images",
        str(folder),
        *flags,
        "--no-multicast-scouting",
        "--namespace",
        f"test_{name}_{os.getpid()}",
    )


def test_a_swapped_recording_is_one_line_at_start_up(tmp_path: Path) -> None:
    """Swapped streams mapped on (valid disparity 0.71 → 0.08) and nothing said why. (This test
    once rendered without setting the scene's time: black frames, which said "no floor" as
    swapped ones do, and told nothing of the swap check.)"""
    scene = generate_scene(1)
    calib = layout_pairs(RigSpec(pair_count=1), scene.floor_size_m)[0]
    swapped = {"left": "p0_right", "right": "p0_left"}
    calib_file = _rendered_recording(tmp_path, scene, calib, swapped, frames=3)
    done = _replayed(tmp_path, calib_file, "swapped")
    assert_one_line_exit_2(done, "--images", "left and right the other way round")


def test_a_camera_gone_black_is_said_and_maps_nothing(tmp_path: Path) -> None:
    """A black frame was mapped as the floor model's rules made of it, re-learned the floor from
    nothing, and was blamed on swapped cameras ("no floor")."""
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for index in range(4):
            (tmp_path / side / f"{index:04d}.png").write_bytes(
                encode_png(np.zeros((480, 640), np.uint8))
            )
    calib_file = _calibration_file(tmp_path)
    done = _replayed(tmp_path, calib_file, "black", "--rate-hz", "8", "--summary-s", "0.2")
    assert "the camera's images showed nothing" in done.stderr, done.stderr
    assert "the floor model finds no floor" not in done.stderr
    assert "Traceback" not in done.stderr


def test_images_too_small_for_the_map_are_said_at_start_up(tmp_path: Path) -> None:
    """320 × 240 cameras at --downscale 2 mapped with 58 % of the floor unknown and nothing said
    why."""
    scene = generate_scene(0)
    calib = layout_pairs(RigSpec(pair_count=1, width_px=320, height_px=240), scene.floor_size_m)[0]
    cameras = {"left": "p0_left", "right": "p0_right"}
    calib_file = _rendered_recording(tmp_path, scene, calib, cameras, frames=2)
    done = _replayed(tmp_path, calib_file, "too_small", "--rate-hz", "20")
    assert done.returncode == 0, done.stderr
    assert "images too small" in done.stderr
    assert "the cameras' images are 320×240 px, under half the pixels of the 640×480" in done.stderr


def test_undersampled_names_small_cameras_at_any_downscale_and_a_downscale_too_deep() -> None:
    assert undersampled((640, 480), 2) is None and undersampled((1280, 960), 4) is None
    assert undersampled((640, 400), 2) is None  # a 16:10 sensor: most of the pixels
    for downscale in (1, 2):  # at --downscale 1, 320 × 240 cameras: IoU 0.52, 21 % unknown
        assert "the cameras' images are 320×240 px" in (undersampled((320, 240), downscale) or "")
    assert "processed at 160×120 px (--downscale 4)" in (undersampled((640, 480), 4) or "")


def test_a_video_that_does_not_read_is_one_line_at_start_up(tmp_path: Path) -> None:
    """FFmpeg's own reason ("moov atom not found") came as a second line."""
    video = tmp_path / "notavideo.mp4"
    video.write_bytes(b"not a video")
    calib = _calibration_file(tmp_path)
    done = run_overgrid("depth", "--pair", "p0", "--calib", str(calib), "--images", str(video))
    assert_one_line_exit_2(done, "--images", "notavideo.mp4")


def test_a_recording_that_gives_no_tile_exits_1_saying_why(tmp_path: Path) -> None:
    """Every frame rejected (unreadable files here; a wrong size or pixel type the same) ended
    with exit 0, as a recording that mapped."""
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for index in range(3):
            (tmp_path / side / f"{index}.png").write_bytes(b"not a png")
    done = run_overgrid(
        "depth",
        "--pair",
        "p0",
        "--calib",
        str(_calibration_file(tmp_path)),
        "--images",
        str(tmp_path),
        "--rate-hz",
        "20",
        "--no-multicast-scouting",
        "--namespace",
        f"test_no_tile_{os.getpid()}",
    )
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    assert "no frame became a tile (rejected {'undecodable': 3})" in done.stderr


def test_one_wildcard_health_query_gets_every_pair(bus: Bus) -> None:
    bus.start("camera-sim", "--pair-count", "2", "--rate-hz", "1", "--frames", "200")
    bus.start("depth", "--pair", "p0")
    bus.start("depth", "--pair", "p1")

    def pairs_answering() -> set[str]:
        replies = bus.session.get(keys.DEPTH_HEALTH_ALL, timeout=3.0)
        return {json.loads(r.ok.payload.to_string())["pair"] for r in replies if r.ok is not None}

    wait_for(lambda: pairs_answering() == {"p0", "p1"}, 60, "health answers of p0 and p1")


def _calibration_file(tmp_path: Path, pair: str = "p0") -> Path:
    calib = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0].model_copy(update={"pair": pair})
    path = tmp_path / f"{pair}.yaml"
    path.write_text(yaml.safe_dump(calib.model_dump(mode="json")))
    return path


def _health_answers(session: zenoh.Session, pair: str) -> list[dict[str, Any]]:
    """Every process's answer: two on one key would be consolidated into one by default."""
    replies = session.get(
        keys.depth_health(pair), timeout=3.0, consolidation=zenoh.ConsolidationMode.NONE
    )
    return [json.loads(r.ok.payload.to_string()) for r in replies if r.ok is not None]


def test_two_depth_processes_on_one_pair_see_each_other(bus: Bus, tmp_path: Path) -> None:
    calib = _calibration_file(tmp_path)
    logs = [tmp_path / "first.log", tmp_path / "second.log"]
    first = bus.start("depth", "--pair", "p0", "--calib", str(calib), log_path=logs[0])
    wait_for(lambda: len(_health_answers(bus.session, "p0")) == 1, 60, "the first process")
    [alone] = _health_answers(bus.session, "p0")
    assert alone["conflict"] == [] and alone["instance"]

    bus.start("depth", "--pair", "p0", "--calib", str(calib), log_path=logs[1])
    bus.start("depth", "--pair", "p1", "--calib", str(_calibration_file(tmp_path, "p1")))

    def conflicted() -> bool:
        answers = _health_answers(bus.session, "p0")
        return len(answers) == 2 and all(a["conflict"] for a in answers)

    wait_for(conflicted, 60, "both processes of p0 to report the other")
    one, two = _health_answers(bus.session, "p0")
    assert one["conflict"] == [two["instance"]] and two["conflict"] == [one["instance"]]
    wait_for(lambda: len(_health_answers(bus.session, "p1")) == 1, 60, "p1's process")
    assert _health_answers(bus.session, "p1")[0]["conflict"] == []  # another pair is no claim
    owners = set()
    for log in logs:
        wait_for(
            cast(Callable[[], bool], lambda log=log: "claims this pair" in log.read_text()),
            10,
            "the warning",
        )
        [warning] = [line for line in log.read_text().splitlines() if "claims this pair" in line]
        fields = dict(f.split("=", 1) for f in warning.split() if "=" in f)
        assert fields["level"] == "warning"
        assert {fields["instance"], fields["other_instance"]} == {one["instance"], two["instance"]}
        owners.add(fields["instance"])
    assert len(owners) == 2  # each process names the other

    bus.kill(first)  # the survivor says the conflict is over
    wait_for(
        lambda: [a["conflict"] for a in _health_answers(bus.session, "p0")] == [[]],
        15,
        "the survivor alone",
    )


def test_a_pair_no_camera_answers_for_is_told_which_pairs_are(bus: Bus, tmp_path: Path) -> None:
    """``depth --pair p7`` beside cameras of p0 only logged "waiting for calibration" each second,
    forever, and nothing else."""
    good = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]

    def on_calib(query: zenoh.Query) -> None:
        query.reply(keys.calib("p0"), encode(CALIB_KIND, good), encoding=WIRE_ENCODING)

    queryable = bus.session.declare_queryable(keys.calib("p0"), on_calib)
    log = tmp_path / "p7.log"
    bus.start("depth", "--pair", "p7", log_path=log)
    wait_for(lambda: "pairs_answering=p0" in log.read_text(), 40, "the pairs answering named")
    [line] = [row for row in log.read_text().splitlines() if "pairs_answering" in row]
    assert "level=warning" in line and "no calibration yet" in line and "cam/p7/calib" in line
    queryable.undeclare()  # type: ignore[no-untyped-call]


def test_an_unusable_calibration_over_zenoh_is_counted_and_a_good_one_later_used(
    bus: Bus, tmp_path: Path
) -> None:
    good = layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]
    absurd = good.model_dump()
    absurd["right"]["T_world_cam"][0][3] = 1000.0  # a 1000 m baseline passes field validation
    payloads = [encode(CALIB_KIND, StereoCalibration.model_validate(absurd)), b"\x93garbage"]
    answer = {"payload": payloads[0]}

    def on_calib(query: zenoh.Query) -> None:
        if answer["payload"] == b"error":
            query.reply_err("camera not ready")
        else:
            query.reply(keys.calib("p0"), answer["payload"], encoding=WIRE_ENCODING)

    queryable = bus.session.declare_queryable(keys.calib("p0"), on_calib)
    depth = bus.start("depth", "--pair", "p0")

    def state() -> dict[str, Any]:
        answers = _health_answers(bus.session, "p0")
        return answers[0] if answers else {}

    wait_for(
        lambda: state().get("calibration_rejected", {}).get("unusable", 0) >= 2,
        60,
        "the absurd calibration refused twice (the process keeps asking)",
    )
    assert state()["state"] == "waiting_for_calibration" and depth.poll() is None
    answer["payload"] = payloads[1]
    wait_for(
        lambda: state().get("calibration_rejected", {}).get("malformed", 0) >= 1,
        20,
        "the malformed calibration counted",
    )
    # An error reply was skipped uncounted; another pair's calibration (a pair id no key may
    # hold, even) was used with a warning.
    answer["payload"] = b"error"
    wait_for(
        lambda: state().get("calibration_rejected", {}).get("error_reply", 0) >= 1,
        20,
        "the error reply counted",
    )
    answer["payload"] = encode(CALIB_KIND, good.model_copy(update={"pair": "p1"}))
    wait_for(
        lambda: state().get("calibration_rejected", {}).get("wrong_pair", 0) >= 1,
        20,
        "another pair's calibration refused",
    )
    assert state()["state"] == "waiting_for_calibration"
    answer["payload"] = encode(CALIB_KIND, good)
    wait_for(lambda: state().get("state") == "running", 30, "the good calibration used")
    assert "p0" in _alive(bus.session) and state()["recalibrated"] == 0
    # The camera restarts with another calibration (the rig a metre lower): the process, which
    # kept the first for good, mapped the floor as obstacles everywhere.
    lower = RigSpec(pair_count=1).model_copy(update={"height_m": 5.0})
    answer["payload"] = encode(CALIB_KIND, layout_pairs(lower, (12.0, 10.0))[0])
    wait_for(lambda: state().get("recalibrated") == 1, 30, "the new calibration used")
    time.sleep(2 * CALIB_RECHECK_S + 1.0)  # and used once: the same again is no change
    assert state()["recalibrated"] == 1 and depth.poll() is None
    queryable.undeclare()  # type: ignore[no-untyped-call]


def test_tiles_no_fusion_takes_are_said_whether_fusion_answers_or_not(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A recording replayed with no fusion running gave its tiles to nobody, exit 0, and said
    nothing; a fusion that answers but takes none was already said."""
    intake = FusionIntake("p0", silent_after_s=10.0)
    start = intake.answered_s
    with caplog.at_level("INFO", logger="depth"):
        intake.check(None, start + 5.0)
        assert "no fusion answers" not in caplog.text  # not yet: fusion may be starting
        intake.check(None, start + 11.0)
        assert caplog.text.count("no fusion answers") == 1
        intake.check(None, start + 20.0)
        assert caplog.text.count("no fusion answers") == 1  # once, not every period
        intake.check({"pairs": {"p0": {"tiles": 3}}}, start + 21.0)
        assert "fusion answers again" in caplog.text


class _Verdicts:
    """A pipeline's ``swapped`` answers, in turn (None: the frame cannot tell)."""

    def __init__(self, *verdicts: str | bool | Exception | None) -> None:
        self.verdicts, self.asked = list(verdicts), 0

    def swapped(self, left: np.ndarray, right: np.ndarray) -> str | bool | None:
        self.asked += 1
        verdict = self.verdicts.pop(0) if self.verdicts else None
        if isinstance(verdict, Exception):
            raise verdict
        return verdict


def test_a_live_camera_is_asked_whether_it_looks_swapped_until_a_frame_tells() -> None:
    """The first frame only was asked: a dark one (auto-exposure settling) told nothing, and the
    camera was never judged. It is asked until a frame tells, SWAP_TRIES frames at most."""
    frame = np.zeros((480, 640), np.uint8)
    told = _Verdicts(None, None, "left and right the other way round")
    worker = Worker(told, None, None)  # type: ignore[arg-type]
    for _ in range(5):
        worker.check_swap(frame, frame)
    assert told.asked == 3 and worker.swapped == "left and right the other way round"
    never = _Verdicts()
    worker = Worker(never, None, None)  # type: ignore[arg-type]
    for _ in range(SWAP_TRIES + 10):
        worker.check_swap(frame, frame)
    assert never.asked == SWAP_TRIES and worker.swapped is None
    # The check failing (OpenCV, memory) must not cost the frame: it is given up, not raised.
    failing = _Verdicts(MemoryError("cannot allocate"))
    worker = Worker(failing, None, None)  # type: ignore[arg-type]
    for _ in range(3):
        worker.check_swap(frame, frame)
    assert failing.asked == 1 and worker.swapped is None


def test_the_summary_says_no_floor_and_each_period_with_blank_frames(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The summary's floor warnings, period by period: a blank frame in a period (the counter
    of a rebuilt pipeline starting again from 0 included: 20 after 500 went unsaid), and a
    floor model that finds no floor."""
    answers = [
        {"received": 1, "floor_model": {"state": "ready", "blank_frames": 500}},
        {"received": 2, "floor_model": {"state": "ready", "blank_frames": 500}},
        {"received": 3, "floor_model": {"state": "learning", "blank_frames": 20}},  # rebuilt
        {"received": 4, "floor_model": {"state": "no_floor", "blank_frames": 20}},
    ]
    stop = threading.Event()

    def health() -> dict[str, Any]:
        if len(answers) == 1:
            stop.set()
        return answers.pop(0)

    _summaries("p0", health, lambda: None, 0.01, stop)
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    blank = [m for m in said if m.startswith("the camera's images showed nothing")]
    assert len(blank) == 2, said  # the first period's 500, the rebuilt pipeline's 20
    assert sum(m.startswith("the floor model finds no floor") for m in said) == 1
