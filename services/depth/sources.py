"""Inputs of the depth service besides the pipeline: calibration files and recorded stereo images.

Recorded images go through exactly the same pipeline as Zenoh frames, so real cameras can replace the
simulator. Supported: a folder with ``left/`` and ``right/`` sub-folders (the same file names, or
names that differ only by the words left and right: ``left_0001.png`` / ``right_0001.png``), a
folder of ``*_left.*`` / ``*_right.*`` files, or a side-by-side video (left | right). Frames play
in the numbers' order (``2.png`` before ``10.png``).
"""

from __future__ import annotations

import itertools
import os
import re
from collections.abc import Generator
from pathlib import Path

import cv2
import numpy as np
import yaml
from pydantic import ValidationError

from common.camera import StereoCalibration
from common.setting_files import data_of, setting_file_text
from services.depth.intake import Rejection, check_images, decoded_image, jpeg_complete
from services.depth.pipeline import DepthPipeline

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"}


class InputError(ValueError):
    """A calibration or recording that cannot be used; the message names the file."""


def load_calibration(path: Path) -> StereoCalibration:
    """A YAML or JSON file with the fields of :class:`StereoCalibration` (see README)."""
    try:
        text = setting_file_text(Path(path))
        if text.lstrip().startswith("%YAML:1.0") or "opencv-matrix" in text:  # YAML or JSON
            raise InputError(
                f"--calib {path}: an OpenCV FileStorage file, which overgrid does not read: write "
                "each camera's width, height, K, dist and T_world_cam (the camera's pose in the "
                "world) as plain YAML or JSON (README, Real cameras: from OpenCV's stereoCalibrate)"
            )
        return StereoCalibration.model_validate(data_of(text, path))
    except InputError:
        raise
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'file'}: {e['msg']}" for e in error.errors()
        )
        raise InputError(f"--calib {path}: {problems}") from None
    except (OSError, ValueError, yaml.YAMLError) as error:
        raise InputError(f"--calib {path}: {' '.join(str(error).split())}") from None


def _video(source: Path) -> cv2.VideoCapture:
    """A video capture of ``source``, FFmpeg's own messages off (unless OPENCV_FFMPEG_LOGLEVEL
    asks for them): its reason for a file it cannot read ("moov atom not found") went to stderr
    beside overgrid's one line."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    return cv2.VideoCapture(str(source))


CHECKED_FRAMES = 10
"""A recording's pairs read at start-up for the first that decodes (:func:`check_recording`)."""


def check_recording(source: Path, pipeline: DepthPipeline | None = None) -> None:
    """Fail at start-up, not at the first frame, on a recording that is not there or not one; with
    the calibration's ``pipeline``, also on one whose first readable pair (of the first
    CHECKED_FRAMES) it cannot take (the wrong size, pixels of no gray scale: every frame of it
    would be refused) or whose left and right look swapped (:meth:`DepthPipeline.swapped`: every
    tile would be phantom obstacles)."""
    names: list[str] = []
    if source.is_dir():
        try:
            names = [left.name for left, _ in _image_pairs(source)]
        except ValueError as error:
            raise InputError(f"--images {source}: {error}") from None
    elif not source.exists():
        raise InputError(f"--images {source}: no such folder or video file")
    elif not source.is_file():  # a pipe or a device: reading it would block the start for good
        raise InputError(f"--images {source}: not a folder of image pairs or a video file")
    else:
        capture = _video(source)
        opened = capture.isOpened()
        capture.release()
        if not opened:
            raise InputError(f"--images {source}: not a folder of image pairs or a readable video")
    if pipeline is None:
        return
    frames = recorded_frames(source)
    read, readable = 0, None
    try:
        for index, frame in enumerate(itertools.islice(frames, CHECKED_FRAMES)):
            read += 1
            if not isinstance(frame, Rejection):
                readable = index, frame
                break
    finally:
        frames.close()
    if read == 0:
        raise InputError(f"--images {source}: the video holds no frame")
    if readable is None:  # unreadable files are refused as the recording plays, and it goes on
        return
    index, frame = readable
    name = names[index] if names else f"frame {index}"
    checked = check_images(*frame, pipeline.calib.image_size)
    if isinstance(checked, Rejection):
        raise InputError(f"--images {source}: {name}: {checked.reason}: {checked.detail}")
    swapped = pipeline.swapped(*checked)
    if isinstance(swapped, str):
        raise InputError(f"--images {source}: {name}: {swapped}")


