"""The whole pipeline offline, for iterating on accuracy: the simulator's frames of every pair, one
depth pipeline per pair, one fused grid, scored against the truth as ``overgrid eval`` scores the
live map. Same code as the services (camera model, published calibration, depth pipeline and floor
model, fusion rules), no processes and no Zenoh: every pair captures at every instant, so it is
deterministic and movers are seen without the live system's latency (their figures here are an
upper bound; the live figures come from ``overgrid up``).

Prints the cell scores (IoU, precision, recall, false-free overall and over static objects,
unknown) as means over snapshots taken every second after the first third of the run, and for the
last snapshot the false-occupied cells by cause and each object's seen cells; ``--picture`` writes
the last map with its errors coloured (false-occupied red, false-free blue, missed-unknown yellow).
With lighting steps (``--sim '{"light_step_period_s": P}'``), every frame's map is scored too and
each step's phases printed as ``overgrid eval`` reports them (IoU before, during and after, how
long the unknown share stayed above its level before). The last line is a JSON object with the
figures.

    .venv/bin/python bench/map_accuracy.py [--seed 0] [--pairs 4] [--floor concrete]
        [--duration-s 20] [--rate-hz 2] [--start-s T] [--ideal-cameras] [--plain-objects]
        [--no-outline] [--picture out.png]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from common.lattice import reframe
from common.mapfiles import OCCUPIED_MIN, free_cells
from common.messages import TrackedObject, TruthObject
from common.occupancy_map import UNKNOWN
from services.camera_sim import truth as scene_truth
from services.camera_sim.capture import StereoCapture
from services.camera_sim.render import SceneRenderer
from services.camera_sim.rig import layout_pairs
from services.camera_sim.settings import CameraSimParams
from services.depth.objects import detections_header
from services.depth.pipeline import DepthPipeline
from services.depth.settings import DepthParams
from services.evaluation import metrics
from services.evaluation import objects as object_scores
from services.evaluation.lighting import TimelineScore, step_phases
from services.evaluation.metrics import OBSTACLE_BAND_M
from services.fusion.grid import FusedGrid
from services.fusion.object_layers import serve_tracks
from services.fusion.objects import ObjectTracker
from services.fusion.params import GridParams
from services.fusion.settings import FusionParams

START_S = 1_700_000_000.0
"""Scene time of the first capture by default (movers' poses and the light steps are functions of
it): ``--start-s`` replays a live run's instants."""


Arrays = tuple[npt.NDArray[np.int8], npt.NDArray[np.bool_], npt.NDArray[np.bool_]]


SCORE_EVERY_S = 1.0
"""The map is scored this often after the warm-up (the first third of the run), and the figures are
the means: one snapshot depends on where the movers happen to be (a 10 s and a 20 s snapshot of the
same run differed by 0.09 of IoU)."""
SCORED = (
    "iou",
    "precision",
    "recall",
    "false_free_rate",
    "iou_static",
    "precision_static",
    "false_free_rate_static",
    "unknown_fraction",
)


