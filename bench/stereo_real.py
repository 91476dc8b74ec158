"""The depth chain on real stereo photographs with ground truth, next to OpenCV's reference SGBM.

Runs ``services.depth.stereo.compute_disparity`` (the depth service's chain) on a rectified pair:
the configured chain, SGBM alone with the project's settings (no optional stage), the configured
chain with each optional stage toggled, and SGBM with the settings of OpenCV's stereo_match sample,
all on one core in the same run. Default data: Middlebury 2014 Motorcycle as scikit-image ships it
(741×500, a quarter of the full resolution). Your own cameras: ``--left L --right R --gt GT`` with
a rectified pair and its left-view disparity (PNG, TIFF, PFM or NPZ; ``--gt-scale`` turns stored
values into pixels, e.g. 1/256 for KITTI's 16-bit PNGs).

Scoring (:func:`score_disparity`): only pixels whose ground truth is known (finite, > 0;
Middlebury marks unknown with inf, KITTI with 0) and visible in the right image
(:func:`non_occluded`: no stereo method can match a pixel the right camera does not see). ``valid``
is the share of those pixels with a disparity; bad-0.5/1/2 px and the median error are over the
valid ones. The search band comes from the ground truth's range (±1 px, rounded up to 16), as the
depth service derives it from the floor-to-2-m geometry; ``--band MIN,NUM`` fixes it instead.

    .venv/bin/python bench/stereo_real.py [--repeats 7] [--left L --right R --gt GT [--gt-scale S]]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from common.arrays import F32, U8, Mask
from services.depth.stereo import MatcherConfig, compute_disparity, stage_variants

BAD_THRESHOLDS_PX = (0.5, 1.0, 2.0)
OCCLUSION_TOL_PX = 1.0
"""A pixel is hidden in the right view when a pixel nearer by more than this lands on its column."""


@dataclasses.dataclass(frozen=True)
class Scores:
    valid: float
    """Share of the scored pixels that have a disparity."""
    bad_05px: float
    bad_1px: float
    bad_2px: float
    """Shares of the valid pixels whose error exceeds 0.5, 1, 2 px."""
    median_err_px: float


def score_disparity(disparity_px: F32, gt_px: F32, scored: Mask) -> Scores:
    """Scores of ``disparity_px`` (NaN: no disparity) against ``gt_px`` over the ``scored`` pixels."""
    valid = scored & np.isfinite(disparity_px)
    error_px = np.abs(disparity_px[valid] - gt_px[valid])
    count = max(int(valid.sum()), 1)
    bad = [float((error_px > t).sum()) / count for t in BAD_THRESHOLDS_PX]
    return Scores(
        valid=float(valid.sum()) / max(int(scored.sum()), 1),
        bad_05px=bad[0],
        bad_1px=bad[1],
        bad_2px=bad[2],
        median_err_px=float(np.median(error_px)) if error_px.size else math.nan,
    )


def known(gt_px: F32) -> Mask:
    """Pixels with ground truth: finite and positive (unknown is inf in Middlebury, 0 in KITTI)."""
    with np.errstate(invalid="ignore"):
        result: Mask = np.isfinite(gt_px) & (gt_px > 0)
    return result


def non_occluded(gt_px: F32) -> Mask:
    """Known pixels the right camera also sees, from the ground truth alone: the match x − d lies
    inside the right image, and no nearer pixel (larger disparity by > OCCLUSION_TOL_PX) lands on
    the same right-image column (a z-buffer of the left view warped into the right)."""
    height, width = gt_px.shape
    rows, cols = np.nonzero(known(gt_px))
    disparity = gt_px[rows, cols]
    right_col = np.round(cols - disparity).astype(np.int64)
    inside = right_col >= 0
    rows, cols, disparity, right_col = (
        rows[inside],
        cols[inside],
        disparity[inside],
        right_col[inside],
    )
    nearest = np.full((height, width), -np.inf, np.float32)
    np.maximum.at(nearest, (rows, right_col), disparity)
    seen = disparity >= nearest[rows, right_col] - OCCLUSION_TOL_PX
    result = np.zeros((height, width), bool)
    result[rows[seen], cols[seen]] = True
    return result


def search_band(gt_px: F32) -> tuple[int, int]:
    """(min_disparity, num_disparities) covering the ground truth's range ±1 px, a multiple of 16."""
    values = gt_px[known(gt_px)]
    d_min = math.floor(float(values.min())) - 1
    d_max = math.ceil(float(values.max())) + 1
    return d_min, 16 * math.ceil((d_max - d_min) / 16)


def read_pfm(path: Path) -> F32:
    """A Portable Float Map (Middlebury's format): rows stored bottom to top, endianness in the
    sign of the scale."""
    data = path.read_bytes()
    match = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+(\S+)\s", data)
    if match is None:
        raise ValueError(f"{path}: not a PFM file")
    channels = 3 if match.group(1) == b"PF" else 1
    width, height, scale = int(match.group(2)), int(match.group(3)), float(match.group(4))
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    values = np.frombuffer(data, dtype, count=width * height * channels, offset=match.end())
    image = values.reshape(height, width, channels)[::-1, :, 0]
    return np.ascontiguousarray(image, dtype=np.float32)


def read_disparity(path: Path, scale: float) -> F32:
    """Ground-truth disparity in pixels (stored values × ``scale``); unknown stays 0/inf/NaN."""
    suffix = path.suffix.lower()
    raw: np.ndarray
    if suffix == ".pfm":
        raw = read_pfm(path)
    elif suffix == ".npz":
        with np.load(path) as archive:
            name = "disparity" if "disparity" in archive else archive.files[0]
            raw = archive[name]
    else:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"{path}: not an image OpenCV can read")
        raw = image if image.ndim == 2 else image[:, :, 0]
    return (np.asarray(raw, dtype=np.float32) * np.float32(scale)).astype(np.float32)


