"""Inputs of the depth service besides the pipeline: calibration files and recorded stereo images.

Recorded images go through exactly the same pipeline as Zenoh frames, so real cameras can replace the
simulator. Supported: a folder with ``left/`` and ``right/`` sub-folders (matching sorted file
names), a folder of ``*_left.*`` / ``*_right.*`` files, or a side-by-side video (left | right).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import yaml
from pydantic import ValidationError

from common.camera import StereoCalibration
from services.depth.intake import Rejection

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"}


class InputError(ValueError):
    """A calibration or recording that cannot be used; the message names the file."""


def load_calibration(path: Path) -> StereoCalibration:
    """A YAML or JSON file with the fields of :class:`StereoCalibration` (see README)."""
    try:
        text = Path(path).read_text()
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
        return StereoCalibration.model_validate(data)
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


def check_recording(source: Path) -> None:
    """Fail at start-up, not at the first frame, on a recording that is not there or not one."""
    if source.is_dir():
        try:
            _image_pairs(source)
        except ValueError as error:
            raise InputError(f"--images {source}: {error}") from None
    elif not source.exists():
        raise InputError(f"--images {source}: no such folder or video file")
    else:
        capture = _video(source)
        opened = capture.isOpened()
        capture.release()
        if not opened:
            raise InputError(f"--images {source}: not a folder of image pairs or a readable video")


def _image_pairs(folder: Path) -> list[tuple[Path, Path]]:
    def images(directory: Path, pattern: str = "*") -> list[Path]:
        return sorted(p for p in directory.glob(pattern) if p.suffix.lower() in IMAGE_SUFFIXES)

    if (folder / "left").is_dir() and (folder / "right").is_dir():
        lefts, rights = images(folder / "left"), images(folder / "right")
        if [p.name for p in lefts] != [p.name for p in rights]:
            raise ValueError(f"{folder}/left and {folder}/right do not hold the same file names")
        return list(zip(lefts, rights, strict=True))
    lefts = images(folder, "*_left.*")
    pairs = [(p, p.with_name(p.name.replace("_left.", "_right."))) for p in lefts]
    missing = [str(r) for _, r in pairs if not r.exists()]
    if missing:
        raise ValueError(f"right images missing for: {missing[:3]}")
    if not pairs:
        raise ValueError(f"{folder} holds no left/ and right/ folders and no *_left.* images")
    return pairs


def recorded_frames(source: Path) -> Iterator[tuple[np.ndarray, np.ndarray] | Rejection]:
    """Stereo frames from a folder of image pairs or a side-by-side video file; a pair that does
    not read is a rejection, and the recording goes on."""
    if source.is_dir():
        for left_path, right_path in _image_pairs(source):
            # Unchanged: 16-bit files are reduced as 16-bit frames are (colour files read as BGR
            # swap the gray weights of red and blue, alike in both images).
            left = cv2.imread(str(left_path), cv2.IMREAD_UNCHANGED)
            right = cv2.imread(str(right_path), cv2.IMREAD_UNCHANGED)
            if left is None or right is None:
                yield Rejection("undecodable", f"cannot read {left_path} or {right_path}")
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