def _natural_key(path: Path) -> list[tuple[int, int | str]]:
    """The name's runs of digits as numbers: ``2.png`` before ``10.png``."""
    parts = re.split(r"([0-9]+)", path.name)  # odd parts are the runs of ASCII digits
    return [(0, int(part)) if k % 2 else (1, part) for k, part in enumerate(parts) if part]


def _side_free(name: str, side: str) -> str:
    """A file name without the word of its side: ``left_0001.png`` and ``right_0001.png`` pair
    (a whole word only: ``cleft_01.png`` keeps its name)."""
    return re.sub(rf"(?<![a-z]){side}(?![a-z])", "", name, flags=re.IGNORECASE)


def _by_name(paths: list[Path], side: str) -> dict[str, Path]:
    """``paths`` by name without the side's word; two files of one name that way are refused."""
    named: dict[str, Path] = {}
    for path in paths:
        key = _side_free(path.name, side)
        if key in named:
            raise ValueError(f"{named[key].name} and {path.name} in {side}/ are one frame's name")
        named[key] = path
    return named


def _image_pairs(folder: Path) -> list[tuple[Path, Path]]:
    def images(directory: Path, pattern: str = "*") -> list[Path]:
        found = (p for p in directory.glob(pattern) if p.suffix.lower() in IMAGE_SUFFIXES)
        return sorted(found, key=_natural_key)

    if (folder / "left").is_dir() and (folder / "right").is_dir():
        lefts, rights = images(folder / "left"), images(folder / "right")
        if not lefts and not rights:
            raise ValueError(f"{folder}/left and {folder}/right hold no images")
        if [p.name for p in lefts] == [p.name for p in rights]:
            return list(zip(lefts, rights, strict=True))
        by_name, right_by_name = _by_name(lefts, "left"), _by_name(rights, "right")
        if by_name.keys() != right_by_name.keys():
            only_left = [p.name for k, p in by_name.items() if k not in right_by_name][:3]
            only_right = [p.name for k, p in right_by_name.items() if k not in by_name][:3]
            raise ValueError(
                f"{folder}/left and {folder}/right do not hold the same images: "
                f"left only {only_left or 'none'}, right only {only_right or 'none'}"
            )
        return [(path, right_by_name[key]) for key, path in by_name.items()]
    lefts = images(folder, "*_left.*")
    pairs = [(p, p.with_name(p.name.replace("_left.", "_right."))) for p in lefts]
    missing = [str(r) for _, r in pairs if not r.exists()]
    if missing:
        raise ValueError(f"right images missing for: {missing[:3]}")
    if not pairs:
        raise ValueError(f"{folder} holds no left/ and right/ folders and no *_left.* images")
    return pairs


def _read_image(path: Path) -> np.ndarray | None:
    """The image file's pixels, unchanged (16-bit files are reduced as 16-bit frames are; colour
    files read as BGR swap the gray weights of red and blue, alike in both images); None if it
    does not decode, or is a JPEG cut short (libjpeg decodes those as grey below the cut)."""
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    if path.suffix.lower() in (".jpg", ".jpeg") and not jpeg_complete(blob):
        return None
    return decoded_image(blob)


def recorded_frames(
    source: Path,
) -> Generator[tuple[np.ndarray, np.ndarray] | Rejection, None, None]:
    """Stereo frames from a folder of image pairs or a side-by-side video file; a pair that does
    not read is a rejection, and the recording goes on."""
    if source.is_dir():
        for left_path, right_path in _image_pairs(source):
            left, right = _read_image(left_path), _read_image(right_path)
            if left is None or right is None:
                unread = [str(p) for p, i in ((left_path, left), (right_path, right)) if i is None]
                yield Rejection("undecodable", f"cannot read {' nor '.join(unread)}")
            else:
                yield left, right
        return
    capture = _video(source)
    if not capture.isOpened():
        raise ValueError(f"cannot open {source} as a folder of image pairs or a video")
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            half = gray.shape[1] // 2
            yield gray[:, :half], gray[:, half:]
    finally:
        capture.release()