def run(
    sim: CameraSimParams,
    depth: DepthParams,
    duration_s: float,
    rate_hz: float,
    outline_static: bool = FusionParams().outline_static,
    start_s: float = START_S,
) -> tuple[dict[str, object], Arrays]:
    """The figures (means over the scored snapshots), and (map occupancy, truth, seen) of the last
    snapshot on the truth's window."""
    scene = sim.scene_spec()
    true_calibrations = layout_pairs(sim.rig, scene.floor_size_m)
    renderer = SceneRenderer(scene, true_calibrations, sim.shadows, sim.lighting())
    captures = [StereoCapture(renderer, c, sim.camera_model(), sim.seed) for c in true_calibrations]
    config = depth.pipeline_config()
    pipelines = [DepthPipeline(capture.calibration, config) for capture in captures]
    grid = FusedGrid(GridParams(resolution_m=config.resolution_m))
    tracker = ObjectTracker()
    window = scene.window(config.resolution_m)
    r = config.resolution_m
    static = [o for o in scene.truth_objects(start_s) if not o.moving]
    seen = metrics.seen_by_cameras(
        [capture.calibration for capture in captures],
        window,
        r,
        scene_truth.top_heights(static, window, r),
        blockers=static,
    )
    static_truth = scene_truth.occupancy(static, window, r, OBSTACLE_BAND_M).astype(np.bool_)
    frames = max(1, round(duration_s * rate_hz))
    every = max(1, round(SCORE_EVERY_S * rate_hz))
    snapshots: list[dict[str, float]] = []
    steps_s = sim.lighting().steps_s(start_s, start_s + frames / rate_hz)
    timeline: list[TimelineScore] = []  # every frame's map, with lighting steps: as eval's
    mover_history: list[tuple[list[TrackedObject], list[TruthObject]]] = []
    started = time.perf_counter()
    for k in range(frames):
        stamp_ns = int((start_s + k / rate_hz) * 1e9)
        renderer.set_time(stamp_ns / 1e9)
        for capture, pipeline in zip(captures, pipelines, strict=True):
            result = pipeline.process(*capture.capture(stamp_ns))
            tile = result.tile
            if tile.window.cols:
                grid.integrate_tile(tile, stamp_ns)
            pair = capture.calibration.pair
            found = detections_header(
                pipeline.detect_objects(result), pair, k, stamp_ns, pipeline.camera_m
            )
            tracker.add(pair, stamp_ns, list(found.detections), k / rate_hz, found.camera_m)
        if tracker.flush(k / rate_hz, {capture.calibration.pair for capture in captures}):
            outlined, tops, _ = serve_tracks(grid, tracker, outline_static)  # as fusion does
            grid.set_predicted(outlined + tops)
            if k >= frames // 3:
                mover_history.append((tracker.objects(), scene.truth_objects(stamp_ns / 1e9)))
        grid.decay(stamp_ns / 1e9, 1.0 / rate_hz)  # as the fusion service does, on scene time
        scored = k == frames - 1 or (k >= frames // 3 and (frames - 1 - k) % every == 0)
        if scored or steps_s:
            objects = scene.truth_objects(stamp_ns / 1e9)
            truth = scene_truth.occupancy(objects, window, r, OBSTACLE_BAND_M).astype(np.bool_)
            occupancy = reframe(grid.served_occupancy(), grid.window, window, UNKNOWN)
            scores = metrics.score_cells(occupancy, truth, seen)
            static_scores = metrics.score_cells(occupancy, static_truth, seen)
            timeline.append(
                TimelineScore.of(
                    stamp_ns / 1e9,
                    scores,
                    static_scores,
                    metrics.unknown_away_from_movers(occupancy, truth, seen, objects, window, r),
                )
            )
        if scored:
            snapshots.append(
                {
                    "iou": scores.iou,
                    "precision": scores.precision,
                    "recall": scores.recall,
                    "false_free_rate": scores.false_free_rate,
                    "iou_static": static_scores.iou,
                    "precision_static": static_scores.precision,
                    "false_free_rate_static": static_scores.false_free_rate,
                    "unknown_fraction": scores.unknown_fraction,
                }
            )
        if (k + 1) % 10 == 0:
            print(f"  {k + 1}/{frames} instants, {time.perf_counter() - started:.0f} s", flush=True)
    renderer.close()
    blocking = object_scores.blocking_static(static, scene.floor_size_m)
    tracked = object_sizes(
        tracker, grid, blocking, object_scores.seen_whole(blocking, seen, window, r)
    )
    breakdown = metrics.error_breakdown(occupancy, truth, seen, objects, window, r)
    figures: dict[str, object] = {
        name: float(np.mean([s[name] for s in snapshots])) for name in SCORED
    }
    figures |= {
        "snapshots": len(snapshots),
        "iou_last": snapshots[-1]["iou"],
        "false_occupied_cells": breakdown["false_occupied_cells"],
        "objects": breakdown["objects"],
        "lighting_steps": step_phases(steps_s, timeline),
        **tracked,
        **mover_figures(mover_history),
        "seconds": time.perf_counter() - started,
    }
    return figures, (occupancy, truth, seen)


def mover_figures(
    history: list[tuple[list[TrackedObject], list[TruthObject]]],
) -> dict[str, object]:
    """The movers' tracks over every capture after the warm-up, as ``overgrid eval`` scores the
    ``map/objects`` puts: id switches (counts), the share of captures each mover was tracked
    moving, the velocity error's median and the share of captures with a phantom mover."""
    scores = object_scores.score_movers(history)
    return {
        "id_switches": scores.id_switches,
        "movers_tracked_share": {k: round(v, 3) for k, v in scores.tracked_share.items()},
        "velocity_error_p50_mps": float(np.median(scores.velocity_error_mps))
        if scores.velocity_error_mps
        else None,
        "phantom_movers_share": round(scores.phantom_share, 3),
    }


def object_sizes(
    tracker: ObjectTracker, grid: FusedGrid, static: list[TruthObject], in_view: set[str]
) -> dict[str, object]:
    """The tracker's static objects' sizes against the truth, as ``overgrid eval`` scores
    ``map/objects``: the mean and max of the length and width errors over the objects found."""
    pieces = tracker.check_against(grid).pieces
    tracks = [t for t in tracker.objects(pieces, grid) if t.object_class == "static"]
    matches = object_scores.match_static(tracks, static)
    return {
        **object_scores.size_errors(matches, in_view),
        "static_found": f"{sum(m.tracks >= 1 for m in matches)}/{len(matches)}",
        "static_split": sum(m.tracks > 1 for m in matches),
        "static_merged": sum(m.merged for m in matches),
        "tracked_objects": {
            m.name: [
                round(m.true_length_m, 3),
                round(m.true_width_m, 3),
                round(m.length_m, 3),
                round(m.width_m, 3),
                m.tracks,
                m.partial,
                m.unsure,
                m.name in in_view,
            ]
            for m in matches
        },
    }


def picture(
    occupancy: npt.NDArray[np.int8], truth: npt.NDArray[np.bool_], seen: npt.NDArray[np.bool_]
) -> npt.NDArray[np.uint8]:
    """The map as map.png draws it (free white, occupied black, unknown grey), with its errors in
    colour over the seen cells; y up, 4 pixels a cell."""
    image = np.full((*occupancy.shape, 3), 180, np.uint8)
    image[free_cells(occupancy)] = 255
    occupied = occupancy >= OCCUPIED_MIN
    image[occupied] = 0
    image[occupied & ~truth & seen] = (0, 0, 230)  # BGR: false occupied, red
    image[free_cells(occupancy) & truth & seen] = (230, 80, 0)
    image[(occupancy == UNKNOWN) & truth & seen] = (0, 200, 230)
    image[~seen & (image == 180).all(axis=2)] = 120
    big = cv2.resize(image[::-1], None, fx=4, fy=4, interpolation=cv2.INTER_NEAREST)
    return np.asarray(big, np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--floor", default="concrete", choices=["concrete", "speckle", "plain"])
    parser.add_argument("--plain-objects", action="store_true")
    parser.add_argument("--ideal-cameras", action="store_true")
    parser.add_argument("--no-floor-model", action="store_true")
    parser.add_argument(
        "--no-outline", action="store_true", help="no static objects' footprints in the map"
    )
    parser.add_argument("--duration-s", type=float, default=20.0)
    parser.add_argument("--rate-hz", type=float, default=2.0)
    parser.add_argument(
        "--start-s", type=float, default=START_S, help="scene time of the first capture (epoch s)"
    )
    parser.add_argument("--picture", type=Path, default=None)
    parser.add_argument(
        "--sim", type=json.loads, default={}, help="more camera-sim settings, as JSON"
    )
    parser.add_argument("--depth", type=json.loads, default={}, help="depth settings, as JSON")
    args = parser.parse_args()
    sim = CameraSimParams.model_validate(
        {
            "seed": args.seed,
            "floor": args.floor,
            "plain_objects": args.plain_objects,
            "ideal_cameras": args.ideal_cameras,
            "rig": {"pair_count": args.pairs},
        }
        | args.sim
    )
    depth = DepthParams.model_validate({"floor_model": not args.no_floor_model} | args.depth)
    cv2.setNumThreads(1)
    result, (occupancy, truth, seen) = run(
        sim, depth, args.duration_s, args.rate_hz, not args.no_outline, args.start_s
    )
    if args.picture is not None:
        cv2.imwrite(str(args.picture), picture(occupancy, truth, seen))
    print(f"means over {result['snapshots']} snapshots, one a second after the first third:")
    for name in SCORED:
        print(f"{name:24s} {result[name]:.4f}")
    print(f"last snapshot: IoU {result['iou_last']:.4f}; false occupied by cause", end=" ")
    print(result["false_occupied_cells"])
    for name, shares in result["objects"].items():  # type: ignore[attr-defined]
        print(
            f"  {name:16s} occupied {shares['occupied']:.2f} free {shares['free']:.2f} "
            f"unknown {shares['unknown']:.2f} of {shares['cells']}"
        )
    print(
        f"object sizes from the tracks: mean {result['length_error_mean_pct']:.1f} %, "
        f"max {result['length_error_max_pct']:.1f} % (complete views: "
        f"{result['length_error_mean_pct_complete']:.1f} %, "
        f"{result['length_error_max_pct_complete']:.1f} %; tops wholly in view: "
        f"{result['length_error_mean_pct_in_view']:.1f} %, "
        f"{result['length_error_max_pct_in_view']:.1f} % over {result['objects_in_view']}), "
        f"found {result['static_found']}, "
        f"split {result['static_split']}, merged {result['static_merged']}"
    )
    print(
        f"movers: id switches {result['id_switches']}, tracked moving "
        f"{result['movers_tracked_share']}, velocity error p50 "
        f"{result['velocity_error_p50_mps']}, captures with a phantom mover "
        f"{result['phantom_movers_share']:.1%}"
    )
    for step in result["lighting_steps"]:  # type: ignore[attr-defined]
        print(
            f"lighting step at {step['step_s'] - args.start_s:.1f} s: IoU before / during / after"
            f" {step['before']['iou']:.3f} / {step['during']['iou']:.3f} /"
            f" {step['after']['iou']:.3f}, unknown above its level before for"
            f" {step['unknown_excess_s']:.1f} s"
        )
    for name, (tl, tw, ml, mw, n, part, unsure, in_view) in result["tracked_objects"].items():  # type: ignore[attr-defined]
        print(
            f"  {name:16s} true {tl:.3f}×{tw:.3f}  map {ml:.3f}×{mw:.3f}  tracks {n} partial {part}"
            f" unsure {unsure} in view {in_view}"
        )
    print(json.dumps({"args": vars(args) | {"picture": str(args.picture)}, **result}))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
