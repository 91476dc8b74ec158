"""Depth pipeline benchmark: the seed project's pipeline vs ours, same frames, same run, one core.

Frames come from camera_sim as a site has them (default scene, every pair, a few instants): the
renders through the realistic camera model (noise, blur, vignetting, auto-exposure), and the
pair's published calibration, off by a good calibration's residual, is what both pipelines get
(``--ideal-cameras``: noise-free renders, exact calibration). Both pipelines run alternately on
each frame; we print the median per-frame time of each, their ratio, and each one's depth error
against MuJoCo's depth buffer (median absolute, on the floor and on object tops) and valid-pixel
fraction; then the same errors for our disparity chain with each optional stage toggled
(stereo.stage_variants). The last line is a JSON object with the figures.

    .venv/bin/python bench/depth_pipeline.py [--rounds 5] [--instants 3] [--ideal-cameras]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import cv2
import numpy as np

from common.camera import StereoCalibration
from common.codec import encode
from common.messages import TILE_KIND, TileHeader
from services.camera_sim.capture import CameraModel, StereoCapture
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import generate_scene
from services.depth.pipeline import DepthPipeline, PipelineConfig
from services.depth.stereo import MatcherConfig, stage_variants, stereo_rectify

FLOOR_DEPTH_TOL_M = 0.005
TOP_MIN_HEIGHT_M = 0.15


def seed_pipeline(
    calib: StereoCalibration, left: np.ndarray, right: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The seed project, as described in the issue: maps recomputed every frame, SGBM 3WAY with
    160 disparities, a 5×5 median blur, reprojectImageTo3D, a height threshold. Returns the depth
    image (rectified left camera z, NaN invalid) and the obstacle mask."""
    size = calib.image_size
    R1, R2, P1, P2, Q = stereo_rectify(calib, calib.left.K_array, calib.right.K_array, size)
    map_l = cv2.initUndistortRectifyMap(
        calib.left.K_array, calib.left.dist_array, R1, P1, size, cv2.CV_32FC1
    )
    map_r = cv2.initUndistortRectifyMap(
        calib.right.K_array, calib.right.dist_array, R2, P2, size, cv2.CV_32FC1
    )
    left_rect = cv2.remap(left, *map_l, cv2.INTER_LINEAR)
    right_rect = cv2.remap(right, *map_r, cv2.INTER_LINEAR)
    matcher = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=160,
        blockSize=5,
        P1=600,
        P2=2400,
        uniquenessRatio=5,
        speckleWindowSize=200,
        speckleRange=2,
        disp12MaxDiff=1,
        preFilterCap=63,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disparity = cv2.medianBlur(matcher.compute(left_rect, right_rect), 5).astype(np.float32) / 16.0
    points = cv2.reprojectImageTo3D(disparity, Q)
    valid = disparity > 0
    depth = np.where(valid, points[:, :, 2], np.nan)
    R_world = calib.left.T_world_cam_array[:3, :3] @ R1.T
    heights = calib.left.position_world[2] + points @ R_world[2]
    return depth, valid & (heights > 0.10)


def ours_to_tile(
    pipeline: DepthPipeline, left: np.ndarray, right: np.ndarray
) -> tuple[bytes, np.ndarray, np.ndarray]:
    """The encoded tile, the disparity chain's depth and the depth the tile was built from (the
    chain's output under the floor model's rules and calibration-offset correction)."""
    result = pipeline.process(left, right)
    window = result.tile.window
    header = TileHeader(
        pair="bench",
        seq=0,
        stamp_ns=0,
        resolution_m=result.tile.resolution_m,
        i0=window.i0,
        j0=window.j0,
        cols=window.cols,
        rows=window.rows,
        stage_ms=result.stage_ms,
    )
    payload = encode(TILE_KIND, header, result.tile.arrays())
    focal_baseline = pipeline.rectifier.focal_px * pipeline.rectifier.baseline_m
    return (
        payload,
        focal_baseline / result.disparity_px,
        focal_baseline / result.evidence_disparity_px,
    )


