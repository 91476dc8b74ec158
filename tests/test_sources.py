"""Recordings and calibration files, as a site's own cameras give them to ``overgrid depth``."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from common.camera import StereoCalibration
from common.codec import encode
from common.messages import STEREO_KIND, StereoFrameHeader
from services.camera_sim.capture import CameraModel, StereoCapture
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import generate_scene
from services.depth.intake import Rejection, build_pipeline, check_images, decode_stereo_frame
from services.depth.pipeline import PipelineConfig
from services.depth.sources import InputError, check_recording, load_calibration, recorded_frames


def _calibration() -> StereoCalibration:
    return layout_pairs(RigSpec(pair_count=1), (12.0, 10.0))[0]


def _write(path: Path, value: int, shape: tuple[int, ...] = (480, 640)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


def test_frames_play_in_the_numbers_order_and_pair_by_name_without_their_side(
    tmp_path: Path,
) -> None:
    """``0, 1, 10, 11, 2`` was the order of ``0.png … 11.png``; a driver's ``left_0001.png`` /
    ``right_0001.png`` did not pair."""
    for index in (0, 1, 2, 10, 11):
        _write(tmp_path / "left" / f"left_{index}.png", index)
        _write(tmp_path / "right" / f"right_{index}.png", 100 + index)
    frames = list(recorded_frames(tmp_path))
    assert [(int(left[0, 0]), int(right[0, 0])) for left, right in frames] == [  # type: ignore[misc]
        (i, 100 + i) for i in (0, 1, 2, 10, 11)
    ]


def test_names_pair_as_they_are_first_and_only_a_whole_side_word_is_set_aside(
    tmp_path: Path,
) -> None:
    """``cleft_01.png`` on both sides, or ``²`` in a name, were refused; two names of one frame
    once the side's word is gone are refused, not one dropped."""
    for name in ("cleft_01.png", "bright_²_02.png"):
        _write(tmp_path / "same" / "left" / name, 1)
        _write(tmp_path / "same" / "right" / name, 2)
    assert len(list(recorded_frames(tmp_path / "same"))) == 2
    for name in ("1left.png", "left1.png"):
        _write(tmp_path / "twice" / "left" / name, 1)
    _write(tmp_path / "twice" / "right" / "right1.png", 2)
    with pytest.raises(InputError, match=r"1left\.png and left1\.png in left/ are one frame's"):
        check_recording(tmp_path / "twice")


def test_folders_that_do_not_pair_name_the_files_and_empty_ones_are_refused(
    tmp_path: Path,
) -> None:
    for name in ("0001.png", "0002.png"):
        _write(tmp_path / "left" / name, 0)
    _write(tmp_path / "right" / "0001.png", 0)
    with pytest.raises(InputError, match=r"left only \['0002.png'\], right only none"):
        check_recording(tmp_path)
    empty = tmp_path / "empty"
    (empty / "left").mkdir(parents=True)
    (empty / "right").mkdir()
    with pytest.raises(InputError, match="hold no images"):
        check_recording(empty)


def test_a_recording_of_the_wrong_size_is_refused_at_start_up_naming_its_first_file(
    tmp_path: Path,
) -> None:
    """It ran to its end with every frame rejected as ``wrong_size``, no tile, exit 0."""
    _write(tmp_path / "left" / "0000.png", 0, (500, 740))
    _write(tmp_path / "right" / "0000.png", 0, (500, 740))
    check_recording(tmp_path)  # a recording, whatever its size
    with pytest.raises(InputError, match=r"0000\.png: wrong_size"):
        check_recording(tmp_path, build_pipeline(_calibration(), PipelineConfig()))
    # Its first file unreadable: the check was skipped, and the recording read to its end.
    (tmp_path / "left" / "0000.png").write_bytes(b"not a png")
    _write(tmp_path / "left" / "0001.png", 0, (500, 740))
    _write(tmp_path / "right" / "0001.png", 0, (500, 740))
    with pytest.raises(InputError, match=r"0001\.png: wrong_size"):
        check_recording(tmp_path, build_pipeline(_calibration(), PipelineConfig()))


def test_a_mono_camera_pairs_with_a_colour_one_and_16_bit_colour_is_taken() -> None:
    gray = np.full((480, 640), 90, np.uint8)
    colour = np.full((480, 640, 3), 90, np.uint8)
    checked = check_images(gray, colour, (640, 480))
    assert not hasattr(checked, "reason") and int(checked[1][0, 0]) == 90
    deep = np.full((480, 640, 3), 90 << 8, np.uint16)
    left, _ = check_images(deep, deep, (640, 480))  # type: ignore[misc]
    assert left.dtype == np.uint8 and int(left[0, 0]) == (90 << 8) >> 7  # brightest kept
    floats = check_images(gray.astype(np.float32), gray, (640, 480))
    assert getattr(floats, "reason", None) == "bad_pixels"


def test_an_opencv_filestorage_calibration_says_which_format_to_write(tmp_path: Path) -> None:
    path = tmp_path / "stereo.yaml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("K1", np.eye(3))
    storage.release()
    with pytest.raises(InputError, match=r"OpenCV FileStorage file.*T_world_cam") as refused:
        load_calibration(path)
    assert str(refused.value).count("--calib") == 1  # it was named twice
    as_json = tmp_path / "stereo.json"  # FileStorage's JSON: a list of fields it does not know
    storage = cv2.FileStorage(str(as_json), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_JSON)
    storage.write("K1", np.eye(3))
    storage.release()
    with pytest.raises(InputError, match=r"OpenCV FileStorage file"):
        load_calibration(as_json)


