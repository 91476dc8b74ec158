"""Floor model cost and coverage: the ``floor`` stage per frame at the processing resolution, one core.

Frames come from camera_sim's realistic cameras (published calibration, noise, auto-exposure) over
a few seconds of the default scene, for each pair; the depth pipeline runs on each in turn. Printed:
the floor stage's median, mean and p90 per frame (learning frames included), the matcher's for
comparison, and each pair's modelled share at the end. The last line is a JSON object.

    .venv/bin/python bench/floor_model.py [--floor concrete|speckle|plain] [--seconds 8] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import cv2
import numpy as np

from services.camera_sim.capture import CameraModel, StereoCapture
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import RigSpec, layout_pairs
from services.camera_sim.scene import generate_scene
from services.depth.pipeline import DepthPipeline, PipelineConfig


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--floor", default="concrete", choices=("concrete", "speckle", "plain"))
    parser.add_argument("--seconds", type=float, default=8.0, help="scene time, at 2 Hz")
    parser.add_argument("--rounds", type=int, default=3, help="passes over the frames")
    args = parser.parse_args()
    cv2.setNumThreads(1)

    scene = generate_scene(0, floor=args.floor)
    calibrations = layout_pairs(RigSpec(), scene.floor_size_m)
    renderer = SceneRenderer(scene, calibrations)
    captures = [StereoCapture(renderer, c, CameraModel(), seed=0) for c in calibrations]
    frames: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in captures]
    print(f"rendering {int(args.seconds * 2) * len(captures)} frames …", file=sys.stderr)
    for k in range(int(args.seconds * 2)):
        t_s = 1000.0 + 0.5 * k
        renderer.set_time(t_s)
        for index, capture in enumerate(captures):
            frames[index].append(capture.capture(int(t_s * 1e9)))
    renderer.close()

    floor_ms: list[float] = []
    disparity_ms: list[float] = []
    shares = {}
    for _round in range(args.rounds):
        pipelines = [DepthPipeline(c.calibration, PipelineConfig()) for c in captures]
        for pipeline, pair_frames in zip(pipelines, frames, strict=True):
            for left, right in pair_frames:
                result = pipeline.process(left, right)
                floor_ms.append(result.stage_ms["floor"])
                disparity_ms.append(result.stage_ms["disparity"])
            shares[pipeline.calib.pair] = pipeline.floor_health()["modelled_share"]
    figures = {
        "floor": args.floor,
        "frames": len(floor_ms),
        "floor_ms_median": statistics.median(floor_ms),
        "floor_ms_mean": statistics.fmean(floor_ms),
        "floor_ms_p90": float(np.percentile(floor_ms, 90)),
        "disparity_ms_median": statistics.median(disparity_ms),
        "modelled_share": shares,
    }
    print(
        f"floor stage {figures['floor_ms_median']:.2f} ms median, {figures['floor_ms_mean']:.2f} "
        f"mean, {figures['floor_ms_p90']:.2f} p90 over {len(floor_ms)} frames "
        f"(matcher chain {figures['disparity_ms_median']:.2f} ms); modelled {shares}"
    )
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