def depth_errors(depth: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    """(median |err| on floor, median |err| on object tops, valid fraction)."""
    camera_height = float(np.nanmax(truth))
    floor = truth >= camera_height - FLOOR_DEPTH_TOL_M
    tops = truth <= camera_height - TOP_MIN_HEIGHT_M
    valid = np.isfinite(depth)
    err = np.abs(depth - truth)
    return (
        float(np.median(err[floor & valid])),
        float(np.median(err[tops & valid])),
        float(valid.mean()),
    )


Frame = tuple[StereoCalibration, np.ndarray, np.ndarray, np.ndarray]


def render_frames(instants: int, model: CameraModel) -> list[Frame]:
    """(published calibration, left, right, true left depth) for every pair at ``instants`` times."""
    scene = generate_scene(0)
    true_calibrations = layout_pairs(RigSpec(), scene.floor_size_m)
    renderer = SceneRenderer(scene, true_calibrations)
    captures = [StereoCapture(renderer, c, model, seed=0) for c in true_calibrations]
    frames = []
    for instant in range(instants):
        t_s = 7.0 * instant
        renderer.set_time(t_s)
        for capture in captures:
            left, right = capture.capture(int(t_s * 1e9))
            w, h = capture.true_calibration.image_size
            depth = renderer.render_depth(f"{capture.true_calibration.pair}_left", w, h)
            frames.append((capture.calibration, left, right, depth))
    renderer.close()
    return frames


def chain_errors(frames: list[Frame], matcher: MatcherConfig) -> tuple[float, float, float]:
    """Median over frames of :func:`depth_errors` of our disparity chain alone (no floor model)."""
    errors = []
    for calib, left, right, truth in frames:
        pipeline = DepthPipeline(calib, PipelineConfig(matcher=matcher))
        disparity = pipeline.disparity_chain(*pipeline.rectifier.rectify(left, right))
        depth = pipeline.rectifier.focal_px * pipeline.rectifier.baseline_m / disparity
        s = pipeline.config.downscale
        truth_small = cv2.resize(
            truth, (truth.shape[1] // s, truth.shape[0] // s), interpolation=cv2.INTER_AREA
        )
        errors.append(depth_errors(depth, truth_small))
    floor_m, top_m, valid = (float(statistics.median(e[k] for e in errors)) for k in range(3))
    return floor_m, top_m, valid


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=5, help="timed repetitions per frame")
    parser.add_argument("--instants", type=int, default=3, help="scene instants rendered per pair")
    parser.add_argument(
        "--ideal-cameras", action="store_true", help="noise-free renders, exact calibration"
    )
    args = parser.parse_args()
    cv2.setNumThreads(1)

    model = CameraModel.ideal() if args.ideal_cameras else CameraModel()
    print("rendering frames …", file=sys.stderr)
    frames = render_frames(args.instants, model)
    calibrations = {calib.pair: calib for calib, *_ in frames}.values()

    pipelines = {c.pair: DepthPipeline(c, PipelineConfig()) for c in calibrations}
    full_res = {c.pair: DepthPipeline(c, PipelineConfig(downscale=1)) for c in calibrations}
    full_ms: list[float] = []
    full_err: list[tuple[float, float, float]] = []
    seed_ms: list[float] = []
    ours_ms: list[float] = []
    seed_err: list[tuple[float, float, float]] = []
    ours_err: list[tuple[float, float, float]] = []
    evidence_err: list[tuple[float, float, float]] = []
    for index, (calib, left, right, truth) in enumerate(frames):
        pipeline = pipelines[calib.pair]
        s = pipeline.config.downscale
        truth_small = cv2.resize(
            truth, (truth.shape[1] // s, truth.shape[0] // s), interpolation=cv2.INTER_AREA
        )
        per_seed, per_ours = [], []
        for _ in range(args.rounds):  # alternate, so drift in machine load hits both alike
            started = time.perf_counter()
            depth_seed, _ = seed_pipeline(calib, left, right)
            per_seed.append((time.perf_counter() - started) * 1e3)
            started = time.perf_counter()
            _, depth_ours, depth_evidence = ours_to_tile(pipeline, left, right)
            per_ours.append((time.perf_counter() - started) * 1e3)
        seed_ms.append(statistics.median(per_seed))
        ours_ms.append(statistics.median(per_ours))
        started = time.perf_counter()
        _, depth_full, _ = ours_to_tile(full_res[calib.pair], left, right)
        full_ms.append((time.perf_counter() - started) * 1e3)
        full_err.append(depth_errors(depth_full, truth))
        seed_err.append(depth_errors(depth_seed, truth))
        ours_err.append(depth_errors(depth_ours, truth_small))
        evidence_err.append(depth_errors(depth_evidence, truth_small))
        print(
            f"frame {index + 1}/{len(frames)} {calib.pair}: seed {seed_ms[-1]:.1f} ms, ours {ours_ms[-1]:.1f} ms",
            file=sys.stderr,
        )

    def med(values: list[tuple[float, float, float]], k: int) -> float:
        return float(statistics.median(v[k] for v in values))

    result = {
        "cameras": "ideal" if args.ideal_cameras else "realistic",
        "frames": len(frames),
        "seed_ms": round(statistics.median(seed_ms), 2),
        "ours_ms": round(statistics.median(ours_ms), 2),
        "speedup": round(statistics.median(seed_ms) / statistics.median(ours_ms), 2),
        "seed_floor_err_m": round(med(seed_err, 0), 4),
        "ours_floor_err_m": round(med(ours_err, 0), 4),
        "seed_top_err_m": round(med(seed_err, 1), 4),
        "ours_top_err_m": round(med(ours_err, 1), 4),
        "seed_valid": round(med(seed_err, 2), 3),
        "ours_valid": round(med(ours_err, 2), 3),
        "ours_evidence_ms": round(statistics.median(ours_ms), 2),
        "ours_evidence_floor_err_m": round(med(evidence_err, 0), 4),
        "ours_evidence_top_err_m": round(med(evidence_err, 1), 4),
        "ours_evidence_valid": round(med(evidence_err, 2), 3),
        "ours_full_ms": round(statistics.median(full_ms), 2),
        "ours_full_floor_err_m": round(med(full_err, 0), 4),
        "ours_full_top_err_m": round(med(full_err, 1), 4),
        "ours_full_valid": round(med(full_err, 2), 3),
    }
    print(f"{'':14}{'ms/frame':>10}{'floor err':>11}{'top err':>10}{'valid':>8}")
    for name in ("seed", "ours", "ours_evidence", "ours_full"):
        print(
            f"{name:14}{result[f'{name}_ms']:>10.1f}{result[f'{name}_floor_err_m'] * 100:>9.2f}cm"
            f"{result[f'{name}_top_err_m'] * 100:>8.2f}cm{result[f'{name}_valid']:>8.3f}"
        )
    print(
        f"speedup (seed/ours): {result['speedup']:.2f}×   (ours: half-resolution default, the "
        "disparity chain's output; ours_evidence: the same run's tile input, after the floor "
        "model; ours_full: --downscale 1, timed once per frame)"
    )
    print(f"disparity chain alone (no floor model), {result['cameras']} cameras:")
    print(f"{'variant':16}{'floor err':>11}{'top err':>10}{'valid':>8}")
    variants = {}
    for label, matcher in stage_variants(MatcherConfig()).items():
        floor_m, top_m, valid = chain_errors(frames, matcher)
        variants[label] = {
            "floor_err_m": round(floor_m, 4),
            "top_err_m": round(top_m, 4),
            "valid": round(valid, 3),
        }
        print(f"{label:16}{floor_m * 100:>9.2f}cm{top_m * 100:>8.2f}cm{valid:>8.3f}")
    print(json.dumps({**result, "variants": variants}))


if __name__ == "__main__":
    main()