def test_distortion_as_numpy_writes_it_is_taken(tmp_path: Path) -> None:
    """``D.tolist()`` of OpenCV's 1 × 5 (or 5 × 1) distortion is nested: it was refused with
    "left.dist.0: Input should be a valid number"."""
    data = _calibration().model_dump(mode="json")
    data["left"]["dist"] = [[0.01, 0.0, 0.0, 0.0, 0.0]]
    data["right"]["dist"] = [[0.01], [0.0], [0.0], [0.0], [0.0]]
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump(data))
    calib = load_calibration(path)
    assert calib.left.dist == calib.right.dist == [0.01, 0.0, 0.0, 0.0, 0.0]


def test_a_calibration_in_millimetres_is_refused_before_it_allocates_gigabytes(
    tmp_path: Path,
) -> None:
    """Every pose ×1000 passed every check; the first frame's tile asked for 21 GB."""
    data = _calibration().model_dump(mode="json")
    for side in ("left", "right"):
        for row in data[side]["T_world_cam"][:3]:
            row[3] *= 1000.0
    path = tmp_path / "mm.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="are the poses in metres"):
        build_pipeline(load_calibration(path), PipelineConfig())
    # The baseline alone in millimetres (T of stereoCalibrate in mm): said as such.
    data = _calibration().model_dump(mode="json")
    data["right"]["T_world_cam"][0][3] = data["left"]["T_world_cam"][0][3] + 500.0
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=r"baseline \(500 m: in metres\?\)"):
        build_pipeline(load_calibration(path), PipelineConfig())


def test_a_jpeg_cut_short_is_refused_and_the_recording_goes_on(tmp_path: Path) -> None:
    """libjpeg decodes a file cut short as grey below the cut, with a warning on stderr and no
    error: seven of twelve frames cut at 40 % put phantom obstacles on the floor. Such a file is
    refused (named), as it is over Zenoh, and the frames after it play."""
    rng = np.random.default_rng(0)
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for index in range(3):
            texture = rng.integers(0, 255, (480, 640), np.uint8)
            cv2.imwrite(str(tmp_path / side / f"{side}_{index}.jpg"), texture)
    cut = tmp_path / "left" / "left_1.jpg"
    blob = cut.read_bytes()
    cut.write_bytes(blob[: len(blob) * 4 // 10])
    assert cv2.imread(str(cut)) is not None  # what OpenCV alone makes of it
    frames = list(recorded_frames(tmp_path))
    assert [type(frame).__name__ for frame in frames] == ["tuple", "Rejection", "tuple"]
    assert str(cut) in frames[1].detail  # type: ignore[union-attr]


def test_a_jpeg_frame_cut_short_over_zenoh_is_refused_by_name() -> None:
    texture = np.random.default_rng(1).integers(0, 255, (480, 640), np.uint8)
    blob = cv2.imencode(".jpg", texture)[1].tobytes()
    header = StereoFrameHeader(pair="p0", seq=1, stamp_ns=1, encoding="jpeg")
    whole = encode(STEREO_KIND, header, blobs={"left": blob, "right": blob})
    assert not isinstance(decode_stereo_frame(whole, "p0", (640, 480), 1 << 24), Rejection)
    cut = encode(STEREO_KIND, header, blobs={"left": blob[: len(blob) // 2], "right": blob})
    refused = decode_stereo_frame(cut, "p0", (640, 480), 1 << 24)
    assert isinstance(refused, Rejection) and refused.reason == "undecodable"
    assert "left jpeg image is cut short" in refused.detail
    # Bytes after the end marker (parts cut from an MJPEG stream end in CR LF) are no harm.
    padded = encode(STEREO_KIND, header, blobs={"left": blob + b"\r\n", "right": blob + b"\xff"})
    assert not isinstance(decode_stereo_frame(padded, "p0", (640, 480), 1 << 24), Rejection)


def test_a_recording_with_left_and_right_swapped_is_refused_at_start_up(tmp_path: Path) -> None:
    """Played with its folders swapped, a recording gave a map of phantom obstacles everywhere
    and exit 0; the floor model's warning came 30 s in, if at all. Its first pair is now judged
    at start-up: the floor agrees at its disparity in the other order, not in this one. The same
    frames the right way round start."""
    scene = generate_scene(0)
    calibrations = layout_pairs(RigSpec(), scene.floor_size_m)
    renderer = SceneRenderer(scene, calibrations)
    capture = StereoCapture(renderer, calibrations[1], CameraModel(), seed=0)
    renderer.set_time(1000.0)
    left, right = capture.capture(1_000_000_000_000)
    renderer.close()
    pipeline = build_pipeline(capture.calibration, PipelineConfig())
    for name, first, second in (("right_way", left, right), ("swapped", right, left)):
        for side, image in (("left", first), ("right", second)):
            (tmp_path / name / side).mkdir(parents=True)
            cv2.imwrite(str(tmp_path / name / side / f"{side}_0.png"), image)
    check_recording(tmp_path / "right_way", pipeline)
    with pytest.raises(InputError, match="left and right the other way round"):
        check_recording(tmp_path / "swapped", pipeline)