def read_gray(path: Path) -> U8:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: not an image OpenCV can read")
    return np.asarray(image, dtype=np.uint8)


def motorcycle() -> tuple[U8, U8, F32]:
    """Middlebury 2014 Motorcycle from scikit-image (its wheel ships it; NaN marks unknown)."""
    from skimage import data

    left, right, gt_px = data.stereo_motorcycle()  # type: ignore[no-untyped-call]
    gray = [np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)) for image in (left, right)]
    return gray[0], gray[1], np.asarray(gt_px, dtype=np.float32)


def opencv_reference(left: U8, right: U8, min_disparity: int, num_disparities: int) -> F32:
    """OpenCV's stereo_match sample settings for one channel: SGBM (5 paths), blockSize 3,
    P1 = 8·bs², P2 = 32·bs², preFilterCap 63, uniquenessRatio 10, speckle 100/32, disp12MaxDiff 1."""
    bs = 3
    matcher = cv2.StereoSGBM.create(
        minDisparity=min_disparity,
        numDisparities=num_disparities,
        blockSize=bs,
        P1=8 * bs * bs,
        P2=32 * bs * bs,
        disp12MaxDiff=1,
        preFilterCap=63,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=32,
        mode=cv2.STEREO_SGBM_MODE_SGBM,
    )
    raw = np.asarray(matcher.compute(left, right))
    disparity: F32 = raw.astype(np.float32) / np.float32(16.0)
    disparity[raw < min_disparity * 16] = np.nan
    return disparity


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--left", type=Path, help="rectified left image")
    parser.add_argument("--right", type=Path, help="rectified right image")
    parser.add_argument("--gt", type=Path, help="left-view ground-truth disparity")
    parser.add_argument("--gt-scale", type=float, default=1.0, help="stored GT value → pixels")
    parser.add_argument("--band", help="MIN,NUM: search band (default: from the GT's range)")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per variant")
    args = parser.parse_args()
    cv2.setNumThreads(1)

    if args.left or args.right or args.gt:
        if not (args.left and args.right and args.gt):
            parser.error("--left, --right and --gt go together")
        left, right = read_gray(args.left), read_gray(args.right)
        gt_px = read_disparity(args.gt, args.gt_scale)
        name = f"{args.left.name} / {args.right.name}"
    else:
        left, right, gt_px = motorcycle()
        name = "Middlebury 2014 Motorcycle (scikit-image)"
    if not left.shape == right.shape == gt_px.shape:
        raise SystemExit(f"sizes differ: left {left.shape}, right {right.shape}, GT {gt_px.shape}")
    if args.band:
        min_disparity, num_disparities = (int(v) for v in args.band.split(","))
    else:
        min_disparity, num_disparities = search_band(gt_px)
    scored = non_occluded(gt_px)
    all_known = known(gt_px)

    def chain(config: MatcherConfig) -> Callable[[], F32]:
        return lambda: compute_disparity(left, right, min_disparity, num_disparities, config)

    runs = {label: chain(config) for label, config in stage_variants(MatcherConfig()).items()}
    runs["opencv_ref"] = lambda: opencv_reference(left, right, min_disparity, num_disparities)
    times_ms: dict[str, list[float]] = {label: [] for label in runs}
    outputs: dict[str, F32] = {}
    for _ in range(args.repeats):  # interleaved, so drift in machine load hits every variant alike
        for label, run in runs.items():
            started = time.perf_counter()
            outputs[label] = run()
            times_ms[label].append((time.perf_counter() - started) * 1e3)

    print(
        f"{name}: {left.shape[1]}×{left.shape[0]}, band {min_disparity}+{num_disparities} px, "
        f"scored {scored.sum()} px (known {all_known.mean():.1%}, of which non-occluded "
        f"{scored.sum() / all_known.sum():.1%}), one core"
    )
    print(
        f"{'variant':18}{'valid':>7}{'bad0.5':>8}{'bad1':>7}{'bad2':>7}{'median':>8}{'ms':>7}"
        f"{'valid(all known)':>18}"
    )
    results: dict[str, dict[str, float]] = {}
    for label, disparity in outputs.items():
        scores = score_disparity(disparity, gt_px, scored)
        ms = statistics.median(times_ms[label])
        results[label] = {
            **{k: round(v, 4) for k, v in dataclasses.asdict(scores).items()},
            "ms": round(ms, 1),
            "valid_all_known": round(score_disparity(disparity, gt_px, all_known).valid, 4),
        }
        print(
            f"{label:18}{scores.valid:>7.3f}{scores.bad_05px:>8.2%}{scores.bad_1px:>7.2%}"
            f"{scores.bad_2px:>7.2%}{scores.median_err_px:>8.3f}{ms:>7.1f}"
            f"{results[label]['valid_all_known']:>18.3f}"
        )
    ratio = results["configured"]["ms"] / results["sgbm"]["ms"]
    print(f"configured / SGBM alone: {ratio:.2f}× the time")
    summary = {
        "data": name,
        "band": [min_disparity, num_disparities],
        **results["configured"],
        "ms_vs_sgbm": round(ratio, 3),
        "opencv_ref": results["opencv_ref"],
        "variants": {k: v for k, v in results.items() if k not in ("configured", "opencv_ref")},
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
